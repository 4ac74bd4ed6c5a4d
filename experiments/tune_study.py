"""Experiment ``tune-study``: the gradient tuner against random search and successive halving
at equal wall time, on four or five leaves of two loops (issue 31, item 3; docs/tuning_loops.md,
"Gradient tuning against search at equal wall time").

The problems:

* ``hdd`` -- seed 003's HDD servo (Case 4, PETC + NUMRE with noise and disturbance; the
  cascade horizon ``hdd_h``), five leaves at once: the sensor's delta_s and sigma_s (untied),
  the controller side's delta_c and sigma_c (untied) and the MRCI controller's direct gain
  ``controller.law.ctrl.Df`` (the high-frequency gain of eq. 33); objective the GPI of
  eq. (29) (an unstable run costs :data:`GPI_UNSTABLE`);
* ``cartpole`` -- the user example (``examples/cartpole.py``), four leaves: the sensor's
  PETC delta and sigma and two scales of the LQR gain K, one on the cart's entries (p, p')
  and one on the pole's (theta, theta') (:class:`CartpoleGains`, a user's configuration
  around the loop: ``tune_loop`` tunes any dataclass its ``run`` accepts); objective the
  run's quadratic cost plus ``w_cartpole`` times the sensor's rate;
* ``hdd-grid`` -- the two-parameter HDD problem of ``tune-loops`` (delta_s = sigma_s and
  delta_c = sigma_c tied), where the tuner is also compared with a fine grid.

For each problem, every method's wall time is measured from its own start to its own end,
compilations included (the seconds spent lowering and compiling are recorded
beside it, from :func:`jaxnc.cache.compile_clock`):

d. (``hdd-grid``, first) a fine grid, every point on the same ``grid_seeds`` seeds; its
   wall time is the tuners' budget there (the issue's "in no more wall time than that grid");
a. :func:`jaxnc.tune.tune_loop` with its defaults (the score function, 16 seeds a step,
   Adam's step size decayed from 0.3 to 0.03) and ``max_seconds`` = the budget
   (``budget_s``; 90 s on hdd, 180 s on the cart-pole), without its own evaluation
   (``evaluate=False``: the study evaluates every method's point itself); its compile
   clock and per-stage times are stored beside its wall time;
a'. the same tuner confined to the searches' box (``Interval`` constraints,
   :func:`box_constraints`): where a. gains by leaving the box, this shows what the
   gradient does where the searches look;
a''. the two-stage tuner: random search (b.) for ``two_stage`` of the budget, then a. from
   its best for the rest (both stages' times counted);
b. random search: :func:`jaxnc.tune.random_points` in the problem's box, each point run on
   the same ``search_seeds`` seeds (common random numbers) with
   :func:`jaxnc.tune.evaluate`, until the tuner's (a.) wall time is spent;
c. successive halving over random points in the same box, sized to the same wall time by a
   timed probe (:func:`halving_timed`).

Every method's final point and the start are then evaluated with hard triggers on the same
fresh seeds (paired 95 % intervals against the start and against each other); the points
each method held along the way (its incumbents, the tuner's iterates) are evaluated on the
first ``curve_seeds`` of those seeds for the figure (objective against wall time). Each
problem's results are written when it finishes (``<problem>.json``) and reused by a re-run
with the same settings.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

import jaxnc.loop as jl
from jaxnc import montecarlo
from jaxnc.cache import compile_clock
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import markdown_table, save_figure
from jaxnc.tune import (Interval, Positive, evaluate, get_path, mean_ci, paired_ci, param_paths, point_objective,
                        random_points, search, set_paths, tune_loop)

PROBLEMS = ("hdd", "cartpole", "hdd-grid")
GPI_UNSTABLE = 10.0          # the GPI charged to an unstable HDD run (as in tune-loops)
EVAL_SEED = 6_000_007        # fresh: the tuner and the searches use seeds below 10^5
VERSION = 3                  # of this study's definition: a stored problem is reused only at the same version
METHODS = ("grid", "tuner", "tuner-box", "two-stage", "random", "halving")
TUNERS = ("tuner", "tuner-box", "two-stage")
DEFAULT_BUDGET_S = {"hdd": 90.0, "cartpole": 180.0}   # the tuner's max_seconds (hdd-grid: the grid's wall time)


@jl.pytree_dataclass
class CartpoleGains:
    """The cart-pole loop with its state-feedback gain written as K0 diag(k_cart, k_pole,
    k_cart, k_pole), x = (p, theta, p', theta'): two tunable scales of the LQR gain K0 of
    ``loop.controller.K`` (float[1, 4]). ``k_cart``, ``k_pole``: float scalars > 0."""

    loop: Any
    k_cart: Any = 1.0
    k_pole: Any = 1.0

    def build(self) -> jl.Loop:
        """The loop with K = K0 * (k_cart, k_pole, k_cart, k_pole)."""
        s = jnp.stack([self.k_cart, self.k_pole, self.k_cart, self.k_pole]).astype(jnp.float32)
        c = self.loop.controller
        return dataclasses.replace(self.loop, controller=dataclasses.replace(c, K=jnp.asarray(c.K) * s))


class Problem(NamedTuple):
    name: str
    config: Any                  # the configuration at the start point (a Loop, or CartpoleGains)
    params: dict                 # tune_loop's params: {path or tuple of tied paths: constraint}
    objective: Callable
    run: Callable
    bounds: dict                 # the searches' box: {name: (low, high, "log")}
    describe: str
    grid: dict | None = None     # {name: values}: the fine grid (two-parameter problems)


def _hdd_parts(settings):
    from jaxnc.schemes import hdd
    y_tts, ise_tts = hdd.tts_reference(steps=settings["hdd_steps"])
    cs = hdd.controller_design().cs
    loop = hdd.hdd_loop(4, thresholds=(1e-4, 1e-3), h=min(settings["hdd_h"], settings["hdd_steps"] - 1),
                        steps=settings["hdd_steps"])

    def objective(m):
        return jnp.where(m.unstable | ~jnp.isfinite(m.GPI), GPI_UNSTABLE, m.GPI)
    return loop, objective, lambda lp, k: hdd.run(lp, k, y_tts=y_tts, ise_tts=ise_tts, cs=cs)


def _hdd_describe(settings, what):
    return (f"seed 003 HDD, Case 4 (PETC + NUMRE, noise and disturbance), cascade horizon h = "
            f"{min(settings['hdd_h'], settings['hdd_steps'] - 1)}, {settings['hdd_steps']} periods; {what}; GPI of "
            f"eq. (29), W = (0.45, 0.45, 0.1)")


def _hdd(settings) -> Problem:
    loop, objective, run = _hdd_parts(settings)
    df = float(np.asarray(loop.controller.law.ctrl.Df))
    params = {"trigger.delta": Positive(), "trigger.sigma": Positive(), "controller_trigger.delta": Positive(),
              "controller_trigger.sigma": Positive(), "controller.law.ctrl.Df": Positive()}
    bounds = {"trigger.delta": (1e-8, 1e-3, "log"), "trigger.sigma": (1e-8, 1e-3, "log"),
              "controller_trigger.delta": (1e-5, 1.0, "log"), "controller_trigger.sigma": (1e-5, 1.0, "log"),
              "controller.law.ctrl.Df": (0.5 * df, 2.0 * df, "log")}
    return Problem("hdd", loop, params, objective, run, bounds,
                   _hdd_describe(settings, "delta_s, sigma_s, delta_c, sigma_c (untied) and the MRCI's direct gain Df"))


def _hdd_grid(settings) -> Problem:
    loop, objective, run = _hdd_parts(settings)
    s, c = "trigger.delta=trigger.sigma", "controller_trigger.delta=controller_trigger.sigma"
    if len(settings["grid_shape"]) != 2:
        raise ConfigError(f"grid_shape must be two integers (points on the delta_s = sigma_s and delta_c = sigma_c "
                          f"axes), got {settings['grid_shape']!r}")
    n_s, n_c = settings["grid_shape"]
    return Problem("hdd-grid", loop, {("trigger.delta", "trigger.sigma"): Positive(),
                                      ("controller_trigger.delta", "controller_trigger.sigma"): Positive()},
                   objective, run, {s: (1e-8, 1e-3, "log"), c: (1e-5, 1.0, "log")},
                   _hdd_describe(settings, "delta_s = sigma_s and delta_c = sigma_c (tied, as in tune-loops)"),
                   grid={s: np.geomspace(1e-8, 1e-3, n_s).tolist(), c: np.geomspace(1e-5, 1.0, n_c).tolist()})


def _cartpole(settings) -> Problem:
    from jaxnc.experiments.tune_loops import _cartpole_module
    loop = _cartpole_module().cartpole(delta=1e-3)
    loop = dataclasses.replace(loop, trigger=dataclasses.replace(loop.trigger, sigma=np.float32(1e-2)))
    w = float(settings["w_cartpole"])
    params = {"loop.trigger.delta": Positive(), "loop.trigger.sigma": Positive(), "k_cart": Positive(),
              "k_pole": Positive()}
    bounds = {"loop.trigger.delta": (1e-5, 1e-1, "log"), "loop.trigger.sigma": (1e-4, 1.0, "log"),
              "k_cart": (0.5, 2.0, "log"), "k_pole": (0.5, 2.0, "log")}
    return Problem("cartpole", CartpoleGains(loop, np.float32(1.0), np.float32(1.0)), params,
                   lambda m: m.cost_raw + w * m.rate_sc, lambda cfg, k: jl.run(cfg.build(), k), bounds,
                   f"user example: cart-pole over a lossy delayed link with PETC; PETC delta, sigma and two scales "
                   f"of the LQR gain (cart, pole); cost + {w:g} x sensor rate")


BUILDERS = {"hdd": _hdd, "cartpole": _cartpole, "hdd-grid": _hdd_grid}


# ----------------------------------------------------------------------------- timing


def _per_seed(problem: Problem, names: dict) -> Callable:
    """``per_seed(point, key)``: the objective of one run at ``point`` ({name: value},
    every path of a tied name written), hard triggers."""
    return point_objective(problem.config, problem.objective, problem.run, names)


def _finite_mean(v) -> float:
    m = float(np.mean(np.asarray(v, np.float64)))
    return m if math.isfinite(m) else math.inf


def random_stream(seed: int, bounds: dict, block: int = 10_000):
    """Random points in ``bounds`` without end: blocks of ``block`` points from
    :func:`jaxnc.tune.random_points` with seeds ``seed + 1_000_003 b``, b = 0, 1, ... (the
    first block is ``random_points(seed, block)``)."""
    b = 0
    while True:
        yield from random_points(seed + 1_000_003 * b, block, **bounds)
        b += 1


def random_search_timed(per_seed: Callable, bounds: dict, *, budget_s: float, seeds: int, seed: int) -> dict:
    """Random search (:func:`random_stream`: uniform in log for ``(low, high, "log")``
    bounds) until ``budget_s`` seconds have passed since its start: every point on the same
    ``seeds`` seeds (one compiled program), the incumbent the lowest mean. At least one
    point is run.

    Returns a dict: best (point), best_mean, n_points, simulations, wall_time_s and trace
    (the incumbent each time it changed: t, point, mean, n_points)."""
    t0 = time.perf_counter()
    c0 = compile_clock()
    pts = random_stream(seed, bounds)
    keys = montecarlo.seed_keys(seed, seeds)
    best, best_mean, trace, n = None, math.inf, [], 0
    for pt in pts:
        m = _finite_mean(evaluate(per_seed, pt, keys, chunk_size=seeds))
        n += 1
        if best is None or m < best_mean:
            best, best_mean = pt, m
            trace.append({"t": time.perf_counter() - t0, "point": pt, "mean": m, "n_points": n})
        if time.perf_counter() - t0 >= budget_s:
            break
    return {"best": best, "best_mean": best_mean, "n_points": n, "simulations": n * seeds,
            "wall_time_s": time.perf_counter() - t0, "compile_s": (compile_clock() - c0).seconds, "trace": trace}


def halving_timed(per_seed: Callable, bounds: dict, start: dict, *, budget_s: float, seeds: int, seed: int) -> dict:
    """Successive halving (Jamieson & Talwalkar 2016) over random points, sized to end at
    ``budget_s`` seconds after its start.

    A timed probe (the start point on ``seeds`` seeds, run twice: the first compiles) gives
    the time u of one candidate-round of ``seeds`` seeds. Round r runs n / 2^r candidates on
    ``seeds`` x 2^r new seeds each (common to all candidates; every round costs about n u),
    the better half (rounded up) by the mean over all seeds run goes on, so ceil(log2 n)
    rounds cost about n ceil(log2 n) u: n is the largest number of candidates that fits in
    the time left (at least 2). A round is not started once the budget is spent; the
    leader then is the result.
    Every call uses one chunk size (``seeds``), so one compiled program serves all rounds
    and the probe.

    Returns a dict as :func:`random_search_timed`, plus n_candidates, rounds_done and probe_s."""
    t0 = time.perf_counter()
    c0 = compile_clock()
    probe_keys = montecarlo.seed_keys(seed + 7, seeds)
    search(per_seed, [start], probe_keys, chunk_size=seeds, progress=False)         # compiles
    t1 = time.perf_counter()
    search(per_seed, [start], probe_keys, chunk_size=seeds, progress=False)
    unit = max(time.perf_counter() - t1, 1e-6)
    left = budget_s - (time.perf_counter() - t0)
    n = 2
    while (n + 1) * math.ceil(math.log2(n + 1)) * unit <= left:
        n += 1
    rounds = math.ceil(math.log2(n))
    pts = random_points(seed, n, **bounds)
    need = seeds * (2 ** rounds - 1)
    keys = montecarlo.seed_keys(seed, need)
    values = np.full((n, need), np.nan)
    alive, used, sims, trace, done = list(range(n)), 0, 2 * seeds, [], 0
    for r in range(rounds):
        if r > 0 and time.perf_counter() - t0 >= budget_s:
            break
        s = seeds * 2 ** r
        res = search(per_seed, [pts[i] for i in alive], keys[used:used + s], chunk_size=seeds, progress=False)
        values[alive, used:used + s] = res.values
        used, sims, done = used + s, sims + len(alive) * s, r + 1
        mean = np.asarray([_finite_mean(values[i, :used]) for i in alive])
        order = np.argsort(mean, kind="stable")
        trace.append({"t": time.perf_counter() - t0, "point": pts[alive[order[0]]], "mean": float(mean[order[0]]),
                      "n_points": len(alive), "seeds": used})
        alive = [alive[j] for j in order[:max(1, math.ceil(len(alive) / 2))]]
    best = trace[-1]["point"]
    return {"best": best, "best_mean": trace[-1]["mean"], "n_points": n, "n_candidates": n, "rounds": rounds,
            "rounds_done": done, "simulations": sims, "probe_s": unit, "wall_time_s": time.perf_counter() - t0,
            "compile_s": (compile_clock() - c0).seconds, "trace": trace}


def grid_timed(per_seed: Callable, axes: dict, *, seeds: int, seed: int) -> dict:
    """Every point of the grid ``axes`` ({name: values}) on the same ``seeds`` seeds; the best
    mean wins. Returns a dict as :func:`random_search_timed` (trace: the best, at the end)."""
    t0 = time.perf_counter()
    c0 = compile_clock()
    names = list(axes)
    mesh = np.meshgrid(*[np.asarray(axes[n], float) for n in names], indexing="ij")
    pts = [{n: float(m.reshape(-1)[i]) for n, m in zip(names, mesh)} for i in range(mesh[0].size)]
    res = search(per_seed, pts, montecarlo.seed_keys(seed, seeds), chunk_size=seeds, progress=False)
    t = time.perf_counter() - t0
    return {"best": res.best_point, "best_mean": float(res.best_mean), "n_points": len(pts),
            "simulations": int(res.n_simulations), "wall_time_s": t, "compile_s": (compile_clock() - c0).seconds,
            "trace": [{"t": t, "point": res.best_point, "mean": float(res.best_mean), "n_points": len(pts)}]}


# ----------------------------------------------------------------------------- one problem


def _f(x) -> float:
    return float(np.asarray(x))


def _tuner_row(r, t_total: float, start: dict, t_offset: float = 0.0) -> dict:
    """A tune_loop result as a method of the study: its point, times, stages and a trace
    (the start, three iterates at times interpolated over the gradient stage, the end)."""
    tuned = {n: _f(v) for n, v in r.params.items()}
    g_wall = r.stages.get("gradient", (0.0,))[0] if r.stages else 0.0
    trace = [{"t": t_offset, "point": start, "mean": None, "kind": "start"}]
    if r.tune is not None:          # iterates, at times interpolated over the gradient stage (it ends the call)
        hist, steps = r.tune.history.params, len(r.tune.history.objective)
        g0 = t_total - g_wall
        for k in sorted({steps // 4, steps // 2, (3 * steps) // 4}):
            if 0 < k < steps:
                trace.append({"t": g0 + g_wall * k / steps, "point": {n: _f(hist[n][k]) for n in hist},
                              "mean": None, "kind": "iterate (time interpolated)"})
    trace.append({"t": t_total, "point": tuned, "mean": None, "kind": "tuned"})
    return {"best": tuned, "wall_time_s": t_total, "compilations": int(r.n_compilations),
            "own_compile_s": float(r.compile_s), "stages": {k: list(v) for k, v in (r.stages or {}).items()},
            "gradient_wall_time_s": g_wall, "simulations": int(r.tuning_simulations),
            "steps_done": len(r.tune.history.objective) if r.tune is not None else 0,
            "estimator": r.estimator, "estimator_reason": r.estimator_reason,
            "check_seeds": int(r.check.seeds) if r.check is not None else 0,
            "objective_history": r.tune.history.objective.tolist() if r.tune is not None else [], "trace": trace}


def box_constraints(problem: Problem) -> dict:
    """``problem.params`` with each constraint replaced by the searches' box,
    ``Interval(low, high)`` of its bounds (the tuner confined where the searches look)."""
    names = param_paths(problem.params)
    return {key: Interval(*problem.bounds[n][:2]) for key, n in zip(problem.params, names)}


def study(problem: Problem, settings: dict, *, eval_seeds: int, progress: bool = True) -> dict:
    """The grid (a two-parameter problem; it sets the budget), the tuner with a wall-time
    budget, the tuner confined to the searches' box, the two-stage tuner, the two searches
    at the tuner's wall time, and the evaluation of one problem (module docstring)."""
    t_all = time.perf_counter()
    seed = settings["seed"]
    names = param_paths(problem.params)
    start = {n: _f(get_path(problem.config, p[0])) for n, p in names.items()}
    methods = {}
    if problem.grid is not None:
        methods["grid"] = grid_timed(_per_seed(problem, names), problem.grid, seeds=settings["grid_seeds"],
                                     seed=seed + 3_000)
        if progress:
            print(f"[{problem.name}] grid: {methods['grid']['wall_time_s']:.1f} s, {methods['grid']['n_points']} points")
    budget = (settings["budget_s"] or (methods["grid"]["wall_time_s"] if "grid" in methods
                                       else DEFAULT_BUDGET_S[problem.name]))
    kw = dict(objective=problem.objective, run=problem.run, steps=settings["steps"], batch=settings["batch"],
              estimator=settings["estimator"], check_seeds=settings["check_seeds"],
              check_max_seeds=settings["check_max_seeds"] or None, seed=seed, evaluate=False, progress=progress)

    def tuner(config, params, seconds):
        c0, t0 = compile_clock(), time.perf_counter()
        r = tune_loop(config, params, max_seconds=seconds, **kw)
        return r, time.perf_counter() - t0, (compile_clock() - c0).seconds

    # (a) the tuner with the budget; (a') confined to the searches' box
    for m, params in (("tuner", problem.params), ("tuner-box", box_constraints(problem))):
        r, t, c = tuner(problem.config, params, budget)
        methods[m] = _tuner_row(r, t, start) | {"compile_s": c}
        if progress:
            print(f"[{problem.name}] {m}: {t:.1f} s, {methods[m]['steps_done']} steps, {methods[m]['best']}")
    # (a'') two stages: random search for a fraction of the budget, then the tuner from its best for the rest
    c0, t0 = compile_clock(), time.perf_counter()
    first = random_search_timed(_per_seed(problem, names), problem.bounds, budget_s=settings["two_stage"] * budget,
                                seeds=settings["search_seeds"], seed=seed + 4_000)
    t_first = time.perf_counter() - t0
    cfg = set_paths(problem.config, {p: np.float32(first["best"][n]) for n in first["best"] for p in names[n]})
    r, t, _ = tuner(cfg, problem.params, max(budget - t_first, 1e-3))
    row = _tuner_row(r, t_first + t, start, t_offset=0.0)
    row["trace"] = [dict(x, t=x["t"]) for x in first["trace"]] + row["trace"][1:]
    methods["two-stage"] = row | {"compile_s": (compile_clock() - c0).seconds, "search_s": t_first,
                                  "search_points": first["n_points"], "gradient_start": first["best"],
                                  "simulations": row["simulations"] + first["simulations"]}
    if progress:
        print(f"[{problem.name}] two-stage: {t_first:.1f} s search ({first['n_points']} points) + {t:.1f} s tuner")
    t_tuner = methods["tuner"]["wall_time_s"]

    # (b), (c): the tuner's wall time, each its own per-seed function (its own compilations)
    methods["random"] = random_search_timed(_per_seed(problem, names), problem.bounds, budget_s=t_tuner,
                                            seeds=settings["search_seeds"], seed=seed + 1_000)
    if progress:
        print(f"[{problem.name}] random search: {methods['random']['wall_time_s']:.1f} s, "
              f"{methods['random']['n_points']} points")
    methods["halving"] = halving_timed(_per_seed(problem, names), problem.bounds, start, budget_s=t_tuner,
                                       seeds=settings["sh_seeds"], seed=seed + 2_000)
    if progress:
        print(f"[{problem.name}] successive halving: {methods['halving']['wall_time_s']:.1f} s, "
              f"{methods['halving']['n_candidates']} candidates, {methods['halving']['rounds_done']} rounds")

    # evaluation: hard triggers, the same fresh seeds for every point
    ev = _per_seed(problem, names)
    ekeys = montecarlo.seed_keys(EVAL_SEED, eval_seeds)
    chunk = min(eval_seeds, 256)
    cache = {}

    def values(pt, n):
        k = (json.dumps({a: float(b) for a, b in pt.items()}, sort_keys=True), n)
        if k not in cache:
            cache[k] = np.asarray(evaluate(ev, pt, ekeys[:n], chunk_size=min(chunk, n)), np.float64)
        return cache[k]
    final = {"start": values(start, eval_seeds)} | {m: values(d["best"], eval_seeds) for m, d in methods.items()}
    n_curve = min(settings["curve_seeds"], eval_seeds)
    for d in methods.values():
        for row in d["trace"]:
            row["eval"] = mean_ci(values(row["point"], n_curve))
    pairs = [(m, "start") for m in methods] + [(a, b) for i, a in enumerate(methods) for b in list(methods)[i + 1:]]
    out = {
        "loop": problem.name, "describe": problem.describe, "start": start,
        "params": list(names), "bounds": {n: list(b) for n, b in problem.bounds.items()},
        "grid_axes": problem.grid, "methods": methods,
        "eval": {"seeds": eval_seeds, "curve_seeds": n_curve, "seed": EVAL_SEED,
                 "mean": {m: mean_ci(v) for m, v in final.items()},
                 "paired": {f"{a} - {b}": paired_ci(final[a], final[b]) for a, b in pairs}},
    }
    if "grid" in methods:
        g = float(np.mean(final["grid"]))
        out["grid_check"] = {}
        for m in TUNERS:
            d, ci = paired_ci(final[m], final["grid"])
            out["grid_check"][m] = {"over_grid": (d / g, ci / abs(g)), "within_2_percent": bool(d / abs(g) <= 0.02),
                                    "not_slower": bool(methods[m]["wall_time_s"] <= methods["grid"]["wall_time_s"])}
    out["wall_time_s"] = time.perf_counter() - t_all
    return out


# ----------------------------------------------------------------------------- report


def _fmt_pt(pt: dict) -> str:
    return ", ".join(f"{k} = {v:.3g}" for k, v in pt.items())


def _ci(x) -> str:
    return f"{x[0]:.4g} ± {x[1]:.2g}"


def _verdict(d) -> str:
    m, ci = d
    return "lower" if m + ci < 0 else "higher" if m - ci > 0 else "no difference resolved"


def tables(results: list[dict]) -> str:
    """The study's tables (markdown): per method, its wall time, compile time, simulations,
    final point and fresh-seed objective; then the paired differences."""
    rows = []
    for res in results:
        e = res["eval"]
        rows.append([res["loop"], "start", "", "", "", "", _fmt_pt(res["start"]), _ci(e["mean"]["start"]), ""])
        for m, d in res["methods"].items():
            how = (f"{d['estimator']}, {d['steps_done']} steps, {d.get('compilations', '?')} compilations"
                   + (f", after {d['search_points']} random points in {d['search_s']:.1f} s" if m == "two-stage" else "")
                   if m in TUNERS else
                   f"{d['n_candidates']} candidates, {d['rounds_done']}/{d['rounds']} rounds" if m == "halving" else
                   f"{d['n_points']} points")
            rows.append([res["loop"], m, f"{d['wall_time_s']:.1f}", f"{d['compile_s']:.1f}", str(d["simulations"]),
                         how, _fmt_pt(d["best"]), _ci(e["mean"][m]), _ci(e["paired"][f"{m} - start"])])
    t1 = markdown_table(["problem", "method", "wall s", "compile s", "simulations", "how", "final point",
                         "objective (fresh seeds, 95 %)", "− start (paired)"], rows)
    rows = []
    for res in results:
        for k, d in res["eval"]["paired"].items():
            if not k.endswith("- start"):
                rows.append([res["loop"], k, _ci(d), _verdict(d)])
    t2 = markdown_table(["problem", "difference", "paired mean (95 %)", "first is"], rows)
    text = ("Each method's final point, hard triggers, the same fresh seeds (wall time: the method's own, "
            "compilations included; compile: the part of it spent lowering and compiling):\n\n" + t1
            + "\n\nPaired differences between methods (same fresh seeds):\n\n" + t2 + "\n")
    for res in results:
        for m, gc in res.get("grid_check", {}).items():
            r, ci = gc["over_grid"]
            text += (f"\n{res['loop']}: {m} against the grid's best: {100 * r:+.2f} % ± {100 * ci:.2f} % "
                     f"(within 2 %: {'yes' if gc['within_2_percent'] else 'no'}); {m} "
                     f"{res['methods'][m]['wall_time_s']:.1f} s, grid {res['methods']['grid']['wall_time_s']:.1f} s "
                     f"(no more wall time: {'yes' if gc['not_slower'] else 'no'})\n")
    return text


COLORS = {"tuner": "C3", "tuner-box": "C1", "two-stage": "C4", "random": "C0", "halving": "C2", "grid": "C7"}


def plot(results: list[dict], out: Path) -> Path:
    """Objective (fresh seeds) against wall time, one panel per problem."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.2), squeeze=False)
    for ax, res in zip(axes[0], results):
        for m, d in res["methods"].items():
            tr = d["trace"]
            t = [row["t"] for row in tr]
            y = [row["eval"][0] for row in tr]
            if m in ("tuner", "tuner-box"):
                ax.plot(t, y, "o:", color=COLORS[m], label=f"{m} (iterates: times interpolated)")
            else:
                ax.step(t + [d["wall_time_s"]], y + [y[-1]], where="post", color=COLORS[m], label=m)
                ax.plot(t, y, ".", color=COLORS[m])
            fm, fci = res["eval"]["mean"][m]
            ax.errorbar([d["wall_time_s"]], [fm], yerr=[fci], fmt="s", color=COLORS[m], ms=7, capsize=3)
        ax.axhline(res["eval"]["mean"]["start"][0], color="k", ls="--", lw=0.8, label="start")
        ax.set_xlabel("wall time of the method (s, compilations included)")
        ax.set_ylabel(f"objective (first {res['eval']['curve_seeds']} fresh seeds; squares: "
                      f"{res['eval']['seeds']})", fontsize=8)
        ax.set_title(res["loop"], fontsize=10)
        ax.legend(fontsize=7)
    p = save_figure(fig, out / "tune_study.png", dpi=110)
    return p


def _config(settings: dict, seeds: int) -> dict:
    return {k: v for k, v in settings.items() if k != "loops"} | {"seeds": seeds, "version": VERSION}


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    return montecarlo.stored_study(
        out, experiment="tune-study", config=_config(settings, seeds), progress=progress,
        parts=PROBLEMS if settings["loops"] == "all" else (settings["loops"],),
        compute=lambda name: study(BUILDERS[name](settings), settings, eval_seeds=seeds, progress=progress),
        tables=tables, plot=plot)


register(Experiment(
    name="tune-study",
    description="the gradient tuner vs random search and successive halving at equal wall time (4-5 leaves, two loops)",
    options=(
        Option("loops", "choice", "all", "which problem(s)", choices=(*PROBLEMS, "all")),
        Option("budget_s", "float", 0.0, "the tuner's max_seconds; 0: 90 s (hdd), 180 s (cartpole), the grid's wall "
               "time (hdd-grid)", low=0.0, high=1e5),
        Option("steps", "int", 100_000, "the most gradient steps of tune_loop (the time budget ends it first)", low=1,
               high=1_000_000),
        Option("batch", "int", 16, "seeds per gradient step (tune_loop's default)", low=2, high=4096),
        Option("estimator", "choice", "score", "tune_loop's estimator (its default: score; auto runs its check)",
               choices=("score", "auto", "richardson")),
        Option("two_stage", "float", 1 / 3, "two-stage tuner: the fraction of the budget its random search gets",
               low=0.01, high=0.99),
        Option("check_seeds", "int", 256, "seeds of tune_loop's gradient check (estimator auto)", low=2,
               high=100_000),
        Option("check_max_seeds", "int", 0, "the check's doubling budget; 0: tune_loop's default (32768)",
               low=0, high=1_000_000),
        Option("search_seeds", "int", 32, "random search: seeds per point (common to all points)", low=1,
               high=100_000),
        Option("sh_seeds", "int", 16, "successive halving: seeds per candidate in its first round", low=1,
               high=100_000),
        Option("grid_seeds", "int", 128, "hdd-grid: seeds per grid point", low=1, high=100_000),
        Option("grid_shape", "ints", (12, 10), "hdd-grid: points on the delta_s = sigma_s and delta_c = sigma_c axes",
               low=2, high=1000),
        Option("curve_seeds", "int", 256, "fresh seeds of the figure's points (the final points use --seeds)",
               low=2, high=100_000),
        Option("hdd_h", "int", 32, "HDD: the cascade horizon h (static; the paper's rule h >= N_max is steps - 1)",
               low=1, high=10_000),
        Option("hdd_steps", "int", 464, "HDD: periods of a run (the paper's 464)", low=8, high=100_000),
        Option("w_cartpole", "float", 2.0, "cart-pole: weight of the sensor rate", low=0.0, high=1e4),
        Option("seed", "int", 0, "base seed of the tuner and the searches (evaluation: 6000007)", low=0,
               high=1_000_000),
    ),
    run=run,
))
