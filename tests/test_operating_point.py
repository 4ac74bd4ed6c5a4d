"""Operating points: ``LTI.linearize`` against closed-form Jacobians, the affine ``LTI``
(``offset``, ``z_offset``) and the linear observers on it against the same loop written in
deviation coordinates, ``StateFeedback.u_ref``, and a linearised nonlinear plant estimated
without the bias a model without its operating point has."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo

T = 0.1
A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
C = np.array([[1.0, 0.0]])
K = np.array([[2.0, 1.0]])
Q, R = np.array([1e-4, 4e-4]), np.array([[2.5e-3]])


def _pendulum(x, u, w):                    # explicit Euler step of a damped pendulum, torque u
    return jnp.stack([x[0] + T * x[1], x[1] + T * (-9.81 * jnp.sin(x[0]) - 0.5 * x[1] + 2.0 * u[0]) + w[0]])


def _angle(x, v):
    return jnp.stack([jnp.sin(x[0])]) + v


def test_linearize_gives_the_closed_form_jacobians_and_constant_terms_at_a_point_that_is_not_an_equilibrium():
    plant = nc.Discrete(x0=[0.3, 0.0], w_std=0.01, v_std=0.02, f=_pendulum, h=_angle, input_dim=1, noise_dim=1,
                        output_dim=1)
    x_op, u_op = np.array([0.4, 0.3]), np.array([0.7])
    lin = nc.LTI.linearize(plant, x_op, u_op, T=T)
    A_ref = np.array([[1.0, T], [-T * 9.81 * np.cos(0.4), 1.0 - 0.5 * T]])
    B_ref, G_ref = np.array([[0.0], [2.0 * T]]), np.array([[0.0], [1.0]])
    C_ref = np.array([[np.cos(0.4), 0.0]])
    f_op = np.array([0.4 + T * 0.3, 0.3 + T * (-9.81 * np.sin(0.4) - 0.5 * 0.3 + 2.0 * 0.7)])
    np.testing.assert_allclose(lin.A, A_ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(lin.B, B_ref, atol=1e-7)
    np.testing.assert_allclose(lin.G, G_ref, atol=1e-7)
    np.testing.assert_allclose(lin.C, C_ref, rtol=1e-6)
    np.testing.assert_allclose(lin.offset, f_op - A_ref @ x_op - B_ref @ u_op, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(lin.z_offset, [np.sin(0.4) - np.cos(0.4) * 0.4], rtol=1e-5)
    # the affine model is the plant at the operating point, and to first order next to it
    w0 = jnp.zeros(1)
    np.testing.assert_allclose(lin.dynamics(jnp.asarray(x_op, jnp.float32), jnp.asarray(u_op, jnp.float32), w0),
                               f_op, rtol=1e-6)
    dx = np.array([1e-2, -2e-2])
    exact = np.asarray(_pendulum(jnp.asarray(x_op + dx), jnp.asarray(u_op), w0))
    model = np.asarray(lin.dynamics(jnp.asarray(x_op + dx, jnp.float32), jnp.asarray(u_op, jnp.float32), w0))
    assert np.abs(exact - model).max() < 1e-4 < np.abs(exact - f_op).max()      # second order, not first
    np.testing.assert_allclose(lin.w_std, [0.01]) and np.testing.assert_allclose(lin.v_std, [0.02])
    np.testing.assert_allclose(lin.x0, [0.3, 0.0])
    # gain scheduling: linearising the same plant at another point compiles nothing
    from jaxnc.cache import compile_clock
    before = compile_clock()
    other = nc.LTI.linearize(plant, [0.8, 0.0], [0.0], T=T)
    assert (compile_clock() - before).compilations == 0
    np.testing.assert_allclose(other.A[1, 0], -T * 9.81 * np.cos(0.8), rtol=1e-5)


def _loops(estimator_of, N):
    """The same loop twice: an affine plant, observer and state feedback around an equilibrium
    (x_op, u_op), and the linear one in deviation coordinates (x - x_op, u - u_op)."""
    x_op, u_op = np.array([2.0, -1.0]), np.array([0.5])
    c = (np.eye(2) - A) @ x_op - B @ u_op            # x_op = A x_op + B u_op + c: an equilibrium
    z_op = np.array([3.0])
    d = z_op - C @ x_op
    x0 = np.array([1.0, -0.5])
    common = dict(A=A, B=B, C=C, w_std=np.sqrt(Q), v_std=np.sqrt(R[0]), T=T)
    affine = nc.LTI(x0=x_op + x0, offset=c, z_offset=d, **common)
    linear = nc.LTI(x0=x0, **common)
    up = nc.Link(nc.Bernoulli(0.3), capacity=1)

    def loop(plant, est, ctrl, initial):
        return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=up, estimator=est, controller=ctrl,
                       downlink=nc.Link(), actuator=nc.HoldLast(initial=initial), N=N, T=T, steps=60 * N,
                       record=nc.Record(signals=("x", "xhat", "u", "recv_sc")))

    return (loop(affine, estimator_of(affine, x_op), nc.StateFeedback(K, x_ref=x_op, u_ref=u_op), u_op),
            loop(linear, estimator_of(linear, np.zeros(2)), nc.StateFeedback(K), [0.0]), x_op, u_op)


@pytest.mark.parametrize("N", [1, 2])
@pytest.mark.parametrize("kind", ["steady_state_kf", "luenberger", "ekf"])
def test_an_affine_loop_is_the_linear_loop_in_deviation_coordinates(kind, N):
    def est(model, mean0):
        if kind == "steady_state_kf":
            return nc.SteadyStateKF(model, Q=Q, R=R, mean0=mean0)
        if kind == "luenberger":
            return nc.Luenberger(model, L=np.array([[0.9], [1.2]]) if N == 1 else np.array([[1.0], [1.5]]), mean0=mean0)
        return nc.EKF(model, Q=Q, R=R, mean0=mean0, cov0=np.eye(2) * 0.1)

    aff, lin, x_op, u_op = _loops(est, N)
    key = jax.random.PRNGKey(7)
    ta, tl = jax.jit(nc.simulate)(aff, key), jax.jit(nc.simulate)(lin, key)
    assert 0.5 < float(np.mean(np.asarray(tl.recv_sc))) < 0.9           # intermittent measurements
    np.testing.assert_allclose(np.asarray(ta.xhat) - x_op, np.asarray(tl.xhat), atol=2e-5)
    np.testing.assert_allclose(np.asarray(ta.x) - x_op, np.asarray(tl.x), atol=2e-5)
    np.testing.assert_allclose(np.asarray(ta.u) - u_op, np.asarray(tl.u), atol=2e-5)
    assert np.abs(np.asarray(tl.xhat)).max() > 0.3                       # the loop does move


# Johansson's quadruple tank (IEEE TCST 2000), minimum-phase point: levels in cm, pumps in V
_AREA, _HOLE, _GRAV = np.array([28.0, 32.0, 28.0, 32.0]), np.array([0.071, 0.057, 0.071, 0.057]), 981.0


def _tanks(x, u, w):
    q = _HOLE * jnp.sqrt(2 * _GRAV * jnp.maximum(x, 0.0))
    k1, k2, g1, g2 = 3.33, 3.35, 0.70, 0.60
    return jnp.stack([(-q[0] + q[2] + g1 * k1 * u[0]) / _AREA[0] + w[0], (-q[1] + q[3] + g2 * k2 * u[1]) / _AREA[1] + w[1],
                      (-q[2] + (1 - g2) * k2 * u[1]) / _AREA[2], (-q[3] + (1 - g1) * k1 * u[0]) / _AREA[3]])


def test_a_linearised_nonlinear_plant_is_estimated_without_the_bias_of_a_model_without_its_operating_point():
    """A steady-state KF on ``LTI.linearize`` of the tanks (an operating point rounded as
    published, not an exact equilibrium) tracks the true levels within a few hundredths of a cm
    on average; the same matrices without the constant terms are biased by about a cm."""
    x_op, u_op = np.array([12.4, 12.7, 1.8, 1.4]), np.array([3.0, 3.0])
    plant = nc.Continuous(x0=x_op + np.array([0.5, -0.3, 0.2, 0.1]), w_std=[0.02, 0.02], v_std=[0.01, 0.01], f=_tanks,
                          h=lambda x, v: 0.5 * x[:2] + v, input_dim=2, noise_dim=2, output_dim=2, T=0.5, substeps=2)
    lin = nc.LTI.linearize(plant, x_op, u_op)
    bare = nc.LTI(A=lin.A, B=lin.B, C=lin.C, G=lin.G, T=0.5, w_std=lin.w_std, v_std=lin.v_std)
    bias = {}
    for name, model in (("affine", lin), ("bare", bare)):
        loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(nc.Bernoulli(0.2)),
                       estimator=nc.SteadyStateKF(model, Q=np.array([1e-4, 1e-4]), R=np.eye(2) * 1e-4, mean0=x_op,
                                                  inputs="applied"),
                       controller=nc.StateFeedback(np.zeros((2, 4)), x_ref=x_op, u_ref=u_op), downlink=nc.Link(),
                       actuator=nc.HoldLast(initial=u_op), N=2, T=0.5, steps=400, record=nc.Record(signals=("x", "xhat")))
        tr = jax.jit(jax.vmap(lambda k: nc.simulate(loop, k)))(montecarlo.seed_keys(0, 32))
        err = np.asarray(tr.xhat)[:, 20:] - np.asarray(tr.x)[:, ::2][:, 20:]
        bias[name] = np.abs(err.mean(axis=(0, 1)))
    assert bias["affine"].max() < 0.05, bias
    assert bias["bare"].min() > 0.3, bias


def test_state_feedback_u_ref_is_the_action_at_x_ref():
    sf = nc.StateFeedback(K, x_ref=[1.0, 2.0], u_ref=[0.25], u_min=-1.0, u_max=1.0)
    np.testing.assert_allclose(sf.action(jnp.asarray([1.0, 2.0])), [0.25])
    np.testing.assert_allclose(sf.action(jnp.asarray([1.1, 2.0])), [0.25 - 0.2], rtol=1e-6)
    np.testing.assert_allclose(sf.action(jnp.asarray([3.0, 2.0])), [-1.0])            # clipped after u_ref


@pytest.mark.parametrize("N", [1, 3])
def test_slow_system_with_a_held_action_sums_the_per_period_inputs(N):
    A_N, B_N = nc.slow_system(A, B, N)
    A_h, B_h = nc.slow_system(A, B, N, hold=True)
    np.testing.assert_allclose(A_h, A_N)
    np.testing.assert_allclose(B_h, np.asarray(B_N) @ np.tile(np.eye(1), (N, 1)), rtol=1e-6)
    x, u = np.array([0.3, -0.2]), np.array([0.7])        # N steps of the fast model with u held
    for _ in range(N):
        x = A @ x + B @ u
    np.testing.assert_allclose(np.asarray(A_h) @ np.array([0.3, -0.2]) + np.asarray(B_h) @ u, x, rtol=1e-6)
