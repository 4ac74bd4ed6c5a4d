"""IntegralFeedback (state feedback with integral action): python-control's LQI law on a
noise-free loop against a float64 NumPy reference, no steady-state error under a constant
load where StateFeedback keeps one, conditional anti-windup, a reference, bad inputs."""
import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import references as refs

A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
C_INT = np.array([[1.0, 0.0]])
LOAD = np.array([0.002, -0.01])              # a constant disturbance x+ = A x + B u + LOAD
KK, _, _ = control.dlqr(A, B, np.diag([1.0, 0.1, 0.5]), np.array([[0.1]]), integral_action=C_INT)
K, KI = KK[:, :2], KK[:, 2:]


def _loop(controller, steps=300, load=LOAD, N=1):
    plant = nc.LTI(A=A, B=B, C=np.eye(2), x0=[0.5, 0.0], offset=load, T=0.1)
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=controller, downlink=nc.Link(), actuator=nc.HoldLast(), N=N, T=0.1, steps=steps,
                   record=nc.Record(signals=("x", "u")))


def _reference_run(steps, r, u_min=-np.inf, u_max=np.inf, anti_windup=True):
    """The LQI law in float64 NumPy (u = -K x - Ki z, z+ = z + C_int x - r)."""
    x, z, xs, us = np.array([0.5, 0.0]), np.zeros(1), [], []
    for k in range(steps):
        v = -K @ x - KI @ z
        u = np.clip(v, u_min, u_max)
        xs.append(x), us.append(u)
        if not (anti_windup and np.any(u != v)):
            z = z + C_INT @ x - r(k)
        x = A @ x + B @ u + LOAD
    return np.array(xs), np.array(us)


def test_the_law_is_python_controls_lqi_and_tracks_a_step_under_a_constant_load():
    step = refs.Step(amplitude=0.3, time=10.0)
    tr = jax.jit(nc.simulate)(_loop(nc.IntegralFeedback(K, KI, C_INT, reference=step)), jax.random.PRNGKey(0))
    xs, us = _reference_run(300, lambda k: 0.3 if k * 0.1 >= 10.0 else 0.0)
    np.testing.assert_allclose(np.asarray(tr.x), xs, atol=2e-5)
    np.testing.assert_allclose(np.asarray(tr.u), us, atol=2e-4)
    assert abs(xs[-1, 0] - 0.3) < 1e-3 and abs(xs[99, 0]) < 1e-2          # settled at each setpoint


def test_integral_action_removes_the_steady_state_error_state_feedback_keeps():
    li = jax.jit(nc.simulate)(_loop(nc.IntegralFeedback(K, KI, C_INT)), jax.random.PRNGKey(0))
    sf = jax.jit(nc.simulate)(_loop(nc.StateFeedback(K)), jax.random.PRNGKey(0))
    x_ss = np.linalg.solve(np.eye(2) - A + B @ K, LOAD)    # state feedback's equilibrium under the load
    assert abs(x_ss[0]) > 1e-3
    np.testing.assert_allclose(np.asarray(sf.x[-1]), x_ss, rtol=1e-3)
    assert abs(float(li.x[-1, 0])) < 1e-2 * abs(x_ss[0])


def test_conditional_anti_windup_stops_integrating_while_saturated():
    lim = dict(u_min=-0.5, u_max=0.5)
    for aw in ("conditional", "none"):
        tr = jax.jit(nc.simulate)(_loop(nc.IntegralFeedback(K, KI, C_INT, anti_windup=aw, **lim)),
                                  jax.random.PRNGKey(0))
        xs, us = _reference_run(300, lambda k: 0.0, anti_windup=aw == "conditional", **lim)
        np.testing.assert_allclose(np.asarray(tr.x), xs, atol=5e-5)
        assert np.isclose(us, 0.5).any() or np.isclose(us, -0.5).any()        # it did saturate
    a = _reference_run(300, lambda k: 0.0, anti_windup=True, **lim)[0]
    b = _reference_run(300, lambda k: 0.0, anti_windup=False, **lim)[0]
    assert np.abs(a[:, 0]).max() <= np.abs(b[:, 0]).max()


def test_operating_point_and_gradient():
    """x_ref and u_ref shift the law; the gradient in Ki is finite and equals float64
    differences of the NumPy law."""
    sh = nc.IntegralFeedback(K, KI, C_INT, x_ref=[1.0, 0.0], u_ref=[0.2])
    st = sh.init(None)
    _, pkt, send = sh.step(st, jnp.asarray([1.0, 0.0]), jnp.float32(1), jnp.int32(0), nc.Context(1, 10, 0.1, 2, 1, 2))
    np.testing.assert_allclose(pkt.data[0], [0.2]) and np.testing.assert_allclose(send, 1.0)

    def cost(ki):
        tr = nc.simulate(_loop(nc.IntegralFeedback(K, ki, C_INT), steps=100), jax.random.PRNGKey(0))
        return jnp.mean(tr.x[:, 0] ** 2)

    g = float(jax.jit(jax.grad(cost))(jnp.asarray(KI, jnp.float32))[0, 0])

    def ref(ki, steps=100):
        x, z, tot = np.array([0.5, 0.0]), np.zeros(1), 0.0
        for _ in range(steps):
            tot += x[0] ** 2
            u = -K @ x - ki @ z
            z = z + C_INT @ x
            x = A @ x + B @ u + LOAD
        return tot / steps

    eps = 1e-6 * max(1.0, abs(KI[0, 0]))
    fd = (ref(KI + np.array([[eps]])) - ref(KI - np.array([[eps]]))) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=2e-3)


@pytest.mark.parametrize("build, fragment", [
    (lambda: nc.IntegralFeedback(K, np.ones((1, 2)), C_INT), "IntegralFeedback.Ki must be 1x1"),
    (lambda: nc.IntegralFeedback(K, KI, np.ones((1, 3))), "IntegralFeedback.C_int must have 2 columns"),
    (lambda: nc.IntegralFeedback(K, KI, C_INT, anti_windup="clamp"), "IntegralFeedback.anti_windup must be one of"),
    (lambda: nc.IntegralFeedback(K, KI, C_INT, reference=refs.Step(amplitude=[1.0, 2.0])),
     "IntegralFeedback.reference must have 1 channel"),
    (lambda: nc.IntegralFeedback(K, None, C_INT), "IntegralFeedback.Ki must be an integral gain matrix"),
    (lambda: nc.IntegralFeedback(K, KI, C_INT, u_min=1.0, u_max=0.0), "IntegralFeedback.u_min must be <= u_max"),
])
def test_bad_integral_feedback_names_the_field(build, fragment):
    with pytest.raises(ValueError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        build()
