"""Experiments ``autotune-mecanum`` and ``autotune-pi``: tuning by gradient vs by hand vs by grid.

``autotune-mecanum`` (seed 000, DRHE, N = 10, DP = 0.3, Lissajous): tune the PETC
thresholds sigma(i), delta(i) for

    L_w = J1' / J1_nom + w J4,   J1' = J1 of a stable run, the tube radius max_dev if unstable,

at several weights w.  By default a two-stage tuner (``init=coarse``): successive halving
over the grid's (sigma scale, delta) points on half the budget, then the score-function
gradient (optax) refines the winner inside its grid cell on the other half; other settings
run the gradient alone from the paper's thresholds (``init=paper``), over the 18
per-output thresholds (``family=per_output``) or with another event-gradient estimator.
A grid search over (sigma scale, delta) gets the *same number of simulations*; re-evaluate the paper's
hand-set thresholds (section 4.1), the grid's best and the tuned point with hard triggers
on fresh seeds; trace the Pareto front J1 vs J4.  J4 is the sensor transmission rate
relative to nominal SR (N = 1 sends every period, so its rate is exactly 1).

``autotune-pi`` (seed 004, scenario a or b, F = 0.1): tune the wheel PI gains (Kp, Ki =
Kp / Ti) for J1 (eq. 23) and compare with the paper's Kp = 6, Ti = 0.12 (section 5.1) and
an equal-budget grid search, all re-evaluated on fresh seeds.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxnc import loop as jl
from jaxnc import metrics, montecarlo
from jaxnc.design.dualrate import DiscreteSS
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.paths import PATHS
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import diffdrive as dd
from jaxnc.schemes import mecanum as mec
from jaxnc.tune import (Interval, Positive, evaluate, grid, halving_schedule, mean_ci, paired_ci, relax_trigger, search,
                        simulations_per_step, successive_halving, tune)

EVAL_SEED_OFFSET = 1_000_003   # evaluation seeds never overlap the tuning / grid seeds


# ----------------------------------------------------------------------------- Mecanum objective


def mecanum_terms(loop: jl.Loop, key, j1_nom):
    """Per-seed (J1'/J1_nom, J4, unstable, J1, J2) of seed 000 eq. (21), (22), (24).

    The completion step l and the instability flag carry no gradient; the mean and
    maximum distance and the transmission count do (through the trigger's estimator)."""
    traj = jl.simulate(loop, key)
    K, N = loop.steps, loop.N
    l = jax.lax.stop_gradient(traj.done_step)
    dist = traj.parts["monitor"]
    mask = jnp.arange(K) < l
    j1 = metrics.J1(dist, mask)
    slow_mask = ((jnp.arange(K // N) * N) < l).astype(traj.sent_sc.dtype)
    j4 = jnp.sum(traj.sent_sc * slow_mask) / l      # nominal SR sends every fast period: rate 1
    unstable = mec.metrics(loop, traj).unstable
    j1p = jnp.where(unstable | ~jnp.isfinite(j1), loop.monitor.max_dev, j1)
    j2 = metrics.J2(dist, mask)
    return j1p / j1_nom, j4, unstable, j1, j2


def near_miss_penalty(j2, unstable, max_dev, r0, charge):
    """Differentiable stand-in for the failure charge: ``charge`` * ((J2 - r0) / (max_dev - r0))^2
    for a stable run whose maximum distance J2 exceeds ``r0`` (0 below r0 and for unstable
    runs, which pay the failure charge itself). Runs that come close to the tube's edge
    are the precursor of runs that leave it (their share grows with the thresholds), and
    unlike a failure they have a pathwise gradient."""
    x = jnp.clip((j2 - r0) / (max_dev - r0), 0.0, 1.0)
    return jnp.where(unstable | ~jnp.isfinite(j2), 0.0, charge * x * x)


def with_thresholds(loop, sigma, delta, estimator="hard", temperature=0.0):
    trig = dataclasses.replace(loop.trigger, sigma=sigma, delta=delta, temperature=0.0)
    return dataclasses.replace(loop, trigger=relax_trigger(trig, estimator, temperature))


def mecanum_loss_fn(loop, j1_nom, w, estimator, near_miss=0.0):
    """loss(params, key, temperature) for :func:`jaxnc.tune.tune`. For ``"hybrid"`` it
    returns (smooth, jump): the stable runs' J1'/J1_nom plus w J4, and the failure charge
    (tube radius / J1_nom on an unstable run, 0 otherwise); their sum is L_w.

    ``near_miss`` = r0 > 0 adds the gradient (not the value: p - stop_gradient(p)) of
    :func:`near_miss_penalty` with the failure charge, so the reported objective stays L_w."""
    max_dev = loop.monitor.max_dev
    charge = float(max_dev) / j1_nom

    def loss(p, key, temperature):
        lt = with_thresholds(loop, p["sigma"], p["delta"], estimator, temperature)
        j1n, j4, unstable, _, j2 = mecanum_terms(lt, key, j1_nom)
        smooth = jnp.where(unstable, 0.0, j1n) + w * j4
        if near_miss > 0:
            pen = near_miss_penalty(j2, unstable, max_dev, near_miss, charge)
            smooth = smooth + pen - jax.lax.stop_gradient(pen)
        if estimator == "hybrid":
            return smooth, jnp.where(unstable, j1n, 0.0)
        return smooth + jnp.where(unstable, j1n, 0.0)
    return loss


def mecanum_eval_fn(loop, j1_nom):
    """per_seed(params, key) with hard triggers: params sigma[9], delta[9], w."""
    def per_seed(p, key):
        j1n, j4, unstable, j1, _ = mecanum_terms(with_thresholds(loop, p["sigma"], p["delta"]), key, j1_nom)
        return dict(loss=j1n + p["w"] * j4, J1n=j1n, J4=j4, unstable=unstable, J1=j1)
    return per_seed


PAPER_D = float(mec.PAPER_DELTA[0])    # the paper's delta(i) are all equal: it lies in the grid's family


def from_scales(p):
    """sigma(i), delta(i) of the two-parameter family the grid searches: sigma = s x the
    paper's sigma pattern, delta(i) = d for every output (the paper's point is s = 1, d = 0.1)."""
    return {"sigma": p["s"] * jnp.asarray(mec.PAPER_SIGMA, jnp.float32), "delta": jnp.full(9, p["d"], jnp.float32)}


def scales_loss(loss):
    """A per-output ``loss(params, key, temperature)`` as a loss of the scales (s, d)."""
    return lambda p, key, temperature: loss(from_scales(p), key, temperature)


def mecanum_grid_fn(loop, j1_nom):
    """per_seed for the grid: sigma = s * paper's sigma pattern, delta(i) = d for all i."""
    def per_seed(p, key):
        q = from_scales(p)
        j1n, j4, _, _, _ = mecanum_terms(with_thresholds(loop, q["sigma"], q["delta"]), key, j1_nom)
        return j1n + p["w"] * j4
    return per_seed


def grid_cell(axis, v) -> tuple[float, float]:
    """The interval between the neighbours of ``v`` on a sorted grid ``axis`` (beyond an end:
    0 below a zero, else the end's ratio to its neighbour): the trust region in which
    ``init=coarse`` refines the search's winner."""
    a = list(axis)
    i = a.index(v)
    lo = a[i - 1] if i > 0 else (0.0 if v == 0 else v * a[0] / a[1])
    hi = a[i + 1] if i < len(a) - 1 else v * a[-1] / a[-2]
    return float(lo), float(hi)


def cell_start(point: dict, s_axis, d_axis) -> tuple[dict, dict]:
    """Constraints and start of ``init=coarse``'s refinement of a grid point {s, d}: each
    parameter an :class:`Interval` over its grid cell (:func:`grid_cell`), started at the
    point, moved 1 % into the cell if it lies on the cell's edge (s = 0), where the logit
    would be infinite and the gradient zero."""
    cons = {"s": Interval(*grid_cell(s_axis, point["s"])), "d": Interval(*grid_cell(d_axis, point["d"]))}
    init = {k: np.float32(c.low + np.clip((point[k] - c.low) / (c.high - c.low), 0.01, 0.99) * (c.high - c.low))
            for k, c in cons.items()}
    return cons, init


def _summ(ev: dict) -> dict:
    out = {k: dict(zip(("mean", "ci95"), mean_ci(ev[k]))) for k in ("loss", "J1n", "J4")}
    stable = ~np.asarray(ev["unstable"], bool)
    j1 = np.asarray(ev["J1"])[stable]
    out["J1_cm_stable"] = dict(zip(("mean", "ci95"), mean_ci(100 * j1))) if j1.size else {"mean": math.inf, "ci95": math.nan}
    out["unstable_fraction"] = float(1 - stable.mean())
    return out


def check_mecanum(settings: dict) -> None:
    """Combinations of autotune-mecanum options (checked when the settings are parsed)."""
    if settings["init"] == "coarse" and settings["family"] != "scales":
        raise ConfigError("init=coarse refines inside a cell of the grid's two-parameter family: it needs "
                          "family=scales")


def run_mecanum(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t_start = time.perf_counter()
    try:
        loop = mec.mecanum_loop("DRHE", settings["N"], settings["dp"], path=settings["path"],
                                max_silence=settings["max_silence"], jacobian_grad=settings["jacobian_grad"])
        nominal = mec.mecanum_loop("SR", 1, 0.0, path=settings["path"])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if settings["near_miss"] >= float(loop.monitor.max_dev):
        raise ConfigError(f"near_miss must lie in [0, max_dev = {float(loop.monitor.max_dev):g} m); got {settings['near_miss']}")
    weights = settings["weights"]
    steps, batch = settings["steps"], settings["batch"]
    budget = steps * simulations_per_step(settings["estimator"], batch)   # the grid gets the same
    s_axis = (0.0, 0.25, 0.5, 1.0)
    d_axis = (0.03, 0.1, 0.3, 1.0)
    grid_seeds = max(2, budget // (len(s_axis) * len(d_axis)))
    eval_keys = montecarlo.seed_keys(settings["seed"] + EVAL_SEED_OFFSET, seeds)
    chunk = min(seeds, 128)
    nom = montecarlo.run_batched(lambda k: mec.run(nominal, k), eval_keys, chunk_size=chunk, progress=progress,
                                 desc="nominal SR")
    j1_nom = float(np.mean(nom.J1[~nom.unstable]))
    paper = {"sigma": np.asarray(mec.PAPER_SIGMA, np.float32), "delta": np.asarray(mec.PAPER_DELTA, np.float32)}
    eval_fn = mecanum_eval_fn(loop, j1_nom)
    grid_fn = mecanum_grid_fn(loop, j1_nom)
    grid_keys = montecarlo.seed_keys(settings["seed"] + 1, grid_seeds)
    # init=coarse splits the grid's budget: half for a successive-halving search over the
    # grid's points (its own seeds, not the comparison grid's), half the steps to refine
    n_cand = len(s_axis) * len(d_axis)
    tune_steps = max(1, steps // 2) if settings["init"] == "coarse" else steps
    coarse_budget = max(budget // 2, n_cand * math.ceil(math.log2(n_cand)))
    coarse_keys = montecarlo.seed_keys(settings["seed"] + 2, sum(s for _, s in halving_schedule(n_cand, coarse_budget)))
    rows, results, histories, front = [], {}, {}, []
    for w in weights:
        loss = mecanum_loss_fn(loop, j1_nom, w, settings["estimator"], settings["near_miss"])
        opt = optax.adam(settings["lr"])
        gs = search(grid_fn, grid(s=s_axis, d=d_axis, w=(w,)), grid_keys, progress=progress, desc=f"grid w={w:g}")
        gbest = {k: np.asarray(v) for k, v in from_scales(gs.best_point).items()}
        # "grid": refine the grid's best point by gradient (the grid sees instability, the
        # gradient does not); the tuned point then used both budgets.  "coarse": a two-stage
        # tuner inside the grid's budget: successive halving over the grid's points on half
        # the budget picks the start, half the gradient steps refine it.
        coarse = None
        if settings["init"] == "coarse":
            coarse = successive_halving(grid_fn, grid(s=s_axis, d=d_axis, w=(w,)), coarse_keys,
                                        budget=coarse_budget, progress=progress, desc=f"halving w={w:g}")
        start_pt = {"grid": gs, "coarse": coarse}.get(settings["init"])
        if settings["family"] == "scales":     # the grid's family: sigma = s x paper's pattern, delta(i) = d
            fn, to_thresholds = scales_loss(loss), from_scales
            if coarse:     # refine inside the grid cell around the search's winner (a trust region)
                constraints, init = cell_start(coarse.best_point, s_axis, d_axis)
            else:
                s0, d0 = (start_pt.best_point["s"], start_pt.best_point["d"]) if start_pt else (1.0, PAPER_D)
                init = {"s": np.float32(max(s0, 1e-3)), "d": np.float32(d0)}
                constraints = {k: Positive() for k in init}
        else:
            start = {k: np.asarray(v) for k, v in from_scales(start_pt.best_point).items()} if start_pt else paper
            fn, init = loss, {"sigma": np.maximum(start["sigma"], 1e-3), "delta": start["delta"]}
            constraints = {k: Positive() for k in init}
            to_thresholds = dict
        tr = tune(fn, init, constraints, steps=tune_steps, batch=batch, optimizer=opt,
                  estimator=settings["estimator"], temperature=(settings["t0"], settings["t1"]),
                  seed=settings["seed"], score_scale=settings["score_scale"], progress=progress, desc=f"tune w={w:g}")
        tuned = {k: np.asarray(v) for k, v in to_thresholds(tr.params).items()}
        # init=coarse also reports the search's winner alone: what the gradient refinement added
        named = (("paper", paper), ("grid", gbest),
                 *((("search", {k: np.asarray(v) for k, v in from_scales(coarse.best_point).items()}),)
                   if coarse else ()), ("tuned", tuned))
        evs = {name: evaluate(eval_fn, {**p, "w": w}, eval_keys, chunk_size=chunk) for name, p in named}
        summ = {n: _summ(e) for n, e in evs.items()}
        diff = {f"tuned-{n}": dict(zip(("mean", "ci95"), paired_ci(evs["tuned"]["loss"], evs[n]["loss"])))
                for n in evs if n != "tuned"}
        sims = {"paper": 0, "grid": gs.n_simulations,
                **({"search": coarse.n_simulations} if coarse else {}),
                "tuned": tr.n_simulations + (start_pt.n_simulations if start_pt else 0)}
        results[f"w={w:g}"] = {
            "summary": summ, "paired_differences": diff, "simulations": sims,
            "tuned": {k: v.tolist() for k, v in tuned.items()},
            **({"tuned_scales": {k: float(v) for k, v in tr.params.items()}} if settings["family"] == "scales" else {}),
            "grid_best": {"sigma_scale": gs.best_point["s"], "delta": gs.best_point["d"],
                          "grid_mean": gs.best_mean, "grid_ci95": gs.best_ci95},
            **({"coarse_best": {"sigma_scale": coarse.best_point["s"], "delta": coarse.best_point["d"],
                                "simulations": coarse.n_simulations}} if coarse else {}),
            "tune_wall_s": tr.wall_time_s, "grid_wall_s": gs.wall_time_s,
            "history": {"objective": tr.history.objective.tolist(), "temperature": tr.history.temperature.tolist()},
        }
        histories[w] = tr.history
        front.append((w, summ))
        for n in evs:
            s = summ[n]
            rows.append([f"{w:g}", n, f"{fmt(s['loss']['mean'], 3)} \u00b1 {fmt(s['loss']['ci95'], 3)}",
                         f"{fmt(s['J1n']['mean'], 3)} \u00b1 {fmt(s['J1n']['ci95'], 3)}",
                         f"{fmt(s['J4']['mean'], 4)} \u00b1 {fmt(s['J4']['ci95'], 4)}",
                         f"{100 * s['unstable_fraction']:.1f}", str(sims[n]),
                         "" if n == "tuned" else f"{fmt(diff[f'tuned-{n}']['mean'], 3)} \u00b1 {fmt(diff[f'tuned-{n}']['ci95'], 3)}"])
    tab = markdown_table(["w", "thresholds", "L_w = J1'/J1nom + w J4", "J1'/J1nom", "J4", "unstable %",
                          "simulations", "tuned - this (paired)"], rows)
    print(f"\nautotune-mecanum: DRHE N={settings['N']} DP={settings['dp']} {settings['path']}, "
          f"estimator={settings['estimator']}, {seeds} fresh evaluation seeds (hard triggers), J1_nom={100 * j1_nom:.2f} cm\n")
    print(tab)
    out.mkdir(parents=True, exist_ok=True)
    figs = _plot_mecanum(loop, paper, results, histories, front, eval_keys[0], out)
    wall = time.perf_counter() - t_start
    config = {"settings": settings, "seeds": seeds, "grid": {"sigma_scale": s_axis, "delta": d_axis,
                                                             "seeds": grid_seeds},
              "h": int(loop.actuator.horizon) // loop.N, "steps": loop.steps, "J1_nom_m": j1_nom,
              "objective": "J1'/J1_nom + w J4; J1' = tube radius for unstable runs"}
    montecarlo.save_results(out / "results.json", experiment="autotune-mecanum", config=config,
                            results={"table": tab, **results}, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'} and {', '.join(str(f) for f in figs)}  ({wall:.1f} s)")
    return results


def _plot_mecanum(loop, paper, results, histories, front, key0, out: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for w, h in histories.items():
        ax.plot(h.objective, label=f"w = {w:g}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean objective over the step's seeds")
    ax.legend()
    f1 = save_figure(fig, out / "objective.png", dpi=120)

    fig, ax = plt.subplots(figsize=(6, 4.5))
    style = {"paper": ("k", "s"), "grid": ("tab:blue", "^"), "tuned": ("tab:red", "o")}
    for n, (c, m) in style.items():
        pts = [(s[n]["J4"]["mean"], s[n]["J1n"]["mean"], s[n]["J4"]["ci95"], s[n]["J1n"]["ci95"], w) for w, s in front]
        pts = pts[:1] if n == "paper" else pts
        x, y, xe, ye, ws = map(np.asarray, zip(*pts))
        ax.errorbar(x, y, xerr=xe, yerr=ye, color=c, marker=m, ls="-" if n == "tuned" else "none",
                    label={"paper": "paper's hand-set", "grid": "grid best", "tuned": "gradient-tuned"}[n])
        if n == "tuned":
            for xi, yi, wi in zip(x, y, ws):
                ax.annotate(f"w={wi:g}", (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("J4 (sensor transmission rate / nominal SR)")
    ax.set_ylabel("J1' / J1 nominal")
    ax.set_title("Pareto front, hard triggers, fresh seeds")
    ax.legend()
    f2 = save_figure(fig, out / "pareto.png", dpi=120)

    fig, ax = plt.subplots(figsize=(7, 5))
    ref = np.asarray(loop.monitor.path.points)
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.5, label="reference")
    sim = jax.jit(jl.simulate)
    wmid = list(results)[len(results) // 2]
    tuned = {k: np.asarray(v, np.float32) for k, v in results[wmid]["tuned"].items()}
    for name, p in (("paper's hand-set", paper), (f"tuned ({wmid})", tuned)):
        traj = sim(with_thresholds(dataclasses.replace(loop, record=mec.FULL_RECORD), p["sigma"], p["delta"]), key0)
        xy = np.asarray(traj.x[:, 3:5])[: int(traj.done_step)]
        sent = np.flatnonzero(np.asarray(traj.sent_sc) > 0.5) * loop.N
        sent = sent[sent < len(xy)]
        line, = ax.plot(xy[:, 0], xy[:, 1], lw=1.2, label=f"{name}: {len(sent)} transmissions")
        ax.plot(xy[sent, 0], xy[sent, 1], ".", color=line.get_color(), ms=4)
    ax.set_aspect("equal")
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.legend(fontsize=8)
    f3 = save_figure(fig, out / "paths.png", dpi=120)
    return f1, f2, f3


# ----------------------------------------------------------------------------- PI gains (seed 004)


def pi_ss(Kp, Ki, Ts) -> DiscreteSS:
    """Eq. (30)-(31) as a state space, differentiable in the gains:
    G_r(z) = Kp (z - 1 + Ts/Ti)/(z - 1) = Kp + Ki Ts / (z - 1), Ki = Kp / Ti, with its period
    ``dt = Ts`` (a concrete number) so that a loop checks it runs at Ts."""
    one = jnp.ones((1, 1), jnp.float32)
    return DiscreteSS(A=one, B=jnp.ones((1,), jnp.float32), C=jnp.reshape(Ki * Ts, (1,)).astype(jnp.float32),
                      D=jnp.asarray(Kp, jnp.float32), dt=float(Ts))


def with_pi(loop, Kp, Ki):
    """``loop`` (a single-rate scenario of :func:`jaxnc.schemes.diffdrive.diffdrive_loop`) with
    the PI gains (Kp, Ki) at its sensing period (eq. 30-31, :func:`pi_ss`)."""
    c = loop.controller
    return dataclasses.replace(loop, controller=dataclasses.replace(c, pi=pi_ss(Kp, Ki, c.ns * loop.plant.T)))


def diffdrive_terms(loop, key, Kp, Ki):
    """Per-seed (J1', unstable, J1_mean, J2): J1 of eq. (23) in mm; unstable runs are
    charged max_dev at every NT instant of the horizon (the worst a tube-bound run scores)."""
    m = dd.run(with_pi(loop, Kp, Ki), key)
    penalty = 1000.0 * dd.MAX_DEV * (loop.steps // (2 * loop.plant.sub))
    j1 = jnp.where(m.unstable, penalty, m.J1)
    return j1, m.unstable, m.J1_mean, m.J2


def run_pi(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t_start = time.perf_counter()
    try:
        loop = dd.diffdrive_loop(settings["scenario"], F=settings["F"])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    Ts = loop.controller.ns * loop.plant.T
    paper = {"Kp": np.float32(dd.KP), "Ki": np.float32(dd.KP / dd.TI)}
    steps, batch = settings["steps"], settings["batch"]
    budget = steps * batch
    kp_axis = (3.0, 4.5, 6.0, 9.0, 12.0)
    ti_axis = (0.06, 0.12, 0.24, 0.48)
    grid_seeds = max(2, budget // (len(kp_axis) * len(ti_axis)))

    def loss(p, key, temperature):
        return diffdrive_terms(loop, key, p["Kp"], p["Ki"])[0]

    def per_seed_eval(p, key):
        j1, unstable, j1m, j2 = diffdrive_terms(loop, key, p["Kp"], p["Ki"])
        return dict(loss=j1, unstable=unstable, J1_mean=j1m, J2=j2)

    def per_seed_grid(p, key):
        return diffdrive_terms(loop, key, p["Kp"], p["Kp"] / p["Ti"])[0]

    tr = tune(loss, paper, {"Kp": Positive(), "Ki": Positive()}, steps=steps, batch=batch,
              optimizer=optax.adam(settings["lr"]), seed=settings["seed"], progress=progress, desc="tune PI")
    gs = search(per_seed_grid, grid(Kp=kp_axis, Ti=ti_axis), montecarlo.seed_keys(settings["seed"] + 1, grid_seeds),
                progress=progress, desc="grid PI")
    gbest = {"Kp": gs.best_point["Kp"], "Ki": gs.best_point["Kp"] / gs.best_point["Ti"]}
    eval_keys = montecarlo.seed_keys(settings["seed"] + EVAL_SEED_OFFSET, seeds)
    chunk = min(seeds, 128)
    evs = {n: evaluate(per_seed_eval, p, eval_keys, chunk_size=chunk)
           for n, p in (("paper", paper), ("grid", gbest), ("tuned", tr.params))}
    sims = {"paper": 0, "grid": gs.n_simulations, "tuned": tr.n_simulations}
    gains = {"paper": paper, "grid": gbest, "tuned": tr.params}
    rows, summ = [], {}
    for n, e in evs.items():
        s = {k: dict(zip(("mean", "ci95"), mean_ci(e[k]))) for k in ("loss", "J1_mean", "J2")}
        s["unstable_fraction"] = float(np.mean(e["unstable"]))
        s["Kp"], s["Ki"] = float(gains[n]["Kp"]), float(gains[n]["Ki"])
        s["Ti"] = s["Kp"] / s["Ki"]
        if n != "tuned":
            s["tuned_minus_this"] = dict(zip(("mean", "ci95"), paired_ci(evs["tuned"]["loss"], e["loss"])))
        summ[n] = s
        rows.append([n, fmt(s["Kp"], 3), fmt(s["Ti"], 4), f"{fmt(s['loss']['mean'], 1)} \u00b1 {fmt(s['loss']['ci95'], 1)}",
                     f"{fmt(s['J1_mean']['mean'], 2)} \u00b1 {fmt(s['J1_mean']['ci95'], 2)}",
                     f"{fmt(s['J2']['mean'], 1)} \u00b1 {fmt(s['J2']['ci95'], 1)}", f"{100 * s['unstable_fraction']:.1f}",
                     str(sims[n]),
                     "" if n == "tuned" else f"{fmt(s['tuned_minus_this']['mean'], 1)} \u00b1 {fmt(s['tuned_minus_this']['ci95'], 1)}"])
    tab = markdown_table(["gains", "Kp", "Ti (s)", "J1 eq. 23 (mm)", "mean dist (mm)", "J2 (mm)", "unstable %",
                          "simulations", "tuned - this (paired)"], rows)
    print(f"\nautotune-pi: seed 004 scenario {settings['scenario']} (PI at Ts = {Ts:g} s), F = {settings['F']}, "
          f"{seeds} fresh evaluation seeds\n")
    print(tab)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(tr.history.objective)
    ax.set_xlabel("iteration")
    ax.set_ylabel("J1 (mm), mean over the step's seeds")
    save_figure(fig, out / "objective.png", dpi=120)
    wall = time.perf_counter() - t_start
    results = {"table": tab, "summary": summ, "simulations": sims,
               "history": {"objective": tr.history.objective.tolist(),
                           "Kp": tr.history.params["Kp"].tolist(), "Ki": tr.history.params["Ki"].tolist()},
               "tune_wall_s": tr.wall_time_s, "grid_wall_s": gs.wall_time_s}
    montecarlo.save_results(out / "results.json", experiment="autotune-pi",
                            config={"settings": settings, "seeds": seeds, "Ts": Ts,
                                    "grid": {"Kp": kp_axis, "Ti": ti_axis, "seeds": grid_seeds}},
                            results=results, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'} and {out / 'objective.png'}  ({wall:.1f} s)")
    return results


COMMON = (
    Option("steps", "int", 40, "gradient steps", low=1, high=10_000),
    Option("batch", "int", 8, "seeds per gradient step (fresh each step)", low=2, high=4096),
    Option("seed", "int", 0, "base random seed (evaluation uses seed + 1000003)", low=0, high=2**31 - 1),
)

register(Experiment(
    name="autotune-mecanum",
    description="Seed 000 DRHE: gradient-tune sigma(i), delta(i) for J1 + w J4 vs paper's thresholds vs grid search",
    options=(
        Option("N", "int", 10, "multiplicity: slow period NT", low=1, high=20),
        Option("dp", "float", 0.3, "dropout probability DP = p_sc = p_ca", low=0.0, high=0.95),
        Option("path", "choice", "lissajous", "reference path", choices=tuple(PATHS)),
        Option("weights", "floats", (1.0, 3.0, 10.0, 30.0), "weights w of J4", low=0.0, high=1e4),
        Option("estimator", "choice", "score", "event-gradient estimator",
               choices=("straight_through", "sigmoid", "score", "hybrid")),
        Option("t0", "float", 1.0, "initial trigger temperature", low=1e-6, high=1e6),
        Option("t1", "float", 0.1, "final trigger temperature", low=1e-6, high=1e6),
        Option("lr", "float", 0.3, "Adam learning rate (raw space: log, or logit for init=coarse)",
               low=1e-6, high=10.0),
        Option("score_scale", "float", 0.5, "score / hybrid estimators: std of the parameter perturbations "
               "(raw space: log, or logit for init=coarse)", low=1e-4, high=10.0),
        Option("init", "choice", "coarse", "gradient start: the paper's thresholds, the grid's best (then the "
               "tuned point used both budgets), or coarse (a two-stage tuner inside the grid's budget: successive "
               "halving over the grid's points on half the budget picks the start, half the steps refine it)",
               choices=("paper", "grid", "coarse")),
        Option("family", "choice", "scales", "gradient parameters: per_output (sigma(i), delta(i), 18 values) "
               "or scales (s, d: sigma = s x paper's pattern, delta(i) = d; the grid's family)",
               choices=("per_output", "scales")),
        Option("max_silence", "int", 0, "DRHE time-triggered safety condition: the sensor also sends after this "
               "many silent slow periods (0 = off, as the paper)", low=0, high=100_000),
        Option("near_miss", "float", 0.0, "gradient only: also penalise stable runs whose maximum distance "
               "exceeds this many metres (a differentiable precursor of failures; 0 = off)", low=0.0, high=10.0),
        Option("jacobian_grad", "bool", True, "false: gradients hold the EKF Jacobians constant (same simulation, "
               "about 2x cheaper steps, gradient 0.3-4.8 % from exact)"),
        *COMMON,
    ),
    run=run_mecanum,
    check=check_mecanum,
))

register(Experiment(
    name="autotune-pi",
    description="Seed 004: gradient-tune the wheel PI (Kp, Ti) for J1 vs the paper's gains vs grid search",
    options=(
        Option("scenario", "choice", "b", "single-rate scenario: a (PI at T) or b (PI at NT)", choices=("a", "b")),
        Option("F", "float", 0.1, "noise factor", low=0.0, high=5.0),
        Option("lr", "float", 0.1, "Adam learning rate (raw, log space)", low=1e-6, high=10.0),
        *COMMON,
    ),
    run=run_pi,
))
