"""Non-uniform multi-rate estimator (NUMRE) of seed 003, eq. (9)-(15).

A Kalman filter whose measurement arrives after a time-varying number N of fast
periods (eq. 9). Between measurements it only predicts; on arrival it corrects with the
gain K(N) of the lifted model (eq. 10),

    M  = A^N P+ (A^N)^T + We(N),   K(N) = M C^T (C M C^T + V)^{-1},   P+ <- (I - K C) M (.)^T + K V K^T

which is eq. (12) written with the posterior covariance (Joseph form). We(N) is the
covariance of the lifted process noise sum_c A^{N-1-c} Bw w_{k+c}. For white w it is
sum_c A^c Bw W Bw^T (A^c)^T (``we_form="white"``, default); eq. (13) as printed,
(sum_c A^{N-1-c} Bw) W (sum_c ...)^T, is the covariance of a w held constant over the N
periods (``we_form="eq13"``). Both agree for N = 1.

Tables of A^N and We(N) for N = 1..n_max are built once (numpy, float64) so that a
traced N just indexes them. The h-step prediction of eq. (14)-(15) is the controller
:class:`jaxnc.loop.Cascade` (on :func:`jaxnc.controllers.prediction.predict_periods`).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int
from jaxnc.estimators.ekf import Gaussian, ekf_update_terms

__all__ = ["NumreTables", "numre_tables", "numre_gain", "numre_correct", "numre_steady_gain"]

WE_FORMS = ("white", "eq13")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NumreTables:
    """A^N and We(N) for N = 0..n_max (index N; N = 0 is the identity / zero), C and V."""
    AN: jax.Array        # (n_max + 1, n, n)
    We: jax.Array        # (n_max + 1, n, n)
    C: jax.Array         # (n,)  single output
    V: jax.Array         # ()    Cov(v)
    n_max: int = dataclasses.field(metadata=dict(static=True), default=1)


def numre_tables(A, Bw, C, W, V, n_max: int, *, we_form: str = "white", dtype=jnp.float32) -> NumreTables:
    """Lifted-model tables for eq. (10)-(13). ``W`` is Cov(w): a scalar or a matrix (Bw then a matrix)."""
    check_int("n_max", n_max, 1)
    if we_form not in WE_FORMS:
        raise ValueError(f"we_form must be one of {', '.join(WE_FORMS)}, got {we_form!r}")
    A = np.asarray(A, float)
    n = A.shape[0]
    Bw = np.asarray(Bw, float).reshape(n, -1)
    W = np.atleast_2d(np.asarray(W, float))
    Q = Bw @ W @ Bw.T
    AN = np.zeros((n_max + 1, n, n))
    We = np.zeros((n_max + 1, n, n))
    AN[0] = np.eye(n)
    S = np.zeros_like(Bw)          # sum_c A^c Bw (for eq13)
    for N in range(1, n_max + 1):
        AN[N] = A @ AN[N - 1]
        if we_form == "white":
            We[N] = A @ We[N - 1] @ A.T + Q
        else:
            S = A @ S + Bw
            We[N] = S @ W @ S.T
    f = lambda a: jnp.asarray(a, dtype)
    return NumreTables(f(AN), f(We), f(np.asarray(C, float)), f(float(np.asarray(V))), n_max=n_max)


def numre_gain(t: NumreTables, P, N):
    """Eq. (12): (K(N), prior covariance M) from the previous posterior covariance P."""
    AN = t.AN[N]
    M = AN @ P @ AN.T + t.We[N]
    M = 0.5 * (M + M.T)
    s = t.C @ M @ t.C + t.V
    K = M @ t.C / s
    return K, M


def numre_correct(t: NumreTables, x_prior, P, y, N):
    """Eq. (11)-(12): x(k|k) = x(k|k-N) + K(N) (y_k - C x(k|k-N)); returns (x, P+, K).

    The Kalman update of the lifted prior N(x(k|k-N), M) (M of :func:`numre_gain`) with the
    scalar y = C x + v, Var(v) = V: :func:`jaxnc.estimators.ekf.ekf_update_terms` (Joseph form).

    Args: t the tables; x_prior float[n]; P float[n, n], the posterior covariance of the last
    arrival; y scalar; N int32 in [0, t.n_max] (0: P is already the prior covariance of this
    instant, no period of dynamics and noise before it). Returns: (x float[n], P+ float[n, n],
    K float[n]).
    """
    _, M = numre_gain(t, P, N)
    h = lambda x, v: jnp.reshape(t.C @ x, (1,)) + v
    post, _, _, K = ekf_update_terms(h, Gaussian(x_prior, M), jnp.reshape(y, (1,)).astype(M.dtype),
                                     jnp.reshape(t.V, (1, 1)), 1)
    return post.mean, post.cov, K[:, 0]


def numre_steady_gain(t: NumreTables, N: int, iters: int = 2000, P0=None):
    """K(N) for a constant multiplicity: eq. (12) (:func:`numre_correct`'s covariance update)
    iterated ``iters`` times from ``P0`` (default I), a fixed point."""
    n = t.AN.shape[-1]
    P = jnp.eye(n, dtype=t.AN.dtype) if P0 is None else P0
    x = jnp.zeros((n,), t.AN.dtype)
    P = jax.lax.fori_loop(0, iters, lambda _, P: numre_correct(t, x, P, 0.0, N)[1], P)
    return numre_gain(t, P, N)[0]
