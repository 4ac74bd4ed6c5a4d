"""One direction of the network: loss model x delay model, time stamps, a ring of packets.

A :class:`Link` carries one packet per slow instant k (when the sender sends). Its
randomness is exogenous: :func:`draw_link` draws, before the run, whether the packet of
each slow instant would be lost and its delay in whole fast periods (delays are
quantised *up* to the fast period T, :func:`jaxnc.network.quantise_delay`; a packet
later than ``tau_max`` is discarded). Inside the run the link keeps the last
``capacity`` packets in a ring (slot ``k mod capacity``), with their arrival instants;
a receiver gets an :class:`~jaxnc.loop.base.Inbox` of that ring at each instant it
looks. A packet still in flight when its slot is reused is lost, so ``capacity`` must
cover the longest delay in slow periods plus one (checked when the loop is built).

Ordering policies (``order``):

* ``"newest"``: a packet is delivered only if its stamp is newer than every packet
  delivered before (older ones arriving late, out of order, are dropped); of several
  arriving together, the newest;
* ``"all"``: every packet is delivered at its arrival instant (a receiver with a
  buffer, e.g. the time-stamped filter, sorts them by stamp itself);
* ``"arrival"``: a receiver without time stamps (seed 001's emulation design, eq. 5):
  every arrival replaces what it holds, even a packet older than one delivered before;
  of several arriving together, the newest (:func:`jaxnc.wifi.newest_arrival`).

The order decides what is *delivered* at an instant (``Inbox.new``): what an actuator,
``DirtyDerivative`` or ``ArrivalHold`` takes, and the ``recv_sc``/``recv_ca`` signals. A
time-stamped estimator (``EKF``, ``UKF``, ``SteadyStateKF``, ``Luenberger``: ``by_stamp``)
reads the packet of the stamp it wants from the ring once it has *arrived*
(``Inbox.packet``), whatever the order: behind an ``"newest"`` uplink an ``EKF(buffer>=1)``
still uses a measurement that arrived after a newer one, although ``recv_sc`` does not
count it (use ``order="all"`` to count every arrival).

Loss models: :class:`NoLoss`, :class:`Bernoulli` (seed 000 eq. 5),
:class:`GilbertElliott` (bursts), :class:`TraceLoss` (recorded). Delay models:
:class:`NoDelay`, :class:`ShiftedExponential` (seed 000 eq. 7),
:class:`TruncatedExponential` (seed 004 section 5.1, never beyond its bound),
:class:`PmfDelay` (a discrete law in fast periods), :class:`TraceDelay` (recorded), and
:class:`WifiModel`, the seed-001 Wi-Fi channel (:mod:`jaxnc.wifi`), which draws loss and
delay jointly. Each model's ``sample(key, n, T)`` returns ``(steps int32[n], seconds
float32[n])`` for delays or ``bool[n]`` for losses; ``n`` is static.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import wifi
from jaxnc._validate import (array_fields, check_bool, check_given, check_instance, check_int, check_nonneg,
                             check_range, concrete, scalar_fields)
from jaxnc.loop.base import AbstractDelay, AbstractLoss, Inbox
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.network import late, quantise_delay

__all__ = ["Link", "LinkDraws", "LinkState", "NoLoss", "Bernoulli", "GilbertElliott", "TraceLoss", "NoDelay",
           "ShiftedExponential", "TruncatedExponential", "PmfDelay", "TraceDelay", "WifiModel",
           "truncated_exponential", "draw_link", "link_delay_bounds", "steps_within", "NEVER"]

NEVER = 2**30          # arrival instant of a packet that never arrives
_F32 = jnp.float32


# a model draws one value per packet from its numbers: they are single numbers
_scalars = scalar_fields


# ----------------------------------------------------------------------------- loss models


@_dataclass
class NoLoss(AbstractLoss):
    """Every packet arrives."""

    def sample(self, key, n: int):
        return jnp.zeros((n,), bool)


@_dataclass
class Bernoulli(AbstractLoss):
    """Independent loss with probability ``p`` (seed 000 eq. 5): ``lost = U < p``, so with
    the same key the losses at a lower p are a subset of those at a higher one."""

    p: Any = 0.0

    def __post_init__(self):
        check_given("Bernoulli.p", self.p)
        check_range("Bernoulli.p", self.p, 0.0, 1.0, high_open=True)
        _scalars(self, "p")

    def sample(self, key, n: int):
        return jax.random.uniform(key, (n,), _F32) < jnp.asarray(self.p, _F32)


@_dataclass
class GilbertElliott(AbstractLoss):
    """Two-state Markov (bursty) loss: good -> bad with ``p_gb``, bad -> good with ``p_bg``
    per packet; a packet is lost with ``loss_good`` / ``loss_bad`` in each state. The chain
    starts in its stationary distribution. Its kernel is :func:`jaxnc.wifi.gilbert_elliott_losses`
    (the Wi-Fi channel's chain with no gap bounds)."""

    p_gb: Any = 0.0
    p_bg: Any = 1.0
    loss_good: Any = 0.0
    loss_bad: Any = 1.0

    def __post_init__(self):
        for n in ("p_gb", "p_bg", "loss_good", "loss_bad"):
            check_given(f"GilbertElliott.{n}", getattr(self, n))
            check_range(f"GilbertElliott.{n}", getattr(self, n), 0.0, 1.0)
        check_range("GilbertElliott.p_bg", self.p_bg, 0.0, 1.0, low_open=True)
        _scalars(self, "p_gb", "p_bg", "loss_good", "loss_bad")

    def stationary_loss(self):
        """Long-run loss rate: pi_b loss_bad + (1 - pi_b) loss_good, pi_b = p_gb / (p_gb + p_bg)."""
        pb = self.p_gb / (self.p_gb + self.p_bg)
        return pb * self.loss_bad + (1 - pb) * self.loss_good

    def sample(self, key, n: int):
        k0, ks, kl = jax.random.split(key, 3)
        p_gb, p_bg = jnp.asarray(self.p_gb, _F32), jnp.asarray(self.p_bg, _F32)
        bad0 = jax.random.uniform(k0, (), _F32) < p_gb / (p_gb + p_bg)
        return wifi.gilbert_elliott_losses(bad0, jax.random.uniform(ks, (n,), _F32), jax.random.uniform(kl, (n,), _F32),
                                           p_gb, p_bg, jnp.asarray(self.loss_good, _F32),
                                           jnp.asarray(self.loss_bad, _F32))


@_dataclass
class TraceLoss(AbstractLoss):
    """A recorded loss sequence (bool, True = lost), replayed from its start; it must be
    at least as long as the run's slow instants."""

    lost: Any

    def __post_init__(self):
        _trace("TraceLoss.lost", self, "lost", "a 1-D array of booleans (True = lost) or 0/1",
               lambda a: a.dtype.kind == "b" or bool(np.all((a == 0) | (a == 1))), bool)

    def packets(self):
        return int(np.shape(self.lost)[0])

    def sample(self, key, n: int):
        lost = jnp.asarray(self.lost, bool)
        if lost.shape[0] < n:
            raise ValueError(f"TraceLoss.lost has {lost.shape[0]} entries, the run needs {n}")
        return lost[:n]


def _trace(name, obj, field, what, ok, dtype):
    """Validate a recorded sequence field (concrete values only) and store it as a numpy
    array of ``dtype``: 1-D, non-empty, numbers, ``ok(array)``."""
    v = getattr(obj, field)
    check_given(name, v, what)
    if isinstance(v, (str, bytes)):
        raise ValueError(f"{name} must be {what}, got {v!r}")
    if not concrete(v):
        return
    try:
        a = np.asarray(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {what}, got {v!r}") from None
    if a.dtype.kind not in "biuf" or a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} must be {what}, got an array of {a.dtype} of shape {a.shape}")
    check_range(name, a)                                     # finite
    if not ok(a):
        raise ValueError(f"{name} must be {what}, got {a.tolist()[:8]}{' ...' if a.size > 8 else ''}")
    object.__setattr__(obj, field, a.astype(dtype))


# ----------------------------------------------------------------------------- delay models


@_dataclass
class NoDelay(AbstractDelay):
    """Zero delay: a packet is usable at the instant it is sent."""

    in_steps = True

    def bounds(self, T):
        return 0, 0

    def sample(self, key, n: int, T):
        return jnp.zeros((n,), jnp.int32), jnp.zeros((n,), _F32)


@_dataclass
class ShiftedExponential(AbstractDelay):
    """tau = eta + phi Exp(1) seconds (seed 000 eq. 7), quantised up to the fast period."""

    eta: Any = 0.0
    phi: Any = 0.0

    def __post_init__(self):
        check_given("ShiftedExponential.eta", self.eta)
        check_given("ShiftedExponential.phi", self.phi)
        check_nonneg("ShiftedExponential.eta", self.eta)
        check_nonneg("ShiftedExponential.phi", self.phi)
        _scalars(self, "eta", "phi")

    def seconds(self, e):
        """The delay for standard exponential draws ``e``."""
        return jnp.asarray(self.eta, _F32) + jnp.asarray(self.phi, _F32) * e

    def bounds(self, T):
        return _periods(self.eta, T, 0), None

    def sample(self, key, n: int, T):
        tau = self.seconds(jax.random.exponential(key, (n,), _F32))
        return quantise_delay(tau, T), tau


def truncated_exponential(u, eta, phi, tau_max):
    """Inverse CDF of eta + phi Exp(1) truncated to [eta, tau_max], at uniforms ``u``
    (never beyond tau_max: seed 004 keeps tau_max < NT so packets never overtake)."""
    m = -jnp.expm1(-(tau_max - eta) / jnp.maximum(phi, 1e-12))
    return jnp.where(phi > 0, eta - phi * jnp.log1p(-u * m), eta)


@_dataclass
class TruncatedExponential(AbstractDelay):
    """eta + phi Exp(1) truncated to [eta, tau_max] seconds (:func:`truncated_exponential`)."""

    eta: Any = 0.0
    phi: Any = 0.0
    tau_max: Any = 1.0

    def __post_init__(self):
        for n in ("eta", "phi", "tau_max"):
            check_given(f"TruncatedExponential.{n}", getattr(self, n))
        check_nonneg("TruncatedExponential.eta", self.eta)
        check_nonneg("TruncatedExponential.phi", self.phi)
        check_range("TruncatedExponential.tau_max", self.tau_max, 0.0, None)
        _scalars(self, "eta", "phi", "tau_max")
        try:
            if float(self.tau_max) < float(self.eta):
                raise ValueError(f"TruncatedExponential.tau_max must be >= eta={float(self.eta):g}, "
                                 f"got {float(self.tau_max):g}")
        except TypeError:
            pass

    def bounds(self, T):
        return _periods(self.eta, T, 0), _periods(self.tau_max, T)

    def sample(self, key, n: int, T):
        tau = truncated_exponential(jax.random.uniform(key, (n,), _F32), self.eta, self.phi, self.tau_max)
        return quantise_delay(tau, T), tau


@_dataclass
class PmfDelay(AbstractDelay):
    """A discrete delay law: ``pmf[d]`` = P(delay = d fast periods)."""

    in_steps = True

    pmf: Any

    def __post_init__(self):
        check_given("PmfDelay.pmf", self.pmf, "a non-empty 1-D array of probabilities")
        array_fields(self, "pmf")
        p = np.asarray(self.pmf, float) if concrete(self.pmf) else None
        if p is not None:
            if p.ndim != 1 or p.size == 0:
                raise ValueError(f"PmfDelay.pmf must be a non-empty 1-D array, got shape {p.shape}")
            check_range("PmfDelay.pmf", p, 0.0, 1.0)
            if abs(p.sum() - 1.0) > 1e-5:
                raise ValueError(f"PmfDelay.pmf must sum to 1, got {p.sum():.6f}")

    def bounds(self, T):
        hi = int(np.shape(self.pmf)[0]) - 1
        if not concrete(self.pmf):
            return 0, hi
        return int(np.flatnonzero(np.asarray(self.pmf) > 0)[0]), hi

    def sample(self, key, n: int, T):
        d = jax.random.categorical(key, jnp.log(jnp.asarray(self.pmf, _F32)), shape=(n,)).astype(jnp.int32)
        return d, d.astype(_F32) * jnp.asarray(T, _F32)


@_dataclass
class TraceDelay(AbstractDelay):
    """Recorded delays in fast periods (int, negative = lost), replayed from the start."""

    in_steps = True

    steps: Any

    def __post_init__(self):
        _trace("TraceDelay.steps", self, "steps", "a 1-D array of integer delays in fast periods (negative = lost)",
               lambda a: a.dtype.kind != "b" and bool(np.all(a == np.round(a)) and np.all(np.abs(a) < 2**31)),
               np.int32)

    def bounds(self, T):
        if not concrete(self.steps):
            return 0, None
        ok = np.asarray(self.steps)[np.asarray(self.steps) >= 0]
        return (int(ok.min()), int(ok.max())) if ok.size else (0, 0)

    def packets(self):
        return int(np.shape(self.steps)[0])

    def sample(self, key, n: int, T):
        d = jnp.asarray(self.steps, jnp.int32)
        if d.shape[0] < n:
            raise ValueError(f"TraceDelay.steps has {d.shape[0]} entries, the run needs {n}")
        d = d[:n]
        return d, jnp.maximum(d, 0).astype(_F32) * jnp.asarray(T, _F32)


@_dataclass
class WifiModel(AbstractDelay):
    """The seed-001 Wi-Fi channel (:class:`jaxnc.wifi.WifiChannel`): bursty loss and the
    delay pmf drawn jointly by :func:`jaxnc.wifi.sample_trace`; use it as the link's delay
    model (a lost packet has delay -1)."""

    in_steps = True

    channel: wifi.WifiChannel = wifi.NOMINAL

    def __post_init__(self):
        check_instance("WifiModel.channel", self.channel, wifi.WifiChannel, "a jaxnc.wifi.WifiChannel")

    def bounds(self, T):
        """(lo, hi): the delay law's first and last possible delays (its first and last
        nonzero entries when concrete, else 0 and ``max_delay``), as :class:`PmfDelay`'s."""
        pmf = self.channel.delay_pmf
        if not concrete(pmf):
            return 0, int(self.channel.max_delay)
        nz = np.flatnonzero(np.asarray(pmf) > 0)
        return int(nz[0]), int(nz[-1])

    def sample(self, key, n: int, T):
        d = wifi.sample_trace(key, self.channel, n)
        return d, jnp.maximum(d, 0).astype(_F32) * jnp.asarray(T, _F32)


# ----------------------------------------------------------------------------- the link


def _periods(seconds, T, traced=None):
    """A concrete delay bound in whole fast periods, quantised as the draws are
    (:func:`jaxnc.network.quantise_delay`); ``traced`` (None) for a traced bound."""
    try:
        seconds = float(seconds)
    except TypeError:          # a tracer (jax's concretisation errors are TypeErrors)
        return traced
    with jax.ensure_compile_time_eval():   # eager, also while a jit is tracing
        return int(quantise_delay(seconds, T))


class LinkDraws(NamedTuple):
    """Per slow instant: the packet's delay in fast periods; NEVER-like when lost or late."""

    delay: jax.Array     # int32[S]; >= 0, or -1 when lost / discarded


class LinkState(NamedTuple):
    """The ring of the last C packets (slot k mod C)."""

    data: Any            # payloads, leading axis C
    stamp: jax.Array     # int32[C] (-1: empty)
    weight: jax.Array    # float[C]: sent and not lost (0/1 float)
    arrival: jax.Array   # int32[C] fast instant of arrival (NEVER: lost / not sent)
    delivered: jax.Array  # bool[C]
    last: jax.Array      # int32: newest stamp delivered so far (order "newest")
    count: jax.Array     # float: packets sent (transmissions)


@_dataclass
class Link:
    """One direction of the network.

    Attributes:
      loss: a loss model (default :class:`NoLoss`).
      delay: a delay model (default :class:`NoDelay`).
      tau_max: seconds; later packets are discarded (None: never).
      reliable_first: static; the packet of the first slow instant is never lost or late
        (a start-up handshake): it keeps its drawn delay, or, where the delay model itself
        marks it lost (a :class:`TraceDelay`'s negative entry, :class:`WifiModel`'s loss), the
        model's shortest delay (``bounds(T)[0]``).
      order: static, ``"newest"``, ``"all"`` or ``"arrival"`` (module docstring).
      capacity: static ring length C (transmissions remembered), >= 1; None (the default):
        sized by the :class:`~jaxnc.loop.Loop` that holds the link, the smallest ring that
        holds every packet the delay model and ``tau_max`` bound (at least 2), or 2 with a
        warning when the delay has no bound.
    """

    loss: Any = NoLoss()
    delay: Any = NoDelay()
    tau_max: Any = None
    reliable_first: bool = _static(False)
    order: str = _static("newest")
    capacity: int | None = _static(None)

    def __post_init__(self):
        check_instance("Link.loss", self.loss, AbstractLoss, "a loss model (a jaxnc.loop.AbstractLoss: NoLoss, "
                       "Bernoulli, GilbertElliott, TraceLoss)")
        check_instance("Link.delay", self.delay, AbstractDelay, "a delay model (a jaxnc.loop.AbstractDelay: NoDelay, "
                       "ShiftedExponential, TruncatedExponential, PmfDelay, TraceDelay, WifiModel)")
        if self.order not in ("newest", "all", "arrival"):
            raise ValueError(f"Link.order must be one of newest, all, arrival, got {self.order!r}")
        if self.capacity is not None:
            check_int("Link.capacity", self.capacity, 1, 100_000)
        check_bool("Link.reliable_first", self.reliable_first)
        if self.tau_max is not None:
            check_range("Link.tau_max", self.tau_max, 0.0, None)
            _scalars(self, "tau_max")

    # -- inside the run
    def init(self, example) -> LinkState:
        """An empty ring for payloads shaped like ``example``.

        Raises:
          ValueError: ``capacity`` is None (a ``Loop`` sizes it; a link used on its own needs one).
        """
        C = self.capacity
        if C is None:
            raise ValueError("Link.capacity is None: a Loop sizes it from the delay bounds; a link used outside "
                             "a Loop needs capacity=C (an int >= 1)")
        data = jax.tree.map(lambda a: jnp.zeros((C, *jnp.shape(a)), jnp.asarray(a).dtype), example)
        return LinkState(data, jnp.full((C,), -1, jnp.int32), jnp.zeros((C,), _F32),
                         jnp.full((C,), NEVER, jnp.int32), jnp.ones((C,), bool),
                         jnp.asarray(-(2**30), jnp.int32), jnp.zeros((), _F32))

    def send(self, state: LinkState, data, stamp, k, send, delay, t_send) -> LinkState:
        """Put a packet in slot ``k mod C``.

        Args:
          data: payload; stamp: int32 time stamp; k: int32 slow instant (the slot).
          send: 0/1 float, whether the sender transmits (may carry a gradient).
          delay: int32 delay in fast periods from :func:`draw_link` (-1: lost).
          t_send: int32 fast instant of sending.
        """
        i = jnp.mod(k, self.capacity)
        send = jnp.asarray(send, _F32)
        ok = (delay >= 0).astype(_F32)
        w = send * ok
        sent = send > 0.5
        return LinkState(
            data=jax.tree.map(lambda r, a: r.at[i].set(jnp.asarray(a, r.dtype)), state.data, data),
            stamp=state.stamp.at[i].set(jnp.where(sent, stamp, -1).astype(jnp.int32)),
            weight=state.weight.at[i].set(w),
            arrival=state.arrival.at[i].set(jnp.where(sent & (delay >= 0), t_send + delay, NEVER).astype(jnp.int32)),
            delivered=state.delivered.at[i].set(~sent),
            last=state.last, count=state.count + send)

    def inbox(self, state: LinkState, t) -> tuple[Inbox, LinkState]:
        """What the receiver gets at fast instant ``t``, and the ring with it marked delivered."""
        arrived = state.arrival <= t
        now = arrived & ~state.delivered
        if self.order in ("newest", "arrival"):
            key = jnp.where(now, state.stamp, -(2**30))
            i = jnp.argmax(key)
            pick = (jnp.arange(self.capacity) == i) & now
            if self.order == "newest":
                pick = pick & (state.stamp > state.last)
            last = jnp.where(jnp.any(pick), jnp.maximum(state.stamp[i], state.last), state.last)
        else:
            pick = now
            last = jnp.maximum(state.last, jnp.max(jnp.where(now, state.stamp, -(2**30))))
        new = jnp.where(pick, state.weight, 0.0)
        inbox = Inbox(state.data, state.stamp, state.weight, arrived & (state.weight > 0), new)
        return inbox, state._replace(delivered=state.delivered | now, last=last)


def link_delay_bounds(link: Link, T: float):
    """(lo, hi): the delay of a packet ``link`` delivers, in fast periods of T seconds, from
    its delay model's declared :meth:`~jaxnc.loop.AbstractDelay.bounds` and ``tau_max``
    (hi None: no known bound).

    Raises:
      ValueError: the delay model's ``bounds(T)`` is not (lo, hi) in whole fast periods with
        0 <= lo <= hi (hi None): e.g. seconds (0.0, 0.2) would size the ring for 0.2 fast
        periods and lose the packets still in flight when their slot is reused."""
    lo, hi = link.delay.bounds(T)
    whole = lambda v: isinstance(v, (int, np.integer)) and not isinstance(v, bool)
    if not (whole(lo) and lo >= 0 and (hi is None or (whole(hi) and hi >= lo))):
        raise ValueError(f"{type(link.delay).__name__}.bounds(T) must return (lo, hi), the shortest and longest "
                         f"delay in whole fast periods (ints, 0 <= lo <= hi; hi None: unbounded), got {(lo, hi)!r}")
    if link.tau_max is not None:
        cap = _periods(link.tau_max, T)
        if cap is not None:
            hi = cap if hi is None else min(hi, cap)
    return lo, hi


def steps_within(tau_max, T):
    """The longest delay in whole fast periods of T seconds that ``tau_max`` keeps, for a
    delay model drawn in periods (``in_steps``): floor(tau_max / T), compared in periods, not
    float32 seconds (d T can round above tau_max = d T), float32."""
    return jnp.floor(jnp.asarray(tau_max, _F32) / jnp.asarray(T, _F32) * (1 + 2.0**-21))


def draw_link(link: Link, key, n: int, T) -> LinkDraws:
    """Before the run: the delays (fast periods of T seconds) of the packets of ``n`` slow
    instants over ``link``; -1 when lost or later than ``tau_max`` (n static).

    Raises:
      ValueError: for a ``reliable_first`` link, the delay model's ``bounds(T)`` is not
        (lo, hi) in whole fast periods (:func:`link_delay_bounds`)."""
    kl, kd = jax.random.split(key)
    lost = link.loss.sample(kl, n)
    steps, seconds = link.delay.sample(kd, n, T)
    bad = lost | (steps < 0)
    if link.tau_max is not None:
        if link.delay.in_steps:
            bad = bad | (steps > steps_within(link.tau_max, T))
        else:
            bad = bad | late(seconds, link.tau_max)
    if link.reliable_first:
        first = jnp.arange(n) == 0
        bad = bad & ~first
        # a model that marks the first packet lost itself (a trace's -1, the Wi-Fi channel's loss) has no
        # delay for it: the handshake's packet takes the model's shortest delay (an int >= 0, checked)
        steps = jnp.where(first & (steps < 0), link_delay_bounds(link, T)[0], steps)
    return LinkDraws(jnp.where(bad, -1, steps).astype(jnp.int32))
