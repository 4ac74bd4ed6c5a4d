"""Smart actuator with a packet buffer (seed 000, section 2.4; packet-based control).

A packet carries the actions u_{k..k+H-1} computed for fast instants k..k+H-1 and its
time stamp k. On arrival it replaces the buffer; at fast instant t the actuator
applies the action indexed by t - stamp, and holds the last action once the buffer
runs out (which is the DR scheme's "hold the last action of the last packet").
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class PacketBuffer(NamedTuple):
    u: jax.Array       # [H, m] actions
    stamp: jax.Array   # int32 fast instant of u[0]


def empty_buffer(horizon: int, m: int, dtype=jnp.float32) -> PacketBuffer:
    """A buffer that applies zero until the first packet arrives."""
    return PacketBuffer(jnp.zeros((horizon, m), dtype), jnp.zeros((), jnp.int32))


def install(buf: PacketBuffer, new: PacketBuffer, arrived) -> PacketBuffer:
    """Replace the buffer when ``arrived`` (a 0/1 float, so gradients can pass)."""
    a = jnp.asarray(arrived, buf.u.dtype)
    return PacketBuffer(a * new.u + (1.0 - a) * buf.u, jnp.where(a > 0.5, new.stamp, buf.stamp))


def current_action(buf: PacketBuffer, t):
    """Action for fast instant t: index by time stamp, hold the last when exhausted."""
    i = jnp.clip(t - buf.stamp, 0, buf.u.shape[0] - 1)
    return buf.u[i]
