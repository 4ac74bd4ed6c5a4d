"""Experiment ``diffdrive``: seed 004 (Cuenca et al., Sensors 2019), scenarios a-e of section 5.2.

Runs the five scenarios on the same seeds (common random numbers), prints Table 2
(J1, J2, J3 absolute with 95 % intervals and normalised to scenario a, network packets),
writes ``results.json`` (full configuration), the per-seed metrics (``seeds.npz``, :func:`jaxnc.load`), ``paths.png`` (Figs. 5-9, seed 0) and
``control.png`` (Fig. 10: control signal of scenario e, seed 0).  ``F`` sets the noise
factor of scenario e (0.1 low, 0.45 high); ``e_high=true`` adds a run of e at F = 0.45,
``e_clean=true`` one of e without noise (F = 0, the delays kept: where the prediction hides
the delay, as the paper claims, it equals c).  ``prediction`` is e's slow-period model
(``integrated``, the default, or ``eq1``, eq. 1 as printed); ``compare=true`` repeats
every e row with the other model (rows marked ``[eq1]`` / ``[integrated]``);
``assumed_delay`` is how long e's prediction stage assumes the previous packet's actions play
each period (0, the default: the paper's prediction, which does not measure the delay).
"""
from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxnc import __version__, loop as nc, montecarlo, results as per_seed, sweep
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import diffdrive as dd

PAPER_TABLE2 = {   # Table 2: J1 (mm, sum over NT instants), J2 (mm), J3 (s)
    "a": (1043.4, 38.76, 22.0), "b": (1671.8, 44.55, 22.4), "c": (1029.9, 38.33, 22.0),
    "d": (1684.4, 44.33, 21.6), "e": (1030.0, 38.97, 21.6)}


def build_loops(settings: dict) -> dict[str, nc.Loop]:
    """Scenarios a-e, then the optional e rows: ``e (F=0)`` (``e_clean``), ``e (F=0.45)``
    (``e_high``), and with ``compare`` each e row again with the other prediction model."""
    kw = dict(N=settings["N"], lad=settings["lad"], eta=settings["eta"], phi=settings["phi"],
              v_ref=settings["v_ref"])
    pred = settings.get("prediction", "integrated")
    ad = settings.get("assumed_delay", 0.0)
    e_rows = [("e", settings["F"])]
    if settings.get("e_clean", False):
        e_rows.append(("e (F=0)", 0.0))
    if settings["e_high"]:
        e_rows.append(("e (F=0.45)", 0.45))
    try:
        loops = {s: dd.diffdrive_loop(s, h=settings["h"], **kw) for s in dd.SCENARIOS if s != "e"}
        for name, F in e_rows:
            loops[name] = dd.diffdrive_loop("e", h=settings["h"], F=F, prediction=pred, assumed_delay=ad, **kw)
        if settings.get("compare", False):
            other = next(p for p in dd.PREDICTIONS if p != loops["e"].plant.lifted)
            for name, F in e_rows:
                loops[f"{name} [{other}]"] = dd.diffdrive_loop("e", h=settings["h"], F=F, prediction=other,
                                                               assumed_delay=ad, **kw)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return loops


NORMALISED = ("J1", "J2", "J1_ref", "J2_ref", "J3")
FIGURE_ROWS = ("a", "b", "c", "d", "e", "e (F=0.45)")     # Figs. 5-9 and 11


def summarise(results: dict) -> dict:
    base = {j: montecarlo.summarize(results["a"][j], results["a"]["unstable"]).mean for j in NORMALISED}
    out = {}
    for name, m in results.items():
        s = {j: montecarlo.summarize(m[j], m["unstable"])
             for j in ("J1", "J1_mean", "J2", "J1_ref", "J2_ref", "J3", "packets")}
        out[name] = {"absolute": {j: v.to_dict() for j, v in s.items()},
                     "normalised": {j: s[j].mean / base[j] for j in NORMALISED},
                     "packets_ratio": s["packets"].mean / float(np.mean(results["a"]["packets"])),
                     "unstable_fraction": float(np.mean(m["unstable"]))}
    return out


def table(summary: dict, printed: bool = False) -> str:
    """Table 2 of seed 004 from the runs: J1 (eq. 23), J2 (eq. 24), J3 (eq. 25), packets, each
    with its ratio to scenario a and the paper's ratio.  ``printed=True``: eq. (23)-(24) as
    printed (distance to the nearest NT sample of the reference trajectory, J1_ref, J2_ref)
    beside Table 2's absolute values."""
    j1, j2 = ("J1_ref", "J2_ref") if printed else ("J1", "J2")
    pa = PAPER_TABLE2["a"]
    rows = []
    for name, s in summary.items():
        a, n = s["absolute"], s["normalised"]
        p = PAPER_TABLE2.get(name)   # the paper gives no Table 2 row for F = 0.45
        cell = lambda j, d=1: fmt(a[j]["mean"], d) + " \u00b1 " + fmt(a[j]["ci95"], d)

        def paper(i, d):             # the paper's value (printed table only) and its ratio to a
            return ([f"{p[i]:.{d}f}" if p else "\u2013"] if printed else []) + \
                [f"{p[i] / pa[i]:.2f}" if p else "\u2013"]
        row = [name, cell(j1), fmt(n[j1]), *paper(0, 1), cell(j2), fmt(n[j2]), *paper(1, 2)]
        if not printed:
            row += [cell("J3", 2), fmt(n["J3"]), fmt(a["packets"]["mean"], 0), fmt(s["packets_ratio"]),
                    f"{100 * s['unstable_fraction']:.1f}"]
        rows.append(row)
    if printed:
        return markdown_table(["scenario", "J1 (mm)", "J1/a", "paper J1", "paper /a", "J2 (mm)", "J2/a", "paper J2",
                               "paper /a"], rows)
    return markdown_table(["scenario", "J1 (mm)", "J1/a", "paper", "J2 (mm)", "J2/a", "paper", "J3 (s)", "J3/a",
                           "packets", "pkt/a", "unstable %"], rows)


def describe(name: str, loop: nc.Loop, settings: dict) -> dict:
    """The configuration of one row, as results.json keeps it (read from the loop's parts)."""
    c, p, scenario = loop.controller, loop.plant, name[0]
    return {"scenario": scenario, "N": settings["N"], "h": c.h if scenario == "e" else settings["h"],
            "n_slow": loop.steps // (settings["N"] * p.sub), "F": float(p.F),
            "prediction": p.lifted if scenario == "e" else None, "v_ref": float(c.v_ref), "lad": float(c.lad),
            "eta": settings["eta"], "phi": settings["phi"], "tau_max": dd.TAU_MAX, "r": float(p.r), "b": float(p.b),
            "noise_F1": {k: float(getattr(p, k)) for k in ("wheel", "enc", "cam", "imu")},
            "path": {"name": c.path.name, "length_m": float(c.path.length), "waypoints": dd.STAIRS}}


def _fine_t(loop: nc.Loop, tr: nc.Trajectory) -> dict:
    """The run every period T (x, u) and the periods until completion, for the figures."""
    sub = loop.plant.sub
    return {"x": tr.x[::sub], "u": tr.u[::sub], "l": tr.done_step // sub}


def plot_paths(loops: dict, key, out: Path) -> tuple[Path, Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = np.asarray(next(iter(loops.values())).controller.path.points)
    n = len(loops)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.4), sharey=True)
    trajs = {}
    for ax, (name, loop) in zip(np.atleast_1d(axes), loops.items()):
        tr = jax.device_get(jax.jit(lambda lp, k: _fine_t(lp, nc.simulate(lp, k)))(loop, key))
        trajs[name] = tr
        xy = np.asarray(tr["x"][: int(tr["l"]), 2:4])
        ax.plot(ref[:, 0], ref[:, 1], "k-", lw=1.2)
        ax.plot(xy[:, 0], xy[:, 1], "b-", lw=1.0)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    np.atleast_1d(axes)[0].set_ylabel("y (m)")
    f1 = save_figure(fig, out / "paths.png", dpi=120)

    fig, axes = plt.subplots(1, 2 if "e (F=0.45)" in trajs else 1, figsize=(10, 3.4), squeeze=False)
    for ax, name in zip(axes[0], [k for k in ("e", "e (F=0.45)") if k in trajs]):
        tr, T = trajs[name], loops[name].plant.T
        l = int(tr["l"])
        t = np.arange(l) * T
        ax.step(t, np.asarray(tr["u"])[:l, 0], where="post", label="u_r")
        ax.step(t, np.asarray(tr["u"])[:l, 1], where="post", label="u_l")
        ax.set_title(f"control signal, scenario {name}")
        ax.set_xlabel("t (s)")
        ax.legend(fontsize=8)
    f2 = save_figure(fig, out / "control.png", dpi=120)
    return f1, f2


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    loops = build_loops(settings)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    results = {}
    for name, loop in loops.items():
        m = montecarlo.run_batched(lambda k, loop=loop: dd.run(loop, k, N=settings["N"]), keys,
                                   chunk_size=min(64, max(seeds, 1)), progress=progress, desc=f"scenario {name}")
        results[name] = {k: np.asarray(v) for k, v in m._asdict().items()}
    summary = summarise(results)
    print(f"\nseed 004 differential drive, N={settings['N']}, h={settings['h']}, F(e)={settings['F']}, "
          f"prediction={loops['e'].plant.lifted}, seeds={seeds}")
    print("J1 = sum over NT instants of the distance to the path (eq. 23), J2 max (eq. 24), J3 time (eq. 25);"
          " '/a' normalised to scenario a, 'paper' the same ratio from Table 2\n")
    print(table(summary))
    ref = loops["a"]
    print(f"\nThe same runs with eq. (23)-(24) as printed: the distance to the nearest NT sample of the reference"
          f" trajectory (references {1000 * float(ref.controller.v_ref) * settings['N'] * ref.plant.T:.0f} mm apart),"
          " not to the"
          " path; 'paper' Table 2's values\n")
    print(table(summary, printed=True))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, results, dims=("case",), experiment="diffdrive", units=dd.Metrics.UNITS)
    f1, f2 = plot_paths({n: l for n, l in loops.items() if n in FIGURE_ROWS}, keys[0], out)
    wall = time.perf_counter() - t0
    config = {"settings": settings, "seeds": seeds,
              "loops": {n: describe(n, l, settings) for n, l in loops.items()},
              "paper_table2": PAPER_TABLE2}
    montecarlo.save_results(out / "results.json", experiment="diffdrive", config=config, results=summary,
                            wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'}, {f1}, {f2}  ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="diffdrive",
    description="Seed 004: differential-drive robot, scenarios a-e (single/dual rate, delays, EKF + prediction)",
    options=(
        Option("N", "int", 2, "multiplicity: sensing period NT (tau_max must stay below NT)", low=2, high=10),
        Option("h", "int", 1, "prediction horizon of scenario e, in sensing periods", low=1, high=50),
        Option("F", "float", 0.1, "noise factor of scenario e (paper: 0.1 low, 0.45 high)", low=0.0, high=2.0),
        Option("e_high", "bool", True, "also run scenario e at F = 0.45"),
        Option("e_clean", "bool", True, "also run scenario e without noise (F = 0, delays kept)"),
        Option("prediction", "choice", "integrated", "scenario e's slow-period model: integrated (the true "
               "plant's integrator with the fine actions applied) or eq1 (eq. 1 as printed)", choices=dd.PREDICTIONS),
        Option("compare", "bool", True, "repeat every e row with the other prediction model"),
        Option("assumed_delay", "float", 0.0, "scenario e: how long (s) the prediction stage assumes the previous "
               "packet's actions play each period (0: the paper's, the delay is not measured)", low=0.0, high=0.2),
        Option("lad", "float", dd.LAD, "pure-pursuit look-ahead distance, m", low=0.02, high=1.0),
        Option("v_ref", "float", dd.V_REF, "reference speed along the path, m/s", low=0.01, high=1.0),
        Option("eta", "float", dd.DELAY_ETA, "delay shift, s (< tau_max = 0.17)", low=0.0, high=0.17),
        Option("phi", "float", dd.DELAY_PHI, "delay scale, s", low=0.0, high=1.0),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
))


# ----------------------------------------------------------------------------- sensitivity


def sensitivity_cell(settings: dict, v: float, lad: float, keys) -> dict:
    """One (v_ref, look-ahead) cell of the sensitivity grid: scenarios a-e on ``keys``."""
    loops = build_loops(dict(settings, v_ref=v, lad=lad, e_high=False, e_clean=False, compare=False))
    results = {}
    for name, loop in loops.items():
        m = montecarlo.run_batched(lambda k, loop=loop: dd.run(loop, k, N=settings["N"]), keys,
                                   chunk_size=min(64, max(len(keys), 1)), progress=False)
        results[name] = {k: np.asarray(v_) for k, v_ in m._asdict().items()}
    s = summarise(results)
    return {"v_ref": v, "lad": lad,
            "J1_a": s["a"]["absolute"]["J1"]["mean"], "J1_ref_a": s["a"]["absolute"]["J1_ref"]["mean"],
            "ratios": {n: {j: s[n]["normalised"][j] for j in ("J1", "J1_ref")} for n in s},
            "unstable": {n: s[n]["unstable_fraction"] for n in s}}


def run_sensitivity(settings: dict, *, seeds: int, out: Path, progress: bool = True,
                    shard: sweep.Shard | None = None) -> dict:
    """Table 2's ratios over the two path-tracking parameters the paper does not give:
    the reference speed v_ref and the look-ahead distance (a grid), both J1 readings.

    Each cell is stored as ``OUT/cells/sensitivity/v<v_ref>_lad<look-ahead>-<hash>.json``
    (the hash of its whole configuration, :func:`jaxnc.sweep.cell_path`) when
    done (a rerun computes only the missing ones; ``shard``: only its share,
    :mod:`jaxnc.sweep`); the table, figure and ``results.json`` are written by the run
    that finds every cell stored."""
    t0 = time.perf_counter()
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    v_refs, lads = settings["v_refs"], settings["lads"]
    out.mkdir(parents=True, exist_ok=True)
    cells = [(v, lad) for lad in lads for v in v_refs]
    common = {k: settings[k] for k in settings if k not in ("v_refs", "lads")}
    cfg = lambda c: {"settings": common, "v_ref": c[0], "lad": c[1], "seeds": seeds,
                     "devices": len(jax.local_devices()), "version": __version__}
    cell_f = lambda c: sweep.cell_path(out / "cells" / "sensitivity", f"v{c[0]:.10g}_lad{c[1]:.10g}", cfg(c))
    mine = shard.share(cells) if shard is not None else cells
    todo = [c for c in mine if sweep.load_cell(cell_f(c), cfg(c)) is None]
    bar = tqdm(todo, desc="(v_ref, look-ahead)", disable=not progress, dynamic_ncols=True)
    for c in bar:
        sweep.save_cell(cell_f(c), {"config": cfg(c), "cell": sensitivity_cell(settings, c[0], c[1], keys)})
        bar.set_postfix(v_ref=c[0], lad=c[1])
    with sweep.assembly_lock(out):
        stored = {c: sweep.load_cell(cell_f(c), cfg(c)) for c in cells}
        missing = [c for c in cells if stored[c] is None]
        if missing:
            print(f"\nsensitivity grid: {len(todo)} cells computed. " + sweep.missing_report(
                cells, missing, shard, describe=lambda c: f"v_ref {c[0]:g}, look-ahead {c[1]:g}"))
            return {"complete": False, "missing": len(missing)}
        return _write_sensitivity(settings, seeds, out, [stored[c]["cell"] for c in cells], t0)


def _write_sensitivity(settings: dict, seeds: int, out: Path, grid: list, t0: float) -> dict:
    """Table, figure and results.json of the sensitivity grid from all its cells."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lads = settings["lads"]
    paper = {n: PAPER_TABLE2[n][0] / PAPER_TABLE2["a"][0] for n in dd.SCENARIOS}
    rows = []
    for g in grid:
        r = g["ratios"]
        ok = lambda j: ("yes" if all(r[n][j] >= 1.3 for n in "bd") and all(abs(r[n][j] - 1) <= 0.05 for n in "ce")
                        else "no")
        rows.append([f"{g['v_ref']:.3f}", f"{g['lad']:.3f}", fmt(g["J1_a"], 0)]
                    + [fmt(r[n]["J1"]) for n in "bcde"] + [ok("J1"), fmt(g["J1_ref_a"], 0)]
                    + [fmt(r[n]["J1_ref"]) for n in "bcde"] + [ok("J1_ref")])
    tab = markdown_table(["v_ref", "look-ahead", "a: J1", "b/a", "c/a", "d/a", "e/a", "pattern",
                          "a: J1 printed", "b/a", "c/a", "d/a", "e/a", "pattern"], rows)
    print(f"\nseed 004 Table 2 sensitivity, {seeds} seeds per cell; J1 to the path, then eq. (23) as printed"
          " (nearest NT reference point). Paper: b/a 1.60, c/a 0.99, d/a 1.61, e/a 0.99. 'pattern': b, d >= 1.3 a"
          " and c, e within 5 % of a (issue 4's acceptance)\n")
    print(tab)
    fig, axes = plt.subplots(2, len(lads), figsize=(4.2 * len(lads), 6.4), squeeze=False, sharex=True)
    for row, (j, label) in enumerate((("J1", "J1 to the path"), ("J1_ref", "J1 as printed (NT references)"))):
        for col, lad in enumerate(lads):
            ax = axes[row, col]
            gs = [g for g in grid if g["lad"] == lad]
            for n, c in zip("bcde", ("C0", "C1", "C2", "C3")):
                ax.plot([g["v_ref"] for g in gs], [g["ratios"][n][j] for g in gs], "o-", color=c, label=f"{n}/a")
                ax.axhline(paper[n], color=c, ls=":", lw=0.8)
            ax.axhspan(0.95, 1.05, color="0.9")
            ax.set_yscale("log")
            ax.set_title(f"{label}, look-ahead {lad} m", fontsize=9)
            if row == 1:
                ax.set_xlabel("v_ref (m/s)")
    axes[0, 0].set_ylabel("J1 / J1(a)")
    axes[1, 0].set_ylabel("J1 / J1(a)")
    axes[0, -1].legend(fontsize=8)
    fig.suptitle("dotted: the paper's ratios; grey band: within 5 % of a", fontsize=9)
    f1 = save_figure(fig, out / "sensitivity.png", dpi=120)
    wall = time.perf_counter() - t0
    montecarlo.save_results(out / "results.json", experiment="diffdrive-sensitivity",
                            config={"settings": settings, "seeds": seeds, "paper_ratios_J1": paper},
                            results={"grid": grid, "complete": True}, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'}, {f1}  ({wall:.1f} s)")
    return {"grid": grid}


SENSITIVITY = register(Experiment(
    name="diffdrive-sensitivity",
    description="Seed 004: Table 2's J1 ratios over the reference speed and look-ahead (unpublished parameters)",
    options=(
        Option("v_refs", "floats", (0.12, 0.13, 0.14, 0.15, 0.16), "reference speeds, m/s", low=0.01, high=1.0),
        Option("lads", "floats", (0.10, 0.12, 0.15), "look-ahead distances, m", low=0.02, high=1.0),
        Option("N", "int", 2, "multiplicity", low=2, high=10),
        Option("h", "int", 1, "prediction horizon of scenario e", low=1, high=50),
        Option("F", "float", 0.1, "noise factor of scenario e", low=0.0, high=2.0),
        Option("prediction", "choice", "integrated", "scenario e's slow-period model (integrated or eq1)",
               choices=dd.PREDICTIONS),
        Option("eta", "float", dd.DELAY_ETA, "delay shift, s", low=0.0, high=0.17),
        Option("phi", "float", dd.DELAY_PHI, "delay scale, s", low=0.0, high=1.0),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run_sensitivity,
    keeps_cells=True,
))
