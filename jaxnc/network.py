"""Network kernels shared by the links' delay models (seed 000, section 2.3, eq. 6-7).

A delay is usable at the first fast instant at or after the packet's arrival
(:func:`quantise_delay`), and a packet later than ``tau_max`` is discarded (:func:`late`).
The loss and delay *models* are the links' (:mod:`jaxnc.loop.links`: ``Bernoulli``,
``ShiftedExponential``, ...).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["quantise_delay", "late"]

_DTYPE = jnp.float32
# Relative guard for quantise_delay: about 4 float32 ulps.  Absorbs the
# round-off of delay/T (at most ~1.5 ulp for decimal inputs) while keeping
# e.g. 0.1000001 / 0.1 (8 ulps above 1) distinguishable from 1.
_QUANT_RTOL = 2.0**-21


def quantise_delay(delay, T) -> jax.Array:
    """Delay in whole fast periods ``T``: ``ceil(delay / T)`` as int32.

    A packet is usable at the first fast instant at or after its arrival.
    A relative guard of a few float32 ulps absorbs division round-off, so a
    delay of exactly ``m*T`` gives ``m`` (not ``m + 1``). When both are Python or NumPy
    numbers (a configuration's bound) it is computed in NumPy, the same float32
    operations, and returns a NumPy int32 array (no program is compiled).
    """
    xp = np if all(isinstance(a, (int, float, np.ndarray, np.generic)) for a in (delay, T)) else jnp
    delay = xp.asarray(delay, np.float32)
    T = xp.asarray(T, np.float32)
    steps = xp.ceil((delay / T) * np.float32(1.0 - _QUANT_RTOL))
    return xp.maximum(steps, np.float32(0.0)).astype(np.int32)


def late(delay, tau_max) -> jax.Array:
    """True where the packet arrives after ``tau_max`` and is discarded.

    The paper (section 2.3) forces ``tau_max < N T`` to avoid packet disorder.
    """
    return jnp.asarray(delay, _DTYPE) > jnp.asarray(tau_max, _DTYPE)
