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
* ``"hybrid"`` (when the objective returns a pair ``(smooth, jump)``, J = smooth + jump,
  e.g. a cost whose failures are charged a constant): the straight-through gradient of J
  plus the score function of ``jump`` alone, on the same perturbations as ``"score"``
  (the pathwise gradient cannot see how the failure probability moves; the score term
  can). It costs no simulation beyond the other two.

Each estimate is a mean over seeds with its standard error. An estimator is *consistent*
with the finite differences when, for every coordinate, the mean of the per-seed
differences (estimator minus finite difference, paired on the seed) is within
``z`` of its standard error (1.96, with Bonferroni's correction for the number of
coordinates) or smaller than ``rel_tol`` (2 %) of the largest
finite-difference component (the finite differences are themselves biased by O(h^2) and
float32 rounding, so an exact gradient differs from them by a tiny but, over many
seeds, *significant* amount: that is agreement, not a failure), *and* the check is
conclusive (it can see a disagreement as large as the gradient: ``z`` times the paired
standard error is at most the largest |component| of the estimate or of the finite
differences; on an objective dominated by rare failures the finite differences are often
too noisy for that, and agreement within their noise proves nothing), *and* its standard error is at most ``max_noise``
(10) times the finite differences' (an estimator so noisy that it agrees with anything,
e.g. a straight-through gradient through a very sharp sigmoid, is flagged as too noisy,
not passed). The recommendation is the consistent estimator with
the smallest standard error (ties: straight-through, which needs one pass); none when
no estimator is consistent. The finite differences themselves estimate the gradient of
the mean objective only up to O(h^2) and their own noise; both are in the report.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import montecarlo
from jaxnc._validate import check_int, check_positive

__all__ = ["GradientCheck", "gradient_check", "objective_total"]

ESTIMATORS = ("straight_through", "score", "hybrid")


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
    names: tuple = ()               # the coordinates' labels (set by jaxnc.tune.check_loop)
    diff_se: dict = {}              # name -> float[d]: standard error of the paired difference to FD;
                                    # 1.96 x it is the smallest disagreement the check can see

    def table(self) -> str:
        """A plain-text table of the check."""
        rows = [f"coordinates: {', '.join(self.names)}"] if self.names else []
        rows += [f"{'estimator':<20} {'gradient':>28} {'std err':>24} {'|z| vs FD':>10}  consistent"]
        for name, (m, s) in self.estimates.items():
            z = self.paired_z.get(name)
            zs = "-" if z is None else f"{float(np.max(np.abs(z))):.2f}"
            c = "-" if name == "finite_difference" else ("yes" if self.consistent[name] else
                                                          f"NO ({self.reason[name]})")
            rows.append(f"{name:<20} {np.array2string(m, precision=4):>28} {np.array2string(s, precision=3):>24} "
                        f"{zs:>10}  {c}")
        rows.append(f"recommended: {self.recommended or 'none (no estimator agrees with the finite differences)'}")
        return "\n".join(rows)


def gradient_check(objective: Callable, theta, keys, *, fd_step: float = 0.05, temperature: float = 1e-3,
                   score_scale: float = 0.05, z: float | None = None, max_noise: float = 10.0, rel_tol: float = 0.02,
                   estimators=None, chunk_size: int = 256, progress: bool = False) -> GradientCheck:
    """Compare gradient estimators of E_seeds[objective] at ``theta`` (module docstring).

    Args:
      objective: ``objective(theta float[d], key, temperature) -> scalar`` for one seed,
        or a pair ``(smooth, jump)`` of scalars whose sum is the objective (this adds the
        ``"hybrid"`` estimator); temperature 0 must give the hard (exact) simulation.
      theta: float[d], the point.
      keys: the seeds' keys, shape (n, 2) (n >= 2).
      fd_step, temperature, score_scale: > 0.
      z: the normal quantile of the consistency test; default the two-sided 95 % quantile
        with Bonferroni's correction for the d coordinates, Phi^-1(1 - 0.025 / d) (1.96 for
        d = 1, 2.24 for d = 2): every coordinate is tested, so without it an unbiased
        estimator would be flagged in about d x 5 % of checks.
      max_noise: the largest ratio of an estimator's standard error to the finite
        differences' for it to count as consistent.
      rel_tol: differences below this fraction of max_j |finite-difference mean_j| agree
        whatever their z (>= 0).
      estimators: which of ``"straight_through"``, ``"score"``, ``"hybrid"`` to check;
        default all that apply (``"hybrid"`` only for a pair objective).
      chunk_size: seeds per compiled batch (:func:`jaxnc.montecarlo.run_batched`), which
        bounds memory; a seed's values do not depend on the other seeds.
      progress: a progress bar over the seeds.

    Returns:
      :class:`GradientCheck`.

    Raises:
      ValueError: theta not a non-empty 1-D vector, fewer than 2 keys, a non-positive
        step/scale/temperature, a chunk_size below 1, an unknown estimator, ``"hybrid"``
        for an objective that is not a pair, or an objective that returns neither a
        scalar nor a pair of scalars.
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
    th = jnp.asarray(theta)
    out_shape = jax.eval_shape(lambda k: objective(th, k, jnp.float32(0.0)), keys[0])
    pair = isinstance(out_shape, (tuple, list))
    if (pair and (len(out_shape) != 2 or any(getattr(o, "shape", None) != () for o in out_shape))) or (
            not pair and getattr(out_shape, "shape", None) != ()):
        raise ValueError(f"gradient_check: the objective must return a scalar or a pair (smooth, jump) of scalars "
                         f"per seed, got {out_shape}")
    if estimators is None:
        estimators = ESTIMATORS if pair else ("straight_through", "score")
    estimators = tuple(estimators)
    unknown = [e for e in estimators if e not in ESTIMATORS]
    if unknown:
        raise ValueError(f"gradient_check: estimators must be among {', '.join(ESTIMATORS)}, got {unknown}")
    if "hybrid" in estimators and not pair:
        raise ValueError("gradient_check: the hybrid estimator needs an objective that returns (smooth, jump)")
    if z is None:
        from scipy.stats import norm
        z = float(norm.ppf(1.0 - 0.025 / d))
    check_positive("z", z)
    eye = jnp.eye(d, dtype=jnp.float32)
    def parts(t, k, temp):
        """(total, jump) of one seed at temperature ``temp``."""
        v = objective(t, k, temp)
        return objective_total(v), (v[1] if pair else jnp.float32(0.0))

    hard = lambda t, k: parts(t, k, jnp.float32(0.0))[0]

    def per_seed(key):
        out = {"value": hard(th, key)}
        fd = jax.vmap(lambda e: (hard(th + fd_step * e, key) - hard(th - fd_step * e, key)) / (2 * fd_step))(eye)
        out["finite_difference"] = fd
        if "straight_through" in estimators or "hybrid" in estimators:
            st = jax.grad(lambda t: parts(t, key, jnp.float32(temperature))[0])(th)
            if "straight_through" in estimators:
                out["straight_through"] = st
        if "score" in estimators or "hybrid" in estimators:
            e = jax.random.normal(jax.random.fold_in(key, 7919), (d,), jnp.float32)
            (tp, jp) = parts(th + score_scale * e, key, jnp.float32(0.0))
            (tm, jm) = parts(th - score_scale * e, key, jnp.float32(0.0))
            if "score" in estimators:
                out["score"] = (tp - tm) / (2 * score_scale) * e
            if "hybrid" in estimators:
                out["hybrid"] = st + (jp - jm) / (2 * score_scale) * e
        return out

    n = keys.shape[0]
    # no chunk larger than the seeds: run_batched pads the last chunk to its full size
    res = montecarlo.run_batched(per_seed, keys, chunk_size=min(chunk_size, n), progress=progress,
                                 desc="gradient check")
    se = lambda a: np.std(a, axis=0, ddof=1) / np.sqrt(n)
    fd = np.asarray(res["finite_difference"], float)
    estimates = {"finite_difference": (fd.mean(0), se(fd))}
    paired, consistent, reason, diff_ses = {}, {}, {}, {}
    margin = rel_tol * float(np.max(np.abs(estimates["finite_difference"][0])))
    for name in estimators:
        g = np.asarray(res[name], float)
        estimates[name] = (g.mean(0), se(g))
        diff = g - fd
        s = se(diff)
        zz = np.where(s > 0, diff.mean(0) / np.where(s > 0, s, 1.0), np.where(diff.mean(0) == 0, 0.0, np.inf))
        paired[name] = zz
        diff_ses[name] = s
        if not np.all(np.isfinite(g)):
            reason[name] = "non-finite values"
        elif not np.all((np.abs(zz) <= z) | (np.abs(diff.mean(0)) <= margin)):
            reason[name] = f"differs from finite differences, |z| = {float(np.max(np.abs(zz))):.1f}"
        elif np.any(estimates[name][1] > max_noise * np.maximum(estimates["finite_difference"][1], 1e-30)):
            ratio = float(np.max(estimates[name][1] / np.maximum(estimates["finite_difference"][1], 1e-30)))
            reason[name] = f"too noisy, std err {ratio:.3g}x the finite differences'"
        elif float(np.max(z * s)) > max(float(np.max(np.abs(g.mean(0)))), float(np.max(np.abs(fd.mean(0))))):
            reason[name] = (f"inconclusive: the check resolves differences of {float(np.max(z * s)):.3g}, more than "
                            f"the gradient itself ({max(float(np.max(np.abs(g.mean(0)))), float(np.max(np.abs(fd.mean(0))))):.3g}); "
                            f"more seeds or a larger fd_step")
        else:
            reason[name] = ""
        consistent[name] = reason[name] == ""
    ok = [nm for nm in estimators if consistent[nm]]
    rec = min(ok, key=lambda nm: (float(np.max(estimates[nm][1])), nm != "straight_through")) if ok else None
    return GradientCheck(theta, float(np.mean(res["value"])), estimates, paired, consistent, reason, rec, (),
                         diff_ses)
