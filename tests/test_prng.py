"""jaxnc.prng: JAX's threefry2x32 stream with the hash unrolled gives the same bits."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import prng


def _keys(n=64):
    return jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(1234), i))(jnp.arange(n))


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))


@pytest.mark.parametrize("shape", [(3,), (69, 10, 7), (2, 3, 5)])
def test_draws_equal_jax_bit_for_bit(shape):
    """normal, uniform and bits of many keys, under jit(vmap), equal JAX's own (raw keys).
    The five draws and their references are one compiled program per shape."""
    draws = (lambda k: jax.random.normal(k, shape, jnp.float32),
             lambda k: jax.random.uniform(k, shape, jnp.float32, -2.0, 3.0),
             lambda k: jax.random.bits(k, shape, jnp.uint32),
             lambda k: jax.random.bits(k, shape, jnp.uint8),
             lambda k: jax.random.bits(k, shape, jnp.uint16))
    both = jax.jit(lambda keys: [(jax.vmap(draw)(keys), jax.vmap(lambda k: draw(prng.unrolled(k)))(keys))
                                 for draw in draws])
    for ref, got in both(_keys()):
        assert _same(ref, got)


def test_split_fold_in_and_typed_keys():
    """split and fold_in are JAX's; a typed threefry key is re-labelled, other impls returned as they are."""
    k = jax.random.PRNGKey(7)
    u = prng.unrolled(k)
    assert jax.random.key_impl(u) == prng.THREEFRY_UNROLLED
    for a, b in zip(jax.random.split(k, 3), jax.random.split(u, 3)):
        assert _same(a, jax.random.key_data(b))
        assert _same(jax.random.normal(a, (11,)), jax.random.normal(b, (11,)))
    assert _same(jax.random.fold_in(k, 5), jax.random.key_data(jax.random.fold_in(u, 5)))
    typed = jax.random.key(7)
    assert _same(jax.random.normal(typed, (4, 3)), jax.random.normal(prng.unrolled(typed), (4, 3)))
    other = jax.random.key(7, impl="rbg")
    assert prng.unrolled(other) is other


def test_hash_matches_the_reference_vectors():
    """Threefry-2x32, 20 rounds: the known-answer vectors of Salmon et al.'s Random123
    (kat_vectors: key, counter -> result), as JAX's own test uses them."""
    u32 = lambda *v: np.array(v, np.uint32)
    cases = [((0x00000000, 0x00000000), (0x00000000, 0x00000000), (0x6b200159, 0x99ba4efe)),
             ((0xffffffff, 0xffffffff), (0xffffffff, 0xffffffff), (0x1cb996fc, 0xbb002be7)),
             ((0x13198a2e, 0x03707344), (0x243f6a88, 0x85a308d3), (0xc4923a9c, 0x483df7a0))]
    for key, count, want in cases:
        got = prng.threefry2x32(u32(key[0]), u32(key[1]), u32(count[0]), u32(count[1]))
        assert [int(np.asarray(g)[0]) for g in got] == list(want)


def test_runner_draws_are_jax_streams():
    """The loop's process and measurement noise are jax.random.normal of their streams' keys, scaled."""
    from jaxnc.loop.runner import STREAMS, draw
    from jaxnc.schemes.mecanum import mecanum_loop
    lp = mecanum_loop("DRHE", 10, 0.5)
    key = jax.random.PRNGKey(3)
    d = jax.jit(draw)(lp, key)
    S, N, p = lp.steps // lp.N, lp.N, lp.plant
    kw = jax.random.fold_in(key, STREAMS.index("process"))
    kv = jax.random.fold_in(key, STREAMS.index("measurement"))
    w = jax.jit(lambda k: jax.random.normal(k, (S, N, p.noise_dim), jnp.float32)
                * jnp.asarray(p.w_std, jnp.float32)[None, None, :])(kw)
    v = jax.jit(lambda k: jax.random.normal(k, (S, p.output_dim), jnp.float32)
                * jnp.asarray(p.v_std, jnp.float32)[None, :])(kv)
    assert _same(d.w, w) and _same(d.v, v)


@pytest.mark.parametrize("shape", [(2,), (3,), (4, 3)])
def test_split_and_fold_in_of_many_keys_equal_jax_bit_for_bit(shape):
    """The unrolled split and fold_in (prng.split, prng.fold_in) under jit(vmap) equal JAX's own."""
    keys = _keys()
    ref = jax.jit(jax.vmap(lambda k: jax.random.split(k, shape)))(keys)
    got = jax.jit(jax.vmap(lambda k: jax.random.key_data(jax.random.split(prng.unrolled(k), shape))))(keys)
    assert _same(ref, got)
    for data in (0, 4, 2**31 + 7):
        ref = jax.jit(jax.vmap(lambda k: jax.random.fold_in(k, data)))(keys)
        got = jax.jit(jax.vmap(lambda k: jax.random.key_data(jax.random.fold_in(prng.unrolled(k), data))))(keys)
        assert _same(ref, got)


@pytest.mark.parametrize("typed", [False, True])
def test_runner_link_draws_and_init_key_are_jax_streams(typed):
    """The links' draws (split, uniform losses, exponential delays) equal those of JAX's own
    stream, and the plant's initial key keeps the run key's kind (raw data or typed)."""
    from jaxnc.loop.links import draw_link
    from jaxnc.loop.runner import STREAMS, draw
    from jaxnc.schemes.mecanum import mecanum_loop
    lp = mecanum_loop("DRHE", 10, 0.5)
    key = jax.random.key(5) if typed else jax.random.PRNGKey(5)
    d = jax.jit(draw)(lp, key)
    S = lp.steps // lp.N
    for name, link, got in (("uplink", lp.uplink, d.uplink), ("downlink", lp.downlink, d.downlink)):
        ref = jax.jit(lambda k: draw_link(link, jax.random.fold_in(k, STREAMS.index(name)), S, lp.T))(key)
        assert _same(ref.delay, got.delay)
    init = jax.random.fold_in(key, STREAMS.index("plant_init"))
    assert d.init_key.dtype == init.dtype
    assert _same(jax.random.key_data(init) if typed else init, jax.random.key_data(d.init_key) if typed else d.init_key)
