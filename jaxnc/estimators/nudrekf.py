"""Non-uniform dual-rate EKF with h-step-ahead prediction stage (NUDREKF).

Seed 000, section 3.3.1. The filter runs at the fast period T. When a sensor packet
arrives (event triggered, eq. 4, and not dropped) it corrects with eq. (13); then the
prediction stage (steps 1-5) iterates controller and model h*N times, producing the
fast-rate estimates xi_{k..k+hN-1} and the control actions u_{k..k+hN-1} that are sent
as one packet (packet-based control).

Between corrections the covariance is propagated with eq. (11) once per elapsed fast
period (``ekf_predict``), along the control actions the remote side itself sent (it
cannot know whether the controller-to-actuator packet was lost). Propagating P along
the whole horizon at every correction, as the text literally says, would compute
h*N covariance steps of which only those up to the next correction are ever used.

The scheme's roles in :mod:`jaxnc.loop` live here too: :class:`NudrekfEstimator`,
:class:`ChainController` and :class:`ChainActuator` (packets as prediction chains,
:class:`jaxnc.controllers.prediction.PacketChain`).
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc.controllers.prediction import PacketChain, advance_chain, exhausted_chain, start_chain
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update, ekf_update_diag
from jaxnc.estimators.sparsity import EKFStructure
from jaxnc.loop.base import AbstractActuator, AbstractController, AbstractEstimator, Inbox, Packet, blend
from jaxnc.loop.base import static_field as _static


def nudrekf_correct(model, belief: Gaussian, z, R, *, jacobian_grad: bool = True,
                    structure: EKFStructure | None = None) -> Gaussian:
    """Correction at an arrival instant, eq. (13)-(16).

    ``R`` is the measurement noise covariance [s, s], or a vector of variances for
    additive noise with a diagonal covariance (then the update is processed one
    scalar at a time: same result, no factorisation; see ``ekf_update_diag``, which
    also explains ``jacobian_grad`` and ``structure``; the general update is dense)."""
    if jnp.ndim(R) == 1:
        return ekf_update_diag(model.measure, belief, z, R, z.shape[0], jacobian_grad=jacobian_grad,
                               structure=structure)
    if not jacobian_grad:
        raise ValueError("nudrekf_correct: jacobian_grad=False needs a diagonal R (a vector of variances)")
    return ekf_update(model.measure, belief, z, R, z.shape[0])


# ----------------------------------------------------------------------------- loop roles
# The NUDREKF scheme as roles of jaxnc.loop (seed 000, section 3.3.1): a packet is a
# prediction chain. The remote controller keeps its copy of the packet it last installed
# and advances it over each period (what the remote filter propagates along); each packet
# carries that copy's chain at every instant of its period, so the actuator installs the
# chain at the instant the packet arrives.


class ChainEstimate(NamedTuple):
    """What :class:`NudrekfEstimator` hands the controller at a slow instant.

    ``mean`` float[n] is the corrected estimate (eq. 13; computed whether or not a
    measurement arrived), ``weight`` the 0/1 float "a measurement arrived and was used
    now" (the sensor's send decision times the uplink's delivery, with the trigger's
    straight-through gradient): the remote side sends a packet exactly then."""

    mean: jax.Array
    weight: jax.Array


class NudrekfState(NamedTuple):
    belief: Gaussian        # the remote belief (after the last correction / prediction)
    means: jax.Array        # float[N, n]: belief means after each fast period of the last prediction


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NudrekfEstimator(AbstractEstimator):
    """The remote NUDREKF as a loop estimator (seed 000 eq. 11-16).

    At a slow instant it corrects with the delivered measurement (eq. 13, additive noise
    with diagonal covariance: :func:`nudrekf_correct`); over the period it propagates the
    belief once per fast period (eq. 11) along the actions the remote side *sent* (the
    runner's ``u_believed``: it cannot know whether a control packet was lost).

    The filter of :class:`jaxnc.loop.EKF` with ``buffer=0``, but: the correction is the
    scalar-sequential :func:`~jaxnc.estimators.ekf.ekf_update_diag` (diagonal R, sparsity
    ``structure``); the measurement's weight is its ring slot's (the trigger's
    straight-through gradient also when the sensor is silent); the estimate is a
    :class:`ChainEstimate` (mean and weight); the means after every fast period are kept.

    Attributes:
      model: the kinematic model (``dynamics``, ``measure``, ``noise_dim``).
      Q: float[q], process noise variances per fast period; R: float[p], measurement
        noise variances.
      mean0: float[n], cov0: float[n, n], the prior at t = 0.
      noise_dim: static, the model's process-noise dimension q.
      jacobian_grad, structure: static, as in :func:`jaxnc.estimators.ekf.ekf_predict`.
    """

    model: Any
    Q: Any
    R: Any
    mean0: Any
    cov0: Any
    noise_dim: int = _static(0)
    jacobian_grad: bool = _static(True)
    structure: EKFStructure | None = _static(None)
    inputs = "believed"
    by_stamp = True

    def init(self, ctx) -> NudrekfState:
        g = Gaussian(jnp.asarray(self.mean0, jnp.float32), jnp.asarray(self.cov0, jnp.float32))
        return NudrekfState(g, jnp.zeros((ctx.N, g.mean.shape[0]), jnp.float32))

    def correct(self, state: NudrekfState, inbox: Inbox, k) -> tuple[NudrekfState, ChainEstimate]:
        """Correct with the measurement of instant k (weight 0: keep the belief); the
        estimate is the corrected mean with the weight of the measurement.

        The measurement of instant k is in slot k mod C of the ring, with the weight
        beta_k (1 - lost_k), which carries the trigger's straight-through gradient also
        when the sensor stays silent (``Inbox.new`` is 0 without a gradient there); a
        packet sent but not delivered by instant k (a delayed uplink; seed 000's has no
        delay, it lumps the round trip on the downlink) weighs 0: it is not used late."""
        slot = jnp.mod(k, inbox.stamp.shape[0])
        late = (inbox.stamp[slot] >= 0) & ~inbox.arrived[slot]      # sent, not delivered yet
        z, w = jax.tree.map(lambda a: a[slot], inbox.data), jnp.where(late, 0.0, inbox.weight[slot])
        corrected = nudrekf_correct(self.model, state.belief, z, self.R, jacobian_grad=self.jacobian_grad,
                                    structure=self.structure)
        belief = blend(w, corrected, state.belief)
        return state._replace(belief=belief), ChainEstimate(corrected.mean, w)

    def predict(self, state: NudrekfState, u_applied, u_believed, k) -> NudrekfState:
        """Eq. (11) once per fast period of period k along the believed actions
        ``u_believed`` float[N, m]; keeps the belief's mean after each (``means``)."""
        def one(g, u):
            g = ekf_predict(self.model.dynamics, g, u, self.Q, self.noise_dim, jacobian_grad=self.jacobian_grad,
                            structure=self.structure)
            return g, g.mean

        g, means = jax.lax.scan(one, state.belief, u_believed)
        return NudrekfState(g, means)


def belief_means(estimator: NudrekfEstimator, state: NudrekfState):
    """float[N, n]: the belief means after each fast period of the period (a
    :class:`jaxnc.loop.Record` function of the estimator)."""
    return state.means


def belief_finite(estimator: NudrekfEstimator, state: NudrekfState):
    """bool: the belief means of the period are all finite (a cheaper Record function)."""
    return jnp.all(jnp.isfinite(state.means))


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
    instant, and installs it in its copy with the weight ``ChainEstimate.weight`` (a new
    packet exactly when a measurement arrived); it then advances the copy over the period,
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
        mean, w = (xhat.mean, xhat.weight) if isinstance(xhat, ChainEstimate) else (xhat, fresh)
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
