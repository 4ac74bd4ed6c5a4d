"""Open-loop prediction: a control law and a noise-free model iterated together (seed 004,
section 3.2, eq. 14; the one kernel behind every predicting part: ``Predictive``,
``LeadFeedback``, ``PursuitPI``).

From a corrected state xi_{k|k} the controller and a noise-free model (one step of it: a
fast period, or a slow period for a lifted model) are iterated in open loop,

    (U_{k+j}, c_{j+1}) = law(c_j, xi_{k+j|k}),   xi_{k+j+1|k} = f(xi_{k+j|k}, U_{k+j}, 0),

for j = 0 .. length - 1, giving the predicted states xi_{k|k} .. xi_{k+length-1|k} and
the actions U_k .. U_{k+length-1} that a packet-based actuator applies by time stamp.
The law's state c (integrators, path progress) is carried along the prediction.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

__all__ = ["predict_periods"]


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
