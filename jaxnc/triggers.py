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
        g = self.gap(z_last, z)
        hard = (g > 0).astype(z.dtype)
        tau = jnp.maximum(jnp.asarray(self.temperature, z.dtype), 1e-12)
        soft = jax.nn.sigmoid(g / tau)
        soft = jnp.where(jnp.asarray(self.temperature) > 0, soft, 0.0)
        # hard + (soft - sg(soft)): forward value is exactly 0 or 1, gradient is d soft.
        return hard + (soft - jax.lax.stop_gradient(soft))


def hold_last_sent(beta, z, z_last):
    """zbar_k = beta z_k + (1 - beta) zbar_{k-1}, eq. (3).

    With beta a 0/1 float this is an exact select that still passes gradients; the
    remote side uses it the same way to keep or replace its belief."""
    return beta * z + (1.0 - beta) * z_last
