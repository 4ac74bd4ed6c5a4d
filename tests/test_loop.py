"""The one runner (jaxnc.loop) against independent references: closed forms, numpy loops."""
import dataclasses
import typing

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxnc import loop as nc
from jaxnc import montecarlo, wifi
from jaxnc.loop.actuators import install
from jaxnc.loop.links import LinkDraws

A2 = np.array([[1.0, 0.1], [0.0, 0.95]])
B2 = np.array([[0.005], [0.1]])
C2 = np.array([[1.0, 0.0]])
K2 = np.array([[3.0, 1.5]])


_COST = nc.Quadratic(Q=[1.0, 1.0], R=[0.1])


def _lti_loop(*, N=1, steps=40, uplink=None, buffer=0, K=K2, A=A2, trigger=None, cost=_COST, **kw):
    plant = nc.LTI(A=A, B=B2, C=C2, x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05**2, mean0=[0.0, 0.0], cov0=np.eye(2),
                 buffer=buffer)
    return nc.Loop(plant=plant, trigger=trigger or nc.Periodic(), uplink=uplink or nc.Link(), estimator=ekf,
                   controller=nc.StateFeedback(K), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=cost, N=N, steps=steps, T=0.1, **kw)


def _kf_lqr_reference(loop, d):
    """float64 numpy: KF at every slow instant, u held over the N fast periods."""
    p = loop.plant
    A, B, C = (np.asarray(a, float) for a in (p.A, p.B, p.C))
    Q, R = np.asarray(loop.estimator.Q, float), np.asarray(loop.estimator.R, float)
    K = np.asarray(loop.controller.K, float)
    x = np.asarray(p.x0, float)
    m, P = np.zeros(2), np.eye(2)
    w, v = np.asarray(d.w, float), np.asarray(d.v, float)
    xs, xhats = [], []
    for k in range(loop.steps // loop.N):
        z = C @ x + v[k]
        S = C @ P @ C.T + R
        G = P @ C.T @ np.linalg.inv(S)
        m = m + G @ (z - C @ m)
        P = (np.eye(2) - G @ C) @ P @ (np.eye(2) - G @ C).T + G @ R @ G.T
        xhats.append(m.copy())
        u = -K @ m
        for j in range(loop.N):
            xs.append(x.copy())
            x = A @ x + B @ u + w[k, j]
            m = A @ m + B @ u
            P = A @ P @ A.T + Q
    return np.array(xs), np.array(xhats)


@pytest.mark.parametrize("N", [1, 3])
def test_kf_lqr_loop_matches_a_numpy_reference(N):
    loop = _lti_loop(N=N, steps=12 * N)
    key = jax.random.PRNGKey(3)
    tr = jax.jit(nc.simulate)(loop, key)
    xs, xhats = _kf_lqr_reference(loop, nc.draw(loop, key))
    np.testing.assert_allclose(np.asarray(tr.x), xs, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.asarray(tr.xhat), xhats, rtol=1e-4, atol=1e-5)
    assert float(tr.tx_sc) == 12 and float(tr.tx_ca) == 12
    assert tr.x.shape == (12 * N, 2) and tr.u.shape == (12 * N, 1) and tr.z.shape == (12, 1)


def _on_time_filter(loop, d, delays, lost):
    """float64: at each k, the KF over every measurement that has arrived by k and arrived
    while its instant was inside the buffer window (the EKF's contract), from scratch."""
    p = loop.plant
    A, B, C = (np.asarray(a, float) for a in (p.A, p.B, p.C))
    Q, R = np.asarray(loop.estimator.Q, float), np.asarray(loop.estimator.R, float)
    D = loop.estimator.buffer
    x = np.asarray(p.x0, float)
    S = loop.steps
    zs = []
    for k in range(S):                      # open loop (K = 0): u = 0, the truth is independent
        zs.append(C @ x + np.asarray(d.v[k], float))
        x = A @ x + np.asarray(d.w[k, 0], float)
    out = []
    for k in range(S):
        m, P = np.zeros(2), np.eye(2)
        for s in range(k + 1):
            usable = (not lost[s]) and s + delays[s] <= k and delays[s] <= D
            if usable:
                G = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
                m = m + G @ (zs[s] - C @ m)
                P = (np.eye(2) - G @ C) @ P @ (np.eye(2) - G @ C).T + G @ R @ G.T
            if s < k:
                m, P = A @ m, A @ P @ A.T + Q
        out.append(m)
    return np.array(out)


def test_time_stamped_ekf_equals_the_on_time_filter_with_the_arrived_measurements():
    pmf = [0.4, 0.2, 0.2, 0.1, 0.1]          # 0..4 fast periods (N = 1)
    up = nc.Link(nc.Bernoulli(0.3), nc.PmfDelay(pmf), order="all", capacity=6)
    loop = _lti_loop(steps=30, uplink=up, buffer=3, K=np.zeros((1, 2)))
    key = jax.random.PRNGKey(11)
    d = nc.draw(loop, key)
    tr = jax.jit(nc.simulate)(loop, key)
    delays = np.asarray(d.uplink.delay)
    lost = delays < 0
    assert lost.any() and (delays > 3).any() and ((delays > 0) & (delays <= 3)).any()   # all cases occur
    ref = _on_time_filter(loop, d, np.where(lost, 0, delays), lost)
    np.testing.assert_allclose(np.asarray(tr.xhat), ref, rtol=2e-4, atol=2e-5)


def test_bernoulli_link_loss_rate_and_common_random_numbers():
    n, p = 20_000, 0.3
    d = nc.draw_link(nc.Link(nc.Bernoulli(p)), jax.random.PRNGKey(0), n, 0.1).delay
    rate = float(np.mean(np.asarray(d) < 0))
    assert abs(rate - p) < 4 * np.sqrt(p * (1 - p) / n)
    d2 = nc.draw_link(nc.Link(nc.Bernoulli(0.1)), jax.random.PRNGKey(0), n, 0.1).delay
    assert np.all(np.asarray(d)[np.asarray(d2) < 0] < 0)      # losses at 0.1 are a subset of those at 0.3


def test_delays_quantised_up_and_late_packets_discarded():
    T = 0.01
    link = nc.Link(delay=nc.ShiftedExponential(eta=0.005, phi=0.02), tau_max=0.03)
    key = jax.random.PRNGKey(1)
    d = np.asarray(nc.draw_link(link, key, 5000, T).delay)
    tau = 0.005 + 0.02 * np.asarray(jax.random.exponential(jax.random.split(key)[1], (5000,)))
    expect = np.where(tau > 0.03, -1, np.ceil(tau / T - 1e-5))
    np.testing.assert_array_equal(d, expect)
    first = nc.draw_link(nc.Link(nc.Bernoulli(0.9), reliable_first=True), key, 50, T).delay
    assert int(first[0]) == 0 and np.mean(np.asarray(first[1:]) < 0) > 0.7


def test_reliable_first_holds_when_the_delay_model_loses_the_first_packet():
    """reliable_first: the first packet is never lost, also where the delay model marks it lost
    itself (a trace's -1, the Wi-Fi channel's loss); it used to keep the model's -1 (lost)."""
    key = jax.random.PRNGKey(0)
    d = nc.draw_link(nc.Link(delay=nc.TraceDelay([-1, 3, -1]), reliable_first=True), key, 3, 0.1).delay
    assert np.asarray(d).tolist() == [3, 3, -1]           # the trace's shortest delay, 3 periods
    blackout = wifi.WifiChannel(p_gb=1.0, p_bg=1e-6, loss_good=1.0, loss_bad=1.0)
    d = nc.draw_link(nc.Link(delay=nc.WifiModel(blackout), reliable_first=True), key, 4, 0.1).delay
    assert np.asarray(d).tolist() == [1, -1, -1, -1]        # the default law's only delay, 1 step
    d = nc.draw_link(nc.Link(delay=nc.TraceDelay([5, 1]), tau_max=0.2, reliable_first=True), key, 2, 0.1).delay
    assert np.asarray(d).tolist() == [5, 1]                # late, delivered all the same


def test_gilbert_elliott_stationary_loss():
    ge = nc.GilbertElliott(p_gb=0.05, p_bg=0.2, loss_good=0.01, loss_bad=0.8)
    lost = np.asarray(ge.sample(jax.random.PRNGKey(2), 200_000))
    assert abs(lost.mean() - ge.stationary_loss()) < 0.01
    # bursty: a loss is more likely right after a loss than on average
    assert np.mean(lost[1:][lost[:-1]]) > 2 * lost.mean()


def test_newest_order_drops_out_of_order_packets_all_delivers_them():
    for order, expect in (("newest", [1, 0]), ("all", [1, 1])):
        link = nc.Link(order=order, capacity=3)
        st = link.init(jnp.zeros(1))
        st = link.send(st, jnp.ones(1), 0, 0, 1.0, jnp.int32(5), 0)     # stamp 0 arrives at 5
        st = link.send(st, 2 * jnp.ones(1), 1, 1, 1.0, jnp.int32(1), 1)  # stamp 1 arrives at 2
        got = []
        for t in (2, 5):
            box, st = link.inbox(st, t)
            got.append(int(np.sum(np.asarray(box.new))))
        assert got == expect, order


def test_packet_actuator_indexes_by_stamp_holds_and_waits_for_future_packets():
    ctx = nc.Context(N=1, steps=10, T=1.0, state_dim=1, input_dim=1, output_dim=1)
    for mode, after in (("hold", 3.0), ("zero", 0.0)):
        act = nc.PacketActuator(horizon=3, capacity=2, on_exhausted=mode)
        st = act.init(ctx)
        st = install(st, jnp.array([[1.0], [2.0], [3.0]]), jnp.int32(2), 1.0)
        st = install(st, jnp.array([[9.0], [9.0], [9.0]]), jnp.int32(8), 1.0)   # for later
        us = []
        for t in range(10):
            st, u = act.output(st, t)
            us.append(float(u[0]))
        assert us == [0, 0, 1, 2, 3, after, after, after, 9, 9], mode


def test_petc_first_sample_threshold_and_max_silence():
    trig = nc.Petc(delta=0.5, max_silence=3)
    st = trig.init(nc.Context(N=1, steps=6, T=1.0, state_dim=1, input_dim=1, output_dim=1, signal_dim=1))
    sends = []
    for k, z in enumerate([0.0, 0.1, 0.2, 0.3, 2.0, 2.1]):
        st, b = trig.step(st, jnp.array([z]), k)
        sends.append(int(b))
    assert sends == [1, 0, 0, 1, 1, 0]          # first; silence 3 forces k = 3; |2 - 0.3|^2 > 0.5


def test_a_seed_is_the_same_alone_and_in_a_batch():
    loop = _lti_loop(uplink=nc.Link(nc.Bernoulli(0.3)))
    keys = montecarlo.seed_keys(0, 9)
    full = montecarlo.run_batched(nc.run_seed, keys, args=(loop,), chunk_size=4, progress=False)
    part = montecarlo.run_batched(nc.run_seed, keys[5:7], args=(loop,), chunk_size=4, progress=False)
    np.testing.assert_array_equal(full.cost[5:7], part.cost)


def test_divergence_is_data():
    loop = _lti_loop(A=np.array([[1.5, 0.0], [0.0, 1.2]]), K=np.zeros((1, 2)), steps=200,
                     monitor=nc.Monitor(bounds=[1e3, 1e3]))
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
    m = nc.evaluate(loop, tr)
    assert bool(tr.failed) and bool(m.unstable) and np.isinf(float(m.cost)) and np.isfinite(float(m.cost_raw))
    assert np.all(np.isfinite(np.asarray(tr.x))) and int(tr.fail_step) < 200


def test_configuration_errors_name_the_parameter():
    slow = nc.Link(delay=nc.PmfDelay([0.5, 0.0, 0.0, 0.5]), capacity=2)
    with pytest.raises(ValueError, match="Loop.uplink.capacity must be >= 4"):
        _lti_loop(uplink=slow)
    with pytest.raises(ValueError, match="multiple of N=2"):
        _lti_loop(N=2, steps=5)
    with pytest.raises(ValueError, match="actuator.horizon"):
        dataclasses.replace(_lti_loop(), actuator=nc.PacketActuator(horizon=3))
    plant = nc.LTI(A=A2, B=B2, C=C2)
    with pytest.raises(ValueError, match="EKF.Q must be 2x2"):
        nc.EKF(plant, Q=np.eye(3), R=np.eye(1), mean0=[0, 0], cov0=np.eye(2))
    with pytest.raises(ValueError, match="EKF.R must be positive"):
        nc.EKF(plant, Q=np.eye(2), R=-np.eye(1), mean0=[0, 0], cov0=np.eye(2))
    with pytest.raises(ValueError, match="PmfDelay.pmf must sum to 1"):
        nc.PmfDelay([0.5, 0.2])
    with pytest.raises(ValueError, match=r"Bernoulli.p must be in \[0, 1\)"):
        nc.Bernoulli(1.0)
    with pytest.raises(ValueError, match="Link.order"):
        nc.Link(order="fifo")


def test_lti_discretisation_matches_python_control_and_rk4():
    Ac, Bc, Cc = np.array([[0.0, 1.0], [-2.0, -0.5]]), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])
    T = 0.05
    ref = control.c2d(control.ss(Ac, Bc, Cc, 0), T, "zoh")
    lti = nc.LTI.from_continuous(Ac, Bc, Cc, T)
    np.testing.assert_allclose(lti.A, ref.A, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(lti.B, ref.B, rtol=1e-6, atol=1e-7)
    tf = nc.LTI.from_control(control.tf([1.0], [1.0, 0.5, 2.0]), T, realization="observable")
    assert (tf.state_dim, tf.input_dim, tf.output_dim) == (2, 1, 1)
    np.testing.assert_allclose(np.linalg.eigvals(tf.A), np.linalg.eigvals(ref.A), rtol=1e-5)
    ct = nc.Continuous(x0=[0.0, 0.0], w_std=0.0, v_std=0.0, f=_lin_f, h=_lin_h, input_dim=1, noise_dim=1,
                       output_dim=1, T=T, substeps=8)
    x, u = jnp.array([1.0, -0.5]), jnp.array([0.3])
    np.testing.assert_allclose(ct.dynamics(x, u, jnp.zeros(1)), lti.A @ x + lti.B @ u, rtol=1e-5, atol=1e-6)
    assert np.allclose(scipy.linalg.expm(Ac * T), ref.A, atol=1e-9)


def _lin_f(x, u, w):
    return jnp.stack([x[1], -2.0 * x[0] - 0.5 * x[1] + u[0] + w[0]])


def _lin_h(x, v):
    return x[:1] + v


def test_controller_trigger_gates_the_packets():
    key = jax.random.PRNGKey(0)
    never = jax.jit(nc.simulate)(_lti_loop(controller_trigger=nc.Petc(delta=1e9)), key)
    assert float(never.tx_ca) == 1.0                      # only the first (forced) packet
    u = np.asarray(never.u)
    assert np.all(u == u[0])                              # the actuator holds it
    always = jax.jit(nc.simulate)(_lti_loop(controller_trigger=nc.Petc(delta=0.0)), key)
    assert float(always.tx_ca) == 40.0


def test_tau_max_of_whole_periods_keeps_a_delay_of_exactly_that_many_periods():
    T, N = 0.001, 10
    link = nc.Link(delay=nc.PmfDelay([0.0] * 10 + [1.0]), tau_max=N * T)       # always 10 periods
    assert np.all(np.asarray(nc.draw_link(link, jax.random.PRNGKey(0), 50, T).delay) == 10)
    link = nc.Link(delay=nc.PmfDelay([0.0] * 11 + [1.0]), tau_max=N * T)       # always 11: late
    assert np.all(np.asarray(nc.draw_link(link, jax.random.PRNGKey(0), 50, T).delay) == -1)


def test_selective_recording_keeps_the_values_and_drops_the_rest():
    key = jax.random.PRNGKey(4)
    full = jax.jit(nc.simulate)(_lti_loop(), key)
    part = jax.jit(nc.simulate)(_lti_loop(record=("xhat", "sent_sc"), cost=None), key)
    np.testing.assert_array_equal(np.asarray(part.xhat), np.asarray(full.xhat))
    np.testing.assert_array_equal(np.asarray(part.sent_sc), np.asarray(full.sent_sc))
    assert part.x.size == 0 and part.u.size == 0 and part.z.size == 0
    np.testing.assert_array_equal(np.asarray(part.final_plant), np.asarray(full.final_plant))
    assert np.isnan(float(nc.evaluate(_lti_loop(record=("xhat",), cost=None), part).cost_raw))   # no cost
    with pytest.raises(ValueError, match="Loop.cost needs the signals x and u recorded"):
        _lti_loop(record=("xhat",))
    with pytest.raises(ValueError, match="Loop.record must be True, False, a tuple of names"):
        _lti_loop(record=("states",))


def test_a_link_whose_minimum_delay_outlives_its_ring_is_refused():
    """ShiftedExponential(eta=0.5 s) at T = 0.1 s: every packet is 5 fast periods late; a
    ring of 2 reuses each slot before its packet arrives (nothing would ever be delivered)."""
    late = nc.Link(delay=nc.ShiftedExponential(eta=0.5, phi=0.0), capacity=2)
    with pytest.raises(ValueError, match="Loop.uplink.capacity must be >= 6: every packet is delayed at least 5"):
        _lti_loop(uplink=late)
    _lti_loop(uplink=nc.Link(delay=nc.ShiftedExponential(eta=0.5, phi=0.0), capacity=6), buffer=5)   # fits


def test_a_user_delay_model_declares_its_bounds_and_the_ring_is_checked():
    @nc.pytree_dataclass
    class Fixed(nc.AbstractDelay):
        d: int = nc.static_field(3)
        in_steps = True

        def bounds(self, T):
            return self.d, self.d

        def sample(self, key, n, T):
            return jnp.full((n,), self.d, jnp.int32), jnp.full((n,), self.d * T, jnp.float32)

    with pytest.raises(ValueError, match="Loop.uplink.capacity must be >= 4"):
        _lti_loop(uplink=nc.Link(delay=Fixed(3), capacity=2))
    loop = _lti_loop(uplink=nc.Link(delay=Fixed(3), capacity=4), buffer=3)     # a window that reaches them
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
    assert float(jnp.sum(tr.recv_sc)) == loop.steps - 3          # every packet arrives 3 instants late

    class NotAModel:
        def sample(self, key, n, T):
            return None
    with pytest.raises(ValueError, match="Link.delay must be a delay model"):
        nc.Link(delay=NotAModel())


def _twice_position(plant, x):
    return x[0] * 2.0


def _post_mean(ekf, state):
    return state.post.mean


def _stamp_of_actuator(act, state, t):
    return state.stamp[0]


def test_a_record_spec_keeps_functions_of_the_roles_states_in_parts():
    """``Record`` (diffrax's SaveAt): a function of a role's state is kept in
    ``Trajectory.parts[role]``: the plant's after every fast step, the estimator's once a
    slow period (after its prediction), the actuator's after every output."""
    base = _lti_loop(N=2, steps=20)
    key = jax.random.PRNGKey(1)
    spec = nc.Record(signals=("x", "xhat"), plant=_twice_position, estimator=_post_mean, actuator=_stamp_of_actuator)
    tr = jax.jit(nc.simulate)(dataclasses.replace(base, record=spec, cost=None), key)
    assert set(tr.parts) == {"plant", "estimator", "actuator"}
    assert tr.parts["plant"].shape == (20,) and tr.parts["estimator"].shape == (10, 2)
    np.testing.assert_allclose(np.asarray(tr.parts["plant"][:-1]), 2.0 * np.asarray(tr.x[1:, 0]), rtol=1e-6)
    # the packet of slow instant k is stamped kN and applied from then (no delay)
    np.testing.assert_array_equal(np.asarray(tr.parts["actuator"]), np.repeat(np.arange(10) * 2, 2))
    assert tr.u.size == 0 and tr.z.size == 0                    # not among the signals
    none = jax.jit(nc.simulate)(dataclasses.replace(base, record=("x",), cost=None), key)
    assert none.parts == {}
    with pytest.raises(ValueError, match="Record.signals must be a tuple of names"):
        nc.Record(signals=("x", "plant"))
    with pytest.raises(ValueError, match="Record.plant"):
        nc.Record(plant="x")


def test_ekf_finds_its_measurements_with_N_above_1_whatever_the_ring():
    """The link keeps the packet of slow instant k in slot k mod C (stamp kN): with N = 2 and
    no delay, the EKF's estimates are the same for rings of 1, 3 and 4 packets (it once
    looked in slot kN mod C and missed measurements for C > 1)."""
    key = jax.random.PRNGKey(5)
    xs = [np.asarray(jax.jit(nc.simulate)(_lti_loop(N=2, steps=40, buffer=0, uplink=nc.Link(capacity=c)), key).xhat)
          for c in (1, 3, 4)]
    np.testing.assert_allclose(xs[1], xs[0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(xs[2], xs[0], rtol=1e-6, atol=1e-7)


class _SettledState(typing.NamedTuple):
    inside: jax.Array     # int32: consecutive fast periods within the band


@nc.pytree_dataclass
class _Settled(nc.AbstractMonitor):
    """Complete once |x_0| < band for ``hold`` consecutive fast periods; failed beyond 5."""

    band: float = 0.05
    hold: int = nc.static_field(3)
    freeze = False

    def init(self, ctx):
        return _SettledState(jnp.zeros((), jnp.int32))

    def step(self, state, x, u, t):
        inside = jnp.where(jnp.abs(x[0]) < self.band, state.inside + 1, 0)
        return _SettledState(inside), jnp.abs(x[0]) > 5.0, inside >= self.hold


def _inside(monitor, state):
    return state.inside


def test_a_monitor_with_state_reports_completion_and_is_recorded():
    """A user monitor (AbstractMonitor): completion at the first fast instant after which
    x_0 has stayed in the band for ``hold`` periods, read back from the recorded x."""
    loop = _lti_loop(N=2, steps=60, monitor=_Settled(), cost=None,
                     record=nc.Record(signals=("x",), monitor=_inside))
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(2))
    x0 = np.asarray(tr.x[:, 0])
    xs_after = np.concatenate([x0[1:], [np.asarray(tr.final_plant)[0]]])   # the state after step t
    inside = np.zeros(60, int)
    for t in range(60):
        inside[t] = (inside[t - 1] + 1 if t else 1) if abs(xs_after[t]) < 0.05 else 0
    np.testing.assert_array_equal(np.asarray(tr.parts["monitor"]), inside)
    first = np.flatnonzero(inside >= 3)
    assert bool(tr.done) == (first.size > 0) and first.size > 0
    assert int(tr.done_step) == first[0] + 1
    assert not bool(tr.failed) and int(tr.fail_step) == 60


def test_a_random_initial_state_is_drawn_from_x0_std_per_seed():
    """LTI(x0_std=...): x_0 = x0 + x0_std * N(0, I) from the run's key; the first recorded state
    has that mean and std over 4000 seeds (4 standard errors), and x0_std=None is x0 exactly."""
    plant = nc.LTI(A=A2, B=B2, C=C2, x0=[1.0, 0.0], x0_std=[0.5, 0.0], T=0.1)
    x0 = np.asarray(jax.jit(jax.vmap(plant.init))(jax.random.split(jax.random.PRNGKey(1), 4000)))
    n = x0.shape[0]
    assert abs(x0[:, 0].mean() - 1.0) < 4 * 0.5 / np.sqrt(n)
    assert abs(x0[:, 0].std() / 0.5 - 1.0) < 4 / np.sqrt(2 * n)
    np.testing.assert_array_equal(x0[:, 1], 0.0)
    loop = dataclasses.replace(_lti_loop(), plant=plant)
    tr = montecarlo.run_batched(lambda k: nc.simulate(loop, k).x[0], jax.random.split(jax.random.PRNGKey(2), 3))
    assert len(set(np.asarray(tr)[:, 0].tolist())) == 3           # each seed its own start
    fixed = nc.LTI(A=A2, B=B2, C=C2, x0=[1.0, 0.0], T=0.1)
    np.testing.assert_array_equal(np.asarray(fixed.init(jax.random.PRNGKey(3))), [1.0, 0.0])
    with pytest.raises(ValueError, match="LTI.x0_std must be a scalar or have 2 entries"):
        nc.LTI(A=A2, B=B2, C=C2, x0=[1.0, 0.0], x0_std=[0.1, 0.1, 0.1], T=0.1)


def test_ideal_downlink_skips_the_believed_copy_bit_for_bit():
    """Through a downlink without loss or delay into a one-packet actuator the runner does
    not run the controller side's copy of the actuator (the applied actions are the
    believed ones): every signal equals the run where the same ideal link is declared as
    a one-point delay law (PmfDelay([1.0])), which keeps the copy."""
    import pathlib
    import sys
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))
    from benchmarks.direct_servo import servo
    from examples.cartpole import cartpole
    for loop in (dataclasses.replace(servo(steps=200), record=True), cartpole()):
        kept = dataclasses.replace(loop, downlink=nc.Link(delay=nc.PmfDelay([1.0])))
        keys = jax.random.split(jax.random.PRNGKey(7), 8)
        a = jax.jit(jax.vmap(lambda k: nc.simulate(loop, k)))(keys)
        b = jax.jit(jax.vmap(lambda k: nc.simulate(kept, k)))(keys)
        for name in ("x", "u", "xhat", "sent_sc", "recv_ca", "failed"):
            np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
        assert np.asarray(a.x).size and np.ptp(np.asarray(a.u)) > 0


def test_a_link_without_capacity_is_sized_by_its_loop():
    """Link(capacity=None), the default: the Loop picks the smallest ring its delay bounds
    and the estimator's window allow (at least 2); the run equals the one with that ring
    given by hand, and a link used outside a Loop asks for a capacity."""
    slow = dict(delay=nc.PmfDelay([0.5, 0.0, 0.0, 0.5]))                      # delays 0 or 3 periods
    auto = _lti_loop(uplink=nc.Link(**slow))
    assert auto.uplink.capacity == 4 and auto.downlink.capacity == 2
    key = jax.random.PRNGKey(3)
    a = jax.jit(nc.simulate)(auto, key)
    b = jax.jit(nc.simulate)(_lti_loop(uplink=nc.Link(**slow, capacity=4)), key)
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert _lti_loop(buffer=5).uplink.capacity == 6                          # the EKF's window + 1
    late = nc.Link(delay=nc.ShiftedExponential(eta=0.5, phi=0.01), tau_max=0.8)   # T = 0.1: 5..8 periods
    assert _lti_loop(uplink=late, buffer=5).uplink.capacity == 9
    with pytest.raises(ValueError, match="Link.capacity is None: a Loop sizes it"):
        nc.Link().init(jnp.zeros(2))


def test_run_applies_a_metrics_function_and_every_scheme_run_is_it():
    """run(loop, key, metrics=fn, **context) = fn(loop, simulate(loop, key), **context) (default
    evaluate); each paper's run is jaxnc.loop.run with that paper's metrics, one signature."""
    import functools
    from jaxnc.schemes import balancing, diffdrive, hdd, mecanum
    loop, key = _lti_loop(), jax.random.PRNGKey(4)
    tr = nc.simulate(loop, key)
    fn = lambda lp, traj, *, scale: scale * jnp.sum(traj.x)
    assert float(nc.run(loop, key, metrics=fn, scale=2.0)) == float(2.0 * jnp.sum(tr.x))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), nc.run(loop, key), nc.evaluate(loop, tr)))
    for scheme in (balancing, diffdrive, hdd, mecanum):
        assert isinstance(scheme.run, functools.partial) and scheme.run.func is nc.run
        assert scheme.run.args == () and scheme.run.keywords == {"metrics": scheme.metrics}


@pytest.mark.parametrize("which", ["lti", "mecanum", "diffdrive"])
def test_a_run_is_the_run_given_its_own_draws_bit_for_bit(which):
    """simulate(loop, key) slices the flat standard draws per slow period and scales them there
    (the runner's fast path); simulate(loop, key, draw(loop, key)) reads the scaled draws: the
    same trajectory bit for bit, under jit and vmap as the Monte-Carlo engine runs it; the
    differential drive's noise enters every ``noise_period`` = 10 fast periods, the Mecanum
    loop's plant noise has q = 7 entries (the draws the fast path is for), and the LTI loop's
    noise is added to the state and the measurement (no fused multiply-add may take the
    scaling's product)."""
    from jaxnc.schemes import diffdrive, mecanum
    loop = {"lti": lambda: _lti_loop(N=2, steps=40, uplink=nc.Link(nc.Bernoulli(0.3))),
            "mecanum": lambda: mecanum.mecanum_loop("DRHE", 10, 0.5, horizon_s=8.0),
            "diffdrive": lambda: diffdrive.diffdrive_loop("e", horizon_s=4.0)}[which]()
    if which == "diffdrive":
        assert loop.plant.noise_period > 1
    keys = montecarlo.seed_keys(3, 16)
    own = jax.jit(jax.vmap(lambda k, lp: nc.simulate(lp, k), in_axes=(0, None)))(keys, loop)
    given = jax.jit(jax.vmap(lambda k, lp: nc.simulate(lp, k, nc.draw(lp, k)), in_axes=(0, None)))(keys, loop)
    assert float(jnp.max(jnp.abs(nc.draw(loop, keys[0]).w))) > 0.0
    for a, b in zip(jax.tree.leaves(own), jax.tree.leaves(given)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_remat_keeps_the_forward_run_and_the_gradient():
    """Loop(remat=True): the same run bit for bit, the same gradient up to rounding, and the
    slow period is a checkpoint in the program's jaxpr (one more than without it: the EKF's
    prediction is one in both); a non-bool is refused."""
    loop = _lti_loop(N=2, steps=40, uplink=nc.Link(nc.Bernoulli(0.3)))
    keys = montecarlo.seed_keys(0, 8)

    def objective(lp):
        def f(K):
            lq = dataclasses.replace(lp, controller=dataclasses.replace(lp.controller, K=K))
            return jnp.mean(jax.vmap(lambda k: nc.run(lq, k).cost_raw)(keys))
        return f

    K = jnp.asarray(K2, jnp.float32)
    plain, remat = loop, dataclasses.replace(loop, remat=True)
    run = jax.jit(jax.vmap(lambda k, lp: nc.simulate(lp, k), in_axes=(0, None)))
    for a, b in zip(jax.tree.leaves(run(keys, plain)), jax.tree.leaves(run(keys, remat))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    (v0, g0), (v1, g1) = (jax.jit(jax.value_and_grad(objective(lp)))(K) for lp in (plain, remat))
    assert float(v0) == float(v1)
    assert np.all(np.abs(np.asarray(g0)) > 0)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-5)
    count = lambda lp: str(jax.make_jaxpr(objective(lp))(K)).count("remat2[")   # jax.checkpoint's primitive
    assert count(remat) == count(plain) + 1
    with pytest.raises(ValueError, match="Loop.remat"):
        dataclasses.replace(loop, remat=1)


def _luenberger_loop():
    plant = nc.LTI(A=A2, B=B2, C=C2, x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(nc.Bernoulli(0.3)),
                   estimator=nc.Luenberger(plant, L=np.array([[0.6], [0.8]]), mean0=np.zeros(2)),
                   controller=nc.StateFeedback(K2), downlink=nc.Link(), actuator=nc.HoldLast(), steps=40, T=0.1)


def _limited_loop():
    loop = _lti_loop(uplink=nc.Link(nc.Bernoulli(0.3)))
    plant = nc.LimitedSensor(loop.plant, (nc.Saturation(np.float64(-0.8), np.array([0.8])), nc.Quantizer(np.float64(0.01))))
    act = nc.LimitedActuator(nc.HoldLast(), (nc.Saturation(np.array([-0.5]), np.float64(0.5)), nc.DeadZone(np.float64(-0.01),
                                                                                                          np.float64(0.01))))
    return dataclasses.replace(loop, plant=plant, actuator=act)


@pytest.mark.parametrize("build", [lambda: _lti_loop(uplink=nc.Link(nc.Bernoulli(0.3)), buffer=1), _luenberger_loop,
                                   _limited_loop])
def test_a_loop_built_under_x64_from_float64_numbers_runs_as_in_float32(build):
    # the runner works in float32; an EKF's Q, R, mean0, cov0 or a Luenberger gain given as
    # numpy float64 used to make the filter's state float64 under jax_enable_x64, a scan
    # carry type error inside tracing; so did a limit's float64 numbers (nx3: the action and
    # the measurement became float64)
    ref = nc.simulate(build(), jax.random.PRNGKey(4))
    with jax.enable_x64(True):
        tr = nc.simulate(build(), jax.random.PRNGKey(4))
        assert tr.xhat.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(tr.xhat), np.asarray(ref.xhat))
    np.testing.assert_array_equal(np.asarray(tr.x), np.asarray(ref.x))


def _actuator_reference(loop, d, K, zero: bool, initial: float = 0.0):
    """A float64 actuator of one-action packets written from the docstrings: at each fast
    instant the newest packet by stamp among those arriving now (newer than every one
    delivered before: the link's order "newest") becomes current. Hold-last
    (``zero=False``) applies the current action from then on; the zero strategy
    (``zero=True``, ZeroOrder) applies it while its stamp kN <= t < (k + 1) N, zero
    otherwise. ``initial`` (hold-last) or 0 before the first."""
    A, B, C = (np.asarray(m, float) for m in (loop.plant.A, loop.plant.B, loop.plant.C))
    N, S = loop.N, loop.steps // loop.N
    w, v, dd = np.asarray(d.w, float), np.asarray(d.v, float), np.asarray(d.downlink.delay)
    x, flying, cur, xs, us = np.asarray(loop.plant.x0, float), [], None, [], []
    for k in range(S):
        z = C @ x + v[k]
        if dd[k] >= 0:
            flying.append((k * N + dd[k], k * N, -K @ z))
        for j in range(N):
            t = k * N + j
            now = [p for p in flying if p[0] <= t and (cur is None or p[1] > cur[0])]
            flying = [p for p in flying if p[0] > t]
            if now:
                _, s, a = max(now, key=lambda p: p[1])
                cur = (s, a)
            due = cur is not None and (not zero or t < cur[0] + N)
            u = cur[1] if due else np.full(1, 0.0 if zero else initial)
            xs.append(x.copy())
            us.append(u.copy())
            x = A @ x + B @ u + w[k, j]
    return np.array(xs), np.array(us)


def _downlink_run(actuator, N, pmf, seed, zero, initial=0.0):
    """A 2-state servo under StateFeedback over a lossy (20 %) downlink delaying by ``pmf``
    fast periods: the run and the float64 reference's (x, u)."""
    K = np.array([[2.0]])
    plant = nc.LTI(A=A2, B=B2, C=C2, x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.01], T=0.1)
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.StateFeedback(K), downlink=nc.Link(nc.Bernoulli(0.2), nc.PmfDelay(pmf)),
                   actuator=actuator, N=N, steps=60 * N, T=0.1)
    key = jax.random.PRNGKey(seed)
    return loop, key, nc.simulate(loop, key), _actuator_reference(loop, nc.draw(loop, key), K, zero, initial)


@pytest.mark.parametrize("N, pmf", [(1, [0.0, 1.0]), (2, [0.4, 0.3, 0.3]), (3, [0.2, 0.2, 0.2, 0.2, 0.2])])
def test_hold_last_applies_a_delayed_action_on_arrival(N, pmf):
    # it used to apply only an action that arrived at the instant it was stamped: over a
    # downlink delaying every packet the plant got u = 0 throughout while recv_ca counted them
    _, _, tr, (xs, us) = _downlink_run(nc.HoldLast(), N, pmf, 11, zero=False)
    assert np.abs(us).max() > 0.5
    np.testing.assert_allclose(np.asarray(tr.u), us, atol=1e-5)
    np.testing.assert_allclose(np.asarray(tr.x), xs, atol=1e-5)


def test_hold_last_applies_its_initial_action_until_the_first_packet_arrives():
    # before 2026-12-04 an actuator applied 0 until its first packet: a lift whose controller
    # carries the hover thrust as its bias (PID.u_bias) fell until the first measurement arrived
    _, _, tr, (xs, us) = _downlink_run(nc.HoldLast(initial=-0.7), 2, [0.0, 0.0, 0.0, 1.0], 11, zero=False,
                                       initial=-0.7)
    assert np.all(us[:3] == -0.7) and np.abs(us + 0.7).max() > 0.5
    np.testing.assert_allclose(np.asarray(tr.u), us, atol=1e-5)
    np.testing.assert_allclose(np.asarray(tr.x), xs, atol=1e-5)


@pytest.mark.parametrize("N, pmf", [(1, [0.5, 0.5]), (2, [0.4, 0.3, 0.3]), (4, [0.3, 0.3, 0.2, 0.1, 0.1, 0.0])])
def test_zero_order_applies_each_action_over_its_period_and_zero_when_it_is_missing(N, pmf):
    # ZeroOrder used to apply each action for one fast period and zero in the N - 1 others,
    # on a perfect network too
    loop, key, tr, (xs, us) = _downlink_run(nc.ZeroOrder(), N, pmf, 12, zero=True)
    u = np.asarray(tr.u)
    assert np.abs(us).max() > 0.5 and np.mean(us == 0) > 0.05     # both actions and zeros occur
    np.testing.assert_allclose(u, us, atol=1e-5)
    np.testing.assert_allclose(np.asarray(tr.x), xs, atol=1e-5)
    # a perfect downlink: every fast period of every slow period gets its period's action
    ideal = dataclasses.replace(loop, downlink=nc.Link())
    u_ideal = np.asarray(nc.simulate(ideal, key).u).reshape(-1, N)
    assert np.all(u_ideal[:, :1] != 0) and np.all(u_ideal == u_ideal[:, :1])


@pytest.mark.parametrize("order", ["newest", "all"])
def test_passthrough_holds_the_newest_measurement_by_stamp(order):
    """Passthrough behind a link whose packets overtake one another (N = 1, x_t = t, z = x): at
    each instant it holds the arrived measurement with the newest stamp. Behind order="all" it
    used to take an older packet delivered after a newer one (x̂ went back in time: 1 after 2)."""
    delays = [0, 2, 0, -1, 0, 3, 0, 0, -1, 0]     # stamp 1 arrives alone at 3 (after 2), 5 at 8 (after 6, 7)
    K = len(delays)
    plant = nc.Discrete(x0=[0.0], w_std=[0.0], v_std=[0.0], f=lambda x, u, w: x + 1.0, h=lambda x, v: x + v,
                        input_dim=1, noise_dim=1, output_dim=1)
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(delay=nc.TraceDelay(delays), order=order),
                   estimator=nc.Passthrough(), controller=nc.StateFeedback(K=[[0.0]]), downlink=nc.Link(),
                   actuator=nc.HoldLast(), N=1, T=0.1, steps=K, record=True)
    tr = nc.simulate(loop, jax.random.PRNGKey(0))
    want, held = [], 0.0
    for k in range(K):                          # the newest stamp among the packets arrived by k
        arrived = [s for s in range(k + 1) if delays[s] >= 0 and s + delays[s] <= k]
        held = float(max(arrived)) if arrived else held
        want.append(held)
    np.testing.assert_array_equal(np.asarray(tr.xhat)[:, 0], want)


def test_eager_draw_and_tracking_metrics_are_one_program_each_and_leave_a_loops_program_unchanged():
    """``nc.draw`` and ``Tracking.metrics`` on concrete values compile one program each (they
    dispatched one small program per operation: 81 for a balancing loop's draw); under a trace
    they add no call of their own, so a loop's program, and its persistent-cache entry, are
    what they were. The eager results are the traced ones, bit for bit."""
    import re

    from jaxnc import references as refs
    from jaxnc.cache import compile_clock
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 1.0]], B=[[0.0], [0.1]], C=np.eye(2), x0=[0.0, 0.0],
                   w_std=[0.01, 0.01], v_std=[0.02, 0.02], T=0.1)
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(loss=nc.GilbertElliott(0.1, 0.3)),
                   estimator=nc.Passthrough(), controller=nc.StateFeedback([[1.0, 1.5]]), downlink=nc.Link(),
                   actuator=nc.HoldLast(), N=3, steps=3 * 23, T=0.1, record=True)
    tracking, key = nc.Tracking(refs.Step(0.0, time=0.5), index=0), jax.random.PRNGKey(5)
    c0 = compile_clock()
    d = nc.draw(loop, key)
    c1 = compile_clock()
    x = jax.jit(nc.simulate)(loop, key).x
    c2 = compile_clock()
    tm = tracking.metrics(x, loop.T)
    c3 = compile_clock()
    assert (c1 - c0).compilations <= 1 and (c3 - c2).compilations <= 1
    for got, want in ((d, jax.jit(nc.draw)(loop, key)), (tm, jax.jit(tracking.metrics)(x, loop.T))):
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    text = str(jax.make_jaxpr(lambda k: nc.run_tracking(k, loop, tracking))(key))
    assert not re.search(r"name=(draw|<lambda>)\b", text)

    class Law:             # a plain Python object a part holds: a leaf jax.jit cannot take
        def init(self):
            return jnp.zeros(())

        def step(self, s, k, x):
            return -x[0], s, jnp.zeros(())

    one = nc.LTI(A=[[1.0]], B=[[0.1]], C=[[1.0]], x0=[1.0], w_std=[0.01], v_std=[0.02], T=0.1)
    plain, arrays = (nc.Loop(plant=one, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                             controller=c, downlink=nc.Link(), actuator=a, T=0.1, steps=10)
                     for c, a in ((nc.Cascade(Law(), horizon=1), nc.PacketActuator(horizon=1)),
                                  (nc.StateFeedback([[1.0]]), nc.HoldLast())))
    # called as it is (op by op, as draw itself unwrapped), where jax.jit would refuse the object
    got, want = nc.draw(plain, key), nc.draw.__wrapped__(arrays, key)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_simulate_called_eagerly_compiles_once_per_loop_structure():
    """``nc.simulate(loop, key)`` outside jit compiled the whole run again at every call (0.65 s
    for a small loop); now a second call, and a call on a loop of the same structure with new
    numbers, compile nothing, and the run is the one of the loop as a jit argument (as
    run_batched passes it), bit for bit."""
    from jaxnc.cache import compile_clock
    loop = _lti_loop(N=2, steps=40, uplink=nc.Link(nc.Bernoulli(0.3)))
    other = dataclasses.replace(loop, uplink=nc.Link(nc.Bernoulli(0.1)))        # new numbers, same structure
    nc.simulate(loop, jax.random.PRNGKey(0))
    before = compile_clock()
    a = nc.simulate(loop, jax.random.PRNGKey(1))
    nc.simulate(other, jax.random.PRNGKey(1))
    assert (compile_clock() - before).compilations == 0
    b = jax.jit(lambda lp, k: nc.simulate(lp, k))(loop, jax.random.PRNGKey(1))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
