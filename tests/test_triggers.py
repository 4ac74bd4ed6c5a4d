"""PETC trigger (seed 000 eq. 3-4) and its straight-through gradient."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxnc.triggers import PetcTrigger, hold_last_sent


def test_fires_exactly_when_eq4_holds():
    rng = np.random.default_rng(0)
    sigma = np.array([0.1, 0.05, 0.05], np.float32)
    delta = np.array([0.1, 0.1, 0.1], np.float32)
    trig = PetcTrigger(sigma, delta)
    f = jax.jit(trig.fires)
    for _ in range(200):
        zl, z = rng.normal(size=3).astype(np.float32), rng.normal(size=3).astype(np.float32)
        lhs = np.sum((zl - z) ** 2)
        rhs = np.sum(sigma * z ** 2 + delta)
        assert float(f(zl, z)) == float(lhs > rhs)


def test_straight_through_value_is_exact_and_gradient_is_sigmoid():
    trig = PetcTrigger(np.zeros(2, np.float32), np.full(2, 0.5, np.float32), temperature=0.2)
    zl = jnp.zeros(2)
    z = jnp.array([0.8, 0.3])
    beta = jax.jit(trig.fires)(zl, z)
    assert float(beta) in (0.0, 1.0)
    g = jax.grad(lambda d: PetcTrigger(jnp.zeros(2), d, 0.2).fires(zl, z))(jnp.full(2, 0.5))
    gap = 0.8 ** 2 + 0.3 ** 2 - 1.0
    s = 1 / (1 + np.exp(-gap / 0.2))
    np.testing.assert_allclose(g, [-s * (1 - s) / 0.2] * 2, rtol=1e-5)


def test_hard_trigger_has_zero_gradient():
    zl, z = jnp.zeros(2), jnp.array([0.8, 0.3])
    g = jax.grad(lambda d: PetcTrigger(jnp.zeros(2), d).fires(zl, z))(jnp.full(2, 0.5))
    np.testing.assert_array_equal(g, 0.0)


def test_hold_last_sent_eq3():
    z, zl = jnp.array([1.0, 2.0]), jnp.array([3.0, 4.0])
    np.testing.assert_array_equal(hold_last_sent(1.0, z, zl), z)
    np.testing.assert_array_equal(hold_last_sent(0.0, z, zl), zl)


def test_negative_threshold_is_rejected():
    with pytest.raises(ValueError, match="PetcTrigger.delta"):
        PetcTrigger(np.zeros(2), np.array([0.1, -0.1]))
