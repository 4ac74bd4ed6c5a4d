"""Library parts of seed 001 against closed forms and independent references: the robot as a
plant (its complementary-filter sensor state), DirtyDerivative, ArrivalHold, LeadFeedback."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from jaxnc import loop as nc
from jaxnc import references
from jaxnc.plants.balancing import Balancing, tilt_error_std

CTX = nc.Context(N=1, steps=10, T=1e-3, state_dim=4, input_dim=1, output_dim=2)


def _inbox(z, stamp, new):
    """An Inbox of one slot per row: payload z float[C, p], stamps int[C], delivered-now 0/1."""
    new = jnp.asarray(new, jnp.float32)
    return nc.Inbox(jnp.asarray(z, jnp.float32), jnp.asarray(stamp, jnp.int32), jnp.ones_like(new),
                    jnp.ones(new.shape, bool), new)


# ----------------------------------------------------------------------------- the robot as a plant


def _cf_reference_error(seed, K, p):
    """The complementary filter itself, on an IMU with the plant's noises and a moving tilt:
    th^_k = a (th^_{k-1} + Ts g_k) + (1 - a) t_k, the gyro integrated exactly."""
    rng = np.random.default_rng(seed)
    Ts, tau = float(p.Ts), float(p.tau_cf)
    a = tau / (tau + Ts)
    th = 0.05 * np.sin(2 * np.pi * 0.7 * Ts * np.arange(K + 1))
    g = np.diff(th) / Ts + float(p.sigma_gyro) * rng.standard_normal(K)
    acc = th[1:] + float(p.sigma_accel) * rng.standard_normal(K)
    est = scipy.signal.lfilter([1.0], [1.0, -a], a * Ts * g + (1 - a) * acc, zi=[a * th[0]])[0]
    return est - th[1:]


def test_sensor_state_is_the_complementary_filters_error():
    """The fifth state, driven by the plant's own process noise through ``dynamics`` and
    started by ``init``, has the variance of the complementary filter's error (computed from
    the filter itself) and i.i.d. increments e+ - a e of the drive's std. Tolerances: 4
    standard errors of each variance estimate (an AR(1)'s sample variance over K samples has
    a relative std of about sqrt(2 (1 + a^2) / ((1 - a^2) K)), over R runs / sqrt(R))."""
    p = Balancing()
    a = float(p.tau_cf) / (float(p.tau_cf) + float(p.Ts))
    std = np.asarray(p.w_std)
    drive = float(std[2])
    assert std[2] > 0 and np.all(np.asarray(p.v_std) == 0.0)
    R, K = 16, 20_000
    rel = 4 * math.sqrt(2 * (1 + a * a) / ((1 - a * a) * K * R))
    ref = np.concatenate([_cf_reference_error(s, K, p)[2500:] for s in range(R)])
    var_cf = np.var(ref)
    assert abs(var_cf / float(tilt_error_std(p)) ** 2 - 1) < rel

    def run(key):
        k0, kw = jax.random.split(key)
        x0 = p.init(k0).at[:4].set(0.0)          # the rigid body upright at rest: only e moves
        w = jax.random.normal(kw, (K, 3), jnp.float32) * (jnp.asarray([0.0, 0.0, 1.0]) * std)[None, :]
        step = lambda x, w_t: (p.dynamics(x, jnp.zeros(1), w_t),) * 2
        return jnp.concatenate([x0[4:], jax.lax.scan(step, x0, w)[1][:, 4]])

    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(7), i))(jnp.arange(R))
    e = np.asarray(jax.jit(jax.vmap(run))(keys), np.float64)
    assert abs(np.mean(e**2) / var_cf - 1) < 2 * rel
    d = e[:, 1:] - a * e[:, :-1]
    assert abs(np.std(d) / drive - 1) < 4 / math.sqrt(2 * d.size)
    assert np.rad2deg(np.std(np.diff(e, axis=1))) < 0.002      # ~1e-3 deg from sample to sample


def test_measure_quantises_the_encoder_and_adds_the_sensor_error():
    p = Balancing(tilt_sensor="white")
    q = float(p.encoder_step)
    x = jnp.asarray([2.6 * q, 0.1, 3.0, -1.0, 0.0], jnp.float32)
    z = np.asarray(p.measure(x, jnp.asarray([5.0, 0.002])))
    np.testing.assert_allclose(z, [3 * q, 0.102], rtol=1e-6)           # v[0] unused, v[1] added
    assert float(p.w_std[2]) == 0.0 and float(p.v_std[1]) == pytest.approx(p.sigma_theta)
    c = Balancing(theta0=0.1)
    z = np.asarray(c.measure(x.at[4].set(0.003), jnp.zeros(2)))
    np.testing.assert_allclose(z[1], 0.103, rtol=1e-6)
    x0 = np.asarray(jax.vmap(c.init)(jax.random.split(jax.random.PRNGKey(0), 4000)))
    np.testing.assert_array_equal(x0[:, :4], np.tile([0.0, 0.1, 0.0, 0.0], (4000, 1)).astype(np.float32))
    sd = float(tilt_error_std(c))                                       # e_0 stationary: 4 SE of a std
    assert abs(np.std(x0[:, 4]) / sd - 1) < 4 / math.sqrt(2 * 4000)
    assert c.state_vector(x).shape == (4,)
    with pytest.raises(ValueError, match="Balancing.theta0"):
        Balancing(theta0=2.0)


# ----------------------------------------------------------------------------- DirtyDerivative


def _observer_run(est, z, stamps, new):
    """The observer's estimates over a sequence of one-slot inboxes (jit)."""
    def step(s, inp):
        zk, sk, nk, k = inp
        return est.correct(s, _inbox(zk[None], sk[None], nk[None]), k)
    ks = jnp.arange(len(new), dtype=jnp.int32)
    return np.asarray(jax.jit(lambda: jax.lax.scan(step, est.init(CTX), (jnp.asarray(z, jnp.float32),
                                                                     jnp.asarray(stamps), jnp.asarray(new), ks))[1])())


def test_simple_derivative_is_the_backward_difference_of_the_held_measurement():
    """Hand computation: nothing before the first arrival, the first arrival held with rate 0,
    then (zbar_k - zbar_{k-1}) / T (0 where nothing arrives; an older packet arriving after a
    newer one is held all the same: no time stamps)."""
    rng = np.random.default_rng(0)
    z = rng.standard_normal((8, 2))
    new = np.array([0, 1, 1, 0, 0, 1, 1, 0], np.float32)
    stamps = np.array([0, 0, 2, 0, 0, 5, 3, 0])                       # k = 6 delivers stamp 3 after 5
    out = _observer_run(nc.DirtyDerivative(), z, stamps, new)
    held = np.zeros((8, 2))
    for k in range(8):
        held[k] = z[k] if new[k] else (held[k - 1] if k else 0.0)
    rate = np.zeros((8, 2))
    for k in range(2, 8):
        rate[k] = (held[k] - held[k - 1]) / 1e-3
    np.testing.assert_allclose(out[:, :2], held, rtol=1e-6)
    np.testing.assert_allclose(out[:, 2:], rate, rtol=1e-5, atol=1e-3)
    assert np.all(out[[0, 1, 3, 4, 7], 2:] == 0.0) and np.all(out[[2, 5, 6], 2:] != 0.0)


def test_filtered_derivative_is_a_first_order_filter_of_the_difference():
    """Arrivals every step: r is scipy's lfilter of the difference quotient with a = exp(-T/tau)."""
    tau = 0.004
    z = np.cumsum(np.random.default_rng(1).standard_normal((40, 2)), axis=0)
    out = _observer_run(nc.DirtyDerivative(tau), z, np.arange(40), np.ones(40, np.float32))
    a = math.exp(-1e-3 / tau)
    dq = np.vstack([np.zeros((1, 2)), np.diff(z, axis=0) / 1e-3])
    ref = scipy.signal.lfilter([1 - a], [1, -a], dq, axis=0)
    np.testing.assert_allclose(out[:, 2:], ref, rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="DirtyDerivative.tau_d"):
        nc.DirtyDerivative(-1.0)


def test_filtered_derivative_per_output_is_the_zoh_of_s_over_tau_s_plus_one_scaled():
    """tau_d per output (float[p]): each output's rate is scipy's cont2discrete of
    s / (tau s + 1) by ZOH, (1/tau)(1 - z^-1)/(1 - a z^-1), scaled by (1 - a) tau / T (the
    docstring's unit gain on the difference quotient), applied to the held measurement; a
    tau_d of another length than the outputs is refused when the Loop is built
    (tests/test_bad_inputs.py)."""
    taus, T = np.array([0.004, 0.02]), 1e-3
    z = np.cumsum(np.random.default_rng(2).standard_normal((40, 2)), axis=0)
    out = _observer_run(nc.DirtyDerivative(list(taus)), z, np.arange(40), np.ones(40, np.float32))
    for i, tau in enumerate(taus):
        num, den, _ = scipy.signal.cont2discrete(([1.0, 0.0], [tau, 1.0]), T, method="zoh")
        a = math.exp(-T / tau)
        assert den[1] == pytest.approx(-a, rel=1e-12)
        b = np.ravel(num) * (1 - a) * tau / T          # c (1 - z^-1): c on the difference z_k - z_{k-1}
        assert b[-1] == pytest.approx(-b[-2], rel=1e-12)
        dz = np.concatenate([[0.0], np.diff(z[:, i])])   # the first arrival: nothing to difference
        ref = scipy.signal.lfilter([b[-2]], den, dz)
        np.testing.assert_allclose(out[:, 2 + i], ref, rtol=1e-4, atol=1e-3)


# ----------------------------------------------------------------------------- ArrivalHold


def test_arrival_hold_applies_the_last_arrival_whatever_its_stamp():
    act = nc.ArrivalHold()
    ctx = CTX

    def run():
        s = act.init(ctx)
        outs = []
        for u, stamp, new in ((9.0, 0, 0.0), (1.0, 1, 1.0), (9.0, 0, 0.0), (3.0, 3, 1.0), (2.0, 2, 1.0), (9.0, 0, 0.0)):
            s = act.receive(s, _inbox(jnp.full((1, 1, 1), u), [stamp], [new]))
            s, out = act.output(s, 0)
            outs.append(out[0])
        return jnp.stack(outs)

    np.testing.assert_array_equal(np.asarray(jax.jit(run)()), [0.0, 1.0, 1.0, 3.0, 2.0, 2.0])


# ----------------------------------------------------------------------------- LeadFeedback


def _lti():
    return nc.LTI(A=[[1.0, 0.01], [0.2, 0.98]], B=[[0.0], [0.05]], C=[[1.0, 0.0]], T=1e-3)


def test_lead_feedback_predicts_along_its_plan_and_stamps_ahead():
    """lead = 2: u_{k+2} = clip(-K (A^2 xhat + A B u_k + B u_{k+1} - r)), stamped k + 2, the
    plan shifted; lead = 0 is StateFeedback."""
    m = _lti()
    A, B = np.asarray(m.A, np.float64), np.asarray(m.B, np.float64)
    K = np.array([[3.0, 1.5]])
    ref = references.Step(amplitude=[0.5, 0.0], time=0.0)
    c = nc.LeadFeedback(K, m, ref, u_max=100.0, lead=2)
    ctx = CTX._replace(state_dim=2, output_dim=1)
    plan = jnp.asarray([[0.3], [-0.7]], jnp.float32)
    xhat = jnp.asarray([0.2, -0.1], jnp.float32)
    plan2, pkt, send = jax.jit(c.step, static_argnums=4)(plan, xhat, 1.0, jnp.int32(5), ctx)
    x2 = A @ A @ np.asarray(xhat) + A @ B[:, 0] * 0.3 + B[:, 0] * -0.7
    u = -(K @ (x2 - [0.5, 0.0]))
    np.testing.assert_allclose(np.asarray(pkt.data)[0], u, rtol=1e-5)
    assert int(pkt.stamp) == 7 and float(send) == 1.0
    np.testing.assert_allclose(np.asarray(plan2)[:, 0], [-0.7, u[0]], rtol=1e-5)
    sat = nc.LeadFeedback(K * 1e4, m, None, u_max=2.0, lead=0)
    _, pkt, _ = sat.step(sat.init(ctx), xhat, 1.0, jnp.int32(3), ctx)
    assert int(pkt.stamp) == 3 and float(pkt.data[0, 0]) == pytest.approx(-2.0)
    law = nc.StateFeedback(K, u_min=-100.0, u_max=100.0)
    zero = nc.LeadFeedback(K, m, None, u_max=100.0, lead=0)
    np.testing.assert_allclose(np.asarray(zero.step((), xhat, 1.0, jnp.int32(0), ctx)[1].data),
                               np.asarray(law.step((), xhat, 1.0, jnp.int32(0), ctx)[1].data), rtol=1e-6)


@pytest.mark.parametrize("actuator,jitter", [("hold_last", False), ("zero_order", False), ("packet", False),
                                             ("hold_last", True)])
def test_lead_feedback_in_a_loop_applies_each_command_at_its_stamp(actuator, jitter):
    """A scalar loop x+ = 1.1 x + u + w, LeadFeedback(lead=2) over perfect links into an
    actuator of lead + 1 packets: the plant gets the command stamped t at t (zero before),
    as a float64 loop of the docstring's equations (with one-packet actuators it got 0 throughout).
    The same over a downlink whose delays vary from 0 to 2 fast periods (every packet still
    arrives by its stamp) with ``order="all"``: with the default ``"newest"``, two packets
    arriving together lost the older, still-due one (the plant held the previous action), a
    loop now refused (tests/test_bad_inputs.py)."""
    a, K, lead, steps = 1.1, 0.5, 2, 30
    plant = nc.LTI([[a]], [[1.0]], [[1.0]], x0=[1.0], w_std=[0.05], v_std=[0.0], T=0.1)
    act = {"hold_last": nc.HoldLast(capacity=3), "zero_order": nc.ZeroOrder(capacity=3),
           "packet": nc.PacketActuator(capacity=3)}[actuator]
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.LeadFeedback([[K]], plant, lead=lead), actuator=act, T=0.1, steps=steps, record=True,
                   downlink=nc.Link(delay=nc.PmfDelay([0.4, 0.3, 0.3]), order="all") if jitter else nc.Link())
    key = jax.random.PRNGKey(1)
    traj = jax.jit(nc.simulate)(loop, key)
    w = np.asarray(nc.draw(loop, key).w, np.float64).reshape(steps, -1)[:, 0]
    x, plan, due, us = 1.0, [0.0] * lead, {}, []
    for k in range(steps):
        xp = x
        for u_j in plan:
            xp = a * xp + u_j
        due[k + lead] = -K * xp
        plan = plan[1:] + [due[k + lead]]
        us.append(due.get(k, 0.0))
        x = a * x + us[-1] + w[k]
    np.testing.assert_allclose(np.asarray(traj.u)[:, 0], us, atol=1e-6)
    assert np.count_nonzero(us) == steps - lead


def test_lead_feedback_validates():
    m = _lti()
    with pytest.raises(ValueError, match="LeadFeedback.lead"):
        nc.LeadFeedback([[1.0, 0.0]], m, lead=-1)
    with pytest.raises(ValueError, match="LeadFeedback.u_max"):
        nc.LeadFeedback([[1.0, 0.0]], m, u_max=0.0)
    with pytest.raises(ValueError, match="LeadFeedback.model"):
        nc.LeadFeedback([[1.0, 0.0]], "A")
    with pytest.raises(ValueError, match="N must be 1"):
        nc.LeadFeedback([[1.0, 0.0]], m).init(CTX._replace(N=2))


# ----------------------------------------------------------------------------- hold-aware LQ gain


def _hold_cost(L, A, B, W, U, theta):
    """The expected cost matrix P of u = L x under the hold (seed 001 eq. 4), computed without
    the Riccati recursion: the jump linear system of z = [x; ubar_{k-1}], arrival (prob theta)
    ubar = L x, loss ubar = ubar_{k-1}, stage cost x'Wx + ubar'U ubar, solved as
    P = sum_i p_i (Q_i + F_i' P F_i) (a linear system in vec P); None if not mean-square stable."""
    n, m = B.shape
    Z = np.zeros
    F1, F0 = np.block([[A + B @ L, Z((n, m))], [L, Z((m, m))]]), np.block([[A, B], [Z((m, n)), np.eye(m)]])
    Q1 = np.block([[W + L.T @ U @ L, Z((n, m))], [Z((m, n)), Z((m, m))]])
    Q0 = np.block([[W, Z((n, m))], [Z((m, n)), U]])
    ops = theta * np.kron(F1.T, F1.T) + (1 - theta) * np.kron(F0.T, F0.T)
    if np.max(np.abs(np.linalg.eigvals(ops))) >= 1:
        return None
    N = n + m
    return np.linalg.solve(np.eye(N * N) - ops, (theta * Q1 + (1 - theta) * Q0).reshape(-1)).reshape(N, N)


@pytest.mark.parametrize("n, m, theta, scale", [(2, 1, 0.9, 0.9), (3, 1, 0.7, 1.15), (3, 2, 0.8, 0.9), (4, 2, 0.95, 1.1)])
def test_hold_aware_gain_minimises_the_expected_cost_of_the_hold_system(n, m, theta, scale):
    """hold_lq_gain's L is the best u = L x for the hold system, checked without its Riccati
    equation: the expected cost of the jump linear system (_hold_cost) has S11 as its x-block,
    and every perturbation of L (each entry, and random directions, +-1e-3) raises its trace."""
    from jaxnc.controllers.hold_lq import hold_lq_gain
    rng = np.random.default_rng(n * 10 + m)
    A = rng.standard_normal((n, n))
    A *= scale / np.max(np.abs(np.linalg.eigvals(A)))
    B, W, U = rng.standard_normal((n, m)), np.eye(n), 0.5 * np.eye(m)
    L, S11 = hold_lq_gain(A, B, W, U, theta)
    P = _hold_cost(L, A, B, W, U, theta)
    np.testing.assert_allclose(P[:n, :n], S11, rtol=1e-7, atol=1e-9)
    J = np.trace(P)
    dirs = [np.eye(m * n)[i].reshape(m, n) for i in range(m * n)] + list(rng.standard_normal((8, m, n)))
    for d in dirs:
        for s in (1e-3, -1e-3):
            Pd = _hold_cost(L + s * d, A, B, W, U, theta)
            assert Pd is None or np.trace(Pd) > J
