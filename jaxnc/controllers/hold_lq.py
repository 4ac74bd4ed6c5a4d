"""Hold-aware optimal LQ gain (seed 001, eq. 16-19, after Schenato 2009) and plain LQR.

The printed eq. (17)-(18) are garbled by extraction, so the gain is derived here.

**Model.** The actuator holds (eq. 4): ``ubar_k = theta_k u_k + (1 - theta_k) ubar_{k-1}``
with ``theta_k`` i.i.d. Bernoulli(``theta``), and ``x_{k+1} = A x_k + B ubar_k``.  The
augmented state is ``z_k = [x_k; ubar_{k-1}]``; the cost is
``E sum x_k' W x_k + ubar_k' U ubar_k``; the controller sees ``x_k`` (full state) but
not ``theta_k``.

**Bellman equation.** Try ``V(z) = z' S z`` with ``S = [[S11, S12], [S12', S22]]``.
Writing ``v = ubar_{k-1}`` and the applied input ``w`` (= u w.p. theta, = v otherwise),

    x'Wx + w'Uw + V([Ax + Bw; w]) = x'(W + A'S11A)x + 2 x'H w + w'T w,
    H = A'(S11 B + S12),   T = U + S22 + B'S11B + B'S12 + S12'B          (18)

Taking the expectation over ``theta_k`` and minimising over ``u``:

    u* = L x,   L = -T^{-1} (B'S11 + S12') A                                (19)

and matching the quadratic forms in ``x`` and ``v`` gives

    S11 = W + A'S11A - theta H T^{-1} H'                                     (17)
    S12 = (1 - theta) H,          S22 = (1 - theta) T.

(The paper prints ``(1 - theta)`` in front of the last term of (17) and a missing ``+``
in (18); with its own eq. (2) convention, theta = arrival probability, the coefficient
is ``theta``.)  At ``theta = 1``: S12 = S22 = 0, T = U + B'S11B, (17) is the DARE and L
is minus the LQR gain (tested).  The last two relations solve in closed form given S11,

    S12 = (1-theta) (I - (1-theta) A')^{-1} A' S11 B,
    T   = (U + B'S11B + B'S12 + S12'B) / theta,

so only S11 is iterated (fixed point from the DARE solution).  Design-time NumPy,
float64; it raises ``ValueError`` when the iteration diverges (theta below the critical
arrival probability of the hold strategy).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["dlqr", "hold_lq_gain"]


def dlqr(A, B, W, U):
    """Plain discrete LQR: ``K, S, E`` with ``u = -K x`` (python-control convention)."""
    A, B, W, U = (np.asarray(a, float) for a in (A, B, W, U))
    S = scipy.linalg.solve_discrete_are(A, B, W, U)
    K = np.linalg.solve(U + B.T @ S @ B, B.T @ S @ A)
    return K, S, np.linalg.eigvals(A - B @ K)


def _terms(A, B, U, S11, theta):
    n = A.shape[0]
    S12 = (1 - theta) * np.linalg.solve(np.eye(n) - (1 - theta) * A.T, A.T @ S11 @ B)
    T = (U + B.T @ S11 @ B + B.T @ S12 + S12.T @ B) / theta
    H = A.T @ (S11 @ B + S12)
    return S12, T, H


def hold_lq_gain(A, B, W, U, theta, *, tol=1e-10, max_iter=200_000):
    """Hold-aware gain ``L`` (``u = L x``, eq. 16, 19) and ``S11`` (eq. 17) for arrival prob. ``theta``."""
    theta = float(theta)
    if not 0.0 < theta <= 1.0:
        raise ValueError(f"hold_lq_gain: theta must be in (0, 1], got {theta}")
    A, B, W, U = (np.asarray(a, float) for a in (A, B, W, U))
    S11 = dlqr(A, B, W, U)[1]
    for _ in range(max_iter):
        _, T, H = _terms(A, B, U, S11, theta)
        new = W + A.T @ S11 @ A - theta * H @ np.linalg.solve(T, H.T)
        new = 0.5 * (new + new.T)
        if not np.all(np.isfinite(new)):
            break
        if np.max(np.abs(new - S11)) <= tol * max(1.0, np.max(np.abs(new))):
            S11 = new
            S12, T, _ = _terms(A, B, U, S11, theta)
            L = -np.linalg.solve(T, (B.T @ S11 + S12.T) @ A)
            return L, S11
        S11 = new
    raise ValueError(f"hold_lq_gain: the Riccati iteration did not converge for theta={theta} "
                     "(theta below the critical arrival probability?)")
