"""Tuning a runner loop by naming its leaves (jaxnc.tune.loop_tune)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.tune import Interval, Positive
from jaxnc.tune.loop_tune import check_loop, get_path, is_static, mc_mean, set_paths, tune_loop

A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
C = np.array([[1.0, 0.0]])


def _loop(K=(3.0, 1.5), buffer=0, pmf=(1.0,), delta=1e-3):
    plant = nc.LTI(A=A, B=B, C=C, x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05**2, mean0=[0.0, 0.0], cov0=np.eye(2),
                 buffer=buffer)
    up = nc.Link(nc.Bernoulli(0.2), nc.PmfDelay(list(pmf)), order="all", capacity=5)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=up, estimator=ekf,
                   controller=nc.StateFeedback(np.asarray([K])), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=40, T=0.1)


def test_paths_get_set_and_static():
    lp = _loop()
    assert float(get_path(lp, "trigger.delta")) == pytest.approx(1e-3)
    assert is_static(lp, "estimator.buffer") and not is_static(lp, "controller.K")
    lp2 = set_paths(lp, {"trigger.delta": 0.5, "uplink.loss.p": 0.1})
    assert float(lp2.trigger.delta) == 0.5 and float(lp2.uplink.loss.p) == 0.1 and float(lp.uplink.loss.p) == 0.2


def test_bad_input_is_refused_before_tracing():
    lp = _loop()
    with pytest.raises(ValueError, match=r"'trigger.dleta'.*no field 'dleta'.*fields: sigma, delta"):
        tune_loop(lp, {"trigger.dleta": Positive()})
    with pytest.raises(ValueError, match=r"'estimator.buffer' is static.*search="):
        tune_loop(lp, {"estimator.buffer": Positive()})
    with pytest.raises(ValueError, match=r"steps must be an integer in \[1"):
        tune_loop(lp, {"trigger.delta": Positive()}, steps=0)
    with pytest.raises(ValueError, match="must return a scalar per seed"):
        tune_loop(lp, {"trigger.delta": Positive()}, lambda m: jnp.stack([m.cost_raw, m.rate_sc]))
    with pytest.raises(ValueError, match="attribute path"):
        tune_loop(lp, {"trigger..delta": Positive()})


def test_mc_mean_is_the_vmap_mean_in_value_and_gradient():
    """mc_mean's chunks (lax.map, each checkpointed) against one vmap, in value and gradient.
    The per-seed function is _loop's plant under the gain written as a scan (40 noisy steps):
    a loop in the checkpointed backward pass, as a runner loop would be, but whose two
    gradient programs compile in a fraction of the runner's time (mc_mean does not look
    inside fn; the runner's own gradient is tested in tests/test_loop.py)."""
    keys = montecarlo.seed_keys(0, 10)
    a, b = jnp.asarray(A, jnp.float32), jnp.asarray(B, jnp.float32)

    def f(k_gain, key):
        def step(x, w):
            u = -(k_gain @ x)
            x = a @ x + b @ u + w
            return x, x @ x + 0.01 * u @ u
        w = jax.random.normal(key, (40, 2)) * jnp.asarray([[0.01, 0.02]])
        return jnp.sum(jax.lax.scan(step, jnp.asarray([1.0, 0.0]), w)[1])

    K = jnp.asarray([[3.0, 1.5]])
    # each side one compiled program (run eagerly, the gradient compiles every primitive apart: ~300 programs)
    direct = jax.jit(jax.value_and_grad(lambda g: jnp.mean(jax.vmap(lambda k: f(g, k))(keys))))(K)
    # 3 chunks, padded
    chunked = jax.jit(jax.value_and_grad(lambda g: mc_mean(lambda k: f(g, k), keys, chunk_size=4)))(K)
    np.testing.assert_allclose(chunked[0], direct[0], rtol=1e-5)
    np.testing.assert_allclose(chunked[1], direct[1], rtol=1e-4, atol=1e-7)


def test_tune_loop_improves_the_gain_on_fresh_seeds():
    """A deliberately sluggish gain is tuned by gradient: the tuned point beats the start on
    fresh seeds with the paired 95 % interval below zero."""
    lp = _loop(K=(0.5, 0.3))
    r = tune_loop(lp, {"controller.K": Positive()}, steps=25, batch=8, learning_rate=0.2, check_seeds=16,
                  estimator="auto", eval_seeds=64, progress=False)
    assert r.estimator in ("straight_through", "score") and r.check is not None
    assert r.paired_diff[0] + r.paired_diff[1] < 0, r.summary()
    assert r.params["controller.K"].shape == (1, 2)


def test_search_over_a_static_buffer_length_prefers_using_late_measurements():
    """Measurements arrive 0-3 periods late; a filter buffer of 3 uses them, of 0 drops the
    late ones: successive halving over the static buffer length picks 3."""
    lp = _loop(pmf=(0.2, 0.3, 0.3, 0.2), delta=0.0)
    r = tune_loop(lp, search={"estimator.buffer": [0, 3]}, search_budget=64, eval_seeds=64, progress=False)
    assert r.params["estimator.buffer"] == 3
    assert r.tune is None and r.paired_diff[0] < 0


def test_with_temperature_reaches_nested_triggers_and_leaves_static_fields():
    from jaxnc.tune import has_temperature, with_temperature
    lp = _loop()
    hot = with_temperature(lp, 0.25)
    assert float(hot.trigger.temperature) == 0.25 and float(lp.trigger.temperature) == 0.0
    assert hot.estimator.buffer == lp.estimator.buffer and hot.N == lp.N
    assert has_temperature(lp)
    assert not has_temperature(dataclasses.replace(lp, trigger=nc.Periodic()))
    # a configuration that is not a runner Loop, with the trigger one level deeper
    @dataclasses.dataclass(frozen=True)
    class Outer:
        inner: nc.Loop
        gain: float = 1.0
    o = with_temperature(Outer(lp), 0.5)
    assert float(o.inner.trigger.temperature) == 0.5 and o.gain == 1.0


def test_tied_paths_move_together_and_must_start_equal():
    lp = dataclasses.replace(_loop(delta=1e-2), trigger=nc.Petc(sigma=1e-2, delta=1e-2))
    r = tune_loop(lp, {("trigger.delta", "trigger.sigma"): Positive()}, lambda m: m.cost_raw + 0.5 * m.rate_sc,
                  steps=3, batch=4, check_seeds=4, eval_seeds=8, progress=False)
    assert list(r.params) == ["trigger.delta=trigger.sigma"]
    assert r.start["trigger.delta=trigger.sigma"] == pytest.approx(1e-2)
    assert r.tuning_simulations == r.n_simulations - 16
    with pytest.raises(ValueError, match=r"tied paths 'trigger.delta=trigger.sigma' must start with equal values"):
        tune_loop(_loop(delta=1e-2), {("trigger.delta", "trigger.sigma"): Positive()})


_TOTAL_KW = dict(steps=2, batch=4, estimator="straight_through", eval_seeds=16, progress=False)


@pytest.fixture(scope="module")
def straight_through_total():
    """The default run's straight-through tune_loop of ``cost_raw + 0.5 rate_sc`` over
    ``trigger.delta`` on ``_loop(delta=1e-2)``: the reference of two tests (one trace of
    the runner's programs instead of two)."""
    return tune_loop(_loop(delta=1e-2), {"trigger.delta": Positive()}, lambda m: m.cost_raw + 0.5 * m.rate_sc,
                     **_TOTAL_KW)


def test_run_argument_takes_any_per_seed_function_of_the_configuration(straight_through_total):
    """``run=`` returns whatever the objective reads (here a tuple): the result is the same
    as the default run with the equivalent objective, on the same seeds. (The default run
    is the straight_through_total fixture, shared with
    test_pair_objective_reaches_the_check_and_the_hybrid_tuner.)"""
    lp = _loop(delta=1e-2)
    a = straight_through_total
    b = tune_loop(lp, {"trigger.delta": Positive()}, lambda t: t[0] + 0.5 * t[1],
                  run=lambda l, k: (lambda m: (m.cost_raw, m.rate_sc))(nc.run(l, k)), **_TOTAL_KW)
    np.testing.assert_allclose(a.params["trigger.delta"], b.params["trigger.delta"], rtol=1e-5)
    steps_a, steps_b = (np.asarray(r.tune.history.params["trigger.delta"]) for r in (a, b))
    assert not np.allclose(steps_a, 1e-2, rtol=1e-3)           # the steps moved, and b's moved alike
    np.testing.assert_allclose(steps_a, steps_b, rtol=1e-5)
    np.testing.assert_allclose(a.eval_values[1], b.eval_values[1], rtol=1e-5)
    with pytest.raises(ValueError, match="run must be a function"):
        tune_loop(lp, {"trigger.delta": Positive()}, run=3)
    with pytest.raises(ValueError, match="does not fit what run"):
        tune_loop(lp, {"trigger.delta": Positive()}, lambda m: m.J1)


def test_check_loop_on_a_gain_agrees_with_finite_differences_at_two_points():
    """A gain has a pathwise derivative (no event depends on it here: periodic sensor), so the
    straight-through (= exact pathwise) gradient must agree with central differences on
    the same seeds and, with its smaller standard error, be recommended; at both points."""
    from jaxnc.tune import check_loop
    lp = dataclasses.replace(_loop(K=(1.0, 0.6)), trigger=nc.Periodic())
    for at in (None, {"controller.K": [[2.0, 1.0]]}):
        c = check_loop(lp, {"controller.K": Positive()}, at=at, seeds=16, fd_step=0.01)
        assert c.names == ("controller.K[0]", "controller.K[1]")
        assert c.consistent["straight_through"], c.table()
        assert c.recommended == "straight_through", c.table()
        g, fd = c.estimates["straight_through"][0], c.estimates["finite_difference"][0]
        np.testing.assert_allclose(g, fd, rtol=2e-2, atol=1e-4)
    assert str(c) == repr(c) == c.table() and "recommended: straight_through" in str(c)   # print(check) is the table
    with pytest.raises(ValueError, match=r"the point names \['K'\]"):
        check_loop(lp, {"controller.K": Positive()}, at={"K": 1.0})


def test_search_over_a_tuned_parameter_picks_the_gradients_start():
    """The two-stage tuner: a key of ``search`` that names a tuned parameter (here a tied
    group) makes successive halving choose where the gradient starts."""
    lp = dataclasses.replace(_loop(delta=1e-2), trigger=nc.Petc(sigma=1e-2, delta=1e-2))
    name = "trigger.delta=trigger.sigma"
    r = tune_loop(lp, {("trigger.delta", "trigger.sigma"): Positive()}, lambda m: m.cost_raw + 0.5 * m.rate_sc,
                  search={name: [1e-4, 1e-2, 1.0]}, search_budget=24, steps=2, batch=4,
                  estimator="straight_through", eval_seeds=8, progress=False)
    best = r.search.best_point
    assert set(best) == {"trigger.delta", "trigger.sigma"} and best["trigger.delta"] == best["trigger.sigma"]
    assert float(r.tune.history.params[name][0]) == pytest.approx(float(best["trigger.delta"]), rel=1e-6)
    assert r.tuning_simulations == r.search.n_simulations + 2 * 4 + 2 * 256     # the steps, the pick
    with pytest.raises(ValueError, match="is tuned as part of 'trigger.delta=trigger.sigma': search that name"):
        tune_loop(lp, {("trigger.delta", "trigger.sigma"): Positive()}, search={"trigger.delta": [1e-3]})


def test_check_is_inconclusive_when_finite_differences_cannot_resolve_the_gradient():
    """Agreement within the finite differences' noise proves nothing: with an objective
    whose per-seed finite differences are pure noise far larger than any gradient (a
    random jump of +-1 at theta = 0 in each seed), every estimator is flagged
    inconclusive and none is recommended."""
    from jaxnc.tune import gradient_check

    def objective(theta, key, temperature):
        flip = jnp.where(jax.random.uniform(key) < 0.5, 1.0, -1.0)
        return 1e-3 * theta[0] + flip * (theta[0] > 0).astype(jnp.float32)

    c = gradient_check(objective, np.zeros(1, np.float32), montecarlo.seed_keys(0, 64), fd_step=0.05)
    assert c.recommended is None, c.table()
    assert c.reason["straight_through"].startswith("inconclusive"), c.table()


def test_without_a_gradient_stage_its_budget_refines_the_search_finalists():
    lp = _loop(delta=1e-2)
    r = tune_loop(lp, {"trigger.delta": Positive()}, lambda m: m.cost_raw + 0.5 * m.rate_sc,
                  search={"trigger.delta": [1e-4, 1e-3, 1e-2, 1e-1, 1.0]}, search_budget=30, estimator="none",
                  steps=2, batch=8, eval_seeds=8, progress=False)
    assert r.estimator == "none" and r.tune is None and r.check is None
    ran = np.sum(~np.isnan(r.search.values), axis=1)           # seeds each candidate ran
    # steps * batch = 16 more simulations: 4 new seeds for each of the 4 best candidates
    assert r.search.n_simulations == r.tuning_simulations
    assert np.sum(ran >= 4) >= 4 and r.search.values.shape[1] == ran.max()
    assert float(r.params["trigger.delta"]) == pytest.approx(float(r.search.best_point["trigger.delta"]))
    with pytest.raises(ValueError, match="estimator='none'.*needs a search"):
        tune_loop(lp, {"trigger.delta": Positive()}, estimator="none")


def _jump_objective(c=3.0):
    """Per seed: smooth theta^2 plus a jump c * 1[u < theta], u ~ U(0, 1): at theta = 0.5
    the gradient of the mean is 2 theta + c = 1 + c; the jump has no pathwise gradient."""
    def objective(theta, key, temperature):
        u = jax.random.uniform(key)
        return theta[0] ** 2, c * (u < theta[0]).astype(jnp.float32)
    return objective


def test_check_hybrid_sees_the_jump_that_straight_through_misses():
    from jaxnc.tune import gradient_check
    c = gradient_check(_jump_objective(), np.full(1, 0.5, np.float32), montecarlo.seed_keys(3, 4096),
                       fd_step=0.05, score_scale=0.05 / np.sqrt(3), chunk_size=1024)
    assert set(c.estimates) == {"finite_difference", "straight_through", "score", "richardson", "hybrid"}
    assert set(c.references) == {"finite_difference_richardson"}
    m, s = c.estimates["hybrid"]
    assert abs(m[0] - 4.0) < 4 * s[0], c.table()                     # the closed form 1 + c
    assert c.estimates["straight_through"][0][0] == pytest.approx(1.0, abs=1e-5)   # only the smooth part
    assert c.reason["straight_through"].startswith("differs"), c.table()
    assert c.consistent["hybrid"] and c.recommended in ("hybrid", "score"), c.table()
    # the chunks do not change a seed's values
    c2 = gradient_check(_jump_objective(), np.full(1, 0.5, np.float32), montecarlo.seed_keys(3, 4096),
                        fd_step=0.05, score_scale=0.05 / np.sqrt(3), chunk_size=256)
    for k in c.estimates:
        np.testing.assert_allclose(c2.estimates[k][0], c.estimates[k][0], rtol=1e-5, atol=1e-6)


def test_check_refuses_hybrid_without_a_pair_and_bad_outputs():
    from jaxnc.tune import gradient_check
    keys = montecarlo.seed_keys(0, 4)
    scalar = lambda t, k, temp: t[0] ** 2
    with pytest.raises(ValueError, match="hybrid estimator needs an objective that returns"):
        gradient_check(scalar, np.zeros(1, np.float32), keys, estimators=("hybrid",))
    with pytest.raises(ValueError, match="scalar or a pair"):
        gradient_check(lambda t, k, temp: (t[0], t[0], t[0]), np.zeros(1, np.float32), keys)
    with pytest.raises(ValueError, match="chunk_size must be an integer"):
        gradient_check(scalar, np.zeros(1, np.float32), keys, chunk_size=0)
    lp = _loop()
    with pytest.raises(ValueError, match="estimator='hybrid' needs an objective"):
        tune_loop(lp, {"trigger.delta": Positive()}, estimator="hybrid")
    with pytest.raises(ValueError, match=r"a pair \(smooth, jump\) of scalars"):
        tune_loop(lp, {"trigger.delta": Positive()}, lambda m: (m.cost_raw, m.rate_sc, m.rate_sc))


def test_pair_objective_reaches_the_check_and_the_hybrid_tuner(straight_through_total):
    from jaxnc.tune import check_loop
    lp = _loop(delta=1e-2)
    obj = lambda m: (m.cost_raw, 0.5 * m.rate_sc)      # smooth, "jump"
    chk = check_loop(lp, {"trigger.delta": Positive()}, obj, seeds=8, chunk_size=8)
    assert "hybrid" in chk.estimates and chk.names == ("trigger.delta",)
    # the corrected estimator is opt-in (check_loop(corrected=True)), though this loop supports it
    from jaxnc.tune.jump import corrected_supported
    assert corrected_supported(lp) == "" and "corrected" not in chk.estimates
    r = tune_loop(lp, {"trigger.delta": Positive()}, obj, **dict(_TOTAL_KW, estimator="hybrid"))
    assert r.estimator == "hybrid" and np.isfinite(float(r.params["trigger.delta"]))
    # the pair's sum is the objective: the start's hard evaluation is the scalar objective's
    # (straight_through_total: the same loop, parameter and evaluation seeds, objective cost_raw + 0.5 rate_sc)
    np.testing.assert_allclose(r.eval_values[0], straight_through_total.eval_values[0], rtol=1e-6)


def test_param_paths_names_tied_groups_like_the_result():
    from jaxnc.tune import param_paths
    assert param_paths({"trigger.delta": Positive(), ("delta_s", "sigma_s"): Positive()}) == {
        "trigger.delta": ("trigger.delta",), "delta_s=sigma_s": ("delta_s", "sigma_s")}
    assert param_paths(["controller.K"]) == {"controller.K": ("controller.K",)}


def test_objective_total_sums_a_pair_and_keeps_a_scalar():
    from jaxnc.tune import objective_total
    assert objective_total((1.5, 2.0)) == 3.5 and objective_total(4.0) == 4.0


def test_point_objective_sets_paths_or_tied_names_and_sums_a_pair():
    """point_objective is objective_total(objective(run(cfg with the point, key))): a path
    point, a tied name (both of its paths set), a (smooth, jump) pair summed."""
    from jaxnc.tune import point_objective
    key = jax.random.PRNGKey(3)
    pair = lambda m: (m, 2.0 * m)
    f = point_objective(_Pair(), pair, _pair_run)
    want = 3.0 * _pair_run(_Pair(b=0.5, a=4.0), key)
    np.testing.assert_allclose(float(f({"b": 0.5, "a": 4.0}, key)), float(want), rtol=1e-6)
    g = point_objective(_Pair(), lambda m: m, _pair_run, {"a=b": ("a", "b")})
    np.testing.assert_allclose(float(g({"a=b": 2.0}, key)), float(_pair_run(_Pair(b=2.0, a=2.0), key)), rtol=1e-6)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Pair:
    """A configuration with two leaves and a closed-form objective (for check_loop's run=)."""
    b: float = 1.0
    a: float = 1.0


def _pair_run(cfg, key):
    """E[J] = 10 b + a: in the log coordinates d/dlog b = 10 b, d/dlog a = a (noise keeps the
    standard errors positive)."""
    eps = jax.random.normal(key, (2,))
    return 10.0 * cfg.b * (1.0 + 0.01 * eps[0]) + cfg.a * (1.0 + 0.01 * eps[1])


def test_check_loop_labels_follow_the_gradients_order_for_an_unsorted_dict():
    """``params`` lists b before a; the gradient vector is flattened in sorted-name order.
    Each label must sit on its own coordinate: b's gradient is 10x a's."""
    from jaxnc.tune import check_loop
    c = check_loop(_Pair(), {"b": Positive(), "a": Positive()}, lambda j: j, run=_pair_run, seeds=8)
    g = dict(zip(c.names, c.estimates["finite_difference"][0]))
    assert set(g) == {"a", "b"}
    assert g["b"] / g["a"] == pytest.approx(10.0, rel=0.02), c.table()     # both at 1: the same chain factor
    # in the user's units (the check ran in log coordinates): dE/db = 10, dE/da = 1
    np.testing.assert_allclose(c.in_units("finite_difference")[0], [1.0, 10.0], rtol=0.02)
    with pytest.raises(ValueError, match=r"max_seeds must be an integer in \[8"):
        check_loop(_Pair(), {"b": Positive(), "a": Positive()}, lambda j: j, run=_pair_run, seeds=8, max_seeds=4)


def test_check_loop_shares_one_program_across_points_and_calls():
    """A second point and a repeated call of check_loop on one loop object, with one
    objective and run, trace the loop no more and compile nothing (theta is an argument of
    the check's program, and the flat objective one function per loop object); their
    numbers are, bit for bit, those of a check whose objective is a fresh closure (its
    own trace and program: how every call ran before the programs were shared)."""
    from jaxnc.cache import compile_clock
    from jaxnc.tune import gradient_check
    from jaxnc.tune.loop_tune import _flat, _prepare
    traced = [0]

    def run(cfg, key):
        traced[0] += 1
        return _pair_run(cfg, key)
    cfg, params, obj = _Pair(), {"b": Positive(), "a": Positive()}, lambda j: j
    first = check_loop(cfg, params, obj, run=run, seeds=8)
    checks = []
    for at in ({"a": 2.0, "b": 0.5}, None):
        c0, t0 = compile_clock(), traced[0]
        checks.append(check_loop(cfg, params, obj, run=run, seeds=8, at=at))
        assert (compile_clock() - c0).compilations == 0 and traced[0] == t0
    spec = _prepare("check_loop", cfg, params, obj, _pair_run)
    for c, at in zip([first] + checks, (None, {"a": 2.0, "b": 0.5}, None)):
        flat0, _, fobj = _flat(cfg, spec, at)
        ref = gradient_check(lambda t, k, temp: fobj(t, k, temp), flat0, montecarlo.seed_keys(0, 8), fd_step=0.2,
                             score_scale=0.2 / np.sqrt(3.0))
        np.testing.assert_array_equal(c.theta, flat0)
        assert c.value == ref.value and c.estimates.keys() == ref.estimates.keys()
        for name, (m, se) in ref.estimates.items():
            np.testing.assert_array_equal(c.estimates[name][0], m)
            np.testing.assert_array_equal(c.estimates[name][1], se)
    assert not np.array_equal(checks[0].estimates["score"][0], first.estimates["score"][0])   # another point
    assert all(np.array_equal(checks[1].estimates[k][0], first.estimates[k][0]) for k in first.estimates)
    # bounds given as JAX scalars (unhashable constraints) give the check of the same bounds
    jb = {"b": Interval(jnp.float32(0.0), jnp.float32(2.0)), "a": Interval(jnp.float32(0.0), jnp.float32(2.0))}
    nb = {"b": Interval(0.0, 2.0), "a": Interval(0.0, 2.0)}
    c_j, c_n = (check_loop(cfg, p, obj, run=run, seeds=8) for p in (jb, nb))
    assert c_j.value == c_n.value and all(np.array_equal(c_j.estimates[k][0], c_n.estimates[k][0]) for k in c_n.estimates)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Nested:
    """A configuration whose gains are a nested dict, as a ``Function`` controller's params."""
    params: dict = dataclasses.field(default_factory=lambda: {"gains": {"kp": 2.0, "kd": 0.5}})
    limits: tuple = (1.0, 4.0)


def _nested_run(cfg, key):
    """E[J] = 10 kp + kd + 3 limits[1] (noise keeps the standard errors positive)."""
    g, eps = cfg.params["gains"], jax.random.normal(key, (3,))
    return (10.0 * g["kp"] * (1.0 + 0.01 * eps[0]) + g["kd"] * (1.0 + 0.01 * eps[1])
            + 3.0 * cfg.limits[1] * (1.0 + 0.01 * eps[2]))


def test_paths_reach_the_entries_of_a_nested_dict_and_a_tuple():
    """A gain inside a dict (``Function(params={"gains": {"kp": ...}})``) is named by its
    keys, ``"params.gains.kp"``, and an entry of a tuple (``LimitedActuator.limits``) by its
    index, ``"limits.1"`` (both were refused: a dict has no field, "1" is no attribute). The
    check's table carries each entry's own label and its gradient in the entry's units; a
    missing key or index is refused, not added."""
    cfg = _Nested()
    assert get_path(cfg, "params.gains.kp") == 2.0 and not is_static(cfg, "params.gains.kd")
    assert get_path(cfg, "limits.1") == 4.0 and not is_static(cfg, "limits.1")
    cfg2 = set_paths(cfg, {"params.gains.kp": 3.0, "limits.1": 5.0})
    assert cfg2.params == {"gains": {"kp": 3.0, "kd": 0.5}} and cfg.params["gains"]["kp"] == 2.0
    assert cfg2.limits == (1.0, 5.0) and cfg.limits == (1.0, 4.0)
    with pytest.raises(ValueError, match=r"'params.gains.ki'.*no field 'ki'.*fields: kp, kd"):
        set_paths(cfg, {"params.gains.ki": 1.0})
    with pytest.raises(ValueError, match=r"'limits.2'.*no field '2'.*fields: 0, 1"):
        set_paths(cfg, {"limits.2": 1.0})
    c = check_loop(cfg, {"params.gains.kp": Positive(), "limits.1": Positive(), "params.gains.kd": Positive()},
                   lambda j: j, run=_nested_run, seeds=8)
    assert c.names == ("limits.1", "params.gains.kd", "params.gains.kp")
    np.testing.assert_allclose(c.in_units("finite_difference")[0], [3.0, 1.0, 10.0], rtol=0.02)
    np.testing.assert_allclose(c.values, [4.0, 0.5, 2.0])


def _linear(theta, key, temperature):
    """J = theta_0 (1 + e_0) + 0.3 theta_1 (1 + e_1), e ~ N(0, I) per seed: the gradient of
    the mean is (1, 0.3). The score function's paired difference to the finite differences
    has variance 4 + 0.18 on coordinate 0 and 2 + 0.36 on coordinate 1, so at z = 3
    coordinate 0 is resolved from about 38 seeds and coordinate 1 only from about 236."""
    e = jax.random.normal(key, (2,))
    return theta[0] * (1.0 + e[0]) + 0.3 * theta[1] * (1.0 + e[1])


def test_check_resolves_every_coordinate_and_names_the_unresolved_one():
    """At 128 seeds the score function agrees with the finite differences and the largest
    coordinate is resolved (the former rule, on the largest coordinate, passed it), but
    coordinate 1 is not: nothing is recommended and the reason names it with the seeds it
    needs. Doubling up to 1024 seeds makes the check conclusive. (z = 3: a doubling check
    looks several times, and a flag, however unlikely for an unbiased estimator, ends it.)"""
    from jaxnc.tune import gradient_check
    kw = dict(estimators=("score",), names=("a", "b"), score_scale=0.05, z=3.0)
    c = gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 128), **kw)
    assert c.seeds == 128 and c.recommended is None, c.table()
    assert c.resolved["score"].tolist() == [True, False], c.table()
    assert c.reason["score"].startswith("inconclusive on b ("), c.reason
    need = c.seeds_needed["score"][1]
    assert 128 < need < 1024 and f"about {int(need)} seeds" in c.reason["score"]
    # the estimate of the seeds needed follows SE ~ 1/sqrt(n), with the gradient's size squared less the
    # means' own noise (E[mean^2] = g^2 + SE^2)
    (g, g_se), (fd, fd_se) = c.estimates["score"], c.estimates["finite_difference"]
    size2 = max(g[1] ** 2 - g_se[1] ** 2, fd[1] ** 2 - fd_se[1] ** 2)
    assert size2 > 0
    np.testing.assert_allclose(need, np.ceil(128 * c.resolution["score"][1] ** 2 / size2))
    assert "no (~" in c.table()
    more = lambda start, count: montecarlo.seed_keys(0, count, start)
    c2 = gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 128), max_seeds=1024,
                        more_keys=more, **kw)
    assert c2.recommended == "score" and c2.resolved["score"].all(), c2.table()
    assert c2.seeds in (256, 512, 1024)
    # the doubled check is the single check on as many seeds (the same chunks)
    c3 = gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, c2.seeds), chunk_size=128, **kw)
    np.testing.assert_allclose(c3.estimates["score"][0], c2.estimates["score"][0], rtol=1e-6)
    with pytest.raises(ValueError, match="needs more_keys"):
        gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 16), max_seeds=32, **kw)
    with pytest.raises(ValueError, match=r"max_seeds must be an integer in \[16"):
        gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 16), max_seeds=8, more_keys=more)
    with pytest.raises(ValueError, match="names must be 2 strings"):
        gradient_check(_linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 16), names=("a",))


def _pair_linear_run(cfg, key):
    """E[J] = a + 0.3 b, noisy as :func:`_linear`, and the pathwise derivative in b misses
    its mean (the straight-through gradient is wrong on b by exactly 0.3 on every seed)."""
    e = jax.random.normal(key, (2,))
    return cfg.a * (1.0 + e[0]) + 0.3 * jax.lax.stop_gradient(cfg.b) + 0.3 * cfg.b * e[1]


def test_gradient_check_args_are_arguments_of_one_program():
    """``args`` reach the objective as arguments of the check's compiled program: a second
    call with other values of the same shapes (and another theta) compiles nothing, and
    gives, bit for bit, the check of a closure over those values (its own program)."""
    from jaxnc.cache import compile_clock
    from jaxnc.tune import gradient_check

    def scaled(theta, key, temperature, w):
        return w[0] * _linear(theta, key, temperature) + w[1] * theta[0] ** 2

    keys = montecarlo.seed_keys(5, 32)
    gradient_check(scaled, np.zeros(2, np.float32), keys, args=(np.float32([1.0, 0.5]),))
    c0 = compile_clock()
    c = gradient_check(scaled, np.full(2, 0.3, np.float32), keys, args=(np.float32([2.0, -1.0]),))
    assert (compile_clock() - c0).compilations == 0
    w = np.float32([2.0, -1.0])
    ref = gradient_check(lambda t, k, temp: scaled(t, k, temp, w), np.full(2, 0.3, np.float32), keys)
    assert c.value == ref.value
    for name, (m, se) in ref.estimates.items():
        np.testing.assert_array_equal(c.estimates[name][0], m)
        np.testing.assert_array_equal(c.estimates[name][1], se)
    with pytest.raises(ValueError, match="args must be a tuple"):
        gradient_check(scaled, np.zeros(2, np.float32), keys, args=[w])
    # steps, temperature and scale given as JAX scalars (unhashable) reach the same program
    j = gradient_check(scaled, np.full(2, 0.3, np.float32), keys, args=(w,), fd_step=jnp.float32(0.05),
                       temperature=jnp.float32(1e-3), score_scale=jnp.asarray(0.05, jnp.float32))
    assert j.value == c.value and all(np.array_equal(j.estimates[n][0], c.estimates[n][0]) for n in c.estimates)


def test_tune_loops_check_doubles_its_seeds_until_conclusive():
    """tune_loop's check: the straight-through gradient misses b (flagged at once); the
    score function needs more than check_seeds = 8 seeds on b, so the check doubles them
    (up to check_max_seeds) and recommends it; the doubled seeds are counted. With the
    increase off, the tuner falls back on the score function and says which coordinate was
    unresolved."""
    cfg = _Pair(b=1.0, a=1.0)
    params = {"b": Interval(0.0, 2.0), "a": Interval(0.0, 2.0)}       # slope 0.5 at the middle
    kw = dict(run=_pair_linear_run, steps=1, batch=2, check_seeds=8, eval_seeds=2, estimator="auto", progress=False)
    r = tune_loop(cfg, params, lambda j: j, check_max_seeds=1024, **kw)
    assert r.estimator == "score" and r.check.recommended == "score", r.check.table()
    assert r.check.reason["straight_through"].startswith("differs"), r.check.table()
    assert 8 < r.check.seeds <= 1024
    # a check seed: the value, 2 x 2 x 2 central differences (h, 2h), a pathwise pass, pairs at s and 2s
    assert r.check.runs_per_seed == 1 + 8 + 1 + 2 + 2
    assert r.tuning_simulations == r.check.seeds * r.check.runs_per_seed + 2 + 2 * 256   # score: batch 2 = one pair; the pick
    # in the user's units: dE/da = 1, dE/db = 0.3; theta is the logit, d value / d theta = 0.5
    assert r.check.names == ("a", "b")
    np.testing.assert_allclose(r.check.values, [1.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(r.check.dvalue_dtheta, [0.5, 0.5], rtol=1e-6)
    fd, fd_se = r.check.in_units("finite_difference")
    np.testing.assert_allclose(fd, r.check.estimates["finite_difference"][0] / 0.5, rtol=1e-6)
    assert np.all(np.abs(fd - [1.0, 0.3]) < 4 * fd_se), r.check.table()
    assert "in the parameter's units" in r.check.table()
    off = tune_loop(cfg, params, lambda j: j, check_max_seeds=8, **kw)
    assert off.check.seeds == 8 and off.check.recommended is None
    assert "inconclusive on b (" in off.estimator_reason and "seeds would resolve it" in off.estimator_reason
    # the reason quotes the resolution in the user's units (d value / d theta = 0.5)
    assert f"resolves {off.check.resolution['score'][1] / 0.5:.3g}," in off.estimator_reason
    with pytest.raises(ValueError, match=r"check_max_seeds must be an integer in \[8"):
        tune_loop(cfg, params, lambda j: j, check_max_seeds=4, **kw)


def test_tune_loop_refuses_a_start_outside_its_interval():
    """The loss probability starts at 0.2, outside Interval(0.3, 0.9): refused, not moved to 0.3."""
    with pytest.raises(ValueError, match=r"tune_loop: the start of 'uplink.loss.p' must be inside the open "
                                         r"interval \(0.3, 0.9\).*got 0.2"):
        tune_loop(_loop(), {"uplink.loss.p": Interval(0.3, 0.9)})
    with pytest.raises(ValueError, match=r"search\['uplink.loss.p'\] value 1.0: the start of 'uplink.loss.p' must "
                                         r"be inside the open interval"):
        tune_loop(_loop(), {"uplink.loss.p": Interval(0.0, 0.9)}, search={"uplink.loss.p": [0.1, 1.0]})


def test_tune_loop_refuses_a_start_of_zero_under_positive():
    """delta = 0 under Positive (log) has no raw value: refused, not replaced by 1e-6."""
    with pytest.raises(ValueError, match=r"tune_loop: the start of 'trigger.delta' must be finite and > 0 "
                                         r"\(Positive\(low=0\).*got 0.0"):
        tune_loop(_loop(delta=0.0), {"trigger.delta": Positive()})
    with pytest.raises(ValueError, match=r"the start of 'controller.K' must be finite and > 2 .*got \[\[3.0, 1.5\]\]"):
        tune_loop(_loop(), {"controller.K": Positive(low=2.0)})       # K = (3, 1.5): one element below


def test_tune_loop_refuses_a_search_budget_of_zero_or_without_a_search():
    """search_budget=0 used to mean "the default"; now None is the default and 0 is refused."""
    lp = _loop(pmf=(0.5, 0.5))
    with pytest.raises(ValueError, match=r"search_budget must be an integer in \[1"):
        tune_loop(lp, search={"estimator.buffer": [0, 1]}, search_budget=0)
    from jaxnc.cache import compile_clock
    before = compile_clock()
    with pytest.raises(ValueError, match=r"search_budget must be at least 2 \(one seed per candidate and round"):
        tune_loop(lp, search={"estimator.buffer": [0, 1]}, search_budget=1)
    assert compile_clock().compilations == before.compilations      # refused before the start's evaluation
    with pytest.raises(ValueError, match="search_budget is given without a search"):
        tune_loop(lp, {"trigger.delta": Positive()}, search_budget=64)


def test_tune_loop_refuses_a_loop_without_a_cost():
    """A Loop without a cost makes m.cost_raw NaN on every run: refused before tracing with
    the default objective, and on the start's evaluation seeds with a user's objective that
    reads it (before any of the budget is spent)."""
    lp = dataclasses.replace(_loop(), cost=None)
    with pytest.raises(ValueError, match=r"the loop has no cost \(Loop.cost is None\)"):
        tune_loop(lp, {"trigger.delta": Positive()})
    with pytest.raises(ValueError, match=r"the objective is NaN at the start on 4 of 4 evaluation seeds"):
        tune_loop(lp, {"trigger.delta": Positive()}, lambda m: m.cost_raw + m.rate_sc, eval_seeds=4, progress=False)


def test_tune_loop_refuses_a_part_or_a_none_field_instead_of_a_leaf():
    lp = _loop()
    with pytest.raises(ValueError, match=r"'trigger' is a part \(Petc\), not a leaf: name one of its fields "
                                         r"\(trigger.sigma, trigger.delta"):
        tune_loop(lp, {"trigger": Positive()})
    with pytest.raises(ValueError, match=r"'controller.u_max' is None in this loop"):
        tune_loop(lp, {"controller.u_max": Positive()})
    with pytest.raises(ValueError, match=r"'controller_trigger' is None in this loop"):
        check_loop(lp, ["controller_trigger"])


# ----------------------------------------------------------------------------- overheads (issue 31, item 3)


def test_hard_program_is_the_objective_at_the_start_and_at_each_perturbed_point():
    """The program the evaluation and the score-function steps share: scale 0 gives the
    objective at the loop's own values; scale s the objective at constrain(raw + s e), e
    drawn from the key, against the per-seed function evaluated directly."""
    from jaxnc.tune.loop_tune import _as_f32, _hard_program, _prepare
    cfg = _Pair(b=0.5, a=2.0)
    spec = _prepare("test", cfg, {"b": Positive(), "a": Interval(0.0, 4.0)}, lambda j: j, _pair_run)
    hard = _hard_program(spec, 16)
    keys = montecarlo.seed_keys(3, 20)                    # two chunks, the second padded
    v0, e = hard(_as_f32(cfg, spec), keys, np.zeros(20))
    direct = np.asarray([_pair_run(cfg, k) for k in keys])
    np.testing.assert_allclose(v0, direct, rtol=1e-6)
    assert e.shape == (20, 2)
    v1, e1 = hard(_as_f32(cfg, spec), keys, np.full(20, 0.1))
    np.testing.assert_array_equal(e1, e)                  # e depends on the key only
    raw_a, raw_b = np.log(2.0 / (4.0 - 2.0)), np.log(0.5)  # sorted names: a, then b
    a = 4.0 / (1.0 + np.exp(-(raw_a + 0.1 * e[:, 0])))
    b = np.exp(raw_b + 0.1 * e[:, 1])
    ref = np.asarray([_pair_run(_Pair(b=bi, a=ai), k) for ai, bi, k in zip(a, b, keys)])
    np.testing.assert_allclose(v1, ref, rtol=1e-5)


def _compilations(**kw):
    from jaxnc.tune import tune_loop
    r = tune_loop(_Pair(b=0.5, a=2.0), {"b": Positive(), "a": Positive()}, lambda j: j, run=_pair_run,
                  batch=4, eval_seeds=8, progress=False, **kw)
    return r


@pytest.mark.parametrize("estimator", ["score", "straight_through"])
def test_tune_loops_compilations_are_bounded_and_do_not_grow_with_steps(estimator):
    """A fresh tune_loop call compiles its programs once each: the same number for 2 and 9
    steps (no re-tracing per step: the point and the temperature are arguments), and the
    score function's steps compile only the optimiser's update (their simulations run in
    the evaluation's program). The compile clock and the stages are reported."""
    _compilations(steps=2, estimator=estimator)          # the small eager programs, once per process
    r2 = _compilations(steps=2, estimator=estimator)
    r9 = _compilations(steps=9, estimator=estimator)
    assert r2.n_compilations == r9.n_compilations, (r2.stages, r9.stages)
    assert set(r9.stages) == {"evaluation", "gradient", "pick"}
    assert r9.stages["pick"][2] == 0                       # the pick runs in the evaluation's program
    assert 0 < r9.compile_s <= r9.wall_time_s
    assert r9.stages["evaluation"][2] == 1                 # the hard program, start and end
    if estimator == "score":
        assert r9.stages["gradient"][2] == 1               # the update alone
    else:
        assert r9.stages["gradient"][2] == 1               # the pathwise step
    assert "compiling" in r9.summary()


@pytest.mark.parametrize("estimator", ["auto", "richardson"])
def test_auto_and_richardson_compile_the_same_programs_for_2_and_12_steps(estimator):
    """A user counted 12 compilations in a 12-step tune_loop: the first call's small eager
    programs (key folding, the constraints' transforms), compiled once per process whatever
    the number of steps, not one program per step. With the check ("auto") and the
    extrapolated score the count is the same for 2 and 12 steps."""
    kw = dict(estimator=estimator, check_seeds=16, check_max_seeds=16)
    _compilations(steps=2, **kw)                           # the small eager programs, once per process
    r2, r12 = _compilations(steps=2, **kw), _compilations(steps=12, **kw)
    assert r2.n_compilations == r12.n_compilations, (r2.stages, r12.stages)
    assert r12.stages["gradient"][2] <= 1, r12.stages
    assert len(r12.tune.history.objective) == 12


def test_repeated_tune_loop_calls_share_the_evaluation_and_search_programs():
    """A second tune_loop call on the same loop object with the same objective and run
    compiles nothing for its evaluations and its search (the hard program is one jitted
    function per objective, run and parameters; the search's per-seed function one per
    loop object); its numbers are, bit for bit, the first call's and those of a call with a
    fresh objective (its own traces and programs)."""
    cfg, params, obj = _Pair(b=0.5, a=2.0), {"b": Positive(), "a": Positive()}, lambda j: j
    kw = dict(run=_pair_run, search={"b": [0.25, 0.5, 1.0, 2.0]}, search_budget=16, steps=3, batch=4, eval_seeds=8,
              pick_seeds=8, progress=False)
    first = tune_loop(cfg, params, obj, **kw)
    again = tune_loop(cfg, params, obj, **kw)
    fresh = tune_loop(cfg, params, lambda j: j, **kw)
    assert again.stages["evaluation"][2] == again.stages["search"][2] == 0, again.stages
    assert fresh.stages["evaluation"][2] >= 1, fresh.stages      # a new objective: its own programs
    for r in (again, fresh):
        for k in ("a", "b"):
            np.testing.assert_array_equal(r.params[k], first.params[k])
            np.testing.assert_array_equal(r.tune.history.params[k], first.tune.history.params[k])
        np.testing.assert_array_equal(r.search.values, first.search.values)
        np.testing.assert_array_equal(r.eval_values[0], first.eval_values[0])
        np.testing.assert_array_equal(r.eval_values[1], first.eval_values[1])


def test_evaluation_is_optional_and_does_not_change_the_tuned_point():
    a = _compilations(steps=3, estimator="score")
    b = _compilations(steps=3, estimator="score", evaluate=False)
    np.testing.assert_array_equal(a.params["a"], b.params["a"])
    np.testing.assert_array_equal(a.params["b"], b.params["b"])
    assert b.eval_values == () and np.isnan(b.start_eval[0]) and np.isnan(b.paired_diff[1])
    assert b.n_simulations == b.tuning_simulations == a.tuning_simulations == a.n_simulations - 16
    assert "evaluation" not in b.stages and "not evaluated" in b.summary()


def test_default_estimator_is_the_score_function_without_a_check():
    """The default never uses an estimator that can be biased on hard triggers without a
    passing check: it is the score function (unbiased for the smoothed objective), no check
    runs, and its reason says so; the check is opt-in (estimator="auto")."""
    r = _compilations(steps=3, evaluate=False)
    assert r.estimator == "score" and r.check is None and "check" not in r.stages
    assert "unbiased" in r.estimator_reason
    import inspect
    sig = inspect.signature(tune_loop).parameters
    assert sig["estimator"].default == "score"
    # the check's defaults are check_loop's: 256 seeds doubling to 32768, fd 0.2, scale fd / sqrt(3)
    cl = inspect.signature(check_loop).parameters
    assert sig["fd_step"].default == cl["fd_step"].default == 0.2
    assert sig["check_seeds"].default == 256 and sig["score_scale"].default is None is cl["score_scale"].default


def test_max_seconds_bounds_the_tuning_and_the_steps_follow_the_time():
    """With max_seconds the gradient stage stops when the budget (the call's time without
    its evaluation, compilations included) would be passed: far fewer than the steps
    allowed, inside the budget plus one step, and the evaluation is not counted."""
    _compilations(steps=2)                                 # the small eager programs, once per process
    budget = 3.0                                           # hundreds of steps of ~ms each: the budget stops them
    r = _compilations(steps=100_000, max_seconds=budget)
    done = len(r.tune.history.objective)
    tuning = sum(w for k, (w, _, _) in r.stages.items() if k not in ("evaluation", "pick"))
    step = r.stages["gradient"][0] / done
    assert 2 <= done < 100_000
    assert tuning <= budget + 2 * step + 0.1, (r.stages, done)
    assert r.tuning_simulations == done * 4 + 2 * 256      # batch 4: 2 antithetic pairs, 4 runs a step; the pick
    with pytest.raises(ValueError, match="max_seconds"):
        _compilations(steps=2, max_seconds=0.0)
    with pytest.raises(ValueError, match="learning_rate"):
        _compilations(steps=2, learning_rate=(0.3, 0.0))


def _bowl_run(cfg, key):
    """E[J] = (log b)^2 + (log a/2)^2 + const: the minimum at b = 1, a = 2."""
    eps = jax.random.normal(key, (2,))
    return jnp.log(cfg.b) ** 2 + jnp.log(cfg.a / 2.0) ** 2 + 0.01 * eps[0]


def test_the_pick_keeps_the_start_when_the_steps_made_it_worse():
    """After the gradient stage its start and end run on common seeds and the better is
    kept: steps of e^3 from the bowl's minimum end far worse, so the start is returned (and
    the reason says so); from b = 3 small steps improve, so the end is kept. pick_seeds=0
    keeps the end whatever it is."""
    from jaxnc.tune import tune_loop
    kw = dict(run=_bowl_run, batch=4, evaluate=False, progress=False)
    params = {"b": Positive(), "a": Positive()}
    wild = tune_loop(_Pair(b=1.0, a=2.0), params, lambda j: j, steps=3, learning_rate=3.0, **kw)
    assert float(wild.params["b"]) == 1.0 and float(wild.params["a"]) == 2.0
    assert wild.pick[1] > wild.pick[0] and "the start is kept" in wild.estimator_reason
    assert wild.tuning_simulations == 3 * 4 + 2 * 256
    off = tune_loop(_Pair(b=1.0, a=2.0), params, lambda j: j, steps=3, learning_rate=3.0, pick_seeds=0, **kw)
    assert float(off.params["b"]) != 1.0 and off.pick == () and "pick" not in off.stages
    calm = tune_loop(_Pair(b=3.0, a=2.0), params, lambda j: j, steps=20, learning_rate=0.3, **kw)
    assert abs(np.log(float(calm.params["b"]))) < np.log(3.0) and calm.pick[1] < calm.pick[0]
    assert "beat its start" in calm.estimator_reason
    with pytest.raises(ValueError, match="pick_seeds"):
        tune_loop(_Pair(), params, lambda j: j, pick_seeds=-1, **kw)


def _flat_run(cfg, key):
    """E[J] = 0 for every b (flat), but each seed's J = eps b moves with b: the score
    function's per-step estimates are noise of mean zero."""
    return jax.random.normal(key) * cfg.b


def test_budget_rule_gives_an_unresolved_gradient_stage_to_the_search_finalists():
    """The default budget rule: on a flat objective the score steps resolve no coordinate
    after a quarter of their number (here 10 of 40), so they stop, their end is dropped,
    and the 30 steps not made plus the pick's seeds refine the search's finalists: the
    same total budget, the tuned point a searched candidate. On a bowl the steps resolve
    the slope at once and all of them run, followed by the pick."""
    from jaxnc.tune import tune_loop
    kw = dict(batch=4, steps=40, pick_seeds=16, evaluate=False, progress=False)
    grid = [0.5, 1.0, 2.0, 4.0]
    # the test is at the 95 % level: of 8 seeds, 7 stop here (seed 0 drifts up for 10 steps, |t| 2.96)
    stopped = [len(tune_loop(_Pair(b=1.0), {"b": Positive()}, lambda j: j, run=_flat_run, search={"b": grid},
                             search_budget=16, seed=s, **kw).tune.history.objective) == 10 for s in range(8)]
    assert sum(stopped) >= 6, stopped
    flat = tune_loop(_Pair(b=1.0), {"b": Positive()}, lambda j: j, run=_flat_run, search={"b": grid},
                     search_budget=16, seed=1, **kw)
    n_test, t, z = flat.resolution
    assert n_test == 10 and t.shape == (1,) and t[0] < z == pytest.approx(1.959964, rel=1e-5)
    assert len(flat.tune.history.objective) == 10 and flat.pick == ()
    assert "no coordinate was resolved" in flat.estimator_reason
    # the steps not made and the pick's seeds, 152 simulations, run 4 finalists (all the grid here) and the
    # steps' end on 30 common new seeds each (the remainder, 2, is not spent): the budget without the rule, less 2
    assert flat.search.n_simulations == 16 + 5 * 30 and len(flat.search.points) == 5
    assert flat.tuning_simulations == 16 + 10 * 4 + 5 * 30 == 16 + 40 * 4 + 2 * 16 - 2
    assert np.all(~np.isnan(flat.search.values[:, -30:]))
    assert float(flat.params["b"]) == pytest.approx(float(flat.search.best_point["b"]))
    assert flat.search.best == int(np.argmin(np.nanmean(flat.search.values[:, -30:], axis=1)))   # on the new seeds
    # the rule off: every step runs, then the pick
    off = tune_loop(_Pair(b=1.0), {"b": Positive()}, lambda j: j, run=_flat_run, search={"b": grid},
                    search_budget=16, resolve_at=0.0, seed=1, **kw)
    assert off.resolution == () and len(off.tune.history.objective) == 40 and off.pick != ()
    assert off.tuning_simulations == 16 + 40 * 4 + 2 * 16
    # a bowl still being descended at the test: resolved, so the steps run on, then the pick
    kb = dict(kw, learning_rate=0.1)
    far = tune_loop(_Pair(b=300.0, a=2.0), {"b": Positive(), "a": Positive()}, lambda j: j, run=_bowl_run,
                    search={"b": [300.0, 500.0]}, search_budget=4, **kb)
    n_test, t, z = far.resolution
    assert n_test == 10 and t[1] >= z == pytest.approx(2.241403, rel=1e-5)   # d = 2; b is coordinate 1
    assert len(far.tune.history.objective) == 40 and far.pick != () and far.pick[1] < far.pick[0]
    assert float(far.params["b"]) < 300.0 / np.e ** 2
    # printing a result gives its summary (a few lines), not the per-seed arrays it holds
    text = str(far)
    assert text == repr(far) == far.summary() and len(text.splitlines()) < 20
    assert "budget rule: after 10 steps" in text and "pick: the gradient's start" in text
    assert "gradient steps made: 40" in text and "doubtful" not in text
    # an evaluation whose costs have rare, large runs says its interval is doubtful (Cochran's rule)
    v0 = np.full(512, 5.0)
    v0[:3] = 100.0
    v1 = v0.copy()
    v1[3] = 4.0
    skewed = far._replace(eval_values=(v0, v1))
    need = max(montecarlo.seeds_for_normal_interval(v) for v in (v0, v1, v1 - v0))
    assert need > 4000 and (f"doubtful: the objective is skewed (rare costly runs); its normal interval needs about "
                            f"{need} seeds by Cochran's rule, the evaluation has 512") in skewed.summary()
    # a bowl reached before the test (from b = 3 at a rate of 0.3): nothing left to resolve, so the
    # steps stop, and their end, a finalist beside the searched 3 and 5, wins on the common seeds
    near = tune_loop(_Pair(b=3.0, a=2.0), {"b": Positive(), "a": Positive()}, lambda j: j, run=_bowl_run,
                     search={"b": [3.0, 5.0]}, search_budget=4, learning_rate=0.3, **kw)
    n_test, t, z = near.resolution
    assert n_test == 10 and np.all(t < z) and len(near.tune.history.objective) == 10
    assert near.search.best == len(near.search.points) - 1 and "the steps' end won" in near.estimator_reason
    assert abs(np.log(float(near.params["b"]))) < np.log(3.0) / 2 and near.tuning_simulations == 4 + 10 * 4 + 3 * 50
    with pytest.raises(ValueError, match="resolve_at"):
        tune_loop(_Pair(b=1.0), {"b": Positive()}, lambda j: j, run=_flat_run, search={"b": grid}, resolve_at=1.5)


def test_steps_resolution_is_the_t_statistic_over_the_steps():
    from jaxnc.tune.loop_tune import steps_resolution
    g = np.array([[1.0, 0.0, 2.0], [3.0, 0.0, 2.0], [2.0, 0.0, 2.0], [np.nan, 1.0, 1.0]])
    t, z = steps_resolution(g)              # the non-finite step is dropped: n = 3
    assert t[0] == pytest.approx(2.0 / (1.0 / np.sqrt(3.0))) and t[1] == 0.0 and t[2] == np.inf
    assert z == pytest.approx(2.393980, rel=1e-5)                     # Phi^-1(1 - 0.025 / 3)
    with pytest.raises(ValueError, match="n >= 2"):
        steps_resolution(np.ones((1, 2)))
