"""A discrete PID controller part: derivative filter, anti-windup, setpoint weights, limits.

:class:`PID` runs at the slow instants (period h = N T) on ``c`` channels at once (one
independent loop per channel: decentralised PID). Channel i measures
``y_i = xhat[index[i]]``, the estimator's output component ``index[i]`` (a measurement's
entry with :class:`~jaxnc.loop.Passthrough`, a state's with an observer or an
:class:`~jaxnc.loop.EKF`), tracks the reference ``r = reference.at(kN, T)`` (a
:mod:`jaxnc.references` object) and drives the plant's input i (the packet's action has
``c`` entries, so ``c`` must equal the plant's ``input_dim``).

At a slow instant k where it computes, with h_k the time since its previous computation
(h at the first one, however many instants without a measurement came before it, and at
every instant when it computes at every instant; Åström and
Hägglund, *Advanced PID control*, section 3.7, backward differences, with Årzén's
event-based sampling interval):

    e = r - y,  e_p = b r - y,  e_d = c_w r - y                         (setpoint weights b, c)
    P_k = Kp e_p
    D_k = (Tf D_prev + Kd (e_d - e_d,prev)) / (Tf + h_k)               (first-order filter, Tf >= 0)
    v_k = u_b + P_k + I + D_k,   u_k = clip(v_k, u_min, u_max)         (u_b: the bias, u_bias)
    I <- I + h_k Ki e                                                   (anti_windup="none")
       = I + h_k Ki e, unless v_k > u_max and Ki e > 0
                       or v_k < u_min and Ki e < 0 (then I)            ("clamping")
       = I + h_k (Ki e + Kb (u_k - v_k))                                ("back_calculation";
                                                                          I unchanged where Ki = 0)

(I is updated after u_k is computed: u_k uses the integral of the errors before k.) A channel
without integral action (Ki = 0) keeps I = 0 in every mode: back-calculation feeds the
integrator, and there is none. The first computation takes e_d,prev = e_d (no derivative kick at start-up).
The bias u_b (``u_bias``, 0 by default; Åström and Hägglund's reset, the operating point's input: a
lift's hover thrust, a heater's base load) is the output at zero error: a PD with the right bias
holds the setpoint against a constant load without integral action, and a PI starts from it
instead of winding its integrator up to it.

No measurement (``hold=True``, the default): at an instant where ``fresh == 0`` (the
estimator received nothing) the controller does not compute: its state (integral,
filtered derivative, previous e_d, last output, instant of the last computation) is
unchanged, the packet carries its last output u_prev (0, clipped to the limits, before
the first computation) and ``send`` is 0, so a :func:`~jaxnc.loop.HoldLast` actuator
keeps applying u_prev: bumpless, no integration of a stale error, no derivative of a held
measurement; the next computation integrates over the whole elapsed time h_k, so the
integral action per second does not depend on how often measurements arrive.
``hold=False``: it computes at every instant (h_k = h, for an estimator that predicts
between measurements) and always sends.

All gains, limits and weights are differentiable leaves; ``fresh`` enters as the 0/1
float blend ``fresh * new + (1 - fresh) * old`` (a trigger's straight-through gradient
passes). The clip and the clamping switch have their a.e. derivatives (0 where saturated).
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import (check_bool, check_components, check_given, check_instance, check_range, index_tuple,
                             unbounded)
from jaxnc.loop.base import AbstractController, Packet, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.references import AbstractReference, at_channels, check_channels

__all__ = ["PID", "PIDState", "pid_update"]

_ANTI_WINDUP = ("none", "clamping", "back_calculation")


class PIDState(NamedTuple):
    """A :class:`PID`'s state (float[c] each, ``started`` float[], ``last`` int32[])."""

    integral: jax.Array   # I
    deriv: jax.Array      # D_prev, the filtered derivative term
    e_d: jax.Array        # e_d,prev
    u: jax.Array          # u_prev, the last output (held when nothing arrives)
    started: jax.Array    # 1.0 once it has computed
    last: jax.Array       # int32, the slow instant of the last computation


@_dataclass
class PID(AbstractController):
    """Discrete PID on ``c`` channels with derivative filter, anti-windup, setpoint
    weighting and output limits (the equations in the module docstring).

    Attributes:
      Kp, Ki, Kd: float or float[c] (Python numbers become float32, arrays keep their dtype), proportional, integral (1/s) and derivative (s) gains.
      Tf: float or float[c] >= 0, derivative filter time constant (s); 0: unfiltered.
      b, c: float or float[c], setpoint weights of the proportional and derivative terms.
      u_min, u_max: float, float[c] or None (unbounded), output limits, u_min <= u_max;
        u_min = -inf and u_max = inf are unbounded too (u_min = +inf or u_max = -inf is refused).
      Kb: float or float[c] >= 0, back-calculation gain (1/s), used with
        ``anti_windup="back_calculation"`` on the channels with Ki != 0.
      u_bias: float or float[c], the output's bias u_b (its value at zero error and zero
        integral: the operating point's input, e.g. a lift's hover thrust); 0 by default.
      reference: a :class:`jaxnc.references.AbstractReference` with 1 or c channels; None: 0.
      index: static int or tuple of c distinct ints >= 0, the estimator-output components
        measured.
      anti_windup: static, ``"none"``, ``"clamping"`` or ``"back_calculation"``.
      hold: static bool, hold (compute nothing, send nothing) when ``fresh == 0``.

    It computes in :attr:`dtype` (float32, or float64 when a gain, limit or the reference is a
    float64 array under x64): its state, the measurement and the reference are in it.

    Raises:
      ValueError: naming the field, for a non-finite gain, Tf or Kb < 0, u_min > u_max,
        u_min = +inf or u_max = -inf, a field that is neither a number nor float[1] /
        float[c] (JAX arrays are not checked: batched leaves), a reference that is not a :mod:`jaxnc.references` object, an index that is not
        a non-negative int or tuple of distinct ones, gains whose channel count differs
        from ``len(index)``, an unknown ``anti_windup``, ``"back_calculation"`` with u_min and
        u_max unbounded (None or inf: it would never act); when a ``Loop`` is built
        (its fit check traces one step), an index beyond the estimator's estimate.
    """

    Kp: Any = 0.0
    Ki: Any = 0.0
    Kd: Any = 0.0
    Tf: Any = 0.0
    b: Any = 1.0
    c: Any = 1.0
    u_min: Any = None
    u_max: Any = None
    Kb: Any = 1.0
    reference: Any = None
    index: Any = _static(0)
    anti_windup: str = _static("clamping")
    hold: bool = _static(True)
    u_bias: Any = 0.0

    def __post_init__(self):
        object.__setattr__(self, "index", index_tuple("PID.index", self.index, "the estimator-output components measured"))
        if self.anti_windup not in _ANTI_WINDUP:
            raise ValueError(f"PID.anti_windup must be one of {', '.join(_ANTI_WINDUP)}, got {self.anti_windup!r}")
        check_bool("PID.hold", self.hold)
        if self.reference is not None:
            check_instance("PID.reference", self.reference, AbstractReference,
                           "a jaxnc.references object (Step, Ramp, Sine, PiecewiseLinear, Recorded) or None")
        n = len(self.index)
        for name in ("Kp", "Ki", "Kd", "Tf", "b", "c", "Kb", "u_bias", "u_min", "u_max"):
            v = getattr(self, name)
            if name in ("u_min", "u_max"):
                check_range(f"PID.{name}", v, finite=False)            # None or +-inf: unbounded
            else:
                check_given(f"PID.{name}", v)
                check_range(f"PID.{name}", v, 0.0 if name in ("Tf", "Kb") else None)
            if v is None or isinstance(v, jax.Array):      # JAX arrays (batched leaves) are not checked
                continue
            a = np.asarray(v)
            if a.dtype.kind != "f" or not isinstance(v, np.ndarray):    # Python numbers: float32
                a = a.astype(np.float32)
            if a.ndim > 1 or (a.ndim == 1 and a.shape[0] not in (1, n)):
                raise ValueError(f"PID.{name} must be a number or have {n} entries (one per channel of "
                                 f"index), got shape {a.shape}")
            object.__setattr__(self, name, np.broadcast_to(a, (n,)).copy())
        lo, hi = self.u_min, self.u_max
        if isinstance(lo, np.ndarray) and np.any(lo == np.inf):
            raise ValueError(f"PID.u_min must be in [-inf, inf) (-inf: unbounded below), got {lo.tolist()}")
        if isinstance(hi, np.ndarray) and np.any(hi == -np.inf):
            raise ValueError(f"PID.u_max must be in (-inf, inf] (inf: unbounded above), got {hi.tolist()}")
        if isinstance(lo, np.ndarray) and isinstance(hi, np.ndarray) and np.any(lo > hi):
            raise ValueError(f"PID.u_min must be <= u_max, got {lo.tolist()} and {hi.tolist()}")
        check_channels("PID", self.reference, n)
        if self.anti_windup == "back_calculation" and unbounded(lo) and unbounded(hi):
            raise ValueError("PID.anti_windup='back_calculation' acts through u - v, u = clip(v, u_min, u_max), and "
                             "u_min and u_max are unbounded: it would never act (a saturation in a LimitedActuator "
                             "does not reach it); give u_min / u_max (the actuator's limits)")

    @property
    def channels(self) -> int:
        """c, the number of loops (``len(index)``)."""
        return len(self.index)

    @property
    def dtype(self):
        """The dtype it computes in: that of its gains, weights, limits and reference
        (float32 unless one of them is a float64 array and x64 is on)."""
        leaves = [getattr(self, n) for n in ("Kp", "Ki", "Kd", "Tf", "b", "c", "u_min", "u_max", "Kb", "u_bias")]
        leaves = [v for v in leaves + jax.tree.leaves(self.reference) if v is not None]
        return jnp.result_type(jnp.float32, *leaves)

    def init(self, ctx) -> PIDState:
        z = jnp.zeros((self.channels,), self.dtype)
        ub = jnp.broadcast_to(jnp.asarray(self.u_bias, self.dtype), z.shape)
        u0 = jnp.clip(ub, self.u_min, self.u_max) if self._limited else ub
        return PIDState(z, z, z, u0, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32))

    @property
    def _limited(self) -> bool:
        return self.u_min is not None or self.u_max is not None

    def step(self, state: PIDState, xhat, fresh, k, ctx):
        xhat = jnp.asarray(xhat)
        check_components("PID.index", self.index, xhat.shape[-1], "the estimator's estimate")
        dt = self.dtype
        y = xhat[jnp.asarray(self.index)].astype(dt)
        h = jnp.asarray(ctx.N * ctx.T, dt)
        if self.hold:
            h = h * jnp.where(state.started > 0.5, k - state.last, 1).astype(dt)
        new, u = pid_update(self, state, y, at_channels(self.reference, k * ctx.N, ctx.T, self.channels).astype(dt), h)
        new = new._replace(last=jnp.asarray(k, jnp.int32))
        if self.hold:
            w = jnp.asarray(fresh, jnp.float32)
            new, send = blend(w, new, state), w
        else:
            send = jnp.ones((), jnp.float32)
        return new, Packet(new.u[None, :], (k * ctx.N).astype(jnp.int32)), send


def pid_update(pid: PID, state: PIDState, y, r, h) -> tuple[PIDState, jax.Array]:
    """One computation of ``pid`` (module docstring) from the measurements y float[c] and the
    reference r float[c], h the time since the previous computation (h_k): (the new
    state, u float[c]); ``last`` is left to the caller."""
    e, ep, ed = r - y, pid.b * r - y, pid.c * r - y
    ed_prev = jnp.where(state.started > 0.5, state.e_d, ed)
    D = (pid.Tf * state.deriv + pid.Kd * (ed - ed_prev)) / (pid.Tf + h)
    v = pid.Kp * ep + state.integral + D + pid.u_bias
    u = jnp.clip(v, pid.u_min, pid.u_max) if pid._limited else v
    gain = pid.Ki * e
    if pid.anti_windup == "clamping" and pid._limited:
        hi = jnp.inf if pid.u_max is None else pid.u_max
        lo = -jnp.inf if pid.u_min is None else pid.u_min
        gain = jnp.where(((v > hi) & (gain > 0)) | ((v < lo) & (gain < 0)), 0.0, gain)
    elif pid.anti_windup == "back_calculation":
        # only where there is integral action: a channel with Ki = 0 has no integrator to unwind
        gain = gain + jnp.where(pid.Ki != 0, pid.Kb * (u - v), 0.0)
    integral = state.integral + h * gain
    return state._replace(integral=integral, deriv=D, e_d=ed, u=u, started=jnp.ones_like(state.started)), u
