"""Experiment ``tune-loops``: the gradient check and one-call tuning on three loops, each
against a Monte-Carlo search of the same simulation budget (docs/tuning_loops.md).

The three loops:

* ``drhe`` -- seed 000's DRHE loop (N = 10, DP = 0.3, Lissajous; the paper's loop, no
  safety condition), thresholds delta and sigma (one value for every output), objective
  L_w = J1'/J1_nom + w J4 (``experiments/autotune.py``: a run that leaves the tube costs
  the tube radius), the loop of :func:`jaxnc.schemes.mecanum.mecanum_loop`;
* ``drhe-safe`` -- the same loop with the time-triggered safety condition (max_silence = 2)
  and a smooth cost (mean distance over the horizon / J1_nom + w x sensor rate);
* ``hdd`` -- seed 003's HDD servo (Case 4, PETC + NUMRE with noise and disturbance), thresholds delta_s = sigma_s and
  delta_c = sigma_c (tied pairs), objective the GPI of eq. (29) (an unstable run costs
  ``GPI_UNSTABLE``);
* ``cartpole`` -- the user's example (``examples/cartpole.py``), the sensor's delta, the
  objective the run's quadratic cost plus ``w`` times the sensor's rate.

For each loop: :func:`jaxnc.tune.check_loop` at two points (the start and a second one),
:func:`jaxnc.tune.tune_loop` from the start (one call: successive halving over the grid
picks the gradient's start, then its default score-function steps, with its budget rule:
steps that resolve no coordinate after a quarter of their number stop, and the rest of
their budget runs the search's finalists and the steps' end; ``estimator=auto``:
its own check picks the estimator), and successive halving over a log grid of the same
parameters with the budget ``tune_loop`` spent (search + check + gradient steps); the start, the tuned point and the search's best are
evaluated with hard triggers on the same fresh seeds, with paired 95 % intervals, the tuned
point and the search's best on more seeds while Cochran's rule says their comparison needs
more (up to ``max_eval_seeds``; :func:`evaluate`).
Each loop's checks, tuning and search are written as soon as they finish
(``<loop>.tuning.json``), then its evaluation (``<loop>.json``); each is reused by a re-run
whose settings it depends on are unchanged, so an interrupted study loses at most one stage
of one loop, and a new evaluation rule does not re-tune.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax.numpy as jnp
import numpy as np

import jaxnc.loop as jl
from jaxnc import montecarlo
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import markdown_table, save_figure
from jaxnc.tune import (Positive, check_loop, get_path, mean_ci, paired_ci, param_paths, point_objective,
                         set_paths, successive_halving, tune_loop)

LOOPS = ("drhe", "drhe-safe", "hdd", "cartpole")
GPI_UNSTABLE = 10.0          # the GPI charged to an unstable HDD run (a stable one is below 1.5)
EVAL_SEED = 5_000_011        # fresh: the check, the tuner and the search use seeds below 10^5
TUNING_VERSION = 11          # of the checks, the tuning and the search: a stored <loop>.tuning.json is reused only at it
VERSION = 12                 # of the whole study (the evaluation's seed rule): a stored <loop>.json likewise
MAX_EVAL_SEEDS = 65_536      # the evaluation's default cap (option max_eval_seeds)


class Problem(NamedTuple):
    name: str
    loop: object                 # the configuration at the start point
    params: dict                 # {path or tuple of tied paths: constraint}
    objective: Callable
    run: Callable
    second: dict                 # the second point of the gradient check, {name: value}
    axes: dict                   # search grid: {name: values}
    describe: str
    fd_step: float = 0.05        # the check's finite-difference step (log units); score scale fd_step / sqrt(3)
    check_seeds: int = 512       # seeds of the study's two gradient checks (study_check_seeds=0)
    eval_seeds: int = 0          # the evaluation's seeds at least (0: the study's seeds); docs/tuning_loops.md


def _j1_nom() -> float:
    """J1 of the nominal single-rate run (N = 1, DP = 0), the normaliser of seed 000."""
    from jaxnc.schemes import mecanum as mec
    nominal = mec.mecanum_loop("SR", 1, 0.0)
    keys = montecarlo.seed_keys(90_001, 64)
    return float(np.mean(montecarlo.run_batched(lambda k: mec.run(nominal, k).J1, keys, chunk_size=64,
                                                progress=False)))


def _drhe_loop(max_silence: int):
    from jaxnc.schemes import mecanum as mec
    loop = mec.mecanum_loop("DRHE", 10, 0.3, max_silence=max_silence)
    return dataclasses.replace(loop, trigger=dataclasses.replace(loop.trigger, sigma=np.float32(1e-3),
                                                                 delta=np.float32(0.1)))


DRHE_AXES = {"trigger.delta": np.geomspace(0.003, 1.0, 6), "trigger.sigma": np.geomspace(1e-4, 0.1, 4)}
DRHE_PARAMS = {"trigger.delta": Positive(), "trigger.sigma": Positive()}


def _drhe(settings) -> Problem:
    """The paper's DRHE loop and the paper's costs: failures charged the tube radius."""
    from jaxnc.experiments.autotune import mecanum_terms
    j1_nom, w = _j1_nom(), float(settings["w_drhe"])
    def objective(t):
        # (smooth, jump): a stable run's J1'/J1_nom + w J4, and the tube radius a failed run is charged
        failed = t[2] | ~jnp.isfinite(t[3])
        return jnp.where(failed, 0.0, t[0]) + w * t[1], jnp.where(failed, t[0], 0.0)
    return Problem(
        "drhe", _drhe_loop(0), DRHE_PARAMS, objective, lambda lp, k: mecanum_terms(lp, k, j1_nom),
        {"trigger.delta": 0.02, "trigger.sigma": 3e-3}, DRHE_AXES,
        f"seed 000 DRHE (the paper's loop), N = 10, DP = 0.3, Lissajous; L_w = J1'/J1_nom + {w:g} J4, a run that "
        f"leaves the tube charged J1' = 0.5 m (J1_nom = {100 * j1_nom:.3f} cm)", fd_step=0.2, check_seeds=4096,
        eval_seeds=8192)


def _drhe_safe(settings) -> Problem:
    """DRHE with the time-triggered safety condition (the sensor also sends after 2 silent
    slow periods, so it cannot stall) and a smooth cost: the mean distance to the path over
    the whole horizon (a run that leaves the tube pays its growing distance, not a
    constant) plus w times the sensor's rate."""
    from jaxnc.schemes import mecanum as mec
    j1_nom, w = _j1_nom(), float(settings["w_drhe"])

    def run(lp, k):
        tr = jl.simulate(lp, k)
        return jnp.mean(tr.parts["monitor"]) / j1_nom, jnp.sum(tr.sent_sc) / lp.steps
    return Problem(
        "drhe-safe", _drhe_loop(2), DRHE_PARAMS, lambda t: t[0] + w * t[1], run,
        {"trigger.delta": 0.02, "trigger.sigma": 3e-3}, DRHE_AXES,
        f"seed 000 DRHE with the safety condition (max_silence = 2), N = 10, DP = 0.3, Lissajous; mean distance "
        f"over the horizon / J1_nom + {w:g} x sensor rate", fd_step=0.2, eval_seeds=8192)


def _hdd(settings) -> Problem:
    from jaxnc.schemes import hdd
    y_tts, ise_tts = hdd.tts_reference()
    cs = hdd.controller_design().cs
    loop = hdd.hdd_loop(4, thresholds=(1e-4, 1e-3))

    def objective(m):
        return jnp.where(m.unstable | ~jnp.isfinite(m.GPI), GPI_UNSTABLE, m.GPI)
    s, c = "trigger.delta=trigger.sigma", "controller_trigger.delta=controller_trigger.sigma"
    return Problem(
        "hdd", loop, {("trigger.delta", "trigger.sigma"): Positive(),
                      ("controller_trigger.delta", "controller_trigger.sigma"): Positive()}, objective,
        lambda lp, k: hdd.run(lp, k, y_tts=y_tts, ise_tts=ise_tts, cs=cs),
        {s: 1e-5, c: 1.32e-2}, {s: np.geomspace(1e-8, 1e-3, 6), c: np.geomspace(1e-5, 1.0, 6)},
        "seed 003 HDD, Case 4 (PETC + NUMRE, noise and disturbance); GPI of eq. (29), W = (0.45, 0.45, 0.1)")


def _cartpole_module():
    """examples/cartpole.py of the source tree (the user's example is not part of the package)."""
    import importlib.util
    import sys
    if "examples.cartpole" in sys.modules:
        return sys.modules["examples.cartpole"]
    path = Path(__file__).resolve().parents[1] / "examples" / "cartpole.py"
    if not path.exists():
        raise ConfigError(f"loops=cartpole needs the user example examples/cartpole.py of the source tree "
                          f"(looked for {path})")
    spec = importlib.util.spec_from_file_location("jaxnc_example_cartpole", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _cartpole(settings) -> Problem:
    from jaxnc import loop as nc
    cartpole = _cartpole_module().cartpole
    w = float(settings["w_cartpole"])
    return Problem(
        "cartpole", cartpole(delta=1e-3), {"trigger.delta": Positive()}, lambda m: m.cost_raw + w * m.rate_sc,
        nc.run, {"trigger.delta": 1e-2}, {"trigger.delta": np.geomspace(1e-5, 1e-1, 9)},
        f"user example: cart-pole over a lossy delayed link with PETC; cost + {w:g} x sensor rate", fd_step=0.2,
        check_seeds=8192)


BUILDERS = {"drhe": _drhe, "drhe-safe": _drhe_safe, "hdd": _hdd, "cartpole": _cartpole}


def _score_scale(problem: Problem) -> float:
    """The score function's perturbation scale that smooths like the central difference:
    (f(x + h) - f(x - h)) / 2h is the derivative of f averaged over a uniform kernel on
    [-h, h] (variance h^2 / 3), so a Gaussian of the same variance, s = h / sqrt(3),
    makes both estimate the gradient of the same smoothed objective to second order."""
    return problem.fd_step / math.sqrt(3.0)


def _check_row(chk) -> dict:
    return {"point": chk.theta.tolist(), "value": chk.value, "recommended": chk.recommended,
            "estimates": {k: {"mean": m.tolist(), "se": s.tolist()} for k, (m, s) in chk.estimates.items()},
            "paired_z": {k: np.asarray(v).tolist() for k, v in chk.paired_z.items()},
            "diff_se": {k: np.asarray(v).tolist() for k, v in chk.diff_se.items()},
            "consistent": chk.consistent, "reason": chk.reason, "table": chk.table()}


def study(problem: Problem, *, check_seeds: int, steps: int, batch: int, seed: int,
          search_budget: int = 0, study_check_seeds: int = 0, estimator: str = "score",
          progress: bool = True) -> dict:
    """The check at two points (``study_check_seeds`` seeds, 0: the problem's own), tune_loop
    (its own check on ``check_seeds``; without its own evaluation, which does not move its
    point or its budget) and the equal-budget search of one loop; the study's evaluation of the
    three points is :func:`evaluate`."""
    t0 = time.perf_counter()
    n_check = study_check_seeds or problem.check_seeds
    names = param_paths(problem.params)
    start = {n: float(np.asarray(get_path(problem.loop, p[0]))) for n, p in names.items()}
    checks = []
    for i, at in enumerate((None, problem.second)):
        chk = check_loop(problem.loop, problem.params, problem.objective, run=problem.run, at=at, seeds=n_check,
                         seed=seed + 11 + i, fd_step=problem.fd_step, score_scale=_score_scale(problem),
                         progress=progress)
        checks.append(dict(_check_row(chk), at=at or start, seeds=n_check))
        if progress:
            print(f"[{problem.name}] gradient check at {at or start}:\n{chk.table()}\n")
    two_stage = search_budget > 0
    r = tune_loop(problem.loop, problem.params, problem.objective, run=problem.run, steps=steps, batch=batch,
                  search={n: list(v) for n, v in problem.axes.items()} if two_stage else None,
                  search_budget=search_budget if two_stage else None,
                  estimator=estimator, seed=seed, check_seeds=check_seeds, evaluate=False,
                  progress=progress)
    budget = r.tuning_simulations
    axes = {n: [float(v) for v in vals] for n, vals in problem.axes.items()}
    grid_names = list(axes)
    mesh = np.meshgrid(*[np.arange(len(axes[n])) for n in grid_names], indexing="ij")
    points = [{p: axes[n][int(idx[j])] for j, n in enumerate(grid_names) for p in names[n]}
              for idx in zip(*[m.reshape(-1) for m in mesh])]
    per_seed = _per_seed(problem)
    sh = successive_halving(per_seed, points, montecarlo.seed_keys(seed + 50_000, budget), budget=budget,
                            progress=progress, desc=f"{problem.name} search")
    best = {n: sh.best_point[names[n][0]] for n in grid_names}
    out = {
        "loop": problem.name, "describe": problem.describe, "checks": checks,
        "tune": {"start": start, "tuned": {n: float(np.asarray(v)) for n, v in r.params.items()},
                 "two_stage": two_stage, "search_budget": search_budget,
                 # the steps' first point (after the rule, r.search's winner may be another candidate or the end)
                 "gradient_start": ({n: float(np.asarray(r.tune.history.params[n][0])) for n in names}
                                    if r.tune is not None else
                                    {n: float(r.search.best_point[names[n][0]]) for n in names} if two_stage else start),
                 "gradient_steps": len(r.tune.history.objective) if r.tune is not None else 0,
                 "steps": steps,
                 "resolution": ({"steps": r.resolution[0], "t": np.asarray(r.resolution[1]).tolist(),
                                 "z": r.resolution[2]} if r.resolution else None),
                 "pick": list(r.pick),
                 "check_at_gradient_start": _check_row(r.check) if r.check is not None else None,
                 "estimator": r.estimator, "estimator_reason": r.estimator_reason,
                 "objective_history": r.tune.history.objective.tolist() if r.tune else [],
                 "simulations": budget},
        "search": {"axes": axes, "best": best, "simulations": int(sh.n_simulations),
                   "candidates": [{n: pt[names[n][0]] for n in grid_names} for pt in sh.points],
                   "candidate_mean": [float(m) if np.isfinite(m) else "inf" for m in sh.mean],
                   "candidate_seeds": np.sum(~np.isnan(sh.values), axis=1).tolist()},
        "wall_time_s": time.perf_counter() - t0,
    }
    return out


def _per_seed(problem: Problem) -> Callable:
    """``f(point, key)``: the objective of one run at ``point`` ({path: value}), hard triggers."""
    return point_objective(problem.loop, problem.objective, problem.run)


def _point(names: dict, values: dict) -> dict:
    """{path: value} for set_paths from {name: value} (a tied name sets each of its paths)."""
    return {p: float(values[n]) for n, paths in names.items() for p in paths}


def evaluate(problem: Problem, res: dict, *, seeds: int, max_seeds: int, progress: bool = True) -> dict:
    """The start, the tuned point and the search's best of ``res`` (a :func:`study` result)
    on common fresh seeds (base ``EVAL_SEED``), hard triggers: each on ``seeds`` seeds (or
    the problem's ``eval_seeds`` if more); then, while Cochran's rule for the tuned-vs-search
    comparison (:func:`jaxnc.montecarlo.seeds_for_paired_interval`) asks for more seeds than
    it has, the tuned point and the search's best on more (at least twice as many, at least
    what the rule asks), up to ``max_seeds``. Identical points need no more (their
    difference is zero on every seed). Returns ``{"eval": ..., "verdict": ...}``: the
    intervals, the paired differences (tuned - start on the first ``start_seeds`` seeds),
    the seed counts of each round and what the rule asks on the final sample."""
    n = max(seeds, problem.eval_seeds)
    names = param_paths(problem.params)
    pts = {k: _point(names, v) for k, v in (("start", res["tune"]["start"]), ("tuned", res["tune"]["tuned"]),
                                            ("search", res["search"]["best"]))}

    per_seed = _per_seed(problem)

    def more(point, have: np.ndarray, upto: int) -> np.ndarray:
        keys = montecarlo.seed_keys(EVAL_SEED, upto - have.size, start=have.size)
        v = montecarlo.run_batched(lambda k, pt: per_seed(pt, k), keys, args=(point,), chunk_size=min(upto - have.size, 1024),
                                   progress=False)
        return np.concatenate([have, np.asarray(v, np.float64)])

    vals = {k: more(pt, np.zeros(0), n) for k, pt in pts.items()}
    rounds = [n]
    same = pts["tuned"] == pts["search"]
    need = montecarlo.seeds_for_paired_interval(vals["tuned"], vals["search"])
    while not same and need > n and n < max_seeds:
        n = min(max_seeds, max(2 * n, -(-need // 1024) * 1024))
        if progress:
            print(f"[{problem.name}] evaluation: Cochran's rule asks {need} seeds; tuned and search on {n}", flush=True)
        vals["tuned"], vals["search"] = more(pts["tuned"], vals["tuned"], n), more(pts["search"], vals["search"], n)
        rounds.append(n)
        need = montecarlo.seeds_for_paired_interval(vals["tuned"], vals["search"])
    v_start, v_tuned, v_search = vals["start"], vals["tuned"], vals["search"]
    ev = {"seeds": n, "start_seeds": rounds[0], "rounds": rounds, "max_seeds": max_seeds,
          "start": mean_ci(v_start), "tuned": mean_ci(v_tuned), "search": mean_ci(v_search),
          "tuned_minus_start": paired_ci(v_tuned[:rounds[0]], v_start),
          "tuned_minus_search": paired_ci(v_tuned, v_search),
          "same_point": same,
          # Cochran's rule (montecarlo.seeds_for_normal_interval) on the final sample
          "normal_interval_seeds": {
              "tuned": montecarlo.seeds_for_normal_interval(v_tuned),
              "search": montecarlo.seeds_for_normal_interval(v_search),
              "tuned_minus_search": montecarlo.seeds_for_normal_interval(v_tuned - v_search)}}
    return {"eval": ev, "verdict": verdict(*ev["tuned_minus_search"], 0 if same else need, n)}


def verdict(d: float, ci: float, need: int, seeds: int) -> str:
    """Tuned against search from the paired difference ``d`` +- ``ci`` (95 %) on ``seeds``
    common seeds; doubtful when Cochran's rule asks ``need`` > ``seeds`` seeds
    (:func:`jaxnc.montecarlo.seeds_for_normal_interval` of either point's costs or of
    their differences)."""
    v = ("better than the search" if d + ci < 0 else
         "within the search's interval" if d - ci <= 0 else "worse than the search")
    return v + (f" (doubtful: skewed costs, the normal interval needs about {need} seeds)" if need > seeds else "")


def _fmt_pt(pt: dict) -> str:
    return ", ".join(f"{k} = {v:.3g}" for k, v in pt.items())


def _ci(x) -> str:
    return f"{x[0]:.4g} ± {x[1]:.2g}"


def _seeds(e: dict) -> str:
    """The evaluation's seeds: each round's count (Cochran's rule), and the start's if fewer."""
    rounds = e.get("rounds", [e["seeds"]])
    s = " → ".join(str(n) for n in rounds)
    return s + (f" (start {e['start_seeds']})" if e.get("start_seeds", rounds[-1]) != rounds[-1] else "")


def _steps(tn: dict) -> str:
    """The gradient steps made, of ``steps``, and the budget rule's test (tune_loop's resolve_at)."""
    if "gradient_steps" not in tn:
        return ""
    made = f"{tn['gradient_steps']} of {tn['steps']}"
    rs = tn.get("resolution")
    if not rs:
        return made
    t = max(rs["t"])
    return f"{made} (after {rs['steps']}: {t:.2f} {'≥' if t >= rs['z'] else '<'} {rs['z']:.2f})"


def tables(results: list[dict]) -> str:
    """The study's two tables (markdown): the checks, and tuned vs search."""
    rows = []
    for res in results:
        for c in res["checks"]:
            for est in [e for e in c["estimates"] if e != "finite_difference"]:
                m, s = c["estimates"][est]["mean"], c["estimates"][est]["se"]
                fm, fs = c["estimates"]["finite_difference"]["mean"], c["estimates"]["finite_difference"]["se"]
                z = max(abs(v) for v in c["paired_z"][est])
                res_ = ", ".join(f"{1.96 * v:.2g}" for v in c["diff_se"][est])
                rows.append([res["loop"], _fmt_pt(c["at"]), str(c.get("seeds", "")), est,
                             ", ".join(f"{a:.3g} ± {1.96 * b:.2g}" for a, b in zip(m, s)),
                             ", ".join(f"{a:.3g} ± {1.96 * b:.2g}" for a, b in zip(fm, fs)), f"{z:.2f}", res_,
                             "yes" if c["consistent"][est] else f"no: {c['reason'][est]}",
                             "**yes**" if c["recommended"] == est else ""])
    t1 = markdown_table(["loop", "point", "seeds", "estimator", "gradient (95 %)", "finite differences (95 %)", "max |z|",
                         "resolution", "consistent", "recommended"], rows)
    rows = []
    for res in results:
        e, tn, sr = res["eval"], res["tune"], res["search"]
        rows.append([res["loop"], _fmt_pt(tn["start"]), _fmt_pt(tn.get("gradient_start", tn["start"])),
                     _fmt_pt(tn["tuned"]), tn["estimator"], _fmt_pt(sr["best"]),
                     _steps(tn), str(tn["simulations"]), str(sr["simulations"]), _seeds(e), _ci(e["start"]),
                     _ci(e["tuned"]),
                     _ci(e["search"]), _ci(e["tuned_minus_search"]), res["verdict"]])
    t2 = markdown_table(["loop", "start", "gradient from", "tuned", "estimator", "search's best",
                         "steps (budget rule: max |t| vs z)", "tuner sims",
                         "search sims", "eval seeds",
                         "start", "tuned", "search", "tuned − search (paired)", "verdict"], rows)
    return ("Gradient check (coordinates: log of each parameter; 95 % intervals over the check's seeds; "
            "resolution: 1.96 x the standard error of the paired difference to the finite differences, the "
            "smallest disagreement the check can see):\n\n" + t1
            + "\n\nTuned (one tune_loop call) vs successive halving of the same budget, hard triggers, the same "
              "fresh seeds:\n\n" + t2 + "\n")


def plot(results: list[dict], out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4.2), squeeze=False)
    for ax, res in zip(axes[0], results):
        sr, tn = res["search"], res["tune"]
        names = list(sr["axes"])
        mean = np.asarray([np.inf if m == "inf" else m for m in sr["candidate_mean"]], float)
        if len(names) == 1:
            x = [c[names[0]] for c in sr["candidates"]]
            ax.semilogx(x, np.where(np.isfinite(mean), mean, np.nan), "o-", label="search candidates (their seeds)")
            for lab, pt, st in (("start", tn["start"], "ks"), ("tuned", tn["tuned"], "r*"), ("search's best", sr["best"], "bD")):
                ax.axvline(pt[names[0]], color=st[0], ls=":", lw=1)
                ax.plot([pt[names[0]]], [np.nanmin(mean)], st, ms=10, label=lab)
            ax.set_xlabel(names[0])
            ax.set_ylabel("objective")
        else:
            x = np.asarray([c[names[0]] for c in sr["candidates"]])
            y = np.asarray([c[names[1]] for c in sr["candidates"]])
            fin = np.isfinite(mean)
            sc = ax.scatter(x[fin], y[fin], c=np.log10(mean[fin]), s=20 + 4 * np.asarray(sr["candidate_seeds"])[fin] ** 0.5,
                            cmap="viridis")
            fig.colorbar(sc, ax=ax, label="log10 objective (search's seeds)")
            ax.set_xscale("log")
            ax.set_yscale("log")
            for lab, pt, st in (("start", tn["start"], "ks"), ("tuned", tn["tuned"], "r*"), ("search's best", sr["best"], "bD")):
                ax.plot([pt[names[0]]], [pt[names[1]]], st, ms=11, mfc="none" if st[0] != "r" else "r", label=lab)
            ax.set_xlabel(names[0])
            ax.set_ylabel(names[1])
        ax.set_title(f"{res['loop']}: {res['verdict']}", fontsize=9)
        ax.legend(fontsize=7)
    p = save_figure(fig, out / "tune_loops.png", dpi=110)
    return p


def _config(settings: dict, seeds: int) -> dict:
    return {k: v for k, v in settings.items() if k != "loops"} | {"seeds": seeds, "version": VERSION}


def _tuning_config(settings: dict, seeds: int) -> dict:
    """The configuration the checks, the tuning and the search depend on (not the evaluation's cap)."""
    return {k: v for k, v in settings.items() if k not in ("loops", "max_eval_seeds")} | {
        "seeds": seeds, "version": TUNING_VERSION}


def _part(name: str, settings: dict, seeds: int, out: Path, progress: bool) -> dict:
    """One loop: its checks, tuning and search (stored in ``out/<loop>.tuning.json``, reused
    while their configuration is unchanged), then :func:`evaluate`."""
    problem = BUILDERS[name](settings)
    res = montecarlo.stored_or_run(
        out / f"{name}.tuning.json", experiment="tune-loops", config=_tuning_config(settings, seeds), progress=progress,
        compute=lambda: study(
            problem, check_seeds=settings["check_seeds"], steps=settings["steps"], batch=settings["batch"],
            seed=settings["seed"], search_budget=settings["search_budget"],
            study_check_seeds=settings["study_check_seeds"], estimator=settings["estimator"], progress=progress))
    t0 = time.perf_counter()
    ev = evaluate(problem, res, seeds=seeds, max_seeds=max(settings["max_eval_seeds"], seeds), progress=progress)
    return dict(res, **ev, wall_time_s=res["wall_time_s"] + time.perf_counter() - t0,
                tuning_wall_time_s=res["wall_time_s"])


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    return montecarlo.stored_study(
        out, experiment="tune-loops", config=_config(settings, seeds), progress=progress,
        parts=LOOPS if settings["loops"] == "all" else (settings["loops"],),
        compute=lambda name: _part(name, settings, seeds, Path(out), progress),
        tables=tables, plot=plot)


register(Experiment(
    name="tune-loops",
    description="gradient check + one-call tuning on the DRHE, HDD and cart-pole loops vs equal-budget search",
    options=(
        Option("loops", "choice", "all", "which loop(s)", choices=(*LOOPS, "all")),
        Option("steps", "int", 200, "gradient steps of tune_loop (its default)", low=1, high=10_000),
        Option("batch", "int", 16, "seeds per gradient step (tune_loop's default)", low=2, high=4096),
        Option("estimator", "choice", "score", "tune_loop's estimator (its default: score; auto runs its own check "
               "on check_seeds)", choices=("score", "auto")),
        Option("check_seeds", "int", 512, "seeds of tune_loop's own gradient check (estimator auto)", low=2,
               high=100_000),
        Option("study_check_seeds", "int", 0, "seeds of the study's two gradient checks per loop; 0: the loop's "
               "own (drhe 4096, cartpole 8192, hdd and drhe-safe 512)", low=0, high=100_000),
        Option("search_budget", "int", 1024, "simulations of tune_loop's first stage (successive halving over "
               "the grid, which picks the gradient's start); 0: the gradient alone from the start point",
               low=0, high=10_000_000),
        Option("w_drhe", "float", 30.0, "DRHE: weight of J4 in L_w", low=0.0, high=1e4),
        Option("w_cartpole", "float", 2.0, "cart-pole: weight of the sensor rate", low=0.0, high=1e4),
        Option("seed", "int", 0, "base seed of checks, tuning and search (evaluation: 5000011)", low=0,
               high=1_000_000),
        Option("max_eval_seeds", "int", MAX_EVAL_SEEDS, "the evaluation's cap: the tuned point and the search's "
               "best get more seeds (doubling) while Cochran's rule asks for more, up to this many", low=2,
               high=1_048_576),
    ),
    run=run,
))
