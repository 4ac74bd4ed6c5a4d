"""Controllers for a loop: state feedback, a user function, and a packet of predicted actions.

* :class:`StateFeedback`: u = -K (xhat - x_ref), saturated to [u_min, u_max] (gains from
  :func:`jaxnc.controllers.hold_lq.dlqr` or the hold-aware LQ gain);
* :class:`IntegralFeedback`: state feedback with integral action on chosen outputs,
  u = u_ref - K (xhat - x_ref) - Ki z, z <- z + C_int xhat - r (python-control's
  ``dlqr(..., integral_action=C_int)`` law), with a reference and anti-windup;
* :class:`Function`: u = fn(params, xhat) for any user law (``fn`` static, ``params``
  a pytree of leaves that can be tuned or differentiated);
* :class:`Predictive`: a packet of ``horizon`` fast actions (seed 000 section 3.3.1,
  seed 004 eq. 14): from xhat the law and the model (noise-free) are iterated in open
  loop, u_j = law(x_j), x_{j+1} = f(x_j, u_j, 0); the actuator applies them by time
  stamp (:class:`jaxnc.loop.actuators.PacketActuator` with the same horizon).

A controller runs at every slow instant; its packet carries the stamp kN.
"""
from __future__ import annotations

from typing import Any, Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.controllers.prediction import predict_periods
from jaxnc._validate import (array_fields, check_callable, check_finite, check_given, check_instance, check_int,
                             check_range, fields_concrete)
from jaxnc.loop.base import AbstractController, AbstractPlant, Packet
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["StateFeedback", "IntegralFeedback", "IntegralFeedbackState", "Function", "Predictive"]


class _OneAction(AbstractController):
    """A law u = action(xhat) sent as a packet of one action."""

    horizon = 1

    def init(self, ctx):
        return ()

    def step(self, state, xhat, fresh, k, ctx):
        u = self.action(xhat)
        return state, Packet(u[None, :], (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)


def _check_feedback(owner: str, part) -> None:
    """The checks a state feedback law's K, x_ref, u_ref and limits get (``StateFeedback``,
    ``IntegralFeedback``), naming ``owner``'s field: given and finite; limits None or in
    [-inf, inf]."""
    check_given(f"{owner}.K", part.K, "a gain matrix (m x n)")
    check_finite(f"{owner}.K", part.K)
    check_given(f"{owner}.x_ref", part.x_ref)
    check_finite(f"{owner}.x_ref", part.x_ref)
    check_finite(f"{owner}.u_ref", part.u_ref)
    for n in ("u_min", "u_max"):        # None or +-inf: unbounded
        check_range(f"{owner}.{n}", getattr(part, n), finite=False)


def _check_limit_order(owner: str, part) -> None:
    if part.u_min is not None and part.u_max is not None and np.any(np.asarray(part.u_min) > np.asarray(part.u_max)):
        raise ValueError(f"{owner}.u_min must be <= u_max")


def _feedback(part, xhat, extra=None):
    """(v, u): v = u_ref - K (xhat - x_ref) - extra (extra None: none), u = v clipped to
    [u_min, u_max] (v itself without limits)."""
    v = -(jnp.asarray(part.K) @ (xhat - part.x_ref))
    if extra is not None:
        v = v - extra
    if part.u_ref is not None:
        v = part.u_ref + v
    if part.u_min is None and part.u_max is None:
        return v, v
    return v, jnp.clip(v, part.u_min, part.u_max)


@_dataclass
class StateFeedback(_OneAction):
    """u = clip(u_ref - K (xhat - x_ref), u_min, u_max).

    Attributes: K float[m, n]; x_ref float[n] (default 0); u_min, u_max float[m] or None;
    u_ref float[m] or None (the default: 0), the action at x_ref, e.g. the input of an
    operating point (x_ref, u_ref) that ``LTI.linearize`` linearised a plant around.
    """

    field_shapes = {"K": (("input", "estimate"),), "x_ref": ((), ("estimate",)), "u_min": ((), ("input",)),
                    "u_max": ((), ("input",)), "u_ref": ((), ("input",))}

    K: Any
    x_ref: Any = 0.0
    u_min: Any = None
    u_max: Any = None
    u_ref: Any = None

    def __post_init__(self):
        _check_feedback("StateFeedback", self)
        array_fields(self, "K", "x_ref", "u_min", "u_max", "u_ref")
        if not fields_concrete(self):
            return
        K = np.atleast_2d(np.asarray(self.K, np.float32))
        object.__setattr__(self, "K", K)
        if not np.all(np.isfinite(K)):
            raise ValueError("StateFeedback.K must be finite")
        _check_limit_order("StateFeedback", self)

    def action(self, xhat):
        return _feedback(self, xhat)[1]


class IntegralFeedbackState(NamedTuple):
    """z float[c], the integrated errors C_int x̂ - r of the slow instants before this one."""

    z: jax.Array


@_dataclass
class IntegralFeedback(AbstractController):
    """State feedback with integral action (LQI), at every slow instant k:

        u_k = clip(u_ref - K (x̂_k - x_ref) - Ki z_k, u_min, u_max),
        z_{k+1} = z_k + (C_int x̂_k - r_k),   z_0 = 0,

    r_k = ``reference.at(kN, T)`` (a :mod:`jaxnc.references` object of 1 or c channels), or
    C_int x_ref when ``reference`` is None (regulation at x_ref). This is python-control's
    law for ``control.dlqr(A_h, B_h, Q, R, integral_action=C_int)``, whose gain is [K, Ki]
    for the system augmented with z_{k+1} = z_k + C_int x_k (design it on the slow-period
    system of the held action, :func:`~jaxnc.loop.slow_system` with ``hold=True``, in the
    coordinates x - x_ref, u - u_ref). A constant load or a model error then leaves no
    steady-state error in C_int x (where the closed loop settles). It computes at every slow
    instant on the estimate, as :class:`StateFeedback`, and always sends; it integrates at every
    slow instant too, so give it an estimator that predicts between measurements (an observer,
    an ``EKF``): behind a ``Passthrough`` over a lossy uplink it would integrate the held
    measurement (``PID(hold=True)`` skips such instants).

    Anti-windup (``anti_windup``, static): ``"conditional"`` (the default) does not integrate
    at an instant where the clip changed the action (any entry: conditional integration; no
    effect without limits), ``"none"`` always integrates.

    Attributes: K float[m, n]; Ki float[m, c]; C_int float[c, n] (c >= 1 integrated outputs);
    x_ref float[n] (default 0); u_ref float[m] or None (0); reference, as above, or None;
    u_min, u_max float[m] or None; anti_windup as above. Every number is a differentiable leaf
    (the clip has its a.e. derivative).

    Raises: ValueError naming the field for a gain that is not given or not finite, Ki or
    C_int whose shapes do not agree with K's (Ki m x c, C_int c x n), a reference that is not a
    :mod:`jaxnc.references` object or has neither 1 nor c channels, u_min > u_max, or an
    unknown ``anti_windup``; when a Loop is built, K, x_ref, u_ref or the limits that do not
    fit the loop's estimate and input.
    """

    field_shapes = {"K": (("input", "estimate"),), "x_ref": ((), ("estimate",)), "u_min": ((), ("input",)),
                    "u_max": ((), ("input",)), "u_ref": ((), ("input",))}
    horizon = 1

    K: Any
    Ki: Any
    C_int: Any
    x_ref: Any = 0.0
    u_ref: Any = None
    reference: Any = None
    u_min: Any = None
    u_max: Any = None
    anti_windup: str = _static("conditional")

    def __post_init__(self):
        from jaxnc._validate import check_choice
        from jaxnc.references import AbstractReference, check_channels
        _check_feedback("IntegralFeedback", self)
        for n, what in (("Ki", "an integral gain matrix (m x c)"), ("C_int", "the integrated outputs' matrix (c x n)")):
            check_given(f"IntegralFeedback.{n}", getattr(self, n), what)
            check_finite(f"IntegralFeedback.{n}", getattr(self, n))
        object.__setattr__(self, "anti_windup", check_choice("IntegralFeedback.anti_windup", self.anti_windup,
                                                             ("conditional", "none")))
        if self.reference is not None:
            check_instance("IntegralFeedback.reference", self.reference, AbstractReference,
                           "a jaxnc.references object (Step, Ramp, Sine, PiecewiseLinear, Recorded) or None")
        array_fields(self, "K", "Ki", "C_int", "x_ref", "u_min", "u_max", "u_ref")
        if not fields_concrete(self):
            return
        K, Ki, C = (np.atleast_2d(np.asarray(getattr(self, n), np.float32)) for n in ("K", "Ki", "C_int"))
        m, n = K.shape
        c = C.shape[0]
        if K.ndim != 2 or C.ndim != 2 or C.shape[1] != n:
            raise ValueError(f"IntegralFeedback.C_int must have {n} columns (K's: the estimate's entries), "
                             f"got shape {C.shape}")
        if Ki.shape != (m, c):
            raise ValueError(f"IntegralFeedback.Ki must be {m}x{c} (K's rows x C_int's rows), got shape {Ki.shape}")
        check_channels("IntegralFeedback", self.reference, c)
        for name, v in (("K", K), ("Ki", Ki), ("C_int", C)):
            object.__setattr__(self, name, v)
        _check_limit_order("IntegralFeedback", self)

    def init(self, ctx) -> IntegralFeedbackState:
        return IntegralFeedbackState(jnp.zeros((np.shape(self.C_int)[0],), jnp.float32))

    def step(self, state: IntegralFeedbackState, xhat, fresh, k, ctx):
        from jaxnc.references import at_channels
        C = jnp.asarray(self.C_int, jnp.float32)
        c = C.shape[0]
        v, u = _feedback(self, xhat, jnp.asarray(self.Ki) @ state.z)
        r = (C @ jnp.broadcast_to(jnp.asarray(self.x_ref, jnp.float32), xhat.shape) if self.reference is None
             else at_channels(self.reference, k * ctx.N, ctx.T, c).astype(jnp.float32))
        z = state.z + (C @ xhat - r)
        if self.anti_windup == "conditional" and (self.u_min is not None or self.u_max is not None):
            z = jnp.where(jnp.any(u != v), state.z, z)
        return IntegralFeedbackState(z), Packet(u[None, :], (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)


@_dataclass
class Function(_OneAction):
    """u = fn(params, xhat) (``fn`` static: define it at module level)."""

    params: Any
    fn: Callable = _static()

    def __post_init__(self):
        check_callable("Function.fn", self.fn, "a function fn(params, xhat) -> u")

    def action(self, xhat):
        return jnp.atleast_1d(self.fn(self.params, xhat))


@_dataclass
class Predictive(AbstractController):
    """A packet of ``horizon`` actions predicted along the noise-free model.

    Attributes: law, a one-action controller (:class:`StateFeedback`, :class:`Function`);
    model, an :class:`~jaxnc.loop.base.AbstractPlant`; horizon, static H >= 1.
    """

    law: Any
    model: Any
    horizon: int = _static(1)

    prediction_model: ClassVar[str] = "model"

    def __post_init__(self):
        if not callable(getattr(self.law, "action", None)):
            raise ValueError(f"Predictive.law must be a one-action controller (StateFeedback, Function), "
                             f"got {type(self.law).__name__}")
        check_instance("Predictive.model", self.model, AbstractPlant,
                       "a plant (a jaxnc.loop.AbstractPlant: LTI, Discrete, ...)")
        check_int("Predictive.horizon", self.horizon, 1, 1_000_000)

    def init(self, ctx):
        return ()

    def step(self, state, xhat, fresh, k, ctx):
        _, us, _, _ = predict_periods(lambda c, x: (self.law.action(x), c), self.model.dynamics, xhat, (),
                                   self.horizon, self.model.noise_dim)
        return state, Packet(us, (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)
