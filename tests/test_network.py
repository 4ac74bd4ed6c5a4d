"""Tests for jaxnc.network (seed 000, section 2.3, eq. 5-7).

Statistical checks use fixed seeds (deterministic) and tolerances derived
from the sample size: a proportion p estimated from n draws is compared with
K_SIGMA * sqrt(p (1 - p) / n).
"""
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxnc.network import (
    Arrivals,
    Channel,
    delay_cdf,
    expected_delay,
    late,
    quantise_delay,
    sample_channel,
)

K_SIGMA = 5.0
N_BIG = 200_000
ETA, PHI, T = 0.01, 0.02, 0.1  # paper values (section 4) for eq. 7 and the fast period

sample_jit = jax.jit(sample_channel, static_argnums=2)
cdf_jit = jax.jit(delay_cdf)
quant_jit = jax.jit(quantise_delay)
late_jit = jax.jit(late)


def binom_tol(p: float, n: int) -> float:
    """K_SIGMA standard errors of an empirical proportion."""
    return K_SIGMA * math.sqrt(p * (1.0 - p) / n)


def paper_channel(p_loss=0.0):
    return Channel(p_loss=p_loss, eta=ETA, phi=PHI)


# 1. Loss rate (eq. 5) ---------------------------------------------------------
@pytest.mark.parametrize("p", [0.0, 0.1, 0.5, 0.7])
def test_loss_rate_matches_p(p):
    arr = sample_jit(jax.random.key(1), paper_channel(p), N_BIG)
    assert arr.lost.shape == (N_BIG,) and arr.lost.dtype == jnp.bool_
    assert arr.delay.shape == (N_BIG,) and arr.delay.dtype == jnp.float32
    rate = float(jnp.mean(arr.lost))
    if p == 0.0:
        assert not bool(jnp.any(arr.lost))
    else:
        assert abs(rate - p) <= binom_tol(p, N_BIG), (rate, p)


# 2. Common random numbers -----------------------------------------------------
def test_common_random_numbers():
    key = jax.random.key(2)
    lo = sample_jit(key, paper_channel(0.3), 50_000)
    hi = sample_jit(key, paper_channel(0.6), 50_000)
    assert bool(jnp.all(~lo.lost | hi.lost))  # lost(0.3) => lost(0.6)
    assert int(jnp.sum(hi.lost)) > int(jnp.sum(lo.lost))
    np.testing.assert_array_equal(np.asarray(lo.delay), np.asarray(hi.delay))


# 3. Delay distribution (eq. 7) ------------------------------------------------
def test_delay_distribution_ks_min_mean():
    n = N_BIG
    ch = paper_channel(0.4)
    d = np.asarray(sample_jit(jax.random.key(3), ch, n).delay, dtype=np.float64)

    # KS statistic against the closed-form CDF, asymptotic critical value for alpha = 0.01.
    cdf = lambda x: np.asarray(cdf_jit(ch, np.asarray(x, np.float32)), np.float64)
    res = stats.kstest(d, cdf)
    assert res.statistic < 1.63 / math.sqrt(n), res
    assert res.pvalue > 0.01, res

    assert d.min() >= np.float32(ETA)
    mean_tol = K_SIGMA * PHI / math.sqrt(n)  # sd of the eq. 7 delay is phi
    assert abs(d.mean() - (ETA + PHI)) <= mean_tol
    assert expected_delay(ch) == pytest.approx(ETA + PHI)


def test_delay_cdf_closed_form_and_phi_zero():
    ch = paper_channel()
    tau = np.array([0.0, 0.005, 0.01, 0.03, 0.1, 1.0], np.float32)
    expect = np.where(tau < ETA, 0.0, 1.0 - np.exp(-(tau.astype(np.float64) - ETA) / PHI))
    np.testing.assert_allclose(np.asarray(cdf_jit(ch, tau)), expect, atol=1e-6)

    det = Channel(p_loss=0.0, eta=0.03, phi=0.0)  # deterministic delay eta
    np.testing.assert_array_equal(
        np.asarray(cdf_jit(det, np.array([0.0, 0.029, 0.03, 0.5], np.float32))),
        np.array([0.0, 0.0, 1.0, 1.0], np.float32),
    )
    d = sample_jit(jax.random.key(4), det, 1000).delay
    np.testing.assert_array_equal(np.asarray(d), np.full(1000, 0.03, np.float32))
    # Gradient w.r.t. phi is finite even at phi = 0 (no NaN from the unused branch).
    g = jax.jit(jax.grad(lambda c: delay_cdf(c, 0.05)))(Channel(0.0, 0.03, 0.0))
    assert np.isfinite(float(g.phi)) and np.isfinite(float(g.eta))


# 4. Quantisation to fast periods ---------------------------------------------
@pytest.mark.parametrize(
    "delay, expected",
    [(0.1, 1), (0.1000001, 2), (0.03, 1), (0.0, 0), (0.2, 2), (0.3, 3), (0.35, 4), (1e-9, 1)],
)
def test_quantise_delay_boundaries(delay, expected):
    q = quant_jit(delay, 0.1)
    assert q.dtype == jnp.int32
    assert int(q) == expected


def test_quantise_delay_multiples_of_T_in_float32():
    m = jnp.arange(0, 50, dtype=jnp.int32)
    for t in (0.1, 0.01, 0.05, 0.3):
        d = m.astype(jnp.float32) * jnp.float32(t)  # exactly m*T in float32 arithmetic
        np.testing.assert_array_equal(np.asarray(quant_jit(d, t)), np.asarray(m))


def test_quantised_steps_distribution():
    n = N_BIG
    ch = paper_channel()
    steps = np.asarray(quant_jit(sample_jit(jax.random.key(5), ch, n).delay, T))
    F = lambda tau: 0.0 if tau < ETA else 1.0 - math.exp(-(tau - ETA) / PHI)
    for m in range(0, 5):
        p_m = F(m * T) - (F((m - 1) * T) if m >= 1 else 0.0)
        frac = float(np.mean(steps == m))
        if p_m == 0.0:
            assert frac == 0.0
        else:
            assert abs(frac - p_m) <= binom_tol(p_m, n), (m, frac, p_m)


# 5. Late packets -------------------------------------------------------------
def test_late_fraction():
    n = N_BIG
    ch = paper_channel()
    tau_max = 0.1
    d = sample_jit(jax.random.key(6), ch, n).delay
    is_late = late_jit(d, tau_max)
    assert is_late.dtype == jnp.bool_
    p_late = 1.0 - float(cdf_jit(ch, tau_max))
    assert p_late == pytest.approx(math.exp(-(tau_max - ETA) / PHI), rel=1e-4)
    frac = float(jnp.mean(is_late))
    assert abs(frac - p_late) <= binom_tol(p_late, n), (frac, p_late)
    assert not bool(late_jit(0.1, 0.1)) and bool(late_jit(0.1000001, 0.1))


# 6. vmap over keys is bitwise identical to single calls ----------------------
def test_vmap_over_keys_bitwise():
    keys = jax.random.split(jax.random.key(7), 8)
    ch = paper_channel(0.3)
    batched = jax.jit(jax.vmap(lambda k: sample_channel(k, ch, 257)))(keys)
    assert isinstance(batched, Arrivals)
    assert batched.lost.shape == (8, 257) and batched.delay.shape == (8, 257)
    for i in range(keys.shape[0]):
        single = sample_jit(keys[i], ch, 257)
        np.testing.assert_array_equal(np.asarray(batched.lost[i]), np.asarray(single.lost))
        np.testing.assert_array_equal(np.asarray(batched.delay[i]), np.asarray(single.delay))


def test_raw_uint32_key_accepted():
    arr = sample_jit(jax.random.PRNGKey(0), paper_channel(0.5), 100)
    assert arr.lost.shape == (100,)


# 7. Validation ----------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(p_loss=1.0), "p_loss"),
        (dict(p_loss=-0.1), "p_loss"),
        (dict(p_loss=np.array([0.1, 1.2])), "p_loss"),
        (dict(p_loss=float("nan")), "p_loss"),
        (dict(eta=-1), "eta"),
        (dict(phi=-0.5), "phi"),
        (dict(phi=np.float32(-0.5)), "phi"),
    ],
)
def test_bad_configuration_raises(kwargs, field):
    with pytest.raises(ValueError, match=rf"Channel\.{field} must be in"):
        Channel(**kwargs)


def test_valid_configurations_and_pytree():
    Channel()
    Channel(p_loss=0.0, eta=0.0, phi=0.0)
    Channel(p_loss=np.array([0.0, 0.99]), eta=np.float32(0.01), phi=2)
    leaves, treedef = jax.tree_util.tree_flatten(paper_channel(0.2))
    assert len(leaves) == 3
    assert jax.tree_util.tree_unflatten(treedef, leaves) == paper_channel(0.2)


# 8. vmap over a Channel with batched leaves -----------------------------------
def test_vmap_over_batched_p_loss():
    key = jax.random.key(8)
    n = 1000
    ps = jnp.array([0.1, 0.5], jnp.float32)
    rates = jax.jit(
        jax.vmap(lambda p: sample_channel(key, Channel(p_loss=p, eta=ETA, phi=PHI), n).lost.mean())
    )(ps)
    assert rates.shape == (2,)
    for r, p in zip(np.asarray(rates), (0.1, 0.5)):
        assert abs(r - p) <= binom_tol(p, n), (r, p)
    assert rates[0] < rates[1]


def test_vmap_over_channel_pytree_in_axes():
    key = jax.random.key(9)
    n = 2000
    chans = Channel(p_loss=jnp.array([0.0, 0.2, 0.6]), eta=ETA, phi=PHI)
    f = jax.jit(
        jax.vmap(
            functools.partial(sample_channel, key, n=n),
            in_axes=(Channel.in_axes(p_loss=0),),
        )
    )
    out = f(chans)
    assert out.lost.shape == (3, n)
    # Same key for every channel: delays identical, loss patterns nested (CRN).
    np.testing.assert_array_equal(np.asarray(out.delay[0]), np.asarray(out.delay[2]))
    assert bool(jnp.all(~out.lost[1] | out.lost[2]))
    assert not bool(jnp.any(out.lost[0]))
    # Matches the unbatched call bitwise.
    single = sample_jit(key, Channel(p_loss=0.2, eta=ETA, phi=PHI), n)
    np.testing.assert_array_equal(np.asarray(out.lost[1]), np.asarray(single.lost))


def test_vmap_over_delay_params_and_grad():
    key = jax.random.key(10)
    n = 50_000
    phis = jnp.array([0.01, 0.02, 0.05], jnp.float32)
    means = jax.jit(
        jax.vmap(lambda ph: sample_channel(key, Channel(0.0, ETA, ph), n).delay.mean())
    )(phis)
    for m, ph in zip(np.asarray(means), (0.01, 0.02, 0.05)):
        assert abs(m - (ETA + ph)) <= K_SIGMA * ph / math.sqrt(n)
    # Reparameterised delay: d mean / d phi = mean of Exp(1) ~ 1, d/d eta = 1.
    g = jax.jit(jax.grad(lambda c: sample_channel(key, c, n).delay.mean()))(paper_channel())
    assert float(g.eta) == pytest.approx(1.0, abs=1e-5)
    assert abs(float(g.phi) - 1.0) <= K_SIGMA / math.sqrt(n)
