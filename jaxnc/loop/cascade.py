"""A packet of actions from a stateful law along a model's prediction, computed on arrival
(seed 003 eq. 14-15, section 3.2.4).

At an arrival (``fresh``) at fast instant k (the slow instant's, k = j N) the controller runs
the prediction cascade from the estimate x(k|k), one action per fast period (A, B the
model over one fast period): for l = 0..H-1,

    u_{k+l} = law(s_{k+l}, k + l, x(k+l|k)),   x(k+l+1|k) = A x(k+l|k) + B u_{k+l},

and sends the packet {u_k, ..., u_{k+H-1}} stamped k (the actuator plays it by time
stamp, :class:`~jaxnc.loop.PacketActuator` of horizon H). The law's state is part of the
cascade: at the next arrival, k' - k fast periods later, the law restarts from the state
s_{k'} its last cascade reached at that instant (s_{k+H} for k' - k >= H), so a law with
memory (an integrator, an interlaced multi-rate controller, a disturbance observer)
continues as if it had run every period on the predictions. Without an arrival it
computes nothing, sends nothing and keeps its state (the paper's control side works only
when a measurement arrives). ``A = None`` holds the estimate along the cascade (a law on
the measurement itself, float[output_dim], without a model; then usually H = 1).

A law is a pytree with ``init() -> s`` and ``step(s, k, x) -> (u, s_next, aux)``: u a
scalar action (single input), ``aux`` anything the law reports (e.g. its disturbance
estimate), kept for the first action of the last packet in :attr:`CascadeState.aux`.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import array_fields, check_finite, check_given, check_int
from jaxnc.controllers.prediction import predict_periods
from jaxnc.loop.base import AbstractController, Packet, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["Cascade", "CascadeState", "cascade"]


class CascadeState(NamedTuple):
    """The state of a :class:`Cascade` controller: the law's states along the last cascade."""

    law: Any             # the law's states s_k .. s_{k+H} along the last cascade (leading axis H + 1)
    k_last: jax.Array    # int32: the instant of the last arrival
    aux: Any             # the law's aux output for the first action of the last cascade
    gap: jax.Array       # int32: k - k_last at an arrival (the multiplicity, eq. 9), 0 otherwise


@_dataclass
class Cascade(AbstractController):
    """The prediction-cascade controller (module docstring).

    Attributes:
      law: a pytree with ``init()`` and ``step(s, k, x) -> (u, s_next, aux)``.
      A: float[n, n], B: float[n], the single-input prediction model on the estimate
        float[n]; A = None: the estimate is the measurement float[output_dim], held along
        the cascade (B unused).
      horizon: static H >= 1, actions per packet.

    ``step(state, xhat, fresh, k, ctx) -> (state, Packet(float[H, 1], stamp k), send)``
    with send = fresh (a controller-side trigger, ``Loop.controller_trigger``, may gate it).
    """

    field_shapes = {"A": (("estimate", "estimate"),), "B": (("estimate",),)}

    law: Any
    A: Any = None
    B: Any = None
    horizon: int = _static(1)

    def __post_init__(self):
        check_int("Cascade.horizon", self.horizon, 1, 1_000_000)
        if self.A is not None:
            check_given("Cascade.B", self.B, "a vector float[n] (the single input's column) when A is given")
            check_finite("Cascade.A", self.A)
            check_finite("Cascade.B", self.B)
            array_fields(self, "A", "B")         # lists: one leaf each, arrays the prediction can use
        for n in ("init", "step"):
            if not callable(getattr(self.law, n, None)):
                raise ValueError(f"Cascade.law must have init() and step(s, k, x) -> (u, s_next, aux), "
                                 f"got {type(self.law).__name__} without {n}")

    def init(self, ctx) -> CascadeState:
        s0 = self.law.init()
        x0 = jnp.zeros((ctx.output_dim if self.A is None else jnp.shape(self.A)[0],), jnp.float32)
        aux0 = jax.eval_shape(lambda: self.law.step(s0, jnp.int32(0), x0)[2])
        states = jax.tree.map(lambda a: jnp.broadcast_to(a, (self.horizon + 1, *jnp.shape(a))), s0)
        zero = jnp.zeros((), jnp.int32)
        return CascadeState(states, zero, jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), aux0), zero)

    def step(self, state: CascadeState, xhat, fresh, k, ctx):
        H = self.horizon
        played = jnp.clip((k - state.k_last) * ctx.N, 1, H)     # actions of the last packet played since
        s0 = jax.tree.map(lambda a: a[played], state.law)
        n = xhat.shape[0]
        # the model in the estimate's dtype (float64 numpy matrices under x64 changed the prediction's dtype)
        A = jnp.eye(n, dtype=xhat.dtype) if self.A is None else jnp.asarray(self.A, xhat.dtype)
        B = jnp.zeros((n,), xhat.dtype) if self.A is None else jnp.asarray(self.B, xhat.dtype)
        # H + 1 steps: the last one only gives the law's state after the packet's last action
        us, ss, aux = cascade(self.law.step, A, B, xhat, s0, k * ctx.N, H + 1)
        new = CascadeState(ss, jnp.asarray(k, jnp.int32), jax.tree.map(lambda a: a[0], aux),
                           jnp.asarray(k - state.k_last, jnp.int32))
        kept = state._replace(gap=jnp.zeros((), jnp.int32))
        return (blend(fresh, new, kept), Packet(us[:H, None], (k * ctx.N).astype(jnp.int32)),
                jnp.asarray(fresh, jnp.float32))


def cascade(law, A, B, x0, s0, k, length: int):
    """Eq. (14)-(15): the prediction cascade x(k+l+1|k) = A x(k+l|k) + B u_{k+l}, with
    u_{k+l} from the stateful ``law``, for l = 0..length-1 (one open-loop prediction,
    :func:`jaxnc.controllers.prediction.predict_periods`).

    Args:
      law: ``law(s, k_l, x) -> (u, s_next, aux)``: the control law at instant k_l from the
        predicted state x float[n] and its own state s (a pytree); u a scalar.
      A: float[n, n]; B: float[n], the (single-input) prediction model.
      x0: float[n], x(k|k); s0: the law's state at k; k: int32 instant of x0.
      length: static, the number of actions (H + 1 for a packet of H actions).

    Returns:
      (us float[length], ss, aux): the actions u_k..u_{k+length-1}, the law's states at
      k..k+length-1 (leading axis length; ``ss[l]`` is the state *before* the action at
      k + l), and the law's ``aux`` outputs (leading axis length).
    """
    def step(c, x):
        s, kl = c
        u, s_next, aux = law(s, kl, x)
        return (u, s, aux), (s_next, kl + 1)

    _, (us, ss, aux), _, _ = predict_periods(step, lambda x, U, w: A @ x + B * U[0], x0,
                                             (s0, jnp.asarray(k, jnp.int32)), length, 0)
    return us, ss, aux
