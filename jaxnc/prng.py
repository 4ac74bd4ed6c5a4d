"""JAX's default random stream (Threefry-2x32), with the hash unrolled: the same bits, faster on CPU.

``jax.random`` lowers the Threefry-2x32 hash on CPU as a ``while`` loop of its five groups of
four rounds (a compile-time saving), so XLA:CPU materialises the two 32-bit words of every
counter five times; on a run's draws (:func:`jaxnc.loop.runner.draw`, e.g. 1000 seeds x 4830
process-noise samples) those passes cost more than the rest of the draw. :func:`unrolled`
re-labels a key with :data:`THREEFRY_UNROLLED`, a PRNG implementation equal to JAX's
``threefry2x32`` in everything (key shape, seeding) except that its 32-bit random bits
(:func:`random_bits`), :func:`split` and :func:`fold_in` come from :func:`threefry2x32`
written out, which XLA fuses with what uses them (one kernel instead of a loop's several).
Integer arithmetic is exact, so every key and draw (``normal``, ``uniform``, ``split``, ...)
is bit for bit JAX's (tests/test_prng.py); docs/design_notes.md, "The draws' hash unrolled"
and "Every draw through the unrolled hash".
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.random import define_prng_impl, threefry_prng_impl

__all__ = ["threefry2x32", "random_bits", "split", "fold_in", "THREEFRY_UNROLLED", "unrolled"]

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def threefry2x32(k1, k2, x1, x2):
    """Threefry-2x32 with 20 rounds (Salmon et al., "Parallel random numbers: as easy as
    1, 2, 3", SC 2011), the hash of JAX's ``threefry2x32`` PRNG, unrolled.

    Args:
      k1, k2: uint32 arrays (broadcastable), the key's two words; x1, x2: uint32 arrays, the
        counter's two words.

    Returns:
      (y1, y2), uint32 arrays of the broadcast shape: the hashed words.
    """
    ks = (k1, k2, k1 ^ k2 ^ np.uint32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x1 = x1 + x2
            x2 = lax.shift_left(x2, np.uint32(r)) | lax.shift_right_logical(x2, np.uint32(32 - r))
            x2 = x1 ^ x2
        x1 = x1 + ks[(i + 1) % 3]
        x2 = x2 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x1, x2


def _size(shape) -> int:
    return int(np.prod(shape, dtype=np.int64))


def _hash_indices(key, shape):
    """The hash under raw key data ``key`` (uint32[2]) of each element's row-major index
    (the counter (0, index)): the partitionable mode's bits and split keys."""
    lo = lax.iota(np.uint32, _size(shape)).reshape(shape)
    return threefry2x32(key[0], key[1], jnp.zeros(shape, np.uint32), lo)


def random_bits(key, bit_width: int, shape):
    """The random bits of JAX's ``threefry2x32`` (``jax_threefry_partitionable`` mode) for raw
    key data ``key`` (uint32[2]): each element's row-major index is the counter, and the
    result the xor of the hash's two words. Other widths, and the non-partitionable mode,
    are JAX's own function.

    Args:
      key: uint32[2]; bit_width: 8, 16, 32 or 64 (static); shape: static tuple of ints.

    Returns:
      uint{bit_width}[shape], bit for bit ``jax.random.bits`` of the same key.
    """
    if bit_width != 32 or not jax.config.jax_threefry_partitionable or _size(shape) >= 2**32:
        return threefry_prng_impl.random_bits(key, bit_width, shape)
    b1, b2 = _hash_indices(key, shape)
    return b1 ^ b2


def split(key, shape):
    """The keys of JAX's ``threefry2x32`` ``split`` (``jax_threefry_partitionable`` mode) of raw
    key data ``key`` (uint32[2]): the hash of the row-major index of each new key, its two words
    the new key. The non-partitionable mode and 2**32 keys or more are JAX's own function.

    Args:
      key: uint32[2]; shape: static tuple of ints, the keys' shape.

    Returns:
      uint32[*shape, 2], bit for bit ``jax.random.split`` of the same key.
    """
    shape = tuple(int(d) for d in shape)
    if not jax.config.jax_threefry_partitionable or _size(shape) >= 2**32:
        return threefry_prng_impl.split(key, shape)
    return jnp.stack(_hash_indices(key, shape), axis=len(shape))


def fold_in(key, data):
    """JAX's ``threefry2x32`` ``fold_in`` of raw key data ``key`` (uint32[2]) and a scalar
    ``data``: the hash of the counter (0, data as uint32), its two words the new key.

    Returns:
      uint32[2], bit for bit ``jax.random.fold_in`` of the same key and data.
    """
    d = jnp.asarray(data).astype(np.uint32)
    b1, b2 = threefry2x32(key[0], key[1], jnp.zeros((), np.uint32), d)
    return jnp.stack([b1, b2])


#: JAX's threefry2x32 PRNG with :func:`random_bits`, :func:`split` and :func:`fold_in` (the same streams)
THREEFRY_UNROLLED = define_prng_impl(
    key_shape=(2,), seed=threefry_prng_impl.seed, split=split,
    random_bits=random_bits, fold_in=fold_in, name="threefry2x32_unrolled", tag="fru")


def unrolled(key):
    """``key`` (a raw uint32[2] key or a typed key) as a typed key of :data:`THREEFRY_UNROLLED`
    when it is a threefry2x32 key (raw keys: when ``jax_default_prng_impl`` is threefry2x32);
    any other key is returned as it is. Draws from the result equal the key's own bit for bit."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if str(jax.random.key_impl(key)) != "threefry2x32":
            return key
        key = jax.random.key_data(key)
    elif jax.config.jax_default_prng_impl != "threefry2x32":
        return key
    return jax.random.wrap_key_data(key, impl=THREEFRY_UNROLLED)
