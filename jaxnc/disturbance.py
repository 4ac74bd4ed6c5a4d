"""Disturbance observer (DOB) of seed 003 section 3.2.2, eq. (16): d_hat = D1(z) u + D2(z) y_hat.

The paper obtains D(z) = [D1, D2] by H-infinity synthesis (eq. 17-18, after [49]). As
printed the problem is unweighted, min ||Fl(M, D)||_inf over the map from d to the
estimation error d - d_hat, and it is solved by D = 0: the plant is strictly proper, so
whatever D is, d_hat depends on d strictly causally, the error's transfer function is 1 at
z = infinity, and by the maximum-modulus principle its H-infinity norm is at least 1, which
D = 0 attains. The design of [49] must weight the error in frequency, and the paper does not
give the weights; with a solver (python-control's ``hinfsyn`` + slycot) our choice of Q below
would only become a choice of weights. So we implement the standard inverse-model DOB that a
weighted synthesis approximates (D1 close to -1, D2 close to G^{-1}, both low-pass filtered):

    D1(z) = -Q(z) z^{-1},   D2(z) = Q(z) z^{-1} Gn(z)^{-1},

Gn the rigid-body mode of eq. (30) discretised by ZOH, with its sampling zero moved to
z = 0 (numerator (b1 + b0) z instead of b1 z + b0) so that z^{-1} Gn^{-1} is the FIR
(1 + a1 z^-1 + a0 z^-2)/(b1 + b0). If y = Gn (u + d) then d_hat = Q(z) z^{-1} d. Q is a
second-order low-pass with unit DC gain, ((1 - q)/(1 - q z^-1))^2, q = exp(-2 pi f_q T).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_positive, check_range

__all__ = ["Dob", "DobState", "dob_design", "dob_init", "dob_output", "dob_update", "rigid_nominal"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Dob:
    """State space of d_hat = [D1 D2] [u; y]: x+ = A x + B [u, y], d_hat = C x + D [u, y]."""
    A: jax.Array
    B: jax.Array      # (n, 2)
    C: jax.Array      # (n,)
    D: jax.Array      # (2,)


class DobState(NamedTuple):
    x: jax.Array


def rigid_nominal(Ts: float):
    """ZOH of 7.153e6/(s^2 + 502.7 s + 1.011e6): (num, den) in z (numerator b1 z + b0).
    Raises ValueError unless the period Ts > 0 (s)."""
    import scipy.signal
    check_positive("Ts", Ts)
    from jaxnc.plants.hdd import RIGID_DEN, RIGID_NUM
    num, den, _ = scipy.signal.cont2discrete(([RIGID_NUM], list(RIGID_DEN)), Ts, method="zoh")
    return np.trim_zeros(np.ravel(num), "f"), np.ravel(den)


def dob_design(Ts: float, f_q_hz: float = 1000.0, dtype=jnp.float32) -> Dob:
    """The inverse-model DOB described in the module docstring, cut-off f_q_hz."""
    import scipy.signal
    check_positive("Ts", Ts)
    check_range("f_q_hz", f_q_hz, 0.0, 0.5 / Ts, low_open=True, high_open=True)
    num, den = rigid_nominal(Ts)
    g = float(np.sum(num))                                  # b1 + b0: sampling zero moved to 0
    q = float(np.exp(-2 * np.pi * f_q_hz * Ts))
    Qn, Qd = np.array([(1 - q) ** 2, 0.0, 0.0]), np.polymul([1.0, -q], [1.0, -q])   # in z
    # D1 = -Q z^-1 ;  D2 = Q z^-1 Gn^-1 = Q (z^2 + a1 z + a0) / (g z^2)   (positive powers of z)
    d1n, d1d = -Qn, np.polymul(Qd, [1.0, 0.0])
    d2n, d2d = np.polymul(Qn, den) / g, np.polymul(Qd, [1.0, 0.0, 0.0])
    A1, B1, C1, D1 = scipy.signal.tf2ss(d1n, d1d)
    A2, B2, C2, D2 = scipy.signal.tf2ss(d2n, d2d)
    n1, n2 = A1.shape[0], A2.shape[0]
    A = np.zeros((n1 + n2, n1 + n2))
    A[:n1, :n1], A[n1:, n1:] = A1, A2
    B = np.zeros((n1 + n2, 2))
    B[:n1, 0], B[n1:, 1] = B1[:, 0], B2[:, 0]
    C = np.concatenate([C1[0], C2[0]])
    D = np.array([D1[0, 0], D2[0, 0]])
    f = lambda a: jnp.asarray(a, dtype)
    return Dob(f(A), f(B), f(C), f(D))


def dob_init(d: Dob, dtype=jnp.float32) -> DobState:
    return DobState(jnp.zeros(d.A.shape[0], dtype))


def _scalar(name, v):
    """``v`` as a float scalar; ValueError naming ``name`` unless it has one entry (the DOB is SISO)."""
    v = jnp.asarray(v)
    if v.size != 1:
        raise ValueError(f"{name} must be a single number (the DOB is SISO), got shape {v.shape}")
    return v.reshape(())


def dob_output(d: Dob, s: DobState, y_hat):
    """d_hat_k (float scalar) before u_k is known: D1 is strictly proper, so D[0] = 0 (no
    algebraic loop). ``y_hat``: one number (shape () or (1,)); ValueError otherwise."""
    return d.C @ s.x + d.D[1] * _scalar("dob_output: y_hat", y_hat)


def dob_update(d: Dob, s: DobState, u, y_hat) -> DobState:
    """The DOB's state after u_k and y_hat_k, each one number (shape () or (1,): a (1,)
    pair made the state a matrix); ValueError otherwise."""
    u, y_hat = _scalar("dob_update: u", u), _scalar("dob_update: y_hat", y_hat)
    return DobState(d.A @ s.x + d.B @ jnp.stack([u, y_hat]))
