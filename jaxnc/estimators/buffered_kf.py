"""Kalman filter with a measurement buffer for delayed and lost packets (seed 001, eq. 9-15).

The controller keeps the last ``N`` instants ``t = k-N, ..., k-1`` in a buffer: the
inputs ``u_t`` it commanded, the measurements ``y_t`` (usable only once their packet
has arrived, ``gamma_t^k = 1``, eq. 3) and the *base* prediction
``x_{k-N|k-N-1}, P_{k-N|k-N-1}``.  At every step it re-runs the filter over the buffer
(eq. 9-13 with the reliable-channel prediction of eq. 14-15):

    x_{t|t}   = x_{t|t-1} + gamma_t^k K_t (y_t - C x_{t|t-1})                (11)
    P_{t|t}   = P_{t|t-1} - gamma_t^k P_{t|t-1} C' (C P C' + R)^-1 C P_{t|t-1} (12)
    x_{t+1|t} = A x_{t|t} + B u_t,     P_{t+1|t} = A P_{t|t} A' + Q          (14, 15)

and returns ``x_{k|k-1}, P_{k|k-1}``.  The first re-run step becomes the next base, so
a measurement is used if it arrives within ``N`` steps of its sampling and counts as
lost otherwise.  The paper re-runs only from the oldest newly-arrived measurement; the
slots before it give the same numbers as at the previous step, so re-running the whole
buffer (fixed shapes, no data-dependent control flow) is equal, just not minimal.

Slots with ``t < 0`` (the first ``N`` steps) are skipped, so at ``k = 0`` the output is
the prior ``x_0, P_0`` (``x_{0|-1}``).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import check_int
from jaxnc.estimators.ekf import Gaussian

__all__ = ["BufferedKF", "BufferedKFState", "bkf_init", "bkf_estimate", "bkf_push", "kf_update", "kf_predict"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BufferedKF:
    """Linear model of eq. (1) and the buffer length ``N`` (static)."""

    A: jax.Array
    B: jax.Array
    C: jax.Array
    Q: jax.Array
    R: jax.Array
    N: int = dataclasses.field(default=10, metadata=dict(static=True))

    def __post_init__(self):
        check_int("BufferedKF.N", self.N, 1, 10_000)


class BufferedKFState(NamedTuple):
    """Base prediction ``x_{k-N|k-N-1}`` and the buffered slots ``t = k-N .. k-1``."""

    base: Gaussian
    y: jax.Array    # (N, p) measurements y_t
    u: jax.Array    # (N, m) inputs u_t assumed applied (eq. 14)
    t: jax.Array    # (N,) int32 sampling instants of the slots


def bkf_init(mean0, cov0, N: int, p: int, m: int) -> BufferedKFState:
    """State at ``k = 0``: base = prior, empty slots at ``t = -N .. -1``."""
    mean0 = jnp.asarray(mean0)
    return BufferedKFState(
        base=Gaussian(mean0, jnp.asarray(cov0, mean0.dtype)),
        y=jnp.zeros((N, p), mean0.dtype),
        u=jnp.zeros((N, m), mean0.dtype),
        t=jnp.arange(-N, 0, dtype=jnp.int32),
    )


def _inv(S):
    """Inverse of a small SPD matrix; closed form for 1x1 and 2x2 (cheap under vmap)."""
    p = S.shape[-1]
    if p == 1:
        return 1.0 / S
    if p == 2:
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        det = a * d - b * c
        return jnp.stack([jnp.stack([d, -b]), jnp.stack([-c, a])]) / det
    return jnp.linalg.inv(S)


def kf_update(kf: BufferedKF, g: Gaussian, y, gamma) -> Gaussian:
    """Measurement update eq. (11)-(13), applied only where ``gamma`` is true."""
    PCt = g.cov @ kf.C.T
    K = PCt @ _inv(kf.C @ PCt + kf.R)                              # (13)
    mean = g.mean + K @ (y - kf.C @ g.mean)                         # (11)
    cov = g.cov - K @ PCt.T                                         # (12)
    cov = 0.5 * (cov + cov.T)
    return Gaussian(jnp.where(gamma, mean, g.mean), jnp.where(gamma, cov, g.cov))


def kf_predict(kf: BufferedKF, g: Gaussian, u) -> Gaussian:
    """Time update with the commanded input, eq. (14)-(15)."""
    return Gaussian(kf.A @ g.mean + kf.B @ u, kf.A @ g.cov @ kf.A.T + kf.Q)


def bkf_estimate(kf: BufferedKF, state: BufferedKFState, avail) -> tuple[Gaussian, Gaussian]:
    """Re-run the buffer: returns ``(x_{k|k-1}, next base x_{k-N+1|k-N})``.

    ``avail`` (bool, shape (N,)) is ``gamma_t^k`` for the slots ``t = k-N .. k-1``:
    whether the packet of ``y_t`` has arrived by step ``k``.
    """
    def body(g, slot):
        y, u, t, gam = slot
        nxt = kf_predict(kf, kf_update(kf, g, y, gam), u)
        valid = t >= 0
        g = jax.tree_util.tree_map(lambda a, b: jnp.where(valid, a, b), nxt, g)
        return g, g

    last, seq = jax.lax.scan(body, state.base, (state.y, state.u, state.t, avail))
    next_base = jax.tree_util.tree_map(lambda s: s[0], seq)
    return last, next_base


def bkf_push(state: BufferedKFState, next_base: Gaussian, y, u, k) -> BufferedKFState:
    """Drop slot ``k-N`` (its information is now in ``next_base``) and append ``(y_k, u_k)``."""
    return BufferedKFState(
        base=next_base,
        y=jnp.concatenate([state.y[1:], jnp.asarray(y, state.y.dtype)[None]], axis=0),
        u=jnp.concatenate([state.u[1:], jnp.asarray(u, state.u.dtype)[None]], axis=0),
        t=jnp.concatenate([state.t[1:], jnp.asarray(k, jnp.int32)[None]]),
    )
