"""Does tuning more leaves make ``tune_loop`` beat an equal-budget search on the tune-loops
cart-pole and DRHE? (helper tl, 2026-12-04; docs/tuning_loops.md, "Four leaves on the
cart-pole and on DRHE".)

Four leaves instead of tune-loops' one or two:

* ``cartpole``: the PETC delta and sigma and two scales of the LQR gain
  (``experiments.tune_study.CartpoleGains``, K = K0 diag(k_cart, k_pole, k_cart, k_pole));
  grid: tune-loops' nine deltas x sigma in {1e-4, 1e-2, 1} x each scale in {0.5, 1, 2}.
* ``drhe``: tune-loops' DRHE delta and sigma and the path follower's look-ahead ``L_ref``
  and heading gain ``K_psi`` (each tied between the controller's and the actuator's copy);
  grid: tune-loops' 6 x 4 thresholds x each gain at {0.5, 1, 2} x nominal.

As in tune-loops: ``tune_loop`` two-stage (successive halving over tune-loops' own
threshold grid, 1024 simulations, picks the thresholds' start; then 200 score steps of 16
seeds on all four leaves with the budget rule; then the pick or the fallback), and
successive halving with the simulations the tuner spent over the four-leaf grid
(``search4``), which holds tune-loops' grid at the start's other leaves as a subset; also,
as a reference, the same budget over tune-loops' grid alone (``search1``). The points are
evaluated by tune-loops' own :func:`evaluate` (its fresh seeds, grown by Cochran's rule).

    PYTHONPATH=. python benchmarks/tune_loops_leaves.py --loop cartpole|drhe [--sigma0 1e-4]
        [--lr 0.3,0.03] [--resolve-at 0.25] [--estimator score] [--max-eval 65536] [--out f.json]
    PYTHONPATH=. python benchmarks/tune_loops_leaves.py --loop cartpole|drhe --landscape 8192
    PYTHONPATH=. python benchmarks/tune_loops_leaves.py --check-lref 2048
"""
from __future__ import annotations

import argparse
import itertools
import json
import resource
import time

import numpy as np

from jaxnc import montecarlo
from jaxnc.experiments import tune_loops as tl
from jaxnc.tune import Positive, param_paths, successive_halving, tune_loop


def problem(sigma0: float) -> tl.Problem:
    import dataclasses
    import jaxnc.loop as jl
    from jaxnc.experiments.tune_study import CartpoleGains
    loop = tl._cartpole_module().cartpole(delta=1e-3)
    loop = dataclasses.replace(loop, trigger=dataclasses.replace(loop.trigger, sigma=np.float32(sigma0)))
    params = {"loop.trigger.delta": Positive(), "loop.trigger.sigma": Positive(), "k_cart": Positive(),
              "k_pole": Positive()}
    axes = {"loop.trigger.delta": np.geomspace(1e-5, 1e-1, 9), "loop.trigger.sigma": np.asarray([1e-4, 1e-2, 1.0]),
            "k_cart": np.asarray([0.5, 1.0, 2.0]), "k_pole": np.asarray([0.5, 1.0, 2.0])}
    return tl.Problem("cartpole", CartpoleGains(loop, np.float32(1.0), np.float32(1.0)), params,
                      lambda m: m.cost_raw + 2.0 * m.rate_sc, lambda cfg, k: jl.run(cfg.build(), k), {}, axes,
                      "cart-pole, four leaves", fd_step=0.2)


GAIN_PATHS = {"L_ref": ("controller.actuator.law.L_ref", "actuator.law.L_ref"),
              "K_psi": ("controller.actuator.law.K_psi", "actuator.law.K_psi")}


def drhe_problem() -> tl.Problem:
    """tune-loops' DRHE with two more leaves: the path follower's look-ahead L_ref and heading
    gain K_psi (each tied between the controller's and the actuator's copy of the follower)."""
    pb = tl._drhe({"w_drhe": 30.0})
    law = pb.loop.actuator.law
    params = dict(pb.params) | {GAIN_PATHS[n]: Positive() for n in ("L_ref", "K_psi")}
    axes = dict(pb.axes) | {"=".join(GAIN_PATHS[n]): float(np.asarray(getattr(law, n))) * np.asarray([0.5, 1.0, 2.0])
                            for n in ("L_ref", "K_psi")}
    return pb._replace(params=params, axes=axes, describe=pb.describe + "; with L_ref and K_psi")


def grid(axes: dict) -> list[dict]:
    names = list(axes)
    return [dict(zip(names, map(float, vals))) for vals in itertools.product(*[axes[n] for n in names])]


def landscape(loop: str, n: int):
    """A few fixed points on ``n`` common seeds, each paired with the first (the grid's best
    for the cart-pole, tune-loops' tuned point for DRHE): how much better than a grid point
    any point found is."""
    from jaxnc.tune import mean_ci, paired_ci
    if loop == "cartpole":
        pb, base = problem(1e-4), tl.EVAL_SEED
        P = lambda d, s, kc, kp: {"loop.trigger.delta": d, "loop.trigger.sigma": s, "k_cart": kc, "k_pole": kp}
        pts = {"grid's best (search4)": P(3.1622776e-4, 1e-4, 1., 1.),
               "tune-loops' point (sigma 0)": P(3.1622776e-4, 0.0, 1., 1.),
               "tune-study tuner": P(2.9978560e-4, 2.978199e-3, 1.0374628, 1.0298046),
               "tune-study halving": P(2.521876e-4, 1.9541797e-3, 0.937293, 0.917877),
               "lr 0.1 (rule)": P(3.874731e-4, 1.466849e-4, 0.9974146, 1.0301651),
               "lr 0.1 (no rule)": P(3.5320851e-4, 1.778766e-4, 1.064453, 1.1202826)}
    else:
        pb, base = drhe_problem(), 7_000_003
        P = lambda lref: {"trigger.delta": 0.009587315, "trigger.sigma": 1e-4, **{p: v for p, v in zip(
            GAIN_PATHS["L_ref"] + GAIN_PATHS["K_psi"], (lref, lref, 1.0, 1.0))}}
        pts = {f"L_ref {v:g}": P(v) for v in (0.08, 0.02, 0.03, 0.04, 0.056)}
    f = tl._per_seed(pb)
    keys = montecarlo.seed_keys(base, n)
    vals = {k: np.asarray(montecarlo.run_batched(lambda key, p: f(p, key), keys, args=(pt,), chunk_size=1024,
                                                 progress=False), np.float64) for k, pt in pts.items()}
    ref = next(iter(vals))
    for k, v in vals.items():
        print(f"{k}: {mean_ci(v)}, exits (> 10) {np.mean(v > 10):.4f}; - {ref}: {paired_ci(v, vals[ref])}, "
              f"Cochran asks {montecarlo.seeds_for_paired_interval(v, vals[ref])}", flush=True)


def check_lref(n: int, sigma: float = 1e-4, both: bool = False):
    """``check_loop`` of DRHE's L_ref alone (tied pair; with K_psi if ``both``) at tune-loops'
    tuned delta and ``sigma`` on ``n`` seeds."""
    from jaxnc.tune import check_loop, set_paths
    pb = tl._drhe({"w_drhe": 30.0})
    loop = set_paths(pb.loop, {"trigger.delta": 0.009587315, "trigger.sigma": sigma})
    t0 = time.perf_counter()
    chk = check_loop(loop, {GAIN_PATHS[g]: Positive() for g in (("L_ref", "K_psi") if both else ("L_ref",))}, pb.objective, run=pb.run, seeds=n, max_seeds=n,
                     seed=11, fd_step=0.2, score_scale=tl._score_scale(pb))
    print(chk.table())
    for k, (m, se) in chk.estimates.items():   # raw (log) coordinate
        print(f"{k}: {np.asarray(m)} +- SE {np.asarray(se)}, per-seed sd {np.asarray(se) * n ** 0.5}")
    print(f"{time.perf_counter() - t0:.0f} s")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--loop", choices=("cartpole", "drhe"), default="cartpole")
    ap.add_argument("--seeds", type=int, default=512)
    ap.add_argument("--max-eval", type=int, default=16384)
    ap.add_argument("--sigma0", type=float, default=1e-4, help="the cart-pole's sigma at the start")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="/tmp/tl_leaves.json")
    ap.add_argument("--resolve-at", type=float, default=0.25)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--search-budget", type=int, default=1024)
    ap.add_argument("--stage", choices=("delta", "all"), default="delta",
                    help="the tuner's search stage: the delta grid alone, or the four-leaf grid")
    ap.add_argument("--no-search1", action="store_true")
    ap.add_argument("--estimator", default="score")
    ap.add_argument("--lr", default="0.3,0.03", help="tune_loop's learning_rate (start,end)")
    ap.add_argument("--gains-only", action="store_true",
                    help="the tuner's gradient on the two gains alone; its search stage picks the thresholds, "
                         "which stay there (the equal-budget search still searches all four leaves)")
    ap.add_argument("--landscape", type=int, default=0, help="only evaluate fixed points on this many seeds")
    ap.add_argument("--check-lref", type=int, default=0, help="only check DRHE's L_ref gradient on this many seeds")
    ap.add_argument("--check-sigma", type=float, default=1e-4, help="--check-lref: the trigger's sigma")
    ap.add_argument("--check-both", action="store_true", help="--check-lref: L_ref and K_psi")
    a = ap.parse_args()
    if a.check_lref:
        return check_lref(a.check_lref, a.check_sigma, a.check_both)
    if a.landscape:
        return landscape(a.loop, a.landscape)
    pb = problem(a.sigma0) if a.loop == "cartpole" else drhe_problem()
    names = param_paths(pb.params)
    first = {"cartpole": ["loop.trigger.delta"], "drhe": ["trigger.delta", "trigger.sigma"]}[a.loop]
    start = {n: float(np.asarray(tl.get_path(pb.loop, ps[0]))) for n, ps in names.items()}
    t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF).ru_utime
    stage = ({n: list(pb.axes[n]) for n in first} if a.stage == "delta" else
             {n: list(v) for n, v in pb.axes.items()})
    tuned_params = ({k: c for k, c in pb.params.items() if "trigger" not in (k if isinstance(k, str) else k[0])}
                    if a.gains_only else pb.params)
    r = tune_loop(pb.loop, tuned_params, pb.objective, run=pb.run, steps=a.steps, batch=16, search=stage,
                  search_budget=a.search_budget, seed=a.seed, evaluate=False, progress=False,
                  resolve_at=a.resolve_at, estimator=a.estimator, learning_rate=tuple(float(x) for x in a.lr.split(",")))
    t_tune = time.perf_counter() - t0
    budget = r.tuning_simulations
    tuned = start | {n: float(np.asarray(v)) for n, v in r.params.items()}
    print(f"tuner: {t_tune:.0f} s, {budget} simulations, steps {len(r.tune.history.objective) if r.tune else 0}, "
          f"resolution {r.resolution}, pick {r.pick}\n  {r.estimator_reason}\n  tuned {tuned}", flush=True)
    per_seed = tl._per_seed(pb)
    end = ({n: float(np.asarray(v[-1])) for n, v in r.tune.history.params.items()} if r.tune is not None else None)
    print(f"  the steps' end {end}", flush=True)
    out = {"args": vars(a), "start": start, "steps_end": end, "tuned": tuned, "budget": budget, "tuner_s": t_tune,
           "resolution": [r.resolution[0], np.asarray(r.resolution[1]).tolist(), r.resolution[2]] if r.resolution
           else None, "reason": r.estimator_reason}
    expand = lambda pts: [{p: pt[n] for n in names for p in names[n]} for pt in pts]   # {name:} -> {path:}
    searches = {"search4": expand(grid(pb.axes)),
                "search1": expand(grid({n: pb.axes[n] if n in first else [start[n]] for n in names}))}
    if a.no_search1:
        del searches["search1"]
    for label, pts in searches.items():
        t1 = time.perf_counter()
        sh = successive_halving(per_seed, pts, montecarlo.seed_keys(a.seed + 50_000, budget), budget=budget,
                                progress=False)
        out[label] = {"best": {n: sh.best_point[names[n][0]] for n in names}, "points": len(pts),
                      "sims": int(sh.n_simulations), "s": time.perf_counter() - t1}
        print(f"{label}: {len(pts)} points, {out[label]}", flush=True)
    for label in searches:
        res = {"tune": {"start": start, "tuned": tuned}, "search": {"best": out[label]["best"]}}
        ev = tl.evaluate(pb, res, seeds=a.seeds, max_seeds=a.max_eval, progress=True)
        e = ev["eval"]
        out[label]["eval"] = e
        out[label]["verdict"] = ev["verdict"]
        print(f"vs {label}: start {e['start']}, tuned {e['tuned']}, search {e['search']}, tuned-search "
              f"{e['tuned_minus_search']} on {e['rounds']} -> {ev['verdict']}", flush=True)
    out["cpu_s"] = resource.getrusage(resource.RUSAGE_SELF).ru_utime - c0
    json.dump(out, open(a.out, "w"), indent=1, default=float)


if __name__ == "__main__":
    main()
