"""Reference signals r(t) for tracking: step, ramp, sine, piecewise-linear, recorded.

Each reference is a frozen dataclass registered as a pytree whose amplitudes, times and
values are leaves (differentiable, vmappable); :meth:`AbstractReference.at` gives
r at the fast instant ``t`` (an integer, time t T) as ``float[p]``, and :func:`evaluate`
gives the whole run ``float[K, p]``. A scalar amplitude is a one-channel reference
(p = 1); vector fields of one reference broadcast to a common p at construction.
Python numbers and lists become float32 arrays; numpy arrays and scalars keep their float
dtype (a reference given float64 numbers under ``jax_enable_x64`` is float64).
"""
from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_finite, check_given, check_int, check_nonneg, check_positive, checked_pytree

__all__ = ["AbstractReference", "Step", "Ramp", "Sine", "PiecewiseLinear", "Recorded", "evaluate", "held_at_end", "at_channels",
           "check_channels"]

# a step or ramp time on a sample instant is reached at that instant despite the rounding
# of t * T: the comparison is made within this fraction of a period
_TIME_TOL = 1e-4


def _leaf(cls, name, v, *, ndim_max=1, scalar_ok=True):
    """``v`` as an array leaf: Python numbers and lists to float32, numpy arrays and scalars
    in their float dtype (a float64 scalar stays float64), other dtypes to float32; at least
    1-d when ``scalar_ok`` (a scalar is one channel); finite when concrete."""
    check_given(f"{cls}.{name}", v)
    check_finite(f"{cls}.{name}", v)
    if isinstance(v, np.generic):           # before float: np.float64 is a Python float too
        v = np.asarray(v)
    elif isinstance(v, (bool, int, float, list, tuple)):
        v = np.asarray(v, np.float32)
    if isinstance(v, np.ndarray):
        if v.ndim == 0 and scalar_ok:
            v = v.reshape(1)
        if v.ndim > ndim_max:
            raise ValueError(f"{cls}.{name} must have at most {ndim_max} dimension(s), got shape {v.shape}")
        if v.dtype.kind != "f":
            v = v.astype(np.float32)
    return v


def _broadcast(obj, *names):
    """Broadcast the named float[p] (or scalar) fields of ``obj`` to one p, or ValueError."""
    shapes = [np.shape(getattr(obj, n)) for n in names]
    try:
        shape = np.broadcast_shapes(*shapes)
    except ValueError:
        raise ValueError(f"{type(obj).__name__}: {', '.join(names)} must have the same number of channels "
                         f"(or be scalars), got shapes {shapes}") from None
    for n in names:
        v = getattr(obj, n)
        object.__setattr__(obj, n, jnp.broadcast_to(v, shape) if isinstance(v, jax.Array)
                           else np.broadcast_to(v, shape).copy())


def _timed_init(obj, name):
    """Validation of a reference with a channel field ``name``, ``initial`` and ``time``."""
    cls = type(obj).__name__
    object.__setattr__(obj, name, _leaf(cls, name, getattr(obj, name)))
    object.__setattr__(obj, "initial", _leaf(cls, "initial", obj.initial))
    object.__setattr__(obj, "time", _leaf(cls, "time", obj.time))
    check_nonneg(f"{cls}.time", obj.time)
    _broadcast(obj, name, "time", "initial")


def _time(t, T, dtype):
    return jnp.asarray(t, dtype) * jnp.asarray(T, dtype)


class AbstractReference(abc.ABC):
    """A reference signal r: fast instant -> float[p].

    ``settles`` (class attribute, declared): the reference ends at a value it holds (a
    setpoint: ``Step``, ``PiecewiseLinear``, ``Recorded``), so a response's step
    characteristics toward its final value mean something; ``Ramp`` and ``Sine`` declare
    False (their last sample is wherever the run happens to stop)."""

    settles: ClassVar[bool] = True

    @abc.abstractmethod
    def at(self, t, T) -> jax.Array:
        """r at the fast instant ``t`` (int scalar, time t T), float[p].

        Args:
          t: int scalar (may be traced), the fast instant.
          T: the fast period in seconds.
        """

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """The number of channels p."""


@checked_pytree
@dataclasses.dataclass(frozen=True)
class Step(AbstractReference):
    """r(t) = initial + amplitude * [t T >= time].

    Attributes:
      amplitude: float[p] (or scalar), the step's height.
      time: float[p] (or scalar), the step time in seconds (>= 0). The step is applied
        from the first instant with t T >= time (to within 1e-4 T of rounding); r has no
        gradient with respect to ``time``.
      initial: float[p] (or scalar), the value before the step.
    """

    amplitude: Any
    time: Any = 0.0
    initial: Any = 0.0

    def __post_init__(self):
        _timed_init(self, "amplitude")

    @property
    def dim(self) -> int:
        return int(np.shape(self.amplitude)[0])

    def applied(self, t, T) -> jax.Array:
        """Whether the step is applied at the fast instant ``t`` (int scalar, may be traced):
        t T >= time to within 1e-4 T, bool[p]. The rule of :meth:`at` and :meth:`onset`."""
        a = jnp.asarray(self.amplitude)
        return _time(t, T, a.dtype) >= jnp.asarray(self.time, a.dtype) - _TIME_TOL * jnp.asarray(T, a.dtype)

    def onset(self, steps: int, T) -> jax.Array:
        """The step's instant in a run of ``steps`` fast instants: the first t in
        [0, steps) at which it is :meth:`applied`, ``steps`` where it is not applied within
        the run; int32[p]. ``steps`` is a static int >= 1; ``time`` may be traced.

        Raises:
          ValueError: ``steps`` < 1.
        """
        check_int("Step.onset: steps", steps, 1)
        on = jax.vmap(self.applied, in_axes=(0, None))(jnp.arange(steps, dtype=jnp.int32), T)   # bool[steps, p]
        return jnp.where(jnp.any(on, axis=0), jnp.argmax(on, axis=0), steps).astype(jnp.int32)

    def at(self, t, T):
        a = jnp.asarray(self.amplitude)
        return jnp.asarray(self.initial, a.dtype) + jnp.where(self.applied(t, T), a, jnp.zeros_like(a))


@checked_pytree
@dataclasses.dataclass(frozen=True)
class Ramp(AbstractReference):
    """r(t) = initial + slope * max(t T - time, 0). Does not settle (``settles`` False).

    Attributes:
      slope: float[p] (or scalar), units per second.
      time: float[p] (or scalar), the ramp's start in seconds (>= 0).
      initial: float[p] (or scalar), the value before the ramp.
    """

    settles: ClassVar[bool] = False

    slope: Any
    time: Any = 0.0
    initial: Any = 0.0

    def __post_init__(self):
        _timed_init(self, "slope")

    @property
    def dim(self) -> int:
        return int(np.shape(self.slope)[0])

    def at(self, t, T):
        s = jnp.asarray(self.slope)
        elapsed = jnp.maximum(_time(t, T, s.dtype) - jnp.asarray(self.time, s.dtype), 0.0)
        return jnp.asarray(self.initial, s.dtype) + s * elapsed


@checked_pytree
@dataclasses.dataclass(frozen=True)
class Sine(AbstractReference):
    """r(t) = offset + amplitude * sin(2 pi frequency t T + phase). Does not settle (``settles`` False).

    Attributes:
      amplitude: float[p] (or scalar).
      frequency: float[p] (or scalar), in Hz (>= 0).
      phase: float[p] (or scalar), in radians.
      offset: float[p] (or scalar).
    """

    settles: ClassVar[bool] = False

    amplitude: Any
    frequency: Any
    phase: Any = 0.0
    offset: Any = 0.0

    def __post_init__(self):
        for n in ("amplitude", "frequency", "phase", "offset"):
            object.__setattr__(self, n, _leaf("Sine", n, getattr(self, n)))
        check_nonneg("Sine.frequency", self.frequency)
        _broadcast(self, "amplitude", "frequency", "phase", "offset")

    @property
    def dim(self) -> int:
        return int(np.shape(self.amplitude)[0])

    def at(self, t, T):
        a = jnp.asarray(self.amplitude)
        arg = 2.0 * jnp.pi * jnp.asarray(self.frequency, a.dtype) * _time(t, T, a.dtype) + self.phase
        return jnp.asarray(self.offset, a.dtype) + a * jnp.sin(arg)


@checked_pytree
@dataclasses.dataclass(frozen=True)
class PiecewiseLinear(AbstractReference):
    """r(t) linear between the breakpoints (times[i], values[i]), constant outside them.

    Attributes:
      times: float[M], strictly increasing breakpoint times in seconds (M >= 1).
      values: float[M] (one channel) or float[M, p], r at the breakpoints.

    The gradient with respect to ``values`` and to ``times`` is that of the linear
    interpolation (``jnp.interp``).
    """

    times: Any
    values: Any

    def __post_init__(self):
        times = _leaf("PiecewiseLinear", "times", self.times)
        values = _leaf("PiecewiseLinear", "values", self.values, ndim_max=2)
        if np.ndim(values) == 1:
            values = values[:, None]
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "values", values)
        if isinstance(times, np.ndarray) and isinstance(values, np.ndarray):
            if times.ndim != 1:
                raise ValueError(f"PiecewiseLinear.times must be float[M], got shape {times.shape}")
            if values.shape[0] != times.shape[0]:
                raise ValueError(f"PiecewiseLinear.values must have one row per time (M={times.shape[0]}), "
                                 f"got shape {values.shape}")
            if times.shape[0] < 1:
                raise ValueError("PiecewiseLinear.times must have at least one breakpoint (M >= 1), got none")
            if np.any(np.diff(times) <= 0):
                raise ValueError(f"PiecewiseLinear.times must be strictly increasing, got {times.tolist()}")

    @property
    def dim(self) -> int:
        return int(np.shape(self.values)[1])

    def at(self, t, T):
        v = jnp.asarray(self.values)
        s = _time(t, T, v.dtype)
        times = jnp.asarray(self.times, v.dtype)
        return jax.vmap(lambda col: jnp.interp(s, times, col), in_axes=1)(v)


@checked_pytree
@dataclasses.dataclass(frozen=True)
class Recorded(AbstractReference):
    """r at fast instant t is ``values[t]`` (a recorded reference at the fast period);
    before 0 the first row, after the record its last row (held).

    Attributes:
      values: float[L] (one channel) or float[L, p], one row per fast instant (L >= 1).
    """

    values: Any

    def __post_init__(self):
        values = _leaf("Recorded", "values", self.values, ndim_max=2, scalar_ok=False)
        if np.ndim(values) == 0:
            raise ValueError("Recorded.values must be float[L] or float[L, p], got a scalar")
        if np.ndim(values) == 1:
            values = values[:, None]
        if np.shape(values)[0] < 1:
            raise ValueError("Recorded.values must have at least one row")
        object.__setattr__(self, "values", values)

    @property
    def dim(self) -> int:
        return int(np.shape(self.values)[1])

    def at(self, t, T):
        v = jnp.asarray(self.values)
        return v[jnp.clip(jnp.asarray(t, jnp.int32), 0, v.shape[0] - 1)]


def evaluate(reference: AbstractReference, steps: int, T, *, start: int = 0) -> jax.Array:
    """The reference over a run: ``reference.at(t, T)`` for t = start .. start + steps - 1.

    Args:
      reference: any :class:`AbstractReference`.
      steps: static int >= 1, the number of fast instants K.
      T: the fast period in seconds.
      start: static int >= 0, the first instant.

    Returns:
      float[K, p].

    Raises:
      ValueError: ``steps`` < 1 or ``start`` < 0, ``T`` <= 0 (when concrete), or
        ``reference`` not a reference.
    """
    if not isinstance(reference, AbstractReference):
        raise ValueError(f"evaluate: reference must be a jaxnc.references reference, got {type(reference).__name__}")
    check_int("evaluate: steps", steps, 1)
    check_int("evaluate: start", start, 0)
    check_positive("evaluate: T", T)
    t = jnp.arange(start, start + steps, dtype=jnp.int32)
    return jax.vmap(reference.at, in_axes=(0, None))(t, T)


def held_at_end(reference: AbstractReference, steps: int, T) -> jax.Array:
    """Whether r holds its value at the run's last instant from then on: bool[p], per
    channel, for a run of ``steps`` fast instants at period T (so that r_{steps-1} is a
    final value to step to). A ``Step`` once applied (:meth:`Step.applied` at steps - 1), a
    ``PiecewiseLinear`` whose last breakpoint is at or before (steps - 1) T (within 1e-4 T),
    a ``Recorded`` of at most ``steps`` rows; never a reference that does not settle
    (``Ramp``, ``Sine``); a reference of another class that settles, always. ``steps`` is a
    static int >= 1; the reference's fields may be traced.

    Raises:
      ValueError: ``steps`` < 1, or ``reference`` not a reference.
    """
    if not isinstance(reference, AbstractReference):
        raise ValueError(f"held_at_end: reference must be a jaxnc.references reference, got "
                         f"{type(reference).__name__}")
    check_int("held_at_end: steps", steps, 1)
    p = reference.dim
    if not reference.settles:
        return jnp.zeros((p,), bool)
    if isinstance(reference, Step):
        return reference.applied(steps - 1, T)
    if isinstance(reference, PiecewiseLinear):
        v = jnp.asarray(reference.values)
        last = jnp.asarray(reference.times, v.dtype)[-1]
        end = _time(steps - 1, T, v.dtype) + _TIME_TOL * jnp.asarray(T, v.dtype)
        return jnp.broadcast_to(last <= end, (p,))
    if isinstance(reference, Recorded):
        return jnp.full((p,), np.shape(reference.values)[0] <= steps)
    return jnp.ones((p,), bool)


def check_channels(owner: str, reference, channels: int) -> None:
    """Refuse a ``reference`` that a part of ``channels`` loops (``len(index)``) cannot track:
    it must have 1 channel (shared by every loop) or ``channels``; None, or a reference that
    is not an :class:`AbstractReference`, passes (checked elsewhere).

    Raises:
      ValueError: "``owner``.reference must have 1 or c channels (len(index) = c), got p"."""
    if isinstance(reference, AbstractReference) and reference.dim not in (1, channels):
        want = "1 channel" if channels == 1 else f"1 or {channels} channels"
        raise ValueError(f"{owner}.reference must have {want} (len(index) = {channels}), got {reference.dim}")


def at_channels(reference: AbstractReference | None, t, T, channels: int) -> jax.Array:
    """float[channels]: ``reference.at(t, T)`` broadcast to ``channels`` (a reference of 1 or
    ``channels`` channels), or float32 zeros when ``reference`` is None: what a controller of
    ``channels`` loops tracks at fast instant ``t``."""
    if reference is None:
        return jnp.zeros((channels,), jnp.float32)
    return jnp.broadcast_to(reference.at(t, T), (channels,))

