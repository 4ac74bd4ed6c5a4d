"""Periodic event-triggered communication (PETC) at the sensor.

Seed 000 eq. (3)-(4): at every slow instant kNT the sensor sends z_k when

    sum_i (zbar_{k-1}(i) - z_k(i))^2  >  sum_i sigma(i) z_k(i)^2 + delta(i),

and keeps zbar_k = beta_k z_k + (1 - beta_k) zbar_{k-1} (eq. 3).

The step function has zero gradient almost everywhere. With ``temperature > 0`` the
trigger returns a straight-through estimate: the forward value is the exact hard
decision, the backward pass is that of ``sigmoid(gap / temperature)``, where ``gap`` is
the left minus the right side of eq. (4) (squared norms, so the gradient is finite
when z = zbar). Simulations are therefore always evaluated with hard triggers.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnc._validate import check_nonneg


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PetcTrigger:
    """Mixed relative/absolute PETC condition, eq. (4), per-output sigma(i), delta(i)."""

    sigma: jax.Array
    delta: jax.Array
    temperature: jax.Array = 0.0   # > 0: straight-through sigmoid gradient

    def __post_init__(self):
        check_nonneg("PetcTrigger.sigma", self.sigma)
        check_nonneg("PetcTrigger.delta", self.delta)
        check_nonneg("PetcTrigger.temperature", self.temperature)

    def gap(self, z_last, z):
        """Left side minus right side of eq. (4); the trigger fires when gap > 0."""
        err = jnp.sum((z_last - z) ** 2)
        return err - jnp.sum(self.sigma * z * z + self.delta)

    def fires(self, z_last, z):
        """beta_k in {0., 1.} (float, so it can weight updates), eq. (4)."""
        return fires_straight_through(self.gap(z_last, z), self.temperature)


def soft_decision(gap, temperature):
    """sigmoid(gap / temperature), in the dtype of ``gap``; 0 where ``temperature`` is 0."""
    tau = jnp.maximum(jnp.asarray(temperature, gap.dtype), 1e-12)
    return jnp.where(jnp.asarray(temperature) > 0, jax.nn.sigmoid(gap / tau), 0.0)


def fires_straight_through(gap, temperature):
    """1[gap > 0] as a float: with ``temperature`` > 0, the gradient is that of
    :func:`soft_decision` (hard + (soft - sg(soft)): the forward value is exactly 0 or 1)."""
    soft = soft_decision(gap, temperature)
    return (gap > 0).astype(gap.dtype) + (soft - jax.lax.stop_gradient(soft))


def hold_last_sent(beta, z, z_last):
    """zbar_k = beta z_k + (1 - beta) zbar_{k-1}, eq. (3).

    With beta a 0/1 float this is an exact select that still passes gradients; the
    remote side uses it the same way to keep or replace its belief."""
    return beta * z + (1.0 - beta) * z_last
