"""Loss and delay models of a link (seed 000, section 2.3, eq. 5-7): Bernoulli loss and the
shifted-exponential delay (:mod:`jaxnc.loop.links`), and the kernels of :mod:`jaxnc.network`
(quantisation to fast periods, late packets).

Statistical checks use fixed seeds (deterministic) and tolerances derived from the sample
size: a proportion p estimated from n draws is compared with K_SIGMA * sqrt(p (1 - p) / n).
The reference CDF of eq. 7 is written here in numpy (independent of the package).
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxnc.loop import Bernoulli, GilbertElliott, Link, ShiftedExponential, TraceDelay, draw_link
from jaxnc.network import late, quantise_delay

K_SIGMA = 5.0
N_BIG = 200_000
ETA, PHI, T = 0.01, 0.02, 0.1  # paper values (section 4) for eq. 7 and the fast period

quant_jit = jax.jit(quantise_delay)
late_jit = jax.jit(late)


@jax.jit
def _lost(key, p, n_like):
    return Bernoulli(p).sample(key, n_like.shape[0])


def lost(key, p, n):
    return _lost(key, jnp.float32(p), jnp.zeros(n))


@jax.jit
def _delay(key, eta, phi, n_like):
    return ShiftedExponential(eta, phi).sample(key, n_like.shape[0], T)


def delay(key, eta, phi, n):
    """(steps int32[n], seconds float32[n])."""
    return _delay(key, jnp.float32(eta), jnp.float32(phi), jnp.zeros(n))


def cdf(tau, eta=ETA, phi=PHI):
    """Eq. 7's CDF in float64: 0 below eta, 1 - exp(-(tau - eta) / phi) above."""
    tau = np.asarray(tau, np.float64)
    if phi == 0:
        return (tau >= eta).astype(float)
    return np.where(tau < eta, 0.0, 1.0 - np.exp(-(tau - eta) / phi))


def binom_tol(p: float, n: int) -> float:
    """K_SIGMA standard errors of an empirical proportion."""
    return K_SIGMA * math.sqrt(p * (1.0 - p) / n)


# 1. Loss rate (eq. 5) ---------------------------------------------------------
@pytest.mark.parametrize("p", [0.0, 0.1, 0.5, 0.7])
def test_loss_rate_matches_p(p):
    x = lost(jax.random.key(1), p, N_BIG)
    assert x.shape == (N_BIG,) and x.dtype == jnp.bool_
    rate = float(jnp.mean(x))
    if p == 0.0:
        assert not bool(jnp.any(x))
    else:
        assert abs(rate - p) <= binom_tol(p, N_BIG), (rate, p)


# 2. Common random numbers -----------------------------------------------------
def test_losses_at_a_lower_p_are_a_subset():
    key = jax.random.key(2)
    lo, hi = lost(key, 0.3, 50_000), lost(key, 0.6, 50_000)
    assert bool(jnp.all(~lo | hi))  # lost(0.3) => lost(0.6)
    assert int(jnp.sum(hi)) > int(jnp.sum(lo))


# 3. Delay distribution (eq. 7) ------------------------------------------------
def test_delay_distribution_ks_min_mean():
    n = N_BIG
    steps, d = delay(jax.random.key(3), ETA, PHI, n)
    d = np.asarray(d, np.float64)
    res = stats.kstest(d, cdf)      # asymptotic critical value for alpha = 0.01
    assert res.statistic < 1.63 / math.sqrt(n), res
    assert res.pvalue > 0.01, res
    assert d.min() >= np.float32(ETA)
    assert abs(d.mean() - (ETA + PHI)) <= K_SIGMA * PHI / math.sqrt(n)  # sd of the eq. 7 delay is phi
    np.testing.assert_array_equal(np.asarray(steps), np.asarray(quantise_delay(d.astype(np.float32), T)))


def test_deterministic_delay_and_bounds():
    steps, d = delay(jax.random.key(4), 0.03, 0.0, 1000)
    np.testing.assert_array_equal(np.asarray(d), np.full(1000, 0.03, np.float32))
    np.testing.assert_array_equal(np.asarray(steps), np.ones(1000, np.int32))
    assert ShiftedExponential(0.03, 0.0).bounds(T) == (1, None)      # at least ceil(eta / T) periods, unbounded


# 4. Quantisation to fast periods ---------------------------------------------
@pytest.mark.parametrize(
    "tau, expected",
    [(0.1, 1), (0.1000001, 2), (0.03, 1), (0.0, 0), (0.2, 2), (0.3, 3), (0.35, 4), (1e-9, 1)],
)
def test_quantise_delay_boundaries(tau, expected):
    q = quant_jit(tau, 0.1)
    assert q.dtype == jnp.int32
    assert int(q) == expected


def test_quantise_delay_multiples_of_T_in_float32():
    m = jnp.arange(0, 50, dtype=jnp.int32)
    for t in (0.1, 0.01, 0.05, 0.3):
        d = m.astype(jnp.float32) * jnp.float32(t)  # exactly m*T in float32 arithmetic
        np.testing.assert_array_equal(np.asarray(quant_jit(d, t)), np.asarray(m))


def test_quantised_steps_distribution():
    n = N_BIG
    steps = np.asarray(delay(jax.random.key(5), ETA, PHI, n)[0])
    for m in range(0, 5):
        p_m = float(cdf(m * T) - (cdf((m - 1) * T) if m >= 1 else 0.0))
        frac = float(np.mean(steps == m))
        if p_m == 0.0:
            assert frac == 0.0
        else:
            assert abs(frac - p_m) <= binom_tol(p_m, n), (m, frac, p_m)


# 5. Late packets -------------------------------------------------------------
def test_late_fraction():
    n = N_BIG
    tau_max = 0.1
    d = delay(jax.random.key(6), ETA, PHI, n)[1]
    is_late = late_jit(d, tau_max)
    assert is_late.dtype == jnp.bool_
    p_late = math.exp(-(tau_max - ETA) / PHI)
    frac = float(jnp.mean(is_late))
    assert abs(frac - p_late) <= binom_tol(p_late, n), (frac, p_late)
    assert not bool(late_jit(0.1, 0.1)) and bool(late_jit(0.1000001, 0.1))


# 6. vmap over keys is bitwise identical to single calls ----------------------
def test_vmap_over_keys_bitwise():
    keys = jax.random.split(jax.random.key(7), 8)
    batched = jax.jit(jax.vmap(lambda k: (Bernoulli(0.3).sample(k, 257),
                                          ShiftedExponential(ETA, PHI).sample(k, 257, T)[1])))(keys)
    assert batched[0].shape == (8, 257) and batched[1].shape == (8, 257)
    for i in range(keys.shape[0]):
        np.testing.assert_array_equal(np.asarray(batched[0][i]), np.asarray(lost(keys[i], 0.3, 257)))
        np.testing.assert_array_equal(np.asarray(batched[1][i]), np.asarray(delay(keys[i], ETA, PHI, 257)[1]))


def test_raw_uint32_key_accepted():
    assert lost(jax.random.PRNGKey(0), 0.5, 100).shape == (100,)


# 7. Validation ----------------------------------------------------------------
@pytest.mark.parametrize(
    "build, field",
    [
        (lambda: Bernoulli(1.0), "Bernoulli.p"),
        (lambda: Bernoulli(-0.1), "Bernoulli.p"),
        (lambda: Bernoulli(float("nan")), "Bernoulli.p"),
        (lambda: ShiftedExponential(eta=-1), "ShiftedExponential.eta"),
        (lambda: ShiftedExponential(phi=-0.5), "ShiftedExponential.phi"),
        (lambda: ShiftedExponential(phi=np.float32(-0.5)), "ShiftedExponential.phi"),
    ],
)
def test_bad_configuration_raises(build, field):
    with pytest.raises(ValueError, match=rf"{field}"):
        build()


def test_pytree_round_trip():
    leaves, treedef = jax.tree_util.tree_flatten(ShiftedExponential(ETA, PHI))
    assert len(leaves) == 2
    assert jax.tree_util.tree_unflatten(treedef, leaves) == ShiftedExponential(ETA, PHI)


# 8. vmap over the models' parameters, gradient of the delay --------------------
def test_vmap_over_batched_p():
    key, n = jax.random.key(8), 1000
    rates = jax.jit(jax.vmap(lambda p: Bernoulli(p).sample(key, n).mean()))(jnp.array([0.1, 0.5], jnp.float32))
    for r, p in zip(np.asarray(rates), (0.1, 0.5)):
        assert abs(r - p) <= binom_tol(p, n), (r, p)
    assert rates[0] < rates[1]


def test_vmap_over_delay_params_and_grad():
    key, n = jax.random.key(10), 50_000
    phis = jnp.array([0.01, 0.02, 0.05], jnp.float32)
    means = jax.jit(jax.vmap(lambda ph: ShiftedExponential(ETA, ph).sample(key, n, T)[1].mean()))(phis)
    for m, ph in zip(np.asarray(means), (0.01, 0.02, 0.05)):
        assert abs(m - (ETA + ph)) <= K_SIGMA * ph / math.sqrt(n)
    # reparameterised delay: d mean / d phi = mean of Exp(1) ~ 1, d/d eta = 1
    g = jax.jit(jax.grad(lambda c: c.sample(key, n, T)[1].mean()))(ShiftedExponential(ETA, PHI))
    assert float(g.eta) == pytest.approx(1.0, abs=1e-5)
    assert abs(float(g.phi) - 1.0) <= K_SIGMA / math.sqrt(n)


# 3. Links: Gilbert-Elliott bursts, delivered fraction under tau_max, ordering rules ------------


def test_gilbert_elliott_loss_rate_and_mean_burst_and_gap_lengths():
    """Classical Gilbert-Elliott (loss_good 0, loss_bad 1): a packet is lost iff the chain is bad,
    so the loss rate is pi_b = p_gb / (p_gb + p_bg), bursts are geometric with mean 1 / p_bg and
    gaps with mean 1 / p_gb (independent closed forms; tolerances K_SIGMA standard errors of the
    per-sequence rates and of the run lengths). Measured (200 x 4000 packets): loss 0.167, burst 10.1, gap 49.4."""
    p_gb, p_bg = 0.02, 0.1
    ge = GilbertElliott(p_gb=p_gb, p_bg=p_bg, loss_good=0.0, loss_bad=1.0)
    lost = np.asarray(jax.jit(jax.vmap(lambda k: ge.sample(k, 4000)))(jax.random.split(jax.random.PRNGKey(0), 200)))
    per = lost.mean(1)
    assert abs(per.mean() - p_gb / (p_gb + p_bg)) < K_SIGMA * per.std(ddof=1) / math.sqrt(per.size)
    assert abs(per.mean() - float(ge.stationary_loss())) < K_SIGMA * per.std(ddof=1) / math.sqrt(per.size)
    for value, mean in ((1, 1 / p_bg), (0, 1 / p_gb)):
        edges = np.diff(np.pad((lost == value).astype(np.int8), ((0, 0), (1, 1))), axis=1)
        runs = []
        for row in edges:
            s, e = np.flatnonzero(row == 1), np.flatnonzero(row == -1)
            keep = (s > 0) & (e < lost.shape[1])                    # runs cut by the ends are biased short
            runs.append((e - s)[keep])
        runs = np.concatenate(runs)
        assert runs.size > 2000
        assert abs(runs.mean() - mean) < K_SIGMA * runs.std(ddof=1) / math.sqrt(runs.size), (value, runs.mean())


def test_link_delivered_fraction_and_delay_histogram_under_tau_max():
    """Bernoulli(p) x (eta + phi Exp(1)) with tau_max: a packet is delivered with probability
    (1 - p) F(tau_max), F the shifted exponential's CDF, and its delay is m fast periods with
    probability (1 - p) (F(min(m T, tau_max)) - F((m - 1) T)) (quantised up); chi-square of the
    counts, delivered and lost, against those closed forms (measured p-value 0.28 at 400 000)."""
    T, eta, phi, tmax, p = 0.01, 0.004, 0.02, 0.035, 0.2
    link = Link(Bernoulli(p), ShiftedExponential(eta, phi), tau_max=tmax)
    n = 200_000
    d = np.asarray(jax.jit(lambda k: draw_link(link, k, n, T).delay)(jax.random.PRNGKey(3)))
    F = lambda x: cdf(x, eta, phi)
    assert abs(np.mean(d >= 0) - (1 - p) * F(tmax)) < binom_tol((1 - p) * F(tmax), n)
    assert d.max() == 4 and d[d >= 0].min() == 1                        # ceil(0.035 / 0.01), ceil(0.004 / 0.01)
    pm = np.array([(1 - p) * (F(min(m * T, tmax)) - F((m - 1) * T)) for m in range(1, 5)])
    counts = np.array([np.sum(d == m) for m in range(1, 5)] + [np.sum(d < 0)])
    assert stats.chisquare(counts, np.append(pm, 1 - pm.sum()) * n).pvalue > 1e-3


def _delivered_by_the_rules(order, delays, N, look):
    """(instant, stamp) of every packet a receiver looking at fast instants ``look`` gets, by the
    Link docstring's rules, written directly: packet k is sent at k N, arrives at k N + delays[k]."""
    arrive = {k: k * N + int(dk) for k, dk in enumerate(delays) if dk >= 0}
    done, last, out = set(), -(2**30), []
    for t in look:
        now = sorted(k for k, a in arrive.items() if a <= t and k not in done and k * N <= t)
        done |= set(now)
        if not now:
            continue
        if order == "all":
            out += [(t, k) for k in now]
        elif order == "arrival" or now[-1] > last:             # "newest" drops what is older than delivered
            out.append((t, now[-1]))
        last = max(last, now[-1])
    return sorted(out)


@pytest.mark.parametrize("order", ["newest", "all", "arrival"])
def test_link_orders_on_overtaking_packets_follow_the_rules(order):
    """Random delays of 0-12 fast periods (N = 3: packets overtake one another) with 15 % lost,
    replayed by TraceDelay: what the ring delivers, read at every fast instant (a downlink) and at
    slow instants only (an uplink), equals the rules of the Link docstring written directly."""
    N, S, C = 3, 120, 6
    rng = np.random.default_rng(0)
    delays = rng.integers(0, 13, S)
    delays[rng.random(S) < 0.15] = -1
    link = Link(delay=TraceDelay(delays), order=order, capacity=C)
    drawn = draw_link(link, jax.random.PRNGKey(0), S, 0.1).delay
    np.testing.assert_array_equal(np.asarray(drawn), delays)            # the trace replayed exactly
    for every_fast in (True, False):
        offsets = jnp.arange(N if every_fast else 1)

        def slow(st, k):
            st = link.send(st, jnp.zeros(1), k, k, 1.0, drawn[k], k * N)

            def look(st, j):
                box, st = link.inbox(st, k * N + j)
                return st, (box.new, box.stamp)
            return jax.lax.scan(look, st, offsets)

        _, (new, stamp) = jax.jit(lambda: jax.lax.scan(slow, link.init(jnp.zeros(1)), jnp.arange(S)))()
        new, stamp = np.asarray(new).reshape(-1, C), np.asarray(stamp).reshape(-1, C)
        look = range(S * N) if every_fast else range(0, S * N, N)
        got = sorted((t, int(stamp[i, c])) for i, t in enumerate(look) for c in np.flatnonzero(new[i] > 0))
        assert got == _delivered_by_the_rules(order, delays, N, look), every_fast
