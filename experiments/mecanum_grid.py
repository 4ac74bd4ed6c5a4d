"""Experiment ``mecanum-grid``: seed 000 in full -- Tables 1-4 and Figs 7-10.

Every case (SR, DR, DRH, DRHE) x N x DP x path, ``--seeds`` Monte-Carlo runs per
cell (1000 by default), event parameters of section 4.1 and h by the rule of
``schemes.mecanum.default_h``.

* **Resumable.** Each cell is written to ``OUT/cells/<path>/N<NN>_<case>_dp<DP>-<hash>.json``
  (with its per-seed indexes in a ``.npz`` beside it) atomically, as soon as it is
  done; a rerun with the same settings computes only the missing cells. ``<hash>`` is
  :func:`jaxnc.sweep.config_hash` of the cell's whole configuration, so cells whose
  settings differ anywhere (``dp=0.1`` and ``dp=0.104``) are distinct files.
* **Across machines.** ``--shard I/N`` computes only shard I's share of the cells
  (:mod:`jaxnc.sweep`) into the shared ``OUT``; the run that finds every cell present
  (a shard, or a run without ``--shard``) writes the outputs, the same bytes however
  the cells were split.
* **One compiled program per (path, N).** The scheme, h and DP are runtime arguments
  (``run_batched(..., args=(loop,))``), so the four cases and all DPs of an N share
  one compilation; the next (path, N)'s program compiles in a thread while this one's
  cells run (:func:`jaxnc.montecarlo.precompile`); compiled programs are also cached on
  disk under ``OUT/.xla_cache`` so a resumed run does not compile again.
* **Outputs** (rewritten from all cells at the end, so they are the same however many
  times the run was interrupted): ``tables_<path>.md`` / ``tables_<path>.csv`` in the
  paper's layout (rows DP x N in {1, 2, 6, 12}, columns SR/DR/DRH/DRHE, J1-J3
  normalised to the nominal SR run of the same path, J4 the sensor transmission rate
  over nominal, inf for unstable cells, "-" where the paper has none), the whole
  grid as ``grid_<path>.csv``, heat maps ``fig_<path>.png`` (Figs 7-10: each index
  over (N, DP) for each case), and ``paper_comparison.md`` (Lissajous: ours beside
  Tables 1-4, cell by cell). ``results.json`` lists the cells' per-seed files, so
  :func:`jaxnc.load` gives the whole grid as one Dataset (path, N, case, dp, seed).

A cell is infinite when more than half of its runs are unstable (``UNSTABLE_CELL``);
a run is unstable when the robot leaves the 0.5 m tube around the path, a state
becomes non-finite, or it does not reach the end within 1.6 x the nominal time + 10 s.
"""
from __future__ import annotations

import csv
import itertools
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
from jaxnc.paths import PATHS
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import mecanum as mec

from .mecanum import UNSTABLE_CELL, horizon, run_seed

INF = math.inf
GRID_N = tuple(range(1, 13))
GRID_DP = tuple(round(0.1 * i, 1) for i in range(8))
TABLE_N = (1, 2, 6, 12)
TABLE_DP = (0.0, 0.2, 0.4, 0.6)
INDEXES = ("J1", "J2", "J3", "J4")


def _paper(rows):
    """{(dp, N): (SR, DR, DRH, DRHE)} from rows in the paper's order (DP inner, N outer)."""
    keys = [(dp, n) for n in TABLE_N for dp in TABLE_DP]
    return dict(zip(keys, rows))


_ = None   # "-": no value in the paper (dual-rate cases at N = 1)
# Seed 000, Tables 1-4 (Lissajous curve), transcribed; inf is the paper's infinity.
PAPER = {
    "J1": _paper([
        (1.00, _, _, _), (1.15, _, _, _), (1.57, _, _, _), (INF, _, _, _),
        (1.07, 0.83, 0.83, 1.01), (1.80, 0.86, 0.85, 1.10), (INF, 1.08, 0.93, 1.15), (INF, 2.15, 1.03, 1.37),
        (INF, 0.85, 0.85, 1.03), (INF, 1.12, 0.86, 1.09), (INF, 1.98, 1.19, 1.40), (INF, INF, 1.61, 1.89),
        (INF, 1.02, 1.02, 1.10), (INF, 1.56, 1.23, 1.28), (INF, 3.32, 1.48, 1.73), (INF, INF, INF, INF)]),
    "J2": _paper([
        (1.00, _, _, _), (1.20, _, _, _), (1.40, _, _, _), (INF, _, _, _),
        (1.10, 0.56, 0.56, 0.58), (2.28, 0.58, 0.57, 0.70), (INF, 1.69, 0.58, 0.81), (INF, 2.80, 0.73, 1.21),
        (INF, 0.65, 0.65, 0.72), (INF, 1.22, 0.68, 0.84), (INF, 2.90, 1.11, 1.29), (INF, INF, 1.15, 1.53),
        (INF, 0.68, 0.68, 0.70), (INF, 2.11, 1.17, 1.27), (INF, 3.20, 1.33, 1.55), (INF, INF, INF, INF)]),
    "J3": _paper([
        (1.00, _, _, _), (1.01, _, _, _), (1.02, _, _, _), (INF, _, _, _),
        (1.02, 1.01, 1.01, 1.03), (1.03, 1.02, 1.01, 1.04), (INF, 1.03, 1.02, 1.07), (INF, 1.25, 1.03, 1.08),
        (INF, 1.03, 1.03, 1.04), (INF, 1.05, 1.03, 1.05), (INF, 1.40, 1.04, 1.07), (INF, INF, 1.04, 1.10),
        (INF, 1.04, 1.04, 1.05), (INF, 1.14, 1.05, 1.07), (INF, 1.51, 1.05, 1.08), (INF, INF, INF, INF)]),
    "J4": _paper([
        (1.000, _, _, _), (1.000, _, _, _), (1.000, _, _, _), (INF, _, _, _),
        (0.500, 0.500, 0.500, 0.119), (0.500, 0.500, 0.500, 0.124), (INF, 0.500, 0.500, 0.129),
        (INF, 0.500, 0.500, 0.132),
        (INF, 0.167, 0.167, 0.099), (INF, 0.167, 0.167, 0.102), (INF, 0.167, 0.167, 0.105),
        (INF, INF, 0.167, 0.108),
        (INF, 0.083, 0.083, 0.067), (INF, 0.083, 0.083, 0.068), (INF, 0.083, 0.083, 0.069),
        (INF, INF, INF, INF)]),
}
del _


# ----------------------------------------------------------------------------- cells


def cell_file(out: Path, cfg: dict) -> Path:
    """The file of the cell whose configuration (:func:`_cell_config`) is ``cfg``."""
    return sweep.cell_path(Path(out) / "cells" / cfg["path"], f"N{cfg['N']:02d}_{cfg['case']}_dp{cfg['dp']:g}", cfg)


def plan(settings: dict, seeds: int) -> tuple[list, dict, dict]:
    """(cells, {cell: loop}, {cell: configuration}) of the grid; ConfigError for a cell
    whose loop cannot be built."""
    cells, loops, cfgs = grid_cells(settings), {}, {}
    for cell in cells:
        p, N, case, dp = cell
        try:
            loops[cell] = mec.mecanum_loop(case, N, dp, p, sigma=settings["sigma"], delta=settings["delta"],
                                           follower_kw=dict(L_ref=settings["L_ref"]))
        except ValueError as e:
            raise ConfigError(str(e)) from None
        cfgs[cell] = _cell_config(settings, seeds, case, N, dp, p, horizon(loops[cell]))
    return cells, loops, cfgs


def cell_files(out: Path, settings: dict, seeds: int) -> dict:
    """{(path, N, case, dp): cell file} of the grid that ``settings`` and ``seeds`` make."""
    _, _, cfgs = plan(settings, seeds)
    return {cell: cell_file(out, cfg) for cell, cfg in cfgs.items()}


def _cell_config(settings: dict, seeds: int, case: str, N: int, dp: float, path: str, h: int) -> dict:
    """What a cell's result depends on; a stored cell is reused only if this matches."""
    return {"case": case, "N": N, "dp": dp, "path": path, "h": h, "seeds": seeds, "seed": settings["seed"],
            "chunk": settings["chunk"], "sigma": list(settings["sigma"]), "delta": list(settings["delta"]),
            "L_ref": settings["L_ref"],
            "devices": len(jax.local_devices()), "version": _version()}


def _version() -> str:
    from jaxnc import __version__
    return __version__


def _load_cell(f: Path, config: dict) -> dict | None:
    # cells written before the device count was recorded ran on one device
    return sweep.load_cell(f, config, defaults={"devices": 1})


def _summary(m: mec.Metrics) -> dict:
    unstable = np.asarray(m.unstable)
    rate = np.asarray(m.tx_sc, float) / np.asarray(m.l, float)
    s = {j: montecarlo.summarize(np.asarray(getattr(m, j), float), unstable).to_dict() for j in ("J1", "J2", "J3")}
    s["rate_sc"] = montecarlo.summarize(rate, unstable).to_dict()
    s["tx_sc_mean"] = float(np.mean(m.tx_sc))
    s["tx_ca_mean"] = float(np.mean(m.tx_ca))
    s["unstable_fraction"] = float(np.mean(unstable))
    return s


def grid_cells(settings: dict) -> list[tuple[str, int, str, float]]:
    """(path, N, case, dp) of the requested grid plus each path's nominal SR cell,
    ordered by (path, N) so a compiled program serves a whole group."""
    paths = tuple(PATHS) if settings["path"] == "all" else (settings["path"],)
    cases = mec.CASES if settings["case"] == "all" else (settings["case"],)
    cells = []
    for p in paths:
        group = {(p, 1, "SR", 0.0)}
        group |= {(p, int(N), c, float(dp)) for N in settings["N"] for c in cases for dp in settings["dp"]}
        cells += sorted(group, key=lambda c: (c[1], mec.CASES.index(c[2]), c[3]))
    return cells


def run_grid(settings: dict, *, seeds: int, out: Path, progress: bool = True, stop_after: int | None = None,
             shard: sweep.Shard | None = None) -> dict:
    """Compute the missing cells (only ``shard``'s share of them if given; at most
    ``stop_after`` of them: a controlled interruption, for tests), then, if every cell of
    the grid is stored (by this run or any other), write tables and figures from them."""
    out = Path(out)
    cells, loops, cfgs = plan(settings, seeds)
    mine = set(shard.share(cells)) if shard is not None else set(cells)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    todo = [(cell, cfgs[cell]) for cell in cells
            if cell in mine and _load_cell(cell_file(out, cfgs[cell]), cfgs[cell]) is None]
    done_before = len(mine) - len(todo)
    computed = 0
    t0 = time.perf_counter()
    bar = tqdm(total=len(mine), initial=done_before, desc="cells" if shard is None else f"cells of shard {shard}",
               unit="cell", disable=not progress, dynamic_ncols=True)
    chunk = min(settings["chunk"], seeds)
    if stop_after is not None:
        todo = todo[:max(stop_after, 0)]
    # one compiled program per (path, N), the order of grid_cells: the next group's program is
    # traced and handed to a compiling thread before this group's cells run
    groups = [list(g) for _, g in itertools.groupby(todo, key=lambda t: t[0][:2])]
    program = lambda group: (run_seed, (montecarlo.uniform_dtypes(loops[group[0][0]]),))
    try:
        for g, group in enumerate(groups):
            montecarlo.precompile([program(x) for x in groups[(g + 1 if g else 0):g + 2]], keys,
                                  chunk_size=chunk, wait=False)
            for cell, cfg in group:
                p, N, case, dp = cell
                bar.set_postfix_str(f"{p} N={N} {case} DP={dp:g}")
                tc = time.perf_counter()
                m = montecarlo.run_batched(run_seed, keys, args=(montecarlo.uniform_dtypes(loops[cell]),),
                                           chunk_size=chunk, progress=False)
                wall = time.perf_counter() - tc
                sweep.save_cell(cell_file(out, cfg), {"config": cfg, "summary": _summary(m), "wall_time_s": wall},
                                arrays={k: np.asarray(getattr(m, k)) for k in m._fields})
                computed += 1
                bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        print(f"\ninterrupted: {done_before + computed} of {len(mine)} cells are saved in {out / 'cells'}; "
              "run the same command again to compute the rest", flush=True)
        raise SystemExit(130) from None
    bar.close()
    elapsed = time.perf_counter() - t0
    with sweep.assembly_lock(out):
        results = collect(out, cfgs)      # this run's cells and other shards'
        complete = len(results) == len(cells)
        written = write_outputs(out, results, settings) if complete else []
    # this run's counts and time, and the totals over every run that stored a cell (a resume
    # that only reuses cells computes 0 in 0 s, but the grid's cells took their time)
    summary = {"cells": len(cells), "computed": computed, "reused": done_before, "complete": complete,
               "wall_time_s": elapsed, "stored": len(results),
               "compute_time_total_s": float(sum(r.get("compute_s") or 0.0 for r in results.values())),
               "meaning": "computed, reused, wall_time_s: this run; stored, compute_time_total_s: all the "
                          "stored cells of this grid, whichever run (or shard) computed them",
               "files": [str(f) for f in written],
               # the stored cells of this configuration, for jaxnc.load
               "per_seed": per_seed.per_seed_index(out, {c: cell_file(out, cfgs[c]).with_suffix(".npz")
                                                         for c in results}, dims=("path", "N", "case", "dp"),
                                                        units=mec.Metrics.UNITS)}
    montecarlo.save_results(out / "results.json", experiment="mecanum-grid",
                            config={"settings": settings, "seeds": seeds}, results=summary, wall_time_s=elapsed)
    print(f"\n{computed} cells computed, {done_before} reused, in {elapsed:.1f} s")
    if not complete:
        missing = [c for c in cells if c not in results]
        if done_before + computed < len(mine):
            print(f"{len(mine) - done_before - computed} cells of this run missing: rerun to finish")
        else:
            print(sweep.missing_report(cells, missing, shard, describe=lambda c: f"{c[0]} N={c[1]} {c[2]} DP={c[3]:g}"))
    return summary


# ----------------------------------------------------------------------------- tables


def collect(out: Path, cfgs: dict) -> dict:
    """{(path, N, case, dp): summary dict} of the stored cells of this grid (``cfgs``:
    each cell's configuration, :func:`plan`)."""
    res = {}
    for cell, cfg in cfgs.items():
        data = _load_cell(cell_file(out, cfg), cfg)
        if data is not None:
            res[cell] = dict(data["summary"], h=cfg["h"], compute_s=data.get("wall_time_s"))
    return res


def normalised(results: dict, cell) -> dict:
    """J1-J4 of a cell as in the paper: ratio of means to the nominal SR cell of the
    path, J4 the ratio of sensor transmission rates; inf for an unstable cell."""
    p = cell[0]
    nom = results[(p, 1, "SR", 0.0)]
    s = results[cell]
    if s["unstable_fraction"] > UNSTABLE_CELL:
        return {j: INF for j in INDEXES}
    out = {j: s[j]["mean"] / nom[j]["mean"] for j in ("J1", "J2", "J3")}
    out["J4"] = s["rate_sc"]["mean"] / nom["rate_sc"]["mean"]
    return out


def _table_value(results, p, N, case, dp, paper: bool = True):
    if paper and N == 1 and case != "SR":
        return None                      # the paper has "-" there
    cell = (p, N, case, dp)
    return normalised(results, cell) if cell in results else None


def table_layout(results: dict, p: str) -> tuple[list[tuple[int, float]], tuple[str, ...], bool]:
    """(rows (N, DP), columns (cases), paper) of path ``p``'s tables: the paper's Tables 1-4
    (rows N in TABLE_N x DP in TABLE_DP, the four cases; ``paper`` True) when this grid
    computed all of them, as the default grid does; otherwise the (N, DP) and the cases
    this grid computed (a custom grid shows what it ran, not the paper's rows)."""
    cells = [c for c in results if c[0] == p]
    computed = {(c[1], c[3]) for c in cells}
    cases = tuple(c for c in mec.CASES if any(cell[2] == c for cell in cells))
    paper_rows = [(N, dp) for N in TABLE_N for dp in TABLE_DP]
    if cases == mec.CASES and all(r in computed for r in paper_rows):
        return paper_rows, cases, True
    return sorted(computed), cases, False


def paper_tables(results: dict, p: str) -> tuple[str, list[list]]:
    """Markdown and CSV rows of path ``p``'s tables, laid out by :func:`table_layout`
    (the paper's Tables 1-4 for the default grid, the computed rows otherwise)."""
    rows_nd, cases, paper = table_layout(results, p)
    md, rows = [], []
    for j in INDEXES:
        body = []
        for N, dp in rows_nd:
            vals = [_table_value(results, p, N, c, dp, paper) for c in cases]
            cells = [fmt(v[j], 3 if j == "J4" else 2) if v is not None else "\u2013" for v in vals]
            body.append([f"{dp:.1f}" if paper or round(dp, 1) == dp else f"{dp:g}", str(N), *cells])
            rows.append([j, dp, N, *[("" if v is None else v[j]) for v in vals]])
        md.append(f"**{j}** ({p})\n\n" + markdown_table(["DP", "N", *cases], body))
    return "\n\n".join(md), rows


def comparison(results: dict, p: str = "lissajous") -> str:
    """Ours beside the paper's Tables 1-4, cell by cell, with the ratio ours / paper: the
    rows of Tables 1-4 that this grid computed (all of them for the default grid)."""
    computed = {(c[1], c[3]) for c in results if c[0] == p}
    rows_nd = [(N, dp) for N in TABLE_N for dp in TABLE_DP if (N, dp) in computed]
    if not rows_nd:
        return (f"No cell of this grid is in Tables 1-4 (their rows are N in {{{', '.join(map(str, TABLE_N))}}} "
                f"x DP in {{{', '.join(f'{d:g}' for d in TABLE_DP)}}}).")
    parts = []
    for j in INDEXES:
        body = []
        for N, dp in rows_nd:
            row = [f"{dp:.1f}", str(N)]
            for i, c in enumerate(mec.CASES):
                ours = _table_value(results, p, N, c, dp)
                paper = PAPER[j][(dp, N)][i]
                d = 3 if j == "J4" else 2
                if ours is None or paper is None:
                    row.append("\u2013")
                    continue
                o = ours[j]
                ratio = "" if (math.isinf(o) or math.isinf(paper)) else f" ({o / paper:.2f}\u00d7)"
                row.append(f"{fmt(o, d)} vs {fmt(paper, d)}{ratio}")
            body.append(row)
        parts.append(f"**{j}**: ours vs paper (ours / paper)\n\n" + markdown_table(["DP", "N", *mec.CASES], body))
    return "\n\n".join(parts)


def trend_checks(results: dict, p: str) -> list[tuple[str, bool, list[str]]]:
    """The paper's qualitative findings (section 4.3), checked on every grid cell of
    path ``p``: (statement, holds, exceptions). A J1 decrease between neighbouring DPs
    counts as an exception only when it exceeds the two cells' 95 % intervals."""
    cells = {c: normalised(results, c) for c in results if c[0] == p}
    Ns = sorted({c[1] for c in cells})
    dps = sorted({c[3] for c in cells})
    get = lambda N, case, dp: cells.get((p, N, case, dp))
    checks = []
    ex = [f"N={N} DP={dp:.1f}" for N in Ns if N >= 6 for dp in dps
          if get(N, "SR", dp) is not None and not math.isinf(get(N, "SR", dp)["J1"])]
    checks.append(("SR is unstable for N >= 6", not ex, ex))
    ex = []
    for N in (n for n in Ns if n >= 2):
        for dp in (d for d in dps if d >= 0.2 - 1e-9):
            a, b = get(N, "DR", dp), get(N, "DRH", dp)
            if a is not None and b is not None and not a["J1"] > b["J1"]:
                ex.append(f"N={N} DP={dp:.1f}: DR {fmt(a['J1'])} vs DRH {fmt(b['J1'])}")
    checks.append(("DR is worse (J1) than DRH for DP >= 0.2 at every N >= 2", not ex, ex))
    ex = []
    for N in (n for n in Ns if n >= 2):
        for dp in dps:
            e, h = get(N, "DRHE", dp), get(N, "DRH", dp)
            if e is None or math.isinf(e["J4"]):
                continue
            if not 0.05 <= e["J4"] <= 0.2 or (h is not None and not e["J4"] < h["J4"]):
                ex.append(f"N={N} DP={dp:.1f}: DRHE J4 {e['J4']:.3f}, DRH {fmt(h['J4'], 3) if h else '-'}")
    checks.append(("DRHE J4 is within [0.05, 0.2] and below DRH's (stable cells, N >= 2)", not ex, ex))
    ex = []
    for case in mec.CASES:
        for N in Ns:
            for d0, d1 in zip(dps, dps[1:]):
                a, b = (p, N, case, d0), (p, N, case, d1)
                if a not in cells or b not in cells or math.isinf(cells[a]["J1"]):
                    continue
                if math.isinf(cells[b]["J1"]):
                    continue            # unstable at the higher DP: grows
                nom = results[(p, 1, "SR", 0.0)]["J1"]["mean"]
                ci = (results[a]["J1"]["ci95"] + results[b]["J1"]["ci95"]) / nom
                if cells[b]["J1"] < cells[a]["J1"] - (ci if math.isfinite(ci) else 0.0):
                    ex.append(f"{case} N={N}: DP {d0:.1f} -> {d1:.1f}: {cells[a]['J1']:.3f} -> {cells[b]['J1']:.3f}")
    checks.append(("for a fixed case and N, J1 grows with DP (beyond the 95 % intervals)", not ex, ex))
    return checks


def trends_markdown(results: dict, p: str) -> str:
    lines = [f"**Trends of the paper, {p}**", ""]
    for statement, holds, ex in trend_checks(results, p):
        lines.append(f"- {'holds' if holds else 'FAILS'}: {statement}"
                     + ("" if holds else f" ({len(ex)} exceptions: " + "; ".join(ex[:8])
                                          + ("; ..." if len(ex) > 8 else "") + ")"))
    return "\n".join(lines)


def write_outputs(out: Path, results: dict, settings: dict) -> list[Path]:
    files = []
    paths = sorted({c[0] for c in results}, key=lambda p: tuple(PATHS).index(p))
    for p in paths:
        md, rows = paper_tables(results, p)
        _, cases, paper = table_layout(results, p)
        f = out / f"tables_{p}.md"
        f.write_text(f"# Seed 000, {p}: {_table_title(paper)}\n\n{md}\n\n{trends_markdown(results, p)}\n")
        files.append(f)
        f = out / f"tables_{p}.csv"
        with open(f, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["index", "DP", "N", *cases])
            w.writerows(rows)
        files.append(f)
        f = out / f"grid_{p}.csv"
        with open(f, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["path", "N", "DP", "case", "h", *INDEXES, "J1_abs_m", "J1_abs_ci95_m", "unstable_fraction"])
            for cell in sorted((c for c in results if c[0] == p), key=lambda c: (mec.CASES.index(c[2]), c[1], c[3])):
                s, n = results[cell], normalised(results, cell)
                w.writerow([p, cell[1], cell[3], cell[2], s["h"], *[n[j] for j in INDEXES],
                            s["J1"]["mean"], s["J1"]["ci95"], s["unstable_fraction"]])
        files.append(f)
        files.append(heatmaps(out, results, p))
    if "lissajous" in paths:
        f = out / "paper_comparison.md"
        f.write_text("# Seed 000, Lissajous: ours vs the paper's Tables 1-4\n\n" + comparison(results) + "\n")
        files.append(f)
    for p in (("lissajous",) if "lissajous" in paths else paths):     # stdout: what the files show
        if not table_layout(results, p)[2]:
            print(f"\n{p}: {_table_title(False)}")
        print("\n" + paper_tables(results, p)[0])
    return files


def _table_title(paper: bool) -> str:
    if paper:
        return "Tables 1-4 (J normalised to nominal SR; \u221e unstable)"
    return ("the N and DP this grid computed (J normalised to nominal SR; \u221e unstable; "
            "\u2013 not computed; the paper's Tables 1-4 have N in {1, 2, 6, 12} x DP in {0, 0.2, 0.4, 0.6})")


def heatmaps(out: Path, results: dict, p: str) -> Path:
    """Figs 7-10: each index over (N, DP) for each case; unstable cells dark grey."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    Ns = sorted({c[1] for c in results if c[0] == p})
    dps = sorted({c[3] for c in results if c[0] == p})
    fig, axes = plt.subplots(len(INDEXES), len(mec.CASES), figsize=(3.2 * len(mec.CASES), 2.6 * len(INDEXES)),
                             squeeze=False)
    fig.subplots_adjust(left=0.05, right=0.97, bottom=0.06, top=0.93, wspace=0.3, hspace=0.45)
    norms = {"J1": LogNorm(0.5, 10.0), "J2": LogNorm(0.3, 10.0), "J3": LogNorm(0.9, 1.6), "J4": LogNorm(0.02, 1.0)}
    for r, j in enumerate(INDEXES):
        im = None
        for c, case in enumerate(mec.CASES):
            ax = axes[r, c]
            grid = np.full((len(dps), len(Ns)), np.nan)
            for a, dp in enumerate(dps):
                for b, N in enumerate(Ns):
                    if (p, N, case, dp) in results:
                        grid[a, b] = normalised(results, (p, N, case, dp))[j]
            unstable = np.isinf(grid)
            ext = (-0.5, len(Ns) - 0.5, -0.5, len(dps) - 0.5)     # index space: any N / DP lists
            ax.imshow(np.where(unstable, 1.0, np.nan), cmap="Greys", vmin=0, vmax=1.4, origin="lower",
                      aspect="auto", extent=ext)
            im = ax.imshow(np.where(unstable, np.nan, grid), cmap="viridis", norm=norms[j], origin="lower",
                           aspect="auto", extent=ext)
            step = max(1, len(Ns) // 6)
            ax.set_xticks(range(0, len(Ns), step), [str(n) for n in Ns[::step]])
            ax.set_yticks(range(len(dps)), [f"{d:.1f}" if round(d, 1) == d else f"{d:g}" for d in dps], fontsize=7)
            ax.set_title(f"{j} {case}", fontsize=9)
            if r == len(INDEXES) - 1:
                ax.set_xlabel("N")
            if c == 0:
                ax.set_ylabel("DP")
        fig.colorbar(im, ax=axes[r, :].tolist(), shrink=0.9, label=f"{j} (grey: unstable)")
    fig.suptitle(f"Seed 000, {p}: cost indexes over (N, DP) (Figs 7-10; normalised to nominal SR)")
    f = save_figure(fig, out / f"fig_{p}.png", dpi=110, tight=False)
    return f


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True, shard: sweep.Shard | None = None) -> dict:
    cache_beside(out)          # a resumed run does not compile again
    return run_grid(settings, seeds=seeds, out=out, progress=progress, shard=shard)


EXPERIMENT = register(Experiment(
    name="mecanum-grid",
    description="Seed 000 in full: SR/DR/DRH/DRHE x N x DP x path, Tables 1-4 and Figs 7-10 (resumable)",
    options=(
        Option("case", "choice", "all", "schemes to run", choices=(*mec.CASES, "all")),
        Option("N", "ints", GRID_N, "multiplicities", low=1, high=20),
        Option("dp", "floats", GRID_DP, "dropout probabilities DP = p_sc = p_ca", low=0.0, high=0.95),
        Option("path", "choice", "all", "reference path", choices=(*PATHS, "all")),
        Option("sigma", "floats", mec.DEFAULT_SIGMA, "PETC sigma(i): 1 or 9 values (paper 4.1: 0.1 x4, 0.05 x5; see README)", low=0.0, high=10.0),
        Option("delta", "floats", mec.PAPER_DELTA, "PETC delta(i): 1 or 9 values", low=0.0, high=100.0),
        Option("L_ref", "float", LOOKAHEAD, "pure-pursuit look-ahead distance, m", low=0.01, high=2.0),
        Option("chunk", "int", 1000, "seeds per compiled batch (memory vs speed)", low=1, high=100_000),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
    keeps_cells=True,
))
