"""Gradient tuning with optax on a Monte-Carlo objective.

The user writes a per-seed loss ``loss(params, key, temperature) -> scalar`` where
``params`` is a dict of arrays in their natural (constrained) units, e.g.
``{"sigma": [9], "delta": [9]}`` or ``{"Kp": [3], "Ki": [3]}``, and builds the loop from
them with ``dataclasses.replace`` (never differentiate a whole loop: it has integer
leaves).  :func:`tune` minimises E_seeds[loss] by stochastic gradient steps:

* constraints by reparametrisation (dynamax style): the optimiser works on raw,
  unconstrained values; :class:`Positive` maps them through exp (raw = log of the value
  above its bound, so a step in raw is a relative step, the same for a threshold of 1e-4
  and one of 10), :class:`Interval` through a sigmoid, so no projection is ever needed;
* each step draws ``batch`` fresh seeds (``resample=True``, stochastic optimisation) or
  reuses the same ones (sample-average approximation);
* the trigger temperature is annealed geometrically from ``temperature[0]`` to
  ``temperature[1]`` and passed to the loss as a runtime argument (one compilation);
* ``estimator`` picks how gradients cross the events (see :mod:`jaxnc.tune.estimators`):
  ``"straight_through"`` and ``"sigmoid"`` differentiate the loss (the loss decides which
  trigger to build from the temperature), ``"score"`` uses the antithetic Gaussian
  score function on the raw parameters and never differentiates the simulation,
  ``"richardson"`` the same extrapolated over its scale (s and 2 s: the smoothing bias
  O(s^2) becomes O(s^4), :mod:`jaxnc.tune.check`);
  ``"hybrid"`` takes a loss that returns ``(smooth, jump)``: the pathwise
  (straight-through) gradient of ``smooth + jump`` plus the antithetic score-function
  gradient of ``jump`` alone, for objectives whose discrete part (a run that fails and
  is charged a constant) has no pathwise derivative;
* the returned parameters are the average of the raw iterates over the last
  ``average_tail`` fraction of steps (Polyak-Ruppert averaging, which removes most of
  the step-to-step noise of a stochastic gradient);
* a tqdm bar shows the running objective; the history keeps it per step.

The tuned point must then be evaluated with hard triggers on fresh seeds
(:func:`jaxnc.tune.search.evaluate` does this).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from tqdm.auto import tqdm

from jaxnc import montecarlo
from jaxnc._validate import check_int, check_positive, check_range
from jaxnc.tune.estimators import ESTIMATORS, annealed_temperature, score_grad

__all__ = ["Positive", "Interval", "Unconstrained", "constrain", "unconstrain", "TuneHistory", "TuneResult", "tune",
           "simulations_per_step"]


@dataclasses.dataclass(frozen=True)
class Positive:
    """value = low + exp(raw), raw = log(value - low): strictly above ``low`` (thresholds,
    gains). Raw steps are relative steps of ``value - low``, so parameters that span
    decades (event thresholds from 1e-5 to 1) move alike."""
    low: float = 0.0

    def __post_init__(self):
        check_range("Positive: low", self.low)

    def forward(self, raw):
        return self.low + jnp.exp(raw)

    def raw(self, value, xp=jnp):
        """raw = log(value - low), unchecked, with the array module ``xp`` (``jnp``:
        traceable; ``np``: on the host, as :meth:`inverse`)."""
        return xp.log(value - self.low)

    def inverse(self, value):
        v = np.asarray(value, np.float64)
        if not np.all(np.isfinite(v) & (v > self.low)):
            raise ValueError(f"must be finite and > {self.low:g} (Positive(low={self.low:g}): raw = "
                             f"log(value - low)), got {v.tolist()}")
        return self.raw(v, np).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Interval:
    """value = low + (high - low) sigmoid(raw): inside the open interval (low, high)."""
    low: float
    high: float

    def __post_init__(self):
        check_range("Interval: low", self.low)
        check_range("Interval: high", self.high)
        if not self.high > self.low:
            raise ValueError(f"Interval: high must be > low, got low={self.low}, high={self.high}")

    def forward(self, raw):
        return self.low + (self.high - self.low) * jax.nn.sigmoid(raw)

    def raw(self, value, xp=jnp):
        """raw = logit((value - low) / (high - low)), unchecked, with the array module ``xp``
        (``jnp``: traceable; ``np``: on the host, as :meth:`inverse`)."""
        f = (value - self.low) / (self.high - self.low)
        return xp.log(f / (1 - f))

    def inverse(self, value):
        v = np.asarray(value, np.float64)
        if not np.all(np.isfinite(v) & (v > self.low) & (v < self.high)):
            raise ValueError(f"must be inside the open interval ({self.low:g}, {self.high:g}) (Interval: raw = "
                             f"logit of the fraction of the interval), got {v.tolist()}")
        return self.raw(v, np).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Unconstrained:
    """value = raw: any finite real."""

    def forward(self, raw):
        return raw

    def raw(self, value, xp=jnp):
        """raw = value (unchecked)."""
        return value

    def inverse(self, value):
        v = np.asarray(value, np.float64)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"must be finite, got {v.tolist()}")
        return self.raw(v, np).astype(np.float32)


def constrain(raw: dict, constraints: dict) -> dict:
    """Raw (optimiser) values -> parameters in their natural units."""
    return {k: constraints.get(k, Unconstrained()).forward(v) for k, v in raw.items()}


def unconstrain(params: dict, constraints: dict) -> dict:
    """Parameters -> raw values (float32), the inverse of :func:`constrain`.

    Raises:
      ValueError: a constraint names a parameter not in ``params``; a value outside its
        constraint's domain (``Positive(low)``: > low; ``Interval(low, high)``: strictly
        inside; any: finite), naming the parameter. Nothing is moved to the edge."""
    unknown = set(constraints) - set(params)
    if unknown:
        raise ValueError(f"constraints name parameters that are not tuned: {sorted(unknown)}")
    raw = {}
    for k, v in params.items():
        try:
            raw[k] = jnp.asarray(constraints.get(k, Unconstrained()).inverse(v))
        except ValueError as e:
            raise ValueError(f"the value of {k!r} {e}") from None
    return raw


class TuneHistory(NamedTuple):
    """Per optimisation step (numpy arrays)."""
    objective: np.ndarray     # [steps] mean loss over the step's seeds (at the step's temperature)
    temperature: np.ndarray   # [steps]
    grad_norm: np.ndarray     # [steps] norm of the raw-parameter gradient
    params: dict              # name -> [steps, ...] constrained parameters before the step


class TuneResult(NamedTuple):
    params: dict              # tuned parameters (numpy), natural units
    history: TuneHistory
    n_simulations: int        # closed-loop runs used (each one forward [+ one backward] pass)
    wall_time_s: float


def _score_pairs(estimator: str, batch: int, score_pairs: int | None) -> int:
    """Antithetic pairs per step: batch // 2 for ``"score"``, ``score_pairs`` (default
    batch // 2, at least 1) for ``"hybrid"``, none for the pathwise estimators."""
    if estimator == "score":
        return batch // 2
    if estimator == "richardson":
        return max(1, batch // 4)
    if estimator == "hybrid":
        return score_pairs or max(1, batch // 2)
    return 0


def simulations_per_step(estimator: str, batch: int, score_pairs: int | None = None) -> int:
    """Closed-loop runs one step of :func:`tune` costs (for equal-budget comparisons)."""
    pairs = _score_pairs(estimator, batch, score_pairs)
    if estimator == "corrected":
        return 4 * batch        # the run, the sensor's replay, two alternatives (jaxnc.tune.jump)
    if estimator == "richardson":
        return 4 * pairs        # each pair at s and at 2 s
    return 2 * pairs if estimator == "score" else batch + 2 * pairs


def tune(loss: Callable, init: dict, constraints: dict | None = None, *, steps: int = 50, batch: int = 8,
         optimizer: optax.GradientTransformation | None = None, estimator: str = "straight_through",
         temperature: tuple[float, float] = (1.0, 0.1), seed: int = 0, resample: bool = True,
         score_scale: float = 0.1, score_pairs: int | None = None, average_tail: float = 0.25,
         progress: bool = True, desc: str = "tune", corrected: Callable | None = None,
         host_grad: Callable | None = None, learning_rate: float | tuple | None = None,
         max_seconds: float | None = None, stop: Callable[[], bool] | None = None) -> TuneResult:
    """Minimise E_seeds[loss(params, key, temperature)] over ``params`` (a dict of arrays).

    ``batch`` seeds per step (for ``"score"``: batch // 2 antithetic pairs, the same
    number of simulations; for ``"richardson"``: max(1, batch // 4) pairs, each at s and
    2 s; for ``"hybrid"``: ``batch`` pathwise seeds plus
    ``score_pairs`` antithetic pairs, default batch // 2, i.e. 2 x batch simulations).
    Seeds come from :func:`jaxnc.montecarlo.seed_keys` with base ``seed``: step k uses
    seeds ``k*batch ... (k+1)*batch - 1`` (``resample``) or always ``0 ... batch - 1``.
    Evaluate the result on a different base seed. ``estimator="corrected"`` needs
    ``corrected(raw float[d], key) -> (value, grad float[d])``, one seed's corrected
    gradient in the flat raw coordinates (:mod:`jaxnc.tune.jump`; ``loss`` is then unused
    for gradients, and :func:`jaxnc.tune.tune_loop` builds it).
    ``host_grad(raw dict, keys [batch, 2], temperature) -> (value, grads dict)``, a host
    function, replaces the estimator's own step (``loss`` is then unused): only the
    optimiser's update is compiled here, and the simulations run in whatever program
    ``host_grad`` calls (:func:`jaxnc.tune.tune_loop` shares one between its
    score-function steps and its evaluation).

    ``learning_rate``: Adam's step size on the raw parameters when ``optimizer`` is None
    (default 0.05), or a pair ``(start, end)`` decayed geometrically over the budget: at
    step k the rate is start (end / start)^f, f = max(k / steps, elapsed / max_seconds)
    the fraction of the budget used (the rate is a runtime argument of the compiled
    update, ``optax.inject_hyperparams``: one compilation for every rate).
    ``max_seconds``: a wall-time budget from this call's start, the compilation of the
    step included: no step starts once the time spent plus the last step's duration
    would exceed it (the first step always runs, and the second whenever time is left:
    the first one's duration includes the compilation); ``steps`` is then the most steps.
    The number of steps made is ``len(history.objective)``; with ``max_seconds`` it
    depends on the machine's speed (``steps`` alone gives a reproducible run).
    ``stop() -> bool``, a host function asked before every step after the first: True
    ends the steps there (e.g. :func:`jaxnc.tune.tune_loop`'s rule that hands an
    unresolved gradient stage's budget to its search's finalists); ``steps`` is then the
    most steps, as with ``max_seconds``.
    Polyak averaging runs over the last ``average_tail`` fraction of the steps made.

    Raises:
      ValueError: steps or batch below their minimum, an unknown estimator, ``corrected``
        missing for ``"corrected"``, ``average_tail`` outside [0, 1], both ``optimizer``
        and ``learning_rate``, a learning rate that is not > 0 (or a pair of them),
        ``max_seconds`` not > 0.
    """
    check_int("steps", steps, 1)
    check_int("batch", batch, 2 if estimator == "score" else 1)
    if score_pairs is not None:
        check_int("score_pairs", score_pairs, 1)
    check_range("average_tail", average_tail, 0.0, 1.0)
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if estimator == "corrected" and not callable(corrected):
        raise ValueError("estimator='corrected' needs corrected(raw, key) -> (value, grad)")
    if optimizer is not None and learning_rate is not None:
        raise ValueError("tune: give either optimizer or learning_rate, not both")
    lr_pair = _rate_pair(0.05 if learning_rate is None else learning_rate)
    if max_seconds is not None:
        check_positive("max_seconds", max_seconds)
    constraints = dict(constraints or {})
    scheduled = optimizer is None
    optimizer = optimizer or optax.inject_hyperparams(optax.adam)(learning_rate=lr_pair[0])
    raw0 = unconstrain({k: np.asarray(v, np.float32) for k, v in init.items()}, constraints)
    opt_state = optimizer.init(raw0)

    def mean_loss(raw, keys, temp):
        p = constrain(raw, constraints)
        return jnp.mean(jax.vmap(lambda k: loss(p, k, temp))(keys))

    n_pairs = _score_pairs(estimator, batch, score_pairs)
    sims_per_step = simulations_per_step(estimator, batch, score_pairs)
    if estimator in ("score", "richardson"):
        flat0, unravel = ravel_pytree(raw0)

        def value_and_grad(raw, keys, temp):
            fn = lambda flat, k: loss(constrain(unravel(flat), constraints), k, temp)
            v, g = score_grad(fn, ravel_pytree(raw)[0], keys[0], n_pairs, score_scale,
                              richardson=estimator == "richardson")
            return v, unravel(g)
    elif estimator == "hybrid":
        def value_and_grad(raw, keys, temp):
            def total(r):
                p = constrain(r, constraints)
                smooth, jump = jax.vmap(lambda k: loss(p, k, temp))(keys)
                return jnp.mean(smooth + jump)
            value, g_path = jax.value_and_grad(total)(raw)
            flat, unravel = ravel_pytree(raw)
            jump_fn = lambda f, k: loss(constrain(unravel(f), constraints), k, temp)[1]
            # the pairs' seeds are drawn from the step's first key: independent of the batch
            _, g_jump = score_grad(jump_fn, flat, jax.random.fold_in(keys[0], 7), n_pairs, score_scale)
            return value, jax.tree.map(jnp.add, g_path, unravel(g_jump))
    elif estimator == "corrected":
        def value_and_grad(raw, keys, temp):
            flat, unravel = ravel_pytree(raw)
            v, g = jax.vmap(lambda k: corrected(flat, k))(keys)
            return jnp.mean(v), unravel(jnp.mean(g, axis=0))
    else:
        value_and_grad = jax.value_and_grad(mean_loss)

    def update(raw, opt_state, value, grads, lr):
        grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), grads)   # divergence is data
        if scheduled:
            opt_state = opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})
        updates, opt_state = optimizer.update(grads, opt_state, raw)
        gnorm = optax.tree.norm(grads)
        return optax.apply_updates(raw, updates), opt_state, value, gnorm

    if host_grad is None:
        @jax.jit
        def step_fn(raw, opt_state, keys, temp, lr):
            return update(raw, opt_state, *value_and_grad(raw, keys, temp), lr)
    else:
        update_fn = jax.jit(update)

        def step_fn(raw, opt_state, keys, temp, lr):
            value, grads = host_grad(raw, keys, temp)
            return update_fn(raw, opt_state, jnp.float32(value), grads, lr)

    t0 = time.perf_counter()
    raw = raw0
    objs, temps, gnorms, hist = [], [], [], {k: [] for k in raw0}
    iterates = []
    last = 0.0
    with tqdm(total=steps, desc=desc, disable=not progress, dynamic_ncols=True) as bar:
        for k in range(steps):
            elapsed = time.perf_counter() - t0
            # the first step's time includes its compilation: the second starts while time is left
            if k > 0 and max_seconds is not None and elapsed + (last if k > 1 else 0.0) > max_seconds:
                break
            if k > 0 and stop is not None and stop():
                break
            used = max(k / steps, elapsed / max_seconds if max_seconds is not None else 0.0)
            lr = lr_pair[0] * (lr_pair[1] / lr_pair[0]) ** min(used, 1.0)
            keys = montecarlo.seed_keys(seed, batch, start=k * batch if resample else 0)
            temp = (float(annealed_temperature(k, steps, *temperature))
                    if estimator not in ("score", "richardson") else 0.0)
            p_now = constrain(raw, constraints)
            for name in hist:
                hist[name].append(np.asarray(p_now[name]))
            ts = time.perf_counter()
            raw, opt_state, value, gnorm = step_fn(raw, opt_state, keys, jnp.float32(temp), jnp.float32(lr))
            iterates.append(jax.tree.map(np.asarray, raw))
            value = float(value)
            last = time.perf_counter() - ts
            objs.append(value)
            temps.append(temp)
            gnorms.append(float(gnorm))
            bar.set_postfix(objective=f"{value:.4g}", T=f"{temp:.3g}")
            bar.update(1)
    done = len(objs)
    tail = iterates[done - max(1, int(round(average_tail * done))):] if average_tail > 0 else iterates[-1:]
    # averaged on the host: a device mean over a stack of len(tail) would compile one program per tail length
    raw_final = jax.tree.map(lambda *xs: np.mean(np.stack(xs), axis=0), *tail)
    params = {k: np.asarray(v) for k, v in constrain(raw_final, constraints).items()}
    history = TuneHistory(np.asarray(objs), np.asarray(temps), np.asarray(gnorms),
                          {k: np.stack(v) for k, v in hist.items()})
    return TuneResult(params, history, done * sims_per_step, time.perf_counter() - t0)


def _rate_pair(learning_rate) -> tuple[float, float]:
    """``(start, end)`` of a learning rate given as a number (constant) or a pair, each > 0."""
    pair = tuple(learning_rate) if isinstance(learning_rate, (tuple, list)) else (learning_rate, learning_rate)
    if len(pair) != 2 or not all(isinstance(v, (int, float)) and np.isfinite(v) and v > 0 for v in pair):
        raise ValueError(f"learning_rate must be a number > 0 or a pair (start, end) of them, got {learning_rate!r}")
    return float(pair[0]), float(pair[1])
