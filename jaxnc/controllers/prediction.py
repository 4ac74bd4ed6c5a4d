"""Open-loop prediction: a control law and a noise-free model iterated together (seed 004,
section 3.2, eq. 14; seed 000, section 3.3.1, eq. 17), in two forms: materialised,
:func:`predict_periods` (every predicting part: ``Predictive``, ``LeadFeedback``,
``PursuitPI``, ``Cascade``), and lazy, a :class:`PacketChain` advanced one fast period at a
time (:func:`advance_chain`: seed 000's actuator and the sender's copy of its packet).

From a corrected state xi_{k|k} the controller and a noise-free model (one step of it: a
fast period, or a slow period for a lifted model) are iterated in open loop,

    (U_{k+j}, c_{j+1}) = law(c_j, xi_{k+j|k}),   xi_{k+j+1|k} = f(xi_{k+j|k}, U_{k+j}, 0),

for j = 0 .. length - 1, giving the predicted states xi_{k|k} .. xi_{k+length-1|k} and
the actions U_k .. U_{k+length-1} that a packet-based actuator applies by time stamp.
The law's state c (integrators, path progress) is carried along the prediction.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["PacketChain", "advance_chain", "exhausted_chain", "predict_periods", "start_chain"]


def predict_periods(law: Callable, model: Callable, x0, c0: Any, length: int, noise_dim: int):
    """Iterate ``law`` and ``model`` in open loop for ``length`` slow periods (module docstring).

    Args:
      law: ``(c, x) -> (U, c)``; x float[n]; U any shape (e.g. float[N, m], the N fast
        actions of a period); c a pytree (the controller's state).
      model: ``(x, U, w) -> x_next``, the slow-period model, called with w = 0.
      x0: float[n], the corrected state xi_{k|k}.
      c0: the law's state at period k.
      length: static int >= 1, periods predicted (h + 1 for an h-step-ahead packet).
      noise_dim: the model's noise dimension (w = zeros(noise_dim)).

    Returns:
      (states float[length, n] = xi_{k|k} .. xi_{k+length-1|k}, actions [length, ...],
      law states after each period, pytree with leading axis ``length``, and the state
      xi_{k+length|k} after the last period).
    """
    w0 = jnp.zeros((noise_dim,), jnp.float32)

    def body(carry, _):
        x, c = carry
        U, c = law(c, x)
        return (model(x, U, w0), c), (x, U, c)

    (x_end, _), (states, Us, cs) = jax.lax.scan(body, (x0, c0), None, length=length)
    return states, Us, cs, x_end


class PacketChain(NamedTuple):
    """A control packet of section 3.3.1, represented by its prediction chain.

    The prediction stage is deterministic: the h*N actions of a packet are a function
    of the corrected estimate and the controller state it starts from. Rather than
    materialising them, a closed loop may keep the chain's position and advance it one
    fast period at a time (:func:`advance_chain`), producing at every instant exactly the
    action the packet carries for it. The cost per fast period is then one controller
    and one model evaluation, whatever h.

    ``j`` is the position (fast instant minus the packet's time stamp); ``x`` the
    predicted state and ``u`` the packet's action at that position; ``c_before`` the
    controller state at the instant (before computing ``u``) and ``c_after`` after it.
    """

    x: jax.Array
    u: jax.Array
    c_before: Any
    c_after: Any
    j: jax.Array   # int32


def start_chain(controller: Callable, mean, ctrl_state) -> PacketChain:
    """Position 0 of a new packet: the first action from the corrected estimate (step 1)."""
    u, c = controller(mean, ctrl_state)
    return PacketChain(mean, u, ctrl_state, c, jnp.zeros((), jnp.int32))


def exhausted_chain(mean, u, ctrl_state, horizon: int) -> PacketChain:
    """A chain that only holds ``u`` (e.g. the actuator before the first packet)."""
    return PacketChain(mean, u, ctrl_state, ctrl_state, jnp.asarray(horizon, jnp.int32))


def advance_chain(model, controller_next: Callable, chain: PacketChain, horizon: int, hold: int = 1,
                  noise_dim: int = 0) -> PacketChain:
    """Move the chain one fast period on (steps 2-4 of section 3.3.1).

    The model is iterated noise-free along the packet's action; the controller runs when
    the new position is a multiple of ``hold`` and below ``horizon`` (= h*N); past the
    horizon the packet's last action is held (section 2.4). Advancing ``start_chain``
    j times gives the packet's action and controller state at position j of the
    prediction stage, eq. (17): what :func:`predict_periods` materialises with a law run
    every ``hold`` periods below ``horizon`` (``tests/test_nudrekf.py`` checks both, and
    docs/design_notes.md says why the two forms are not one function).
    """
    w0 = jnp.zeros((noise_dim,), chain.x.dtype)
    x = model.dynamics(chain.x, chain.u, w0)
    j = chain.j + 1
    run = (j < horizon) & ((j % hold) == 0)
    u_new, c_new = controller_next(x, chain.c_after)
    u = jnp.where(run, u_new, chain.u)
    c_after = jax.tree.map(lambda a, b: jnp.where(run, a, b), c_new, chain.c_after)
    # past the horizon the prediction is no longer used: freeze it
    x = jnp.where(j <= horizon, x, chain.x)
    return PacketChain(x, u, chain.c_after, c_after, jnp.minimum(j, horizon))
