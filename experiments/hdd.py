"""Experiments ``hdd`` and ``hdd-gpi``: seed 003 (Cuenca et al.), HDD servo, section 5.

``hdd`` runs Cases 1-6 on the same seeds (common random numbers), prints the table of
Uc, Ua, Cc, ISE, ISEP, NE and GPI (eq. 23-29) next to the paper's values, writes
``results.json``, the per-seed metrics (``seeds.npz``, :func:`jaxnc.load`), one figure per case like Figs 6-9, 11, 13 (output, control, utilisation
bars; a black dot where the actuator applies a packet's current action), Figs 10 and 12
(Cases 4 and 5: the disturbance estimate and the multiplicity N over time) and the plant's
frequency response (``plant_bode.png``).

``hdd-gpi`` is the Monte-Carlo grid of Fig. 5: GPI (W1 = W2 = 0.45, W3 = 0.1) over
(delta_s = sigma_s, delta_c = sigma_c) on a log grid, its minimum marked.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import jaxnc.loop as jl
from jaxnc import __version__, montecarlo, results as per_seed, sweep
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.plants import hdd as hdd_plant
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import hdd
from jaxnc.tune import set_paths

# Section 5 of the paper: (N_sc, Uc, N_ca, Ua, Cc %, NE) per case; None where not reported.
PAPER = {1: dict(Uc=1.0, Ua=1.0, Cc=66, NE=0.0, ISE=3.75), 2: dict(Uc=0.54, Ua=0.16, Cc=35, NE=0.14),
         3: dict(Uc=0.26, Ua=0.10, Cc=17, NE=None), 4: dict(Uc=0.44, Ua=0.15, Cc=29, NE=0.09),
         5: dict(Uc=0.73, Ua=231 / 464, Cc=48, NE=0.02), 6: dict(Uc=0.78, Ua=315 / 464, Cc=53, NE=0.01)}
CASE_NAMES = {1: "TTS", 2: "PETC", 3: "PETC+NUMRE", 4: "+noise+dist", 5: "narrow thr.", 6: "DOB"}
METRICS = ("Uc", "Ua", "Cc", "ISE", "ISEP", "NE", "GPI")


def _common(settings):
    # h = 0: the whole run (schemes.hdd.whole_run_horizon), the paper's rule h >= N_max
    return dict(reading=settings["reading"], h=settings["h"] or None, k_max=settings["k_max"], m=settings["m"],
                w_std=settings["w_std"])


def build_loops(settings: dict) -> dict[int, jl.Loop]:
    cases = hdd.CASES if settings["case"] == "all" else (int(settings["case"]),)
    try:
        return {c: hdd.hdd_loop(c, **_common(settings)) for c in cases}
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _batched():
    """jit(vmap over keys) of :func:`jaxnc.schemes.hdd.run`: (loop, keys, y_tts, ise_tts, cs) -> Metrics."""
    per_seed = lambda loop, key, y_tts, ise_tts, cs: hdd.run(loop, key, y_tts=y_tts, ise_tts=ise_tts, cs=cs)
    return jax.jit(jax.vmap(per_seed, in_axes=(None, 0, None, None, None)), static_argnums=(4,))


def summarise(m) -> dict:
    unstable = np.asarray(m.unstable)
    return {k: montecarlo.summarize(np.asarray(getattr(m, k), float), unstable).to_dict()
            for k in METRICS} | {"n_sc_mean": float(np.mean(m.n_sc)), "n_ca_mean": float(np.mean(m.n_ca)),
                                 "unstable_fraction": float(np.mean(unstable)),
                                 "N_max": int(np.max(m.N_max)), "n_held_mean": float(np.mean(m.n_held))}


def table(summary: dict) -> str:
    rows = []
    for c, s in summary.items():
        p = PAPER[int(c)]
        rows.append([f"{c} {CASE_NAMES[int(c)]}", fmt(s["Uc"]["mean"]), fmt(p["Uc"]), fmt(s["Ua"]["mean"]), fmt(p["Ua"]),
                     fmt(100 * s["Cc"]["mean"], 0), fmt(p["Cc"], 0), fmt(s["ISEP"]["mean"], 3),
                     fmt(s["NE"]["mean"], 3) + " \u00b1 " + fmt(s["NE"]["ci95"], 3), fmt(p["NE"]),
                     fmt(s["GPI"]["mean"], 3), f"{100 * s['unstable_fraction']:.1f}", str(s["N_max"]),
                     fmt(s["n_held_mean"], 1)])
    return markdown_table(["case", "Uc", "paper", "Ua", "paper", "Cc %", "paper", "ISEP", "NE", "paper", "GPI",
                           "unstable %", "N_max", "held"], rows)


def series(loop: jl.Loop, tr) -> dict:
    """The signals the figures show, from the runner's trajectory ``tr`` of one run: the
    output y and disturbance d, the estimated output and disturbance (C x-hat, Cbar x-hat of
    the estimate used at each instant, eq. 15; NaN without NUMRE), the disturbance estimate
    the controller used at an arrival (NaN elsewhere), N at arrivals, the send flags."""
    numre = isinstance(loop.estimator, jl.Numre)
    law, xhat = loop.controller.law, np.asarray(tr.xhat)
    nan = np.full(loop.steps, np.nan)
    beta = np.asarray(tr.sent_sc) > 0.5
    dhat, N = (np.asarray(a) for a in tr.parts["controller"])
    return dict(y=np.asarray(hdd.output(loop, tr)), d=np.asarray(hdd.disturbance(tr)), u=np.asarray(tr.u)[:, 0],
                yhat=xhat @ np.asarray(law.C) if numre else nan, dpred=xhat @ np.asarray(law.Cbar) if numre else nan,
                dhat=np.where(beta, dhat, np.nan), N=N, beta=beta, gamma=np.asarray(tr.sent_ca) > 0.5,
                current=(np.asarray(tr.recv_ca) > 0) | (np.arange(loop.steps) == 0), numre=numre,
                noise=bool(np.any(np.asarray(loop.plant.w_std) > 0)))


def plot_case(loop, traj, out: Path, case: int) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    s = series(loop, traj)
    t = np.arange(loop.steps) * hdd_plant.T * 1e3
    fig, ax = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    ax[0].plot(t, np.full_like(t, float(loop.controller.law.r)), "k--", lw=1, label="reference")
    ax[0].plot(t, s["y"], lw=1.3, label="output y")
    if s["numre"]:
        ax[0].plot(t, s["yhat"], lw=0.8, ls=":", label="estimated output")
    ax[0].set_ylabel("position")
    ax[0].legend(fontsize=8)
    ax[1].step(t, s["u"], where="post", lw=1)
    if s["noise"]:
        ax[1].plot(t, -s["d"], lw=0.8, label="-d (true disturbance)")
        ax[1].legend(fontsize=8)
    ax[1].set_ylabel("control u")
    beta, gamma = s["beta"], s["gamma"]
    ax[2].vlines(t[beta], 0, 1, color="C0", lw=0.6, label=f"controller used ({beta.sum()})")
    ax[2].vlines(t[gamma], 1.1, 2.1, color="C3", lw=0.6, label=f"actuator updated ({gamma.sum()})")
    if s["numre"]:
        cur = s["current"] & gamma
        ax[2].plot(t[cur], np.full(cur.sum(), 2.25), "k.", ms=3, label="current action applied")
    ax[2].set_yticks([0.5, 1.6], ["controller", "actuator"])
    ax[2].set_xlabel("time (ms)")
    ax[2].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"Case {case}: {CASE_NAMES[case]} (seed 0)")
    f = save_figure(fig, out / f"case{case}.png", dpi=120)
    return f


# The paper's figures of the disturbance estimate and the multiplicity N (Cases 4 and 5).
DISTURBANCE_FIGS = {4: 10, 5: 12}


def plot_disturbance_n(loop, traj, out: Path, case: int) -> Path:
    """Figs. 10 and 12 (Cases 4, 5): top, the disturbance d and its estimates (the
    filter's d-hat every period, eq. 15, and the value the controller used at each arrival);
    middle, the multiplicity N (eq. 9) of each arrival over time; bottom, how often each N
    occurs over the run's periods, N = 0 where no event is triggered at the sensor."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig_no = DISTURBANCE_FIGS[case]
    s = series(loop, traj)
    t = np.arange(loop.steps) * hdd_plant.T * 1e3
    beta, N = s["beta"], s["N"]
    fig, ax = plt.subplots(3, 1, figsize=(8, 7))
    ax[0].plot(t, s["d"], "k", lw=1.2, label="disturbance d")
    ax[0].plot(t, s["dpred"], lw=0.9, label="estimate (filter, eq. 15)")
    ax[0].plot(t[beta], s["dhat"][beta], ".", ms=3, label="estimate used at an arrival")
    ax[0].set_ylabel("d")
    ax[0].set_xlabel("time (ms)")
    ax[0].legend(fontsize=8)
    arr = beta & (N > 0)
    ax[1].vlines(t[arr], 0, N[arr], lw=0.8)
    ax[1].plot(t[arr], N[arr], ".", ms=3)
    ax[1].set_ylabel("N at an arrival")
    ax[1].set_xlabel("time (ms)")
    counts = np.bincount(N, minlength=2)
    ax[2].bar(np.arange(counts.size), counts / loop.steps, width=0.8)
    ax[2].set_xlabel("N (0: no event at the sensor)")
    ax[2].set_ylabel("fraction of periods")
    ax[2].set_yscale("log")
    fig.suptitle(f"Fig. {fig_no}: Case {case} ({CASE_NAMES[case]}), disturbance estimate and multiplicity N\n"
                 f"seed 0: N_max = {int(N.max())}, {int(beta.sum())} arrivals, h = {loop.actuator.horizon - 1}", fontsize=10)
    f = save_figure(fig, out / f"fig{fig_no}_case{case}_disturbance_N.png", dpi=120)
    return f


def plot_bode(out: Path, reading: str) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for r in hdd_plant.READINGS:
        f, G = hdd_plant.frequency_response(r)
        lw = 1.8 if r == reading else 0.8
        ax[0].semilogx(f, 20 * np.log10(np.abs(G)), lw=lw, label=f"eq. (30) read as '{r}'")
        ax[1].semilogx(f, np.unwrap(np.angle(G)) * 180 / np.pi, lw=lw)
    ax[0].set_ylabel("|G| (dB)")
    ax[0].legend(fontsize=8)
    ax[1].set_ylabel("phase (deg)")
    ax[1].set_xlabel("frequency (Hz)")
    fig.suptitle("10th-order HDD plant (eq. 30-31), T = 20 us")
    p = save_figure(fig, out / "plant_bode.png", dpi=120)
    return p


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    loops = build_loops(settings)
    y_tts, ise_tts = hdd.tts_reference(reading=settings["reading"], m=settings["m"])
    cs = hdd.controller_design(settings["m"]).cs
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    f = _batched()
    summary, runs = {}, {}
    for c, loop in (tqdm(loops.items(), desc="cases") if progress else loops.items()):
        m = jax.device_get(f(loop, keys, y_tts, ise_tts, cs))
        summary[c] = summarise(m)
        runs[str(c)] = m
    print(f"\nseed 003 HDD servo, {seeds} seeds, ISE (TTS, eq. 23) = {float(ise_tts):.3f} (paper 3.75), "
          f"CS = {100 * cs:.0f} % (paper 33 %)\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, runs, dims=("case",), experiment="hdd")
    figs = [plot_bode(out, settings["reading"])]
    for c, loop in loops.items():
        traj = jax.device_get(jax.jit(jl.simulate)(loop, keys[0]))
        figs.append(plot_case(loop, traj, out, c))
        if c in DISTURBANCE_FIGS:
            figs.append(plot_disturbance_n(loop, traj, out, c))
    wall = time.perf_counter() - t0
    config = {"settings": settings, "seeds": seeds, "T": hdd_plant.T, "steps": hdd.STEPS,
              "h": {c: l.actuator.horizon - 1 for c, l in loops.items() if c >= 3},
              "noise": {"w_std": settings["w_std"], "v_std": hdd_plant.V_STD},
              "filter": {"W": hdd.filter_disturbance_var(settings["w_std"]), "slope_std": hdd.FILTER_SLOPE_STD,
                         "V": hdd.FILTER_V,
                         "case6_input_std": hdd.FILTER_INPUT_STD},
              "thresholds": {c: {"delta_s=sigma_s": float(l.trigger.delta), "delta_c=sigma_c": float(l.controller_trigger.delta)}
                             for c, l in loops.items() if c >= 2}}
    montecarlo.save_results(out / "results.json", experiment="hdd", config=config,
                            results={"cases": {str(c): s for c, s in summary.items()}, "ISE_TTS": float(ise_tts),
                                     "CS": cs, "paper": PAPER}, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'} and {len(figs)} figures ({wall:.1f} s)")
    return summary


# ----------------------------------------------------------------------------- GPI surface (Fig. 5)


def gpi_grid(loop: jl.Loop, ts_values, tc_values, keys, y_tts, ise_tts, cs, *, progress=True,
             W=(0.45, 0.45, 0.1), points=None, on_point=None):
    """Mean GPI, Uc, Ua, NE and the unstable fraction over ``keys`` for every
    (delta_s = sigma_s, delta_c = sigma_c) pair: float[len(ts), len(tc), 5].

    ``points``: only these (i, j) (the others are NaN); ``on_point(i, j, values)`` is
    called as each is done (the sweep stores it)."""
    @jax.jit
    def point(ts, tc, keys):
        l = set_paths(loop, {"trigger.sigma": ts, "trigger.delta": ts, "controller_trigger.sigma": tc,
                             "controller_trigger.delta": tc})
        m = jax.vmap(lambda k: hdd.run(l, k, y_tts=y_tts, ise_tts=ise_tts, cs=cs, W=W))(keys)
        ok = ~m.unstable
        mean = lambda a: jnp.sum(jnp.where(ok, a, 0.0)) / jnp.maximum(jnp.sum(ok), 1)
        return jnp.stack([mean(m.GPI), mean(m.Uc), mean(m.Ua), mean(m.NE), jnp.mean(m.unstable)])

    res = np.full((len(ts_values), len(tc_values), 5), np.nan)
    if points is None:
        points = [(i, j) for i in range(len(ts_values)) for j in range(len(tc_values))]
    bar = tqdm(total=len(points), desc="GPI grid", disable=not progress)
    for i, j in points:
        res[i, j] = np.asarray(point(jnp.float32(ts_values[i]), jnp.float32(tc_values[j]), keys))
        if on_point is not None:
            on_point(i, j, res[i, j])
        bar.update(1)
    bar.close()
    return res


def plot_gpi(ts, tc, res, out: Path, imin) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(11, 4.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    X, Y = np.meshgrid(np.log10(tc), np.log10(ts))
    ax.plot_surface(X, Y, res[..., 0], cmap="viridis", alpha=0.85)
    ax.scatter([np.log10(tc[imin[1]])], [np.log10(ts[imin[0]])], [res[imin][0]], color="r", s=40)
    ax.set_xlabel("log10 delta_c = sigma_c")
    ax.set_ylabel("log10 delta_s = sigma_s")
    ax.set_zlabel("GPI")
    ax2 = fig.add_subplot(1, 2, 2)
    cs_ = ax2.contourf(X, Y, res[..., 0], levels=20, cmap="viridis")
    fig.colorbar(cs_, ax=ax2, label="GPI")
    ax2.plot(np.log10(tc[imin[1]]), np.log10(ts[imin[0]]), "r*", ms=14, label="minimum")
    ax2.plot(np.log10(1.32e-2), np.log10(1e-5), "wx", ms=10, label="paper's optimum")
    ax2.set_xlabel("log10 delta_c = sigma_c")
    ax2.set_ylabel("log10 delta_s = sigma_s")
    ax2.legend(fontsize=8)
    fig.suptitle("GPI = 0.45 Uc + 0.45 Ua + 0.1 NE (Fig. 5)")
    p = save_figure(fig, out / "gpi_surface.png", dpi=120)
    return p


def run_gpi(settings: dict, *, seeds: int, out: Path, progress: bool = True,
            shard: sweep.Shard | None = None) -> dict:
    """The GPI surface. Each (i, j) point is stored as ``OUT/cells/gpi/ts<i>_tc<j>-<hash>.json``
    (the hash of its whole configuration, :func:`jaxnc.sweep.cell_path`) when
    done (a rerun computes only the missing ones; ``shard``: only its share,
    :mod:`jaxnc.sweep`); the surface, figure and ``results.json`` are written by the run
    that finds every point stored."""
    t0 = time.perf_counter()
    if settings["ts_min"] >= settings["ts_max"] or settings["tc_min"] >= settings["tc_max"]:
        raise ConfigError("ts_min must be < ts_max and tc_min < tc_max")
    try:
        loop = hdd.hdd_loop(int(settings["case"]), **_common(settings))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    n = settings["n"]
    ts = np.logspace(math.log10(settings["ts_min"]), math.log10(settings["ts_max"]), n)
    tc = np.logspace(math.log10(settings["tc_min"]), math.log10(settings["tc_max"]), n)
    y_tts, ise_tts = hdd.tts_reference(reading=settings["reading"], m=settings["m"])
    cs = hdd.controller_design(settings["m"]).cs
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    points = [(i, j) for i in range(n) for j in range(n)]
    cfg = lambda i, j: {"settings": settings, "seeds": seeds, "i": i, "j": j, "ts": float(ts[i]), "tc": float(tc[j]),
                        "version": __version__}
    cell_f = lambda i, j: sweep.cell_path(out / "cells" / "gpi", f"ts{i:02d}_tc{j:02d}", cfg(i, j))
    mine = shard.share(points) if shard is not None else points
    todo = [p for p in mine if sweep.load_cell(cell_f(*p), cfg(*p)) is None]
    gpi_grid(loop, ts, tc, keys, y_tts, ise_tts, cs, progress=progress, points=todo,
             on_point=lambda i, j, v: sweep.save_cell(cell_f(i, j), {"config": cfg(i, j), "values": v.tolist()}))
    with sweep.assembly_lock(out):
        stored = {p: sweep.load_cell(cell_f(*p), cfg(*p)) for p in points}
        missing = [p for p in points if stored[p] is None]
        if missing:
            print(f"\nGPI surface: {len(todo)} points computed. " + sweep.missing_report(
                points, missing, shard, describe=lambda p: f"delta_s {ts[p[0]]:.3g}, delta_c {tc[p[1]]:.3g}"))
            return {"complete": False, "missing": len(missing)}
        res = np.array([[stored[(i, j)]["values"] for j in range(n)] for i in range(n)], float)
        return _write_gpi(settings, seeds, out, ts, tc, res, t0)


def _write_gpi(settings, seeds, out, ts, tc, res, t0) -> dict:
    """The surface's minimum, figure and results.json from all points ``res``."""
    n = len(ts)
    g = np.where(np.isfinite(res[..., 0]), res[..., 0], np.inf)
    imin = np.unravel_index(np.argmin(g), g.shape)
    out.mkdir(parents=True, exist_ok=True)
    fig = plot_gpi(ts, tc, res, out, imin)
    wall = time.perf_counter() - t0
    best = {"delta_s=sigma_s": float(ts[imin[0]]), "delta_c=sigma_c": float(tc[imin[1]]),
            "GPI": float(res[imin][0]), "Uc": float(res[imin][1]), "Ua": float(res[imin][2]), "NE": float(res[imin][3])}
    print(f"\nGPI surface (case {settings['case']}, {n}x{n} grid, {seeds} seeds per point): minimum GPI "
          f"{best['GPI']:.3f} at delta_s = sigma_s = {best['delta_s=sigma_s']:.3g}, delta_c = sigma_c = "
          f"{best['delta_c=sigma_c']:.3g} (Uc {best['Uc']:.2f}, Ua {best['Ua']:.2f}, NE {best['NE']:.3f}); "
          f"paper: 1e-5, 1.32e-2")
    montecarlo.save_results(out / "results.json", experiment="hdd-gpi",
                            config={"settings": settings, "seeds": seeds, "ts": ts, "tc": tc, "W": (0.45, 0.45, 0.1)},
                            results={"GPI": res[..., 0], "Uc": res[..., 1], "Ua": res[..., 2], "NE": res[..., 3],
                                     "unstable_fraction": res[..., 4], "minimum": best}, wall_time_s=wall)
    print(f"wrote {out / 'results.json'} and {fig} ({wall:.1f} s)")
    return best


_OPTS = (
    Option("reading", "choice", "sum", "how eq. (30)'s resonances are read", choices=hdd_plant.READINGS),
    Option("h", "int", 0, "NUMRE cascade horizon h (fast periods); 0 = the whole run, steps - 1 "
           "(the paper's h >= N_max for any gap)", low=0, high=1000),
    Option("k_max", "int", 0, "time-triggered safety condition eq. (7), 0 = off", low=0, high=1000),
    Option("m", "int", 2, "MRCI rate ratio m", low=1, high=8),
    Option("w_std", "float", hdd_plant.W_STD, "std of the noise driving the disturbance (eq. 32), Cases 4-6",
           low=0.0, high=1e-2),
    Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
)

EXPERIMENT = register(Experiment(
    name="hdd",
    description="Seed 003: HDD servo, Cases 1-6 (TTS, PETC, NUMRE, noise+disturbance, narrow thresholds, DOB)",
    options=(Option("case", "choice", "all", "case to run", choices=("1", "2", "3", "4", "5", "6", "all")), *_OPTS),
    run=run,
))

EXPERIMENT_GPI = register(Experiment(
    name="hdd-gpi",
    description="Seed 003: GPI surface over (delta_s = sigma_s, delta_c = sigma_c), Fig. 5",
    options=(Option("case", "choice", "4", "case whose thresholds are swept", choices=("2", "3", "4", "5", "6")),
             Option("n", "int", 10, "grid points per axis", low=2, high=40),
             Option("ts_min", "float", 1e-8, "smallest delta_s = sigma_s", low=1e-12, high=1.0),
             Option("ts_max", "float", 1e-3, "largest delta_s = sigma_s", low=1e-12, high=1.0),
             Option("tc_min", "float", 1e-5, "smallest delta_c = sigma_c", low=1e-12, high=10.0),
             Option("tc_max", "float", 1.0, "largest delta_c = sigma_c", low=1e-12, high=10.0),
             *_OPTS),
    run=run_gpi,
    keeps_cells=True,
))
