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

from typing import Callable

import jax
import jax.numpy as jnp

from jaxnc.estimators.ekf import Gaussian, ekf_update


def nudrekf_correct(model, belief: Gaussian, z, R) -> Gaussian:
    """Correction at an arrival instant, eq. (13)-(16)."""
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
