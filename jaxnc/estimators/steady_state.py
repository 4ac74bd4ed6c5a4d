"""Steady-state (time-invariant) observers of x+ = A x + B u + G w, z = C x + v.

* :func:`dlqe`: the stationary Kalman gain from the filter's discrete algebraic Riccati
  equation (python-control's ``dlqe``: ``L, P, E = dlqe(A, G, C, Q, R)``), solved in JAX
  by the structure-preserving doubling algorithm, so that L and P are differentiable in
  every matrix;
* :func:`luenberger_step`: one step of the predictor-form observer
  x̂+ = A x̂ + B u + L (z - C x̂), whose estimation error obeys e+ = (A - L C) e.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, concrete, jit_when_eager
from jaxnc.estimators.ekf import _check_cov, _symmetrize

__all__ = ["dlqe", "luenberger_step"]


def _matrix(name, M, rows=None, cols=None):
    M = jnp.asarray(M)
    if M.ndim == 1 and rows is not None and cols == 1:
        M = M[:, None]
    if M.ndim != 2 or (rows is not None and M.shape[0] != rows) or (cols is not None and M.shape[1] != cols):
        want = f"({'?' if rows is None else rows}, {'?' if cols is None else cols})"
        raise ValueError(f"dlqe: {name} must be a matrix of shape {want}, got shape {tuple(M.shape)}")
    if not jnp.issubdtype(M.dtype, jnp.floating):
        M = M.astype(jnp.float32)
    return M


@jit_when_eager(static_argnums=(3,))      # eagerly (SteadyStateKF.init at every loop built) one program per shape
def _sda(A, G, H, iterations):
    """Structure-preserving doubling for the DARE
    X = A' X A - A' X B (R + B' X B)^-1 B' X A + Q given A, G = B R^-1 B', H = Q
    (Chu, Fan & Lin, "A structure-preserving doubling algorithm for continuous-time
    algebraic Riccati equations", Linear Algebra Appl. 396, 2005, section 3): H_k -> X
    quadratically, H_k being the Riccati recursion from X = Q after 2^k steps."""
    I = jnp.eye(A.shape[0], dtype=A.dtype)

    def body(_, c):
        A, G, H = c
        W = I + G @ H
        WA, WG = jnp.linalg.solve(W, A), jnp.linalg.solve(W, G)
        return A @ WA, _symmetrize(G + A @ WG @ A.T), _symmetrize(H + A.T @ H @ WA)

    return jax.lax.fori_loop(0, iterations, body, (A, G, H))[2]


#: the margin below 1 of a Schur spectral radius (:func:`dlqe`): float32 rounding moves a mode on the unit circle
_SCHUR_MARGIN = 1e-5


def dlqe(A, G, C, Q, R, *, iterations: int = 60):
    """Stationary Kalman gain: python-control's ``L, P, E = dlqe(A, G, C, Q, R)``.

    For x+ = A x + B u + G w, z = C x + v, E[w w'] = Q, E[v v'] = R, the filter's DARE

        P = A P A' - A P C' (C P C' + R)^-1 C P A' + G Q G'

    gives the steady-state *prior* covariance P (of x_k given z up to k - 1), the
    predictor-form gain L = A P C' (C P C' + R)^-1 of x̂+ = A x̂ + B u + L (z - C x̂)
    (:func:`luenberger_step`) and the observer poles E = eig(A - L C). The current-form
    (filter) gain is M = P C' (C P C' + R)^-1, L = A M.

    Solved by ``iterations`` doubling steps (static; each doubles the Riccati horizon,
    the default 60 is 2^60 steps), a fixed-length loop that ``jit`` compiles and
    reverse mode differentiates.

    Args:
      A: float[n, n]; G: float[n, q]; C: float[p, n].
      Q: float[q, q], process noise covariance (PSD); R: float[p, p], measurement noise
        covariance (PD).
      iterations: static int >= 1.

    Returns:
      (L float[n, p], P float[n, n], E complex[n]).

    Raises:
      ValueError: shapes that do not match, Q or R not symmetric, Q not PSD or R not PD
        (when concrete), and,
        when every input is concrete, no stabilising solution (A - L C not Schur: (A, C)
        must be detectable and (A, G Q^1/2) stabilisable). Schur means a spectral radius
        below 1 - 1e-5: in float32 an undetectable mode on the unit circle (an oscillation
        sampled at a multiple of its half period) comes out at 0.99999994, and its
        covariance grows to float32's rounding instead of converging.
    """
    check_int("dlqe: iterations", iterations, 1, 10_000)
    A = _matrix("A", A)
    n = A.shape[0]
    A = _matrix("A", A, n, n)
    G = _matrix("G", G, n, None)
    C = _matrix("C", C, None, n)
    q, p = G.shape[1], C.shape[0]
    Q, R = jnp.atleast_2d(jnp.asarray(Q)), jnp.atleast_2d(jnp.asarray(R))
    _check_cov("dlqe", "Q", Q, q, form="matrix", definite=False)
    _check_cov("dlqe", "R", R, p, form="matrix", definite=True)
    dtype = jnp.result_type(A, G, C)
    A, G, C = A.astype(dtype), G.astype(dtype), C.astype(dtype)
    Q, R = Q.astype(dtype), R.astype(dtype)
    # the filter DARE is the control DARE of (A', C'): X = P
    P = _sda(A.T, C.T @ jnp.linalg.solve(R, C), G @ Q @ G.T, iterations)
    S = C @ P @ C.T + R
    L = jnp.linalg.solve(S, C @ P @ A.T).T                 # A P C' S^-1 (S symmetric)
    E = jnp.linalg.eigvals(A - L @ C)
    if concrete(A, G, C, Q, R):
        rho = float(np.max(np.abs(np.asarray(E)))) if np.all(np.isfinite(np.asarray(P))) else np.inf
        if not rho < 1.0 - _SCHUR_MARGIN:
            raise ValueError("dlqe: no stabilising solution of the Riccati equation (spectral radius of "
                             f"A - L C is {rho:.8g}, not below 1 - {_SCHUR_MARGIN:g}): (A, C) must be detectable "
                             "and (A, G Q^1/2) stabilisable, with no mode they leave within 1e-5 of the unit circle")
    return L, P, E


def luenberger_step(A, B, C, L, xhat, u, z):
    """One step of the predictor-form Luenberger observer.

        x̂_{k+1} = A x̂_k + B u_k + L (z_k - C x̂_k)

    x̂_k estimates x_k from z up to k - 1; without noise the error e = x - x̂ obeys
    e_{k+1} = (A - L C) e_k. With L from :func:`dlqe` it is the steady-state Kalman
    filter's prediction.

    Args:
      A: float[n, n]; B: float[n, m]; C: float[p, n]; L: float[n, p].
      xhat: float[n]; u: float[m]; z: float[p], the measurement at k.

    Returns:
      float[n], x̂_{k+1}.
    """
    return A @ xhat + B @ u + L @ (z - C @ xhat)
