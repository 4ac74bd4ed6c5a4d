"""Tracking metrics of a loop's run against a reference, per seed.

:class:`Tracking` names what is tracked: state components ``index`` of the true state x
(``Trajectory.x``, sampled at every fast instant t, time t T) against a
:mod:`jaxnc.references` reference r. Its :meth:`Tracking.metrics` applies
:mod:`jaxnc.tracking` to e_t = r_t - x_t[index]:

* ``ise``, ``iae``, ``itae``: :func:`jaxnc.tracking.ise` / ``iae`` / ``itae`` of e;
* ``overshoot`` (%), ``rise_time``, ``settling_time`` (s): :func:`jaxnc.tracking.step_info`
  of y = x[:, index] measured from its first sample y_0 to the reference's final value
  r_{K-1} (python-control's ``step_info`` with ``yfinal`` = the setpoint);
* ``steady_state_error``: :func:`jaxnc.tracking.steady_state_error` of e over the last
  ``window`` samples.

:func:`run_tracking` is the per-seed function for
``jaxnc.montecarlo.run_batched(run_tracking, keys, args=(loop, tracking))``: the loop's
:class:`~jaxnc.loop.Metrics` and the :class:`TrackingMetrics`.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc import tracking as _tr
from jaxnc._validate import check_components, check_instance, check_int, check_range
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop import runner as _runner
from jaxnc.references import AbstractReference, evaluate

__all__ = ["Tracking", "TrackingMetrics", "run_tracking"]


class TrackingMetrics(NamedTuple):
    """One run's tracking metrics, float[c] each (c = len(index)); see :class:`Tracking`."""

    ise: jax.Array
    iae: jax.Array
    itae: jax.Array
    overshoot: jax.Array
    rise_time: jax.Array
    settling_time: jax.Array
    steady_state_error: jax.Array

    def __repr__(self) -> str:
        from jaxnc.montecarlo import describe
        return describe(self, run_ndim=1)


@_dataclass
class Tracking:
    """State components ``index`` of the true state tracking ``reference`` (module docstring).

    Attributes:
      reference: a :class:`jaxnc.references.AbstractReference` with 1 or c channels.
      index: static int or tuple of c distinct ints >= 0, components of x.
      settling_threshold: static, relative band of the settling time, in (0, 1).
      window: static int >= 1, samples averaged for the steady-state error.

    Raises: ValueError naming the field; :meth:`signals` (so :meth:`metrics` and
    :func:`run_tracking`, at their first trace) when ``index`` is beyond the state x.
    """

    reference: Any
    index: Any = _static(0)
    settling_threshold: float = _static(0.02)
    window: int = _static(1)

    def __post_init__(self):
        check_instance("Tracking.reference", self.reference, AbstractReference,
                       "a jaxnc.references object (Step, Ramp, Sine, PiecewiseLinear, Recorded)")
        idx = (self.index,) if isinstance(self.index, int) and not isinstance(self.index, bool) else self.index
        if not isinstance(idx, (tuple, list)) or not idx or len(set(idx)) != len(idx) or \
                not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in idx):
            raise ValueError(f"Tracking.index must be an int >= 0 or a tuple of distinct ints >= 0, got {self.index!r}")
        object.__setattr__(self, "index", tuple(idx))
        if self.reference.dim not in (1, len(self.index)):
            c = len(self.index)
            want = "1 channel" if c == 1 else f"1 or {c} channels"
            raise ValueError(f"Tracking.reference must have {want} (len(index) = {c}), got {self.reference.dim}")
        check_range("Tracking.settling_threshold", self.settling_threshold, 0.0, 1.0, low_open=True, high_open=True)
        check_int("Tracking.window", self.window, 1)

    def signals(self, x, T):
        """(y float[K, c], r float[K, c]) for the state trajectory x float[K, n] at period T."""
        check_components("Tracking.index", self.index, x.shape[1], "the state x")
        y = x[:, jnp.asarray(self.index)]
        r = evaluate(self.reference, x.shape[0], T).astype(y.dtype)
        return y, jnp.broadcast_to(r, y.shape)

    def metrics(self, x, T) -> TrackingMetrics:
        """:class:`TrackingMetrics` of x float[K, n] sampled at period T (module docstring)."""
        y, r = self.signals(x, T)
        e = r - y
        info = _tr.step_info(y, T, y_final=r[-1], y_initial=y[0], reference=r[-1],
                             settling_threshold=self.settling_threshold)
        return TrackingMetrics(_tr.ise(e, T), _tr.iae(e, T), _tr.itae(e, T), info.overshoot, info.rise_time,
                               info.settling_time, _tr.steady_state_error(e, window=self.window))


def run_tracking(key, loop, tracking: Tracking):
    """(Metrics, TrackingMetrics) of one seed: ``run_batched(run_tracking, keys, args=(loop,
    tracking))``. Raises ValueError when the loop does not record ``"x"``."""
    if "x" not in loop.record.signals:
        raise ValueError("run_tracking: the loop must record 'x' (Loop.record)")
    traj = _runner.simulate(loop, key)
    return _runner.evaluate(loop, traj), tracking.metrics(traj.x, loop.T)
