"""Monte-Carlo tuning: grid and random search with common random numbers, and the
hard-trigger evaluation every tuned point goes through.

A candidate is a dict of parameter values (floats or ints); ``per_seed(params, key)``
returns the loss of one run.  Every candidate is run on the *same* keys (common random
numbers), so differences between candidates are not blurred by different noise and
losses: the paired differences have a much smaller variance than the losses.

Integers that shape arrays (N, h) are not runtime arguments: search over them by
building one loop per value inside ``per_seed`` from a Python int -- each distinct
value then compiles once; pass ``static=("N",)`` so those values are baked into a
separate function rather than traced.
"""
from __future__ import annotations

import itertools
import math
import time
import weakref
from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxnc import montecarlo
from jaxnc._validate import check_int, check_range

__all__ = ["grid", "random_points", "SearchResult", "search", "halving_schedule", "successive_halving", "evaluate",
           "mean_ci", "paired_ci"]


def grid(**axes) -> list[dict]:
    """Cartesian product of the given value lists, as a list of candidate dicts."""
    names = list(axes)
    return [dict(zip(names, vals)) for vals in itertools.product(*(list(axes[n]) for n in names))]


def random_points(seed: int, n: int, **bounds) -> list[dict]:
    """``n`` candidates drawn uniformly: ``name=(low, high)`` uniform, ``name=(low, high, "log")``
    log-uniform, ``name=(low, high, "int")`` integers in [low, high]."""
    check_int("n", n, 1)
    rng = np.random.default_rng(seed)
    cols = {}
    for name, b in bounds.items():
        lo, hi, *kind = b
        kind = kind[0] if kind else "lin"
        if kind == "log":
            if lo <= 0:
                raise ValueError(f"{name}: a log-uniform range needs low > 0, got {lo}")
            cols[name] = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
        elif kind == "int":
            cols[name] = rng.integers(int(lo), int(hi) + 1, n)
        elif kind == "lin":
            cols[name] = rng.uniform(lo, hi, n)
        else:
            raise ValueError(f"{name}: kind must be lin, log or int, got {kind!r}")
    return [{k: (int(v[i]) if np.issubdtype(v.dtype, np.integer) else float(v[i])) for k, v in cols.items()}
            for i in range(n)]


mean_ci = montecarlo.mean_ci


def paired_ci(a, b) -> tuple[float, float]:
    """Mean of a - b over common seeds and its 95 % half-width (CRN comparison)."""
    return mean_ci(np.asarray(a, np.float64) - np.asarray(b, np.float64))


class SearchResult(NamedTuple):
    points: list[dict]        # the candidates
    values: np.ndarray        # [candidates, seeds] per-seed losses (common random numbers)
    mean: np.ndarray          # [candidates]
    ci95: np.ndarray          # [candidates] half-width of the 95 % interval of the mean
    best: int                 # index of the lowest mean
    best_point: dict
    best_mean: float
    best_ci95: float
    n_simulations: int
    wall_time_s: float


_WRAPPED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _key_first(per_seed: Callable) -> Callable:
    """``(params, key) -> loss`` as ``(key, params) -> loss`` for run_batched, one wrapper
    per function (run_batched caches its compilation per function object)."""
    try:
        return _WRAPPED[per_seed]
    except (KeyError, TypeError):
        pass
    try:
        ref = weakref.ref(per_seed)        # the wrapper must not keep its own key alive
    except TypeError:
        return lambda key, args: per_seed(args, key)
    f = lambda key, args: ref()(args, key)
    _WRAPPED[per_seed] = f
    return f


_WITH_STATIC: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _with_static(per_seed: Callable, skey: tuple) -> Callable:
    """``(key, args) -> per_seed({**args, **static}, key)`` for run_batched, one wrapper per
    function and static values, kept across calls: repeated searches with the same
    ``per_seed`` (every weight of a study, every round of successive halving) reuse the
    compilation instead of tracing and compiling a fresh lambda each call."""
    st = dict(skey)
    try:
        cache = _WITH_STATIC.setdefault(per_seed, {})
        ref = weakref.ref(per_seed)        # the wrapper must not keep its own key alive
    except TypeError:
        return lambda key, args: per_seed({**args, **st}, key)
    if skey not in cache:
        cache[skey] = lambda key, args: ref()({**args, **st}, key)
    return cache[skey]


def _as_args(point: dict, static: tuple):
    return {k: jnp.asarray(v, jnp.float32) for k, v in point.items() if k not in static}


def _check_seconds(fn: str, max_seconds) -> None:
    """A wall-time budget: None, or a number > 0 (inf allowed); ValueError naming ``fn``."""
    if max_seconds is not None:
        check_range(f"{fn}: max_seconds", max_seconds, 0.0, None, low_open=True, finite=False)


def search(per_seed: Callable, points: list[dict], keys, *, static: tuple = (), chunk_size: int | None = None,
           max_seconds: float | None = None, progress: bool = True, desc: str = "search") -> SearchResult:
    """Evaluate every candidate on the same ``keys`` and return the best (lowest mean).

    ``per_seed(params, key) -> scalar``; the non-static values are passed as runtime
    arguments (one compilation for all candidates with the same static values).  Non-finite
    losses are kept (they make a candidate's mean inf, so it is never chosen).

    ``max_seconds``: a wall-time budget (random search for a given time: pass many
    points); no candidate starts once it is spent (the first always runs). A candidate
    not run has NaN values and an inf mean; ``n_simulations`` counts the runs made.

    Raises:
      ValueError: no candidates, a max_seconds that is not > 0.
    """
    if not points:
        raise ValueError("search: no candidates")
    _check_seconds("search", max_seconds)
    t0 = time.perf_counter()
    n = int(np.asarray(keys).shape[0])
    chunk = chunk_size or n
    rows = []
    for i, p in enumerate(points):
        if i > 0 and max_seconds is not None and time.perf_counter() - t0 >= max_seconds:
            break
        fn = _with_static(per_seed, tuple((k, p[k]) for k in static))
        rows.append(np.asarray(montecarlo.run_batched(fn, keys, args=(_as_args(p, static),),
                                                      chunk_size=chunk, progress=False), np.float64))
        if progress:
            print(f"\r{desc}: {i + 1}/{len(points)}", end="", flush=True)
    if progress:
        print()
    n_run = len(rows)
    values = np.concatenate([np.stack(rows), np.full((len(points) - n_run, n), np.nan)])
    stats = [mean_ci(r) for r in values]
    mean = np.asarray([s[0] for s in stats])
    ci = np.asarray([s[1] for s in stats])
    mean = np.where(np.isfinite(mean), mean, np.inf)
    best = int(np.argmin(mean))
    return SearchResult(points, values, mean, ci, best, points[best], float(mean[best]), float(ci[best]),
                        n_run * n, time.perf_counter() - t0)


def halving_schedule(n_points: int, budget: int) -> list[tuple[int, int]]:
    """(candidates, new seeds per candidate) of each round of :func:`successive_halving`:
    ceil(log2 n) rounds share the budget equally; each keeps the better half."""
    check_int("n_points", n_points, 1)
    rounds = max(1, math.ceil(math.log2(n_points)))
    check_int("budget", budget, rounds * n_points)    # at least one seed per candidate and round
    sched, m = [], n_points
    for _ in range(rounds):
        sched.append((m, max(1, (budget // rounds) // m)))
        m = max(1, math.ceil(m / 2))
    return sched


def successive_halving(per_seed: Callable, points: list[dict], keys, *, budget: int, static: tuple = (),
                       chunk_size: int | None = None, max_seconds: float | None = None, progress: bool = True,
                       desc: str = "halving") -> SearchResult:
    """Monte-Carlo search that spends its budget where it decides (successive halving,
    Jamieson & Talwalkar 2016, with common random numbers).

    ``ceil(log2 n)`` rounds share ``budget`` simulations equally.  In each round every
    surviving candidate runs on the same *new* seeds (taken in order from ``keys``), all
    survivors are ranked by their mean over every seed they have run, and the better half
    goes on; the best of the last round is returned.  A grid of the same budget gives every
    candidate ``budget / n`` seeds; here the final candidates get about
    ``budget / 2 / log2 n`` each, and the clearly bad ones are dropped after a few seeds.
    ``values`` is ``[candidates, seeds]`` with NaN where a dropped candidate did not run;
    ``mean``/``ci95`` are over the seeds each candidate ran.

    Every round runs in chunks of ``chunk_size`` seeds (default: the first round's seeds
    per candidate, the fewest), so all rounds share one compiled program (per static
    value) instead of compiling one per round size. ``max_seconds``: a wall-time budget;
    no round starts once it is spent (the first always runs), and the leader of the last
    round run (by its mean over the seeds it ran) is the result.

    Raises:
      ValueError: no candidates, a budget below one seed per candidate and round, too few
        keys, a chunk_size below 1, a max_seconds that is not > 0.
    """
    if not points:
        raise ValueError("successive_halving: no candidates")
    sched = halving_schedule(len(points), budget)
    chunk = sched[0][1] if chunk_size is None else chunk_size
    check_int("chunk_size", chunk, 1)
    _check_seconds("successive_halving", max_seconds)
    need = sum(s for _, s in sched)
    keys = np.asarray(keys) if not hasattr(keys, "shape") else keys
    if int(keys.shape[0]) < need:
        raise ValueError(f"successive_halving: needs {need} keys for budget {budget} and {len(points)} "
                         f"candidates, got {int(keys.shape[0])}")
    t0 = time.perf_counter()
    values = np.full((len(points), need), np.nan)
    alive, used, sims = list(range(len(points))), 0, 0
    for r, (m, s) in enumerate(sched):
        if r > 0 and max_seconds is not None and time.perf_counter() - t0 >= max_seconds:
            alive = alive[:1]              # ranked at the end of the last round run
            break
        res = search(per_seed, [points[i] for i in alive], keys[used:used + s], static=static, chunk_size=chunk,
                     progress=False)
        values[alive, used:used + s] = res.values
        used, sims = used + s, sims + m * s
        mean = np.asarray([np.mean(values[i, :used]) for i in alive])
        mean = np.where(np.isfinite(mean), mean, np.inf)
        order = np.argsort(mean, kind="stable")
        alive = [alive[j] for j in order[:max(1, math.ceil(m / 2))]] if r < len(sched) - 1 else [alive[order[0]]]
        if progress:
            print(f"\r{desc}: round {r + 1}/{len(sched)}, {m} candidates x {s} seeds", end="", flush=True)
    if progress:
        print()
    stats = np.asarray([mean_ci(row[~np.isnan(row)]) for row in values])   # over the seeds each one ran
    mean = np.where(np.isfinite(stats[:, 0]), stats[:, 0], np.inf)
    ci = stats[:, 1]
    best = alive[0]
    return SearchResult(points, values, mean, ci, best, points[best], float(mean[best]), float(ci[best]),
                        sims, time.perf_counter() - t0)


def evaluate(per_seed: Callable, params: dict, keys, *, chunk_size: int | None = None, progress: bool = False,
             desc: str = "evaluate"):
    """Run ``per_seed(params, key)`` (hard triggers) on ``keys``; returns whatever pytree
    of per-seed arrays it returns, as numpy.  ``params`` are runtime arguments."""
    n = int(np.asarray(keys).shape[0])
    args = {k: jnp.asarray(v, jnp.float32) for k, v in params.items()}
    return montecarlo.run_batched(_key_first(per_seed), keys, args=(args,), chunk_size=chunk_size or n,
                                  progress=progress, desc=desc)
