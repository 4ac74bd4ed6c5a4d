"""A gradient check a user can run on their own loop: which estimator to trust here.

For a per-seed objective ``J(theta, key, temperature) -> scalar`` (theta a flat vector in
the space being tuned, e.g. log thresholds) and a set of seeds, :func:`gradient_check`
computes, *on the same seeds* (common random numbers):

* ``"finite_difference"``: central differences of the hard objective (temperature 0),
  (J(theta + h e_j) - J(theta - h e_j)) / 2h per seed and coordinate: the reference;
* ``"straight_through"``: the pathwise gradient ``jax.grad`` at ``temperature`` > 0 (hard
  forward pass, sigmoid backward, :mod:`jaxnc.tune.estimators`);
* ``"score"``: the antithetic Gaussian score function at scale ``score_scale``,
  (J(theta + s e) - J(theta - s e)) e / 2s with e ~ N(0, I) drawn per seed;
* ``"richardson"``: the score function extrapolated over its smoothing scale. The score
  estimate at scale s is unbiased for the gradient of the objective smoothed by
  N(0, s^2), i.e. biased for the gradient of the mean objective by c s^2 + O(s^4) (a
  Taylor expansion of E_e J(theta + s e)); on the same seeds and perturbations e, the
  estimate at 2 s has bias 4 c s^2 + O(s^4), so (4 g(s) - g(2 s)) / 3 has bias O(s^4)
  (Richardson extrapolation) and (g(2 s) - g(s)) / 3, per seed, estimates the plain
  score's bias c s^2 (its mean and standard error are reported: ``smoothing_bias``).
  With it the check also computes the finite differences extrapolated the same way,
  (4 FD(h) - FD(2 h)) / 3 (``GradientCheck.references["finite_difference_richardson"]``,
  bias O(h^4); FD(h)'s own
  measured bias, (FD(2 h) - FD(h)) / 3, is reported too), and compares with them the
  estimators of the unsmoothed gradient (straight-through, richardson, corrected); the
  score function and the hybrid, smoothed like FD(h), are compared with FD(h). It costs
  2 + 2 d simulations a seed beyond the score and the finite differences;
* ``"hybrid"`` (when the objective returns a pair ``(smooth, jump)``, J = smooth + jump,
  e.g. a cost whose failures are charged a constant): the straight-through gradient of J
  plus the score function of ``jump`` alone, on the same perturbations as ``"score"``
  (the pathwise gradient cannot see how the failure probability moves; the score term
  can). It costs no simulation beyond the other two;
* ``"corrected"`` (when the check is given ``corrected``, a per-seed function: e.g.
  :func:`jaxnc.tune.jump.corrected_grad`, which :func:`jaxnc.tune.check_loop` supplies for
  a loop whose sensor trigger is a PETC with additive measurement noise): the pathwise
  gradient with the hard decisions held plus the jump term of the decisions theta moves.

Each estimate is a mean over seeds with its standard error. An estimator is *consistent*
with the finite differences when

1. for every coordinate, the mean of the per-seed differences (estimator minus finite
   difference, paired on the seed) is within ``z`` of its standard error (1.96, with
   Bonferroni's correction for the number of coordinates) or smaller than ``rel_tol``
   (2 %) of the largest finite-difference component (the finite differences are
   themselves biased by O(h^2) and float32 rounding, so an exact gradient differs from
   them by a tiny but, over many seeds, *significant* amount: that is agreement, not a
   failure) *and* no larger than the gradient on that coordinate, max(|estimate_j|,
   |finite difference_j|): the two do not have opposite signs (a derivative read with the
   wrong sign on a small coordinate, seen at any |z|, is a disagreement however small
   beside the largest component);
2. (optional, ``max_noise``, off by default) its standard error is at most ``max_noise``
   times the finite differences'. Rule 3 already makes agreement a test (an estimator so
   noisy that it "agrees with anything" is unresolved until the seeds make the agreement
   mean something), and the ratio does not change with the seeds, so with the rule on an
   unbiased estimator noisier than the finite differences is never recommended (it was on,
   at 10, until 2026-12-05: docs/tuning_loops.md, "No 'too noisy' rule by default"). A
   reason "differs" or "too noisy" adds "heavy-tailed" when the per-seed differences to the
   finite differences are too skewed for a normal interval on these seeds (Cochran's rule,
   :func:`jaxnc.montecarlo.seeds_for_normal_interval`: the verdict is then not to be
   trusted as a test), and "non-finite values" says on how many seeds;
3. **every coordinate is resolved**: coordinate j is resolved when the check could have
   seen a disagreement as large as the gradient on that coordinate,
   ``z * SE_j <= max(|estimate_j|, |finite difference_j|)`` with SE_j the standard error
   of the paired difference on coordinate j (its *resolution* is ``z * SE_j``). A rule on
   the largest coordinate alone passes an estimator whose small coordinates were never
   tested (agreement within the noise proves nothing); a coordinate whose gradient is
   near zero (a flat direction) is resolved only with many seeds, and the check says so.
   An unresolved coordinate's report gives the seeds that would resolve it, estimated from
   the standard error's 1/sqrt(n) scaling: ``n * (z * SE_j)^2 / g_j^2`` with g_j^2 the larger
   of ``estimate_j^2 - SE(estimate_j)^2`` and ``fd_j^2 - SE(fd_j)^2`` (the squared means less
   their noise); where both are <= 0 (no gradient seen yet), ``g_j = max(|estimate_j|,
   |fd_j|)`` and the report says "at least".

**The smoothed estimator: plain or extrapolated, by the measured bias.** When the check
has both ``"score"`` and ``"richardson"``, at most one of them is recommended. The plain
score's smoothing bias is *resolved* when, on some coordinate, the measured bias exceeds
``z`` of its own standard errors and ``rel_tol`` of the largest finite-difference
component (the margin below which the check calls differences agreement). Resolved: the
plain score is refused (biased, by a measured amount, for the gradient of the mean
objective; its agreement with FD(h) only says that both are smoothed alike) and the
extrapolated one may be recommended. Not resolved: the extrapolated one is refused (the
bias it would remove is not seen, and its variance is larger: (16 + 1) / 9 of the plain
score's when g(s) and g(2 s) are uncorrelated, less when they are correlated) and the
plain one may be recommended.

The recommendation is the consistent estimator with the smallest standard error (ties:
straight-through, which needs one pass); none when no estimator is consistent, so never
one with an unresolved coordinate. With ``max_seeds`` (and ``more_keys``, which gives
the keys of further seeds) a check that recommends nothing while some estimator fails
only for unresolved coordinates doubles its seeds (the new seeds run on top of the old
ones, in the same compiled chunks) until one is recommended, none is left unresolved, or
``max_seeds`` is reached: it ends conclusive or says which coordinate is unresolved and
how many seeds it would need. (Looking again after each doubling is a sequential test;
the stopping rule depends on the resolution, not on the z of the disagreement.)

The finite differences themselves estimate the gradient of the mean objective only up to
O(h^2) and their own noise; both are in the report.
"""
from __future__ import annotations

import weakref
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import montecarlo
from jaxnc._validate import check_int, check_positive
from jaxnc.tune.estimators import score_terms

__all__ = ["GradientCheck", "gradient_check", "objective_total"]

ESTIMATORS = ("straight_through", "score", "richardson", "hybrid", "corrected")
# each estimator's reference: the finite differences with the same order of smoothing bias
_UNSMOOTHED = ("straight_through", "richardson", "corrected")


def _reference(name: str, available) -> str:
    """The finite differences ``name`` is compared with: the extrapolated ones (bias
    O(h^4)) for the estimators of the unsmoothed gradient when they were computed, FD(h)
    for the score function and the hybrid (smoothed like FD(h): module docstring)."""
    rich = "finite_difference_richardson"
    return rich if name in _UNSMOOTHED and rich in available else "finite_difference"


def objective_total(value):
    """The objective's value: the sum of a ``(smooth, jump)`` pair, or the scalar itself."""
    return value[0] + value[1] if isinstance(value, (tuple, list)) else value


class GradientCheck(NamedTuple):
    """Result of :func:`gradient_check` (arrays over theta's coordinates)."""

    theta: np.ndarray
    value: float                    # mean hard objective at theta
    estimates: dict                 # name -> (mean float[d], standard error float[d])
    paired_z: dict                  # name -> float[d]: (mean difference to FD) / its SE
    consistent: dict                # name -> bool
    reason: dict                    # name -> "" when consistent, else why not
    recommended: str | None
    names: tuple = ()               # the coordinates' labels
    diff_se: dict = {}              # name -> float[d]: standard error of the paired difference to FD
    resolution: dict = {}           # name -> float[d]: z x diff_se, the smallest disagreement the check sees
    resolved: dict = {}             # name -> bool[d]: resolution <= max(|estimate|, |FD|) on the coordinate
    seeds_needed: dict = {}         # name -> float[d]: seeds that would resolve each coordinate (SE ~ 1/sqrt(n))
    seeds: int = 0                  # seeds the check ran (after any doubling)
    values: np.ndarray | None = None         # float[d]: each coordinate's parameter in the user's units
    dvalue_dtheta: np.ndarray | None = None  # float[d]: d value / d theta (the constraint's slope)
    smoothing_bias: dict = {}       # "score" / "finite_difference" -> (mean, SE) float[d] each: the measured bias
    bias_resolved: bool | None = None        # the score's smoothing bias resolved (None: not measured)
    runs_per_seed: int = 0          # simulations one seed of the check costs (a forward-backward pass counts one)
    references: dict = {}           # "finite_difference_richardson" -> (mean, SE): the extrapolated reference

    def in_units(self, name: str, bias: bool = False) -> tuple:
        """(mean, standard error) of estimator ``name`` (or a finite-difference reference)
        as d E[objective] / d value in the user's units (theta's own units when the check
        was given no ``dvalue_dtheta``); with ``bias``, of the measured smoothing bias of
        ``"score"`` or ``"finite_difference"`` (``smoothing_bias``) instead."""
        m, s = (self.smoothing_bias if bias else {**self.estimates, **self.references})[name]
        slope = np.ones_like(m) if self.dvalue_dtheta is None else np.asarray(self.dvalue_dtheta, float)
        return m / slope, s / np.abs(slope)

    def __str__(self) -> str:
        return self.table()

    __repr__ = __str__

    def table(self) -> str:
        """A plain-text table: one row per estimator and coordinate, gradients and the
        resolution in the user's units when the check knows them (``values``)."""
        d = len(self.theta)
        labels = self.names or tuple(f"theta[{j}]" for j in range(d))
        slope = np.ones(d) if self.dvalue_dtheta is None else np.abs(np.asarray(self.dvalue_dtheta, float))
        units = ("d E[objective] / d parameter, in the parameter's units" if self.values is not None else
                 "d E[objective] / d theta")
        rows = [f"gradient check on {self.seeds} seeds ({units}; +- 95 %; resolution: the smallest disagreement "
                f"with the finite differences the check can see)"]
        w = max(12, *(len(x) for x in labels))
        rows.append(f"{'estimator':<17} {'coordinate':<{w}} {'value':>10} {'gradient':>22} {'finite diff.':>22} "
                    f"{'|z|':>6} {'resolution':>10}  resolved")
        for name in self.estimates:
            if name.startswith("finite_difference"):
                continue
            m, s = self.in_units(name)
            fd_m, fd_s = self.in_units(_reference(name, self.references))
            for j in range(d):
                val = "-" if self.values is None else f"{float(self.values[j]):.4g}"
                res = self.resolution.get(name)
                rs = "-" if res is None else f"{float(res[j] / slope[j]):.3g}"
                ok = self.resolved.get(name)
                needed = self.seeds_needed.get(name)
                okstr = "-" if ok is None else ("yes" if ok[j] else (
                    f"no (~{_seeds_str(needed[j])} seeds)" if needed is not None else "no"))
                rows.append(f"{name if j == 0 else '':<17} {labels[j]:<{w}} {val:>10} "
                            f"{f'{m[j]:.4g} +- {1.96 * s[j]:.2g}':>22} {f'{fd_m[j]:.4g} +- {1.96 * fd_s[j]:.2g}':>22} "
                            f"{abs(float(self.paired_z[name][j])):>6.2f} {rs:>10}  {okstr}")
        for name in self.smoothing_bias:
            m, s = self.in_units(name, bias=True)
            rows.append(f"measured smoothing bias of {name}: " + ", ".join(
                f"{labels[j]} {m[j]:.3g} +- {1.96 * s[j]:.2g}" for j in range(d)))
        if self.bias_resolved is not None:
            rows.append("the score's smoothing bias is " + (
                "resolved: the extrapolated score (richardson) is the smoothed estimator" if self.bias_resolved else
                "not resolved: the plain score is the smoothed estimator"))
        for name in self.estimates:
            if not name.startswith("finite_difference"):
                rows.append(f"{name}: " + ("consistent" if self.consistent[name] else f"NO ({self.reason[name]})"))
        rows.append("recommended: " + (self.recommended or "none (no estimator agrees with the finite differences "
                                                           "on every coordinate, each resolved)"))
        return "\n".join(rows)


def _runs_per_seed(estimators: tuple, d: int) -> int:
    """Simulations one seed of :func:`gradient_check` costs: the value, 2 d central
    differences (4 d with the extrapolated reference), one forward-backward pass for the
    pathwise estimators, an antithetic pair per smoothing scale, four for the corrected one."""
    rich = "richardson" in estimators
    return (1 + 2 * d * (1 + rich) + bool({"straight_through", "hybrid"} & set(estimators))
            + 2 * bool({"score", "hybrid"} & set(estimators) or rich) + 2 * rich + 4 * ("corrected" in estimators))


def _seeds_str(n) -> str:
    return "inf" if not np.isfinite(n) else f"{int(n)}"


def _heavy_tail(diff: np.ndarray, slope: np.ndarray, names: tuple) -> str:
    """"; heavy-tailed: ..." when the per-seed differences ``diff`` [n, d] (an estimator
    minus its finite differences) are too skewed on some coordinate for the normal interval
    of their mean over n seeds, by Cochran's rule
    (:func:`jaxnc.montecarlo.seeds_for_normal_interval`), else "". The worst coordinate's
    median difference is quoted divided by ``slope`` (the user's units)."""
    need = [montecarlo.seeds_for_normal_interval(diff[:, j]) for j in range(diff.shape[1])]
    j = int(np.argmax(need))
    if need[j] <= diff.shape[0]:
        return ""
    return (f"; heavy-tailed on {names[j]}: its normal interval needs about {need[j]} seeds by Cochran's rule "
            f"(median difference to the finite differences {np.median(diff[:, j]) / slope[j]:.3g})")


def _verdicts(res: dict, estimators: tuple, z: float, max_noise: float | None, rel_tol: float, names: tuple,
              slope: np.ndarray):
    """The check's statistics and verdicts from the per-seed values ``res`` (module
    docstring); the reasons quote gradients and resolutions divided by ``|slope|`` (d value
    / d theta: the user's units)."""
    n = len(res["value"])
    se = lambda a: np.std(a, axis=0, ddof=1) / np.sqrt(n)
    refs = {k: np.asarray(res[k], float) for k in res if k.startswith("finite_difference")}
    estimates = {k: (v.mean(0), se(v)) for k, v in refs.items()}     # the references first, then the estimators
    bias = {k: (np.asarray(res[f"bias_{k}"], float).mean(0), se(np.asarray(res[f"bias_{k}"], float)))
            for k in ("score", "finite_difference") if f"bias_{k}" in res}
    out = {k: {} for k in ("paired", "consistent", "reason", "diff_se", "resolution", "resolved", "needed")}
    margin = rel_tol * float(np.max(np.abs(estimates["finite_difference"][0])))
    for name in estimators:
        ref = _reference(name, refs)
        fd = refs[ref]
        g = np.asarray(res[name], float)
        estimates[name] = (g.mean(0), se(g))
        diff = g - fd
        s = se(diff)
        zz = np.where(s > 0, diff.mean(0) / np.where(s > 0, s, 1.0), np.where(diff.mean(0) == 0, 0.0, np.inf))
        size = np.maximum(np.abs(g.mean(0)), np.abs(fd.mean(0)))       # a disagreement as large as the gradient
        resolution = z * s
        resolved = resolution <= size
        # the seeds that would resolve a coordinate, from SE ~ 1/sqrt(n) and the gradient's size
        # with the means' own noise taken out (E[mean^2] = g^2 + SE^2: a noisy estimator's |mean|
        # overstates |g| and understates the seeds); where that leaves nothing, the noisy size, a
        # lower bound ("at least")
        true2 = np.maximum(g.mean(0) ** 2 - se(g) ** 2, fd.mean(0) ** 2 - se(fd) ** 2)
        lower = true2 <= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            needed = np.where(resolved, n, np.ceil(n * resolution ** 2 / np.where(lower, size ** 2, true2)))
        needed = np.where(np.isnan(needed), np.inf, needed)
        out["paired"][name], out["diff_se"][name] = zz, s
        out["resolution"][name], out["resolved"][name], out["needed"][name] = resolution, resolved, needed
        if not np.all(np.isfinite(g)):
            bad = int(np.sum(~np.all(np.isfinite(g.reshape(n, -1)), axis=1)))
            reason = f"non-finite values on {bad} of {n} seeds"
        elif not np.all((np.abs(zz) <= z) | ((np.abs(diff.mean(0)) <= margin) & (np.abs(diff.mean(0)) <= size))):
            reason = (f"differs from finite differences, |z| = {float(np.max(np.abs(zz))):.1f}"
                      + _heavy_tail(diff, slope, names))
        elif max_noise is not None and np.any(estimates[name][1] > max_noise * np.maximum(estimates[ref][1], 1e-30)):
            ratio = float(np.max(estimates[name][1] / np.maximum(estimates[ref][1], 1e-30)))
            reason = f"too noisy, std err {ratio:.3g}x the finite differences'" + _heavy_tail(diff, slope, names)
        elif not np.all(resolved):
            reason = "inconclusive on " + "; ".join(
                f"{names[j]} (resolves {resolution[j] / slope[j]:.3g}, gradient {size[j] / slope[j]:.3g}: "
                f"{'at least' if lower[j] else 'about'} {_seeds_str(needed[j])} seeds would resolve it)"
                for j in np.flatnonzero(~resolved))
        else:
            reason = ""
        out["reason"][name], out["consistent"][name] = reason, reason == ""
    bias_resolved = None
    if "score" in bias and "score" in estimators and "richardson" in estimators:
        # the smoothed estimator: plain or extrapolated, by the measured bias (module docstring)
        b, b_se = bias["score"]
        seen = (np.abs(b) > z * b_se) & (np.abs(b) > margin)
        bias_resolved = bool(np.any(seen))
        quote = "; ".join(f"{names[j]} {b[j] / slope[j]:.3g} +- {z * b_se[j] / slope[j]:.2g}" for j in range(len(b)))
        if bias_resolved and out["consistent"]["score"]:
            out["reason"]["score"] = (f"biased by its smoothing: the measured bias ({quote}; +- z SE) is resolved "
                                      f"(the finite differences are smoothed alike): the extrapolated score, "
                                      f"richardson, is the smoothed estimator here")
        elif not bias_resolved and out["consistent"]["richardson"]:
            out["reason"]["richardson"] = (f"not needed: the plain score's measured smoothing bias ({quote}; +- z SE) "
                                           f"is not resolved, and the plain score has the lower variance")
        for name in ("score", "richardson"):
            out["consistent"][name] = out["reason"][name] == ""
    ok = [nm for nm in estimators if out["consistent"][nm]]
    rec = min(ok, key=lambda nm: (float(np.max(estimates[nm][1])), nm != "straight_through")) if ok else None
    references = {k: estimates.pop(k) for k in list(estimates) if k != "finite_difference" and k in refs}
    return estimates, out, rec, bias, bias_resolved, references


def gradient_check(objective: Callable, theta, keys, *, fd_step: float = 0.05, temperature: float = 1e-3,
                   score_scale: float = 0.05, z: float | None = None, max_noise: float | None = None, rel_tol: float = 0.02,
                   estimators=None, chunk_size: int = 256, progress: bool = False, names=None,
                   max_seeds: int | None = None, more_keys: Callable | None = None, values=None,
                   dvalue_dtheta=None, corrected: Callable | None = None, args: tuple = ()) -> GradientCheck:
    """Compare gradient estimators of E_seeds[objective] at ``theta`` (module docstring).

    Args:
      objective: ``objective(theta float[d], key, temperature) -> scalar`` for one seed,
        or a pair ``(smooth, jump)`` of scalars whose sum is the objective (this adds the
        ``"hybrid"`` estimator); temperature 0 must give the hard (exact) simulation.
      theta: float[d], the point.
      keys: the seeds' keys, shape (n, 2) (n >= 2).
      fd_step, temperature, score_scale: > 0.
      z: the normal quantile of the consistency test and of the resolution; default the
        two-sided 95 % quantile with Bonferroni's correction for the d coordinates,
        Phi^-1(1 - 0.025 / d) (1.96 for d = 1, 2.24 for d = 2): every coordinate is
        tested, so without it an unbiased estimator would be flagged in about d x 5 % of
        checks.
      max_noise: None (default: no such rule), or the largest ratio of an estimator's
        standard error to the finite differences' for it to count as consistent (10 until
        2026-12-05; module docstring, rule 2).
      rel_tol: differences below this fraction of max_j |finite-difference mean_j| agree
        whatever their z (>= 0), unless estimate and finite difference have opposite signs
        on the coordinate.
      estimators: which of ``"straight_through"``, ``"score"``, ``"richardson"``,
        ``"hybrid"``, ``"corrected"`` to check; default all that apply (``"hybrid"`` only
        for a pair objective, ``"corrected"`` only with ``corrected``).
      chunk_size: seeds per compiled batch (:func:`jaxnc.montecarlo.run_batched`; at
        most n, kept for every doubling), which bounds memory; a seed's values do not
        depend on the other seeds.
      progress: a progress bar over the seeds.
      names: the d coordinates' labels for the report (default ``theta[j]``).
      max_seeds: the budget of the automatic increase: while nothing is recommended and
        some estimator fails only for unresolved coordinates, the seeds double (the last
        step capped) up to ``max_seeds`` (>= n); default n (no increase).
      more_keys: ``more_keys(start, count) -> keys (count, 2)`` of seeds ``start ...
        start + count - 1`` (e.g. ``lambda s, c: jaxnc.montecarlo.seed_keys(base, c,
        start=s)`` when ``keys`` are ``seed_keys(base, n)``); needed when max_seeds > n.
      values, dvalue_dtheta: float[d] each, the parameter each coordinate sets (in the
        user's units) and its slope d value / d theta (non-zero), e.g. value = exp(theta)
        for a log coordinate: the table and the reasons then give gradients and
        resolutions as d E[objective] / d value (:func:`jaxnc.tune.check_loop` sets them).
      corrected: ``corrected(theta float[d], key) -> (value, float[d])``, one seed's
        corrected gradient of the hard objective (:mod:`jaxnc.tune.jump`); adds
        ``"corrected"``.
      args: a tuple of pytrees passed after the temperature, ``objective(theta, key,
        temperature, *args)`` (and after the key, ``corrected(theta, key, *args)``), as
        arguments of the compiled program, like theta: checks of one ``objective`` (the
        same function object) with the same estimators, steps, d and shapes run in one
        compiled program whatever theta and ``args`` hold (a configuration, e.g.
        :func:`jaxnc.tune.check_loop`'s loop).

    Compiled programs: one per ``objective``, ``corrected`` and settings (estimators,
    pair or scalar, d, ``fd_step``, ``temperature``, ``score_scale``) and chunk size,
    kept while ``objective`` lives: a second point, a second call and every seed doubling
    reuse it.

    Returns:
      :class:`GradientCheck` (``seeds``: the seeds it ran; ``smoothing_bias`` and
      ``bias_resolved`` when ``"richardson"`` is checked).

    Raises:
      ValueError: theta not a non-empty 1-D vector, fewer than 2 keys, a non-positive
        step/scale/temperature or max_noise, a chunk_size below 1, an unknown estimator, ``"hybrid"``
        for an objective that is not a pair, ``"corrected"`` without ``corrected``, an
        objective that returns neither a scalar
        nor a pair of scalars, args not a tuple, names not d strings, max_seeds below n, or max_seeds > n
        without more_keys.
    """
    theta = np.asarray(theta, np.float32)
    if theta.ndim != 1 or theta.size == 0:
        raise ValueError(f"gradient_check: theta must be a non-empty 1-D vector, got shape {theta.shape}")
    keys = jnp.asarray(keys)
    if keys.ndim != 2 or keys.shape[0] < 2:
        raise ValueError(f"gradient_check: keys must have shape (n, 2) with n >= 2, got {keys.shape}")
    for name, v in (("fd_step", fd_step), ("temperature", temperature), ("score_scale", score_scale)):
        check_positive(name, v)
    check_int("chunk_size", chunk_size, 1)
    if not (isinstance(rel_tol, (int, float)) and 0.0 <= rel_tol < 1.0):
        raise ValueError(f"gradient_check: rel_tol must be a number in [0, 1), got {rel_tol!r}")
    d = theta.shape[0]
    n = int(keys.shape[0])
    names = tuple(f"theta[{j}]" for j in range(d)) if names is None else tuple(names)
    if len(names) != d or not all(isinstance(x, str) for x in names):
        raise ValueError(f"gradient_check: names must be {d} strings (one per coordinate), got {names!r}")
    if (values is None) != (dvalue_dtheta is None):
        raise ValueError("gradient_check: give both values and dvalue_dtheta, or neither")
    if values is not None:
        values, dvalue_dtheta = np.asarray(values, float), np.asarray(dvalue_dtheta, float)
        if values.shape != (d,) or dvalue_dtheta.shape != (d,) or not np.all(np.isfinite(dvalue_dtheta) &
                                                                               (dvalue_dtheta != 0)):
            raise ValueError(f"gradient_check: values and dvalue_dtheta must be float[{d}], the slopes finite and "
                             f"non-zero, got {values!r}, {dvalue_dtheta!r}")
    slope = np.ones(d) if dvalue_dtheta is None else np.abs(dvalue_dtheta)
    if max_noise is not None:
        check_positive("max_noise", max_noise)
    max_seeds = n if max_seeds is None else max_seeds
    check_int("max_seeds", max_seeds, n)
    if max_seeds > n and not callable(more_keys):
        raise ValueError("gradient_check: max_seeds > the number of keys needs more_keys(start, count) -> keys")
    th = jnp.asarray(theta)
    if not isinstance(args, tuple):
        raise ValueError(f"gradient_check: args must be a tuple (of the objective's extra arguments), got "
                         f"{type(args).__name__}")
    out_shape = jax.eval_shape(objective, th, keys[0], jnp.float32(0.0), *args)
    pair = isinstance(out_shape, (tuple, list))
    if (pair and (len(out_shape) != 2 or any(getattr(o, "shape", None) != () for o in out_shape))) or (
            not pair and getattr(out_shape, "shape", None) != ()):
        raise ValueError(f"gradient_check: the objective must return a scalar or a pair (smooth, jump) of scalars "
                         f"per seed, got {out_shape}")
    if estimators is None:
        estimators = ("straight_through", "score", "richardson") + (("hybrid",) if pair else ())
        estimators = estimators + (("corrected",) if corrected is not None else ())
    estimators = tuple(estimators)
    unknown = [e for e in estimators if e not in ESTIMATORS]
    if unknown:
        raise ValueError(f"gradient_check: estimators must be among {', '.join(ESTIMATORS)}, got {unknown}")
    if "hybrid" in estimators and not pair:
        raise ValueError("gradient_check: the hybrid estimator needs an objective that returns (smooth, jump)")
    if "corrected" in estimators and not callable(corrected):
        raise ValueError("gradient_check: the corrected estimator needs corrected(theta, key) -> (value, grad)")
    if z is None:
        from scipy.stats import norm
        z = float(norm.ppf(1.0 - 0.025 / d))
    check_positive("z", z)
    per_seed = _per_seed_program(objective, corrected, (estimators, pair, d, float(fd_step), float(temperature),
                                                        float(score_scale)))

    # one chunk size for every block (no chunk larger than the first block's seeds:
    # run_batched pads the last chunk), so a doubled check's seeds are those of one run
    chunk = min(chunk_size, n)
    run = lambda ks: montecarlo.run_batched(per_seed, ks, args=(th, tuple(args)), chunk_size=chunk, progress=progress,
                                            desc="gradient check")
    res = {k: np.asarray(v) for k, v in run(keys).items()}
    while True:
        estimates, out, rec, bias, bias_resolved, references = _verdicts(res, estimators, z, max_noise, rel_tol, names, slope)
        unresolved_only = any(out["reason"][nm].startswith("inconclusive") for nm in estimators)
        if rec is not None or not unresolved_only or n >= max_seeds:
            break
        m = min(n, max_seeds - n)
        more = jnp.asarray(more_keys(n, m))
        if more.shape != (m, keys.shape[1]):
            raise ValueError(f"gradient_check: more_keys({n}, {m}) must return keys of shape {(m, keys.shape[1])}, "
                             f"got {more.shape}")
        new = run(more)
        res = {k: np.concatenate([res[k], np.asarray(new[k])]) for k in res}
        n += m
    return GradientCheck(theta, float(np.mean(res["value"])), estimates, out["paired"], out["consistent"],
                         out["reason"], rec, names, out["diff_se"], out["resolution"], out["resolved"], out["needed"],
                         n, values, dvalue_dtheta, bias, bias_resolved, _runs_per_seed(estimators, d), references)


# per_seed programs, per objective (weakly: a program must not keep its own key alive) and
# per (corrected, configuration): the points of a check, and repeated checks of one objective,
# run in one compiled program (theta and the objective's args are its arguments)
_PROGRAMS: "weakref.WeakKeyDictionary[Callable, dict]" = weakref.WeakKeyDictionary()


def _per_seed_program(objective: Callable, corrected: Callable | None, config: tuple) -> Callable:
    """``per_seed(key, theta, args) -> {name: per-seed value}``, the check's simulations of
    one seed at ``theta`` (:func:`gradient_check`), one function per ``objective``,
    ``corrected`` and ``config`` = (estimators, pair, d, fd_step, temperature,
    score_scale), kept across calls so that :func:`jaxnc.montecarlo.run_batched` reuses its
    compilation."""
    try:
        cache = _PROGRAMS.setdefault(objective, {})
        obj_ref = weakref.ref(objective)
        corr_ref = None if corrected is None else weakref.ref(corrected)
    except TypeError:                 # not weak-referenceable: a program for this call alone
        cache, obj_ref, corr_ref = {}, (lambda: objective), (lambda: corrected)
    ckey = (config, corr_ref)
    if ckey not in cache:
        cache[ckey] = _build_per_seed(obj_ref, corr_ref, *config)
    return cache[ckey]


def _build_per_seed(obj_ref, corr_ref, estimators: tuple, pair: bool, d: int, fd_step: float, temperature: float,
                    score_scale: float) -> Callable:
    """The per-seed function of :func:`_per_seed_program` (the objective and the corrected
    gradient reached through ``obj_ref()`` / ``corr_ref()``)."""
    eye = jnp.eye(d, dtype=jnp.float32)
    rich = "richardson" in estimators
    smoothed = "score" in estimators or "hybrid" in estimators or rich

    def per_seed(key, th, args):
        objective = obj_ref()

        def parts(t, k, temp):
            """(total, jump) of one seed at temperature ``temp``."""
            v = objective(t, k, temp, *args)
            return objective_total(v), (v[1] if pair else jnp.float32(0.0))

        # every hard simulation of the seed (the value, the central differences, the score
        # function's antithetic pairs) is a lane of one vmap over theta: one copy of the
        # loop in the compiled program instead of one per point
        row = th[None, :]
        blocks = {"value": row, "fd+": row + fd_step * eye, "fd-": row - fd_step * eye}
        if rich:
            blocks |= {"fd2+": row + 2 * fd_step * eye, "fd2-": row - 2 * fd_step * eye}
        if smoothed:
            e = jax.random.normal(jax.random.fold_in(key, 7919), (d,), jnp.float32)
            blocks |= {"s+": (th + score_scale * e)[None], "s-": (th - score_scale * e)[None]}
            if rich:
                blocks |= {"s2+": (th + 2 * score_scale * e)[None], "s2-": (th - 2 * score_scale * e)[None]}
        tot, jmp = jax.vmap(lambda t: parts(t, key, jnp.float32(0.0)))(jnp.concatenate(list(blocks.values())))
        at, i = {}, 0
        for name, b in blocks.items():
            at[name] = (tot[i:i + b.shape[0]], jmp[i:i + b.shape[0]])
            i += b.shape[0]
        out = {"value": at["value"][0][0]}
        fd = (at["fd+"][0] - at["fd-"][0]) / (2 * fd_step)
        out["finite_difference"] = fd
        if rich:
            fd2 = (at["fd2+"][0] - at["fd2-"][0]) / (4 * fd_step)
            out["finite_difference_richardson"] = (4.0 * fd - fd2) / 3.0
            out["bias_finite_difference"] = (fd2 - fd) / 3.0
        if "straight_through" in estimators or "hybrid" in estimators:
            st = jax.grad(lambda t: parts(t, key, jnp.float32(temperature))[0])(th)
            if "straight_through" in estimators:
                out["straight_through"] = st
        if smoothed:
            (tp, jp), (tm, jm) = [(a[0], b[0]) for a, b in (at["s+"], at["s-"])]
            g1 = score_terms(tp, tm, e, score_scale)
            if "score" in estimators:
                out["score"] = g1
            if rich:
                # the same seed and perturbation at twice the scale (module docstring)
                g2 = score_terms(at["s2+"][0][0], at["s2-"][0][0], e, 2 * score_scale)
                out["richardson"] = (4.0 * g1 - g2) / 3.0
                out["bias_score"] = (g2 - g1) / 3.0
            if "hybrid" in estimators:
                out["hybrid"] = st + score_terms(jp, jm, e, score_scale)
        if "corrected" in estimators:
            out["corrected"] = jnp.asarray(corr_ref()(th, key, *args)[1], jnp.float32)
        return out
    return per_seed
