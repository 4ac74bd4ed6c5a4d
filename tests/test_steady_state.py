"""Steady-state observers: dlqe against python-control and scipy's DARE, the Luenberger
step against its closed-form error dynamics (float64)."""
import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from jax.test_util import check_grads

from jaxnc.estimators import dlqe, ekf_predict, ekf_update, Gaussian, luenberger_step


def _systems():
    rng = np.random.default_rng(3)
    A1 = np.array([[1.0, 0.1], [0.0, 1.0]])                  # double integrator (unstable, observable)
    yield "double_integrator", A1, np.array([[0.005], [0.1]]), np.array([[1.0, 0.0]]), np.eye(1) * 0.3, np.eye(1) * 0.01
    A2 = rng.normal(size=(4, 4)) * 0.6                        # random, two outputs, G non-square
    yield "random_4x4", A2, rng.normal(size=(4, 2)), rng.normal(size=(2, 4)), np.array([[1.0, 0.2], [0.2, 0.5]]), \
        np.diag([0.1, 0.2])
    A3 = np.array([[1.2, 0.3, 0.0], [0.0, 0.9, 0.2], [0.0, 0.0, 0.5]])   # unstable mode, singular Q
    yield "singular_Q", A3, np.eye(3), np.array([[1.0, 0.0, 0.0]]), np.diag([1.0, 0.0, 0.5]), np.eye(1) * 0.2


@pytest.mark.parametrize("name, A, G, C, Q, R", list(_systems()), ids=[s[0] for s in _systems()])
def test_dlqe_matches_python_control_and_scipy(name, A, G, C, Q, R):
    L_ref, P_ref, E_ref = control.dlqe(A, G, C, Q, R)
    P_sp = scipy.linalg.solve_discrete_are(A.T, C.T, G @ Q @ G.T, R)
    with jax.enable_x64(True):
        L, P, E = jax.jit(dlqe)(A, G, C, Q, R)
    np.testing.assert_allclose(np.asarray(P), P_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(P), P_sp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(L), L_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.sort_complex(np.asarray(E)), np.sort_complex(E_ref), rtol=1e-9, atol=1e-12)


def test_dlqe_is_the_kalman_filter_limit():
    """The time-varying KF's prior covariance converges to P; its gain A K to L."""
    _, A, G, C, Q, R = next(_systems())
    with jax.enable_x64(True):
        L, P, _ = dlqe(A, G, C, Q, R)
        f = lambda x, u, w: jnp.asarray(A) @ x + jnp.asarray(G) @ w
        h = lambda x, v: jnp.asarray(C) @ x + v

        def body(g, _):
            post = ekf_update(h, g, jnp.zeros(1), R, 1)
            return ekf_predict(f, post, jnp.zeros(1), Q, 1), None

        prior, _ = jax.jit(lambda g: jax.lax.scan(body, g, None, length=400))(Gaussian(jnp.zeros(2), jnp.eye(2)))
    np.testing.assert_allclose(np.asarray(prior.cov), np.asarray(P), rtol=1e-9)


def test_dlqe_gradient():
    """dP/dQ and dL/dR by reverse mode through the doubling, against finite differences."""
    _, A, G, C, Q, R = next(_systems())
    with jax.enable_x64(True):
        fn = lambda q, r: jnp.sum(dlqe(A, G, C, q, r)[0]) + jnp.trace(dlqe(A, G, C, q, r)[1])
        check_grads(fn, (jnp.asarray(Q), jnp.asarray(R)), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_luenberger_error_dynamics():
    """Without noise, x - x̂ after k steps is (A - L C)^k (x0 - x̂0), whatever the inputs."""
    _, A, G, C, Q, R = next(_systems())
    B = np.array([[0.005], [0.1]])
    rng = np.random.default_rng(0)
    us = rng.normal(size=(30, 1))
    with jax.enable_x64(True):
        L = np.asarray(dlqe(A, G, C, Q, R)[0])

        def body(c, u):
            x, xh = c
            xh = luenberger_step(A, B, C, L, xh, u, C @ x)
            return (A @ x + B @ u, xh), x - xh

        x0, xh0 = jnp.array([1.0, -2.0]), jnp.zeros(2)
        (x, xh), _ = jax.jit(lambda c, us: jax.lax.scan(body, c, us))((x0, xh0), jnp.asarray(us))
    want = np.linalg.matrix_power(A - L @ C, 30) @ np.array([1.0, -2.0])
    np.testing.assert_allclose(np.asarray(x - xh), want, rtol=1e-10, atol=1e-14)


def test_dlqe_bad_inputs():
    A, C = np.eye(2), np.array([[1.0, 0.0]])
    with pytest.raises(ValueError, match="no stabilising solution"):
        dlqe(np.diag([1.5, 2.0]), np.eye(2), C, np.eye(2), np.eye(1))      # mode 2.0 unobservable
    with pytest.raises(ValueError, match="R must be positive definite"):
        dlqe(A, np.eye(2), C, np.eye(2), np.zeros((1, 1)))
    with pytest.raises(ValueError, match="Q must be"):
        dlqe(A, np.eye(2), C, np.eye(3), np.eye(1))
    with pytest.raises(ValueError, match="C must be a matrix"):
        dlqe(A, np.eye(2), np.ones((1, 3)), np.eye(2), np.eye(1))


def test_dlqe_float32():
    """The default dtype: the doubling keeps float32 precision on the double integrator."""
    _, A, G, C, Q, R = next(_systems())
    L_ref, P_ref, _ = control.dlqe(A, G, C, Q, R)
    L, P, _ = jax.jit(dlqe)(*(np.float32(M) for M in (A, G, C, Q, R)))
    assert L.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(L), L_ref, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(P), P_ref, rtol=1e-5)


def test_dlqe_on_concrete_matrices_compiles_once_per_shape_not_per_call():
    """Called eagerly (a SteadyStateKF's gain when a Loop is built, at every tuner step) the
    Riccati solve compiled its loop again on every call (a new body each time, 0.1 s each);
    now a second call with other numbers of the same shapes compiles nothing. A Loop of one
    structure with a steady-state KF, built again with a new trigger threshold, compiles
    nothing either."""
    from jaxnc import loop as nc
    from jaxnc.cache import compile_clock
    A = np.array([[1.0, 0.1], [0.0, 0.97]], np.float32)
    G, C = np.eye(2, dtype=np.float32), np.array([[1.0, 0.0]], np.float32)
    L1, _, _ = dlqe(A, G, C, np.eye(2, dtype=np.float32) * 0.01, np.eye(1, dtype=np.float32) * 0.1)
    before = compile_clock()
    L2, _, _ = dlqe(A * 0.99, G, C, np.eye(2, dtype=np.float32) * 0.02, np.eye(1, dtype=np.float32) * 0.1)
    assert (compile_clock() - before).compilations == 0
    assert not np.allclose(L1, L2)                           # other numbers, another gain
    plant = nc.LTI(A=A, B=[[0.005], [0.1]], C=C, w_std=0.1, v_std=0.3, T=0.1)

    def build(delta):
        return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=nc.Link(),
                       estimator=nc.SteadyStateKF(plant, Q=[0.01, 0.01], R=[[0.09]]), controller=nc.StateFeedback([[2.0, 1.0]]),
                       downlink=nc.Link(), actuator=nc.HoldLast(), N=2, T=0.1, steps=20)

    build(1e-3)
    before = compile_clock()
    build(2e-3)
    assert (compile_clock() - before).compilations == 0
