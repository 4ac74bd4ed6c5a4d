"""jaxnc.tune: event-gradient estimators, optax tuning, Monte-Carlo search."""
import dataclasses
import math
import sys
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxnc import montecarlo
from jaxnc.controllers.pi import pi_step
import jaxnc.loop as jl
from jaxnc.loop.triggers import petc_gap, soft_decision
from jaxnc.tune import (Interval, Positive, bernoulli_fires, constrain, grid, halving_schedule,
                        mean_ci, paired_ci, random_points, relax_trigger, score_grad, score_surrogate, search,
                        successive_halving, tune, Unconstrained, unconstrain)

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))


# ----------------------------------------------------------------------------- a toy networked loop


def toy_cost(params, key, *, steps=60, w=0.5, temperature=0.05):
    """Scalar plant x+ = 1.02 x + 0.1 u + n, PI control (pi_step) on a PETC-sampled
    output (the relaxed PETC, seed 000 eq. 3-4): mean x^2 + w * mean(beta)."""
    dt = params["Kp"].dtype
    noise = 0.05 * jax.random.normal(key, (steps,), dt)

    def step(c, n):
        x, zbar, integ = c
        z = jnp.reshape(x + 0.2, (1,))          # offset: the relative term sigma z^2 matters
        beta = soft_decision(petc_gap(zbar, z, params["sigma"], params["delta"]), temperature)
        zbar = jl.blend(beta, z, zbar)
        u, integ = pi_step(params["Kp"], params["Ki"], integ, -(zbar[0] - 0.2), 0.1)
        x = 1.02 * x + 0.1 * u + n
        return (x, zbar, integ), (x * x, beta)

    c0 = (jnp.asarray(1.0, dt), jnp.asarray([1.2], dt), jnp.asarray(0.0, dt))
    _, (x2, beta) = jax.lax.scan(step, c0, noise)
    return jnp.mean(x2) + w * jnp.mean(beta)


def test_relaxed_gradient_matches_central_differences_float64():
    """d/d(delta, sigma, Kp) of the relaxed objective == central finite differences (rel. err < 1e-2)."""
    with jax.enable_x64(True):
        p0 = {"sigma": jnp.asarray([0.05]), "delta": jnp.asarray([0.02]), "Kp": jnp.asarray(2.0),
              "Ki": jnp.asarray(1.0)}
        keys = montecarlo.seed_keys(0, 4)
        f = jax.jit(lambda p: jnp.mean(jax.vmap(lambda k: toy_cost(p, k))(keys)))
        g = jax.jit(jax.grad(f))(p0)
        for name in ("delta", "sigma", "Kp"):
            h = 1e-5 * max(1.0, float(jnp.abs(p0[name]).max()))
            up = {**p0, name: p0[name] + h}
            dn = {**p0, name: p0[name] - h}
            fd = (f(up) - f(dn)) / (2 * h)
            ad = jnp.sum(g[name])
            assert abs(float(fd)) > 1e-4, f"{name}: the objective must depend on it"
            assert abs(float(ad - fd)) / abs(float(fd)) < 1e-2, (name, float(ad), float(fd))


def test_relaxed_trigger_approaches_hard_trigger_and_straight_through_is_exact_forward():
    z_last, z = jnp.asarray([0.0, 1.0]), jnp.asarray([0.5, 1.1])
    hard = jl.Petc(sigma=jnp.asarray([0.1, 0.1]), delta=jnp.asarray([0.01, 0.01]))
    fires = lambda trig: trig.step(jl.PetcState(z_last, jnp.int32(0)), z, 1)[1]
    gap = float(jl.petc_gap(z_last, z, hard.sigma, hard.delta, hard.reading))
    assert gap > 0 and float(fires(hard)) == 1.0
    soft = [float(fires(relax_trigger(hard, "sigmoid", t))) for t in (1.0, 0.1, 0.01)]
    assert soft[0] < soft[1] < soft[2] and soft[2] > 0.99 and abs(soft[0] - 1 / (1 + math.exp(-gap))) < 1e-6
    st = relax_trigger(hard, "straight_through", 0.1)
    assert float(fires(st)) == 1.0
    dst = jax.grad(lambda d: fires(dataclasses.replace(st, delta=d)))(hard.delta)
    s = 1 / (1 + math.exp(-gap / 0.1))
    np.testing.assert_allclose(dst, -s * (1 - s) / 0.1 * np.ones(2), rtol=1e-5)
    assert float(relax_trigger(st, "score", 0.1).temperature) == 0.0
    with pytest.raises(ValueError, match="temperature"):
        relax_trigger(hard, "sigmoid", 0.0)
    with pytest.raises(ValueError, match="estimator"):
        relax_trigger(hard, "magic", 0.1)


def test_bernoulli_score_function_is_unbiased_on_a_toy():
    """E[(beta - c)^2] with beta ~ Bernoulli(s(g(theta)/tau)), g = theta - 0.3: d/dtheta is
    s'(.)/tau ((1 - c)^2 - c^2) in closed form; REINFORCE with a leave-one-out baseline must
    match within 4 standard errors, and differ from the zero of the straight-through-free step."""
    tau, c, theta, n = 0.5, 0.8, 0.1, 20000

    def estimates(theta, key):
        keys = jax.random.split(key, n)
        def one(k):
            beta, logp = bernoulli_fires(k, theta - 0.3, tau)
            return (beta - c) ** 2, logp
        costs, _ = jax.vmap(one)(keys)
        baseline = (jnp.sum(costs) - costs) / (n - 1)        # leave-one-out: independent of sample i
        def surrogate(th, k, b):
            beta, logp = bernoulli_fires(k, th - 0.3, tau)
            return score_surrogate((beta - c) ** 2, logp, b)
        return jax.vmap(jax.grad(surrogate), in_axes=(None, 0, 0))(theta, keys, baseline)

    g = np.asarray(jax.jit(estimates)(jnp.float32(theta), jax.random.PRNGKey(3)), np.float64)
    p = 1 / (1 + math.exp(-(theta - 0.3) / tau))
    exact = p * (1 - p) / tau * ((1 - c) ** 2 - c ** 2)
    se = g.std(ddof=1) / math.sqrt(n)
    assert abs(g.mean() - exact) < 4 * se, (g.mean(), exact, se)
    assert abs(exact) > 10 * se                                # the test can tell a wrong sign / zero


def test_gaussian_score_grad_is_unbiased_for_the_smoothed_objective():
    """f(x) = sum (x - m)^2 + x_0^4: E f(mu + s e) has gradient 2(mu - m) + 4 mu_0^3 + 12 s^2 mu_0."""
    m = jnp.asarray([0.3, -0.2, 1.0])
    mu = jnp.asarray([0.5, 0.1, 0.4])
    s = 0.3
    f = lambda x, k: jnp.sum((x - m) ** 2) + x[0] ** 4 + 0.0 * jax.random.normal(k)
    reps = 400
    gs = jax.jit(jax.vmap(lambda k: score_grad(f, mu, k, 64, s)[1]))(jax.random.split(jax.random.PRNGKey(0), reps))
    gs = np.asarray(gs, np.float64)
    exact = np.asarray(2 * (mu - m)) + np.asarray([4 * mu[0] ** 3 + 12 * s ** 2 * mu[0], 0, 0])
    se = gs.std(axis=0, ddof=1) / math.sqrt(reps)
    assert np.all(np.abs(gs.mean(axis=0) - exact) < 4 * se + 1e-6), (gs.mean(axis=0), exact, se)


def test_reparametrisation_round_trips_and_respects_bounds():
    cons = {"a": Positive(), "b": Interval(-1.0, 2.0), "c": Positive(low=0.5)}
    p = {"a": np.asarray([0.01, 1.0, 30.0]), "b": np.asarray(0.7), "c": np.asarray(0.9)}
    back = constrain(unconstrain(p, cons), cons)
    for k in p:
        np.testing.assert_allclose(back[k], p[k], rtol=1e-4)
    extreme = constrain({"a": jnp.asarray(-50.0), "b": jnp.asarray(50.0), "c": jnp.asarray(-50.0)}, cons)
    assert float(extreme["a"]) >= 0 and float(extreme["b"]) <= 2.0 and float(extreme["c"]) >= 0.5
    with pytest.raises(ValueError, match="not tuned"):
        unconstrain({"a": 1.0}, {"zz": Positive()})


def test_positive_is_exp_of_the_raw_value_so_raw_steps_are_relative():
    """Positive(low): value = low + exp(raw). A raw step of 0.1 multiplies value - low by
    e^0.1 whether the value is 1e-4 or 10 (thresholds span decades); the check's and the
    tuner's fd_step / score_scale are relative steps."""
    for v in (1e-4, 1e-2, 1.0, 10.0):
        raw = unconstrain({"x": v}, {"x": Positive()})["x"]
        np.testing.assert_allclose(float(raw), np.log(v), rtol=1e-6, atol=1e-6)
        up = constrain({"x": raw + 0.1}, {"x": Positive()})["x"]
        np.testing.assert_allclose(float(up) / v, np.exp(0.1), rtol=1e-5)
    raw = unconstrain({"x": 0.75}, {"x": Positive(low=0.5)})["x"]
    np.testing.assert_allclose(float(raw), np.log(0.25), rtol=1e-6)


@pytest.mark.parametrize("cons, value, msg", [
    (Positive(), 0.0, r"'x' must be finite and > 0"),
    (Positive(), -1.0, r"'x' must be finite and > 0"),
    (Positive(low=0.5), 0.5, r"'x' must be finite and > 0.5"),
    (Positive(), np.nan, r"'x' must be finite"),
    (Interval(0.0, 1.0), 1.5, r"'x' must be inside the open interval \(0, 1\)"),
    (Interval(0.0, 1.0), 0.0, r"'x' must be inside the open interval \(0, 1\)"),
    (Unconstrained(), np.inf, r"'x' must be finite"),
])
def test_unconstrain_refuses_a_value_outside_its_constraint_naming_it(cons, value, msg):
    """Nothing is moved to the edge silently (a start of 0 under Positive used to become
    1e-6, one outside an Interval its edge)."""
    with pytest.raises(ValueError, match=msg):
        unconstrain({"x": value}, {"x": cons})


@pytest.mark.parametrize("estimator", ["straight_through", "score", "richardson"])
def test_tuning_a_noisy_quadratic_recovers_the_optimum(estimator):
    """loss = (delta - 0.4)^2 + (Kp - 2)^2 * (1 + 0.5 n), n ~ N(0, 1) per seed: the optimum
    (0.4, 2) must be found within what the averaged stochastic iterates allow. The
    extrapolated score runs each pair at two scales: twice the batch for as many pairs."""
    def loss(p, key, temperature):
        n = jax.random.normal(key)
        return (p["delta"] - 0.4) ** 2 + (p["Kp"] - 2.0) ** 2 * (1 + 0.5 * n) + 0.1 * n

    batch = 16 if estimator == "richardson" else 8
    res = tune(loss, {"delta": 0.05, "Kp": 0.5}, {"delta": Positive(), "Kp": Positive()}, steps=300, batch=batch,
               optimizer=optax.adam(0.05), estimator=estimator, progress=False, score_scale=0.05)
    assert abs(float(res.params["delta"]) - 0.4) < 0.05
    assert abs(float(res.params["Kp"]) - 2.0) < 0.05
    assert res.history.objective.shape == (300,) and res.history.objective[-20:].mean() < res.history.objective[:5].mean()
    assert res.n_simulations == 300 * batch
    assert res.history.params["Kp"].shape == (300,)


def test_grid_search_with_common_random_numbers_finds_the_best_point():
    """per_seed = (x - 0.62)^2 + y + 3 n (n shared by all candidates via the key): with CRN the
    noise cancels in comparisons, so the closest grid point wins even with few seeds."""
    def per_seed(p, key):
        n = jax.random.normal(key)
        return (p["x"] - 0.62) ** 2 + p["y"] + 3.0 * n

    pts = grid(x=np.linspace(0, 1, 11), y=(0.0, 0.5))
    assert len(pts) == 22 and pts[1] == {"x": 0.0, "y": 0.5}
    keys = montecarlo.seed_keys(0, 16)
    res = search(per_seed, pts, keys, progress=False)
    assert res.best_point["y"] == 0.0 and abs(res.best_point["x"] - 0.6) < 1e-6
    assert res.n_simulations == 22 * 16 and res.values.shape == (22, 16)
    # the interval of the best mean covers its expectation (0.02^2); paired differences are exact
    assert abs(res.best_mean - 0.0004) < res.best_ci95 * 2.5
    d, ci = paired_ci(res.values[res.best], res.values[0])
    assert abs(d - (0.02 ** 2 - 0.62 ** 2)) < 1e-5 and ci < 1e-5


def test_successive_halving_spends_the_budget_on_the_best_and_beats_the_grid_on_rare_failures():
    """16 candidates with cost c + 20 [failure], failure probability q (rare-failure objectives
    such as autotune-mecanum's).  Successive halving keeps the budget, runs all survivors on
    common seeds, and over 16 independent repetitions its choice is on average closer to the
    best expected cost than a grid search of the same budget (regret = chosen - best)."""
    def per_seed(p, key):
        u = jax.random.uniform(key)
        return p["c"] + 20.0 * (jnp.mod(u + p["phase"], 1.0) < p["q"])   # phase: failures on different seeds

    rng = np.random.default_rng(0)
    q = np.r_[0.02, rng.uniform(0.03, 0.3, 15)]
    c = np.r_[0.5, rng.uniform(0.4, 1.0, 15)]
    pts = [dict(c=float(c[i]), q=float(q[i]), phase=i / 16) for i in range(16)]
    expected = c + 20 * q
    assert halving_schedule(16, 160) == [(16, 2), (8, 5), (4, 10), (2, 20)]
    regret_grid, regret_halving = [], []
    for r in range(16):
        keys = montecarlo.seed_keys(100 + r, 37)
        g = search(per_seed, pts, keys[:10], progress=False)                    # 160 simulations
        h = successive_halving(per_seed, pts, keys, budget=160, progress=False)  # 152
        assert h.n_simulations == 152 <= 160 and g.n_simulations == 160
        ran = ~np.isnan(h.values)
        # every candidate ran the first round's seeds; survivors ran a common prefix of the seeds
        assert ran[:, :2].all() and ran[h.best].all() and ran.sum() == 152
        assert all(ran[i, :ran[i].sum()].all() for i in range(16))
        regret_grid.append(expected[g.best] - expected.min())
        regret_halving.append(expected[h.best] - expected.min())
    assert np.mean(regret_halving) < 0.5 * np.mean(regret_grid)
    with pytest.raises(ValueError, match="budget"):
        successive_halving(per_seed, pts, montecarlo.seed_keys(0, 37), budget=63)
    with pytest.raises(ValueError, match="keys"):
        successive_halving(per_seed, pts, montecarlo.seed_keys(0, 10), budget=160)


def test_random_points_and_mean_ci():
    pts = random_points(1, 200, a=(0.01, 1.0, "log"), k=(2, 5, "int"), u=(-1.0, 1.0))
    a = np.asarray([p["a"] for p in pts])
    k = np.asarray([p["k"] for p in pts])
    assert a.min() >= 0.01 and a.max() <= 1.0 and np.median(np.log10(a)) == pytest.approx(-1.0, abs=0.2)
    assert set(k) == {2, 3, 4, 5} and all(isinstance(p["k"], int) for p in pts)
    m, ci = mean_ci(np.arange(100.0))
    assert m == 49.5 and ci == pytest.approx(1.96 * np.arange(100.0).std(ddof=1) / 10)
    with pytest.raises(ValueError, match="log"):
        random_points(0, 3, a=(0.0, 1.0, "log"))


def test_pi_state_space_matches_the_paper_design():
    """experiments.autotune.pi_ss == DiscreteSS.from_tf(single_rate_pi) (eq. 30-31)."""
    from experiments.autotune import pi_ss
    from jaxnc.design.dualrate import DiscreteSS, single_rate_pi
    for Ts in (0.1, 0.2):
        ref = DiscreteSS.from_tf(single_rate_pi(6.0, 0.12, Ts))
        ours = pi_ss(6.0, 50.0, Ts)
        for f in ("A", "B", "C", "D"):
            np.testing.assert_allclose(getattr(ours, f), getattr(ref, f), rtol=1e-6)
        assert ours.dt == ref.dt == Ts            # its period, which a PursuitPI loop checks


def test_experiment_options_are_validated_before_tracing():
    from experiments import autotune  # noqa: F401  (registers)
    from jaxnc.experiment import ConfigError, get_experiment
    exp = get_experiment("autotune-mecanum")
    with pytest.raises(ConfigError, match="estimator"):
        exp.parse_settings(["estimator=magic"])
    with pytest.raises(ConfigError, match="dp"):
        exp.parse_settings(["dp=1.5"])
    assert get_experiment("autotune-pi").parse_settings(["scenario=a"])["scenario"] == "a"


def test_hybrid_estimator_sees_a_failure_region_that_the_pathwise_gradient_cannot():
    """Per seed xi ~ N(0, 0.3^2): smooth = (a - 2)^2, jump = 4 if a + xi > 1.5 (a failure
    charged a constant, no pathwise derivative). The pathwise gradient only sees the
    quadratic and stops at a = 2; the hybrid estimator adds the score-function gradient
    of the jump, smoothed by its perturbation scale s, so it minimises
    (a - 2)^2 + 4 Phi((a - 1.5) / sqrt(0.3^2 + s^2)), whose minimum is computed here."""
    from scipy.stats import norm

    def loss(p, key, temperature):
        fail = p["a"] + 0.3 * jax.random.normal(key) > 1.5
        return (p["a"] - 2.0) ** 2, jnp.where(fail, 4.0, 0.0)

    s = 0.1
    grid_a = np.linspace(0.0, 3.0, 30001)
    smoothed = (grid_a - 2) ** 2 + 4 * norm.cdf((grid_a - 1.5) / math.sqrt(0.09 + s ** 2))
    a_star = grid_a[np.argmin(smoothed)]
    assert abs(a_star - 2.0) > 0.5                      # the failure term moves the optimum
    kw = dict(steps=400, batch=8, optimizer=optax.adam(0.02), progress=False, score_scale=s, average_tail=0.5)
    hyb = tune(loss, {"a": 2.0}, estimator="hybrid", score_pairs=16, **kw)
    path = tune(lambda p, k, t: sum(loss(p, k, t)), {"a": 2.0}, estimator="straight_through", **kw)
    assert abs(float(hyb.params["a"]) - a_star) < 0.1, (float(hyb.params["a"]), a_star)
    assert abs(float(path.params["a"]) - 2.0) < 0.05   # blind to the failures
    assert hyb.n_simulations == 400 * (8 + 2 * 16)


def test_near_miss_penalty_ramps_from_r0_to_the_failure_charge_and_adds_only_a_gradient():
    """autotune-mecanum's near-miss surrogate: 0 up to r0, the failure charge at the tube's
    edge, 0 for unstable runs (they pay the charge itself); added as p - stop_gradient(p)
    it leaves the objective's value unchanged and contributes dp/dJ2."""
    from experiments.autotune import near_miss_penalty
    pen = lambda j2, bad=False: near_miss_penalty(jnp.float32(j2), jnp.bool_(bad), 0.5, 0.2, 100.0)
    assert float(pen(0.1)) == 0.0 and float(pen(0.2)) == 0.0
    np.testing.assert_allclose(float(pen(0.5)), 100.0, rtol=1e-6)
    np.testing.assert_allclose(float(pen(0.35)), 25.0, rtol=1e-5)      # half-way: charge / 4
    assert float(pen(0.45, bad=True)) == 0.0 and float(pen(jnp.inf)) == 0.0
    value_and_grad = jax.value_and_grad(lambda j2: pen(j2) - jax.lax.stop_gradient(pen(j2)))
    v, g = value_and_grad(jnp.float32(0.35))
    assert float(v) == 0.0
    np.testing.assert_allclose(float(g), 2 * 100.0 * 0.5 / 0.3, rtol=1e-5)   # d/dJ2 of charge x^2


def test_scales_family_is_the_grids_family_and_contains_the_papers_thresholds():
    """autotune-mecanum family=scales: sigma = s x the paper's sigma pattern, delta(i) = d;
    (s, d) = (1, 0.1) is the paper's point, and scales_loss passes exactly those
    thresholds (and their gradient) to the per-output loss."""
    from experiments.autotune import PAPER_D, from_scales, scales_loss
    from jaxnc.experiment import ConfigError, get_experiment
    from jaxnc.schemes import mecanum as mec
    p = from_scales({"s": jnp.float32(1.0), "d": jnp.float32(PAPER_D)})
    np.testing.assert_array_equal(np.asarray(p["sigma"]), np.asarray(mec.PAPER_SIGMA, np.float32))
    np.testing.assert_array_equal(np.asarray(p["delta"]), np.asarray(mec.PAPER_DELTA, np.float32))
    per_output = lambda q, key, t: jnp.sum(q["sigma"] ** 2) + 3.0 * jnp.sum(q["delta"])
    g = jax.grad(lambda q: scales_loss(per_output)(q, None, 0.0))({"s": jnp.float32(2.0), "d": jnp.float32(0.5)})
    sig = np.asarray(mec.PAPER_SIGMA, np.float32)
    np.testing.assert_allclose(float(g["s"]), 2 * 2.0 * np.sum(sig ** 2), rtol=1e-6)
    np.testing.assert_allclose(float(g["d"]), 3.0 * 9, rtol=1e-6)
    exp = get_experiment("autotune-mecanum")
    assert exp.parse_settings(["family=scales"])["family"] == "scales"
    with pytest.raises(ConfigError, match="family"):
        exp.parse_settings(["family=diagonal"])
    # init=coarse refines inside the grid cell around the search's winner: only in this family
    assert exp.parse_settings([])["init"] == "coarse" and exp.parse_settings([])["family"] == "scales"  # defaults
    with pytest.raises(ConfigError, match="family=scales"):
        exp.parse_settings(["family=per_output"])
    assert exp.parse_settings(["family=per_output", "init=paper"])["family"] == "per_output"
    from experiments.autotune import grid_cell
    assert grid_cell((0.0, 0.25, 0.5, 1.0), 0.0) == (0.0, 0.25) and grid_cell((0.0, 0.25, 0.5, 1.0), 1.0) == (0.5, 2.0)
    assert grid_cell((0.03, 0.1, 0.3, 1.0), 0.1) == (0.03, 0.3)
    np.testing.assert_allclose(grid_cell((0.03, 0.1, 0.3, 1.0), 0.03), (0.009, 0.1))


def _fresh_quadratic():
    def per_seed(p, key):
        return (p["x"] - 0.62) ** 2 + 0.1 * jax.random.normal(key)
    return per_seed


def test_successive_halving_rounds_share_one_program_and_stop_at_max_seconds():
    """Rounds of 2, 5, 10 and 20 seeds per candidate run in chunks of the first round's 2:
    one compilation for the whole search (a fresh per-seed function). With a spent
    wall-time budget only the first round runs, and its leader is the result."""
    from jaxnc.cache import compile_clock
    pts = [{"x": float(x)} for x in np.linspace(0, 1, 16)]
    keys = montecarlo.seed_keys(0, 37)
    successive_halving(_fresh_quadratic(), pts, keys, budget=160, progress=False)    # the eager helpers, once
    c0 = compile_clock()
    h = successive_halving(_fresh_quadratic(), pts, keys, budget=160, progress=False)
    assert (compile_clock() - c0).compilations == 1
    assert h.n_simulations == 152 and abs(h.best_point["x"] - 0.6) < 0.1
    t = successive_halving(_fresh_quadratic(), pts, keys, budget=160, max_seconds=1e-9, progress=False)
    assert t.n_simulations == 16 * 2 and np.isnan(t.values[:, 2:]).all()
    first = np.mean(t.values[:, :2], axis=1)
    assert t.best == int(np.argmin(first))
    with pytest.raises(ValueError, match="max_seconds"):
        successive_halving(_fresh_quadratic(), pts, keys, budget=160, max_seconds=0)
    with pytest.raises(ValueError, match="chunk_size"):
        successive_halving(_fresh_quadratic(), pts, keys, budget=160, chunk_size=0)


def test_search_stops_at_max_seconds_after_the_first_candidate():
    pts = [{"x": float(x)} for x in np.linspace(0, 1, 5)]
    keys = montecarlo.seed_keys(0, 8)
    r = search(_fresh_quadratic(), pts, keys, max_seconds=1e-9, progress=False)
    assert r.n_simulations == 8 and r.best == 0 and np.isnan(r.values[1:]).all()
    assert np.isinf(r.mean[1:]).all() and np.isfinite(r.mean[0])
    full = search(_fresh_quadratic(), pts, keys, max_seconds=1e6, progress=False)
    assert full.n_simulations == 40 and full.best == 2          # x = 0.5, the closest to 0.62
    with pytest.raises(ValueError, match="max_seconds"):
        search(_fresh_quadratic(), pts, keys, max_seconds=-1.0)


def _constant_grad(sleep_s=0.0):
    """host_grad for tune(): the gradient +1 on every coordinate (after ``sleep_s``)."""
    def host_grad(raw, keys, temp):
        time.sleep(sleep_s)
        return 0.0, jax.tree.map(jnp.ones_like, raw)
    return host_grad


def test_learning_rate_pair_decays_geometrically_over_the_steps():
    """With a constant gradient, Adam's bias-corrected step is exactly the learning rate, so
    the raw iterate is raw0 - sum_k lr_k with lr_k = a (b / a)^(k / steps) (closed form)."""
    steps, (a, b) = 12, (0.3, 0.03)
    r = tune(None, {"x": np.float32(0.0)}, steps=steps, batch=2, learning_rate=(a, b), host_grad=_constant_grad(),
             average_tail=0.0, progress=False)
    lr = a * (b / a) ** (np.arange(steps) / steps)
    np.testing.assert_allclose(r.history.params["x"][1:], -np.cumsum(lr)[:-1], rtol=1e-4)
    np.testing.assert_allclose(r.params["x"], -np.sum(lr), rtol=1e-4)
    c = tune(None, {"x": np.float32(0.0)}, steps=5, batch=2, learning_rate=0.1, host_grad=_constant_grad(),
             average_tail=0.0, progress=False)
    np.testing.assert_allclose(c.params["x"], -0.5, rtol=1e-4)         # a number: constant


def test_max_seconds_ends_the_steps_within_the_budget(monkeypatch):
    """No step starts once the time spent plus the last step's would pass max_seconds; the
    number of steps made is the history's length, the simulations count those steps, and the
    rate decays with the fraction of the budget spent. The tuner's clock is replaced by one that
    advances 0.05 s per gradient, so the steps made and the rates are exact (a timed test would
    depend on the machine's load)."""
    import types
    import jaxnc.tune.gradient as gradient_module
    ticks = [0]
    monkeypatch.setattr(gradient_module, "time", types.SimpleNamespace(perf_counter=lambda: 0.05 * ticks[0]))

    def host_grad(raw, keys, temp):
        ticks[0] += 1
        return 0.0, jax.tree.map(jnp.ones_like, raw)

    r = tune(None, {"x": np.float32(0.0)}, steps=1000, batch=2, learning_rate=(0.1, 0.01), max_seconds=0.625,
             host_grad=host_grad, average_tail=0.0, progress=False)
    # step k starts at 0.05 k; the 12th (k = 12) would end at 0.65 > 0.625, so 12 steps run
    done = len(r.history.objective)
    assert done == 12 and r.n_simulations == done * 2
    np.testing.assert_allclose(r.wall_time_s, 0.6, rtol=1e-9)
    k = np.arange(done)
    lr = 0.1 * 0.1 ** np.minimum(np.maximum(k / 1000, 0.05 * k / 0.625), 1.0)
    np.testing.assert_allclose(r.history.params["x"][1:], -np.cumsum(lr)[:-1], rtol=1e-4)
    np.testing.assert_allclose(r.params["x"], -np.sum(lr), rtol=1e-4)
    one = tune(None, {"x": np.float32(0.0)}, steps=1, batch=2, learning_rate=0.1, max_seconds=1e-3,
               host_grad=_constant_grad(0.01), progress=False)
    assert len(one.history.objective) == 1                              # the first step always runs


@pytest.mark.parametrize("kw, msg", [(dict(learning_rate=0.0), "learning_rate"),
                                     (dict(learning_rate=(0.1, -1.0)), "learning_rate"),
                                     (dict(learning_rate=(0.1, 0.2, 0.3)), "learning_rate"),
                                     (dict(max_seconds=0.0), "max_seconds"),
                                     (dict(learning_rate=0.1, optimizer=optax.sgd(0.1)), "optimizer")])
def test_tune_refuses_bad_rates_and_budgets(kw, msg):
    with pytest.raises(ValueError, match=msg):
        tune(None, {"x": np.float32(0.0)}, steps=2, batch=2, host_grad=_constant_grad(), progress=False, **kw)


def test_max_seconds_does_not_count_the_first_steps_compilation_as_a_step(monkeypatch):
    """A first step that takes 1.2 s (as a compilation would) and later steps of 0.02 s under
    a 2.01 s budget: the second step starts (2 x 1.2 > 2.01 would have stopped it), and the
    steps go on until the budget: 1 + 40 steps, the last ending at 2.0 s. The tuner's clock is
    replaced by one the gradient advances (exact, whatever the machine's load)."""
    import types
    import jaxnc.tune.gradient as gradient_module
    ticks = [0]                                            # hundredths of a second
    monkeypatch.setattr(gradient_module, "time", types.SimpleNamespace(perf_counter=lambda: 0.01 * ticks[0]))

    def host_grad(raw, keys, temp):
        ticks[0] += 120 if ticks[0] == 0 else 2
        return 0.0, jax.tree.map(jnp.ones_like, raw)
    r = tune(None, {"x": np.float32(0.0)}, steps=1000, batch=2, learning_rate=0.1, max_seconds=2.01,
             host_grad=host_grad, progress=False)
    assert len(r.history.objective) == 41
    np.testing.assert_allclose(r.wall_time_s, 2.0, rtol=1e-9)
