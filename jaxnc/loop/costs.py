"""Tracking metrics of a loop's run against a reference, per seed.

:class:`Tracking` names what is tracked: state components ``index`` of the true state x
(``Trajectory.x``, sampled at every fast instant t, time t T) against a
:mod:`jaxnc.references` reference r. Its :meth:`Tracking.metrics` applies
:mod:`jaxnc.tracking` to e_t = r_t - x_t[index] and to y = x[:, index], measured from
the step instant k0 of each channel (:meth:`Tracking.step_instant`): for a
:class:`~jaxnc.references.Step` the first fast instant at which it is applied
(:meth:`Step.onset <jaxnc.references.Step.onset>`, the rule of ``Step.at``), for every
other reference (Ramp, Sine, PiecewiseLinear, Recorded: no step instant) the first
sample, k0 = 0:

* ``ise``, ``iae``: :func:`jaxnc.tracking.ise` / ``iae`` of e over the whole run;
* ``itae``: :func:`jaxnc.tracking.itae` of e with time counted from k0,
  sum_t (t - k0)_+ T |e_t| T (the samples before the step weigh 0);
* ``overshoot`` (%), ``rise_time``, ``settling_time`` (s): :func:`jaxnc.tracking.step_info`
  of the samples y_{k0}, ..., y_{K-1}, times counted from k0 T, measured from
  y_initial = y_{k0} (the response at the step's instant) to the reference's final value
  r_{K-1} (python-control's ``step_info`` of the post-step data with ``yfinal`` = the
  setpoint); what y does before k0 does not enter them;
* ``steady_state_error``: :func:`jaxnc.tracking.steady_state_error` of e over the last
  ``window`` samples.

A reference that does not hold its last sample's value from then on
(:func:`jaxnc.references.held_at_end`: a ``Ramp`` or a ``Sine``, which do not settle, and a
``PiecewiseLinear`` whose last breakpoint, or a ``Recorded`` whose record, ends after the
run) has no final value to step to: its ``overshoot``, ``rise_time`` and ``settling_time``
are nan (measured toward r's last sample they changed with where the run stops); ISE, IAE,
ITAE and the steady-state error are as above.

A ``Step`` not applied within the run (``time`` after the last instant) has no step
response: its channels' ``itae``, ``overshoot``, ``rise_time`` and ``settling_time`` are
nan.

:func:`run_tracking` is the per-seed function for
``jaxnc.montecarlo.run_batched(run_tracking, keys, args=(loop, tracking))``: the loop's
:class:`~jaxnc.loop.Metrics` and the :class:`TrackingMetrics`.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc import tracking as _tr
from jaxnc._validate import check_components, check_instance, check_int, check_range, index_tuple
from jaxnc._validate import jit_when_eager
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop import runner as _runner
from jaxnc.references import AbstractReference, Step, check_channels, evaluate, held_at_end

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

    The step metrics (``overshoot``, ``rise_time``, ``settling_time``, ``itae``) are measured
    from :meth:`step_instant`: a ``Step``'s instant (per channel when its ``time`` is a
    vector), the run's first sample for the other references.

    Attributes:
      reference: a :class:`jaxnc.references.AbstractReference` with 1 or c channels.
      index: static int or tuple of c distinct ints >= 0, components of x.
      settling_threshold: static, relative band of the settling time, in (0, 1).
      window: static int >= 1, samples averaged for the steady-state error.

    Raises: ValueError naming the field; :meth:`signals` (so :meth:`metrics` and
    :func:`run_tracking`, at their first trace) when ``index`` is beyond the state x, and
    :meth:`metrics` when ``window`` is longer than the run.
    """

    reference: Any
    index: Any = _static(0)
    settling_threshold: float = _static(0.02)
    window: int = _static(1)

    def __post_init__(self):
        check_instance("Tracking.reference", self.reference, AbstractReference,
                       "a jaxnc.references object (Step, Ramp, Sine, PiecewiseLinear, Recorded)")
        object.__setattr__(self, "index", index_tuple("Tracking.index", self.index))
        check_channels("Tracking", self.reference, len(self.index))
        check_range("Tracking.settling_threshold", self.settling_threshold, 0.0, 1.0, low_open=True, high_open=True)
        check_int("Tracking.window", self.window, 1)

    def signals(self, x, T):
        """(y float[K, c], r float[K, c]) for the state trajectory x float[K, n] at period T."""
        check_components("Tracking.index", self.index, x.shape[1], "the state x")
        y = x[:, jnp.asarray(self.index)]
        r = evaluate(self.reference, x.shape[0], T).astype(y.dtype)
        return y, jnp.broadcast_to(r, y.shape)

    def step_instant(self, steps: int, T) -> jax.Array:
        """k0, int32[c]: the fast instant of each channel from which the step metrics are
        measured in a run of ``steps`` instants at period T (module docstring): the
        reference's :meth:`~jaxnc.references.Step.onset` for a ``Step`` (``steps`` when it
        is not applied within the run), 0 for any other reference."""
        c = len(self.index)
        if isinstance(self.reference, Step):
            return jnp.broadcast_to(self.reference.onset(steps, T), (c,))
        return jnp.zeros((c,), jnp.int32)

    def metrics(self, x, T) -> TrackingMetrics:
        """:class:`TrackingMetrics` of x float[K, n] sampled at period T (module docstring).

        One compiled program when called on concrete values
        (:func:`jaxnc._validate.jit_when_eager`)."""
        return _tracking_metrics(self, x, T)

    def _metrics(self, x, T) -> TrackingMetrics:
        y, r = self.signals(x, T)
        e = r - y
        K = y.shape[0]
        check_int(f"Tracking.window (samples averaged, the run has {K})", self.window, 1, K)
        k0 = self.step_instant(K, T)
        # the samples from k0 on, the last one repeated to length K: step_info's characteristics
        # of this are those of y[k0:] (the repeats change no first crossing, extremum or band exit)
        post = jnp.take_along_axis(y, jnp.minimum(jnp.arange(K)[:, None] + k0[None, :], K - 1), axis=0)
        stepped = k0 < K
        info = _tr.step_info(post, T, y_final=jnp.where(stepped, r[-1], jnp.nan), y_initial=post[0],
                             reference=r[-1], settling_threshold=self.settling_threshold)
        itae = jnp.where(stepped, _tr.itae(e, T, start=k0), jnp.nan)
        # no final value to step to (r still moves after the run): nan, not r's last sample
        held = jnp.broadcast_to(held_at_end(self.reference, K, T), k0.shape)
        overshoot, rise, settling = (jnp.where(held, v, jnp.nan)
                                     for v in (info.overshoot, info.rise_time, info.settling_time))
        return TrackingMetrics(_tr.ise(e, T), _tr.iae(e, T), itae, overshoot, rise,
                               settling, _tr.steady_state_error(e, window=self.window))


_tracking_metrics = jit_when_eager(lambda tracking, x, T: tracking._metrics(x, T))


def run_tracking(key, loop, tracking: Tracking):
    """(Metrics, TrackingMetrics) of one seed: ``run_batched(run_tracking, keys, args=(loop,
    tracking))``. Raises ValueError when the loop does not record ``"x"``.

    A run that failed (``Metrics.unstable``: the plant frozen at its last good state) has no
    tracking metrics, as its ``Metrics.cost`` is inf: its ``ise``, ``iae`` and ``itae`` are inf
    and its other fields nan, so that a summary of the batch (``print(tm)``,
    :func:`jaxnc.montecarlo.summarize`) leaves it out and counts it instead of averaging the
    frozen state's numbers with the others (the gradient of a mean flows through the runs that
    did not fail). ``tracking.metrics(traj.x, loop.T)`` of the run's trajectory gives the frozen
    run's numbers (as ``Metrics.cost_raw`` does for the cost)."""
    if "x" not in loop.record.signals:
        raise ValueError("run_tracking: the loop must record 'x' (Loop.record)")
    traj = _runner.simulate(loop, key)
    return _runner.evaluate(loop, traj), _failed(tracking.metrics(traj.x, loop.T), traj.failed)


def _failed(tm: TrackingMetrics, failed) -> TrackingMetrics:
    """``tm`` of a run, with a failed run's (``failed`` a bool scalar) integrals (``ise``,
    ``iae``, ``itae``) inf and its other fields nan (:func:`run_tracking`)."""
    integrals = ("ise", "iae", "itae")
    return TrackingMetrics(**{f: jnp.where(failed, jnp.inf if f in integrals else jnp.nan, v)
                              for f, v in tm._asdict().items()})
