"""Experiment ``mecanum-validation``: seed 000, section 5 (experimental validation) on the
MJX robot -- Tables 5-6 and Figs. 12, 15-16 beside the paper's numbers.

The paper's hardware test (section 5.1): the radio cannot send faster than every
0.2 s, so the slow period is NT = 0.2 s at the smallest multiplicity; with T = 0.1 s
as in section 4 (J4 = 0.500 for DRH at N = 2, 0.167 at N = 6 in Table 6, i.e. one
packet per NT over one per T), N in {2, 4, 6} gives NT in {0.2, 0.4, 0.6} s. DP in
{0, 0.1, 0.2, 0.3, 0.4}, DRH and DRHE on the Lissajous curve, and a reference reduced
in size because of the workspace (the paper gives no size: ``scale`` of our
section-4 path, 0.5 by default). Our counterpart of the robot is the multibody plant
:mod:`jaxnc.plants.mecanum_mjx` (``plant=mjx``, the default; ``plant=kinematic`` runs
the kinematic model, for quick tests); the NUDREKF keeps eq. (1) in both.

Normalisation as Tables 5-6: the hardware has no nominal single-rate run (T = 0.1 s
is below the radio's period), so J1-J3 are ratios of means to DRH at N = 2, DP = 0
on the same seeds (the tables' first row is 1.00); J4 is the sensor transmission
rate over that of the nominal single-rate loop, which sends once per T: the number
of sensor packets over the fast periods to completion.

Beside the DRH/DRHE grid, the Fig. 12 comparison at N = 4, DP = 0.4 (DR there, and
SR at its fastest period NT = 0.2 s, N = 2, at the same DP) as Monte-Carlo cells,
and seed 0's paths as a figure.

Each cell is stored as soon as it is done (``OUT/cells/<case>_N<N>_dp<DP>.json`` and
its per-seed ``.npz``, :mod:`jaxnc.sweep`); a rerun computes only the missing ones.
Outputs: ``tables.md`` (Tables 5-6, ours beside the paper's, the Fig. 12 cells and the
list of section-5 conclusions checked), ``fig15_16.png`` (J1-J4 over DP per N, the
paper's table values as open markers), ``fig12_paths.png``, ``results.json`` (full
configuration and every cell, per-seed files for :func:`jaxnc.load`).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxnc.cache import cache_beside
from jaxnc import montecarlo, results as per_seed, sweep
from jaxnc.controllers.path_following import LOOKAHEAD
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.paths import PATHS, get_path, scaled
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import mecanum as mec

from .mecanum import UNSTABLE_CELL, horizon, plot_paths, run_seed, true_plant
from .mecanum_grid import _version

INF = math.inf
CASES = ("DRH", "DRHE")
TABLE_N = (2, 6)
TABLE_DP = (0.0, 0.2, 0.4)
BASE = ("DRH", 2, 0.0)              # the normalising cell (Tables 5-6, first row)
FIG12 = (("SR", 2, 0.4), ("DR", 4, 0.4), ("DRH", 4, 0.4), ("DRHE", 4, 0.4))
SR_CLEAN = ("SR", 2, 0.0)           # SR at its fastest period without dropouts, for comparison
# Verdicts: a percentage holds within TOL_PP percentage points of the paper's, a J4 end
# within TOL_J4 (relative) of the paper's; a trend holds when its sign does.
TOL_PP = 10.0
TOL_J4 = 0.3

# Seed 000, Tables 5-6 (Lissajous, experiments), transcribed: {(N, DP): (DRH, DRHE)}.
# (The paper's caption of Table 6 says "J_2 and J_4"; its first block is J_3.)
PAPER = {
    "J1": {(2, 0.0): (1.00, 1.05), (2, 0.2): (1.01, 1.12), (2, 0.4): (1.10, 1.23),
           (6, 0.0): (1.54, 1.97), (6, 0.2): (1.55, 1.99), (6, 0.4): (1.65, 2.10)},
    "J2": {(2, 0.0): (1.00, 1.04), (2, 0.2): (1.02, 1.11), (2, 0.4): (1.04, 1.22),
           (6, 0.0): (1.05, 1.11), (6, 0.2): (1.06, 1.17), (6, 0.4): (1.19, 1.51)},
    "J3": {(2, 0.0): (1.00, 1.01), (2, 0.2): (1.01, 1.02), (2, 0.4): (1.02, 1.05),
           (6, 0.0): (1.07, 1.11), (6, 0.2): (1.08, 1.13), (6, 0.4): (1.09, 1.15)},
    "J4": {(2, 0.0): (0.500, 0.170), (2, 0.2): (0.500, 0.188), (2, 0.4): (0.500, 0.192),
           (6, 0.0): (0.167, 0.092), (6, 0.2): (0.167, 0.093), (6, 0.4): (0.167, 0.101)},
}
INDEXES = ("J1", "J2", "J3", "J4")


def reference(settings: dict):
    """The reduced-size reference path of section 5.1."""
    return scaled(get_path(settings["path"]), settings["scale"])


def cells_of(settings: dict) -> list[tuple[str, int, float]]:
    """(case, N, dp) to compute, grouped by N (one compiled program per N)."""
    cells = {(c, int(N), float(dp)) for c in CASES for N in settings["N"] for dp in settings["dp"]}
    cells.add(BASE)
    if settings["fig12"]:
        cells |= {*FIG12, SR_CLEAN}
    return sorted(cells, key=lambda c: (c[1], mec.CASES.index(c[0]), c[2]))


def build(settings: dict, cells, truth) -> dict:
    ref = reference(settings)
    loops = {}
    for case, N, dp in cells:
        try:
            loops[(case, N, dp)] = mec.mecanum_loop(case, N, dp, ref, sigma=settings["sigma"], delta=settings["delta"],
                                                    follower_kw=dict(L_ref=settings["L_ref"]), truth=truth)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    return loops


def cell_file(out: Path, cfg: dict) -> Path:
    """``OUT/cells/<case>_N<N>_dp<DP>-<hash>.json``: the file of the cell whose
    configuration (:func:`_cell_config`) is ``cfg`` (:func:`jaxnc.sweep.cell_path`)."""
    return sweep.cell_path(Path(out) / "cells", f"{cfg['case']}_N{cfg['N']}_dp{cfg['dp']:g}", cfg)


def _cell_config(settings: dict, seeds: int, cell, loop) -> dict:
    """What a cell's result depends on (its file is named by it; a stored cell is reused
    only if it matches): the chunk and device count set the float32 rounding."""
    case, N, dp = cell
    return {"case": case, "N": N, "dp": dp, "h": horizon(loop), "steps": loop.steps, "seeds": seeds,
            "seed": settings["seed"], "plant": settings["plant"], "path": settings["path"],
            "scale": settings["scale"], "sigma": list(settings["sigma"]), "delta": list(settings["delta"]),
            "L_ref": settings["L_ref"], "chunk": settings["chunk"], "devices": len(jax.local_devices()),
            "version": _version()}


def _summary(m: mec.Metrics) -> dict:
    unstable = np.asarray(m.unstable)
    # J4: sensor packets per fast period; the nominal single-rate loop sends one per T
    rate = np.asarray(m.tx_sc, float) / np.asarray(m.l, float)
    s = {j: montecarlo.summarize(np.asarray(getattr(m, j), float), unstable).to_dict() for j in ("J1", "J2", "J3")}
    s["J4"] = montecarlo.summarize(rate, unstable).to_dict()
    s["unstable_fraction"] = float(np.mean(unstable))
    return s


def normalised(results: dict, cell) -> dict:
    """J1-J3 of a cell over the BASE cell's means, J4 as is; inf for an unstable cell."""
    s, b = results[cell], results[BASE]
    if s["unstable_fraction"] > UNSTABLE_CELL:
        return {j: INF for j in INDEXES}
    out = {j: (s[j]["mean"] / b[j]["mean"] if b["unstable_fraction"] <= UNSTABLE_CELL else INF)
           for j in ("J1", "J2", "J3")}
    out["J4"] = s["J4"]["mean"]
    return out


def table_rows(results: dict, j1: str, j2: str) -> list[list]:
    """Rows (DP, N) of Table 5 (J1, J2) or 6 (J3, J4): ours DRH, DRHE beside the paper's."""
    Ns = sorted({c[1] for c in results if c[0] in CASES})
    dps = sorted({c[2] for c in results if c[0] in CASES})
    rows = []
    for N in Ns:
        for dp in dps:
            if not all((c, N, dp) in results for c in CASES):
                continue
            row = [f"{dp:g}", str(N)]
            for j in (j1, j2):
                d = 3 if j == "J4" else 2
                ours = [normalised(results, (c, N, dp))[j] for c in CASES]
                paper = PAPER[j].get((N, dp), (None, None))
                row += [fmt(ours[0], d), fmt(ours[1], d), fmt(paper[0], d), fmt(paper[1], d)]
            rows.append(row)
    return rows


def table_md(results: dict, j1: str, j2: str) -> str:
    head = ["DP", "N"]
    for j in (j1, j2):
        head += [f"{j} DRH", f"{j} DRHE", f"{j} DRH paper", f"{j} DRHE paper"]
    return markdown_table(head, table_rows(results, j1, j2))


def absolute_md(results: dict) -> str:
    rows = []
    for cell in sorted(results, key=lambda c: (c[1], mec.CASES.index(c[0]), c[2])):
        s = results[cell]
        a = s["J1"]
        rows.append([cell[0], str(cell[1]), f"{cell[2]:g}", str(s.get("h", "")),
                     fmt(100 * a["mean"], 2) + ("" if math.isinf(a["mean"]) else " \u00b1 " + fmt(100 * a["ci95"], 2)),
                     fmt(100 * s["J2"]["mean"], 2), fmt(s["J3"]["mean"], 1), fmt(s["J4"]["mean"], 3),
                     f"{100 * s['unstable_fraction']:.1f}"])
    return markdown_table(["case", "N", "DP", "h", "J1 (cm, ± 95 %)", "J2 (cm)", "J3 (s)", "J4", "unstable %"], rows)


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else INF


def conclusions(results: dict) -> list[tuple[str, str, str, bool | None]]:
    """The section-5 conclusions: (claim, paper, ours, holds). Averages over the cells of
    Tables 5-6 (N in {2, 6}, DP in {0, 0.2, 0.4}) that this run computed; a percentage
    holds within TOL_PP points of the paper's (an increase must also be one), a J4 end
    within TOL_J4 of it, a trend
    (or "slightly worse", "similar": within 1.5x) when it goes the paper's way."""
    tab = [(N, dp) for N in TABLE_N for dp in TABLE_DP if all((c, N, dp) in results for c in CASES)]
    if not tab:
        return []
    nz = {k: normalised(results, ("DRH", *k)) for k in tab}
    ne = {k: normalised(results, ("DRHE", *k)) for k in tab}
    out = []
    paper_inc = {"J1": 16, "J2": 10, "J3": 3}
    inc = {}
    for j, p in paper_inc.items():
        pj = _mean([100 * (PAPER[j][k][1] / PAPER[j][k][0] - 1) for k in tab])
        inc[j] = _mean([100 * (ne[k][j] / nz[k][j] - 1) for k in tab])
        out.append((f"DRHE's {j} above DRH's, on average", f"+{p} % (its table cells: {pj:+.0f} %)",
                    f"{inc[j]:+.1f} %", inc[j] > 0 and abs(inc[j] - p) <= TOL_PP))
    worse = all(inc[j] >= 0 for j in inc)
    slight = all(inc[j] <= 40 for j in inc)
    out.append(("DRHE slightly worse than DRH in J1-J3 (\"acceptable deterioration\")",
                "all three up, by 3-16 %", ", ".join(f"{j} {inc[j]:+.1f} %" for j in inc), worse and slight))
    j4 = [ne[k]["J4"] for k in tab]
    lo, hi = min(j4), max(j4)
    out.append(("DRHE's J4 range over the table cells", "0.092 (N=6, DP=0) to 0.192 (N=2, DP=0.4)",
                f"{lo:.3f} to {hi:.3f}", abs(lo / 0.092 - 1) <= TOL_J4 and abs(hi / 0.192 - 1) <= TOL_J4))
    out.append(("resource saving of DRHE over nominal SR", "81-91 %", f"{100 * (1 - hi):.0f}-{100 * (1 - lo):.0f} %",
                abs(100 * (1 - hi) - 81) <= TOL_PP and abs(100 * (1 - lo) - 91) <= TOL_PP))
    for N, p in ((2, 64), (6, 46)):
        ks = [k for k in tab if k[0] == N]
        if not ks:
            continue
        sav = _mean([100 * (1 - ne[k]["J4"] / nz[k]["J4"]) for k in ks])
        out.append((f"DRHE's transmission saving over DRH at N = {N}", f"{p} %", f"{sav:.0f} %", abs(sav - p) <= TOL_PP))
    if all(("DRH", N, 0.0) in results for N in (2, 6)):
        s2, s6 = (_mean([ne[k]["J4"] / nz[k]["J4"] for k in tab if k[0] == N]) for N in (2, 6))
        out.append(("the saving over DRH shrinks as N grows", "64 % at N=2 > 46 % at N=6",
                    f"{100 * (1 - s2):.0f} % > {100 * (1 - s6):.0f} %", (1 - s2) > (1 - s6)))
    j1_up = all(nz[(6, dp)]["J1"] > nz[(2, dp)]["J1"] and ne[(6, dp)]["J1"] > ne[(2, dp)]["J1"]
                for dp in TABLE_DP if (6, dp) in nz and (2, dp) in nz)
    out.append(("J1 grows with N (DRH and DRHE, every DP)", "1.00-1.23 at N=2, 1.54-2.10 at N=6",
                ", ".join(f"N={N}: {min(nz[k]['J1'] for k in tab if k[0] == N):.2f}-"
                          f"{max(ne[k]['J1'] for k in tab if k[0] == N):.2f}" for N in TABLE_N
                          if any(k[0] == N for k in tab)), j1_up))
    dp_up = all(nz[(N, 0.4)]["J1"] >= nz[(N, 0.0)]["J1"] and ne[(N, 0.4)]["J1"] >= ne[(N, 0.0)]["J1"]
                for N in TABLE_N if (N, 0.4) in nz and (N, 0.0) in nz)
    out.append(("J1 grows with DP (DP=0.4 above DP=0, each N and case)", "yes (e.g. 1.00 -> 1.10, 1.97 -> 2.10)",
                "yes" if dp_up else "no", dp_up))
    if all(c in results for c in FIG12):
        n = {c[0]: normalised(results, c) for c in FIG12}
        sr, dr = n["SR"]["J1"], n["DR"]["J1"]
        best = max(n["DRH"]["J1"], n["DRHE"]["J1"])
        out.append(("Fig. 12 (N=4, DP=0.4): DRH and DRHE clearly outperform DR",
                    "DR on the verge of instability", f"J1 DR {fmt(dr)} vs DRH {fmt(n['DRH']['J1'])}, DRHE "
                    f"{fmt(n['DRHE']['J1'])}; DR unstable in {100 * results[FIG12[1]]['unstable_fraction']:.0f} %",
                    dr > 1.2 * best))
        out.append(("Fig. 12: DRH and DRHE similar to the fastest SR (NT = 0.2 s, same DP = 0.4)", "similar",
                    f"J1 SR {fmt(sr)} (unstable in {100 * results[FIG12[0]]['unstable_fraction']:.0f} %) vs DRH "
                    f"{fmt(n['DRH']['J1'])}, DRHE {fmt(n['DRHE']['J1'])}", math.isfinite(sr) and best <= 1.5 * sr))
        if SR_CLEAN in results:
            sr0 = normalised(results, SR_CLEAN)["J1"]
            out.append(("the same with SR at NT = 0.2 s without dropouts (DP = 0)", "similar",
                        f"J1 SR {fmt(sr0)} vs DRH {fmt(n['DRH']['J1'])}, DRHE {fmt(n['DRHE']['J1'])}",
                        math.isfinite(sr0) and best <= 1.5 * sr0))
    return out


def conclusions_md(results: dict) -> str:
    rows = [[c, p, o, "–" if h is None else ("holds" if h else "does not hold")] for c, p, o, h in conclusions(results)]
    if not rows:
        return "(none: this run has no cell of Tables 5-6 with both DRH and DRHE)"
    return markdown_table(["section-5 conclusion", "paper", "ours", "verdict"], rows)


def fig15_16(out: Path, results: dict, settings: dict) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(15, 3.8))
    Ns = sorted({c[1] for c in results if c[0] in CASES})
    colours = dict(zip(Ns, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for ax, j in zip(axes, INDEXES):
        for N in Ns:
            for case, ls, mk in (("DRH", "-", "o"), ("DRHE", "--", "s")):
                dps = sorted(c[2] for c in results if c[0] == case and c[1] == N)
                ys = [normalised(results, (case, N, dp))[j] for dp in dps]
                ys = [y if math.isfinite(y) else np.nan for y in ys]
                ax.plot(dps, ys, ls=ls, marker=mk, ms=4, color=colours[N], label=f"{case} N={N}")
                pk = [(dp, PAPER[j][(N, dp)][CASES.index(case)]) for dp in TABLE_DP if (N, dp) in PAPER[j]]
                if pk:
                    ax.plot(*zip(*pk), ls="none", marker=mk, ms=7, mfc="none", color=colours[N])
        ax.set_xlabel("DP")
        ax.set_title(j + (" (rate / nominal SR)" if j == "J4" else " / DRH(N=2, DP=0)"), fontsize=9)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle(f"Seed 000 section 5 on the {settings['plant']} plant (Figs. 15-16): lines ours, "
                 "open markers the paper's Tables 5-6; solid DRH, dashed DRHE", fontsize=10)
    f = save_figure(fig, Path(out) / "fig15_16.png", dpi=120)
    return f


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    out = Path(out)
    cache_beside(out)          # a resumed run does not compile again
    truth = true_plant(settings["plant"])
    cells = cells_of(settings)
    loops = build(settings, cells, truth)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    results, todo = {}, []
    cfgs = {cell: _cell_config(settings, seeds, cell, loops[cell]) for cell in cells}
    for cell in cells:
        cfg = cfgs[cell]
        data = sweep.load_cell(cell_file(out, cfg), cfg)
        if data is None:
            todo.append((cell, cfg))
        else:
            results[cell] = dict(data["summary"], h=cfg["h"])
    bar = tqdm(total=len(cells), initial=len(cells) - len(todo), desc="cells", unit="cell",
               disable=not progress, dynamic_ncols=True)
    for cell, cfg in todo:
        bar.set_postfix_str(f"{cell[0]} N={cell[1]} DP={cell[2]:g}")
        tc = time.perf_counter()
        m = montecarlo.run_batched(run_seed, keys, args=(montecarlo.uniform_dtypes(loops[cell]),),
                                   chunk_size=min(settings["chunk"], seeds), progress=False)
        s = _summary(m)
        sweep.save_cell(cell_file(out, cfg), {"config": cfg, "summary": s, "wall_time_s": time.perf_counter() - tc},
                        arrays={k: np.asarray(getattr(m, k)) for k in m._fields})
        results[cell] = dict(s, h=cfg["h"])
        bar.update(1)
    bar.close()
    files = []
    ref = reference(settings)
    text = [f"# Seed 000 section 5 on the {settings['plant']} plant: {seeds} seeds, "
            f"{settings['path']} x {settings['scale']:g} (length {float(ref.length):.2f} m), T = 0.1 s, NT = N T",
            "",
            "J1-J3 normalised to DRH at N = 2, DP = 0 (same seeds); J4 = sensor packets per fast period "
            "(nominal SR sends one per T). Paper: Tables 5-6 (hardware).", "",
            "## Table 5 (J1, J2)", "", table_md(results, "J1", "J2"), "",
            "## Table 6 (J3, J4)", "", table_md(results, "J3", "J4"), "",
            "## Every cell, absolute", "", absolute_md(results), "",
            "## Section-5 conclusions", "", conclusions_md(results), ""]
    tables = out / "tables.md"
    out.mkdir(parents=True, exist_ok=True)
    tables.write_text("\n".join(text), encoding="utf-8")
    files.append(tables)
    print("\n" + "\n".join(text))
    files.append(fig15_16(out, results, settings))
    if settings["fig12"]:
        f = plot_paths({f"{c} N={N} DP={dp:g}": loops[(c, N, dp)] for c, N, dp in (SR_CLEAN, *FIG12)}, keys[0], out,
                       f"{ref.name}, {settings['plant']} plant: N=4, DP=0.4; SR at NT=0.2 s (seed 0)")
        files.append(f.rename(out / "fig12_paths.png"))
    wall = time.perf_counter() - t0
    summary = {"cells": {f"{c}_N{N}_dp{dp:g}": {**results[(c, N, dp)], "normalised": normalised(results, (c, N, dp))}
                         for c, N, dp in cells},
               "conclusions": [dict(claim=c, paper=p, ours=o, holds=h) for c, p, o, h in conclusions(results)],
               "files": [str(f) for f in files],
               "per_seed": per_seed.per_seed_index(out, {c: cell_file(out, cfgs[c]).with_suffix(".npz") for c in cells},
                                                   dims=("case", "N", "dp"))}
    config = {"settings": settings, "seeds": seeds, "path_length_m": float(ref.length),
              "loops": {f"{c}_N{N}_dp{dp:g}": {"h": horizon(loops[(c, N, dp)]), "steps": loops[(c, N, dp)].steps}
                        for c, N, dp in cells}}
    montecarlo.save_results(out / "results.json", experiment="mecanum-validation", config=config,
                            results=summary, wall_time_s=wall)
    print(f"\nwrote {', '.join(str(f) for f in files)} and {out / 'results.json'} ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="mecanum-validation",
    description="Seed 000 section 5: DRH/DRHE on the MJX robot, NT = 0.2 s at N = 2, reduced path; Tables 5-6 "
                "and Figs. 12, 15-16 beside the paper's",
    options=(
        Option("plant", "choice", "mjx", "true plant: the MJX multibody robot (pip install 'jaxnc[mjx]') or "
               "the kinematic model (quick runs)", choices=("mjx", "kinematic")),
        Option("N", "ints", (2, 4, 6), "multiplicities (NT = N x 0.1 s)", low=1, high=20),
        Option("dp", "floats", (0.0, 0.1, 0.2, 0.3, 0.4), "dropout probabilities DP = p_sc = p_ca", low=0.0, high=0.95),
        Option("path", "choice", "lissajous", "reference path (section 4's, then scaled)", choices=tuple(PATHS)),
        Option("scale", "float", 0.5, "size of the reduced reference relative to section 4's path", low=0.05, high=1.0),
        Option("fig12", "bool", True, "also the Fig. 12 cells (SR N=2, DR N=4 at DP=0.4) and the path figure"),
        Option("sigma", "floats", mec.DEFAULT_SIGMA, "PETC sigma(i): 1 or 9 values", low=0.0, high=10.0),
        Option("delta", "floats", mec.PAPER_DELTA, "PETC delta(i): 1 or 9 values", low=0.0, high=100.0),
        Option("L_ref", "float", LOOKAHEAD, "pure-pursuit look-ahead distance, m", low=0.01, high=2.0),
        Option("chunk", "int", 256, "seeds per compiled batch", low=1, high=100_000),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
    keeps_cells=True,
))
