"""Extended Kalman filter: predict and Joseph-form update.

Seed 000 eq. (11)-(16): prediction with Jacobians A = df/dxi, L = df/dn1; correction
with H = dh/dxi, M = dh/dn2, gain K = P H' (H P H' + M R M')^-1 and the Joseph form
P = (I - K H) P (I - K H)' + K (M R M') K'. Jacobians come from ``jax.jacfwd`` of
the model's own ``dynamics(x, u, w)`` / ``measure(x, v)`` methods, so a linear model
gives exactly the Kalman filter.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl


class Gaussian(NamedTuple):
    """Belief N(mean, cov) of the state."""

    mean: jax.Array
    cov: jax.Array


def _symmetrize(P):
    return 0.5 * (P + P.T)


def ekf_predict(f: Callable, belief: Gaussian, u, Q, noise_dim: int) -> Gaussian:
    """One prediction step, eq. (11)-(12): mean = f(mean, u, 0), P = A P A' + L Q L'."""
    w0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    mean = f(belief.mean, u, w0)
    A = jax.jacfwd(f, argnums=0)(belief.mean, u, w0)
    L = jax.jacfwd(f, argnums=2)(belief.mean, u, w0)
    cov = A @ belief.cov @ A.T + L @ Q @ L.T
    return Gaussian(mean, _symmetrize(cov))


def kalman_gain(P, H, S):
    """K = P H' S^-1 through a Cholesky solve of the SPD innovation covariance S (eq. 15)."""
    c = jsl.cho_factor(S, lower=True)
    return jsl.cho_solve(c, H @ P).T


def ekf_update(h: Callable, belief: Gaussian, z, R, noise_dim: int) -> Gaussian:
    """Correction with measurement z, eq. (13)-(16), Joseph form covariance."""
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    zhat = h(belief.mean, v0)
    H = jax.jacfwd(h, argnums=0)(belief.mean, v0)
    M = jax.jacfwd(h, argnums=1)(belief.mean, v0)
    Rm = M @ R @ M.T
    S = H @ belief.cov @ H.T + Rm
    K = kalman_gain(belief.cov, H, S)
    mean = belief.mean + K @ (z - zhat)
    IKH = jnp.eye(belief.mean.shape[0], dtype=belief.cov.dtype) - K @ H
    cov = IKH @ belief.cov @ IKH.T + K @ Rm @ K.T
    return Gaussian(mean, _symmetrize(cov))
