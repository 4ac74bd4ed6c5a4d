"""The `mecanum-validation` experiment (seed 000, section 5): CLI run on the kinematic
plant at a tiny size, resume, and the verdict logic of the section-5 conclusions."""
import json

import numpy as np
import pytest

from experiments import mecanum_validation as mv
from jaxnc.cli import main


def _run(argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    return e.value.code


def _synthetic(values):
    """Cell summaries whose means are ``values[j][(N, dp)] = (DRH, DRHE)``."""
    res = {}
    for (N, dp) in values["J1"]:
        for i, case in enumerate(mv.CASES):
            res[(case, N, dp)] = {j: {"mean": values[j][(N, dp)][i]} for j in mv.INDEXES}
            res[(case, N, dp)]["unstable_fraction"] = 0.0
    return res


def test_paper_numbers_pass_their_own_conclusions_and_a_changed_one_fails():
    verdicts = {c: h for c, _, _, h in mv.conclusions(_synthetic(mv.PAPER))}
    assert verdicts and all(verdicts.values()), verdicts
    # DRHE sending as often as DRH: no saving, the J4 and saving conclusions fail
    same = {j: dict(mv.PAPER[j]) for j in mv.INDEXES}
    same["J4"] = {k: (v[0], v[0]) for k, v in mv.PAPER["J4"].items()}
    v2 = {c: h for c, _, _, h in mv.conclusions(_synthetic(same))}
    assert not v2["DRHE's transmission saving over DRH at N = 2"]
    assert not v2["DRHE's J4 range over the table cells"]
    assert v2["DRHE's J1 above DRH's, on average"]          # J1-J3 untouched


def test_bad_scale_is_a_one_line_error(tmp_path, capsys):
    code = _run(["run", "mecanum-validation", "--out", str(tmp_path), "--set", "scale=0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "scale" in err[0]


def test_cli_run_writes_tables_results_and_resumes(tmp_path, capsys):
    argv = ["run", "mecanum-validation", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
            "--set", "plant=kinematic", "--set", "N=2", "--set", "dp=0,0.4", "--set", "fig12=false"]
    assert _run(argv) == 0
    out = capsys.readouterr().out
    assert "Table 5" in out and "Table 6" in out and "section-5 conclusion" in out
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["experiment"] == "mecanum-validation"
    assert res["config"]["settings"]["plant"] == "kinematic"
    cells = res["results"]["cells"]
    assert set(cells) == {"DRH_N2_dp0", "DRH_N2_dp0.4", "DRHE_N2_dp0", "DRHE_N2_dp0.4"}
    assert cells["DRH_N2_dp0"]["normalised"]["J1"] == 1.0              # the normalising cell
    # DRH's sensor sends every NT = 2 T: J4 = ceil(l / 2) / l
    assert cells["DRH_N2_dp0"]["normalised"]["J4"] == pytest.approx(0.5, abs=0.01)
    assert cells["DRHE_N2_dp0"]["normalised"]["J4"] < 0.5              # events send less
    # the reduced reference: half of section 4's Lissajous curve
    assert res["config"]["path_length_m"] == pytest.approx(0.5 * 7.32, abs=0.02)
    tables = (tmp_path / "tables.md").read_text()
    assert "1.23" in tables                                        # the paper's DRHE J1 at N=2, DP=0.4
    assert (tmp_path / "fig15_16.png").stat().st_size > 10_000
    [f] = (tmp_path / "cells").glob("DRHE_N2_dp0.4-*.npz")            # named by its whole configuration
    arrays = np.load(f)
    assert arrays["J1"].shape == (2,)
    # a rerun reuses every stored cell: the same tables
    stamp = {f: f.stat().st_mtime_ns for f in (tmp_path / "cells").glob("*.json")}
    assert _run(argv) == 0
    assert {f: f.stat().st_mtime_ns for f in (tmp_path / "cells").glob("*.json")} == stamp
    assert (tmp_path / "tables.md").read_text() == tables


def test_conclusions_of_a_run_without_table_cells_are_a_sentence():
    one = {k: v for k, v in _synthetic(mv.PAPER).items() if k[0] == "DRH"}
    assert mv.conclusions(one) == []
    assert mv.conclusions_md(one).startswith("(none")


@pytest.mark.parametrize("name, sets", [
    ("mecanum-validation", ["plant=kinematic", "N=2", "dp=0", "fig12=false"]),
    ("mecanum-grid", ["path=turn180", "case=SR", "N=1", "dp=0"]),
])
def test_no_cache_writes_no_cache_beside_the_results(name, sets, tmp_path, capsys, monkeypatch):
    """Issue 33: with --no-cache both still kept compiled programs in OUT/.xla_cache."""
    import sys

    import jax

    from jaxnc.experiment import ConfigError, get_experiment, load_builtin
    load_builtin()                           # (registers the built-ins the command line runs)
    seen = []

    def stop(*a, **k):                       # what the study sees once it has set its cache up
        seen.append(jax.config.jax_compilation_cache_dir)
        raise ConfigError("stopped before simulating")
    module = sys.modules[get_experiment(name).run.__module__]       # the module the command line runs
    monkeypatch.setattr(module, "true_plant" if name == "mecanum-validation" else "run_grid", stop)
    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", None)            # as in a fresh process
        argv = ["run", name, "--no-cache", "--seeds", "2", "--out", str(tmp_path), "--set", *sets]
        assert _run(argv) == 2
        assert "stopped before simulating" in capsys.readouterr().err
        assert seen == [None] and not (tmp_path / ".xla_cache").exists()
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
        from jaxnc.cache import allow_cache_beside
        allow_cache_beside(True)
