"""Delay compensation by a lead: act now on the state predicted ``lead`` periods ahead.

:class:`LeadFeedback` is seed 001's controller (eq. 16): the command for step ``k + lead``
is computed at k from the estimate predicted ``lead`` steps along the commands already
sent for steps ``k .. k + lead - 1`` (the controller's own plan, which it knows), and sent
stamped ``k + lead``. With a :class:`~jaxnc.loop.PacketActuator` that holds ``lead + 1``
packets the command is applied at its step if it arrived by then (seed 001 eq. 4).
"""
from __future__ import annotations

from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np

from jaxnc.controllers.prediction import predict_periods
from jaxnc._validate import (array_fields, check_finite, check_given, check_instance, check_int, check_range,
                             concrete)
from jaxnc.loop.base import AbstractController, AbstractPlant, Packet
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.references import AbstractReference

__all__ = ["LeadFeedback"]


@_dataclass
class LeadFeedback(AbstractController):
    """State feedback on the estimate predicted ``lead`` steps ahead (seed 001 eq. 16).

    At slow instant k (one rate: ``N = 1``), with the plan ``u_k .. u_{k+lead-1}`` of the
    commands already sent (zeros before the first):

        x_{j+1} = f(x_j, u_j, 0)  for j = k .. k+lead-1, from x_k = xhat_k
        u_{k+lead} = clip(-K (x_{k+lead} - r(k+lead)), -u_max, u_max)

    ``f`` is ``model.dynamics``; the command is sent in a packet of one action stamped
    ``k + lead`` and appended to the plan. ``lead = 0``: ``u_k = clip(-K (xhat_k - r(k)))``
    stamped k.

    Attributes:
      K: float[m, n], the gain (u = -K (x - r)).
      model: an :class:`~jaxnc.loop.AbstractPlant` (e.g. :class:`~jaxnc.loop.LTI`) with
        the estimate's state, for the prediction.
      reference: a :class:`jaxnc.references.AbstractReference` of n channels, or None (0).
      u_max: float[m] or scalar > 0, or None (no saturation).
      lead: static int in [0, 1000].

    In a :class:`~jaxnc.loop.Loop` its actuator must hold ``lead + 1`` packets and, when the
    downlink's delays vary by a fast period or more, the downlink must deliver every packet
    (``Link(order="all")``): newest-only delivery drops an older packet that arrives with a
    newer one although its action is still due (both refused when the loop is built).

    Raises:
      ValueError: a field out of range (naming it); at trace time, a loop with N != 1.
    """

    K: Any
    model: Any
    reference: Any = None
    u_max: Any = None
    lead: int = _static(2)

    field_shapes = {"K": (("input", "estimate"),), "u_max": ((), ("input",))}

    horizon = 1

    prediction_model: ClassVar[str] = "model"

    @property
    def stamps_ahead(self) -> int:
        """Its packets are stamped ``lead`` periods (N = 1: fast periods) ahead."""
        return self.lead

    def __post_init__(self):
        check_given("LeadFeedback.K", self.K, "a gain matrix (m x n)")
        check_finite("LeadFeedback.K", self.K)
        check_instance("LeadFeedback.model", self.model, AbstractPlant, "a plant (a jaxnc.loop.AbstractPlant: LTI, ...)")
        if self.reference is not None:
            check_instance("LeadFeedback.reference", self.reference, AbstractReference,
                           "a jaxnc.references reference (Step, Ramp, ...) or None")
        if self.u_max is not None:
            check_range("LeadFeedback.u_max", self.u_max, 0.0, None, low_open=True)
        check_int("LeadFeedback.lead", self.lead, 0, 1000)
        array_fields(self, "K", "u_max")
        if self.reference is not None and concrete(self.K) and np.ndim(self.K) == 2 \
                and self.reference.dim != np.shape(self.K)[1]:
            raise ValueError(f"LeadFeedback.reference must have n = {np.shape(self.K)[1]} channels (one per state, "
                             f"K's columns), got {self.reference.dim}")

    def init(self, ctx):
        if ctx.N != 1:
            raise ValueError(f"LeadFeedback runs at one rate: the loop's N must be 1, got {ctx.N}")
        return jnp.zeros((self.lead, ctx.input_dim), jnp.float32)

    def step(self, plan, xhat, fresh, k, ctx):
        x = xhat
        if self.lead:       # the state after the planned actions: the open-loop prediction along them
            x = predict_periods(lambda i, x: (plan[i], i + 1), self.model.dynamics, xhat, jnp.zeros((), jnp.int32),
                                self.lead, self.model.noise_dim)[3]
        r = 0.0 if self.reference is None else self.reference.at(k + self.lead, ctx.T)
        u = -(jnp.asarray(self.K, jnp.float32) @ (x - r))
        if self.u_max is not None:
            u = jnp.clip(u, -jnp.asarray(self.u_max, jnp.float32), jnp.asarray(self.u_max, jnp.float32))
        if self.lead:
            plan = jnp.concatenate([plan[1:], u[None]], axis=0)
        return plan, Packet(u[None], (k + self.lead).astype(jnp.int32)), jnp.ones((), jnp.float32)
