"""Parts for a receiver without time stamps (seed 001's emulation design, eq. 5).

With a link of ``order="arrival"`` the receiver takes whatever arrives now, even a packet
older than one it already holds (of several arriving together, the newest by stamp); it
detects no loss and does not know a packet's age. Two parts use only that:

* :class:`DirtyDerivative` (estimator): holds the most recently arrived measurement and
  differences it over the slow period (seed 001 section 5's "simple differentiation"),
  optionally through a first-order filter;
* :class:`ArrivalHold` (actuator): applies the action of the most recently arrived packet
  and holds it.

Neither is :class:`~jaxnc.loop.Passthrough` / :class:`~jaxnc.loop.PacketActuator`:
``PacketActuator`` applies a packet by its stamp (a late one-action packet is already
exhausted, an older one than it holds is ignored), which is what a receiver without
stamps cannot do.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import array_fields, check_given, check_nonneg, concrete
from jaxnc.loop.base import AbstractActuator, AbstractEstimator, Inbox, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass

__all__ = ["DirtyDerivative", "DirtyDerivativeState", "ArrivalHold"]


class DirtyDerivativeState(NamedTuple):
    """The state of a :class:`DirtyDerivative` estimator: the held measurement and its rate."""

    z: jax.Array        # float[p] the held measurement
    rate: jax.Array     # float[p] its (filtered) difference quotient
    held: jax.Array     # float 0/1: a measurement has arrived
    dt: jax.Array       # float: the slow period N T (s)


@_dataclass
class DirtyDerivative(AbstractEstimator):
    """The held measurement and its rate, without a model (seed 001 eq. 5 and section 5).

    At slow instant k, with ``zbar_k`` the measurement delivered now (or, if none, the one
    held) and ``dt = N T``:

        r_k = a r_{k-1} + (1 - a) (zbar_k - zbar_{k-1}) / dt,   a = exp(-dt / tau_d)

    With an arrival every period this is scipy's ``cont2discrete`` of ``s / (tau_d s + 1)``
    by ZOH, ``(1/tau_d)(1 - z^-1)/(1 - a z^-1)``, scaled by ``(1 - a) tau_d / dt``: unit gain
    on the difference quotient (a ramp's slope is read exactly), where the ZOH form reads it
    ``dt / ((1 - a) tau_d)`` times too high (tests/test_parts_balancing.py).

    ``tau_d = 0`` gives ``a = 0``, the backward difference ``(zbar_k - zbar_{k-1}) / dt``:
    0 where nothing new arrives, the whole change since the previous arrival divided by one
    period where something does. Before the first arrival the estimate is 0; the first
    arrival is held with rate 0 (there is no earlier sample to difference).

    Attributes:
      tau_d: float >= 0, the filter's time constant (s); 0: the simple difference; or
        float[p], one per measured output.

    Returns (``correct``): xhat float[2p] = ``(zbar_k, r_k)``.

    Raises:
      ValueError: ``tau_d`` missing or negative; when the Loop is built, a ``tau_d`` with
        another number of entries than the plant's outputs (its rates had that many entries
        and the loop failed with a state-shape message, or broadcast one output to two).
    """

    tau_d: Any = 0.0

    inputs = "applied"

    def __post_init__(self):
        check_given("DirtyDerivative.tau_d", self.tau_d)
        check_nonneg("DirtyDerivative.tau_d", self.tau_d)
        array_fields(self, "tau_d")

    def init(self, ctx) -> DirtyDerivativeState:
        if concrete(self.tau_d) and np.ndim(self.tau_d) > 0 and np.shape(self.tau_d) != (ctx.output_dim,):
            raise ValueError(f"DirtyDerivative.tau_d must be a number or float[{ctx.output_dim}] (one per measured "
                             f"output), got shape {np.shape(self.tau_d)}")
        z = jnp.zeros((ctx.output_dim,), jnp.float32)
        return DirtyDerivativeState(z, z, jnp.float32(0.0), jnp.float32(ctx.N * ctx.T))

    def correct(self, state: DirtyDerivativeState, inbox: Inbox, k):
        y, _, w = inbox.newest()
        z = blend(w, y, state.z)
        prev = blend(state.held, state.z, z)        # the first arrival: nothing to difference
        tau = jnp.asarray(self.tau_d, jnp.float32)
        a = jnp.where(tau > 0, jnp.exp(-state.dt / jnp.maximum(tau, 1e-30)), 0.0)
        rate = a * state.rate + (1.0 - a) * (z - prev) / state.dt
        held = jnp.maximum(state.held, w)
        return DirtyDerivativeState(z, rate, held, state.dt), jnp.concatenate([z, rate])

    def predict(self, state, u_applied, u_believed, k):
        return state


@_dataclass
class ArrivalHold(AbstractActuator):
    """Applies the first action of the packet delivered last and holds it; 0 before the
    first. With ``order="arrival"`` on the downlink that is the most recently arrived
    packet, whatever its stamp (seed 001 eq. 4-5 without time stamps).

    State float[m], the held action; ``output`` returns ``(state, u)`` with u float[m].
    """

    def init(self, ctx):
        return jnp.zeros((ctx.input_dim,), jnp.float32)

    def receive(self, u, inbox: Inbox):
        data, _, w = inbox.newest()
        return blend(w, jnp.asarray(data[0], jnp.float32), u)

    def output(self, u, t):
        return u, u
