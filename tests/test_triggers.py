"""The one PETC part (seed 000 eq. 3-4, seed 003 eq. 6-7 and 21-22) and its gradients."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

import jaxnc.loop as jl
from jaxnc.loop.triggers import fires_straight_through, petc_gap, soft_decision

CTX1 = jl.Context(N=1, steps=8, T=1.0, state_dim=1, input_dim=1, output_dim=1, signal_dim=1)


def _first_step(trig, zl, z, k=1):
    """One decision of ``trig`` whose zbar is ``zl`` (k > 0: nothing forced)."""
    return trig.step(jl.PetcState(zl, jnp.zeros((), jnp.int32)), z, k)[::-1]


def test_fires_exactly_when_eq4_holds():
    rng = np.random.default_rng(0)
    sigma = np.array([0.1, 0.05, 0.05], np.float32)
    delta = np.array([0.1, 0.1, 0.1], np.float32)
    trig = jl.Petc(sigma, delta)
    f = jax.jit(lambda zl, z: _first_step(trig, zl, z)[0])
    for _ in range(200):
        zl, z = rng.normal(size=3).astype(np.float32), rng.normal(size=3).astype(np.float32)
        lhs = np.sum((zl - z) ** 2)
        rhs = np.sum(sigma * z ** 2 + delta)
        assert float(f(zl, z)) == float(lhs > rhs)


def test_each_reading_fires_when_any_output_alone_holds():
    sigma, delta = np.zeros(2, np.float32), np.array([0.5, 0.5], np.float32)
    zl, z = jnp.zeros(2), jnp.array([0.8, 0.1])       # 0.64 > 0.5 on output 0 only; the sum 0.65 < 1.0
    assert float(_first_step(jl.Petc(sigma, delta, reading="each"), zl, z)[0]) == 1.0
    assert float(_first_step(jl.Petc(sigma, delta, reading="sum"), zl, z)[0]) == 0.0
    assert float(petc_gap(zl, z, sigma, delta, "each")) == pytest.approx(0.64 - 0.5)


def test_straight_through_value_is_exact_and_gradient_is_sigmoid():
    zl, z = jnp.zeros(2), jnp.array([0.8, 0.3])
    beta = _first_step(jl.Petc(np.zeros(2, np.float32), np.full(2, 0.5, np.float32), temperature=0.2), zl, z)[0]
    assert float(beta) in (0.0, 1.0)
    g = jax.grad(lambda d: _first_step(jl.Petc(jnp.zeros(2), d, 0.2), zl, z)[0])(jnp.full(2, 0.5))
    gap = 0.8 ** 2 + 0.3 ** 2 - 1.0
    s = 1 / (1 + np.exp(-gap / 0.2))
    np.testing.assert_allclose(g, [-s * (1 - s) / 0.2] * 2, rtol=1e-5)


def test_relaxed_forward_is_the_sigmoid():
    zl, z = jnp.zeros(2), jnp.array([0.8, 0.3])
    gap = 0.8 ** 2 + 0.3 ** 2 - 1.0
    beta = _first_step(jl.Petc(0.0, 0.5, temperature=0.2, relaxed=True), zl, z)[0]
    assert float(beta) == pytest.approx(1 / (1 + np.exp(-gap / 0.2)), rel=1e-6)
    with pytest.raises(ValueError, match="Petc.temperature"):
        jl.Petc(0.0, 0.5, relaxed=True)


def test_hard_trigger_has_zero_gradient():
    zl, z = jnp.zeros(2), jnp.array([0.8, 0.3])
    g = jax.grad(lambda d: _first_step(jl.Petc(jnp.zeros(2), d), zl, z)[0])(jnp.full(2, 0.5))
    np.testing.assert_array_equal(g, 0.0)
    assert float(soft_decision(jnp.float32(1.0), 0.0)) == 0.0
    assert float(fires_straight_through(jnp.float32(1e-9), 0.0)) == 1.0


def test_eq3_zbar_holds_the_last_sent_value_and_first_instant_sends():
    trig = jl.Petc(0.0, 1.0)                        # fires when (zbar - z)^2 > 1
    st = trig.init(CTX1)
    sends = []
    for k, z in enumerate([0.3, 0.8, 1.2, 1.5, 2.4]):
        st, b = trig.step(st, jnp.array([z], jnp.float32), k)
        sends.append(float(b))
    # k = 0 forced (zbar = 0.3); 0.25, 0.81 < 1; (1.5 - 0.3)^2 = 1.44 > 1 (zbar = 1.5); 0.81 < 1
    assert sends == [1.0, 0.0, 0.0, 1.0, 0.0]
    assert float(st.last[0]) == pytest.approx(1.5)


def test_max_silence_is_a_leaf_and_1_is_periodic():
    """The safety condition (seed 003 eq. 7) as a dynamic leaf: one compiled program for
    max_silence = 0 (off), 3 and 1 (every instant)."""
    z = jnp.zeros((8, 1), jnp.float32)                 # a constant signal never fires eq. (4)

    @jax.jit
    def sends(ms):
        trig = jl.Petc(0.0, 1.0, max_silence=ms)
        def body(st, kz):
            return trig.step(st, kz[1], kz[0])
        return jax.lax.scan(body, trig.init(CTX1), (jnp.arange(8), z))[1]

    np.testing.assert_array_equal(sends(jnp.int32(0)), [1, 0, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(sends(jnp.int32(3)), [1, 0, 0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(sends(jnp.int32(1)), np.ones(8))
    assert sends._cache_size() == 1


@pytest.mark.parametrize("kw, match", [(dict(delta=np.array([0.1, -0.1])), "Petc.delta"),
                                       (dict(sigma=-1.0), "Petc.sigma"),
                                       (dict(max_silence=1.5), "Petc.max_silence"),
                                       (dict(max_silence=-1), "Petc.max_silence"),
                                       (dict(reading="any"), "Petc.reading")])
def test_bad_parameters_are_rejected(kw, match):
    with pytest.raises(ValueError, match=match):
        jl.Petc(**kw)


def test_blend_is_an_exact_select_that_passes_gradients():
    z, zl = jnp.array([1.0, 2.0]), jnp.array([3.0, 4.0])
    np.testing.assert_array_equal(jl.blend(1.0, z, zl), z)
    np.testing.assert_array_equal(jl.blend(0.0, z, zl), zl)
    np.testing.assert_array_equal(jl.blend(1.0, jnp.int32(3), jnp.int32(5)), 3)
    g = jax.grad(lambda w: jnp.sum(jl.blend(w, z, zl)))(1.0)
    assert float(g) == pytest.approx(float(jnp.sum(z - zl)))


def test_a_temperature_known_to_be_zero_gives_the_hard_decision_with_no_soft_term():
    """fires_straight_through with a concrete temperature 0: the hard value, and no sigmoid in
    the program (nothing for reverse mode to carry); a traced temperature keeps the term, and
    a positive one the straight-through gradient."""
    gap = jnp.asarray([-0.5, 0.0, 0.7], jnp.float32)
    np.testing.assert_array_equal(np.asarray(fires_straight_through(gap, 0.0)), [0.0, 0.0, 1.0])
    assert "logistic" not in str(jax.make_jaxpr(lambda g: fires_straight_through(g, 0.0))(gap))
    assert "logistic" in str(jax.make_jaxpr(fires_straight_through)(gap, jnp.float32(0.0)))
    np.testing.assert_array_equal(np.asarray(jax.jit(fires_straight_through)(gap, jnp.float32(0.0))), [0.0, 0.0, 1.0])
    assert np.all(np.asarray(jax.grad(lambda g: jnp.sum(fires_straight_through(g, 0.5)))(gap)) > 0)
