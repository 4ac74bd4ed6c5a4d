"""jaxnc.load: per-seed metrics as an xarray.Dataset whose means are the printed tables."""
import dataclasses
import json
import math
import re

import numpy as np
import pytest

import jaxnc
from jaxnc import montecarlo, results
from jaxnc.experiment import get_experiment, load_builtin
from jaxnc.report import fmt

load_builtin()


def _settings(name, **kw):
    return dict(get_experiment(name).defaults(), **kw)


def _row(table: str, label: str) -> list[str]:
    """The cells of the printed Markdown row whose first cell is ``label``."""
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == label:
            return cells
    raise AssertionError(f"no row {label!r} in\n{table}")


def _same(a, b):
    """Equal floats, inf and nan included."""
    return (math.isnan(a) and math.isnan(b)) or a == b


# ----------------------------------------------------------------------------- format


def _metrics(n, shift=0.0):
    return {"J1": np.arange(n, dtype=np.float32) + shift, "tx": np.arange(n, dtype=np.int32),
            "unstable": np.arange(n) % 3 == 0}


def test_save_and_load_round_trip_with_attributes(tmp_path):
    runs = {"A": _metrics(5), "B": _metrics(5, 10.0)}
    results.save_per_seed(tmp_path, runs, dims=("case",))
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"settings": {"k": 1}, "seeds": 5},
                            results={}, wall_time_s=1.5)
    ds = jaxnc.load(tmp_path)
    assert ds["J1"].dims == ("case", "seed") and list(ds["case"].values) == ["A", "B"]
    assert ds["J1"].dtype == np.float32 and ds["tx"].dtype == np.int32 and ds["unstable"].dtype == bool
    np.testing.assert_array_equal(ds["J1"].sel(case="B").values, runs["B"]["J1"])
    assert ds.attrs["experiment"] == "toy" and ds.attrs["settings"] == {"k": 1} and ds.attrs["seeds"] == 5
    # the summary is montecarlo.summarize over the stable runs, per case
    s = ds.jaxnc.summary()
    ref = montecarlo.summarize(runs["B"]["J1"], runs["B"]["unstable"])
    assert float(s["J1"].sel(case="B")) == ref.mean and float(s["J1_ci95"].sel(case="B")) == ref.ci95
    assert float(s["unstable_fraction"].sel(case="A")) == 2 / 5
    df = results.to_pandas(ds)
    assert df.loc["B", "J1"] == ref.mean and df.loc["B", "n"] == 5


def test_missing_combinations_are_nan_and_marked(tmp_path):
    runs = {("x", 1): _metrics(3), ("y", 2): _metrics(3, 1.0)}
    results.save_per_seed(tmp_path, runs, dims=("p", "N"))
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={}, results={}, wall_time_s=0.0)
    ds = jaxnc.load(tmp_path)
    assert ds["J1"].dims == ("p", "N", "seed")
    assert ds["present"].values.tolist() == [[True, False], [False, True]]
    assert np.isnan(ds["J1"].sel(p="x", N=2)).all() and ds["unstable"].sel(p="x", N=2).all()
    assert float(ds.jaxnc.summary()["J1"].sel(p="y", N=2)) == montecarlo.summarize(
        runs[("y", 2)]["J1"], runs[("y", 2)]["unstable"]).mean


def test_a_combination_never_run_has_no_statistics(tmp_path):
    """The summary of a grid's combination that no run computed (a sweep that skips one; the
    seed-000 grid at N = 1 holds only nominal SR) is no runs: n 0 and nan statistics. It used
    to read as every run failed: n the seed count, unstable_fraction 1.0, the means inf."""
    runs = {("x", 1): _metrics(3), ("y", 2): _metrics(3, 1.0)}
    runs[("x", 1)]["ok"] = np.array([True, False, True])
    runs[("y", 2)]["ok"] = np.array([True, True, True])
    results.save_per_seed(tmp_path, runs, dims=("p", "N"))
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={}, results={}, wall_time_s=0.0)
    s = jaxnc.load(tmp_path).jaxnc.summary()
    absent = s.sel(p="x", N=2)
    assert int(absent["n"]) == 0 and not bool(absent["present"])
    for name in ("J1", "J1_ci95", "J1_std", "tx", "unstable_fraction", "ok"):
        assert np.isnan(float(absent[name])), name
    assert int(absent["J1_n_stable"]) == 0
    here = s.sel(p="x", N=1)
    ref = montecarlo.summarize(runs[("x", 1)]["J1"], runs[("x", 1)]["unstable"])
    assert int(here["n"]) == 3 and float(here["J1"]) == ref.mean and float(here["unstable_fraction"]) == 1 / 3
    assert float(here["ok"]) == 2 / 3


def test_summary_without_a_stable_run_is_nan_for_a_rate_and_inf_for_a_divergent_cost(tmp_path):
    """A case where every run failed: the rate has no mean (nan, n_stable 0), as describe's
    '–'; a cost that is +inf in every failed run is the papers' ∞. to_pandas used to give
    inf for the rate too, a number no run had."""
    runs = {"ok": {"rate": np.array([0.5, 0.25], np.float32), "cost": np.array([1.0, 3.0], np.float32),
                   "unstable": np.array([False, False])},
            "failed": {"rate": np.array([0.5, 0.75], np.float32), "cost": np.full(2, np.inf, np.float32),
                       "unstable": np.array([True, True])}}
    results.save_per_seed(tmp_path, runs, dims=("case",))
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"seeds": 2}, results={},
                            wall_time_s=0.0)
    df = jaxnc.load(tmp_path).jaxnc.to_pandas()
    assert math.isnan(df.loc["failed", "rate"]) and df.loc["failed", "rate_n_stable"] == 0
    assert df.loc["failed", "cost"] == math.inf and df.loc["failed", "cost_n_stable"] == 0
    assert df.loc["failed", "unstable_fraction"] == 1.0 and df.loc["failed", "n"] == 2
    assert df["rate_n_stable"].dtype.kind == "i" and df.loc["ok", "rate_n_stable"] == 2      # counts as integers
    assert df.loc["ok", "rate"] == pytest.approx(0.375) and df.loc["ok", "cost"] == pytest.approx(2.0)


def test_old_and_damaged_folders_give_errors_naming_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "results.json"))):
        jaxnc.load(tmp_path)
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={}, results={}, wall_time_s=0.0)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "seeds.npz")) + ".*older"):
        jaxnc.load(tmp_path)                      # a folder from before per-seed results
    (tmp_path / "seeds.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "seeds.npz")) + ": damaged"):
        jaxnc.load(tmp_path)
    f = results.save_per_seed(tmp_path, {"A": _metrics(4)})
    f.write_bytes(f.read_bytes()[:-40])           # cut short
    with pytest.raises(ValueError, match=re.escape(str(f)) + ": damaged"):
        jaxnc.load(tmp_path)
    (tmp_path / "results.json").write_text('{"experiment": ')
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "results.json"))):
        jaxnc.load(tmp_path)


def test_save_per_seed_refuses_ragged_runs(tmp_path):
    with pytest.raises(ValueError, match="unstable"):
        results.save_per_seed(tmp_path, {"A": {"J1": np.zeros(3)}})
    with pytest.raises(ValueError, match="one value per seed"):
        results.save_per_seed(tmp_path, {"A": _metrics(3), "B": _metrics(4)})


# ----------------------------------------------------------------------------- the experiments


def test_mecanum_dataset_means_are_the_printed_table(tmp_path, capsys):
    from experiments import mecanum
    # N = 1: the case and the nominal run share one compiled program, the one
    # tests/test_experiment_mecanum.py's run compiles (the means do not depend on N)
    settings = _settings("mecanum", case="DRH", N=1, dp=0.1, path="turn180")
    summary = mecanum.run(settings, seeds=4, out=tmp_path, progress=False)
    printed = capsys.readouterr().out
    ds = jaxnc.load(tmp_path)
    assert ds.attrs["experiment"] == "mecanum" and ds.attrs["settings"]["N"] == 1
    assert list(ds["case"].values) == ["SR nominal", "DRH"] and ds.sizes["seed"] == 4
    assert [ds[j].attrs["units"] for j in ("J1", "J2", "J3", "l")] == ["m", "m", "s", "fast periods"]
    s = ds.jaxnc.summary()
    for case in ("SR nominal", "DRH"):
        for j in ("J1", "J2", "J3"):                   # exactly the numbers in results.json
            assert _same(float(s[j].sel(case=case)), summary[case]["absolute"][j]["mean"])
        j1 = float(s["J1"].sel(case=case)) / float(s["J1"].sel(case="SR nominal"))
        assert _row(printed, case)[1] == fmt(j1)       # J1 normalised, as printed
        assert _row(printed, case)[6] == f"{100 * float(s['unstable_fraction'].sel(case=case)):.1f}"


def test_mecanum_grid_dataset_means_are_the_tables(tmp_path):
    from experiments import mecanum_grid as mg
    settings = _settings("mecanum-grid", path="turn180", N=(2,), dp=(0.0, 0.3), chunk=4)
    mg.run_grid(settings, seeds=4, out=tmp_path, progress=False)
    ds = jaxnc.load(tmp_path)
    assert ds["J1"].dims == ("path", "N", "case", "dp", "seed") and ds.attrs["experiment"] == "mecanum-grid"
    assert ds.sizes == {"path": 1, "N": 2, "case": 4, "dp": 2, "seed": 4}     # N = 1: the nominal SR cell only
    assert int(ds["present"].sum()) == len(mg.grid_cells(settings))
    s = ds.jaxnc.summary()
    import csv
    with open(tmp_path / "grid_turn180.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(mg.grid_cells(settings))
    nom = float(s["J1"].sel(path="turn180", N=1, case="SR", dp=0.0))
    for r in rows:
        cell = dict(path=r["path"], N=int(r["N"]), case=r["case"], dp=float(r["DP"]))
        assert _same(float(s["J1"].sel(**cell)), float(r["J1_abs_m"]))
        assert _same(float(s["unstable_fraction"].sel(**cell)), float(r["unstable_fraction"]))
        if float(r["unstable_fraction"]) <= mg.UNSTABLE_CELL:
            assert float(r["J1"]) == float(s["J1"].sel(**cell)) / nom


def test_grid_folder_without_index_says_rerun(tmp_path):
    from experiments import mecanum_grid as mg
    settings = _settings("mecanum-grid", path="turn180", N=(2,), dp=(0.0,), case="SR", chunk=4)
    mg.run_grid(settings, seeds=2, out=tmp_path, progress=False)
    doc = json.loads((tmp_path / "results.json").read_text())
    del doc["results"]["per_seed"]                            # as an older jaxnc wrote it
    (tmp_path / "results.json").write_text(json.dumps(doc))
    with pytest.raises(FileNotFoundError, match="results.json: lists no per-seed cells.*rerun"):
        jaxnc.load(tmp_path)


def test_hdd_dataset_means_are_the_printed_table(tmp_path, capsys):
    from experiments import hdd
    summary = hdd.run(_settings("hdd", case="2"), seeds=3, out=tmp_path, progress=False)
    printed = capsys.readouterr().out
    ds = jaxnc.load(tmp_path)
    assert list(ds["case"].values) == ["2"] and ds.sizes["seed"] == 3
    s = ds.jaxnc.summary()
    for k in hdd.METRICS:
        assert _same(float(s[k].sel(case="2")), summary[2][k]["mean"])
    row = _row(printed, "2 PETC")
    assert row[1] == fmt(float(s["Uc"].sel(case="2"))) and row[10] == fmt(float(s["GPI"].sel(case="2")), 3)


# The balancing run's dataset against its printed table: tests/test_experiment_balancing.py
# (test_the_dataset_means_are_the_printed_table), on the folder its quick run writes.


# ----------------------------------------------------------------------------- one folder, one run


def test_claim_records_the_run_and_refuses_what_would_mix_or_overwrite(tmp_path):
    results.claim(tmp_path, "toy", {"k": 1, "t": (0.1, 0.2)}, 5)
    doc = json.loads((tmp_path / results.RUN_FILE).read_text())
    run = doc.pop("run")
    assert doc == {"format": "jaxnc-run-1", "experiment": "toy", "settings": {"k": 1, "t": [0.1, 0.2]}, "seeds": 5}
    assert results.run_id(tmp_path) == run and re.fullmatch("[0-9a-f]{32}", run)
    assert results.folder_owner(tmp_path) == {"experiment": "toy", "settings": {"k": 1, "t": [0.1, 0.2]}, "seeds": 5}
    results.claim(tmp_path, "toy", {"k": 2, "t": (0.1, 0.2)}, 5)     # nothing finished yet: nothing to lose
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={}, results={}, wall_time_s=0.0)
    results.claim(tmp_path, "toy", {"k": 2, "t": [0.1, 0.2]}, 5)     # the same run again (tuples as lists)
    with pytest.raises(results.FolderError, match=r"holds the results of toy with other settings \(k: 2 there, 3 "
                                                  r"here; t: 0.1,0.2 there, 0.3 here; seeds: 5 there, 6 here\)"):
        results.claim(tmp_path, "toy", {"k": 3, "t": (0.3,)}, 6)
    assert results.claim(tmp_path, "toy", {"k": 3, "t": (0.3,)}, 6, keeps_cells=True) == [  # a sweep's cells stay apart
        "k: 2 there, 3 here", "t: 0.1,0.2 there, 0.3 here", "seeds: 5 there, 6 here"]
    with pytest.raises(results.FolderError, match="holds the results of experiment 'toy', not 'other'"):
        results.claim(tmp_path, "other", {"k": 3, "t": (0.3,)}, 6, keeps_cells=True)
    assert results.folder_owner(tmp_path)["settings"] == {"k": 3, "t": [0.3]}


def test_a_folder_without_run_file_is_owned_by_its_results_file(tmp_path):
    assert results.folder_owner(tmp_path) is None
    montecarlo.save_results(tmp_path / "results.json", experiment="mecanum",
                            config={"settings": {"N": 2}, "seeds": 4}, results={}, wall_time_s=0.0)
    assert results.folder_owner(tmp_path) == {"experiment": "mecanum", "settings": {"N": 2}, "seeds": 4}
    with pytest.raises(results.FolderError, match=r"\(N: 2 there, 3 here\)"):
        results.claim(tmp_path, "mecanum", {"N": 3}, 4)
    (tmp_path / results.RUN_FILE).write_text("{damaged")                 # unreadable: the results file says
    with pytest.raises(results.FolderError, match="not 'hdd'"):
        results.claim(tmp_path, "hdd", {}, 4)


def test_a_run_stopped_between_its_two_files_is_not_loaded_with_the_former_runs_summary(tmp_path):
    # run A finished; run B of the same settings (other code: other numbers) claimed the folder
    # and wrote its seeds.npz, then stopped before results.json: load gave B's seeds under A's summary
    results.claim(tmp_path, "toy", {"k": 1}, 4)
    results.save_per_seed(tmp_path, {"A": _metrics(4)}, experiment="toy")
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"settings": {"k": 1}, "seeds": 4},
                            results={"J1": 1.5}, wall_time_s=0.0)
    assert float(jaxnc.load(tmp_path).J1.mean()) == 1.5
    results.claim(tmp_path, "toy", {"k": 1}, 4)
    results.save_per_seed(tmp_path, {"A": _metrics(4, 10.0)}, experiment="toy")
    with pytest.raises(ValueError, match="mixes the files of two runs: seeds.npz was written by run [0-9a-f]{32}, "
                                         "results.json by run [0-9a-f]{32}"):
        jaxnc.load(tmp_path)
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"settings": {"k": 1}, "seeds": 4},
                            results={"J1": 11.5}, wall_time_s=0.0)
    assert float(jaxnc.load(tmp_path).J1.mean()) == 11.5            # B finished: its own files


def test_a_run_killed_by_a_signal_after_its_per_seed_file_leaves_a_folder_load_refuses(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    results.claim(tmp_path, "toy", {"k": 1}, 4)
    results.save_per_seed(tmp_path, {"A": _metrics(4)}, experiment="toy")
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"settings": {"k": 1}, "seeds": 4},
                            results={}, wall_time_s=0.0)
    script = ("import os, signal, sys, numpy as np\n"
              "from jaxnc import results\n"
              "results.claim(sys.argv[1], 'toy', {'k': 1}, 4)\n"
              "results.save_per_seed(sys.argv[1], {'A': {'J1': np.full(4, 7.0, np.float32), "
              "'unstable': np.zeros(4, bool)}}, experiment='toy')\n"
              "os.kill(os.getpid(), signal.SIGKILL)\n")
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], env=env, capture_output=True, timeout=120)
    assert done.returncode == -signal.SIGKILL, done.stderr.decode()
    with pytest.raises(ValueError, match="mixes the files of two runs"):
        jaxnc.load(tmp_path)
    assert not list(tmp_path.glob(".*.tmp"))


def test_units_reach_the_dataset_and_its_summary(tmp_path):
    from jaxnc import loop as nc
    m = nc.Metrics(cost=np.arange(4, dtype=np.float32), cost_raw=np.arange(4, dtype=np.float32),
                   rate_sc=np.full(4, 0.5, np.float32), rate_ca=np.ones(4, np.float32), unstable=np.zeros(4, bool),
                   unstable_action=np.zeros(4, bool))
    results.save_per_seed(tmp_path, {"A": m}, units={"cost": "m^2"})          # the runner's rates: its own units
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"seeds": 4}, results={},
                            wall_time_s=0.0)
    ds = jaxnc.load(tmp_path)
    assert {k: v.attrs.get("units") for k, v in ds.data_vars.items()} == {
        "cost": "m^2", "cost_raw": None, "rate_sc": "transmissions per slow period",
        "rate_ca": "transmissions per slow period", "unstable": None, "unstable_action": None}
    s = ds.jaxnc.summary()
    assert [s[k].attrs.get("units") for k in ("cost", "cost_ci95", "cost_std", "cost_n_stable", "n")] == [
        "m^2", "m^2", "m^2", None, None]
    assert float(s["rate_sc"].sel(case="A")) == 0.5
    # a sweep's index carries them too, through a combination never run (present False)
    cells = {}
    for k in ("a", "b"):
        np.savez(tmp_path / f"{k}.npz", J1=np.ones(3, np.float32), unstable=np.zeros(3, bool))
        cells[(k, 1)] = tmp_path / f"{k}.npz"
    del cells[("b", 1)]
    cells[("b", 2)] = tmp_path / "b.npz"
    (tmp_path / "seeds.npz").unlink()
    montecarlo.save_results(tmp_path / "results.json", experiment="grid", config={"seeds": 3}, wall_time_s=0.0,
                            results={"per_seed": results.per_seed_index(tmp_path, cells, ("x", "y"),
                                                                        units={"J1": "mm"})})
    ds = jaxnc.load(tmp_path)
    assert ds.J1.attrs["units"] == "mm" and not bool(ds.present.sel(x="a", y=2))
    s = ds.jaxnc.summary()
    assert s.J1.attrs["units"] == "mm" and s.J1_ci95.attrs["units"] == "mm"


def test_per_seed_file_names_its_experiment(tmp_path):
    results.save_per_seed(tmp_path, {"A": _metrics(3)}, experiment="toy")
    montecarlo.save_results(tmp_path / "results.json", experiment="toy", config={"seeds": 3}, results={},
                            wall_time_s=0.0)
    assert jaxnc.load(tmp_path).attrs["experiment"] == "toy"
    montecarlo.save_results(tmp_path / "results.json", experiment="hdd", config={"seeds": 3}, results={},
                            wall_time_s=0.0)
    with pytest.raises(ValueError, match="mixes the files of two experiments: results.json is 'hdd''s, "
                                         "seeds.npz 'toy''s"):
        jaxnc.load(tmp_path)


def test_save_figure_writes_the_file_at_its_dpi_and_closes_the_figure(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from jaxnc.report import save_figure
    fig, ax = plt.subplots(figsize=(2, 1))
    ax.plot([0, 1], [1, 0])
    n_open = len(plt.get_fignums())
    p = save_figure(fig, str(tmp_path / "a.png"), dpi=50)
    assert p == tmp_path / "a.png" and p.is_file()
    assert Image.open(p).size == (100, 50)                  # 2 x 1 inches at 50 dpi
    assert len(plt.get_fignums()) == n_open - 1
def _servo_loop(p=0.3, delta=0.01, N=2, w=0.01):
    from jaxnc import loop as nc
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 1.0]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                   w_std=[w, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05**2, mean0=[0.0, 0.0], cov0=np.eye(2))
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=nc.Link(nc.Bernoulli(p)), estimator=ekf,
                   controller=nc.StateFeedback(np.asarray([[3.0, 1.5]])), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=N, steps=40, T=0.1)


def test_config_of_a_loop_names_every_leaf_so_a_changed_loop_is_another_cell(tmp_path):
    """results.config_of(loop) is JSON with every part's type and fields (static ones too): equal
    loops give one sweep cell file, and a change to any leaf (the process noise, a loss
    probability, the threshold), a static field (N) or a part's type gives another, so a user
    sweep whose cell configuration holds it does not reuse a cell of the old loop (one whose
    configuration held only its grid values reused it: a cost of 0.051 reported for a loop
    with three times the noise, whose cost is 0.111)."""
    from jaxnc import loop as nc
    from jaxnc import sweep
    base = results.config_of(_servo_loop())
    text = json.dumps(base, allow_nan=False)
    assert json.loads(text) == base and base["type"] == "Loop"
    assert base["uplink"]["loss"] == {"type": "Bernoulli", "p": pytest.approx(0.3)}
    assert base["trigger"]["delta"] == pytest.approx(0.01) and base["N"] == 2 and base["steps"] == 40
    assert base["plant"]["w_std"] == pytest.approx([0.01, 0.02])
    cell = lambda cfg: sweep.cell_path(tmp_path, "c", {"loop": cfg, "seeds": 64})
    assert cell(results.config_of(_servo_loop())) == cell(base)
    changed = [_servo_loop(w=0.03), _servo_loop(p=0.31), _servo_loop(delta=0.02), _servo_loop(N=4),
               dataclasses.replace(_servo_loop(), trigger=nc.Periodic())]
    paths = {cell(results.config_of(v)) for v in changed}
    assert len(paths) == len(changed) and cell(base) not in paths
    sweep.save_cell(cell(base), {"config": {"loop": base, "seeds": 64}})
    assert sweep.load_cell(cell(base), {"loop": results.config_of(_servo_loop()), "seeds": 64}) is not None
    assert sweep.load_cell(cell(base), {"loop": results.config_of(_servo_loop(w=0.03)), "seeds": 64}) is None
    assert results.config_of(np.sin).endswith("sin") and results.config_of({"f": (1, np.float32(2))}) == {"f": [1, 2.0]}
    with pytest.raises(TypeError, match=r"config_of: config\.x of type object"):
        results.config_of(_Holder(object()))


@dataclasses.dataclass(frozen=True)
class _Holder:
    x: object


_GAIN = 2.0


def _cost_global(x):
    return _GAIN * x


def test_config_of_a_function_tells_an_edited_body_a_closure_a_partial_and_a_read_constant_apart(tmp_path):
    """config_of describes a Python function by its name *and* its code, the values it closes
    over, its defaults and the module constants it reads, so a sweep cell of a loop whose cost
    or dynamics function changed is not reused. Before, only the qualified name was kept: two
    lambdas of one module, two closures of one factory (gains 1 and 2), two
    ``functools.partial`` of one function and a function whose module constant changed each
    gave one configuration, so a stored result of the other function was returned."""
    import functools
    global _GAIN
    f1 = lambda x: x ** 2                                   # noqa: E731
    f2 = lambda x: 2.0 * x ** 2                             # noqa: E731
    assert results.config_of(f1) != results.config_of(f2)
    assert results.config_of(f1) == results.config_of(f1)

    def make(k):
        return lambda x: k * x
    assert results.config_of(make(1.0)) != results.config_of(make(2.0))
    assert results.config_of(make(1.0)) == results.config_of(make(1.0))
    assert results.config_of(make(np.ones(2)))["closure"]["k"] == [1.0, 1.0]
    pw = functools.partial(np.power, 2.0)
    assert results.config_of(functools.partial(pow, exp=2)) != results.config_of(functools.partial(pow, exp=3))
    assert results.config_of(pw)["partial"].endswith("power")
    before = results.config_of(_cost_global)
    assert before["globals"] == {"_GAIN": 2.0}
    _GAIN = 3.0
    try:
        assert results.config_of(_cost_global) != before
    finally:
        _GAIN = 2.0
    assert results.config_of(_cost_global) == before
    assert json.loads(json.dumps(results.config_of(make(object())))) == results.config_of(make(object()))

    def rec(n):                                             # refers to itself: no endless recursion
        return 1 if n <= 0 else rec(n - 1)
    assert results.config_of(rec)["closure"]["rec"].endswith("rec")


_USER_PARTS = """
import jax.numpy as jnp
from jaxnc import loop as nc
from jaxnc.loop.base import AbstractPlant


@nc.pytree_dataclass
class Integrator(AbstractPlant):
    a: float = 1.0
    state_dim = 1
    input_dim = 1
    noise_dim = 1
    output_dim = 1

    def dynamics(self, x, u, w):
        return self.a * x + u + w

    def measure(self, x, v):
        return x + v


class Gain:
    def __init__(self, k):
        self.k = k

    def __call__(self, x, u):
        return self.k * jnp.mean(x * x)
"""


def _user_module(name, source=_USER_PARTS):
    import types
    module = types.ModuleType(name)
    exec(compile(source, f"/users/{name}.py", "exec"), module.__dict__)
    return module


def test_config_of_a_users_part_tells_an_edited_method_and_another_modules_class_apart():
    """A part a user writes (a dataclass subclassing a role's base class, as
    docs/build_your_own_loop.md shows) was described by its class name and fields only: its
    edited ``dynamics``, or a class of the same name in another module, gave the same
    configuration, so a sweep cell of the old plant was reused (and two such sweeps shared
    one cell file). A callable object of the user's (a cost) was its type name only, whatever
    its attributes. Now its module, its methods' code and its class-level data count."""
    a = _user_module("user_a")
    same = _user_module("user_a")
    edited = _user_module("user_a", _USER_PARTS.replace("return self.a * x + u + w", "return self.a * x + 2 * u + w"))
    other = _user_module("user_b")
    config = lambda m: results.config_of(m.Integrator(a=1.0))
    assert config(a) == config(same) and json.loads(json.dumps(config(a))) == config(a)
    assert config(a) != config(edited)                      # its dynamics edited
    assert config(a) != config(other)                       # another module's Integrator
    assert config(a)["a"] == 1.0 and config(a)["type"] == "Integrator"
    gain = lambda m, k: results.config_of(m.Gain(k))
    assert gain(a, 1.0) == gain(same, 1.0) and gain(a, 1.0) != gain(a, 2.0)
    assert gain(a, 1.0) != gain(_user_module("user_a", _USER_PARTS.replace("self.k * jnp.mean", "self.k * jnp.sum")), 1.0)
