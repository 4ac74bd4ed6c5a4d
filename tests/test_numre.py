"""NUMRE (seed 003 eq. 9-15): K(N) against scipy's DARE and the lifted model."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxnc.estimators import numre
from jaxnc.plants import hdd


def _dare_gain(A, Q, C, V):
    P = scipy.linalg.solve_discrete_are(A.T, C.reshape(-1, 1), Q, np.array([[V]]))
    return P @ C / (C @ P @ C + V)


@pytest.fixture
def plant():
    A, B, C = hdd.plant_matrices()
    return A, B, C


def test_K1_equals_steady_state_kalman_gain(plant):
    """K(1) of the NUMRE recursion is the single-rate steady-state Kalman gain (DARE)."""
    A, B, C = plant
    W, V = 1e-2, 1e-6
    ref = _dare_gain(A, W * np.outer(B, B), C, V)
    with jax.enable_x64(True):
        t = numre.numre_tables(A, B, C, W, V, 4, dtype=jnp.float64)
        K = np.asarray(jax.jit(numre.numre_steady_gain, static_argnums=(1, 2))(t, 1, 3000))
    np.testing.assert_allclose(K, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("N", [2, 5])
def test_KN_equals_dare_of_lifted_model(plant, N):
    """For constant N the fixed point is the DARE of (A^N, We(N)) with white lifted noise."""
    A, B, C = plant
    W, V = 1e-2, 1e-6
    Q = sum(np.linalg.matrix_power(A, c) @ (W * np.outer(B, B)) @ np.linalg.matrix_power(A, c).T for c in range(N))
    ref = _dare_gain(np.linalg.matrix_power(A, N), Q, C, V)
    with jax.enable_x64(True):
        t = numre.numre_tables(A, B, C, W, V, 6, dtype=jnp.float64)
        K = np.asarray(jax.jit(numre.numre_steady_gain, static_argnums=(1, 2))(t, N, 3000))
    np.testing.assert_allclose(K, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())


def test_eq13_form_agrees_at_N1_and_differs_after(plant):
    A, B, C = plant
    t1 = numre.numre_tables(A, B, C, 1.0, 1.0, 3)
    t2 = numre.numre_tables(A, B, C, 1.0, 1.0, 3, we_form="eq13")
    np.testing.assert_allclose(np.asarray(t1.We[1]), np.asarray(t2.We[1]), rtol=1e-6)
    assert not np.allclose(np.asarray(t1.We[3]), np.asarray(t2.We[3]), rtol=1e-2)
    S = B + A @ B + A @ A @ B
    np.testing.assert_allclose(np.asarray(t2.We[3]), np.outer(S, S), rtol=1e-5, atol=1e-7)


def test_correction_is_bayes_update_of_lifted_model():
    """One correction after N silent periods equals the Gaussian conditioning computed directly."""
    rng = np.random.default_rng(0)
    A = np.array([[0.9, 0.2], [0.0, 0.7]])
    Bw = np.array([0.3, 1.0])
    C = np.array([1.0, 0.5])
    W, V, N = 0.4, 0.2, 3
    P0 = np.array([[1.0, 0.1], [0.1, 0.5]])
    x0 = rng.normal(size=2)
    y = 0.7
    with jax.enable_x64(True):
        t = numre.numre_tables(A, Bw, C, W, V, 5, dtype=jnp.float64)
        AN = np.linalg.matrix_power(A, N)
        xp = AN @ x0
        x, P, K = jax.jit(numre.numre_correct)(t, jnp.asarray(xp), jnp.asarray(P0), y, N)
    M = AN @ P0 @ AN.T + sum(np.linalg.matrix_power(A, c) @ np.outer(Bw, Bw) @ np.linalg.matrix_power(A, c).T * W for c in range(N))
    S = C @ M @ C + V
    np.testing.assert_allclose(np.asarray(x), xp + M @ C / S * (y - C @ xp), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(P), M - np.outer(M @ C, M @ C) / S, rtol=1e-10, atol=1e-14)


def test_tables_validation():
    with pytest.raises(ValueError, match="n_max"):
        numre.numre_tables(np.eye(2), np.ones(2), np.ones(2), 1.0, 1.0, 0)
    with pytest.raises(ValueError, match="we_form"):
        numre.numre_tables(np.eye(2), np.ones(2), np.ones(2), 1.0, 1.0, 2, we_form="x")


def test_design_accepts_a_singular_float32_noise_covariance_and_refuses_an_indefinite_one():
    """The textbook discrete white-noise-acceleration W = s2 g g' (g = (T^2/2, T), rank 1) built
    in float32: its zero eigenvalue rounds to either sign, and Numre.design refused 4 of these 28
    (T, s2) pairs ("smallest eigenvalue -3.7e-11"), where EKF, UKF and SteadyStateKF accept them
    (one float32 allowance, jaxnc._validate.psd_rounding). An eigenvalue of -1e-5 of W's scale
    is still refused."""
    import jaxnc.loop as jl
    C, eye = np.array([[1.0, 0.0]], np.float32), np.eye(2, dtype=np.float32)
    for T in (0.01, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0):
        A, B = np.array([[1, T], [0, 1]], np.float32), np.array([[T ** 2 / 2], [T]], np.float32)
        g = np.array([[T ** 2 / 2], [T]], np.float32)
        for s2 in (1e-3, 0.1, 1.0, 10.0):
            jl.Numre.design(A, B, eye, C, (s2 * g @ g.T).astype(np.float32), 0.01, 5, cov0=eye)
    bad = np.diag([1.0, -1e-5]).astype(np.float32)
    with pytest.raises(ValueError, match="Numre.W must be positive semi-definite"):
        jl.Numre.design(np.eye(2, dtype=np.float32), B, eye, C, bad, 0.01, 5, cov0=eye)
