"""Lossy, delayed network channel (seed 000, section 2.3, eq. 5-7).

Each direction of the network (sensor-to-controller, controller-to-actuator)
is a :class:`Channel`: packets are dropped by a Bernoulli process with
probability ``p_loss`` (eq. 5) and the surviving ones arrive after a delay
drawn from the shifted ("generalised") exponential pdf of eq. 7,

    P(tau) = (1/phi) exp(-(tau - eta)/phi)  for tau >= eta,  0 otherwise.

All functions are pure JAX and work under ``jax.jit`` and ``jax.vmap`` (over
keys and over a ``Channel`` with batched leaves).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import check_given, check_int, check_nonneg, check_range, checked_pytree, unchecked

__all__ = [
    "Channel",
    "Arrivals",
    "sample_channel",
    "quantise_delay",
    "late",
    "expected_delay",
    "delay_cdf",
]

_DTYPE = jnp.float32
# Relative guard for quantise_delay: about 4 float32 ulps.  Absorbs the
# round-off of delay/T (at most ~1.5 ulp for decimal inputs) while keeping
# e.g. 0.1000001 / 0.1 (8 ulps above 1) distinguishable from 1.
_QUANT_RTOL = 2.0**-21


@checked_pytree
@dataclasses.dataclass(frozen=True)
class Channel:
    """One direction of the network: Bernoulli loss (eq. 5) and shifted-exponential delay (eq. 7).

    Attributes:
      p_loss: packet dropout probability, in [0, 1) (eq. 5).
      eta: delay shift in seconds, >= 0 (eq. 7).
      phi: delay scale (mean excess over ``eta``) in seconds, >= 0 (eq. 7);
        ``phi = 0`` means the deterministic delay ``eta``.

    All three are dynamic pytree leaves, so they can be vmapped or
    differentiated.  Validation runs only on concrete Python/NumPy values (a
    number, or an array checked element-wise), when a person builds a Channel:
    ValueError for None, a string, a value out of range or not finite. jax
    rebuilds Channels (tracers, gradients) without validating them; a ``vmap``
    ``in_axes`` prefix, whose fields are axes or None, is :meth:`in_axes`.
    """

    p_loss: float | jax.Array = 0.0
    eta: float | jax.Array = 0.0
    phi: float | jax.Array = 0.0

    @classmethod
    def in_axes(cls, p_loss=None, eta=None, phi=None) -> "Channel":
        """A ``vmap`` ``in_axes`` prefix for a Channel argument: each field an axis or
        None (not validated), e.g. ``Channel.in_axes(p_loss=0)`` maps over p_loss only."""
        return unchecked(cls, p_loss=p_loss, eta=eta, phi=phi)

    def __post_init__(self):
        for name in ("p_loss", "eta", "phi"):
            check_given(f"Channel.{name}", getattr(self, name))
        check_range("Channel.p_loss", self.p_loss, 0.0, 1.0, high_open=True)
        check_nonneg("Channel.eta", self.eta)
        check_nonneg("Channel.phi", self.phi)


class Arrivals(NamedTuple):
    """Per-packet outcome of :func:`sample_channel`."""

    lost: jax.Array  # bool[n]: True when the packet is dropped (eq. 5)
    delay: jax.Array  # float32[n]: delay in seconds (eq. 7), drawn even for lost packets


def sample_channel(key, channel: Channel, n: int) -> Arrivals:
    """Draw ``n`` independent packets through ``channel`` (eq. 5 and 7).

    Common random numbers: ``u ~ U(0, 1)`` and ``lost = u < p_loss``, so with
    the same key the loss pattern at a lower ``p_loss`` is a subset of that at
    a higher one.  The delay ``eta + phi * Exponential(1)`` uses a separate
    subkey and does not depend on ``p_loss``.  ``n`` is a static Python int >= 0
    (ValueError otherwise, before tracing).
    """
    check_int("sample_channel: n", n, 0)
    n = int(n)
    k_loss, k_delay = jax.random.split(key)
    p = jnp.asarray(channel.p_loss, _DTYPE)
    eta = jnp.asarray(channel.eta, _DTYPE)
    phi = jnp.asarray(channel.phi, _DTYPE)
    u = jax.random.uniform(k_loss, (n,), _DTYPE)
    e = jax.random.exponential(k_delay, (n,), _DTYPE)
    return Arrivals(lost=u < p, delay=eta + phi * e)


def quantise_delay(delay, T) -> jax.Array:
    """Delay in whole fast periods ``T``: ``ceil(delay / T)`` as int32.

    A packet is usable at the first fast instant at or after its arrival.
    A relative guard of a few float32 ulps absorbs division round-off, so a
    delay of exactly ``m*T`` gives ``m`` (not ``m + 1``).
    """
    delay = jnp.asarray(delay, _DTYPE)
    T = jnp.asarray(T, _DTYPE)
    steps = jnp.ceil((delay / T) * (1.0 - _QUANT_RTOL))
    return jnp.maximum(steps, 0.0).astype(jnp.int32)


def late(delay, tau_max) -> jax.Array:
    """True where the packet arrives after ``tau_max`` and is discarded.

    The paper (section 2.3) forces ``tau_max < N T`` to avoid packet disorder.
    """
    return jnp.asarray(delay, _DTYPE) > jnp.asarray(tau_max, _DTYPE)


def expected_delay(channel: Channel) -> float | jax.Array:
    """Mean of the eq. 7 delay: ``eta + phi``."""
    return channel.eta + channel.phi


def delay_cdf(channel: Channel, tau) -> jax.Array:
    """Closed-form CDF of eq. 7: 0 for ``tau < eta``, ``1 - exp(-(tau - eta)/phi)`` otherwise.

    For ``phi = 0`` it is the unit step at ``eta``.  Safe to differentiate
    (no NaN from the ``phi = 0`` branch).
    """
    tau = jnp.asarray(tau, _DTYPE)
    eta = jnp.asarray(channel.eta, _DTYPE)
    phi = jnp.asarray(channel.phi, _DTYPE)
    pos = phi > 0.0
    safe_phi = jnp.where(pos, phi, 1.0)
    z = jnp.maximum(tau - eta, 0.0) / safe_phi
    cdf = jnp.where(pos, -jnp.expm1(-z), 1.0)
    return jnp.where(tau < eta, 0.0, cdf).astype(_DTYPE)
