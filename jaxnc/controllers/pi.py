"""Discrete PI controller (rectangular integration at the controller period Ts)."""
from __future__ import annotations

import jax.numpy as jnp


def pi_step(Kp, Ki, integ, e, Ts):
    """u_k = Kp e_k + Ki I_k with I_k = I_{k-1} + Ts e_k. Returns (u, I_k)."""
    integ = integ + Ts * e
    return Kp * e + Ki * integ, integ


def wrap_angle(a):
    """Angle to (-pi, pi]."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))
