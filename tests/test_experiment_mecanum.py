"""The `mecanum` experiment end to end through the CLI (small: 2 seeds, one case, N = 1 so
that the case and the nominal run share one compiled program)."""
import json

import pytest

from jaxnc.cli import main


def _run(argv):
    with pytest.raises(SystemExit) as e:
        main(argv)
    return e.value.code


def test_bad_combination_is_a_one_line_error(tmp_path, capsys):
    code = _run(["run", "mecanum", "--out", str(tmp_path), "--set", "sigma=0.1,0.2"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "sigma" in err[0] and "Traceback" not in err[0]


def test_run_writes_table_results_and_figure(tmp_path, capsys):
    code = _run(["run", "mecanum", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
                 "--set", "case=DRH", "--set", "N=1", "--set", "dp=0.1", "--set", "path=turn180"])
    assert code == 0
    out = capsys.readouterr().out
    assert "SR nominal" in out and "DRH" in out
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["experiment"] == "mecanum"
    assert res["config"]["settings"]["N"] == 1
    assert res["results"]["SR nominal"]["normalised"]["J1"] == 1.0      # by construction
    assert set(res["results"]["DRH"]["absolute"]) == {"J1", "J2", "J3"}
    assert (tmp_path / "paths.png").stat().st_size > 10_000
