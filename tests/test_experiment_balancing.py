"""The `balancing` experiment end to end through the CLI (quick size: 2 seeds, one
severity, the shortest horizon): table, results.json and the Fig. 5 / Fig. 7 figures."""
import json

import numpy as np

from tests.test_cli import assert_one_line_error, run


def test_bad_derivative_is_a_one_line_error(tmp_path, capsys):
    assert run(["run", "balancing", "--out", str(tmp_path), "--set", "derivative=dirty"]) == 2
    assert_one_line_error(capsys, "derivative", "simple, filtered")


def test_quick_run_writes_fig5_and_fig7(tmp_path, capsys):
    code = run(["run", "balancing", "--seeds", "2", "--no-progress", "--out", str(tmp_path),
                 "--set", "severity=nominal", "horizon=16"])
    assert code == 0
    out = capsys.readouterr().out
    assert "nominal / emulation" in out and "emulation derivative=simple" in out
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["config"]["settings"]["derivative"] == "simple"
    assert res["config"]["settings"]["tilt_sensor"] == "complementary"
    assert set(res["results"]) == {"nominal / model", "nominal / emulation"}
    for f in ("fig5_loopback_cdf.png", "fig7_time_responses.png"):
        assert (tmp_path / f).stat().st_size > 10_000
    # Fig. 5's data: a CDF per noise level, non-decreasing to 1; more noise (a retry a step
    # later) delays the packets: no higher CDF, up to 5 standard errors of an empirical
    # CDF of the >= 10 x 60 000 x 0.8 delivered packets
    lb = res["config"]["fig5"]["loopback"]
    assert list(lb) == ["no noise", "-21 dBm", "-19 dBm"]
    cdfs = np.array([lb[n]["cdf"] for n in lb])
    assert np.all(np.diff(cdfs, axis=1) >= 0) and np.allclose(cdfs[:, -1], 1.0, atol=1e-3)
    tol = 5 * np.sqrt(cdfs * (1 - cdfs) / (10 * 60_000 * 0.8)) + 1e-12
    assert np.all(cdfs[1] <= cdfs[0] + tol[0] + tol[1]) and np.all(cdfs[2] <= cdfs[1] + tol[1] + tol[2])
    assert cdfs[0, 3] - cdfs[2, 3] > 0.05                                    # visibly later at -19 dBm
    assert lb["no noise"]["stats"]["delay_median"] == 3.0                     # Table 1
    csv = (tmp_path / "fig5_loopback_cdf.csv").read_text().splitlines()
    assert csv[0] == "delay_steps,no noise,-21 dBm,-19 dBm" and len(csv) == 1 + 21
