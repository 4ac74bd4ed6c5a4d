"""The seed-000 grid experiment: resumable cell by cell, identical tables after an interruption."""

import numpy as np
import pytest

from experiments import mecanum_grid as mg
from jaxnc import montecarlo
from jaxnc.experiment import get_experiment

SETTINGS = dict(get_experiment("mecanum-grid").defaults(), path="turn180", N=(2,), dp=(0.0, 0.3), chunk=4)


def _outputs(out):
    return {f.name: f.read_bytes() for f in sorted(out.glob("tables_*")) + sorted(out.glob("grid_*"))}


def test_interrupted_grid_resumes_and_gives_identical_tables(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    cells = mg.grid_cells(SETTINGS)
    assert len(cells) == 1 + 4 * 2            # nominal SR + 4 cases x 2 DP
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
    f = mg.cell_file(a, "turn180", 2, "DRH", 0.3)
    f.write_text('{"config": ')
    assert mg.run_grid(SETTINGS, seeds=4, out=a, progress=False)["computed"] == 1
    assert _outputs(a) == _outputs(b)
    # a cell computed with other settings is not reused
    other = dict(SETTINGS, delta=(0.2,))
    assert mg.run_grid(other, seeds=4, out=a, progress=False, stop_after=0)["reused"] == 0
    assert not list(a.rglob("*.tmp"))


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
