"""Prediction stage of the NUDREKF (seed 000, section 3.3.1): the lazily advanced
packet chain yields exactly the actions and controller states of the materialised packet;
the scheme's loop roles (estimator, copy-keeping controller, chain actuator) against chains
advanced by hand."""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.controllers.path_following import PathFollower
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.controllers.prediction import advance_chain, exhausted_chain, predict_periods, start_chain
from jaxnc.loop import ChainActuator, ChainController
from jaxnc.paths import get_path
from jaxnc.plants.mecanum import PROCESS_NOISE_DIM, Mecanum


def materialised_packet(model, controller, controller_next, mean, ctrl_state, steps, hold, noise_dim):
    """Reference: the prediction stage of section 3.3.1 (steps 1-5, eq. 17) written out as
    a Python loop, the packet materialised. The controller (``controller`` at position 0,
    from the corrected estimate; ``controller_next`` after) runs every ``hold`` fast
    periods and its action is held in between; the noise-free model moves one fast period
    per action. Returns (actions[steps], controller states[steps + 1]) as lists, entry j of
    the states being the one before position j's computation."""
    w0 = jnp.zeros((noise_dim,), mean.dtype)
    x, c, u = mean, ctrl_state, None
    us, cs = [], [ctrl_state]
    for j in range(steps):
        if j % hold == 0:
            u, c = (controller if j == 0 else controller_next)(x, c)
        us.append(u)
        cs.append(c)
        x = model.dynamics(x, u, w0)
    return jnp.stack(us), jax.tree.map(lambda *a: jnp.stack(a), *cs)


def _packet_problem(hold):
    """Seed 000's model and path follower (the first action's law, the later ones'), a
    horizon of 12 actions, a corrected estimate and a controller state."""
    plant, fol = Mecanum(), PathFollower(get_path("lissajous"))
    Ts = plant.T * hold
    ctrl = lambda m, c: fol(plant, m, c, Ts)
    nxt = lambda m, c: fol(plant, m, c, Ts, narrow=True)
    mean = jnp.array([0.05, -0.02, 0.1, 0.01, -0.03, 0.2], jnp.float32)
    c0 = fol.init()._replace(integ=jnp.array([0.01, -0.02, 0.03], jnp.float32))
    return plant, ctrl, nxt, 12, mean, c0


@pytest.mark.parametrize("hold", [1, 3])
def test_chain_reproduces_the_materialised_packet(hold):
    plant, ctrl, nxt, H, mean, c0 = _packet_problem(hold)

    @jax.jit
    def both():
        us, cs = materialised_packet(plant, ctrl, nxt, mean, c0, H, hold, PROCESS_NOISE_DIM)

        def body(ch, _):
            return advance_chain(plant, nxt, ch, H, hold, PROCESS_NOISE_DIM), (ch.u, ch.c_before)
        # H + 5 positions: past the horizon the last action is held
        _, (u_chain, c_chain) = jax.lax.scan(body, start_chain(ctrl, mean, c0), None, length=H + 5)
        return us, cs, u_chain, c_chain

    us, cs, u_chain, c_chain = both()
    np.testing.assert_allclose(u_chain[:H], us, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(u_chain[H:], np.broadcast_to(us[-1], (5, 4)), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(c_chain.idx[:H + 1], cs.idx)
    np.testing.assert_allclose(c_chain.integ[:H + 1], cs.integ, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(c_chain.integ[H + 1:], np.broadcast_to(cs.integ[-1], (4, 3)), rtol=1e-5, atol=1e-6)
    assert not np.allclose(us[0], us[-1])                   # the packet does vary
    if hold > 1:
        np.testing.assert_array_equal(us[1:hold], np.broadcast_to(us[0], (hold - 1, 4)))


@pytest.mark.parametrize("hold", [1, 3])
def test_chain_is_the_lazy_form_of_predict_periods(hold):
    """Advancing ``start_chain`` position by position gives what ``predict_periods``
    materialises with the packet's law (the first action from the corrected estimate, then
    every ``hold`` periods below the horizon, held in between): the same states, actions and
    controller states at every position below the horizon."""
    plant, ctrl, nxt, H, mean, c0 = _packet_problem(hold)

    def law(c, x):                  # c: (the follower's state, the position j, the action held)
        s, j, u = c
        first = jax.tree.map(lambda a, b: jnp.where(j == 0, a, b), ctrl(x, s), nxt(x, s))
        run = (j < H) & (j % hold == 0)
        u, s = jax.tree.map(lambda a, b: jnp.where(run, a, b), first, (u, s))
        return u, (s, j + 1, u)

    @jax.jit
    def both():
        states, us, (cs, _, _), _ = predict_periods(law, plant.dynamics, mean, (c0, jnp.zeros((), jnp.int32),
                                                                                 jnp.zeros(4, jnp.float32)),
                                                    H, PROCESS_NOISE_DIM)
        body = lambda ch, _: (advance_chain(plant, nxt, ch, H, hold, PROCESS_NOISE_DIM), ch)
        _, chains = jax.lax.scan(body, start_chain(ctrl, mean, c0), None, length=H)
        return states, us, cs, chains

    states, us, cs, chains = both()
    # the same operations in another program: XLA:CPU fuses them differently, a few float32 ulps apart
    np.testing.assert_allclose(chains.x, states, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(chains.u, us, rtol=1e-5, atol=1e-5)
    for a, b in zip(jax.tree.leaves(chains.c_after), jax.tree.leaves(cs)):
        if jnp.issubdtype(a.dtype, jnp.integer):
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(us[0], us[-1])                   # the packet does vary


def test_exhausted_chain_holds_its_action():
    plant, fol = Mecanum(), PathFollower(get_path("turn180"))
    nxt = lambda m, c: fol(plant, m, c, plant.T, narrow=True)
    u = jnp.array([1.0, 2.0, 3.0, 4.0], jnp.float32)
    ch = exhausted_chain(jnp.zeros(6, jnp.float32), u, fol.init(), 5)
    for _ in range(3):
        ch = advance_chain(plant, nxt, ch, 5, 1, PROCESS_NOISE_DIM)
        np.testing.assert_array_equal(ch.u, u)
        assert int(ch.j) == 5


# ------------------------------------------------------------------ the scheme's loop roles
N_ROLES = 4


def _roles(H=12, hold=1):
    plant, fol = Mecanum(), PathFollower(get_path("lissajous"))
    x0 = jnp.array([0.05, -0.02, 0.1, 0.0, 0.0, 0.2], jnp.float32)
    act = ChainActuator(plant, fol, plant.T * hold, jnp.int32(H), jnp.int32(hold), x0, noise_dim=PROCESS_NOISE_DIM)
    ctx = nc.Context(N=N_ROLES, steps=4 * N_ROLES, T=float(plant.T), state_dim=6, input_dim=4, output_dim=9)
    return plant, fol, act, ChainController(act), ctx


def _advance_n(plant, fol, act, chain, n):
    nxt = lambda m, c: fol(plant, m, c, act.Ts, narrow=True)
    for _ in range(n):
        chain = advance_chain(plant, nxt, chain, act.horizon, act.hold, PROCESS_NOISE_DIM)
    return chain


def test_parts_implement_at_most_three_methods():
    # issue 30's acceptance: a part implements at most three methods (docs/build_your_own_loop.md)
    for cls in (nc.EKF, ChainController, ChainActuator):
        own = [n for n, v in vars(cls).items() if callable(v) and not n.startswith("_")]
        assert len(own) <= 3, (cls.__name__, own)


def test_controller_copy_starts_a_chain_and_sends_its_period():
    """The packet is the copy at each instant of the period: position 0 is the chain started
    from the estimate (with the copy's controller state), position j that chain advanced j
    times (advance_chain by hand); sent() are the copy's N actions; a weight-0 packet continues
    the old copy."""
    plant, fol, act, ctrl, ctx = _roles()
    mean = jnp.array([0.04, -0.01, 0.12, 0.02, -0.03, 0.21], jnp.float32)
    s0 = ctrl.init(ctx)
    step = jax.jit(lambda s, w, k: ctrl.step(s, nc.WeightedEstimate(mean, jnp.float32(w)), 1.0, jnp.int32(k), ctx))
    s1, pkt, send = step(s0, 1.0, 3)
    assert int(pkt.stamp) == 3 * N_ROLES and float(send) == 1.0 and float(pkt.data.weight) == 1.0
    start = start_chain(lambda m, c: fol(plant, m, c, act.Ts), mean, s0.chain.c_before)
    for j in range(N_ROLES + 1):
        want = _advance_n(plant, fol, act, start, j)
        got = jax.tree.map(lambda a: a[j], pkt.data.chain)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(ctrl.sent(s1), pkt.data.chain.u[:N_ROLES])
    assert ctrl.sent(s1).shape == (N_ROLES, 4) and not np.allclose(ctrl.sent(s1)[0], 0.0)
    # no measurement now: the copy continues where it was
    s2, pkt2, _ = step(s1, 0.0, 4)
    np.testing.assert_allclose(pkt2.data.chain.x[0], s1.chain.x)
    np.testing.assert_allclose(pkt2.data.chain.u[0], s1.chain.u)
    np.testing.assert_allclose(ctrl.sent(s2), _period_u(plant, fol, act, s1.chain), rtol=1e-5, atol=1e-6)


def _period_u(plant, fol, act, chain):
    return np.stack([np.asarray(_advance_n(plant, fol, act, chain, j).u) for j in range(N_ROLES)])


@functools.cache
def _installing_actuator():
    """The roles, the packet stamped s = 2 N (the mean, the controller's first chain start)
    and ``run(w, arrive)``: the actuator's outputs u_t, t = 0 .. s + N + 2, when that packet
    (with weight ``w``) is delivered at instant ``arrive`` (the inbox empty before and after).
    One compiled program (a scan over t; the weight and the instant are arguments) for every
    test case below."""
    plant, fol, act, ctrl, ctx = _roles()
    mean = jnp.array([0.04, -0.01, 0.12, 0.02, -0.03, 0.21], jnp.float32)
    k = 2
    _, pkt, _ = ctrl.step(ctrl.init(ctx), nc.WeightedEstimate(mean, jnp.float32(1.0)), 1.0, jnp.int32(k), ctx)
    s = k * N_ROLES

    @jax.jit
    def run(w, arrive):
        data = jax.tree.map(lambda a: a[None], pkt.data._replace(weight=jnp.float32(w)))

        def body(st, t):
            arrived = t == arrive
            box = nc.Inbox(data, jnp.asarray([s], jnp.int32), jnp.ones((1,)), arrived[None],
                           arrived[None].astype(jnp.float32))
            st = act.receive(st, box)
            return act.output(st, t)

        return jax.lax.scan(body, act.init(ctx), jnp.arange(s + N_ROLES + 3, dtype=jnp.int32))[1]

    return plant, fol, act, mean, s, run


@pytest.mark.parametrize("d", [0, 2, N_ROLES])
def test_actuator_installs_the_chain_at_its_arrival(d):
    """A packet stamped s arriving at t = s + d: the actuator applies at t the action the
    packet's chain holds at position d (its first action advanced d times by hand), and
    afterwards continues that chain; a packet of weight 0 is not installed."""
    plant, fol, act, mean, s, run = _installing_actuator()
    us = run(1.0, s + d)
    start = start_chain(lambda m, c: fol(plant, m, c, act.Ts), mean, fol.init())
    for j in range(3):
        np.testing.assert_allclose(us[s + d + j], _advance_n(plant, fol, act, start, d + j).u, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(us[:s + d], 0.0)               # the idle chain holds zero
    np.testing.assert_array_equal(run(0.0, s + d), 0.0)          # weight 0: never installed


def test_estimator_predicts_along_the_believed_actions():
    plant, fol, act, ctrl, ctx = _roles()
    Q = jnp.full((PROCESS_NOISE_DIM,), 1e-4, jnp.float32)
    est = nc.EKF(plant, Q, jnp.full((9,), 1e-3, jnp.float32), jnp.zeros(6, jnp.float32),
                 0.01 * jnp.eye(6, dtype=jnp.float32), form="sequential", keep_means=True)
    ub = jnp.linspace(-1.0, 2.0, N_ROLES * 4, dtype=jnp.float32).reshape(N_ROLES, 4)
    st = jax.jit(lambda s: est.predict(s, jnp.zeros_like(ub), ub, jnp.int32(0)))(est.init(ctx))
    g = Gaussian(jnp.zeros(6, jnp.float32), 0.01 * jnp.eye(6, dtype=jnp.float32))
    for j in range(N_ROLES):
        g = ekf_predict(plant.dynamics, g, ub[j], Q, PROCESS_NOISE_DIM)
        np.testing.assert_allclose(st.means[j], g.mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(st.base.cov, g.cov, rtol=1e-5, atol=1e-7)


def test_loop_with_a_copy_keeping_controller_refuses_a_controller_trigger_or_limits():
    from jaxnc.schemes import mecanum as mec
    loop = mec.mecanum_loop("DRHE", 4, 0.2, horizon_s=1.0)
    assert loop.controller.keeps_copy
    with pytest.raises(ValueError, match="controller_trigger"):
        dataclasses.replace(loop, controller_trigger=nc.Petc(delta=0.1))
    with pytest.raises(ValueError, match="LimitedActuator"):
        dataclasses.replace(loop, actuator=nc.LimitedActuator(loop.actuator, nc.Saturation(-1.0, 1.0)))


def test_estimator_does_not_use_a_measurement_before_it_arrives():
    """On a delayed uplink (seed 000's has none) the NUDREKF uses the measurement of instant
    k only if it was delivered by k: with half the packets 3 fast periods late (N = 2) the
    run (states and actions, steered by its estimates) equals the same loop's that lost
    exactly those packets (it used to equal the undelayed loop's: measurements used before
    they arrived); an uplink that
    delays every packet is refused when the loop is built."""
    from jaxnc.schemes import mecanum as mec
    base = mec.mecanum_loop("DRHE", 2, 0.0, horizon_s=3.0, sigma=0.0, delta=0.0, full=True)
    key = jax.random.PRNGKey(0)
    half = dataclasses.replace(base, uplink=nc.Link(delay=nc.PmfDelay([0.5, 0.0, 0.0, 0.5]), capacity=3))
    late = np.asarray(nc.draw(half, key).uplink.delay) > 0
    lost = dataclasses.replace(base, uplink=nc.Link(loss=nc.TraceLoss(late), capacity=3))
    sim = jax.jit(nc.simulate)
    a, b = sim(half, key), sim(lost, key)
    assert 0 < late.sum() < late.size
    assert float(np.sum(a.recv_sc)) > float(np.sum(b.recv_sc))       # the late packets did arrive, later
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))     # the robot, steered by the estimates
    np.testing.assert_array_equal(np.asarray(a.u), np.asarray(b.u))
    with pytest.raises(ValueError, match=r"EKF\) uses a measurement at most 0 slow periods late"):
        dataclasses.replace(base, uplink=nc.Link(delay=nc.PmfDelay([0.0, 0.0, 1.0]), capacity=3))


# --- the EKF's options that make it seed 000's NUDREKF (form="sequential", weight="slot",
# output="weighted", keep_means): the former NudrekfEstimator is this configuration of nc.EKF

_A2 = np.array([[1.0, 0.1], [0.0, 0.95]])
_B2 = np.array([[0.005], [0.1]])
_C2 = np.array([[1.0, 0.0], [0.3, 1.0]])        # two outputs: the sequential update has two scalar steps


def _lti2():
    return nc.LTI(_A2, _B2, _C2, x0=[1.0, -0.5], x0_std=[0.3, 0.3], w_std=[0.05, 0.05], v_std=[0.1, 0.2], T=0.1)


def _ekf2(plant, **kw):
    R = np.diag([0.1 ** 2, 0.2 ** 2])
    return nc.EKF(plant, Q=np.diag([0.05 ** 2] * 2), R=np.diag(R) if kw.get("form") == "sequential" else R,
                  mean0=[1.0, -0.5], cov0=0.09 * np.eye(2), **kw)


def _loop2(estimator, trigger=None, steps=60):
    return nc.Loop(plant=estimator.model, trigger=trigger or nc.Periodic(), uplink=nc.Link(nc.Bernoulli(0.3)),
                   estimator=estimator, controller=nc.StateFeedback([[2.0, 1.0]]), downlink=nc.Link(),
                   actuator=nc.HoldLast(), N=2, steps=steps, T=0.1,
                   record=nc.Record(signals=("x", "u", "xhat", "sent_sc")))


def test_sequential_form_is_the_joseph_form_up_to_rounding():
    # the scalar-sequential update is the same posterior as the batch Joseph update in exact
    # arithmetic: over a lossy 60-step run the estimates agree to float32 rounding
    plant = _lti2()
    key = jax.random.PRNGKey(4)
    a = jax.jit(nc.simulate)(_loop2(_ekf2(plant)), key)
    b = jax.jit(nc.simulate)(_loop2(_ekf2(plant, form="sequential")), key)
    assert not np.array_equal(np.asarray(a.xhat), np.asarray(b.xhat))      # a different computation ...
    np.testing.assert_allclose(b.xhat, a.xhat, rtol=1e-4, atol=1e-5)     # ... of the same estimate
    np.testing.assert_allclose(b.x, a.x, rtol=1e-4, atol=1e-5)


def test_slot_weight_passes_the_triggers_gradient_where_the_sensor_is_silent():
    # weight="stamp" reads a silent instant's weight as the constant 0, "slot" as the ring's
    # 0 that carries the PETC's straight-through gradient: the same run, and with a threshold
    # that keeps the sensor silent after its first packet the delta-gradient is exactly 0
    # through "stamp" and not through "slot" (the gradient seed 000's tuning of delta needs)
    plant = _lti2()
    key = jax.random.PRNGKey(1)

    def cost(delta, weight):
        lp = _loop2(_ekf2(plant, form="sequential", weight=weight), nc.Petc(delta=delta, temperature=0.5))
        tr = nc.simulate(lp, key)
        return jnp.mean(jnp.square(tr.x)), tr

    (ca, ta), ga = jax.jit(jax.value_and_grad(lambda d: cost(d, "stamp"), has_aux=True))(jnp.float32(1.0))
    (cb, tb), gb = jax.jit(jax.value_and_grad(lambda d: cost(d, "slot"), has_aux=True))(jnp.float32(1.0))
    np.testing.assert_array_equal(np.asarray(tb.x), np.asarray(ta.x))
    assert float(ca) == float(cb)
    assert float(jnp.sum(ta.sent_sc)) <= 1.0                               # silent after the first
    assert float(ga) == 0.0
    assert np.isfinite(float(gb)) and float(gb) != 0.0


def test_weighted_output_is_the_corrected_mean_and_the_packets_weight():
    # output="weighted": WeightedEstimate(mean had the measurement of now been used, its weight)
    plant = _lti2()
    est = _ekf2(plant, form="sequential", output="weighted", keep_means=True)
    ctx = nc.Context(N=2, steps=10, T=0.1, state_dim=2, input_dim=1, output_dim=2)
    st = est.init(ctx)
    z = jnp.array([0.7, -0.2], jnp.float32)
    for w, arrived in ((1.0, True), (0.0, True), (1.0, False)):
        inbox = nc.Inbox(z[None], jnp.array([0], jnp.int32), jnp.array([w], jnp.float32), jnp.array([arrived]),
                         jnp.array([w], jnp.float32))
        s1, out = est.correct(st, inbox, jnp.int32(0))
        ref = ekf_update(plant.measure, Gaussian(st.post.mean, st.post.cov), z, np.diag([0.1 ** 2, 0.2 ** 2]), 2)
        assert isinstance(out, nc.WeightedEstimate)
        np.testing.assert_allclose(out.mean, ref.mean, rtol=1e-5, atol=1e-6)
        used = w if arrived else 0.0
        assert float(out.weight) == used
        np.testing.assert_allclose(s1.post.mean, ref.mean if used else st.post.mean, rtol=1e-5, atol=1e-6)


def test_slot_weight_makes_a_relaxed_petc_loop_smooth_and_its_exact_gradient_match_differences():
    # A relaxed PETC's link sends only where beta > 1/2, so with weight="stamp" the filter's
    # weight jumps 0 -> 1/2 where a beta crosses 1/2 and the exact gradient misses the jumps; with
    # weight="slot" the filter blends by beta at every instant (no delay on the uplink), the
    # objective is smooth and the exact gradient equals central differences (float32: the
    # differences' rounding is ~1e-7 * cost / step, 1e-6 of the derivative here)
    from benchmarks.silent_instants import relaxed_pendulum_cost
    cost = relaxed_pendulum_cost("slot", jax.random.split(jax.random.PRNGKey(1), 64), 120)

    c, g = jax.jit(cost), jax.jit(jax.grad(cost))
    d0, e = jnp.float32(0.025), 2e-3
    vals = np.array([float(c(jnp.float32(d))) for d in np.linspace(0.02, 0.03, 11)])
    d2, d3 = np.abs(np.diff(vals, 2)), np.abs(np.diff(vals, 3))
    assert d3.max() < 0.2 * d2.max(), (d2, d3)      # the curvature varies smoothly: no jumps
    fd = (float(c(d0 + e)) - float(c(d0 - e))) / (2 * e)
    assert abs(float(g(d0)) - fd) <= 0.01 * abs(fd), (float(g(d0)), fd)


@pytest.mark.parametrize("make", ["SteadyStateKF", "Luenberger"])
def test_slot_weight_of_the_linear_observers_makes_a_relaxed_petc_loop_smooth(make):
    # the same for the stationary-gain filters (their weight option reads the ring the same way), at a
    # temperature of 0.1 (at 0.02 this 80-step loop's relaxed objective varies faster than differences
    # of 1e-3 resolve, with or without the slot: exact 10.3 against 0.35-0.71)
    plant = nc.LTI(_A2, _B2, _C2, x0=[1.0, -0.5], x0_std=[0.3, 0.3], w_std=[0.05, 0.05], v_std=[0.1, 0.2], T=0.1)
    if make == "SteadyStateKF":
        est = nc.SteadyStateKF(plant, Q=[0.05 ** 2] * 2, R=np.diag([0.1 ** 2, 0.2 ** 2]), mean0=[1.0, -0.5], weight="slot")
    else:
        est = nc.Luenberger(plant, L=[[0.5, 0.0], [0.0, 0.3]], mean0=[1.0, -0.5], weight="slot")
    keys = jax.random.split(jax.random.PRNGKey(2), 64)

    def cost(d):
        lp = nc.Loop(plant=plant, trigger=nc.Petc(delta=d, temperature=0.1, relaxed=True),
                     uplink=nc.Link(nc.Bernoulli(0.2)), estimator=est, controller=nc.StateFeedback([[2.0, 1.0]]),
                     downlink=nc.Link(), actuator=nc.HoldLast(), N=1, steps=80, T=0.1, record=nc.Record(signals=("x",)))
        return jnp.mean(jnp.square(jax.vmap(lambda k: nc.simulate(lp, k).x)(keys)))

    c, g = jax.jit(cost), jax.jit(jax.grad(cost))
    d0, e = jnp.float32(0.1), 3e-3
    vals = np.array([float(c(jnp.float32(d))) for d in np.linspace(0.08, 0.12, 11)])
    d2, d3 = np.abs(np.diff(vals, 2)), np.abs(np.diff(vals, 3))
    assert d3.max() < 0.2 * d2.max(), (d2, d3)
    fd = (float(c(d0 + e)) - float(c(d0 - e))) / (2 * e)
    assert abs(float(g(d0)) - fd) <= 0.01 * abs(fd), (float(g(d0)), fd)


def test_slot_weight_with_a_window_of_late_measurements_runs_the_same_loop():
    # EKF(buffer=2) over a lossy uplink delaying packets 0-5 fast periods (N = 2): with a hard
    # (straight-through) PETC the run with weight="slot" is bit for bit the run with "stamp" (each
    # window instant reads its own slot, and a packet in flight weighs 0 until it arrives), and
    # the delta-gradient differs (the silent instants' terms)
    plant = _lti2()
    key = jax.random.PRNGKey(5)

    def run(delta, weight):
        lp = nc.Loop(plant=plant, trigger=nc.Petc(delta=delta, temperature=0.05),
                     uplink=nc.Link(nc.Bernoulli(0.2), nc.PmfDelay([0.3, 0.2, 0.1, 0.1, 0.1, 0.2])),
                     estimator=_ekf2(plant, buffer=2, weight=weight), controller=nc.StateFeedback([[2.0, 1.0]]),
                     downlink=nc.Link(), actuator=nc.HoldLast(), N=2, steps=60, T=0.1,
                     record=nc.Record(signals=("x", "xhat", "recv_sc")))
        tr = nc.simulate(lp, key)
        return jnp.mean(jnp.square(tr.x)), tr

    (ca, ta), ga = jax.jit(jax.value_and_grad(lambda d: run(d, "stamp"), has_aux=True))(jnp.float32(0.05))
    (cb, tb), gb = jax.jit(jax.value_and_grad(lambda d: run(d, "slot"), has_aux=True))(jnp.float32(0.05))
    assert 0 < float(jnp.sum(ta.recv_sc)) < 30                      # some measurements, not all
    np.testing.assert_array_equal(np.asarray(tb.xhat), np.asarray(ta.xhat))
    np.testing.assert_array_equal(np.asarray(tb.x), np.asarray(ta.x))
    assert float(ga) != float(gb) and np.isfinite(float(gb))


def test_straight_through_gradient_through_a_filter_needs_the_silent_instants():
    """The straight-through δ-derivative of a servo with PETC and an EKF (hard forward, τ = 0.05)
    against central differences of the hard objective on common random numbers (h = 0.02,
    4096 seeds, 95 % interval from the per-seed differences): with the filter's default
    weight="slot" it lies within 3 standard errors of them; with "stamp", which cuts the gradient
    at the instants the sensor is silent, it has the other sign (docs/tuning.md)."""
    plant = _lti2()
    keys = jax.random.split(jax.random.PRNGKey(7), 4096)

    def per_seed(d, weight, tau):
        lp = nc.Loop(plant=plant, trigger=nc.Petc(delta=d, temperature=tau), uplink=nc.Link(nc.Bernoulli(0.2)),
                     estimator=_ekf2(plant, weight=weight), controller=nc.StateFeedback([[2.0, 1.0]]),
                     downlink=nc.Link(), actuator=nc.HoldLast(), N=2, steps=60, T=0.1,
                     record=nc.Record(signals=("x",)))
        return jax.vmap(lambda k: jnp.mean(jnp.square(nc.simulate(lp, k).x)))(keys)

    hard = jax.jit(lambda d: per_seed(d, "slot", 0.0))
    d0, h = 0.05, 0.02
    diff = (np.asarray(hard(jnp.float32(d0 + h)), float) - np.asarray(hard(jnp.float32(d0 - h)), float)) / (2 * h)
    fd, se = diff.mean(), diff.std(ddof=1) / np.sqrt(diff.size)
    assert fd > 3 * se                                              # resolved: a positive derivative
    st = {w: float(jax.jit(jax.grad(lambda d: per_seed(d, w, 0.05).mean()))(jnp.float32(d0))) for w in ("slot", "stamp")}
    assert abs(st["slot"] - fd) < 3 * se, (st, fd, se)
    assert st["stamp"] < 0, (st, fd, se)


def test_batch_last_ekf_is_the_default_up_to_rounding_values_and_gradients():
    # EKF(batch_last=True) runs the sequential form's covariance arithmetic with the seed axis
    # last under vmap (ekf_batched's drop-ins): the same filter, its estimates and the loop's
    # trajectory equal to the default's up to float32 rounding, and so is the exact gradient
    # of a relaxed PETC loop's cost (through the kernels' custom_vjp) with respect to the
    # trigger's threshold and the filter's process noise
    T = 0.02

    def f(x, u, w):
        return jnp.stack([x[0] + T * x[1], x[1] + T * (-9.81 * jnp.sin(x[0]) - 0.2 * x[1] + u[0]) + w[0]])

    pend = nc.Discrete(x0=[0.3, 0.0], x0_std=[0.05, 0.05], w_std=[0.02], v_std=[0.01, 0.05, 0.05], f=f,
                       h=lambda x, v: jnp.stack([x[0], x[1], jnp.sin(x[0]) * x[1]]) + v, input_dim=1, noise_dim=1,
                       output_dim=3)
    keys = jax.random.split(jax.random.PRNGKey(5), 16)

    def run(d, q, batch_last):
        ekf = nc.EKF(pend, Q=q, R=[0.01 ** 2, 0.05 ** 2, 0.05 ** 2], mean0=[0.3, 0.0], cov0=0.01 * np.eye(2),
                     form="sequential", weight="slot", batch_last=batch_last)
        lp = nc.Loop(plant=pend, trigger=nc.Petc(delta=d, temperature=0.02, relaxed=True),
                     uplink=nc.Link(nc.Bernoulli(0.2)), estimator=ekf, controller=nc.StateFeedback([[8.0, 2.0]]),
                     downlink=nc.Link(), actuator=nc.HoldLast(), N=4, steps=120, T=T,
                     record=nc.Record(signals=("x", "xhat")))
        return jax.vmap(lambda k: nc.simulate(lp, k))(keys)

    def cost(d, q, batch_last):
        return jnp.mean(jnp.square(run(d, q, batch_last).x))

    d, q = jnp.float32(0.025), jnp.array([0.02 ** 2], jnp.float32)
    ta, tb = (jax.jit(run, static_argnums=2)(d, q, b) for b in (False, True))
    np.testing.assert_allclose(tb.xhat, ta.xhat, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(tb.x, ta.x, rtol=1e-4, atol=1e-5)
    ga, gb = (jax.jit(jax.grad(cost, argnums=(0, 1)), static_argnums=2)(d, q, b) for b in (False, True))
    assert float(ga[0]) != 0.0 and float(ga[1][0]) != 0.0
    np.testing.assert_allclose(gb[0], ga[0], rtol=1e-3)
    np.testing.assert_allclose(gb[1], ga[1], rtol=1e-3)
    # forward mode too (the kernels' derivative is a custom_jvp; a custom_vjp refused jacfwd)
    fa, fb = (jax.jit(jax.jacfwd(cost), static_argnums=2)(d, q, b) for b in (False, True))
    np.testing.assert_allclose(fb, fa, rtol=1e-3)
    np.testing.assert_allclose(fb, gb[0], rtol=1e-3)
    # the batch-last kernels are what runs: the program differs from the default's
    texts = [jax.jit(run, static_argnums=2).lower(d, q, b).as_text(debug_info=False) for b in (False, True)]
    assert texts[0] != texts[1]
