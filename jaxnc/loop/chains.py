"""Packet-based control with prediction chains: the NUDREKF scheme's controller and actuator.

Seed 000, section 3.3.1. The remote side's filter (the NUDREKF: ``ekf_predict`` once per
fast period along the actions the remote side itself sent, eq. 11, a correction when a
sensor packet arrives, eq. 13) is :class:`jaxnc.loop.EKF` with ``form="sequential"``,
``weight="slot"``, ``output="weighted"`` and ``keep_means=True``
(:func:`jaxnc.schemes.mecanum.mecanum_loop`). Here are its controller and actuator: the
prediction stage (steps 1-5) iterates controller and model h*N times from the corrected
estimate, producing the control actions u_{k..k+hN-1} sent as one packet;
:class:`ChainController` and :class:`ChainActuator` hold packets as prediction chains
(:class:`jaxnc.controllers.prediction.PacketChain`), advanced one fast period at a time.
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc.controllers.prediction import PacketChain, advance_chain, exhausted_chain, start_chain
from jaxnc.loop.base import AbstractActuator, AbstractController, Inbox, Packet, blend
from jaxnc.loop.base import static_field as _static
from jaxnc.loop.estimators import WeightedEstimate


# ----------------------------------------------------------------------------- loop roles
# The NUDREKF scheme as roles of jaxnc.loop (seed 000, section 3.3.1): a packet is a
# prediction chain. The remote controller keeps its copy of the packet it last installed
# and advances it over each period (what the remote filter propagates along); each packet
# carries that copy's chain at every instant of its period, so the actuator installs the
# chain at the instant the packet arrives.


class ChainPacket(NamedTuple):
    """The payload of a control packet stamped kN: ``chain``, the sender's copy of its
    packet at each fast instant kN .. kN + N of the period (a :class:`PacketChain` with a
    leading axis of N + 1), and ``weight``, the 0/1 float "the remote side installed a new
    packet now" (with the trigger's straight-through gradient). A packet of weight 0 (the
    copy continued) still travels, so that this gradient reaches the actuator at the instant
    the packet would have arrived, as in the hand-written loop."""

    chain: PacketChain
    weight: jax.Array


class ChainActuatorState(NamedTuple):
    chain: PacketChain      # the installed packet, at the current instant
    stamp: jax.Array        # int32, its time stamp (-1: the idle chain before the first packet)
    now: jax.Array          # int32, the next fast instant (the actuator's clock: the last output's t + 1)


def _idle_chain(act: "ChainActuator", m: int) -> PacketChain:
    """The chain before the first packet: it holds zero at ``act.mean0``."""
    return exhausted_chain(jnp.asarray(act.mean0, jnp.float32), jnp.zeros((m,), jnp.float32), act.law.init(),
                           act.horizon)


def _advance(act: "ChainActuator", chain: PacketChain) -> PacketChain:
    """``chain`` one fast period on with ``act``'s model and law (narrow path search)."""
    nxt = lambda m, c: act.law(act.model, m, c, act.Ts, narrow=True)
    return advance_chain(act.model, nxt, chain, act.horizon, act.hold, act.noise_dim)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ChainActuator(AbstractActuator):
    """The actuator of packet-based control with packets held as prediction chains (seed 000
    section 2.4 and 3.3.1).

    Every fast period it applies the action its chain holds for the instant and advances the
    chain one period (:func:`advance_chain`; past h*N actions the last is held). When a
    packet stamped s arrives at instant t (with its weight) it installs the packet's chain
    at position t - s (:class:`ChainPacket` carries the positions 0..N; the downlink's delays
    must not exceed N fast periods, seed 000's tau_max <= NT), so it continues exactly as
    if it had advanced the packet itself from s.

    Attributes:
      model: the kinematic model the chain is predicted with; law: the control law,
        ``law(model, mean, c, Ts, narrow=...) -> (u, c)`` with ``law.init()``
        (:class:`jaxnc.controllers.path_following.PathFollower`).
      Ts: the law's period (s); horizon: int32, actions per packet (h*N); hold: int32,
        fast periods each action is held (N single rate, 1 dual rate).
      mean0: float[n], the idle chain's state before the first packet (it applies zero).
      noise_dim: static, the model's process-noise dimension (the chain is noise-free).
    """

    model: Any
    law: Any
    Ts: Any
    horizon: Any = dataclasses.field()      # a leaf without default (the base declares None)
    hold: Any
    mean0: Any
    noise_dim: int = _static(0)

    def init(self, ctx) -> ChainActuatorState:
        z = jnp.zeros((), jnp.int32)
        return ChainActuatorState(_idle_chain(self, ctx.input_dim), z - 1, z)

    def receive(self, state: ChainActuatorState, inbox: Inbox) -> ChainActuatorState:
        """Install the newest delivered packet's chain at the current instant, with the
        packet's weight."""
        # the newest packet's slot, then one gather of its chain at position d (not the whole period's)
        i, stamp, wn = inbox._replace(data=jnp.arange(inbox.stamp.shape[0])).newest()
        pkt = inbox.data
        w = wn * pkt.weight[i]
        d = jnp.clip(state.now - stamp, 0, pkt.chain.j.shape[1] - 1)
        chain = jax.tree.map(lambda a: a[i, d], pkt.chain)
        return ChainActuatorState(blend(w, chain, state.chain), jnp.where(w > 0.5, stamp, state.stamp).astype(jnp.int32),
                                  state.now)

    def output(self, state: ChainActuatorState, t):
        """(state advanced one fast period, u_t)."""
        return ChainActuatorState(_advance(self, state.chain), state.stamp, jnp.asarray(t + 1, jnp.int32)), state.chain.u


class ChainCopy(NamedTuple):
    """:class:`ChainController`'s state: the sender's copy of the packet it last installed."""

    chain: PacketChain      # the copy at the next slow instant
    sent: jax.Array         # float[N, m]: the actions the copy applied over the last period


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ChainController(AbstractController):
    """The remote controller of section 3.3.1, keeping its copy of what it sent
    (``keeps_copy``).

    At slow instant k, from the corrected estimate it starts a new prediction chain (step 1,
    :func:`start_chain`) that continues the controller state its copy predicted for this
    instant, and installs it in its copy with the weight of the estimate (a
    :class:`jaxnc.loop.WeightedEstimate` of ``EKF(output="weighted")``; a plain mean: the
    uplink's ``fresh``): a new packet exactly when a measurement arrived; it then advances the copy over the period,
    as ``actuator`` would. The packet, stamped kN, is the copy at each instant kN .. kN + N
    (:class:`ChainPacket`); :meth:`sent` gives the copy's N actions (what the remote filter
    propagates along). Every slow instant's packet is handed to the link (send = 1): the
    runner's controller transmission counts are therefore per slow instant, the scheme's
    are the weights.

    Attributes:
      actuator: the :class:`ChainActuator` its packets drive (model, law, Ts, horizon,
        hold, mean0): the copy advances as it does.
    """

    actuator: Any
    keeps_copy = True

    def init(self, ctx) -> ChainCopy:
        return ChainCopy(_idle_chain(self.actuator, ctx.input_dim), jnp.zeros((ctx.N, ctx.input_dim), jnp.float32))

    def step(self, state: ChainCopy, xhat, fresh, k, ctx):
        a = self.actuator
        mean, w = (xhat.mean, xhat.weight) if isinstance(xhat, WeightedEstimate) else (xhat, fresh)
        w = jnp.asarray(w, jnp.float32)
        new = start_chain(lambda m, c: a.law(a.model, m, c, a.Ts), mean, state.chain.c_before)
        copy = blend(w, new, state.chain)
        last, chains = jax.lax.scan(lambda ch, _: (_advance(a, ch), ch), copy, None, length=ctx.N)
        period = jax.tree.map(lambda cs, c: jnp.concatenate([cs, c[None]], axis=0), chains, last)
        pkt = Packet(ChainPacket(period, w), (k * ctx.N).astype(jnp.int32))
        return ChainCopy(last, chains.u), pkt, jnp.ones((), jnp.float32)

    def sent(self, state: ChainCopy):
        """float[N, m]: the actions the copy applied over the period of the last step."""
        return state.sent
