"""Tracking metrics of one run: integral error criteria and step-response characteristics.

Every function takes one seed's sampled signal (fast period ``T``, sample k at time
t_k = k T) and works under ``jax.jit`` and ``jax.vmap`` (vmap over seeds for a
Monte-Carlo batch). Signals are ``float[K]`` (one channel) or ``float[K, p]``
(p channels, reduced per channel).

* :func:`ise`, :func:`iae`, :func:`itae`: the integral criteria by the rectangle rule
  over the samples (the error held over each period, as a sampled loop applies it);
* :func:`step_info`: python-control's ``step_info`` definitions on a sampled response;
* :func:`steady_state_error`: the mean error over the run's last samples.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, check_positive, check_range

__all__ = ["ise", "iae", "itae", "steady_state_error", "StepInfo", "step_info"]


def _signal(name, e):
    e = jnp.asarray(e)
    if e.ndim not in (1, 2) or e.shape[0] < 1:
        raise ValueError(f"{name} must be float[K] or float[K, p] with K >= 1, got shape {e.shape}")
    if not jnp.issubdtype(e.dtype, jnp.floating):
        e = e.astype(jnp.float32)
    return e


def ise(e, T) -> jax.Array:
    """Integral of the squared error, ISE = sum_k e_k^2 T (rectangle rule).

    Args:
      e: float[K] or float[K, p], the error r - y at t_k = k T.
      T: the sampling period in seconds (> 0).

    Returns:
      float[] or float[p] (per channel).

    Raises:
      ValueError: ``e`` not float[K] / float[K, p] with K >= 1, ``T`` <= 0 (when concrete).
    """
    e = _signal("ise: e", e)
    check_positive("ise: T", T)
    return jnp.sum(e * e, axis=0) * jnp.asarray(T, e.dtype)


def iae(e, T) -> jax.Array:
    """Integral of the absolute error, IAE = sum_k |e_k| T (rectangle rule).

    Args and Returns as :func:`ise`. The gradient at e_k = 0 is 0 (``jnp.abs``).
    """
    e = _signal("iae: e", e)
    check_positive("iae: T", T)
    return jnp.sum(jnp.abs(e), axis=0) * jnp.asarray(T, e.dtype)


def itae(e, T, *, start=0) -> jax.Array:
    """Integral of the time-weighted absolute error, ITAE = sum_k (t_k - t_s)_+ |e_k| T,
    t_k = k T, with time counted from sample ``start`` (t_s = start T; the samples before
    it weigh 0): the textbook ITAE of a step applied at t_s. The default ``start = 0`` is
    sum_k t_k |e_k| T.

    Args:
      e, T: as :func:`ise`.
      start: int scalar >= 0, or int[p] for a float[K, p] ``e`` (one per channel); may be
        traced (a start >= K weighs every sample 0).

    Returns:
      float[] or float[p] (per channel).

    Raises:
      ValueError: ``start`` not an integer scalar or int[p], or negative (when concrete);
        ``T`` <= 0 (when concrete); ``e`` without samples.
    """
    e = _signal("itae: e", e)
    check_positive("itae: T", T)
    s = jnp.asarray(start)
    if not jnp.issubdtype(s.dtype, jnp.integer) or s.ndim > e.ndim - 1 or (s.ndim == 1 and s.shape[0] != e.shape[1]):
        want = "an int" if e.ndim == 1 else f"an int or int[{e.shape[1]}]"
        raise ValueError(f"itae: start must be {want}, got {s.dtype}{list(s.shape)}")
    if not isinstance(start, jax.core.Tracer) and np.any(np.asarray(start) < 0):
        raise ValueError(f"itae: start must be >= 0 (a sample of e), got {np.asarray(start).tolist()}")
    k = jnp.arange(e.shape[0])
    if e.ndim == 2:
        k, s = k[:, None], jnp.broadcast_to(s, e.shape[1:])[None, :]
    t = jnp.maximum(k - s, 0).astype(e.dtype) * jnp.asarray(T, e.dtype)
    return jnp.sum(t * jnp.abs(e), axis=0) * jnp.asarray(T, e.dtype)


def steady_state_error(e, *, window: int = 1) -> jax.Array:
    """The steady-state error: the mean of ``e`` over its last ``window`` samples.

    Args:
      e: float[K] or float[K, p], the error r - y.
      window: static int in [1, K], the number of final samples averaged.

    Returns:
      float[] or float[p].

    Raises:
      ValueError: ``window`` not an integer in [1, K].
    """
    e = _signal("steady_state_error: e", e)
    check_int("steady_state_error: window", window, 1, e.shape[0])
    return jnp.mean(e[e.shape[0] - window:], axis=0)


class StepInfo(NamedTuple):
    """Step-response characteristics (python-control's ``step_info`` keys in brackets).

    Every field is float[] for a float[K] response, float[p] for float[K, p]; times in
    seconds, multiples of T.

    Attributes:
      rise_time: time from the first sample at ``rise_time_limits[0]`` of the final
        change to the first at ``rise_time_limits[1]`` [RiseTime]; nan if not reached.
      settling_time: first time after which the response stays within
        ``settling_threshold`` (relative) of the final value [SettlingTime]; nan if the
        last sample is outside.
      settling_min, settling_max: min / max of the response from the rise's upper
        instant on, each including the final value [SettlingMin, SettlingMax]; nan if
        that instant is not reached.
      overshoot: percent by which the peak in the final value's direction exceeds it
        [Overshoot], 0 if it does not.
      undershoot: percent of the final value by which the response goes the opposite way
        [Undershoot], 0 if it does not.
      peak: largest magnitude of the response [Peak]; peak_time: its first time [PeakTime].
      steady_state_value: the final value ``y_final`` [SteadyStateValue].
      steady_state_error: ``reference - y_final`` (nan when no reference is given).
    """

    rise_time: jax.Array
    settling_time: jax.Array
    settling_min: jax.Array
    settling_max: jax.Array
    overshoot: jax.Array
    undershoot: jax.Array
    peak: jax.Array
    peak_time: jax.Array
    steady_state_value: jax.Array
    steady_state_error: jax.Array


def _first(mask):
    """Index of the first True of ``mask`` (bool[K]) and whether there is one."""
    return jnp.argmax(mask), jnp.any(mask)


def _step_info_1(y, T, y_final, y_initial, reference, thr, lo, hi) -> StepInfo:
    """:func:`step_info` of one channel ``y`` float[K] (all other arguments scalars)."""
    K = y.shape[0]
    nan = jnp.asarray(jnp.nan, y.dtype)
    T = jnp.asarray(T, y.dtype)
    d = y - y_initial                      # python-control measures from 0: y_initial = 0 is its case
    inf = y_final - y_initial
    ok = jnp.isfinite(inf) & (inf != 0)
    inf_safe = jnp.where(ok, inf, 1.0)
    sgn = jnp.sign(inf_safe)
    i_lo, any_lo = _first(sgn * (d - lo * inf_safe) >= 0)
    i_hi, any_hi = _first(sgn * (d - hi * inf_safe) >= 0)
    rise_time = jnp.where(any_lo & any_hi, (i_hi - i_lo).astype(y.dtype) * T, nan)
    outside = jnp.abs(d / inf_safe - 1) >= thr
    k = jnp.arange(K)
    settled = jnp.max(jnp.where(outside, k + 1, 0))     # one past the last sample outside
    settling_time = jnp.where(settled < K, settled.astype(y.dtype) * T, nan)
    after = (k >= i_hi) & any_hi
    settling_min = jnp.where(any_hi, jnp.minimum(jnp.min(jnp.where(after, d, jnp.inf)), inf_safe), nan)
    settling_max = jnp.where(any_hi, jnp.maximum(jnp.max(jnp.where(after, d, -jnp.inf)), inf_safe), nan)
    dy_os = jnp.abs(jnp.max(sgn * d)) - jnp.abs(inf_safe)
    overshoot = jnp.where(dy_os > 0, jnp.abs(100.0 * dy_os / inf_safe), 0.0)
    y_us = d[jnp.argmin(sgn * d)]
    undershoot = jnp.where(sgn * y_us < 0, -100.0 * y_us / inf_safe, 0.0)
    i_pk = jnp.argmax(jnp.abs(d))
    peak, peak_time = jnp.abs(d[i_pk]), i_pk.astype(y.dtype) * T
    bad = lambda v, fill: jnp.where(ok, v, jnp.asarray(fill, y.dtype))
    return StepInfo(
        rise_time=bad(rise_time, jnp.nan), settling_time=bad(settling_time, jnp.nan),
        settling_min=bad(settling_min + y_initial, jnp.nan),
        settling_max=bad(settling_max + y_initial, jnp.nan),
        overshoot=bad(overshoot, jnp.nan), undershoot=bad(undershoot, jnp.nan),
        peak=bad(peak, jnp.inf), peak_time=bad(peak_time, jnp.inf),
        steady_state_value=jnp.where(jnp.isfinite(inf), y_final, nan),
        steady_state_error=reference - y_final)


def step_info(y, T, *, y_final=None, y_initial=0.0, reference=None, settling_threshold=0.02,
              rise_time_limits=(0.1, 0.9)) -> StepInfo:
    """Step-response characteristics of a sampled response, as python-control defines them.

    The definitions are python-control's ``step_info`` applied to time-series data with
    time points t_k = k T (``control.step_info(y, timepts=T * arange(K))``): every
    instant is a sample instant (no interpolation between samples), so the times are
    multiples of T and their gradient with respect to ``y`` is zero almost everywhere;
    overshoot, undershoot, peak and the settling extrema are differentiable in ``y``.

    One generalisation: python-control measures the response from 0. Here every
    characteristic is computed on the deviation ``y - y_initial`` from the response's
    initial value, with final change ``y_final - y_initial`` (identical for the default
    ``y_initial = 0``); ``peak`` is the magnitude of that deviation, ``settling_min``,
    ``settling_max`` and ``steady_state_value`` are levels of ``y`` itself.

    Args:
      y: float[K] or float[K, p], the response at t_k = k T (a float[K, p] response is
        characterised channel by channel).
      T: the sampling period in seconds.
      y_final: the final value, scalar or float[p]; None: the last sample ``y[-1]``
        (python-control's choice for time-series data). The final change must be
        nonzero.
      y_initial: the initial (pre-step) value, scalar or float[p].
      reference: the commanded final value, scalar or float[p], for
        ``steady_state_error = reference - y_final``; None: nan.
      settling_threshold: relative band around the final value (python-control's
        ``SettlingTimeThreshold``), in (0, 1).
      rise_time_limits: the two fractions of the final change between which the rise
        time is measured (``RiseTimeLimits``), 0 <= low < high <= 1.

    Returns:
      :class:`StepInfo`, each field float[] (or float[p]). A non-finite final change
      gives nan characteristics (peak and peak_time inf), as python-control does; so
      does a zero final change (python-control divides by it).

    Raises:
      ValueError: ``y`` not float[K] / float[K, p] with K >= 1, ``y_final``,
        ``y_initial`` or ``reference`` neither a scalar nor float[p] (float[K, p] ``y``),
        ``T`` <= 0, ``settling_threshold`` outside (0, 1) or ``rise_time_limits`` not two
        fractions low < high in [0, 1] (when concrete).
    """
    y = _signal("step_info: y", y)
    check_positive("step_info: T", T)
    p = 1 if y.ndim == 1 else y.shape[1]
    for name, v in (("y_final", y_final), ("y_initial", y_initial), ("reference", reference)):
        if v is not None and np.ndim(v) > 0 and (y.ndim == 1 or np.shape(v) not in ((p,), (1,))):
            want = "a scalar" if y.ndim == 1 else f"a scalar or float[{p}] (one per channel of y)"
            raise ValueError(f"step_info: {name} must be {want}, got shape {np.shape(v)}")
    check_range("step_info: settling_threshold", settling_threshold, 0.0, 1.0, low_open=True, high_open=True)
    if len(rise_time_limits) != 2:
        raise ValueError(f"step_info: rise_time_limits must be two fractions (low, high), got {rise_time_limits!r}")
    lo, hi = rise_time_limits
    check_range("step_info: rise_time_limits", rise_time_limits, 0.0, 1.0)
    if not isinstance(lo, jax.core.Tracer) and not isinstance(hi, jax.core.Tracer) and not float(lo) < float(hi):
        raise ValueError(f"step_info: rise_time_limits must have low < high, got {rise_time_limits!r}")
    dt = y.dtype
    y_final = y[-1] if y_final is None else jnp.asarray(y_final, dt)
    ref = jnp.full_like(y_final, jnp.nan) if reference is None else jnp.asarray(reference, dt)
    args = (jnp.asarray(T, dt), y_final, jnp.asarray(y_initial, dt), ref, jnp.asarray(settling_threshold, dt),
            jnp.asarray(lo, dt), jnp.asarray(hi, dt))
    if y.ndim == 1:
        return _step_info_1(y, *args)
    p = y.shape[1]
    per = tuple(jnp.broadcast_to(a, (p,)) for a in args[1:4])
    return jax.vmap(_step_info_1, in_axes=(1, None, 0, 0, 0, None, None, None))(
        y, args[0], *per, *args[4:])
