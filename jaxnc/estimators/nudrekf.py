"""Non-uniform dual-rate EKF with h-step-ahead prediction stage (NUDREKF).

Seed 000, section 3.3.1. The filter runs at the fast period T. When a sensor packet
arrives (event triggered, eq. 4, and not dropped) it corrects with eq. (13); then the
prediction stage (steps 1-5) iterates controller and model h*N times, producing the
fast-rate estimates xi_{k..k+hN-1} and the control actions u_{k..k+hN-1} that are sent
as one packet (packet-based control).

Between corrections the covariance is propagated with eq. (11) once per elapsed fast
period (``ekf_predict``), along the control actions the remote side itself sent (it
cannot know whether the controller-to-actuator packet was lost). Propagating P along
the whole horizon at every correction, as the text literally says, would compute
h*N covariance steps of which only those up to the next correction are ever used.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc.estimators.ekf import Gaussian, ekf_update, ekf_update_diag
from jaxnc.estimators.sparsity import EKFStructure


def nudrekf_correct(model, belief: Gaussian, z, R, *, jacobian_grad: bool = True,
                    structure: EKFStructure | None = None) -> Gaussian:
    """Correction at an arrival instant, eq. (13)-(16).

    ``R`` is the measurement noise covariance [s, s], or a vector of variances for
    additive noise with a diagonal covariance (then the update is processed one
    scalar at a time: same result, no factorisation; see ``ekf_update_diag``, which
    also explains ``jacobian_grad`` and ``structure``; the general update is dense)."""
    if jnp.ndim(R) == 1:
        return ekf_update_diag(model.measure, belief, z, R, z.shape[0], jacobian_grad=jacobian_grad,
                               structure=structure)
    if not jacobian_grad:
        raise ValueError("nudrekf_correct: jacobian_grad=False needs a diagonal R (a vector of variances)")
    return ekf_update(model.measure, belief, z, R, z.shape[0])


def predict_horizon(model, controller: Callable, mean, ctrl_state, steps: int, hold: int = 1, noise_dim: int = 0,
                    controller_next: Callable | None = None):
    """Prediction stage of section 3.3.1 (steps 1-5), eq. (17).

    Starting from the corrected estimate, evaluate ``controller(mean, ctrl_state) ->
    (u, ctrl_state)`` and iterate the noise-free model ``steps`` times. The controller
    runs every ``hold`` fast periods and its action is held in between (``hold = N``
    gives a single-rate controller at period NT; ``hold = 1`` the dual-rate one).

    ``controller_next``, if given, replaces ``controller`` after the first step: along
    the noise-free prediction the controller can use cheaper searches (e.g. a narrow
    path window), while the first step starts from a corrected estimate.

    Returns ``(means[steps + 1], actions[steps], ctrl_states)`` where ``ctrl_states``
    has a leading axis of ``steps + 1``: entry j is the controller state at time k + j.
    """
    w0 = jnp.zeros((noise_dim,), mean.dtype)
    nxt = controller if controller_next is None else controller_next
    u_spec = jax.eval_shape(controller, mean, ctrl_state)[0]

    def body(carry, j):
        x, c, u_prev = carry
        u_new, c_new = jax.lax.cond(j == 0, controller, nxt, x, c) if nxt is not controller else controller(x, c)
        run = (j % hold) == 0
        u = jnp.where(run, u_new, u_prev)
        c = jax.tree.map(lambda a, b: jnp.where(run, a, b), c_new, c)
        x_next = model.dynamics(x, u, w0)
        return (x_next, c, u), (x_next, u, c)

    u_init = jnp.zeros(u_spec.shape, u_spec.dtype)
    _, (xs, us, cs) = jax.lax.scan(body, (mean, ctrl_state, u_init), jnp.arange(steps))
    means = jnp.concatenate([mean[None], xs], axis=0)
    ctrl_states = jax.tree.map(lambda a0, a: jnp.concatenate([a0[None], a], axis=0), ctrl_state, cs)
    return means, us, ctrl_states


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
    controller state at the instant (before computing ``u``, entry j of
    ``predict_horizon``'s ``ctrl_states``) and ``c_after`` after it.
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
    j times gives entry j of :func:`predict_horizon` (a test checks this).
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
