"""Monte-Carlo engine: seed keys, chunked vmap, statistics, atomic results files."""
import json
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import montecarlo as mc


# ----------------------------------------------------------------------------- seed_keys


def test_seed_keys_independent_of_batch():
    k10 = np.asarray(mc.seed_keys(0, 10))
    k100 = np.asarray(mc.seed_keys(0, 100))
    assert k10.shape == (10, 2) and k100.shape == (100, 2)
    np.testing.assert_array_equal(k10[7], k100[7])
    np.testing.assert_array_equal(k10, k100[:10])
    np.testing.assert_array_equal(np.asarray(mc.seed_keys(0, 5, start=5))[2], k10[7])
    direct = jax.random.fold_in(jax.random.PRNGKey(0), 7)
    np.testing.assert_array_equal(k10[7], np.asarray(direct))


def test_seed_keys_are_fold_in_across_blocks_and_compile_once_for_every_size():
    """Seed i's key is fold_in(PRNGKey(seed), i) also across the blocks seed_keys makes them in
    (KEY_BLOCK at a time) and near the top of the uint32 range; a new number of seeds compiles
    nothing (it compiled a program per n: a compilation for every batch size a study used)."""
    from jaxnc.cache import compile_clock
    ref = lambda seed, n, start: np.asarray(jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(
        jnp.arange(start, start + n, dtype=jnp.uint32)))
    B = mc.KEY_BLOCK
    for seed, n, start in ((7, B, 0), (3, B + 1, 10), (2**32 - 1, 2 * B + 5, 123), (0, 3, 2**32 - 3)):
        k = mc.seed_keys(seed, n, start)
        assert k.shape == (n, 2) and k.dtype == jnp.uint32
        np.testing.assert_array_equal(np.asarray(k), ref(seed, n, start))
    before = compile_clock()
    for n in (17, 300, 1000, B + 7):
        mc.seed_keys(5, n, start=n)
    assert (compile_clock() - before).compilations == 0


def test_seed_keys_distinct():
    k = np.asarray(mc.seed_keys(3, 50))
    assert len({tuple(r) for r in k}) == 50
    assert not np.array_equal(np.asarray(mc.seed_keys(4, 50)), k)
    assert mc.seed_keys(0, 0).shape == (0, 2)


# ----------------------------------------------------------------------------- run_batched


def _normal_sum(key):
    return jax.random.normal(key, (3,)).sum()


def _walk(key):
    steps = jax.random.normal(key, (20,))

    def body(x, dx):
        x = x + dx
        return x, x

    last, path = jax.lax.scan(body, jnp.zeros(()), steps)
    return {"last": last, "path": path, "hit": jnp.any(path > 1.0)}


@pytest.mark.parametrize("n", [1, 13, 20])
def test_run_batched_chunk_invariant(n):
    keys = mc.seed_keys(1, n)
    ref = np.stack([np.asarray(_normal_sum(k)) for k in keys])
    for chunk in (1, 7, 256):
        out = mc.run_batched(_normal_sum, keys, chunk_size=chunk, progress=False)
        assert isinstance(out, np.ndarray) and out.shape == (n,)
        np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6)


def test_run_batched_pytree_and_scan():
    n = 23                                  # not divisible by 7 or 5
    keys = mc.seed_keys(2, n)
    outs = [mc.run_batched(_walk, keys, chunk_size=c, progress=False) for c in (1, 7, 256)]
    ref = outs[-1]
    assert set(ref) == {"last", "path", "hit"}
    assert ref["last"].shape == (n,) and ref["path"].shape == (n, 20) and ref["hit"].shape == (n,)
    assert ref["hit"].dtype == np.bool_
    for o in outs[:-1]:
        for name in ref:
            np.testing.assert_allclose(o[name], ref[name], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(ref["last"], ref["path"][:, -1], rtol=1e-6)
    # row i depends only on key i: a subset of the keys gives the same rows
    sub = mc.run_batched(_walk, mc.seed_keys(2, 6, start=10), chunk_size=1, progress=False)
    np.testing.assert_allclose(sub["path"], ref["path"][10:16], rtol=1e-6, atol=1e-6)


def test_run_batched_progress_and_empty(capsys):
    out = mc.run_batched(_normal_sum, mc.seed_keys(0, 5), chunk_size=2, progress=True, desc="test")
    assert out.shape == (5,)
    empty = mc.run_batched(_walk, mc.seed_keys(0, 0), progress=False)
    assert empty["path"].shape == (0, 20)
    from jaxnc.loop import Metrics
    z = np.zeros((0,), np.float32)
    assert repr(Metrics(z, z, z, z, z.astype(bool), z.astype(bool))) == "Metrics over 0 runs"    # printing no runs used to raise
    with pytest.raises(ValueError):
        mc.run_batched(_normal_sum, mc.seed_keys(0, 3), chunk_size=0, progress=False)


def test_run_batched_typed_keys():
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(0), i))(jnp.arange(5))
    out = mc.run_batched(_normal_sum, keys, chunk_size=2, progress=False)
    ref = np.stack([np.asarray(_normal_sum(k)) for k in keys])
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6)


def test_run_batched_compiles_once_per_fn():
    traces = []

    def fn(key):
        traces.append(1)
        return jax.random.uniform(key)

    keys = mc.seed_keys(0, 10)
    mc.run_batched(fn, keys, chunk_size=4, progress=False)   # 3 chunks, one compilation
    assert len(traces) == 1
    mc.run_batched(fn, keys, chunk_size=4, progress=False)   # cached for the same fn
    assert len(traces) == 1


def test_chunk_lanes_caps_only_a_chunk_over_the_memory_budget(monkeypatch):
    # within the budget the chunk is as given (a seed alone or in a batch: one program)
    assert mc.chunk_lanes(64, 1, out_bytes=40) == 64
    assert mc.chunk_lanes(1000, 4, out_bytes=40, devices=2) == 1024
    # issue 33: chunk_size=2e8 with 4 seeds allocated 7.2 GB; now one group of lanes
    assert mc.chunk_lanes(200_000_000, 4, out_bytes=4) == mc.LANES
    # a huge chunk over many seeds: the lanes that fit in CHUNK_MEMORY, a whole number of groups
    size = mc.chunk_lanes(200_000_000, 10**9, out_bytes=4000, devices=3)
    assert size % (3 * mc.LANES) == 0 and size * (mc.LANE_BYTES + 4000) <= mc.CHUNK_MEMORY
    assert (size + 3 * mc.LANES) * (mc.LANE_BYTES + 4000) > mc.CHUNK_MEMORY
    monkeypatch.setattr(mc, "CHUNK_MEMORY", 100)                 # never below one group
    assert mc.chunk_lanes(64, 1000, out_bytes=40) == mc.LANES


def test_run_batched_with_a_huge_chunk_runs_the_seeds_in_bounded_memory():
    keys = mc.seed_keys(5, 4)
    ref = mc.run_batched(_walk, keys, chunk_size=4, progress=False)
    t0 = time.perf_counter()
    out = mc.run_batched(_walk, keys, chunk_size=200_000_000, progress=False)
    assert time.perf_counter() - t0 < 20                          # (it allocated 7.2 GB)
    for k in ref:                                                 # both ran one 16-lane chunk
        np.testing.assert_array_equal(out[k], ref[k])


def test_results_that_cannot_fit_are_refused_before_running(monkeypatch):
    calls = []

    def fn(key):
        calls.append(1)                      # traced (eval_shape), never run
        return jnp.zeros((250,), jnp.float32)

    monkeypatch.setattr(mc, "available_memory", lambda: 10_000)
    with pytest.raises(mc.MemoryBudgetError, match=r"run_batched: the results of 10 seeds need .* \(2000 bytes per "
                                                   r"seed\), more than the .* available; at most 5 seeds fit"):
        mc.run_batched(fn, mc.seed_keys(0, 10), chunk_size=4, progress=False)
    assert mc.run_batched(fn, mc.seed_keys(0, 5), chunk_size=4, progress=False).shape == (5, 250)
    monkeypatch.setattr(mc, "available_memory", lambda: None)       # unknown: no check
    assert mc.run_batched(fn, mc.seed_keys(0, 10), chunk_size=4, progress=False).shape == (10, 250)


def test_available_memory_is_a_positive_byte_count_or_unknown():
    free = mc.available_memory()
    assert free is None or (isinstance(free, int) and free > 0)


# ----------------------------------------------------------------------------- summarize


def test_summarize_excludes_unstable():
    v = np.array([1.0, 2.0, 3.0, 100.0, 4.0])
    u = np.array([False, False, False, True, False])
    s = mc.summarize(v, u)
    good = np.array([1.0, 2.0, 3.0, 4.0])
    assert s.n == 5 and s.n_stable == 4
    assert s.unstable_fraction == pytest.approx(0.2)
    assert s.mean == pytest.approx(good.mean())
    assert s.std == pytest.approx(np.std(good, ddof=1))
    assert s.ci95 == pytest.approx(1.96 * np.std(good, ddof=1) / np.sqrt(4))
    d = s.to_dict()
    assert set(d) == {"mean", "ci95", "std", "n", "n_stable", "unstable_fraction"}


def test_summarize_without_a_stable_run_is_inf_only_for_a_divergent_cost():
    """No stable run: inf only where the value is +inf in every run (the papers' ∞ for a
    failed run's cost), else nan (describe's '–'): a rate of failed runs, 1.0 here, used to
    summarise as inf, a number no run had."""
    s = mc.summarize(np.ones(4), np.ones(4, bool))
    assert math.isnan(s.mean) and s.n_stable == 0 and s.unstable_fraction == 1.0
    assert math.isnan(s.ci95)
    s = mc.summarize(np.full(4, np.inf), np.ones(4, bool))
    assert s.mean == math.inf and s.n_stable == 0 and math.isnan(s.ci95)
    s = mc.summarize(np.array([np.inf, 2.0]), np.ones(2, bool))
    assert math.isnan(s.mean) and s.n_stable == 0


def test_summarize_nonfinite_counts_as_unstable():
    v = np.array([1.0, np.nan, 3.0, np.inf])
    s = mc.summarize(v, np.zeros(4, bool))
    assert s.n_stable == 2 and s.unstable_fraction == 0.5
    assert s.mean == pytest.approx(2.0) and math.isfinite(s.ci95)
    one = mc.summarize(np.array([5.0, np.nan]), np.zeros(2, bool))
    assert one.mean == 5.0 and one.n_stable == 1 and math.isnan(one.ci95)


def test_metrics_print_as_a_summary_of_the_batch():
    """print(run_batched(...)) of the runner's Metrics: one line per field (mean and 95 %
    half-width over the stable runs, as summarize); one run prints its values; traced or
    other shapes keep the plain tuple repr."""
    from jaxnc.loop.runner import Metrics
    m = Metrics(jnp.array([1.0, 3.0, jnp.inf, 2.0]), jnp.array([1.0, 3.0, 9.0, 2.0]), jnp.full(4, 0.5),
                jnp.ones(4), jnp.array([False, False, True, False]), jnp.array([False, False, True, False]))
    lines = repr(m).splitlines()
    assert str(m) == repr(m) and lines[0] == "Metrics over 4 runs (mean +- 95 % over the stable runs)"
    s = mc.summarize(np.array([1.0, 3.0, np.inf, 2.0]), np.array([False, False, True, False]))
    assert lines[1].split() == ["cost", f"{s.mean:.6g}", "+-", f"{s.ci95:.2g}", "(1", "left", "out:", "unstable",
                                "or", "not", "finite)"]
    assert lines[2].split()[:2] == ["cost_raw", "2"] and lines[5].split() == ["unstable", "0.25", "of", "the", "runs"]
    assert lines[6].split() == ["unstable_action", "0.25", "of", "the", "runs"]
    one = jax.tree.map(lambda a: a[0], m)
    assert repr(one) == "Metrics(cost=1, cost_raw=1, rate_sc=0.5, rate_ca=1, unstable=False, unstable_action=False)"
    seen = []
    jax.jit(lambda t: seen.append(repr(t)) or t)(m)
    assert seen[0].startswith("Metrics(cost=") and "float32[4]" in seen[0]
    assert repr(jax.tree.map(lambda a: a[:, None], m)).startswith("Metrics(cost=Array(")


def test_seeds_for_normal_interval_is_cochrans_rule_on_the_sample_skewness():
    """n > 28 + 25 G1^2 (Sugden, Smith and Jones 2000). A 0/1 sample with exactly k ones in n
    has the closed-form skewness (1 - 2p) / sqrt(p (1 - p)), p = k / n; the rule is affine
    invariant; symmetric samples need the floor of 28 (+1); too few values give 28."""
    for n, k in ((1000, 5), (512, 3), (200, 100)):
        x = np.zeros(n)
        x[:k] = 1.0
        p = k / n
        g1 = (1 - 2 * p) / math.sqrt(p * (1 - p))
        assert mc.seeds_for_normal_interval(x) == math.floor(28 + 25 * g1 ** 2) + 1
        # a rare failure at 20x the typical cost, anywhere on the scale: the same rule
        assert mc.seeds_for_normal_interval(5.0 + 95.0 * x) == mc.seeds_for_normal_interval(x)
    assert mc.seeds_for_normal_interval(np.r_[np.zeros(995), np.ones(5)]) > 4000   # 1000 seeds are too few
    assert mc.seeds_for_normal_interval(np.array([-1.0, 0.0, 1.0])) == 29
    assert mc.seeds_for_normal_interval([1.0, 2.0]) == 28 and mc.seeds_for_normal_interval(np.ones(9)) == 28
    assert mc.seeds_for_normal_interval(np.r_[np.zeros(10), np.inf, np.nan]) == 28   # non-finite values dropped
    a = np.r_[np.full(509, 5.0), np.full(3, 100.0)]
    assert mc.seeds_for_normal_interval((a - 0.1) - a) == 28     # a constant difference up to rounding has no skew


def test_seeds_for_paired_interval_counts_each_point_and_the_differences():
    """Two points with the same three rare failures agree on every seed (differences nearly
    symmetric), yet each point's mean needs thousands of seeds: the paired count is the
    largest of the three; unequal shapes (not paired) raise."""
    a = np.r_[np.full(509, 5.0), np.full(3, 100.0)] + np.linspace(-1.0, 1.0, 512)
    b = a + np.linspace(-0.5, 0.5, 512)[::-1]
    n_a, n_b, n_d = (mc.seeds_for_normal_interval(v) for v in (a, b, a - b))
    assert n_d < 100 < 2000 < min(n_a, n_b)
    assert mc.seeds_for_paired_interval(a, b) == max(n_a, n_b, n_d) == mc.seeds_for_paired_interval(b, a)
    # differences skewed more than either point: the differences decide
    c = a.copy()
    c[10] += 400.0
    assert mc.seeds_for_paired_interval(a, c) == mc.seeds_for_normal_interval(a - c) > mc.seeds_for_normal_interval(a)
    with pytest.raises(ValueError, match="same shape"):
        mc.seeds_for_paired_interval(a, b[:-1])


def test_describe_flags_a_field_too_skewed_for_its_interval():
    """print(metrics) of a batch whose cost has 3 failures in 512 runs says the interval needs
    thousands of runs; a symmetric field does not."""
    from jaxnc.loop.runner import Metrics
    n = 512
    cost = np.full(n, 5.0)
    cost[:3] = 100.0
    cost[3:] += np.linspace(-1, 1, n - 3)
    sym = np.linspace(0.0, 1.0, n)
    m = Metrics(jnp.asarray(cost), jnp.asarray(sym), jnp.asarray(sym), jnp.asarray(sym), jnp.zeros(n, bool), jnp.zeros(n, bool))
    lines = repr(m).splitlines()
    need = mc.seeds_for_normal_interval(cost)
    assert need > 2000
    assert lines[1].split()[0] == "cost" and f"needs about {need} runs (Cochran's rule), not {n}" in lines[1]
    assert all("skewed" not in ln for ln in lines[2:])


def test_describe_shows_no_mean_where_every_run_failed():
    """A batch where every run failed: the cost (inf in every failed run) prints inf, the
    transmission rates and a finite cost_raw print a dash with the count of failed runs,
    not summarize's inf (a rate no run had); a loop without a cost (nan, no failure) is
    counted as not finite, and the line says the loop has no cost."""
    from jaxnc.loop.runner import Metrics
    n = 64
    m = Metrics(jnp.full(n, jnp.inf), jnp.linspace(1.0, 2.0, n), jnp.full(n, 0.5), jnp.full(n, 0.25),
                jnp.ones(n, bool), jnp.zeros(n, bool))
    lines = repr(m).splitlines()
    assert lines[1].split() == ["cost", "inf", "(no", "stable", "run:", "all", "64", "failed)"]
    for ln, name in zip(lines[2:5], ("cost_raw", "rate_sc", "rate_ca")):
        assert ln.split() == [name, "\u2013", "(no", "stable", "run:", "all", "64", "failed)"]
    assert "inf" not in "".join(lines[2:5])
    half = Metrics(jnp.full(n, jnp.nan), jnp.full(n, jnp.nan), jnp.full(n, 0.5), jnp.full(n, 0.25),
                   jnp.arange(n) < 10, jnp.zeros(n, bool))
    lines = repr(half).splitlines()
    assert lines[1].split() == ["cost", "\u2013", "(no", "run", "to", "average:", "10", "failed,", "54", "not",
                                "finite;", "the", "loop", "has", "no", "cost", "(Loop(cost=...)))"]
    other = Metrics(jnp.full(n, jnp.nan).at[20].set(jnp.inf), *half[1:])     # not nan in every stable run: no hint
    assert "has no cost" not in repr(other).splitlines()[1]
    assert lines[3].split()[:2] == ["rate_sc", "0.5"] and "(10 left out" in lines[3]


def test_tracking_metrics_print_per_channel_and_count_runs_that_never_settled():
    """TrackingMetrics (float[c] per run): a batch prints one line per field and channel,
    a nan settling time (never settled) is left out and counted; one run prints its values."""
    from jaxnc.loop import TrackingMetrics
    n = 4
    two = jnp.array([[1.0, 10.0], [3.0, 30.0], [2.0, 20.0], [2.0, 20.0]])
    settle = jnp.array([[1.0, jnp.nan], [2.0, 3.0], [jnp.nan, 4.0], [3.0, 5.0]])
    tm = TrackingMetrics(two, two, two, two, two, settle, two)
    lines = repr(tm).splitlines()
    assert lines[0] == f"TrackingMetrics over {n} runs (mean +- 95 % over the stable runs)" and len(lines) == 1 + 14
    s0 = mc.summarize(np.array([1.0, 3.0, 2.0, 2.0]), np.zeros(n, bool))
    assert lines[1].split() == ["ise[0]", f"{s0.mean:.6g}", "+-", f"{s0.ci95:.2g}"]
    assert lines[2].split()[:2] == ["ise[1]", "20"]
    s1 = mc.summarize(np.array([3.0, 4.0, 5.0]), np.zeros(3, bool))
    assert lines[12].split() == ["settling_time[1]", f"{s1.mean:.6g}", "+-", f"{s1.ci95:.2g}", "(1", "left", "out:",
                                 "unstable", "or", "not", "finite)"]
    one = jax.tree.map(lambda a: a[1], tm)
    assert repr(one) == ("TrackingMetrics(ise=[3, 30], iae=[3, 30], itae=[3, 30], overshoot=[3, 30], "
                         "rise_time=[3, 30], settling_time=[2, 3], steady_state_error=[3, 30])")


def test_summarize_ci95_random():
    rng = np.random.default_rng(0)
    v = rng.normal(size=200)
    u = rng.random(200) < 0.1
    s = mc.summarize(v, u)
    good = v[~u]
    assert s.ci95 == pytest.approx(1.96 * good.std(ddof=1) / np.sqrt(good.size), rel=1e-12)
    with pytest.raises(ValueError):
        mc.summarize(np.ones(3), np.zeros(4, bool))


# ----------------------------------------------------------------------------- results files


def _results():
    return {
        "SR": mc.summarize(np.array([1.0, 2.0]), np.array([False, False])),
        "DR": {"mean": math.inf, "ratio": -math.inf, "ci95": float("nan"),
               "n": np.int64(7), "x": np.float32(0.5), "arr": np.array([1.0, np.inf]),
               "jarr": jnp.arange(3), "flag": np.bool_(True), "t": (1, 2.5)},
    }


def test_save_load_roundtrip(tmp_path):
    p = tmp_path / "sub" / "results.json"
    mc.save_results(p, experiment="demo", config={"N": 10, "sigma": (0.1, 0.2)},
                    results=_results(), wall_time_s=np.float64(1.5))
    raw = json.loads(p.read_text())        # valid strict JSON
    assert raw["results"]["DR"]["mean"] == "inf"
    for key in ("jaxnc_version", "experiment", "config", "results", "wall_time_s", "created",
                "jax_version", "platform"):
        assert key in raw
    d = mc.load_results(p)
    assert d["experiment"] == "demo" and d["wall_time_s"] == 1.5
    assert d["jax_version"] == jax.__version__
    assert d["config"] == {"N": 10, "sigma": [0.1, 0.2]}
    dr = d["results"]["DR"]
    assert dr["mean"] == math.inf and dr["ratio"] == -math.inf and math.isnan(dr["ci95"])
    assert dr["n"] == 7 and dr["x"] == 0.5 and dr["arr"] == [1.0, math.inf]
    assert dr["jarr"] == [0, 1, 2] and dr["flag"] is True and dr["t"] == [1, 2.5]
    assert d["results"]["SR"]["mean"] == 1.5 and d["results"]["SR"]["n_stable"] == 2
    assert os.listdir(p.parent) == ["results.json"]


def test_save_is_atomic(tmp_path, monkeypatch):
    p = tmp_path / "results.json"
    mc.save_results(p, experiment="old", config={}, results={"a": 1}, wall_time_s=0.0)
    before = p.read_bytes()

    def broken_dump(obj, fp, **kw):
        fp.write('{"experiment": "new", "res')
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(json, "dump", broken_dump)
    with pytest.raises(RuntimeError, match="disk on fire"):
        mc.save_results(p, experiment="new", config={}, results={"a": 2}, wall_time_s=0.0)
    assert p.read_bytes() == before
    assert os.listdir(tmp_path) == ["results.json"]        # no temp file left behind
    monkeypatch.undo()
    assert mc.load_results(p)["experiment"] == "old"


def test_save_rejects_unserialisable_without_touching_file(tmp_path):
    p = tmp_path / "results.json"
    with pytest.raises(TypeError, match="not JSON-serialisable"):
        mc.save_results(p, experiment="x", config={}, results={"a": object()}, wall_time_s=0.0)
    assert os.listdir(tmp_path) == []


def test_run_batched_args_are_runtime_arguments():
    """Values passed through ``args`` change the result without recompiling."""
    def fn(key, scale):
        return scale["a"] * jax.random.normal(key, (3,))
    keys = mc.seed_keys(0, 5)
    one = mc.run_batched(fn, keys, args=({"a": jnp.float32(1.0)},), chunk_size=4, progress=False)
    two = mc.run_batched(fn, keys, args=({"a": jnp.float32(2.0)},), chunk_size=4, progress=False)
    np.testing.assert_allclose(two, 2.0 * one, rtol=1e-6)
    assert mc._compiled(fn)._cache_size() == 1


def _ar1(key, cfg):
    def step(x, w):
        x = cfg["a"] * x + cfg["g"] * w
        return x, x
    return {"path": jax.lax.scan(step, 0.0, jax.random.normal(key, cfg["w"].shape))[1], "n": cfg["w"].shape[0]}


def test_precompile_compiles_each_program_once_and_the_runs_compile_nothing():
    """Three calls, two programs (two configurations of one structure, one of longer noise):
    ``precompile`` compiles two, side by side; the ``run_batched`` calls after it compile
    (or load) nothing, and give the results of a function object that was never precompiled
    (the sequential path) bit for bit."""
    from jaxnc.cache import compile_clock

    def fresh(key, cfg):                    # the same body, its own compiled programs
        return _ar1(key, cfg)

    def run(key, cfg):
        return _ar1(key, cfg)

    cfgs = [mc.uniform_dtypes({"a": 0.9, "g": 0.5, "w": np.zeros(30)}),
            mc.uniform_dtypes({"a": 0.7, "g": 2.0, "w": np.zeros(30)}),
            mc.uniform_dtypes({"a": 0.8, "g": 1.0, "w": np.zeros(45)})]
    keys = mc.seed_keys(3, 37)               # three chunks of 16, the last padded
    before = compile_clock()
    assert mc.precompile([(run, (c,)) for c in cfgs], keys, chunk_size=16, workers=2) == 2
    assert (compile_clock() - before).compilations == 2
    before = compile_clock()
    ahead = [mc.run_batched(run, keys, args=(c,), chunk_size=16, progress=False) for c in cfgs]
    assert (compile_clock() - before).compilations == 0
    assert mc._compiled(run)._cache_size() == 2
    alone = [mc.run_batched(fresh, keys, args=(c,), chunk_size=16, progress=False) for c in cfgs]
    assert (compile_clock() - before).compilations == 2
    for a, b in zip(ahead, alone):
        assert a["path"].shape == b["path"].shape and a["path"].tobytes() == b["path"].tobytes()
        assert np.array_equal(a["n"], b["n"])
    assert mc.precompile([(run, (cfgs[0],))], keys, chunk_size=16) == 1     # cached: nothing compiled again
    assert (compile_clock() - before).compilations == 2
    assert mc.precompile([(run, (cfgs[0],))], keys[:0], chunk_size=16) == 0


def test_precompile_without_waiting_lets_the_next_run_wait_for_its_program():
    """``wait=False`` returns with the programs handed to the compiling threads; each
    ``run_batched`` call after it waits for its own program and compiles nothing more: two
    programs in all for two structures, each once, and the results of a never-precompiled
    function."""
    from jaxnc.cache import compile_clock

    def run(key, cfg):
        return _ar1(key, cfg)

    def fresh(key, cfg):
        return _ar1(key, cfg)

    cfgs = [mc.uniform_dtypes({"a": 0.5, "g": 1.0, "w": np.zeros(n)}) for n in (12, 20)]
    keys = mc.seed_keys(5, 20)
    before = compile_clock()
    assert mc.precompile([(run, (c,)) for c in cfgs], keys, chunk_size=16, wait=False) == 2
    ahead = [mc.run_batched(run, keys, args=(c,), chunk_size=16, progress=False) for c in cfgs]
    assert not mc._IN_FLIGHT
    assert (compile_clock() - before).compilations == 2 and mc._compiled(run)._cache_size() == 2
    alone = [mc.run_batched(fresh, keys, args=(c,), chunk_size=16, progress=False) for c in cfgs]
    for a, b in zip(ahead, alone):
        assert a["path"].tobytes() == b["path"].tobytes()


_SHARD_SCRIPT = r"""
import sys, jax, numpy as np
jax.config.update("jax_num_cpu_devices", int(sys.argv[1]))
from jaxnc import montecarlo as mc
def fn(key, gain):
    def step(x, w):
        x = 0.9 * x + gain * w
        return x, x
    return jax.lax.scan(step, 0.0, jax.random.normal(key, (50,)))[1]
out = mc.run_batched(fn, mc.seed_keys(0, 37), args=(np.float32(0.5),), chunk_size=8, progress=False)
np.save(sys.argv[2], out)
print(len(jax.devices()))
"""


def test_run_batched_shards_over_devices(tmp_path):
    """Two CPU devices: every chunk is split over both; same results as one device."""
    import subprocess
    import sys
    outs = []
    for n in (1, 2):
        f = tmp_path / f"out{n}.npy"
        r = subprocess.run([sys.executable, "-c", _SHARD_SCRIPT, str(n), str(f)], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == str(n)
        outs.append(np.load(f))
    assert outs[0].shape == (37, 50)
    np.testing.assert_allclose(outs[1], outs[0], rtol=1e-6, atol=1e-7)


def test_stored_study_writes_every_part_and_reuses_them(tmp_path, capsys):
    calls = []

    def compute(name):
        calls.append(name)
        return {"loop": name, "value": len(name), "wall_time_s": 0.5}

    def plot(results, out):
        p = out / "fig.png"
        p.write_text(",".join(r["loop"] for r in results))
        return p

    tables = lambda results: "| " + " | ".join(f"{r['loop']}={r['value']}" for r in results) + " |"
    kw = dict(experiment="demo", config={"seeds": 4}, parts=("ab", "cde"), compute=compute, tables=tables, plot=plot)
    res = mc.stored_study(tmp_path / "o", **kw)
    assert calls == ["ab", "cde"] and res["cde"]["value"] == 3
    assert (tmp_path / "o" / "tables.md").read_text() == "| ab=2 | cde=3 |"
    assert (tmp_path / "o" / "fig.png").read_text() == "ab,cde"
    doc = mc.load_results(tmp_path / "o" / "results.json")
    assert doc["config"] == {"seeds": 4, "loops": ["ab", "cde"]} and set(doc["results"]) == {"ab", "cde"}
    capsys.readouterr()
    again = mc.stored_study(tmp_path / "o", **kw)            # the same config: nothing recomputed
    assert calls == ["ab", "cde"] and again == res and "reusing" in capsys.readouterr().out
    mc.stored_study(tmp_path / "o", **dict(kw, config={"seeds": 8}))
    assert calls == ["ab", "cde", "ab", "cde"]
    # numpy numbers in the configuration (saved as numbers): reused, not a TypeError on resuming
    mc.stored_study(tmp_path / "p", **dict(kw, config={"seeds": np.int64(8), "p": np.float32(0.3)}))
    mc.stored_study(tmp_path / "p", **dict(kw, config={"seeds": np.int64(8), "p": np.float32(0.3)}))
    assert calls == ["ab", "cde"] * 3


def test_uniform_dtypes_lets_configurations_share_one_program():
    """Two configurations of one structure, one with Python ints and float64 numpy leaves,
    the other with Python floats: as given they compile two programs; through
    ``uniform_dtypes`` one (float32 / int32 leaves, booleans unchanged)."""
    traces = []

    def fn(key, cfg):
        traces.append(1)
        return {"y": cfg["gain"] * jax.random.normal(key) + cfg["n"]}

    a = {"gain": np.float64(2.0), "n": 3, "on": True}
    b = {"gain": 1.5, "n": np.int64(4), "on": False}
    u = mc.uniform_dtypes(a)
    assert u["gain"].dtype == np.float32 and u["n"].dtype == np.int32 and u["on"].dtype == np.bool_
    keys = mc.seed_keys(0, 4)
    mc.run_batched(fn, keys, args=(a,), chunk_size=4, progress=False)
    mc.run_batched(fn, keys, args=(b,), chunk_size=4, progress=False)
    assert len(traces) == 2
    ra = mc.run_batched(fn, keys, args=(mc.uniform_dtypes(a),), chunk_size=4, progress=False)
    rb = mc.run_batched(fn, keys, args=(mc.uniform_dtypes(b),), chunk_size=4, progress=False)
    assert len(traces) == 3
    z = np.asarray(jax.vmap(jax.random.normal)(keys))        # the same draws: only the values changed
    # float32 rounding of terms below 8 in size (the program may fuse the multiply-add): 2^-20
    z = z.astype(np.float64)
    np.testing.assert_allclose(ra["y"], 2.0 * z + 3, rtol=0, atol=2.0 ** -20)
    np.testing.assert_allclose(rb["y"], 1.5 * z + 4, rtol=0, atol=2.0 ** -20)
