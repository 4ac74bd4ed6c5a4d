"""The corrected pathwise gradient with hard PETC triggers (jaxnc.tune.jump) against closed forms."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.loop.triggers import petc_crossings, petc_gap
from jaxnc.tune.jump import corrected_grad, corrected_supported, crossing_weights


@pytest.mark.parametrize("reading", ["sum", "each"])
def test_crossings_are_the_zeros_of_the_gap(reading):
    """Each valid crossing puts the gap at zero, with |d gap / d xi| = the returned slope;
    an output without noise has none."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        last, z = rng.normal(size=3).astype(np.float32), rng.normal(size=3).astype(np.float32)
        v = (0.3 * rng.normal(size=3)).astype(np.float32)
        std = np.asarray([0.3, 0.5, 0.0], np.float32)
        sigma, delta = np.float32(rng.uniform(0, 0.5)), np.float32(rng.uniform(0, 1.0))
        xi, slope, valid = jax.jit(petc_crossings, static_argnames="reading")(last, z, v, std, sigma, delta,
                                                                              reading=reading)
        assert not np.any(valid[2])
        for i in range(2):
            for r in range(2):
                if not valid[i, r]:
                    continue
                g = lambda x: petc_gap(last, z + np.eye(3, dtype=np.float32)[i] * (std[i] * x - v[i]), sigma, delta,
                                       reading)
                assert abs(float(g(xi[i, r]))) < 1e-4 * (1 + float(slope[i, r]))
                assert abs(float(jax.grad(g)(xi[i, r]))) == pytest.approx(float(slope[i, r]), rel=1e-3, abs=1e-5)


def _gaps_of(last, sigma, delta, s):
    """gaps_of for crossing_weights: one instant, one output, z = x + v with x = theta[0]."""
    v = jnp.asarray([[0.123]], jnp.float32)
    def gaps_of(t):
        z = t[0] + v
        return (jnp.full((1, 1), last, jnp.float32), z, v, jnp.asarray([s], jnp.float32), sigma, delta, "sum",
                jnp.zeros((1,), bool))
    return gaps_of


@pytest.mark.parametrize("x", [-0.3, 0.05, 0.4])
def test_jump_weights_give_the_derivative_of_a_gaussian_exceedance(x):
    """d/dx P(decision fires) for z = x + eps, eps ~ N(0, s^2), in closed form: the sum of
    the crossing weights (the jump term with a jump of 1), whatever the drawn eps.

    sigma = 1, zbar = -1/2: the gap is z - (delta - 1/4), so P = P(x + eps > delta - 1/4);
    sigma = 0, zbar = 0: the gap is z^2 - delta, so P = P(|x + eps| > sqrt(delta))."""
    s, delta = 0.2, 0.3
    th = jnp.asarray([x], jnp.float32)
    w, _, _, _ = jax.jit(lambda t: crossing_weights(_gaps_of(-0.5, 1.0, delta, s), t))(th)
    c = delta - 0.25
    assert float(jnp.sum(w)) == pytest.approx(norm.pdf((c - x) / s) / s, rel=1e-4)
    w, _, _, _ = jax.jit(lambda t: crossing_weights(_gaps_of(0.0, 0.0, delta, s), t))(th)
    a = np.sqrt(delta)
    exact = (norm.pdf((a - x) / s) - norm.pdf((-a - x) / s)) / s
    assert float(jnp.sum(w)) == pytest.approx(exact, rel=1e-4, abs=1e-6)
    # and with respect to the threshold: dP/d delta = -pdf((sqrt(delta) -+ x)/s) / (2 s sqrt(delta)) summed
    def gaps_delta(t):
        v = jnp.asarray([[0.0]], jnp.float32)
        return (jnp.zeros((1, 1)), x + v, v, jnp.asarray([s], jnp.float32), 0.0, t[0], "sum", jnp.zeros((1,), bool))
    w, _, _, _ = jax.jit(lambda t: crossing_weights(gaps_delta, t))(jnp.asarray([delta], jnp.float32))
    exact_d = -(norm.pdf((a - x) / s) + norm.pdf((a + x) / s)) / (2 * s * a)
    assert float(jnp.sum(w)) == pytest.approx(exact_d, rel=1e-4)


# ---------------------------------------------------------------------------- a scalar loop

S_V, DELTA, R_U, THETA = 0.2, 0.04, 0.5, 0.6


def _scalar_loop(theta=THETA):
    """x' = x + u, z = x + v, u = -theta zhat; zhat the last z sent (Passthrough), k = 0
    always sends; two periods, J = (x0^2 + x1^2 + r u0^2 + r u1^2) / 2."""
    plant = nc.LTI(A=[[1.0]], B=[[1.0]], C=[[1.0]], x0=[1.0], w_std=[0.0], v_std=[S_V], T=1.0)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=DELTA), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.StateFeedback(jnp.reshape(jnp.asarray(theta, jnp.float32), (1, 1))),
                   downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0], R=[R_U]), N=1, steps=2, T=1.0)


def _exact_mean_cost(theta: float) -> float:
    """E[J] in float64: truncated-normal moments over v1 given v0 (the decision at k = 1
    fires when |z1 - z0| > sqrt(delta)), Gauss-Hermite over v0 (smooth in v0)."""
    u, wts = np.polynomial.hermite_e.hermegauss(80)
    wts = wts / wts.sum()
    s, a = S_V, np.sqrt(DELTA)
    z0 = 1.0 + s * u
    x1 = 1.0 - theta * z0
    c = x1 - z0
    up, lo = (a - c) / s, (-a - c) / s
    m = x1
    tail_up = m * m * norm.sf(up) + 2 * m * s * norm.pdf(up) + s * s * (norm.sf(up) + up * norm.pdf(up))
    tail_lo = m * m * norm.cdf(lo) - 2 * m * s * norm.pdf(lo) + s * s * (norm.cdf(lo) - lo * norm.pdf(lo))
    e_xhat2 = tail_up + tail_lo + z0 * z0 * (norm.cdf(up) - norm.cdf(lo))
    J = 0.5 * (1.0 + x1 * x1 + R_U * theta ** 2 * z0 * z0 + R_U * theta ** 2 * e_xhat2)
    return float(np.sum(wts * J))


def test_scalar_loop_closed_form_mean_cost():
    """The closed form is the Monte-Carlo mean of the hard loop (the reference is right)."""
    keys = montecarlo.seed_keys(0, 20000)
    J = np.asarray(jax.jit(jax.vmap(lambda k: nc.run(_scalar_loop(), k).cost_raw))(keys))
    assert abs(J.mean() - _exact_mean_cost(THETA)) < 4 * J.std() / np.sqrt(J.size)


def test_scalar_loop_corrected_gradient_is_unbiased_and_the_pathwise_alone_is_not():
    """dE[J]/dtheta in closed form (central difference of the float64 closed form) against
    the corrected estimate's mean over seeds (within 4 standard errors); the pathwise
    gradient alone (decisions held) misses the jump term by many standard errors."""
    h = 1e-4
    exact = (_exact_mean_cost(THETA + h) - _exact_mean_cost(THETA - h)) / (2 * h)
    loop_of = lambda t: _scalar_loop(t[0])
    cost = lambda lp, k: nc.run(lp, k).cost_raw
    th = jnp.asarray([THETA], jnp.float32)

    def per(key):
        _, g = corrected_grad(loop_of, cost, th, key)
        return g[0], jax.grad(lambda t: cost(loop_of(t), key))(th)[0]
    keys = montecarlo.seed_keys(1, 20000)
    g, path = (np.asarray(a, float) for a in jax.jit(jax.vmap(per))(keys))
    se = g.std() / np.sqrt(g.size)
    assert abs(g.mean() - exact) < 4 * se, (g.mean(), exact, se)
    se_p = path.std() / np.sqrt(path.size)
    assert abs(path.mean() - exact) > 10 * se_p, (path.mean(), exact, se_p)


def test_supported_says_why_not():
    lp = _scalar_loop()
    assert corrected_supported(lp) == ""
    assert "noise" in corrected_supported(dataclasses.replace(lp, plant=dataclasses.replace(lp.plant, v_std=[0.0])))
    assert "relaxed" in corrected_supported(dataclasses.replace(lp, trigger=nc.Petc(delta=0.1, temperature=0.1,
                                                                                     relaxed=True)))
    assert corrected_supported(dataclasses.replace(lp, trigger=nc.Periodic())) == ""


def test_check_loop_adds_the_corrected_estimator_and_finds_it_consistent():
    """check_loop(corrected=True) on the scalar loop's gain: the corrected estimator is
    checked beside the others, agrees with the central differences and is resolved; the
    refusals name why. (That check_loop leaves it out by default on a loop that supports it
    is asserted by tests/test_loop_tune.py::test_pair_objective_reaches_the_check_and_the_hybrid_tuner,
    whose check runs anyway.)"""
    from jaxnc.tune import Unconstrained, check_loop, gradient_check, tune_loop
    chk = check_loop(_scalar_loop(), {"controller.K": Unconstrained()}, seeds=2048, fd_step=0.05, corrected=True)
    assert "corrected" in chk.estimates
    assert chk.consistent["corrected"], chk.table()
    assert chk.resolved["corrected"].all()
    with pytest.raises(ValueError, match="corrected estimator needs corrected"):
        gradient_check(lambda t, k, T: t[0], np.zeros(1), montecarlo.seed_keys(0, 2), estimators=("corrected",))
    quiet = dataclasses.replace(_scalar_loop(), plant=dataclasses.replace(_scalar_loop().plant, v_std=[0.0]))
    with pytest.raises(ValueError, match="corrected.*no output has measurement noise"):
        tune_loop(quiet, {"controller.K": Unconstrained()}, estimator="corrected", progress=False)
    assert "corrected" not in check_loop(quiet, {"controller.K": Unconstrained()}, seeds=8, corrected=True).estimates


def test_tune_loop_with_the_corrected_estimator_improves_a_sluggish_gain():
    """tune_loop(estimator="corrected") from a sluggish gain: better on fresh seeds."""
    from jaxnc.tune import Unconstrained, tune_loop
    r = tune_loop(_scalar_loop(0.2), {"controller.K": Unconstrained()}, estimator="corrected", steps=20, batch=16,
                  learning_rate=0.1, eval_seeds=256, progress=False)
    assert r.estimator == "corrected"
    assert r.paired_diff[0] + r.paired_diff[1] < 0, r.summary()
    # one program for the 20 steps (a per-step recompilation would count at least 20; the
    # first call in a process adds about 11 small eager programs)
    assert r.stages["gradient"][2] < 20, r.stages


# ---------------------------------------------------------------------------- a 2-state servo


def _servo(kp):
    """A 2-state servo (position, damped velocity) with an EKF, PETC on the noisy position
    (noise 0.05, delta 0.01) and state feedback u = -(kp, 1.5) xhat from x0 = (1, 0), 40
    periods (benchmarks/bench_corrected.py's ``servo``)."""
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 0.95]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                   w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05 ** 2, mean0=[0.0, 0.0], cov0=np.eye(2))
    K = jnp.stack([jnp.asarray(kp, jnp.float32), jnp.float32(1.5)])[None, :]
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=1e-2), uplink=nc.Link(), estimator=ekf,
                   controller=nc.StateFeedback(K), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=40, T=0.1)


def _servo_check(n, seed):
    """(corrected, reference) per seed at kp = 3: the reference is the Richardson
    extrapolation of central differences at h = 0.1 and 0.05 on the same seeds (its O(h^2)
    bias removed)."""
    cost = lambda lp, k: nc.run(lp, k).cost_raw
    loop_of = lambda t: _servo(t[0])
    th = jnp.asarray([3.0], jnp.float32)

    def per(key):
        J = lambda kp: cost(_servo(kp), key)
        fd = lambda h: (J(3.0 + h) - J(3.0 - h)) / (2 * h)
        return corrected_grad(loop_of, cost, th, key)[1][0], (4 * fd(0.05) - fd(0.1)) / 3
    g, ref = (np.asarray(a, float) for a in jax.jit(jax.vmap(per))(montecarlo.seed_keys(seed, n)))
    return g, ref


def _paired_z(g, ref):
    d = g - ref
    return d.mean() / (d.std(ddof=1) / np.sqrt(d.size))


def test_servo_gain_corrected_agrees_with_central_differences():
    """On the servo's Kp, the corrected gradient agrees with the extrapolated central
    differences on the same 1024 seeds (paired |z| < 3) and resolves the gain."""
    g, ref = _servo_check(1024, 3)
    assert abs(_paired_z(g, ref)) < 3.0
    assert 1.96 * g.std(ddof=1) / np.sqrt(g.size) < abs(g.mean())


@pytest.mark.slow
def test_servo_gain_corrected_agrees_with_central_differences_many_seeds():
    """The same on 16384 seeds (resolution about 2 % of the gradient)."""
    g, ref = _servo_check(16384, 4)
    assert abs(_paired_z(g, ref)) < 3.0
