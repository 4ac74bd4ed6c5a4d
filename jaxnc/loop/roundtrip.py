"""A round-trip delay lumped on one direction of the loop.

When the sensor-to-controller delay is not modelled on the uplink (the controller runs as
soon as a measurement arrives, seed 000 section 2.3), the delay that matters to the
actuator is the sum of both directions' delays (seed 000 eq. 6-7): :class:`RoundTrip`
draws each direction from its own delay model, adds the seconds and quantises the sum up
to whole fast periods (:func:`jaxnc.network.quantise_delay`), as one delay model of a
:class:`~jaxnc.loop.Link`.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxnc._validate import check_instance
from jaxnc.loop.base import AbstractDelay
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.network import quantise_delay

__all__ = ["RoundTrip"]


@_dataclass
class RoundTrip(AbstractDelay):
    """tau = tau_forward + tau_back seconds, quantised up to the fast period.

    Args:
      forward: the delay model of the direction the link carries (e.g. controller ->
        actuator, :class:`~jaxnc.loop.ShiftedExponential`, seed 000 eq. 7).
      back: the delay model of the other direction (sensor -> controller), drawn
        independently.

    ``sample(key, n, T)`` returns ``(steps int32[n], seconds float32[n])`` with
    ``seconds = forward_seconds + back_seconds`` and ``steps = ceil(seconds / T)`` (the sum
    of the parts' steps where both draw whole fast periods, ``in_steps``); the two
    directions use ``split(key)``'s two keys. A packet lost in either direction (a
    part's steps negative: :class:`~jaxnc.loop.TraceDelay`, :class:`~jaxnc.loop.WifiModel`)
    is lost: steps -1, seconds 0.

    Raises:
      ValueError: when ``forward`` or ``back`` is not a delay model.
    """

    forward: Any
    back: Any

    @property
    def in_steps(self) -> bool:
        """Declared (:class:`~jaxnc.loop.AbstractDelay`): both parts draw whole fast periods, so
        the sum does and a link compares it with ``tau_max`` in periods (in float32 seconds
        3 T + 4 T can round above tau_max = 7 T and every packet would be discarded)."""
        return bool(self.forward.in_steps and self.back.in_steps)

    def __post_init__(self):
        check_instance("RoundTrip.forward", self.forward, AbstractDelay, "a delay model (AbstractDelay)")
        check_instance("RoundTrip.back", self.back, AbstractDelay, "a delay model (AbstractDelay)")

    def bounds(self, T):
        """(lo, hi) in fast periods: ceil(a + b) >= ceil(a) + ceil(b) - 1 gives the
        lower bound (the sum of the parts' where both draw whole periods, ``in_steps``); the
        upper bound is the sum of the parts' (None if either is)."""
        lo_f, hi_f = self.forward.bounds(T)
        lo_b, hi_b = self.back.bounds(T)
        lo = lo_f + lo_b if self.in_steps else max(lo_f, lo_b, lo_f + lo_b - 1, 0)
        hi = None if hi_f is None or hi_b is None else hi_f + hi_b
        return lo, hi

    def packets(self):
        """The fewer of the parts' (a recorded part's length), None if neither has a limit."""
        caps = [c for c in (self.forward.packets(), self.back.packets()) if c is not None]
        return min(caps) if caps else None

    def sample(self, key, n: int, T):
        kf, kb = jax.random.split(key)
        df, sf = self.forward.sample(kf, n, T)
        db, sb = self.back.sample(kb, n, T)
        lost = (df < 0) | (db < 0)
        tau = jnp.where(lost, 0.0, sf + sb)
        steps = df + db if self.in_steps else quantise_delay(tau, T)
        return jnp.where(lost, -1, steps).astype(jnp.int32), tau
