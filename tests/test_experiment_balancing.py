"""The `balancing` experiment end to end through the CLI (quick size: 2 seeds, one
severity, the shortest horizon): table, results.json and the Fig. 5 / Fig. 7 figures."""
import contextlib
import io
import json

import numpy as np
import pytest

import jaxnc
from jaxnc.schemes import balancing as bal
from tests.test_cli import assert_one_line_error, run
from tests.test_results import _row, _same


def test_bad_derivative_is_a_one_line_error(tmp_path, capsys):
    assert run(["run", "balancing", "--out", str(tmp_path), "--set", "derivative=dirty"]) == 2
    assert_one_line_error(capsys, "derivative", "simple, filtered")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """One quick run of the command (2 seeds, the nominal network, 16 s), shared by the tests
    of its figures and of its dataset: (folder, what it printed)."""
    folder = tmp_path_factory.mktemp("balancing")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = run(["run", "balancing", "--seeds", "2", "--no-progress", "--out", str(folder),
                    "--set", "severity=nominal", "horizon=16"])
    assert code == 0
    return folder, buf.getvalue()


def test_quick_run_writes_fig5_and_fig7(quick_run):
    tmp_path, out = quick_run
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


def test_the_dataset_means_are_the_printed_table(quick_run):
    """``jaxnc.load`` of the run's folder: its per-seed dataset's means are the results.json
    summary and the printed table's numbers, with the metrics' units."""
    folder, printed = quick_run
    summary = json.loads((folder / "results.json").read_text())["results"]
    ds = jaxnc.load(folder)
    assert ds["tilt_rms_deg"].dims == ("severity", "design", "seed")
    assert [ds[k].attrs.get("units") for k in ("tilt_rms_deg", "track_rms_mm", "upright")] == ["deg", "mm", None]
    s = ds.jaxnc.summary()
    for d in ds["design"].values:
        name = f"nominal / {d}"
        assert float(s["upright"].sel(severity="nominal", design=d)) == summary[name]["upright_fraction"]
        assert _same(float(s["tilt_rms_deg"].sel(severity="nominal", design=d)), summary[name]["tilt_rms_deg"]["mean"])
        assert _row(printed, name)[1].startswith(f"{100 * float(s['upright'].sel(severity='nominal', design=d)):.1f}")


SWEEP = ["run", "balancing-sweep", "--seeds", "4", "--no-progress", "--set", "axis=delay", "horizon=16"]


def test_sweep_stores_points_resumes_and_harsher_delay_is_not_better(tmp_path, capsys, monkeypatch):
    """balancing-sweep on the delay axis, 2 points x 4 seeds x 16 s: the saved structure, the
    emulation design on the *delay* severity's law (index 1) falls where it stood at the
    Table-1 fit (index 0; fixed seeds), and a second run computes only what is missing."""
    from jaxnc import montecarlo
    out = str(tmp_path)
    assert run([*SWEEP, "--out", out, "--set", "delay=0,1"]) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["experiment"] == "balancing-sweep" and list(res["results"]["axes"]) == ["delay"]
    pts = res["results"]["axes"]["delay"]["points"]
    assert [p["value"] for p in pts] == [0.0, 1.0]
    assert all(p[d]["n"] == 4 for p in pts for d in ("model", "emulation"))
    nominal, harsh = pts
    assert harsh["emulation"]["upright_fraction"] < nominal["emulation"]["upright_fraction"]
    assert harsh["model"]["upright_fraction"] == 1.0 and harsh["verdict"] == "separates"
    assert harsh["channel"]["delay_median"] > nominal["channel"]["delay_median"]
    assert len(res["results"]["per_seed"]["cells"]) == 4
    assert res["config"]["channels"]["delay=1"]["delay_pmf"] == pytest.approx(
        np.asarray(bal.SEVERITIES["delay"].delay_pmf).tolist())
    assert (tmp_path / "fig_sweep.png").stat().st_size > 10_000 and "## delay" in (tmp_path / "sweep.md").read_text()
    ds = jaxnc.load(tmp_path)                                   # the per-seed points as one Dataset
    assert ds.upright.dims == ("axis", "value", "design", "seed") and ds.upright.shape == (1, 2, 2, 4)
    assert int(ds.upright.sel(value=1.0, design="emulation").sum()) == round(4 * harsh["emulation"]["upright_fraction"])
    # resume: the stored points are reused, only the new value is computed (one run per design)
    calls = []
    real = montecarlo.run_batched
    monkeypatch.setattr(montecarlo, "run_batched", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert run([*SWEEP, "--out", out, "--set", "delay=0,0.5,1"]) == 0
    assert len(calls) == 2
    again = json.loads((tmp_path / "results.json").read_text())["results"]["axes"]["delay"]["points"]
    assert [p["value"] for p in again] == [0.0, 0.5, 1.0]
    assert again[0]["emulation"] == nominal["emulation"] and again[2]["model"] == harsh["model"]
    capsys.readouterr()


def test_sweep_bad_point_is_a_one_line_error(tmp_path, capsys):
    assert run([*SWEEP, "--out", str(tmp_path), "--set", "delay=0,2"]) == 2
    assert_one_line_error(capsys, "delay", "[0, 1.75]")
