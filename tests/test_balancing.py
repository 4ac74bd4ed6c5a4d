"""Seed 001 balancing robot: plant linearisation, hold-aware gain, and the closed loops."""
import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import wifi
from jaxnc.controllers.hold_lq import dlqr, hold_lq_gain
from jaxnc.plants.balancing import Balancing
from jaxnc.schemes import balancing as bal

SHORT = 3.0          # s of simulated time for loop tests (step at 1.5 s)
PERFECT = wifi.WifiChannel(delay_pmf=np.asarray([1.0], np.float32))


def test_linearisation_is_the_jacobian_of_the_nonlinear_model():
    p = Balancing()
    with jax.enable_x64(True):
        x0, u0 = jnp.zeros(4), jnp.float64(0.0)
        Ac = np.asarray(jax.jacfwd(p.derivative, argnums=0)(x0, u0))
        Bc = np.asarray(jax.jacfwd(p.derivative, argnums=1)(x0, u0))
    A_ref, B_ref = p.continuous()
    np.testing.assert_allclose(Ac, A_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(Bc, B_ref[:, 0], rtol=1e-10, atol=1e-10)
    assert np.max(np.linalg.eigvals(A_ref).real) > 1.0          # unstable inverted pendulum


def test_exact_zoh_matches_python_control():
    p = Balancing()
    A, B, _ = p.discrete()
    Ac, Bc = p.continuous()
    sysd = control.c2d(control.ss(Ac, Bc, np.eye(4), np.zeros((4, 1))), p.Ts, method="zoh")
    np.testing.assert_allclose(A, sysd.A, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(B, sysd.B, rtol=1e-9, atol=1e-12)


def test_nonlinear_step_agrees_with_linear_model_near_upright():
    p = Balancing(w_servo=0.0, w_theta=0.0)
    A, B, _ = p.discrete()
    x = np.array([0.0, 1e-4, 0.0, 0.0])
    with jax.enable_x64(True):
        xn = np.asarray(p.dynamics(jnp.asarray(x), jnp.asarray([0.5]), jnp.zeros(2)))
    np.testing.assert_allclose(xn, A @ x + B[:, 0] * 0.5, rtol=1e-6, atol=1e-10)


def test_hold_aware_gain_is_lqr_at_theta_one():
    p = Balancing()
    A, B, _ = p.discrete()
    L, S11 = hold_lq_gain(A, B, bal.W_LQ, bal.U_LQ, 1.0)
    K, S, _ = control.dlqr(A, B, bal.W_LQ, bal.U_LQ)
    np.testing.assert_allclose(L, -K, rtol=1e-6)
    np.testing.assert_allclose(S11, S, rtol=1e-6)


def test_hold_aware_gain_satisfies_its_riccati_equation_and_differs_below_one():
    """Brute-force check on a small system: value iteration of the augmented hold problem."""
    A = np.array([[1.1, 0.2], [0.0, 0.9]])
    B = np.array([[0.0], [1.0]])
    W, U, theta = np.eye(2), np.array([[0.5]]), 0.7
    L, _ = hold_lq_gain(A, B, W, U, theta)
    # independent reference: iterate the Bellman recursion on z = [x; v] with the full S
    n = 2
    S = np.zeros((3, 3))
    for _ in range(5000):
        Fu = np.vstack([np.hstack([A, np.zeros((n, 1))]), np.zeros((1, 3))])  # z -> [Ax; 0]
        Gw = np.vstack([B, np.eye(1)])                                          # + [B; 1] w
        Wz = np.zeros((3, 3)); Wz[:n, :n] = W
        # E over w in {u (theta), v (1 - theta)}; u = Lz x minimises theta * (...)
        Tm = U + Gw.T @ S @ Gw
        Hm = Fu.T @ S @ Gw                                                       # 3 x 1
        Lz = -np.linalg.solve(Tm, Hm.T)                                          # u = Lz z
        Ev = np.zeros((1, 3)); Ev[0, n] = 1.0
        Ku = np.hstack([Lz[:, :n], np.zeros((1, 1))])
        def q(M):  # quadratic form of applying w = M z
            return Wz + Fu.T @ S @ Fu + M.T @ Tm @ M + Hm @ M + M.T @ Hm.T
        S = theta * q(Ku) + (1 - theta) * q(Ev)
    Tm = U + Gw.T @ S @ Gw
    L_ref = -np.linalg.solve(Tm, (Fu.T @ S @ Gw).T)[:, :n]
    np.testing.assert_allclose(L, L_ref, rtol=1e-6)
    K = dlqr(A, B, W, U)[0]
    assert np.max(np.abs(L + K)) > 1e-3                          # differs from LQR for theta < 1


@pytest.mark.parametrize("design", bal.DESIGNS)
def test_perfect_network_balances_and_tracks_the_step(design):
    loop = bal.balancing_loop(design, horizon_s=SHORT, t_step=1.0)
    m = jax.jit(bal.run)(loop, jax.random.PRNGKey(0), PERFECT, PERFECT)
    assert bool(m.upright)
    assert float(m.tilt_max_deg) < 10.0
    tr = jax.jit(bal.simulate)(loop, np.zeros(loop.steps, np.int32), np.zeros(loop.steps, np.int32),
                               jax.random.PRNGKey(1))
    pos = float(loop.plant.robot.r) * (float(tr.x[-1, 0]) + float(tr.x[-1, 1]))
    assert abs(pos - 0.1) < 0.02                                  # within 2 cm of the 0.1 m step after 2 s


def test_same_trace_same_run_and_designs_share_the_network():
    loop = bal.balancing_loop("model", horizon_s=1.0)
    key = jax.random.PRNGKey(3)
    sc, ca = bal.traces(key, wifi.NOMINAL, wifi.NOMINAL, loop.steps)
    f = jax.jit(bal.simulate)
    a, b = f(loop, sc, ca, key), f(loop, np.asarray(sc), np.asarray(ca), key)
    np.testing.assert_array_equal(a.x, b.x)
    sc2 = np.asarray(sc).copy(); sc2[100:300] = wifi.LOST                # a different network differs
    assert not np.array_equal(np.asarray(f(loop, sc2, ca, key).xhat), np.asarray(a.xhat))


def test_total_blackout_makes_it_fall_as_data_not_exception():
    loop = bal.balancing_loop("emulation", horizon_s=2.0)
    lost = np.full(loop.steps, wifi.LOST, np.int32)
    m = bal.metrics(loop, jax.jit(bal.simulate)(loop, lost, lost, jax.random.PRNGKey(0)))
    assert not bool(m.upright) and np.isinf(float(m.tilt_rms_deg))


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="design"):
        bal.balancing_loop("foo")
    with pytest.raises(ValueError, match="gain"):
        bal.balancing_loop(gain="bar")
    with pytest.raises(ValueError, match="theta"):
        hold_lq_gain(np.eye(1), np.eye(1), np.eye(1), np.eye(1), 0.0)
