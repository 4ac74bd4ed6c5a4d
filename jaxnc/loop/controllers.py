"""Controllers for a loop: state feedback, a user function, and a packet of predicted actions.

* :class:`StateFeedback`: u = -K (xhat - x_ref), saturated to [u_min, u_max] (gains from
  :func:`jaxnc.controllers.hold_lq.dlqr` or the hold-aware LQ gain);
* :class:`Function`: u = fn(params, xhat) for any user law (``fn`` static, ``params``
  a pytree of leaves that can be tuned or differentiated);
* :class:`Predictive`: a packet of ``horizon`` fast actions (seed 000 section 3.3.1,
  seed 004 eq. 14): from xhat the law and the model (noise-free) are iterated in open
  loop, u_j = law(x_j), x_{j+1} = f(x_j, u_j, 0); the actuator applies them by time
  stamp (:class:`jaxnc.loop.actuators.PacketActuator` with the same horizon).

A controller runs at every slow instant; its packet carries the stamp kN.
"""
from __future__ import annotations

from typing import Any, Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.controllers.prediction import predict_periods
from jaxnc._validate import (array_fields, check_callable, check_finite, check_given, check_instance, check_int,
                             check_range, fields_concrete)
from jaxnc.loop.base import AbstractController, AbstractPlant, Packet
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["StateFeedback", "Function", "Predictive"]


class _OneAction(AbstractController):
    """A law u = action(xhat) sent as a packet of one action."""

    horizon = 1

    def init(self, ctx):
        return ()

    def step(self, state, xhat, fresh, k, ctx):
        u = self.action(xhat)
        return state, Packet(u[None, :], (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)


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
        check_given("StateFeedback.K", self.K, "a gain matrix (m x n)")
        check_finite("StateFeedback.K", self.K)
        check_given("StateFeedback.x_ref", self.x_ref)
        check_finite("StateFeedback.x_ref", self.x_ref)
        check_finite("StateFeedback.u_ref", self.u_ref)
        for n in ("u_min", "u_max"):        # None or +-inf: unbounded
            check_range(f"StateFeedback.{n}", getattr(self, n), finite=False)
        array_fields(self, "K", "x_ref", "u_min", "u_max", "u_ref")
        if not fields_concrete(self):
            return
        K = np.atleast_2d(np.asarray(self.K, np.float32))
        object.__setattr__(self, "K", K)
        if not np.all(np.isfinite(K)):
            raise ValueError("StateFeedback.K must be finite")
        if self.u_min is not None and self.u_max is not None and np.any(np.asarray(self.u_min) > np.asarray(self.u_max)):
            raise ValueError("StateFeedback.u_min must be <= u_max")

    def action(self, xhat):
        u = -(jnp.asarray(self.K) @ (xhat - self.x_ref))
        if self.u_ref is not None:
            u = self.u_ref + u
        if self.u_min is not None or self.u_max is not None:
            u = jnp.clip(u, self.u_min, self.u_max)
        return u


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
