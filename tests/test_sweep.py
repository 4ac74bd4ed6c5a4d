"""Sweeps over shards (--shard I/N): shares, validation, and tables assembled from the cell
files byte for byte as an unsharded run writes them; a shard killed midway loses nothing."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from jaxnc.cli import main
from jaxnc.experiment import get_experiment, load_builtin
from jaxnc.sweep import Shard, load_cell, missing_report, parse_shard, save_cell

load_builtin()
ROOT = Path(__file__).resolve().parent.parent


def _cli(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    return e.value.code, capsys.readouterr()


# ----------------------------------------------------------------------------- shares


@pytest.mark.parametrize("n_cells", [0, 1, 7, 9, 1152])
@pytest.mark.parametrize("count", [1, 2, 3, 8])
def test_shards_cover_every_cell_once_in_contiguous_blocks(n_cells, count):
    cells = list(range(n_cells))
    shares = [Shard(i, count).share(cells) for i in range(count)]
    assert sum(shares, []) == cells                               # in order, each cell once
    assert max(map(len, shares)) - min(map(len, shares)) <= 1
    for i, share in enumerate(shares):
        assert all(Shard(0, count).owner(c, n_cells) == i for c in share)


@pytest.mark.parametrize("text, shard", [("0/1", Shard(0, 1)), ("3/4", Shard(3, 4)), (" 1 / 2 ", Shard(1, 2))])
def test_parse_shard(text, shard):
    assert parse_shard(text) == shard and str(shard) == text.replace(" ", "")


@pytest.mark.parametrize("text", ["4/4", "-1/4", "1/0", "0/0", "a/2", "1", "1/2/3", "1.0/2", "", "\uff11/2"])
def test_parse_shard_refuses_bad_values(text):
    with pytest.raises(ValueError, match=r"--shard must be I/N with integers 0 <= I < N"):
        parse_shard(text)


def test_cli_shard_errors_are_one_line(tmp_path, capsys):
    code, cap = _cli(["run", "mecanum-grid", "--shard", "2/2", "--out", str(tmp_path)], capsys)
    assert code == 2 and cap.err.count("\n") == 1 and "--shard must be I/N" in cap.err and "'2/2'" in cap.err
    code, cap = _cli(["run", "mecanum", "--shard", "0/2", "--out", str(tmp_path)], capsys)
    assert code == 2 and cap.err.count("\n") == 1 and "not a sweep" in cap.err


def test_cell_files_are_reused_only_with_their_configuration(tmp_path):
    f = tmp_path / "cells" / "c.json"
    assert load_cell(f, {"a": 1}) is None                             # missing
    save_cell(f, {"config": {"a": 1, "t": (0.1, 0.2)}, "value": float("inf")})
    assert load_cell(f, {"a": 1, "t": (0.1, 0.2)})["value"] == float("inf")
    assert load_cell(f, {"a": 2, "t": (0.1, 0.2)}) is None            # other configuration
    f.write_text('{"config": {"a"')                                    # damaged: computed again
    assert load_cell(f, {"a": 1}) is None


def test_a_cell_whose_configuration_holds_numpy_numbers_is_saved_and_reused(tmp_path):
    """cell_path hashed numpy numbers (seeds from np.arange, a grid from np.linspace(dtype=
    float32)) but save_cell raised TypeError on them, after the cell had been computed."""
    import numpy as np
    from jaxnc.sweep import cell_path
    cfg = {"seeds": np.int64(1024), "p": np.float32(0.3), "grid": np.linspace(0.0, 1.0, 3)}
    f = cell_path(tmp_path, "c", cfg)
    save_cell(f, {"config": cfg, "cost": np.float32(0.25)})
    assert load_cell(f, cfg)["cost"] == 0.25
    assert load_cell(f, dict(cfg, p=np.float32(0.31))) is None


def test_cell_files_are_named_by_their_whole_configuration(tmp_path):
    from jaxnc.sweep import cell_path, config_hash
    a = {"dp": 0.1, "sigma": (0.1, 0.2), "seeds": 4}
    assert config_hash(a) == config_hash({"seeds": 4, "sigma": [0.1, 0.2], "dp": 0.1})   # order, tuples
    others = [dict(a, dp=0.104), dict(a, sigma=(0.1, 0.3)), dict(a, seeds=5), dict(a, extra=None), dict(a, dp=1e-17)]
    names = {cell_path(tmp_path, "N02_DRH_dp0.1", c).name for c in [a, *others]}
    assert len(names) == 1 + len(others)                       # settings that differ anywhere: other files
    f = cell_path(tmp_path / "cells", "N02_DRH_dp0.1", a)
    assert f.parent == tmp_path / "cells" and f.name.startswith("N02_DRH_dp0.1-") and f.suffix == ".json"
    assert len(f.stem.split("-")[-1]) == 12




#: the line of loop/runner.py that returns the Quadratic cost, edited in a copy of the library
_COST_LINE = "return _pairwise_mean(_weighted_square(e, Q) + _weighted_square(u, R))"


@pytest.fixture
def library_copy(tmp_path, monkeypatch):
    """A copy of the jaxnc package as the code fingerprint's imported code (the running code
    is unchanged): returns ``edit((old, new), ...)``, which replaces each ``old`` by ``new`` in
    the copy's ``loop/runner.py`` (the ``Quadratic`` cost) as if that code had been imported."""
    import shutil
    from jaxnc import sweep
    lib = tmp_path / "lib" / "jaxnc"
    shutil.copytree(Path(sweep.__file__).parent, lib, ignore=shutil.ignore_patterns("__pycache__", "experiments"))
    runner = lib / "loop" / "runner.py"
    text = runner.read_text()
    assert text.count('"""Cost J = (1/K)') == 1 and text.count(_COST_LINE) == 1

    def refresh():
        if hasattr(sweep, "_package_sources"):
            monkeypatch.setattr(sweep, "_IMPORTED_SOURCES", sweep._package_sources(lib))
            sweep.code_fingerprint.cache_clear()
    refresh()

    def edit(*pairs):
        edited = text
        for old, new in pairs:
            edited = edited.replace(old, new)
        runner.write_text(edited)
        refresh()
    yield edit
    monkeypatch.undo()
    if hasattr(sweep, "code_fingerprint"):
        sweep.code_fingerprint.cache_clear()


def test_a_cell_computed_by_other_library_code_is_not_reused(tmp_path, library_copy):
    """A cell's configuration (the loop by ``config_of``, the settings) does not name the
    library code it ran on: a cell stored before an edit of jaxnc (here the ``Quadratic`` cost
    doubled) was reused by the edited library with its old numbers. The code's fingerprint
    is part of the cell's name and record now; an edit of docstrings or comments alone keeps it."""
    from jaxnc import sweep
    cfg = {"loop": {"type": "Loop", "N": 2}, "seeds": 64}
    f = sweep.cell_path(tmp_path / "cells", "c", cfg)
    sweep.save_cell(f, {"config": cfg, "cost": 0.05})
    assert sweep.load_cell(f, cfg)["cost"] == 0.05
    library_copy(('"""Cost J = (1/K)', '"""Cost (a docstring edited) J = (1/K)'),
                 (_COST_LINE, _COST_LINE + "  # a comment"))
    assert sweep.cell_path(tmp_path / "cells", "c", cfg) == f and sweep.load_cell(f, cfg)["cost"] == 0.05
    library_copy((_COST_LINE, _COST_LINE.replace("return ", "return 2 * ")))
    assert sweep.load_cell(f, cfg) is None                          # the old library's number
    assert sweep.cell_path(tmp_path / "cells", "c", cfg) != f       # beside it, not over it


def test_a_stored_part_of_other_library_code_is_computed_again(tmp_path, library_copy):
    """``montecarlo.stored_or_run`` (the parts of tune-loops and tune-study) reused a part
    whose configuration matched whatever code had written it."""
    from jaxnc import montecarlo
    calls = []
    compute = lambda: calls.append(1) or {"cost": 0.05 * len(calls), "wall_time_s": 0.0}
    run = lambda: montecarlo.stored_or_run(tmp_path / "part.json", experiment="demo", config={"seeds": 4},
                                           compute=compute, progress=False)
    assert run()["cost"] == 0.05 and run()["cost"] == 0.05 and len(calls) == 1
    library_copy((_COST_LINE, _COST_LINE.replace("return ", "return 2 * ")))
    assert run()["cost"] == 0.1 and len(calls) == 2

def test_the_code_fingerprint_is_kept_by_the_files_bytes_and_a_bad_memo_is_ignored(tmp_path, monkeypatch,
                                                                                     library_copy):
    """Parsing the package's files for :func:`sweep.code_fingerprint` took about a second in
    every process that stores a result; the digest is now kept in a file named by the files'
    exact bytes. What is read from there is what the function returns (so the memo is used),
    a file that is not a digest is ignored and rewritten, and other bytes (a code edit, or a
    docstring edit, which keeps the digest) are another memo."""
    from jaxnc import sweep
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    folder = tmp_path / "jaxnc" / "code"

    def fresh():                       # as a new process would compute it
        sweep.code_fingerprint.cache_clear()
        return sweep.code_fingerprint()
    first = fresh()
    [memo] = folder.iterdir()
    assert memo.read_text() == first and len(first) == 16
    memo.write_text("0123456789abcdef")
    assert fresh() == "0123456789abcdef"                    # read, not computed
    for bad in ("not a digest", "", "0123456789ABCDEF"):
        memo.write_text(bad)
        assert fresh() == first and memo.read_text() == first
    library_copy(('"""Cost J = (1/K)', '"""Cost (a docstring edited) J = (1/K)'))
    assert fresh() == first and len(list(folder.iterdir())) == 2
    library_copy((_COST_LINE, _COST_LINE.replace("return ", "return 2 * ")))
    assert fresh() != first and len(list(folder.iterdir())) == 3
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "a file"))
    (tmp_path / "a file").write_text("")                    # no folder can be made there
    assert fresh() not in (first, None) and not list(folder.glob("*.tmp"))
    sweep.code_fingerprint.cache_clear()


def test_missing_report_names_the_shards_that_owe_cells():
    cells = list(range(10))
    text = missing_report(cells, [5, 9], Shard(0, 3), describe=lambda c: f"cell {c}")
    assert text.startswith("shard 0/3 has done its share (3 cells); 2 of 10 cells are missing (shards 1/3, 2/3): cell 5; cell 9")


# ----------------------------------------------------------------------------- mecanum-grid

GRID = dict(get_experiment("mecanum-grid").defaults(), path="turn180", N=(2,), dp=(0.0, 0.3), chunk=4)
SEEDS = 4


def _tables(out):
    files = sorted(out.glob("tables_*")) + sorted(out.glob("grid_*")) + sorted(out.glob("fig_*"))
    return {f.name: f.read_bytes() for f in files}


_CHILD = """
import os, sys
sys.path.insert(0, {root!r})
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
if not os.environ.get("JAXNC_NO_CACHE"):
    from jaxnc.cache import enable_cache
    enable_cache()
from pathlib import Path
from experiments import mecanum_grid as mg
from jaxnc import sweep
from jaxnc.sweep import Shard
save = sweep.save_cell
def save_then_wait(*args, **kwargs):         # the parent kills this process during the wait: a loaded
    save(*args, **kwargs)                     # machine can otherwise see the shard finish between two polls
    import time; time.sleep(300)
sweep.save_cell = save_then_wait
mg.run_grid({settings!r}, seeds={seeds}, out=Path({out!r}), progress=False, shard=Shard(0, 2))
"""


def test_two_shards_assemble_the_tables_of_an_unsharded_run_and_a_killed_shard_loses_nothing(tmp_path, capsys):
    from experiments import mecanum_grid as mg
    whole, shared = tmp_path / "whole", tmp_path / "shared"
    cells = mg.grid_cells(GRID)
    first, second = Shard(0, 2).share(cells), Shard(1, 2).share(cells)
    assert len(cells) == 9 and len(first) == 4
    mg.run_grid(GRID, seeds=SEEDS, out=whole, progress=False)
    reference = _tables(whole)
    assert {"tables_turn180.md", "tables_turn180.csv", "grid_turn180.csv", "fig_turn180.png"} <= set(reference)

    # shard 0 in a process of its own, killed (SIGKILL) once its first cell is stored (it waits after each)
    script = _CHILD.format(root=str(ROOT), settings=GRID, seeds=SEEDS, out=str(shared))
    child = subprocess.Popen([sys.executable, "-c", textwrap.dedent(script)], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    files = [mg.cell_files(shared, GRID, SEEDS)[c] for c in first]
    try:
        deadline = time.monotonic() + 240
        while not any(f.exists() for f in files):
            assert child.poll() is None, child.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "shard 0 stored no cell in 240 s"
            time.sleep(0.02)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=30)
    saved = [f for f in files if f.exists()]
    assert 1 <= len(saved) < len(first), "the kill came after shard 0 had finished"
    assert all(f.with_suffix(".npz").exists() for f in saved)       # arrays written before each cell's JSON

    # shard 1: its share done, shard 0's missing -> says so, no tables, exits normally
    r = mg.run_grid(GRID, seeds=SEEDS, out=shared, progress=False, shard=Shard(1, 2))
    out = capsys.readouterr().out
    assert (r["computed"], r["complete"]) == (len(second), False)
    assert f"shard 1/2 has done its share ({len(second)} cells); {len(first) - len(saved)} of 9 cells are missing (shard 0/2)" in out
    assert not _tables(shared)

    # shard 0 again: reuses what the killed run stored, computes the rest, assembles
    r = mg.run_grid(GRID, seeds=SEEDS, out=shared, progress=False, shard=Shard(0, 2))
    assert (r["reused"], r["computed"], r["complete"]) == (len(saved), len(first) - len(saved), True)
    assert _tables(shared) == reference
    # a final run without --shard finds everything and rewrites the same bytes
    assert mg.run_grid(GRID, seeds=SEEDS, out=shared, progress=False)["computed"] == 0
    assert _tables(shared) == reference


def test_cli_shards_of_the_grid(tmp_path, capsys):
    """The commands of the README's recipe: two shards through `jaxnc run --shard`."""
    sets = ["--set", "path=turn180", "--set", "N=2", "--set", "dp=0.3", "--set", "case=DRH", "--set", "chunk=4"]
    code, cap = _cli(["run", "mecanum-grid", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
                      "--shard", "1/2", *sets], capsys)
    assert code == 0 and "shard 1/2 has done its share (1 cell); 1 of 2 cells are missing (shard 0/2)" in cap.out
    code, cap = _cli(["run", "mecanum-grid", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
                      "--shard", "0/2", *sets], capsys)
    assert code == 0 and (tmp_path / "tables_turn180.md").exists()


# ----------------------------------------------------------------------------- hdd-gpi, diffdrive-sensitivity


def test_gpi_shards_assemble_the_unsharded_surface(tmp_path, capsys):
    from experiments import hdd
    from jaxnc.montecarlo import load_results
    settings = dict(get_experiment("hdd-gpi").defaults(), n=2, case="3")
    best = hdd.run_gpi(settings, seeds=2, out=tmp_path / "whole", progress=False)
    assert hdd.run_gpi(settings, seeds=2, out=tmp_path / "s", progress=False, shard=Shard(1, 2)) == \
        {"complete": False, "missing": 2}
    assert "shard 1/2 has done its share (2 cells); 2 of 4 cells are missing (shard 0/2)" in capsys.readouterr().out
    assert hdd.run_gpi(settings, seeds=2, out=tmp_path / "s", progress=False, shard=Shard(0, 2)) == best
    a, b = (load_results(tmp_path / d / "results.json")["results"] for d in ("whole", "s"))
    assert a == b


def test_sensitivity_shards_assemble_the_unsharded_table(tmp_path, capsys, monkeypatch):
    """The sweep's bookkeeping, with a stand-in for the (expensive) cell: the real cell
    runs in tests/test_diffdrive.py::test_sensitivity_experiment_smoke."""
    from experiments import diffdrive
    calls = []

    def cell(settings, v, lad, keys):
        calls.append((v, lad))
        ratios = {n: {"J1": 1.0 + v + lad * i, "J1_ref": 1.0 + v * i} for i, n in enumerate("abcde")}
        return {"v_ref": v, "lad": lad, "J1_a": 1000 * v, "J1_ref_a": 900 * lad, "ratios": ratios,
                "unstable": {n: 0.0 for n in "abcde"}}
    monkeypatch.setattr(diffdrive, "sensitivity_cell", cell)
    settings = dict(diffdrive.SENSITIVITY.defaults(), v_refs=(0.12, 0.14), lads=(0.1, 0.15))
    diffdrive.run_sensitivity(settings, seeds=2, out=tmp_path / "whole", progress=False)
    table = capsys.readouterr().out
    assert len(calls) == 4
    assert diffdrive.run_sensitivity(settings, seeds=2, out=tmp_path / "s", progress=False,
                                     shard=Shard(0, 2))["complete"] is False
    capsys.readouterr()
    diffdrive.run_sensitivity(settings, seeds=2, out=tmp_path / "s", progress=False, shard=Shard(1, 2))
    sharded = capsys.readouterr().out
    assert len(calls) == 8
    strip = lambda text: text.split("\nwrote")[0]
    assert strip(sharded) == strip(table) and "| 0.140 |" in table
    diffdrive.run_sensitivity(settings, seeds=2, out=tmp_path / "s", progress=False)   # nothing left to compute
    assert len(calls) == 8
