"""Actuator and sensor limits: saturation, rate limit, dead zone, quantiser.

A *limit* is a small pytree acting element-wise on a signal (Simulink's blocks of the
same names):

* :class:`Saturation`: y = clip(s, low, high);
* :class:`DeadZone`: y = s - end for s > end, s - start for s < start, 0 in between;
* :class:`Quantizer`: y = q round(s / q) (round half to even);
* :class:`RateLimit`: y_t = y_{t-1} + clip(s_t - y_{t-1}, -falling T, rising T), with
  y_{-1} = ``initial`` (rates per second, T the fast period): the only one with a state,
  built by ``init(dim, T, dtype)`` in the signal's dtype.

Two parts apply limits in the given order: :class:`LimitedActuator` wraps an actuator
(every fast instant, to the action it outputs: what the plant receives and
``Trajectory.u`` records, and what an estimator with ``inputs="believed"`` is told, since
the runner's copy of the actuator is the same wrapped part), and :class:`LimitedSensor`
wraps a plant (to its measurement z = h(x, v); stateless limits only).

Gradients: saturation, dead zone and rate limit are piecewise linear and carry their
derivative almost everywhere (1 where the signal passes, 0 where it is clipped or in the
dead band). The quantiser's derivative is 0 almost everywhere, so it uses a
straight-through (identity) gradient: forward q round(s / q), backward d y / d s = 1.
Every number (bounds, widths, interval, rates) is a differentiable leaf.
"""
from __future__ import annotations

import abc
import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import array_fields, check_finite, check_given, check_instance, check_range, concrete
from jaxnc.loop.base import AbstractActuator, AbstractPlant, AbstractWrappedPlant
from jaxnc.loop.base import pytree_dataclass as _dataclass

__all__ = ["AbstractLimit", "Saturation", "DeadZone", "Quantizer", "RateLimit", "RateLimitState",
           "LimitedActuator", "LimitedSensor"]


class AbstractLimit(abc.ABC):
    """An element-wise nonlinearity on a signal float[d], with an optional state."""

    def init(self, dim: int, T: float, dtype=jnp.float32):
        """State before the first sample, for a signal of ``dim`` entries of ``dtype`` (the
        signal's float dtype; a loop's actions are float32) at period T (s)."""
        return ()

    @abc.abstractmethod
    def apply(self, state, s):
        """(state, y float[d]) for the signal s float[d]."""


def _ordered(name, lo_name, hi_name, lo, hi):
    if lo is not None and hi is not None and concrete(lo, hi):
        if np.any(np.asarray(lo) > np.asarray(hi)):
            raise ValueError(f"{name}.{lo_name} must be <= {name}.{hi_name}")


@_dataclass
class Saturation(AbstractLimit):
    """y = clip(s, low, high). low, high: float, float[d] or None (unbounded), low <= high."""

    low: Any = None
    high: Any = None

    def __post_init__(self):
        for n in ("low", "high"):
            check_range(f"Saturation.{n}", getattr(self, n), finite=False)
        array_fields(self, "low", "high")
        _ordered("Saturation", "low", "high", self.low, self.high)

    def apply(self, state, s):
        return state, jnp.clip(s, self.low, self.high)


@_dataclass
class DeadZone(AbstractLimit):
    """y = s - end (s > end), s - start (s < start), 0 otherwise. start <= end: float or float[d]."""

    start: Any = 0.0
    end: Any = 0.0

    def __post_init__(self):
        for n in ("start", "end"):
            check_given(f"DeadZone.{n}", getattr(self, n))
            check_finite(f"DeadZone.{n}", getattr(self, n))
        array_fields(self, "start", "end")
        _ordered("DeadZone", "start", "end", self.start, self.end)

    def apply(self, state, s):
        return state, jnp.where(s > self.end, s - self.end, jnp.where(s < self.start, s - self.start, 0.0 * s))


@_dataclass
class Quantizer(AbstractLimit):
    """y = interval * round(s / interval), straight-through gradient (d y / d s = 1).
    interval: float or float[d] > 0."""

    interval: Any = 1.0

    def __post_init__(self):
        check_given("Quantizer.interval", self.interval)
        check_range("Quantizer.interval", self.interval, 0.0, None, low_open=True)
        array_fields(self, "interval")

    def apply(self, state, s):
        q = self.interval * jnp.round(s / self.interval)
        return state, s + jax.lax.stop_gradient(q - s)


class RateLimitState(NamedTuple):
    """A :class:`RateLimit`'s state: the last output and the largest steps per period."""

    last: jax.Array       # float[d], y_{t-1}
    up: jax.Array         # float[d], rising T
    down: jax.Array       # float[d], falling T


@_dataclass
class RateLimit(AbstractLimit):
    """y_t = y_{t-1} + clip(s_t - y_{t-1}, -falling T, rising T), y_{-1} = initial.

    Attributes: rising float or float[d] >= 0 (units per second); falling, the same for a
    decrease (None: ``rising``); initial, float or float[d], the output before the first."""

    rising: Any = 1.0
    falling: Any = None
    initial: Any = 0.0

    def __post_init__(self):
        check_given("RateLimit.rising", self.rising)
        for n in ("rising", "falling"):
            check_range(f"RateLimit.{n}", getattr(self, n), 0.0, None)
        check_given("RateLimit.initial", self.initial)
        check_finite("RateLimit.initial", self.initial)
        array_fields(self, "rising", "falling", "initial")

    def init(self, dim, T, dtype=jnp.float32):
        """The state in the signal's ``dtype`` (float64 under ``jax_enable_x64`` for a float64
        signal), so that :meth:`apply` keeps it: y_{-1} = ``initial``, the steps rising T and
        falling T."""
        full = lambda v: jnp.broadcast_to(jnp.asarray(v, dtype), (dim,))
        falling = self.rising if self.falling is None else self.falling
        return RateLimitState(full(self.initial), full(self.rising) * T, full(falling) * T)

    def apply(self, state, s):
        y = state.last + jnp.clip(s - state.last, -state.down, state.up)
        return state._replace(last=y), y


def _check_limits(owner, limits, *, stateless=False):
    if isinstance(limits, AbstractLimit):
        limits = (limits,)
    if not isinstance(limits, (tuple, list)) or not limits:
        raise ValueError(f"{owner}.limits must be a limit or a non-empty tuple of limits (Saturation, DeadZone, "
                         f"Quantizer, RateLimit), got {limits!r}")
    for i, lim in enumerate(limits):
        check_instance(f"{owner}.limits[{i}]", lim, AbstractLimit,
                       "a jaxnc.loop limit (Saturation, DeadZone, Quantizer, RateLimit)")
        if stateless and isinstance(lim, RateLimit):
            raise ValueError(f"{owner}.limits[{i}] must be stateless (Saturation, DeadZone, Quantizer): a sensor "
                             f"has no state in which a RateLimit could keep its last value")
    return tuple(limits)


def _check_sizes(owner, limits, dim: int, what: str):
    """Each limit's numbers are one value or one per entry of the ``dim``-vector it limits
    (static shapes; a traced field is not checked). Raises ValueError naming the field: a
    longer vector would otherwise broadcast the signal to its length, or fail inside JAX."""
    for i, lim in enumerate(limits):
        for f in dataclasses.fields(lim):
            v = getattr(lim, f.name)
            if v is None or not concrete(v) or np.shape(v) in ((), (1,), (dim,)):
                continue
            raise ValueError(f"{owner}.limits[{i}] ({type(lim).__name__}).{f.name} must be a number or have {dim} "
                             f"entries ({what}), got shape {np.shape(v)}")


def _apply(limits, states, s):
    """The limits applied in order, in the signal's dtype: a limit's float numbers are cast to
    it (float64 numbers under ``jax_enable_x64`` would otherwise promote a float32 action or
    measurement to float64), and so is each output."""
    out = []
    cast = lambda a: jnp.asarray(a, s.dtype) if isinstance(a, (float, np.floating, np.ndarray, jax.Array)) \
        and jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a
    for lim, st in zip(limits, states):
        st, y = jax.tree.map(cast, lim).apply(st, s)
        s = jnp.asarray(y, s.dtype)
        out.append(st)
    return tuple(out), s


@_dataclass
class LimitedActuator(AbstractActuator):
    """An actuator whose every output goes through ``limits`` in order.

    Attributes:
      actuator: the inner :class:`~jaxnc.loop.base.AbstractActuator` (e.g. ``HoldLast()``).
        A loop whose controller keeps its own copy of what it sent (``keeps_copy``) refuses
        a LimitedActuator: the limits would not reach that copy.
      limits: a limit or a tuple of limits (:class:`Saturation`, :class:`DeadZone`,
        :class:`Quantizer`, :class:`RateLimit`), applied first to last.

    State: (the inner actuator's state, a tuple of the limits' states).
    Raises: ValueError naming ``LimitedActuator.actuator`` or ``LimitedActuator.limits[i]``.
    """

    actuator: Any
    limits: Any

    def __post_init__(self):
        check_instance("LimitedActuator.actuator", self.actuator, AbstractActuator,
                       "an actuator (a jaxnc.loop.AbstractActuator: HoldLast, PacketActuator)")
        object.__setattr__(self, "limits", _check_limits("LimitedActuator", self.limits))

    @property
    def horizon(self):
        """The inner actuator's declared packet length (:class:`~jaxnc.loop.AbstractActuator`)."""
        return self.actuator.horizon

    def init(self, ctx):
        """The inner actuator's state and the limits'. Raises ValueError when a limit's numbers
        are neither one value nor one per plant input."""
        _check_sizes("LimitedActuator", self.limits, ctx.input_dim, "one per plant input")
        return self.actuator.init(ctx), tuple(lim.init(ctx.input_dim, ctx.T) for lim in self.limits)

    def receive(self, state, inbox):
        return self.actuator.receive(state[0], inbox), state[1]

    def output(self, state, t):
        inner, u = self.actuator.output(state[0], t)
        states, u = _apply(self.limits, state[1], u)
        return (inner, states), u


@_dataclass
class LimitedSensor(AbstractWrappedPlant):
    """A plant whose measurement goes through stateless ``limits`` in order:
    z = limits(h(x, v)); everything else (dynamics, noise, initial state, declared data)
    is the inner plant's (:class:`~jaxnc.loop.base.AbstractWrappedPlant`).

    Attributes:
      plant: the inner :class:`~jaxnc.loop.base.AbstractPlant`.
      limits: a limit or a tuple of :class:`Saturation`, :class:`DeadZone`, :class:`Quantizer`.

    Raises: ValueError naming ``LimitedSensor.plant`` or ``LimitedSensor.limits[i]`` (a
    :class:`RateLimit` is refused).
    """

    plant: Any
    limits: Any

    def __post_init__(self):
        check_instance("LimitedSensor.plant", self.plant, AbstractPlant,
                       "a plant (a jaxnc.loop.AbstractPlant: LTI, Discrete, Continuous)")
        object.__setattr__(self, "limits", _check_limits("LimitedSensor", self.limits, stateless=True))

    def measure(self, x, v):
        z = self.plant.measure(x, v)
        _check_sizes("LimitedSensor", self.limits, jnp.shape(z)[-1], "one per measurement")
        return _apply(self.limits, tuple(() for _ in self.limits), z)[1]
