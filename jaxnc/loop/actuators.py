"""Actuators: a buffer of received packets indexed by time stamp (seed 000 section 2.4).

:class:`PacketActuator` keeps the ``capacity`` received packets with the newest stamps.
At fast instant t it applies, of the packets whose stamp is <= t, the newest: its action
``data[t - stamp]``. When that packet is exhausted (t - stamp >= H) or none has arrived,
it holds the last action it applied (``on_exhausted="hold"``, seed 001 eq. 4) or applies
zero (``"zero"``). Each action lasts one fast period (``span="fast"``: action i of a packet
stamped s is due at t = s + i) or one period of the loop, N fast periods (``span="period"``:
due for s + i N <= t < s + (i + 1) N), the zero strategy's action over the controller's
period (:func:`ZeroOrder`). A packet that arrives after all its actions are due (a one-action
packet delayed by a fast period or more) is then never applied (``late="drop"``, the
time-stamped actuator of seeds 000 and 001); with ``late="apply"`` its last action is
applied from its arrival and held. A packet of one action (H = 1) stamped with the
instant it is sent, ``late="apply"``, makes the plain hold-last actuator
(:func:`HoldLast`: the newest action received, applied on arrival, however late); a packet of H future actions is
packet-based control (seeds 000, 003, 004); a capacity > 1 keeps packets stamped for the
future (seed 001's commands stamped k + lead) until their time comes. Before the first
packet's action is due, a holding actuator applies its ``initial`` action (0 by default: an
operating point's input, e.g. a lift's hover thrust, the same as the controller's bias
:attr:`jaxnc.loop.PID.u_bias`, keeps the plant there until the first packet arrives).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_given, check_int, check_range, concrete
from jaxnc.loop.base import AbstractActuator, Inbox, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["PacketActuator", "ActuatorState", "HoldLast", "ZeroOrder"]

_EMPTY = -(2**30)


class ActuatorState(NamedTuple):
    """The state of a :class:`PacketActuator`: its buffered packets and the last action."""

    u: jax.Array         # float[B, H, m] actions of the buffered packets
    stamp: jax.Array     # int32[B] their stamps (_EMPTY: free slot)
    last: jax.Array      # float[m] the last action applied
    period: Any = ()     # int32: fast periods an action lasts (span="period"; () with span="fast")


def install(state: ActuatorState, actions, stamp, w) -> ActuatorState:
    """A :class:`PacketActuator`'s buffer with one more packet (actions float[H, m], stamp)
    of weight ``w`` (0/1 float): in the slot of the oldest stamp, if it is newer than that one."""
    j = jnp.argmin(state.stamp)
    take = (w > 0.5) & (stamp > state.stamp[j])
    wt = jnp.where(take, jnp.asarray(w, jnp.float32), 0.0)
    u = state.u.at[j].set(blend(wt, jnp.asarray(actions, jnp.float32), state.u[j]))
    return state._replace(u=u, stamp=state.stamp.at[j].set(jnp.where(take, stamp, state.stamp[j])))


@_dataclass
class PacketActuator(AbstractActuator):
    """Packet buffer by time stamp (module docstring).

    Attributes:
      horizon: static H, actions per packet (must equal the controller's).
      capacity: static B >= 1, packets kept.
      on_exhausted: static, ``"hold"`` or ``"zero"``.
      late: static, ``"drop"`` (a packet that arrives after all its actions are due is not
        applied) or ``"apply"`` (its last action is applied from its arrival; needs
        ``on_exhausted="hold"``).
      span: static, how long each action lasts: ``"fast"`` (one fast period) or
        ``"period"`` (the loop's period, N fast periods: ``Context.N``).
      initial: float or float[m], the action held before the first packet's action is due
        (``on_exhausted="hold"``; 0 by default).

    Raises:
      ValueError: naming the field, for a horizon or capacity out of range, an unknown
        option, ``late="apply"`` without ``on_exhausted="hold"``, a non-finite ``initial`` or
        a nonzero one with ``on_exhausted="zero"`` (it would never be applied); when a
        ``Loop`` is built, an ``initial`` whose size is not 1 or the plant's input_dim.
    """

    field_shapes = {"initial": ((), ("input",))}

    horizon: int = _static(1)
    capacity: int = _static(1)
    on_exhausted: str = _static("hold")
    late: str = _static("drop")
    span: str = _static("fast")
    initial: Any = 0.0

    def __post_init__(self):
        check_int("PacketActuator.horizon", self.horizon, 1, 1_000_000)
        check_int("PacketActuator.capacity", self.capacity, 1, 10_000)
        if self.on_exhausted not in ("hold", "zero"):
            raise ValueError(f"PacketActuator.on_exhausted must be one of hold, zero, got {self.on_exhausted!r}")
        if self.late not in ("drop", "apply"):
            raise ValueError(f"PacketActuator.late must be one of drop, apply, got {self.late!r}")
        if self.late == "apply" and self.on_exhausted != "hold":
            raise ValueError("PacketActuator.late='apply' needs on_exhausted='hold' (a late packet's last action "
                             "is held)")
        if self.span not in ("fast", "period"):
            raise ValueError(f"PacketActuator.span must be one of fast, period, got {self.span!r}")
        check_given("PacketActuator.initial", self.initial)
        check_range("PacketActuator.initial", self.initial)
        if self.on_exhausted == "zero" and concrete(self.initial) and np.any(np.asarray(self.initial)):
            raise ValueError("PacketActuator.initial is held only with on_exhausted='hold' (with 'zero' the actuator "
                             f"applies 0 when it has no action due), got {self.initial!r}")

    def init(self, ctx) -> ActuatorState:
        m = ctx.input_dim
        return ActuatorState(jnp.zeros((self.capacity, self.horizon, m), jnp.float32),
                             jnp.full((self.capacity,), _EMPTY, jnp.int32),
                             jnp.broadcast_to(jnp.asarray(self.initial, jnp.float32), (m,)),
                             jnp.asarray(ctx.N, jnp.int32) if self.span == "period" else ())

    def receive(self, state: ActuatorState, inbox: Inbox) -> ActuatorState:
        C = inbox.stamp.shape[0]
        for c in range(C):                       # C is static and small
            state = install(state, inbox.data[c], inbox.stamp[c], inbox.new[c])
        return state

    def output(self, state: ActuatorState, t):
        valid = (state.stamp != _EMPTY) & (state.stamp <= t)
        key = jnp.where(valid, state.stamp, _EMPTY)
        j = jnp.argmax(key)
        idx = t - state.stamp[j]
        if self.span == "period":
            idx = idx // state.period
        live = valid[j] & (idx < self.horizon)
        u_pkt = state.u[j, jnp.clip(idx, 0, self.horizon - 1)]
        fallback = state.last if self.on_exhausted == "hold" else jnp.zeros_like(state.last)
        if self.late == "apply":        # the newest packet's last action: a late one's too
            fallback = jnp.where(valid[j], state.u[j, self.horizon - 1], fallback)
        u = jnp.where(live, u_pkt, fallback)
        return state._replace(last=u), u


def HoldLast(capacity: int = 1, initial: Any = 0.0) -> PacketActuator:
    """Applies the newest received action (by time stamp) from its arrival, however late,
    and holds it (packets of one action; ``late="apply"``); ``initial`` (float or float[m])
    before the first arrives."""
    return PacketActuator(horizon=1, capacity=capacity, on_exhausted="hold", late="apply", initial=initial)


def ZeroOrder(capacity: int = 1) -> PacketActuator:
    """The zero strategy: the action of the controller's packet stamped kN is applied over
    its period, kN <= t < (k + 1) N, from its arrival; zero in a period whose packet was
    lost or arrives after the period (packets of one action; ``span="period"``,
    ``on_exhausted="zero"``)."""
    return PacketActuator(horizon=1, capacity=capacity, on_exhausted="zero", span="period")
