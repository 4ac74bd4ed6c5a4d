"""The thresholds' smoothed estimator: the score function's smoothing bias, measured and
removed by Richardson extrapolation (jaxnc.tune.check, issue 31 item 1), on closed forms."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from jaxnc import montecarlo
from jaxnc.tune import gradient_check, score_grad, simulations_per_step, tune

SIG = 0.5          # the per-seed noise of the cubic


def _cubic(theta, key, temperature):
    """sum_i (theta_i + eps_i)^3, eps ~ N(0, SIG^2) per seed: the gradient of the mean is
    3 theta^2 + 3 SIG^2. Smoothed by N(0, s^2 I) it is 3 theta^2 + 3 SIG^2 + 3 s^2 exactly
    (the third derivative is 6, the higher ones 0), and a central difference of step h
    reads 3 theta^2 + 3 SIG^2 + h^2 exactly: both biases are pure O(s^2), so the
    extrapolations remove them exactly."""
    eps = SIG * jax.random.normal(key, theta.shape)
    return jnp.sum((theta + eps) ** 3)


def _within(mean, se, exact, k=4.0):
    """Every coordinate of ``mean`` within k standard errors of ``exact``."""
    return bool(np.all(np.abs(np.asarray(mean) - np.asarray(exact)) <= k * np.asarray(se)))


def test_richardson_removes_the_score_functions_smoothing_bias_on_a_cubic():
    theta = np.array([0.3, -0.6], np.float32)
    h = 0.2
    s = h / np.sqrt(3.0)
    c = gradient_check(_cubic, theta, montecarlo.seed_keys(0, 16384), fd_step=h, score_scale=s, chunk_size=4096,
                       names=("a", "b"))
    true = 3 * theta ** 2 + 3 * SIG ** 2
    m, se = c.estimates["score"]
    assert _within(m, se, true + 3 * s ** 2), c.table()            # unbiased for the smoothed objective
    m, se = c.estimates["richardson"]
    assert _within(m, se, true), c.table()                          # the extrapolation removes its bias
    b, b_se = c.smoothing_bias["score"]
    assert _within(b, b_se, 3 * s ** 2), c.table()                  # the reported bias is the closed form's
    assert np.all(3 * s ** 2 > 8 * b_se)                             # and resolved (paired on the seed)
    np.testing.assert_allclose(c.smoothing_bias["finite_difference"][0], h ** 2, rtol=2e-3)
    np.testing.assert_allclose(c.references["finite_difference_richardson"][0], true, rtol=1e-2)
    # the choice: the bias is resolved, so the plain score is refused with the bias quoted
    assert c.bias_resolved is True
    assert c.reason["score"].startswith("biased by its smoothing"), c.table()
    assert c.consistent["richardson"], c.table()
    # the exact (pathwise) gradient agrees with the extrapolated differences, not only within rel_tol
    assert c.consistent["straight_through"] and c.recommended == "straight_through", c.table()
    assert "measured smoothing bias of score: a" in c.table()
    only = gradient_check(_cubic, theta, montecarlo.seed_keys(0, 16384), fd_step=h, score_scale=s, chunk_size=4096,
                          estimators=("score", "richardson"))
    assert only.recommended == "richardson", only.table()
    # one seed: value, 2 x 2 x 2 central differences, a pathwise pass, two pairs
    assert c.runs_per_seed == 1 + 8 + 1 + 2 + 2


def _step(sigma):
    """1[theta + sigma xi > 0], xi ~ N(0, 1) per seed: the mean is Phi(theta / sigma)."""
    def objective(theta, key, temperature):
        return (theta[0] + sigma * jax.random.normal(key) > 0).astype(jnp.float32)
    return objective


def _smoothed_slope(theta, sigma, s):
    """d/dtheta E_e Phi((theta + s e) / sigma) = phi(theta / r) / r, r = sqrt(sigma^2 + s^2)."""
    r = np.hypot(sigma, s)
    return norm.pdf(theta / r) / r


def test_smoothing_bias_of_the_derivative_of_a_gaussian_tail_probability():
    """d/dtheta P(theta + eps > 0): the score function at s estimates the slope smoothed by
    N(0, s^2) (closed form), biased for the true slope by O(s^2); its extrapolation from s
    and 2 s has the closed form (4 g(s) - g(2 s)) / 3, within O(s^4) of the true slope, and
    the reported bias is (g(2 s) - g(s)) / 3."""
    sigma, theta, s = 1.0, 0.3, 0.25
    c = gradient_check(_step(sigma), np.full(1, theta, np.float32), montecarlo.seed_keys(1, 2 ** 18),
                       fd_step=s * np.sqrt(3.0), score_scale=s, chunk_size=2 ** 16, estimators=("score", "richardson"))
    true = _smoothed_slope(theta, sigma, 0.0)
    g1, g2 = _smoothed_slope(theta, sigma, s), _smoothed_slope(theta, sigma, 2 * s)
    m, se = c.estimates["score"]
    assert _within(m, se, g1), c.table()
    b, b_se = c.smoothing_bias["score"]
    assert _within(b, b_se, (g2 - g1) / 3), c.table()         # the reported bias is its closed form
    assert abs(g2 - g1) / 3 > 8 * b_se[0]                     # and resolved (paired on the seed)
    assert c.bias_resolved is True and c.recommended == "richardson", c.table()
    m, se = c.estimates["richardson"]
    extrapolated = (4 * g1 - g2) / 3
    assert _within(m, se, extrapolated), c.table()
    assert abs(extrapolated - true) < 0.2 * abs(g1 - true)    # O(s^4): 0.4 % of the slope against 2.7 %
    assert _within(m, se, true), c.table()


def test_the_plain_score_is_kept_where_its_bias_is_not_resolved():
    """A small smoothing scale (s = sigma / 10, bias 0.5 % of the slope) and 4096 seeds: the
    measured bias is within its noise, so the extrapolated estimator (larger variance) is
    refused and the plain score is recommended."""
    sigma, theta, s = 1.0, 0.3, 0.1
    c = gradient_check(_step(sigma), np.full(1, theta, np.float32), montecarlo.seed_keys(2, 4096),
                       fd_step=s * np.sqrt(3.0), score_scale=s, chunk_size=4096, estimators=("score", "richardson"))
    assert c.bias_resolved is False, c.table()
    assert c.reason["richardson"].startswith("not needed"), c.table()
    assert c.estimates["richardson"][1][0] > c.estimates["score"][1][0]
    assert c.recommended == "score", c.table()
    # without richardson nothing is measured and the choice is not made
    c1 = gradient_check(_step(sigma), np.full(1, theta, np.float32), montecarlo.seed_keys(2, 64),
                        fd_step=s * np.sqrt(3.0), score_scale=s, estimators=("score",))
    assert c1.bias_resolved is None and c1.smoothing_bias == {} and c1.references == {}


def test_score_grad_richardson_and_the_tuner():
    """On a deterministic cubic each antithetic pair's estimate is A + s^2 B (A unbiased for
    3 theta^2): the extrapolation removes s^2 B exactly, pair by pair."""
    theta = jnp.array([0.5, -1.0])
    f = lambda t, k: jnp.sum(t ** 3)
    _, g = score_grad(f, theta, jax.random.PRNGKey(0), 200_000, 0.3)
    _, gr = score_grad(f, theta, jax.random.PRNGKey(0), 200_000, 0.3, richardson=True)
    np.testing.assert_allclose(g - gr, 3 * 0.3 ** 2, rtol=0.05)      # the bias 3 s^2 (E e^4 = 3)
    np.testing.assert_allclose(gr, 3 * np.asarray(theta) ** 2, atol=0.03)
    assert simulations_per_step("richardson", 16) == 16 and simulations_per_step("richardson", 2) == 4
    r = tune(lambda p, k, temp: (p["x"] - 2.0) ** 2 + 0.1 * jax.random.normal(k), {"x": 1.0}, steps=60, batch=8,
             estimator="richardson", progress=False, score_scale=0.2)
    assert r.n_simulations == 60 * 8 and abs(float(r.params["x"]) - 2.0) < 0.2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Flat:
    a: float = 1.0


def _flat_run(cfg, key):
    """A gradient of 1e-6 under unit noise per seed: no feasible number of seeds resolves it
    (no pathwise gradient either, so that no estimator is exact on every seed)."""
    a = jax.lax.stop_gradient(cfg.a)
    return 1e-6 * a + a * jax.random.normal(key)


def test_check_loops_default_budget_doubles_from_256_to_32768():
    from jaxnc.tune import Positive, check_loop
    from jaxnc.tune.loop_tune import CHECK_MAX_SEEDS
    c = check_loop(_Flat(), {"a": Positive()}, lambda j: j, run=_flat_run)
    assert CHECK_MAX_SEEDS == 32768 and c.seeds == CHECK_MAX_SEEDS and c.recommended is None, c.table()
    assert c.reason["score"].startswith("inconclusive on a"), c.table()
    assert check_loop(_Flat(), {"a": Positive()}, lambda j: j, run=_flat_run, max_seeds=256).seeds == 256


def _flipped(theta, key, temperature):
    """E[J] = theta_0 + 0.01 theta_1, whose pathwise derivative on theta_1 reads -0.009: the
    sign flipped (a term with its value stopped), 2 % of the largest component in size."""
    e = jax.random.normal(key, (2,))
    wrong = -0.019 * theta[1]
    return (theta[0] * (1.0 + 0.05 * e[0]) + 0.01 * theta[1] * (1.0 + 0.05 * e[1])
            + wrong - jax.lax.stop_gradient(wrong))


def test_a_derivative_of_the_wrong_sign_is_not_agreement_within_rel_tol():
    """The estimator's theta_1 is -0.009 against the finite differences' +0.010, |z| ~ 10^5,
    resolved: it was called consistent and recommended, the difference (0.019) being within
    rel_tol (2 %) of the largest component (1). The margin now passes only differences no
    larger than the gradient on the coordinate (the same sign); theta_0's float32 rounding,
    significant but tiny, still passes."""
    c = gradient_check(_flipped, np.array([1.0, 1.0]), montecarlo.seed_keys(0, 256), estimators=("straight_through",))
    g, fd = c.estimates["straight_through"][0], c.estimates["finite_difference"][0]
    assert g[1] < 0 < fd[1] and abs(g[1] - fd[1]) < 0.02 * abs(fd[0]) and c.resolved["straight_through"].all()
    assert not c.consistent["straight_through"] and c.recommended is None, c.table()
    assert "differs from finite differences" in c.reason["straight_through"]


def _rare(value):
    """theta_0 with a straight-through derivative of ``value`` on the seeds whose uniform
    draw is below 0.02 and 1 elsewhere (at temperature 0, the finite differences' hard
    objective, the derivative is 1 on every seed)."""
    def objective(theta, key, temperature):
        r = jnp.where(jax.random.uniform(key) < 0.02, value, 1.0)
        soft = theta[0] * jnp.where(temperature > 0, r, 1.0)
        return theta[0] + soft - jax.lax.stop_gradient(soft)
    return objective


def _noisy(theta, key, temperature):
    """theta_0 whose straight-through derivative is 1 + 100 N(0, 1) per seed."""
    soft = theta[0] * jnp.where(temperature > 0, 100.0 * jax.random.normal(key), 0.0)
    return theta[0] + soft - jax.lax.stop_gradient(soft)


def test_a_non_finite_or_heavy_tailed_estimate_says_on_how_many_seeds():
    """The reasons the check gives an estimator say how many seeds were non-finite (it said
    only "non-finite values": one NaN seed and all NaN read alike) and whether the per-seed
    differences are too skewed for the normal interval the verdict rests on ("heavy-tailed",
    Cochran's rule; the cart-pole's straight-through gradient, docs/tuning_loops.md); a
    normal, merely noisy estimate is not called heavy-tailed."""
    keys = montecarlo.seed_keys(0, 256)
    hits = int(np.sum(np.asarray(jax.vmap(jax.random.uniform)(keys)) < 0.02))
    assert 1 <= hits <= 12
    c = gradient_check(_rare(jnp.nan), np.array([1.0]), keys, estimators=("straight_through",))
    assert c.reason["straight_through"] == f"non-finite values on {hits} of 256 seeds", c.table()
    c = gradient_check(_rare(1e6), np.array([1.0]), keys, estimators=("straight_through",))
    assert "heavy-tailed on theta[0]: its normal interval needs about" in c.reason["straight_through"], c.table()
    c = gradient_check(_noisy, np.array([1.0]), keys, estimators=("straight_through",))     # normal, not skewed
    assert c.reason["straight_through"].startswith("inconclusive on theta[0]"), c.table()
    assert "heavy-tailed" not in c.reason["straight_through"], c.table()
    assert gradient_check(_noisy, np.array([1.0]), keys, estimators=("straight_through",),
                          max_noise=10.0).reason["straight_through"].startswith("too noisy")   # the rule before 2026-12-05


def _noisy10(theta, key, temperature):
    """theta_0 whose straight-through derivative is 1 + 10 N(0, 1) per seed: unbiased (the finite
    differences read exactly 1 on every seed), its standard error 10 / sqrt(n)."""
    soft = theta[0] * jnp.where(temperature > 0, 10.0 * jax.random.normal(key), 0.0)
    return theta[0] + soft - jax.lax.stop_gradient(soft)


def test_an_unbiased_estimator_noisier_than_the_finite_differences_is_recommended_once_resolved():
    """An unbiased estimator whose standard error is any multiple of the finite differences'
    was refused as "too noisy" (more than 10x, here the finite differences have none) at every
    seed count, so the check never recommended it. Now its agreement is a test once every
    coordinate is resolved: z SE = 1.96 x 10 / sqrt(n) <= 1 from n = 385, so the check starting
    at 256 seeds doubles to 512 and recommends it."""
    more = lambda start, count: montecarlo.seed_keys(0, count, start)
    keys = montecarlo.seed_keys(0, 256)
    one = gradient_check(_noisy10, np.array([1.0]), keys, estimators=("straight_through",))
    assert one.reason["straight_through"].startswith("inconclusive on theta[0]"), one.table()
    c = gradient_check(_noisy10, np.array([1.0]), keys, estimators=("straight_through",), max_seeds=4096,
                       more_keys=more)
    assert c.seeds == 512 and c.recommended == "straight_through", c.table()
    # the seeds that would resolve it: n (z SE)^2 / g^2 with g^2 the squared mean less its noise. With
    # max(|mean|, |fd|) as g, a noisy mean (-3.5 +- 12 for _noisy, whose g is 1) read "about 2759 seeds";
    # the truth is 1.96^2 x 100^2 = 38 416
    noisy = gradient_check(_noisy, np.array([1.0]), keys, estimators=("straight_through",))
    need = float(noisy.seeds_needed["straight_through"][0])
    assert 0.5 * 38416 < need < 2 * 38416, noisy.reason
    assert f"about {int(need)} seeds would resolve it" in noisy.reason["straight_through"]
