"""jaxnc.loop.PID against the z-domain closed loop (float64), python-control's simulation of
the same loop, hand-computed anti-windup sequences, and its hold on stale instants."""
import dataclasses

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal
from jax.test_util import check_grads

from jaxnc import loop as nc
from jaxnc import references as refs

A_P, B_P, H = 0.9, 0.2, 0.1       # first-order plant x+ = a x + b u at period h


def _ctx(N=1, T=H):
    return nc.Context(N=N, steps=10, T=T, state_dim=1, input_dim=1, output_dim=1)


def _closed_loop(pid, r, x0=0.0):
    """y_k of x+ = a x + b u with u_k = PID(y_k, r_k), every step computed (float64)."""
    def body(c, rk):
        x, s = c
        s, u = nc.pid_update(pid, s, x[None], rk[None], H)
        return (A_P * x + B_P * u[0], s), x
    z = jnp.zeros((1,), r.dtype)
    s0 = nc.PIDState(z, z, z, z, jnp.zeros((), r.dtype), jnp.zeros((), jnp.int32))
    return jax.lax.scan(body, (jnp.asarray(x0, r.dtype), s0), r)[1]


def test_pi_with_setpoint_weight_equals_the_z_domain_closed_loop_float64():
    Kp, Ki, b = 1.5, 2.0, 0.4
    with jax.enable_x64(True):
        f64 = lambda v: np.asarray([v], np.float64)
        pid = nc.PID(Kp=f64(Kp), Ki=f64(Ki), b=f64(b), anti_windup="none")
        r = jnp.ones(60, jnp.float64)
        y = np.asarray(jax.jit(_closed_loop)(pid, r))
    # Y (z - a)(z - 1) = b_p [(Kp b (z - 1) + h Ki) R - (Kp (z - 1) + h Ki) Y]
    num = [0.0, B_P * Kp * b, B_P * (H * Ki - Kp * b)]
    den = [1.0, B_P * Kp - A_P - 1.0, A_P - B_P * Kp + B_P * H * Ki]
    expected = scipy.signal.lfilter(num, den, np.ones(60))
    np.testing.assert_allclose(y, expected, rtol=1e-12, atol=1e-13)
    assert abs(y[-1] - 1.0) < 0.05            # integral action: no steady-state error


def _controller_tfs(Kp, Ki, Kd, Tf, b, c):
    z = control.tf([1, 0], [1], dt=H)
    i = H * Ki / (z - 1)
    d = Kd * (z - 1) / ((Tf + H) * z - Tf)
    return Kp + i + d, Kp * b + i + c * d          # u = Cr r - Cy y


def test_pid_loop_equals_python_control_forced_response():
    Kp, Ki, Kd, Tf, b, c = 1.2, 1.5, 0.05, 0.02, 0.7, 0.3
    K = 80
    ref = refs.Step(1.0, time=5 * H)              # r = 0 before: zero initial conditions in both
    loop = nc.Loop(plant=nc.LTI(A=[[A_P]], B=[[B_P]], C=[[1.0]], x0=[0.0]), trigger=nc.Periodic(),
                   uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.PID(Kp=Kp, Ki=Ki, Kd=Kd, Tf=Tf, b=b, c=c, reference=ref, anti_windup="none"),
                   downlink=nc.Link(), actuator=nc.HoldLast(), T=H, steps=K)
    x = np.asarray(jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0)).x[:, 0])
    Cy, Cr = _controller_tfs(Kp, Ki, Kd, Tf, b, c)
    P = control.tf([B_P], [1, -A_P], dt=H)
    r = np.asarray(refs.evaluate(ref, K, H))[:, 0]
    y = control.forced_response(control.feedback(P, Cy) * Cr, timepts=H * np.arange(K), inputs=r).outputs
    np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)
    assert np.ptp(y) > 0.5


def _drive(pid, ys, fresh):
    ctx = _ctx(T=1.0)

    def body(s, inp):
        k, y, f = inp
        s, pkt, send = pid.step(s, y[None], f, k, ctx)
        return s, (pkt.data[0, 0], s.integral[0], send)
    ks = jnp.arange(len(ys), dtype=jnp.int32)
    return jax.jit(lambda: jax.lax.scan(body, pid.init(ctx), (ks, jnp.asarray(ys, jnp.float32),
                                                              jnp.asarray(fresh, jnp.float32)))[1])()


# Kp = Ki = 1, h = 1, limits +-1, r = 2; y = 0 for four instants (e = 2), then y = 3 (e = -1)
_YS = [0, 0, 0, 0, 3, 3, 3]
_HAND = {   # (u_k, I_{k+1}) by hand from the module docstring's equations
    "none": ([1, 1, 1, 1, 1, 1, 1], [2, 4, 6, 8, 7, 6, 5]),
    "clamping": ([1, 1, 1, 1, -1, -1, -1], [0, 0, 0, 0, -1, -1, -1]),
    "back_calculation": ([1, 1, 1, 1, 1, 0.40625, -0.59375],
                         [1.5, 2.25, 2.625, 2.8125, 1.40625, 0.40625, -0.59375]),   # Kb = 0.5
}


@pytest.mark.parametrize("anti_windup", sorted(_HAND))
def test_anti_windup_follows_the_hand_computed_sequence(anti_windup):
    pid = nc.PID(Kp=1.0, Ki=1.0, u_min=-1.0, u_max=1.0, Kb=0.5, reference=refs.Step(2.0), anti_windup=anti_windup)
    u, integral, send = _drive(pid, _YS, np.ones(len(_YS)))
    np.testing.assert_array_equal(u, _HAND[anti_windup][0])
    np.testing.assert_array_equal(integral, _HAND[anti_windup][1])
    assert np.all(np.asarray(send) == 1)


def test_no_measurement_holds_the_output_and_the_state():
    pid = nc.PID(Kp=1.0, Ki=0.5, Kd=0.2, Tf=0.5, reference=refs.Step(1.0))
    fresh = [1, 0, 0, 1, 0]
    ys = [0.0, 5.0, -5.0, 0.5, 9.0]                # stale values must not be used
    u, integral, send = _drive(pid, ys, fresh)
    # by the equations: a computation at k = 0 (h_0 = h = 1), the next at k = 3 over h_3 = 3
    s1, u0 = nc.pid_update(pid, pid.init(_ctx(T=1.0)), jnp.zeros(1), jnp.ones(1), 1.0)
    s2, u3 = nc.pid_update(pid, s1, jnp.full(1, 0.5), jnp.ones(1), 3.0)
    # u0 = Kp e = 1, I = 0.5; then D = 0.2 (-0.5) / 3.5, u3 = 0.5 + 0.5 + D, I = 0.5 + 3 * 0.5 * 0.5
    np.testing.assert_allclose([u0[0], u3[0], s2.integral[0]], [1.0, 1.0 - 0.1 / 3.5, 1.25], rtol=1e-6)
    np.testing.assert_array_equal(send, fresh)
    np.testing.assert_allclose(u, [u0[0]] * 3 + [u3[0]] * 2, rtol=1e-6)
    np.testing.assert_allclose(integral, [s1.integral[0]] * 3 + [s2.integral[0]] * 2, rtol=1e-6)
    u2, _, send2 = _drive(nc.PID(Kp=1.0, reference=refs.Step(1.0), hold=False), ys, fresh)
    np.testing.assert_allclose(u2, 1.0 - np.asarray(ys), rtol=1e-7)      # computes on whatever it is given
    assert np.all(np.asarray(send2) == 1)


def test_two_channels_with_per_channel_gains_and_reference():
    pid = nc.PID(Kp=[1.0, 2.0], reference=refs.Step([1.0, -1.0]), index=(2, 0))
    ctx = nc.Context(N=2, steps=10, T=0.5, state_dim=3, input_dim=2, output_dim=3)
    _, pkt, _ = pid.step(pid.init(ctx), jnp.asarray([0.5, 7.0, 0.25]), jnp.float32(1), jnp.int32(3), ctx)
    np.testing.assert_allclose(pkt.data, [[0.75, -3.0]])
    assert int(pkt.stamp) == 6


def test_gains_are_differentiable_leaves():
    with jax.enable_x64(True):
        r = jnp.ones(30, jnp.float64)

        def f(kp, ki, kd, tf, ub):
            pid = nc.PID(Kp=kp, Ki=ki, Kd=kd, Tf=tf, b=jnp.ones(1), c=jnp.ones(1), Kb=jnp.ones(1), u_bias=ub,
                         anti_windup="none")
            return jnp.sum((_closed_loop(pid, r) - 1.0) ** 2)
        check_grads(f, tuple(jnp.asarray([v], jnp.float64) for v in (1.0, 0.8, 0.05, 0.1, 0.3)), order=1,
                    modes=("rev",), eps=1e-5)


@pytest.mark.parametrize("kwargs, field", [
    (dict(Tf=-0.1), "PID.Tf"), (dict(Kp=np.nan), "PID.Kp"), (dict(u_min=1.0, u_max=0.0), "PID.u_min"),
    (dict(index=-1), "PID.index"), (dict(index=(0, 0)), "PID.index"), (dict(anti_windup="clip"), "PID.anti_windup"),
    (dict(reference=1.0), "PID.reference"), (dict(Kp=[1.0, 2.0]), "PID.Kp"), (dict(Kb=-1.0), "PID.Kb"),
    (dict(reference=refs.Step([1.0, 2.0, 3.0]), index=(0, 1)), "PID.reference"),
    (dict(u_bias=np.inf), "PID.u_bias"), (dict(u_bias=[1.0, 2.0]), "PID.u_bias"),
])
def test_bad_parameters_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        nc.PID(**kwargs)


def test_tracking_metrics_of_the_pid_loop_match_python_control_step_info():
    K = 120
    ref = refs.Step(1.0)
    # gains chosen so that no sample lies on a rise-time threshold (Kp = 3, Ki = 6 puts y_2 at 0.9 exactly,
    # where float32 and float64 round to opposite sides)
    loop = nc.Loop(plant=nc.LTI(A=[[A_P]], B=[[B_P]], C=[[1.0]], x0=[0.0]), trigger=nc.Periodic(),
                   uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.PID(Kp=2.5, Ki=5.0, reference=ref, anti_windup="none"),
                   downlink=nc.Link(), actuator=nc.HoldLast(), T=H, steps=K)
    tracking = nc.Tracking(ref, index=0, window=10)
    from jaxnc import montecarlo
    m, tm = montecarlo.run_batched(nc.run_tracking, montecarlo.seed_keys(0, 4), args=(loop, tracking),
                                   progress=False, chunk_size=4)
    y = np.asarray(jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0)).x[:, 0], np.float64)
    info = control.step_info(y, timepts=H * np.arange(K), yfinal=1.0)
    assert info["Overshoot"] > 5                                     # an underdamped response
    np.testing.assert_allclose(tm.overshoot[:, 0], info["Overshoot"], rtol=1e-4)
    np.testing.assert_allclose(tm.settling_time[:, 0], info["SettlingTime"], rtol=1e-6)
    np.testing.assert_allclose(tm.rise_time[:, 0], info["RiseTime"], rtol=1e-6)
    np.testing.assert_allclose(tm.ise[:, 0], np.sum((1.0 - y) ** 2) * H, rtol=1e-5)
    np.testing.assert_allclose(tm.steady_state_error[:, 0], np.mean(1.0 - y[-10:]), atol=1e-6)
    with pytest.raises(ValueError, match="Tracking.index"):
        nc.Tracking(ref, index=(0, 0))


def _pid_loop(Kp):
    plant = nc.LTI(A=[[A_P]], B=[[B_P]], C=[[1.0]], x0=[0.0], w_std=0.05, v_std=0.02)
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(nc.Bernoulli(0.3)), estimator=nc.Passthrough(),
                   controller=nc.PID(Kp=Kp, Ki=1.0, Kd=0.05, Tf=0.05, u_min=-3.0, u_max=3.0,
                                     reference=refs.Step(1.0)),
                   downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0], R=[0.01]),
                   T=H, steps=60)


def test_the_loop_cost_is_differentiable_in_a_gain_through_the_hold():
    """d cost / d Kp through a lossy loop (the hold blends on fresh) equals central
    differences of the same seeds' cost."""
    keys = jax.random.split(jax.random.PRNGKey(2), 8)

    def mean_cost(kp):
        loop = _pid_loop(jnp.asarray([1.0], jnp.float32) * kp)
        return jnp.mean(jax.vmap(lambda k: nc.run(loop, k).cost_raw)(keys))
    g = float(jax.jit(jax.grad(mean_cost))(jnp.float32(1.5)))
    f = jax.jit(mean_cost)
    fd = (float(f(jnp.float32(1.5 + 1e-2))) - float(f(jnp.float32(1.5 - 1e-2)))) / 2e-2
    assert g != 0 and abs(g - fd) < 2e-2 * abs(fd) + 1e-4, (g, fd)


def test_a_pid_with_more_channels_than_plant_inputs_is_refused_by_the_loop():
    with pytest.raises(ValueError, match="Loop.controller"):
        nc.Loop(plant=nc.LTI(A=np.eye(2) * 0.9, B=[[1.0], [0.0]], C=np.eye(2)), trigger=nc.Periodic(),
                uplink=nc.Link(), estimator=nc.Passthrough(), controller=nc.PID(Kp=1.0, index=(0, 1)),
                downlink=nc.Link(), actuator=nc.HoldLast())


def _pid_reference(z, fresh, r, h, *, Kp, Ki, Kd, Tf, b, c, u_min, u_max, Kb, anti_windup, u_bias=0.0):
    """The module docstring's equations in plain float64 Python, one slow instant at a time:
    the output u_k from the measurements z_k, arrivals fresh_k and reference r_k (hold=True)."""
    I = D = 0.0
    ed_prev, last, u, us = None, None, min(max(u_bias, u_min), u_max), []
    for k in range(len(z)):
        if fresh[k]:
            hk = h if last is None else (k - last) * h
            e, ep, ed = r[k] - z[k], b * r[k] - z[k], c * r[k] - z[k]
            D = (Tf * D + Kd * (ed - (ed if ed_prev is None else ed_prev))) / (Tf + hk)
            v = u_bias + Kp * ep + I + D
            u = min(max(v, u_min), u_max)
            g = Ki * e
            if anti_windup == "clamping" and ((v > u_max and g > 0) or (v < u_min and g < 0)):
                g = 0.0
            elif anti_windup == "back_calculation":
                g += Kb * (u - v)
            I, ed_prev, last = I + hk * g, ed, k
        us.append(u)
    return np.asarray(us)


@pytest.mark.parametrize("anti_windup, u_bias", [("none", 0.0), ("clamping", 0.0), ("back_calculation", 0.0),
                                                  ("clamping", 12.0), ("back_calculation", -6.0)])
def test_a_float64_pid_in_a_lossy_saturated_loop_equals_the_documented_equations(anti_windup, u_bias):
    """A heated chamber 0.8 / (20 s + 1) (exact ZOH, T = 0.5 s) under a PID with filtered
    derivative, setpoint weights, heater limits 0..45 and a 30-degree step at 5 s, over an
    uplink losing 40 % at N = 2 (hold: h_k spans the silent periods): the actions equal the
    docstring's equations in float64 driven by the run's own measurements and arrivals, to
    the float32 rounding of the applied action (u_max eps32), and the plant follows them. A
    PID of float64 gains used to be refused by the Loop under x64 (its state was float32
    zeros, its computations float64)."""
    T, N, steps = 0.5, 2, 160
    a = float(np.exp(-T / 20.0))
    gains = dict(Kp=5.0, Ki=0.3, Kd=1.0, Tf=1.0, b=0.7, c=0.3, u_min=0.0, u_max=45.0, Kb=0.5, u_bias=u_bias)
    with jax.enable_x64(True):
        sp = refs.Step(np.array([30.0]), time=np.array([5.0]))
        pid = nc.PID(**{k: np.array([v]) for k, v in gains.items()}, reference=sp, anti_windup=anti_windup)
        loop = nc.Loop(plant=nc.LTI(A=[[a]], B=[[0.8 * (1.0 - a)]], C=[[1.0]], x0=[0.0], T=T), trigger=nc.Periodic(),
                       uplink=nc.Link(nc.Bernoulli(0.4)), estimator=nc.Passthrough(), controller=pid,
                       downlink=nc.Link(), actuator=nc.HoldLast(initial=min(max(u_bias, 0.0), 45.0)), T=T, N=N,
                       steps=steps)
        tr = jax.device_get(jax.jit(nc.simulate)(loop, jax.random.PRNGKey(3)))
        r = np.asarray(refs.evaluate(sp, steps, T))[::N, 0]
    fresh = np.asarray(tr.recv_sc) > 0.5
    assert 0.3 < fresh.mean() < 0.9
    u = _pid_reference(np.asarray(tr.z[:, 0], np.float64), fresh, r, N * T, anti_windup=anti_windup, **gains)
    assert u.max() == 45.0 and 0.0 < u[-1] < 45.0                 # saturated, then in the linear range
    np.testing.assert_allclose(np.asarray(tr.u)[::N, 0], u, rtol=0, atol=45.0 * np.finfo(np.float32).eps)
    x, xs = 0.0, []
    for uk in np.repeat(u, N):
        xs.append(x)
        x = a * x + 0.8 * (1.0 - a) * uk
    np.testing.assert_allclose(np.asarray(tr.x)[:, 0], xs, rtol=1e-5, atol=1e-4)


def test_anti_windup_removes_the_overshoot_of_a_saturated_step():
    """The same chamber, every measurement: without anti-windup the integral winds up while
    the heater is at 45 and the temperature overshoots the 30-degree step by 12 %; clamping
    and back-calculation keep it below 0.5 % (python-control's step_info overshoot, through
    Tracking)."""
    T, steps = 0.5, 400
    a = float(np.exp(-T / 20.0))
    sp = refs.Step(30.0, time=5.0)
    overshoot = {}
    for aw in ("none", "clamping", "back_calculation"):
        pid = nc.PID(Kp=5.0, Ki=0.3, Kd=1.0, Tf=1.0, b=0.7, c=0.3, u_min=0.0, u_max=45.0, Kb=0.5, reference=sp,
                     anti_windup=aw)
        loop = nc.Loop(plant=nc.LTI(A=[[a]], B=[[0.8 * (1.0 - a)]], C=[[1.0]], x0=[0.0], T=T), trigger=nc.Periodic(),
                       uplink=nc.Link(), estimator=nc.Passthrough(), controller=pid, downlink=nc.Link(),
                       actuator=nc.HoldLast(), T=T, steps=steps)
        tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
        y = np.asarray(tr.x[:, 0], np.float64)
        info = control.step_info(y[10:], timepts=T * np.arange(steps - 10), yfinal=30.0)
        tm = nc.Tracking(sp, index=0).metrics(tr.x, T)
        np.testing.assert_allclose(float(tm.overshoot[0]), info["Overshoot"], rtol=1e-4, atol=1e-4)
        overshoot[aw] = info["Overshoot"]
    assert overshoot["none"] > 10.0 and overshoot["clamping"] < 0.5 and overshoot["back_calculation"] < 0.5, overshoot


def test_back_calculation_adds_no_integral_to_a_pd():
    """A PD (Ki = 0) saturated by a large step: back-calculation has no integrator to unwind,
    so the run reaches the proportional steady state x = 0.8 Kp r / (1 + 0.8 Kp) = 24, as
    without anti-windup. It used to integrate Kb (u - v) while saturated (I = -79) and settle
    at 11.3 with that bias for ever."""
    T, steps = 0.5, 200
    a = float(np.exp(-T / 20.0))
    sp = refs.Step(30.0, time=5.0)
    final = {}
    for aw in ("none", "back_calculation"):
        pid = nc.PID(Kp=5.0, Ki=0.0, Kd=1.0, Tf=1.0, u_min=0.0, u_max=45.0, Kb=0.5, reference=sp, anti_windup=aw)
        loop = nc.Loop(plant=nc.LTI(A=[[a]], B=[[0.8 * (1.0 - a)]], C=[[1.0]], x0=[0.0], T=T), trigger=nc.Periodic(),
                       uplink=nc.Link(), estimator=nc.Passthrough(), controller=pid, downlink=nc.Link(),
                       actuator=nc.HoldLast(), T=T, steps=steps)
        tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
        assert float(jnp.max(tr.u)) == 45.0                          # it saturated
        final[aw] = float(tr.x[-1, 0])
    np.testing.assert_allclose(final["back_calculation"], 24.0, rtol=1e-4)
    np.testing.assert_allclose(final["none"], 24.0, rtol=1e-4)


def test_the_exact_gradient_of_a_held_pid_over_a_lossy_link_equals_float64_differences_of_a_numpy_loop():
    """A PID (hold=True, filtered derivative) on a lightly damped 2-state plant over a 20 %-lossy
    uplink: the gradient of the mean cost over 8 seeds in Kp, Ki, Kd, Tf and the plant's noise
    stds equals central differences in float64 of the docstring's equations written in NumPy on
    the run's draws; the first computation integrates over h whatever was lost before it (a seed
    here loses its first measurement)."""
    from jaxnc import montecarlo
    T, steps, seeds = 0.05, 40, 8
    plant = nc.LTI.from_control(control.ss([[0, 1], [-4, -0.6]], [[0], [1]], [[1, 0]], [[0]]), T, x0=[0.5, 0.0],
                                w_std=[0.02, 0.05], v_std=[0.01])
    th0 = np.array([3.0, 1.0, 0.4, 0.1, 0.02, 0.05, 0.01])            # Kp, Ki, Kd, Tf, w_std, v_std

    def loop_of(th):
        pid = nc.PID(Kp=th[0], Ki=th[1], Kd=th[2], Tf=th[3], reference=refs.Step(1.0), u_min=-50.0, u_max=50.0)
        return nc.Loop(plant=dataclasses.replace(plant, w_std=th[4:6], v_std=th[6:7]), trigger=nc.Periodic(1),
                       uplink=nc.Link(nc.Bernoulli(0.2)), estimator=nc.Passthrough(), controller=pid,
                       downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 0.0], R=[0.01]),
                       T=T, steps=steps)

    keys = montecarlo.seed_keys(0, seeds)
    th32 = jnp.asarray(th0, jnp.float32)
    mean_cost = lambda th: jax.vmap(lambda k: nc.run(loop_of(th), k).cost_raw)(keys).mean()
    grad = np.asarray(jax.jit(jax.grad(mean_cost))(th32))
    draws = jax.vmap(lambda k: nc.draw(loop_of(th32), k))(keys)
    wn = np.asarray(draws.w, np.float64)[:, :, 0, :] / th0[4:6]
    vn = np.asarray(draws.v, np.float64)[:, :, 0] / th0[6]
    arrived = np.asarray(draws.uplink.delay) >= 0
    assert not arrived[:, 0].all()
    A, B = np.asarray(plant.A, np.float64), np.asarray(plant.B, np.float64)[:, 0]

    def cost(th):
        Kp, Ki, Kd, Tf, ws, vs = th[0], th[1], th[2], th[3], th[4:6], th[6]
        total = 0.0
        for s in range(seeds):
            x, u, I, D, e_prev, elapsed = np.array([0.5, 0.0]), 0.0, 0.0, 0.0, None, 0.0
            for k in range(steps):
                z = x[0] + vs * vn[s, k]
                elapsed += T
                if arrived[s, k]:
                    e = 1.0 - z
                    h = T if e_prev is None else elapsed
                    D = (Tf * D + Kd * (e - (e if e_prev is None else e_prev))) / (Tf + h)
                    u = float(np.clip(Kp * e + I + D, -50.0, 50.0))
                    I, e_prev, elapsed = I + h * Ki * e, e, 0.0
                total += x[0] ** 2 + 0.01 * u ** 2
                x = A @ x + B * u + ws * wn[s, k]
        return total / (steps * seeds)

    fd = np.array([(cost(th0 + e) - cost(th0 - e)) / (2 * e[i]) for i, e in enumerate(np.diag(1e-5 * th0))])
    np.testing.assert_allclose(grad, fd, rtol=2e-5)       # float32 gradient; measured within 5e-7 at 60 steps


@pytest.mark.parametrize("u_bias", [0.0, 4.905, 9.81])
def test_a_pd_with_a_bias_holds_a_lift_at_the_closed_form_steady_state(u_bias):
    """A lift z'' = u - g (a quadcopter's altitude, exact ZOH at T = 0.01 s, no noise) under a
    PD (Kp = 4, Kd = 3) with the bias u_b, every measurement, a 1 m step: it settles where
    Kp (r - z) + u_b = g, z = r - (g - u_b) / Kp: 1 m with the hover thrust as the bias,
    1 - 9.81 / 4 = -1.45 m without one (it falls below the setpoint: a PD has no integrator).
    Before the first computation the packet carries the bias (the lift hovers from t = 0)."""
    g, T, Kp = 9.81, 0.01, 4.0
    lift = nc.Discrete(x0=[0.0, 0.0], w_std=[0.0], v_std=[0.0], f=lambda x, u, w: jnp.stack([x[0] + T * x[1] + 0.5 * T * T * (u[0] - g),
                                                                  x[1] + T * (u[0] - g)]),
                       h=lambda x, v: x[:1], input_dim=1, noise_dim=1, output_dim=1)
    pid = nc.PID(Kp=Kp, Kd=3.0, u_bias=u_bias, reference=refs.Step(1.0))
    assert float(pid.init(_ctx()).u[0]) == np.float32(u_bias)
    loop = nc.Loop(plant=lift, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(), controller=pid,
                   downlink=nc.Link(), actuator=nc.HoldLast(), T=T, steps=3000)
    z = np.asarray(jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0)).x[:, 0])
    np.testing.assert_allclose(z[-1], 1.0 - (g - u_bias) / Kp, atol=2e-4)
    assert np.ptp(z[-200:]) < 1e-4                                  # settled
