"""Rows of a random draw without drawing the rest: ``normal_rows(key, shape, every)`` equals
``jax.random.normal(key, shape)[::every]`` bit for bit, at 1/every of the cost.

The closed loops draw their noises per fast instant so that every scheme, whatever its
multiplicity N, meets the same realisation at the same time (common random numbers), but
the sensor and network draws are only used at slow instants, every N-th row. XLA does not
fuse the slice into the generator, so the unused rows would cost as much as the used ones
(what that measured: docs/design_notes.md).

JAX's default generator (threefry 2x32 with ``jax_threefry_partitionable``, the default
since JAX 0.5) hashes each element's flat index: element ``i`` of a float32 draw comes
from the 32-bit word ``threefry(key, (0, i))`` xor-folded, turned into a uniform by its
top 23 bits. We hash only the flat indices of the rows we keep and apply the same
transforms as ``jax.random.uniform`` / ``normal`` / ``exponential``. With another
generator or configuration the functions fall back to the full draw and the slice (same
values, full cost). ``tests/test_rows.py`` checks the equality bit for bit, so a JAX
release that changed the generator's layout would fail there, not silently.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["uniform_rows", "normal_rows", "exponential_rows"]


def _fast_path(key) -> bool:
    return (bool(jax.config.jax_threefry_partitionable)
            and not jax.dtypes.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key)
            and jax.config.jax_default_prng_impl == "threefry2x32")


def _bits_rows(key, shape, every: int):
    """uint32 words of ``jax.random.bits(key, shape)[::every]`` (threefry, partitionable)."""
    from jax.extend.random import threefry2x32_p
    rows = -(-shape[0] // every)
    inner = math.prod(shape[1:])
    if math.prod(shape) >= 2 ** 32:
        raise ValueError("rows: draws of 2**32 elements or more are not supported")
    idx = (jnp.arange(rows, dtype=jnp.uint32)[:, None] * np.uint32(every * inner)
           + jnp.arange(inner, dtype=jnp.uint32)[None, :]).reshape((rows,) + tuple(shape[1:]))
    key = jnp.asarray(key, jnp.uint32)
    b1, b2 = threefry2x32_p.bind(key[0], key[1], jnp.zeros_like(idx), idx)
    return b1 ^ b2


def _unit(bits):
    """float32 in [0, 1) from uint32 words, as ``jax.random.uniform`` (mantissa of [1, 2) - 1)."""
    f = lax.shift_right_logical(bits, np.uint32(32 - 23)) | np.uint32(np.array(1.0, np.float32).view(np.uint32))
    return lax.bitcast_convert_type(f, jnp.float32) - np.float32(1.0)


def uniform_rows(key, shape, every: int):
    """``jax.random.uniform(key, shape)[::every]`` (float32 in [0, 1))."""
    if not _fast_path(key):
        return jax.random.uniform(key, shape)[::every]
    # jax.random.uniform maps u to max(minval, u (maxval - minval) + minval): the identity
    # for [0, 1) (u * 1 and u + 0 are exact for u >= +0)
    return _unit(_bits_rows(key, shape, every))


def normal_rows(key, shape, every: int):
    """``jax.random.normal(key, shape)[::every]`` (float32)."""
    if not _fast_path(key):
        return jax.random.normal(key, shape)[::every]
    lo = np.nextafter(np.float32(-1.0), np.float32(0.0), dtype=np.float32)
    hi = np.float32(1.0)
    u = lax.max(lo, _unit(_bits_rows(key, shape, every)) * (hi - lo) + lo)
    return np.float32(np.sqrt(2)) * lax.erf_inv(u)


def exponential_rows(key, shape, every: int):
    """``jax.random.exponential(key, shape)[::every]`` (float32)."""
    if not _fast_path(key):
        return jax.random.exponential(key, shape)[::every]
    return lax.neg(lax.log1p(lax.neg(uniform_rows(key, shape, every))))
