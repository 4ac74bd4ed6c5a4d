"""An actuator that starts a packet's actions when the packet arrives (seed 004, scenario d).

A packet carries the H actions of one period of H fast instants, stamped with the period's
first instant s. Where :class:`jaxnc.loop.PacketActuator` plays them by time stamp
(``data[t - s]``: the actions due before the arrival are skipped), an
:class:`ArrivalActuator` plays them from the instant a of arrival, ``data[t - a]``, and
stops at the end of the period (t < s + H): a delayed packet shifts its actions and its
tail is cut. Outside that window, and before the first packet, it holds the last action
applied (zero at first). This is dual-rate control with delays when the local side starts
the period's actions only once the reference arrives.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import check_int
from jaxnc.loop.base import AbstractActuator, Inbox, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["ArrivalActuator", "ArrivalState"]

_EMPTY = -(2**30)


class ArrivalState(NamedTuple):
    """The state of an :class:`ArrivalActuator`: the newest packet and when its actions started."""

    u: jax.Array         # float[H, m] the newest packet's actions
    stamp: jax.Array     # int32 its time stamp (the start of its period)
    start: jax.Array     # int32 fast instant its first action started (_EMPTY: none yet)
    pending: jax.Array   # bool: a packet was received and starts at the next output
    last: jax.Array      # float[m] the last action applied


@_dataclass
class ArrivalActuator(AbstractActuator):
    """Plays a packet's actions from its arrival to the end of its period (module docstring).

    Attributes:
      horizon: static H >= 1, actions per packet (the controller's horizon).

    ``receive``: installs the newest delivered packet if it is newer (by stamp) than the one
    it holds (over a link of ``order="all"`` an older packet arriving after a newer one would
    cut the newer one's actions); ``output(state, t)``: its action ``data[t - arrival]``
    while t < stamp + H, else the last action applied.

    Raises:
      ValueError: ``horizon`` not an integer >= 1.
    """

    horizon: int = _static(1)

    def __post_init__(self):
        check_int("ArrivalActuator.horizon", self.horizon, 1, 1_000_000)

    def init(self, ctx) -> ArrivalState:
        m = ctx.input_dim
        e = jnp.asarray(_EMPTY, jnp.int32)
        return ArrivalState(jnp.zeros((self.horizon, m), jnp.float32), e, e, jnp.zeros((), bool),
                            jnp.zeros((m,), jnp.float32))

    def receive(self, state: ArrivalState, inbox: Inbox) -> ArrivalState:
        data, stamp, w = inbox.newest()
        take = (w > 0.5) & (stamp > state.stamp)    # an older packet arriving late (order="all") is not played
        return state._replace(u=blend(jnp.where(take, w, 0.0), jnp.asarray(data, jnp.float32), state.u),
                              stamp=jnp.where(take, stamp, state.stamp), pending=state.pending | take)

    def output(self, state: ArrivalState, t):
        start = jnp.where(state.pending, t, state.start)
        live = (start != _EMPTY) & (t < state.stamp + self.horizon)
        u = jnp.where(live, state.u[jnp.clip(t - start, 0, self.horizon - 1)], state.last)
        return state._replace(start=start, pending=jnp.zeros((), bool), last=u), u
