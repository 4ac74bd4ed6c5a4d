"""The tune-study experiment (experiments/tune_study.py): the time-budgeted searches on a
closed-form objective, and the whole study in a tiny size (the two-parameter HDD problem,
which runs all six methods), its files, and the reuse of a stored problem."""
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import montecarlo
from jaxnc.experiment import load_builtin

load_builtin()
from jaxnc.experiments import tune_study as ts  # noqa: E402

BOUNDS = {"a": (1e-4, 1.0, "log"), "b": (0.5, 2.0, "log")}


def _per_seed(p, key):
    """(log10 a + 2)^2 + (log2 b)^2 + noise: the minimum 0 at a = 0.01, b = 1."""
    return (jnp.log10(p["a"]) + 2.0) ** 2 + jnp.log2(p["b"]) ** 2 + 0.01 * jax.random.normal(key)


def test_random_search_spends_its_time_and_finds_the_minimum_region():
    ts.evaluate(_per_seed, {"a": 0.1, "b": 1.0}, montecarlo.seed_keys(0, 4), chunk_size=4)   # compiled before
    r = ts.random_search_timed(_per_seed, BOUNDS, budget_s=0.5, seeds=4, seed=1)
    assert r["wall_time_s"] >= 0.5                          # runs until the budget is spent
    assert r["n_points"] >= 2 and r["simulations"] == 4 * r["n_points"]
    times = [row["t"] for row in r["trace"]]
    assert times == sorted(times) and [row["mean"] for row in r["trace"]] == sorted((row["mean"] for row in r["trace"]),
                                                                                 reverse=True)
    assert r["best"] == r["trace"][-1]["point"]
    # the incumbent is the best of the points run: no other point of the stream does better
    stream = ts.random_stream(1, BOUNDS)                               # the points random_search_timed draws
    pts = [next(stream) for _ in range(r["n_points"])]
    f = lambda p: (math.log10(p["a"]) + 2) ** 2 + math.log2(p["b"]) ** 2
    assert f(r["best"]) <= min(f(p) for p in pts) + 0.05


def test_halving_sizes_itself_to_the_budget_and_keeps_the_better_half():
    start = {"a": 0.1, "b": 1.5}
    t0 = time.perf_counter()
    r = ts.halving_timed(_per_seed, BOUNDS, start, budget_s=1.0, seeds=4, seed=2)
    assert r["n_candidates"] >= 2
    assert 1 <= r["rounds_done"] <= r["rounds"] == math.ceil(math.log2(r["n_candidates"]))
    assert r["wall_time_s"] <= time.perf_counter() - t0
    # candidates per round halve; the seeds double (every round the same n x seeds simulations)
    n = [row["n_points"] for row in r["trace"]]
    assert n == [math.ceil(r["n_candidates"] / 2 ** i) for i in range(r["rounds_done"])]
    assert [row["seeds"] for row in r["trace"]] == [4 * (2 ** (i + 1) - 1) for i in range(r["rounds_done"])]
    f = lambda p: (math.log10(p["a"]) + 2) ** 2 + math.log2(p["b"]) ** 2
    pts = ts.random_points(2, r["n_candidates"], **BOUNDS)
    assert f(r["best"]) <= np.median([f(p) for p in pts])


def test_tune_study_tiny_end_to_end_writes_and_resumes(tmp_path, capsys):
    settings = dict(loops="hdd-grid", budget_s=0.0, steps=3, batch=4, estimator="score", two_stage=0.3,
                    check_seeds=4, check_max_seeds=4, search_seeds=4, sh_seeds=2, grid_seeds=2, grid_shape=(2, 2),
                    curve_seeds=4, hdd_h=4, hdd_steps=40, w_cartpole=2.0, seed=0)
    res = ts.run(settings, seeds=8, out=tmp_path, progress=False)["hdd-grid"]
    m = res["methods"]
    assert set(m) == {"grid", "tuner", "tuner-box", "two-stage", "random", "halving"}
    for name, d in m.items():
        assert d["wall_time_s"] > 0 and 0 <= d["compile_s"] <= d["wall_time_s"] + 1e-6, name
        assert d["simulations"] > 0 and d["trace"], name
        assert all(np.isfinite(row["eval"][0]) for row in d["trace"]), name
    # equal wall time: random search runs until the tuner's time is spent
    assert m["random"]["wall_time_s"] >= m["tuner"]["wall_time_s"]
    for name in ts.TUNERS:
        assert m[name]["estimator"] == "score" and 1 <= m[name]["steps_done"] <= 3, name
        # the tuner's own overheads, without its evaluation (the study evaluates every point)
        st = m[name]["stages"]
        assert "gradient" in st and "check" not in st and "evaluation" not in st, name
    # the box-confined tuner stays inside the searches' box
    for n, v in m["tuner-box"]["best"].items():
        lo, hi, _ = res["bounds"][n]
        assert lo < v < hi, n
    assert m["two-stage"]["search_points"] >= 1 and m["two-stage"]["search_s"] > 0
    assert m["tuner"]["compilations"] >= 1 and 0 < m["tuner"]["own_compile_s"] <= m["tuner"]["wall_time_s"]
    e = res["eval"]
    assert e["seeds"] == 8 and set(e["mean"]) == {"start", *m}
    # a paired difference is the difference of the means (same fresh seeds)
    for k, (d, _) in e["paired"].items():
        a, b = k.split(" - ")
        assert abs(d - (e["mean"][a][0] - e["mean"][b][0])) < 1e-9, k
    for name, gc in res["grid_check"].items():
        assert gc["not_slower"] == (m[name]["wall_time_s"] <= m["grid"]["wall_time_s"])
        diff = e["paired"].get(f"{name} - grid", (None,))[0]
        diff = -e["paired"][f"grid - {name}"][0] if diff is None else diff
        assert abs(gc["over_grid"][0] - diff / e["mean"]["grid"][0]) < 1e-9
    for f in ("hdd-grid.json", "results.json", "tables.md", "tune_study.png"):
        assert (tmp_path / f).exists(), f
    before = (tmp_path / "hdd-grid.json").read_bytes()
    capsys.readouterr()
    again = ts.run(settings, seeds=8, out=tmp_path, progress=True)["hdd-grid"]
    assert "reusing" in capsys.readouterr().out
    assert (tmp_path / "hdd-grid.json").read_bytes() == before
    assert json.dumps(again, sort_keys=True) == json.dumps(
        montecarlo.load_results(tmp_path / "hdd-grid.json")["results"], sort_keys=True)
