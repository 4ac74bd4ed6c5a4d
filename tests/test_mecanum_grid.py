"""The seed-000 grid experiment: resumable cell by cell, identical tables after an interruption."""

import json

import numpy as np
import pytest

from experiments import mecanum_grid as mg
from jaxnc import montecarlo
from jaxnc.experiment import get_experiment

# N = 1: every cell of this grid (the nominal SR cell too) runs on one compiled program, the one
# test_close_dps_... uses as well; what these tests check (resume, identical tables) does not depend on N
SETTINGS = dict(get_experiment("mecanum-grid").defaults(), path="turn180", N=(1,), dp=(0.0, 0.3), chunk=4)


def _outputs(out):
    return {f.name: f.read_bytes() for f in sorted(out.glob("tables_*")) + sorted(out.glob("grid_*"))}


def test_interrupted_grid_resumes_and_gives_identical_tables(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    cells = mg.grid_cells(SETTINGS)
    assert len(cells) == 4 * 2                # 4 cases x 2 DP, the nominal SR cell among them
    first = mg.run_grid(SETTINGS, seeds=4, out=a, progress=False, stop_after=3)   # "interrupted"
    assert (first["computed"], first["complete"]) == (3, False)
    assert not list(a.glob("tables_*"))       # no tables from an incomplete grid
    second = mg.run_grid(SETTINGS, seeds=4, out=a, progress=False)
    assert (second["computed"], second["reused"], second["complete"]) == (len(cells) - 3, 3, True)
    fresh = mg.run_grid(SETTINGS, seeds=4, out=b, progress=False)
    assert fresh["computed"] == len(cells)
    assert _outputs(a) == _outputs(b) and _outputs(a)
    # nothing left to do; a damaged cell file counts as missing and is recomputed
    assert mg.run_grid(SETTINGS, seeds=4, out=a, progress=False)["computed"] == 0
    # a resume that only reuses cells keeps the grid's totals (finding 9 of issue 25: it
    # wrote computed 0, wall_time_s 0.0 as if that were the grid's)
    from jaxnc.montecarlo import load_results
    r = load_results(a / "results.json")["results"]
    assert (r["computed"], r["reused"], r["stored"]) == (0, len(cells), len(cells))
    cell_times = [json.loads(f.read_text())["wall_time_s"] for f in (a / "cells").rglob("*.json")]
    assert len(cell_times) == len(cells) and r["compute_time_total_s"] == pytest.approx(sum(cell_times))
    assert r["compute_time_total_s"] > 0 and "this run" in r["meaning"]
    # cell files get the same mode as results.json (they were 0600 from mkstemp)
    modes = {f.name: f.stat().st_mode & 0o777 for f in [a / "results.json", *(a / "cells").rglob("*.*")]}
    assert len(set(modes.values())) == 1, modes
    f = mg.cell_files(a, SETTINGS, 4)[("turn180", 1, "DRH", 0.3)]
    f.write_text('{"config": ')
    assert mg.run_grid(SETTINGS, seeds=4, out=a, progress=False)["computed"] == 1
    assert _outputs(a) == _outputs(b)
    # a cell computed with other settings is not reused
    other = dict(SETTINGS, delta=(0.2,))
    assert mg.run_grid(other, seeds=4, out=a, progress=False, stop_after=0)["reused"] == 0
    assert not list(a.rglob("*.tmp"))


def test_each_groups_program_compiles_ahead_while_the_previous_group_runs(tmp_path, monkeypatch):
    """run_grid hands the next (path, N) group's program to precompile (wait=False) before this
    group's cells run, each group's once, in the cells' order; the runs themselves faked (no XLA)."""
    from jaxnc.schemes import mecanum as mec
    settings = dict(SETTINGS, path="all", N=(2, 3), dp=(0.0,), case="DRHE")
    cells, loops, _ = mg.plan(settings, 4)
    name = {(lp.steps, lp.N): cell[:2] for cell, lp in loops.items()}     # a path's horizon is its own
    assert len(name) == len({c[:2] for c in cells})
    events = []
    monkeypatch.setattr(montecarlo, "precompile", lambda calls, keys, *, chunk_size, wait: events.append(
        ("compile", [name[a[0].steps, a[0].N] for _, a in calls], chunk_size, wait)))

    def fake_run(fn, keys, *, args, chunk_size, progress):
        events.append(("run", *name[args[0].steps, args[0].N]))
        z = np.ones(len(keys), np.float32)
        return mec.Metrics(z, z, z, z, z, z, z < 0)
    monkeypatch.setattr(montecarlo, "run_batched", fake_run)
    mg.run_grid(settings, seeds=4, out=tmp_path, progress=False, stop_after=5)
    groups = [c[:2] for c in cells[:5]]           # one cell per (path, N) here: the nominal SR cell at N = 1
    assert len(set(groups)) == 5 and len({g[0] for g in groups}) == 2
    compiles = [e for e in events if e[0] == "compile"]
    assert [c[1] for c in compiles] == [groups[:2], [groups[2]], [groups[3]], [groups[4]], []]
    assert {(c[2], c[3]) for c in compiles} == {(4, False)}
    # a group's program is handed over before its first cell runs, the next one's before the group runs
    order = [e[1:] if e[0] == "run" else ("compile", *e[1]) for e in events]
    for g in groups:
        assert min(i for i, e in enumerate(order) if e[0] == "compile" and g in e[1:]) < order.index(g)
    assert [e for e in order if e[0] != "compile"] == groups     # stop_after=5: the first five cells


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "cell.json"

    def boom(fh):
        fh.write(b"{partial")
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        montecarlo.atomic_write(target, boom)
    assert not target.exists() and not list(tmp_path.iterdir())


def test_tables_show_paper_layout_and_infinity():
    res = {("lissajous", 1, "SR", 0.0): {"J1": {"mean": 0.04}, "J2": {"mean": 0.1}, "J3": {"mean": 50.0},
                                         "rate_sc": {"mean": 1.0}, "unstable_fraction": 0.0, "h": 1}}
    for N in mg.TABLE_N:                   # the paper's rows are all computed: the paper's layout
        for dp in mg.TABLE_DP:
            for c in mg.mec.CASES:
                if (N, c, dp) not in ((1, "SR", 0.0), (2, "SR", 0.2), (2, "DRHE", 0.2)):
                    res[("lissajous", N, c, dp)] = dict(res[("lissajous", 1, "SR", 0.0)])
    res[("lissajous", 2, "DR", 0.2)] = dict(res[("lissajous", 1, "SR", 0.0)], unstable_fraction=0.6)
    res[("lissajous", 2, "DRH", 0.2)] = {"J1": {"mean": 0.05}, "J2": {"mean": 0.1}, "J3": {"mean": 51.0},
                                        "rate_sc": {"mean": 0.5}, "unstable_fraction": 0.1, "h": 3}
    md, rows = mg.paper_tables(res, "lissajous")
    row = [r for r in md.split("**J1**")[1].splitlines() if r.startswith("| 0.2 |  2 |")][0]
    assert [c.strip() for c in row.strip("|").split("|")] == ["0.2", "2", "\u2013", "\u221e", "1.25", "\u2013"]
    j4 = [r for r in rows if r[0] == "J4" and r[1] == 0.2 and r[2] == 2][0]
    assert j4[3:] == ["", np.inf, 0.5, ""]
    cmp = mg.comparison(res)
    assert "1.25 vs 0.85 (1.47\u00d7)" in cmp           # ours vs Table 1 DRH at N = 2, DP = 0.2


def test_trend_checks_find_violations():
    def cell(J1, rate=0.5, unstable=0.0, ci=0.0):
        return {"J1": {"mean": J1, "ci95": ci}, "J2": {"mean": J1}, "J3": {"mean": 50.0},
                "rate_sc": {"mean": rate}, "unstable_fraction": unstable, "h": 1}
    p = "turn180"
    res = {(p, 1, "SR", 0.0): cell(0.04, rate=1.0)}
    for dp, j in ((0.0, 0.04), (0.2, 0.05), (0.4, 0.045)):         # DRH: a drop 0.05 -> 0.045
        res[(p, 6, "SR", dp)] = cell(1.0, unstable=1.0)
        res[(p, 6, "DR", dp)] = cell(2 * j)
        res[(p, 6, "DRH", dp)] = cell(j, rate=1 / 6)
        res[(p, 6, "DRHE", dp)] = cell(1.1 * j, rate=0.1)
    res[(p, 6, "SR", 0.2)] = cell(0.08)                               # SR stable at N = 6
    checks = {s: (ok, ex) for s, ok, ex in mg.trend_checks(res, p)}
    assert checks["SR is unstable for N >= 6"] == (False, ["N=6 DP=0.2"])
    assert checks["DR is worse (J1) than DRH for DP >= 0.2 at every N >= 2"][0]
    assert checks["DRHE J4 is within [0.05, 0.2] and below DRH's (stable cells, N >= 2)"][0]
    ok, ex = checks["for a fixed case and N, J1 grows with DP (beyond the 95 % intervals)"]
    assert not ok and any(e.startswith("DRH N=6: DP 0.2 -> 0.4") for e in ex)
    # within the confidence intervals a drop is not a violation
    for dp in (0.2, 0.4):
        res[(p, 6, "DRH", dp)]["J1"]["ci95"] = 0.01
        res[(p, 6, "DRHE", dp)]["J1"]["ci95"] = 0.01
        res[(p, 6, "DR", dp)]["J1"]["ci95"] = 0.01
    assert {s: ok for s, ok, _ in mg.trend_checks(res, p)}[
        "for a fixed case and N, J1 grows with DP (beyond the 95 % intervals)"]


def _cell(J, rate=1.0, unstable=0.0, h=1):
    return {"J1": {"mean": J, "ci95": 0.0}, "J2": {"mean": J}, "J3": {"mean": J}, "rate_sc": {"mean": rate},
            "unstable_fraction": unstable, "h": h}


def test_custom_grid_tables_show_the_cells_it_computed(tmp_path, capsys):
    # finding 2 of issue 25: N = 2, 4, 6 and DP = 0, 0.3, 0.5 were shown as the paper's fixed
    # rows (N in 1, 2, 6, 12 x DP in 0, 0.2, 0.4, 0.6), mostly "-"; N = 4 and DP = 0.3, 0.5
    # only in grid_*.csv
    p, Ns, dps = "lissajous", (2, 4, 6), (0.0, 0.3, 0.5)
    res = {(p, 1, "SR", 0.0): _cell(1.0)}
    for N in Ns:
        for dp in dps:
            res[(p, N, "DRH", dp)] = _cell(1.0 + N / 10 + dp, rate=1 / N)
    rows, cases, paper = mg.table_layout(res, p)
    assert not paper and cases == ("SR", "DRH")
    assert rows == [(1, 0.0)] + [(N, dp) for N in Ns for dp in dps]
    files = mg.write_outputs(tmp_path, res, {})
    md = (tmp_path / "tables_lissajous.md").read_text()
    assert "the N and DP this grid computed" in md and "Tables 1-4 (" not in md
    j1 = md.split("**J1**")[1].split("**J2**")[0]
    assert "| 0.3 | 4 |    – | 1.70 |" in j1 and "| 0.5 | 6 |    – | 2.10 |" in j1
    assert " 12 |" not in j1 and "| 0.2 |" not in j1 and "DRHE" not in j1
    csv_rows = (tmp_path / "tables_lissajous.csv").read_text().splitlines()
    assert csv_rows[0] == "index,DP,N,SR,DRH" and len(csv_rows) == 1 + 4 * 10
    assert "J4,0.3,4,,0.25" in csv_rows
    out = capsys.readouterr().out                                 # stdout: the same tables
    assert "| 0.3 | 4 |    – | 1.70 |" in out and "the N and DP this grid computed" in out
    cmp = (tmp_path / "paper_comparison.md").read_text()           # only the paper's rows computed
    assert "| 0.0 | 2 |" in cmp and "| 0.3 |" not in cmp and "| 0.2 |" not in cmp
    assert tmp_path / "fig_lissajous.png" in files


def test_default_grid_tables_are_the_saved_seed000_tables():
    # the default grid keeps the paper's layout: rebuilt from the saved grid CSV (nominal
    # means 1, so the ratios are the saved values exactly), the tables are byte for byte the
    # saved tables_lissajous.csv and the table part of tables_lissajous.md
    import csv
    from pathlib import Path
    saved = Path(__file__).resolve().parent.parent / "docs" / "results" / "seed000"
    res = {}
    with open(saved / "grid_lissajous.csv") as fh:
        for r in csv.DictReader(fh):
            cell = (r["path"], int(r["N"]), r["case"], float(r["DP"]))
            res[cell] = {"J1": {"mean": float(r["J1"]), "ci95": 0.0}, "J2": {"mean": float(r["J2"])},
                         "J3": {"mean": float(r["J3"])}, "rate_sc": {"mean": float(r["J4"])},
                         "unstable_fraction": float(r["unstable_fraction"]), "h": int(r["h"])}
    assert mg.table_layout(res, "lissajous")[2]
    md, rows = mg.paper_tables(res, "lissajous")
    text = (saved / "tables_lissajous.md").read_text()
    assert text.startswith("# Seed 000, lissajous: Tables 1-4 (J normalised to nominal SR; \u221e unstable)\n\n" + md + "\n\n")
    import io
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\r\n")
    w.writerow(["index", "DP", "N", *mg.mec.CASES])
    w.writerows(rows)
    assert buf.getvalue().encode() == (saved / "tables_lissajous.csv").read_bytes()


def test_close_dps_are_two_cells_and_the_tables_are_written(tmp_path, capsys):
    """Issue 33: dp=0.1 and dp=0.104 mapped to one cell file (dp0.10), each overwrote the
    other and the tables were never written. A rerun with other settings into the same
    folder keeps its cells beside the first run's, and the first run's come back."""
    from jaxnc.cli import run_cli
    from jaxnc.montecarlo import load_results
    argv = ["run", "mecanum-grid", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
            "--set", "path=turn180", "case=SR", "N=1", "dp=0.1,0.104", "chunk=2"]
    assert run_cli(argv) == 0
    cells = sorted(f.name for f in (tmp_path / "cells" / "turn180").glob("*.json"))
    assert len(cells) == 3 and [c.split("-")[0] for c in cells] == ["N01_SR_dp0", "N01_SR_dp0.1", "N01_SR_dp0.104"]
    grid = (tmp_path / "grid_turn180.csv").read_text()
    assert "turn180,1,0.1,SR" in grid and "turn180,1,0.104,SR" in grid
    assert (tmp_path / "tables_turn180.md").exists()
    assert load_results(tmp_path / "results.json")["results"]["complete"]
    stamp = {f: f.stat().st_mtime_ns for f in (tmp_path / "cells").rglob("*.json")}
    # other settings, same folder: three more cells, none of the first run's touched
    assert run_cli([*argv, "--set", "L_ref=0.3"]) == 0
    assert len(list((tmp_path / "cells").rglob("*.json"))) == 6
    assert all(f.stat().st_mtime_ns == t for f, t in stamp.items())
    r = run_cli(argv)                                  # the first settings again: all reused
    assert r == 0 and load_results(tmp_path / "results.json")["results"]["computed"] == 0
    capsys.readouterr()
