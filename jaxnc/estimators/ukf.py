"""Unscented Kalman filter: Merwe scaled sigma points, predict and update.

Sigma points (van der Merwe, "Sigma-Point Kalman Filters for Probabilistic Inference
in Dynamic State-Space Models", PhD thesis, 2004, eq. 3.11-3.13; filterpy's
``MerweScaledSigmaPoints``): with lambda = alpha^2 (n + kappa) - n and S the lower
Cholesky factor of (n + lambda) P, the 2n + 1 points are X_0 = mean,
X_i = mean + S[:, i-1], X_{n+i} = mean - S[:, i-1]; the weights are
Wm_0 = lambda / (n + lambda), Wc_0 = Wm_0 + 1 - alpha^2 + beta,
Wm_i = Wc_i = 1 / (2 (n + lambda)).

The model is the EKF's (:mod:`jaxnc.estimators.ekf`): ``f(x, u, w)`` and ``h(x, v)``
with noise inputs w, v of dimension ``noise_dim``. The state passes through the
unscented transform; the noise enters through its Jacobian at the mean and zero noise,
L Q L' with L = df/dw (M R M', M = dh/dv): exact when the noise is additive through a
constant matrix, f = g(x, u) + G w (filterpy's UKF is the case G = I). For noise that
enters nonlinearly, augment the state with it.

Each update draws its sigma points from the belief it is given (the predicted one after
a prediction), not from the points the prediction propagated. On a linear model either kernel equals the Kalman filter for any alpha, beta, kappa.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import concrete
from jaxnc.estimators.ekf import Gaussian, _check_cov, _check_z, _noise_dim, _symmetrize

__all__ = ["SigmaPoints", "merwe_sigma_points", "ukf_predict", "ukf_update"]


class SigmaPoints(NamedTuple):
    """Sigma points and their weights.

    Attributes:
      points: float[2n + 1, n], X_0 = mean first.
      wm: float[2n + 1], the mean weights; wc: float[2n + 1], the covariance weights.
    """

    points: jax.Array
    wm: jax.Array
    wc: jax.Array


def merwe_sigma_points(belief: Gaussian, *, alpha=1.0, beta=2.0, kappa=0.0) -> SigmaPoints:
    """Merwe's scaled sigma points of ``belief`` (module docstring for the equations).

    Args:
      belief: Gaussian with mean float[n] and cov float[n, n] (positive definite: the
        Cholesky factor of a singular covariance is not finite).
      alpha: spread, > 0; beta: prior knowledge of the distribution (2 is optimal for a
        Gaussian); kappa: secondary scaling, with n + kappa > 0. Scalars (may be traced).

    Returns:
      :class:`SigmaPoints` with 2n + 1 points.

    Raises:
      ValueError: a concrete alpha <= 0 or kappa <= -n (n + lambda = alpha^2 (n + kappa)
        would divide the weights by zero or have no Cholesky factor: NaN without an error).
    """
    x = belief.mean
    n = x.shape[0]
    if concrete(alpha) and not float(alpha) > 0:
        raise ValueError(f"merwe_sigma_points: alpha must be > 0, got {alpha!r}")
    if concrete(kappa) and not n + float(kappa) > 0:
        raise ValueError(f"merwe_sigma_points: kappa must be > -n = {-n} (n + kappa > 0), got {kappa!r}")
    dt = x.dtype
    alpha, beta, kappa = (jnp.asarray(v, dt) for v in (alpha, beta, kappa))
    lam = alpha ** 2 * (n + kappa) - n
    S = jnp.linalg.cholesky(_symmetrize((n + lam) * belief.cov))
    points = jnp.concatenate([x[None, :], x[None, :] + S.T, x[None, :] - S.T], axis=0)
    wi = jnp.full((2 * n,), 0.5 / (n + lam), dt)
    w0 = lam / (n + lam)
    wm = jnp.concatenate([w0[None], wi])
    wc = jnp.concatenate([(w0 + 1.0 - alpha ** 2 + beta)[None], wi])
    return SigmaPoints(points, wm, wc)


def _moments(Y, sp: SigmaPoints):
    """Weighted mean float[d] and deviations float[2n+1, d] of the transformed points Y."""
    mean = sp.wm @ Y
    return mean, Y - mean[None, :]


def _noise_cov(J, Q):
    """J Q J' for a covariance matrix Q or a vector of variances."""
    return (J * Q[None, :]) @ J.T if Q.ndim == 1 else J @ Q @ J.T


def ukf_predict(f: Callable, belief: Gaussian, u, Q, noise_dim: int, *, alpha=1.0, beta=2.0,
                kappa=0.0) -> Gaussian:
    """One unscented prediction step.

        X_i = sigma points of belief,  Y_i = f(X_i, u, 0),
        mean+ = sum_i Wm_i Y_i,  P+ = sum_i Wc_i (Y_i - mean+)(Y_i - mean+)' + L Q L',

    L = df/dw at (mean, u, 0) (module docstring).

    Args:
      f: the model's ``f(x, u, w)``, float[n] -> float[n].
      belief: the prior, mean float[n], cov float[n, n] (positive definite).
      u: the input.
      Q: float[noise_dim, noise_dim], or float[noise_dim] variances (diagonal).
      noise_dim: static int >= 1, the dimension of w.
      alpha, beta, kappa: the sigma points' parameters (:func:`merwe_sigma_points`).

    Returns:
      :class:`~jaxnc.estimators.ekf.Gaussian`, the predicted belief (symmetric cov).

    Raises:
      ValueError (at trace time): ``noise_dim`` not an integer >= 1, ``Q`` of the wrong
      shape or (concrete) not PSD.
    """
    noise_dim = _noise_dim("ukf_predict", noise_dim)
    _check_cov("ukf_predict", "Q", Q, noise_dim, form="either", definite=False)
    w0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    sp = merwe_sigma_points(belief, alpha=alpha, beta=beta, kappa=kappa)
    Y = jax.vmap(lambda x: f(x, u, w0))(sp.points)
    mean, dY = _moments(Y, sp)
    L = jax.jacfwd(lambda w: f(belief.mean, u, w))(w0)
    cov = (dY * sp.wc[:, None]).T @ dY + _noise_cov(L, jnp.asarray(Q, belief.cov.dtype))
    return Gaussian(mean, _symmetrize(cov))


def ukf_update(h: Callable, belief: Gaussian, z, R, noise_dim: int, *, alpha=1.0, beta=2.0,
               kappa=0.0) -> Gaussian:
    """One unscented measurement update.

        X_i = sigma points of belief,  Z_i = h(X_i, 0),  zhat = sum_i Wm_i Z_i,
        S = sum_i Wc_i (Z_i - zhat)(Z_i - zhat)' + M R M',
        Pxz = sum_i Wc_i (X_i - mean)(Z_i - zhat)',  K = Pxz S^-1,
        mean+ = mean + K (z - zhat),  P+ = P - K S K',

    M = dh/dv at (mean, 0) (module docstring). P+ is symmetrised; it is positive
    semi-definite in exact arithmetic when every Wc_i >= 0 or the UT is exact.

    Args:
      h: the model's ``h(x, v)``, float[n] -> float[p].
      belief: the prior, mean float[n], cov float[n, n] (positive definite).
      z: float[p], the measurement.
      R: float[noise_dim, noise_dim], or float[noise_dim] variances (diagonal).
      noise_dim: static int >= 1, the dimension of v.
      alpha, beta, kappa: the sigma points' parameters (:func:`merwe_sigma_points`).

    Returns:
      :class:`~jaxnc.estimators.ekf.Gaussian`, the posterior.

    Raises:
      ValueError (at trace time): ``noise_dim`` not an integer >= 1, ``R`` of the wrong
      shape or (concrete) not PD, ``z`` not of the shape of h(x, v).
    """
    noise_dim = _noise_dim("ukf_update", noise_dim)
    _check_cov("ukf_update", "R", R, noise_dim, form="either", definite=True)
    _check_z("ukf_update", h, belief.mean, z, noise_dim)
    v0 = jnp.zeros((noise_dim,), belief.mean.dtype)
    sp = merwe_sigma_points(belief, alpha=alpha, beta=beta, kappa=kappa)
    Z = jax.vmap(lambda x: h(x, v0))(sp.points)
    zhat, dZ = _moments(Z, sp)
    dX = sp.points - belief.mean[None, :]
    M = jax.jacfwd(lambda v: h(belief.mean, v))(v0)
    S = _symmetrize((dZ * sp.wc[:, None]).T @ dZ + _noise_cov(M, jnp.asarray(R, belief.cov.dtype)))
    Pxz = (dX * sp.wc[:, None]).T @ dZ
    K = jnp.linalg.solve(S, Pxz.T).T                        # Pxz S^-1 (S symmetric)
    mean = belief.mean + K @ (z - zhat)
    cov = belief.cov - K @ S @ K.T
    return Gaussian(mean, _symmetrize(cov))
