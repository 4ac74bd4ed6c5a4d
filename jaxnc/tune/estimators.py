"""Gradients through event triggers: the estimators and how to pick one.

A trigger fires when a gap g(theta) > 0 (seed 000 eq. 4: g = ||zbar - z||^2 -
sum_i (sigma(i) z(i)^2 + delta(i))); beta = 1[g > 0] is a step function, so its exact
derivative is zero almost everywhere and d J / d theta of any closed-loop cost J
built on it carries no information.  jaxnc offers:

=====================  =========================  ===============================  ==================
estimator              forward pass                gradient                         bias / variance
=====================  =========================  ===============================  ==================
``"sigmoid"``          soft: beta = s(g / tau)     exact gradient of the relaxed    biased w.r.t. the
(``Petc(relaxed=      (a fractional "partial       objective J_tau (it *is* the     hard objective by
True)``)               send" blends z into zbar)    objective it optimises): can be  O(tau); no extra
                                                   checked against finite           variance; bias -> 0
                                                   differences                      as tau -> 0, but the
                                                                                    gradient grows stiff
``"straight_through"`` hard: beta = 1[g > 0]        that of s(g / tau) (backward     biased (the forward
(``Petc(temperatu     (the exact simulation)       only)                            and backward passes
re=tau)``)                                                                          disagree), no extra
                                                                                    variance; cheap
``"score"``            hard, thresholds drawn       (J(mu + s e) - J(mu - s e))      unbiased for the
(:func:`score_grad`,   theta = mu + s e,            e / (2 s), antithetic, i.e. the  Gaussian-smoothed
:func:`bernoulli_fi    e ~ N(0, I)                  score function of N(mu, s^2 I)   objective E J(mu+se);
res`)                                               (REINFORCE with a baseline)      variance ~ dim / n;
                                                                                    needs no gradient of
                                                                                    the simulation
``"richardson"``       hard, as ``"score"``,       (4 g(s) - g(2 s)) / 3, g(s) the  smoothing bias
(:func:`score_grad`    each pair also at 2 s        score estimate at scale s:       O(s^4) instead of
``richardson=True``)                               Richardson extrapolation over    O(s^2); variance up
                                                   the smoothing scale              to ~2x the score's;
                                                                                    4 runs a pair; the
                                                                                    check picks it only
                                                                                    where the score's
                                                                                    bias is measured
                                                                                    (:mod:`jaxnc.tune.
                                                                                    check`)
``"hybrid"``           hard; the loss returns      straight-through gradient of     straight-through's
(:func:`jaxnc.tune.    (smooth, jump)              smooth + jump, plus the score    bias on the smooth
tune`)                                             gradient of jump alone           part; the jump part
                                                   (antithetic pairs)               unbiased for its
                                                                                    smoothing, variance
                                                                                    ~ dim / pairs
``"corrected"``        hard                        pathwise gradient with the       unbiased for the hard
(:mod:`jaxnc.tune.                                 decisions held, plus the jump    objective as far as its
jump`)                                             term of the sensor decisions     jumps are the sensor's
                                                   theta moves, one alternative     decisions; needs
                                                   pair per run at the crossing     Gaussian additive
                                                   (smoothed perturbation           measurement noise;
                                                   analysis)                        4 runs a seed
=====================  =========================  ===============================  ==================

How to pick.  Start with ``straight_through``: it simulates the exact hard loop, costs
one backward pass and in practice points the right way for thresholds and gains
(the tuned result is always re-evaluated with hard triggers anyway).  Use ``sigmoid``
when you need a gradient that is *exactly* the derivative of something (finite
difference checks, line searches, second-order methods) and anneal tau towards 0 so
the relaxed objective approaches the hard one.  Use ``score`` when the simulation is
not differentiable (integer leaves, hard selects, a black box) or when the biased
estimators stall on a plateau; it needs many more seeds per step for the same noise,
since its variance grows with the number of tuned parameters.  Its scale s is a
bias-variance trade-off (bias O(s^2), variance O(1 / s) on a step); ``richardson`` removes
the O(s^2) term, and :func:`jaxnc.tune.gradient_check` uses it only where it measures the
plain score's bias (:mod:`jaxnc.tune.check`).  Use ``hybrid`` when the
objective charges a constant for discrete failures (a run that leaves the tube): the
pathwise gradient cannot see how the failure probability moves, the score term can,
and the smooth part keeps its low-variance pathwise gradient.

The score-function pieces also exist per event: :func:`bernoulli_fires` makes the
trigger itself random (fires with probability s(g / tau)) and returns log p(beta) so
that :func:`score_surrogate` turns a cost into a REINFORCE surrogate whose gradient is
unbiased for d E[J] / d theta (the toy test checks this against a closed form).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnc._validate import check_positive
from jaxnc.loop.triggers import Petc, fires_straight_through

__all__ = ["ESTIMATORS", "relax_trigger", "sigmoid_relaxation", "straight_through",
           "annealed_temperature", "bernoulli_fires", "score_surrogate", "score_grad", "score_terms"]

ESTIMATORS = ("straight_through", "sigmoid", "score", "richardson", "hybrid", "corrected")


def sigmoid_relaxation(gap, temperature):
    """Soft trigger s(g / tau): forward *and* backward are the sigmoid (biased, smooth)."""
    return jax.nn.sigmoid(gap / temperature)


straight_through = fires_straight_through
"""Hard trigger 1[g > 0] forward, the gradient of s(g / tau) backward: the triggers' own
:func:`jaxnc.loop.triggers.fires_straight_through` (one definition for the runner and the tuner)."""


def annealed_temperature(step, n_steps: int, t0: float, t1: float):
    """Geometric annealing tau_k = t0 (t1 / t0)^(k / (n - 1)), from t0 at step 0 to t1
    at the last step: early steps see a wide, low-variance relaxation, late steps one
    close to the hard trigger."""
    check_positive("t0", t0)
    check_positive("t1", t1)
    frac = jnp.asarray(step, jnp.float32) / max(n_steps - 1, 1)
    return t0 * (t1 / t0) ** frac


def relax_trigger(trigger, estimator: str, temperature):
    """The :class:`jaxnc.loop.Petc` a loop should use for ``estimator``: ``"sigmoid"``
    the relaxed trigger (soft forward and backward, ``relaxed=True``), ``"straight_through"``
    (and ``"hybrid"``, whose pathwise part is straight-through) the hard trigger with a
    straight-through gradient at ``temperature`` > 0, ``"score"`` (and ``"richardson"``,
    ``"hard"``, ``"corrected"``) the hard trigger (temperature 0). A trigger with no temperature (e.g. ``Periodic``) is
    returned unchanged for ``"score"``/``"hard"``.

    Raises:
      ValueError: an unknown ``estimator``, or ``temperature`` <= 0 for a relaxed one.
    """
    if estimator in ("sigmoid", "straight_through", "hybrid"):
        check_positive("temperature", temperature)
        if not isinstance(trigger, Petc):
            raise ValueError(f"relax_trigger: estimator {estimator!r} needs a jaxnc.loop.Petc trigger, "
                             f"got {type(trigger).__name__}")
        return dataclasses.replace(trigger, temperature=temperature, relaxed=estimator == "sigmoid")
    if estimator in ("score", "richardson", "hard", "corrected"):
        return dataclasses.replace(trigger, temperature=0.0, relaxed=False) if isinstance(trigger, Petc) else trigger
    raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)} or hard, got {estimator!r}")


# ----------------------------------------------------------------------------- score function


def bernoulli_fires(key, gap, temperature):
    """Stochastic trigger: beta ~ Bernoulli(p), p = s(gap / tau).

    Returns (beta as a 0/1 float with no gradient, log p(beta)); sum the log-probabilities
    of a run and pass them to :func:`score_surrogate`."""
    logit = gap / temperature
    beta = jax.random.bernoulli(key, jax.nn.sigmoid(jax.lax.stop_gradient(logit))).astype(jnp.result_type(gap))
    # log p(beta) = beta log s(l) + (1 - beta) log s(-l), stable for large |l|
    logp = beta * jax.nn.log_sigmoid(logit) + (1.0 - beta) * jax.nn.log_sigmoid(-logit)
    return jax.lax.stop_gradient(beta), logp


def score_surrogate(cost, logp, baseline=0.0):
    """REINFORCE surrogate: value ``cost``, gradient

        d cost (pathwise part) + (cost - b) d log p(beta),

    an unbiased estimate of d E[cost] / d theta when the baseline b does not depend on
    this sample (e.g. a running mean, or the mean of the *other* samples)."""
    adv = jax.lax.stop_gradient(cost - baseline)
    return cost + adv * (logp - jax.lax.stop_gradient(logp))


def score_terms(plus, minus, e, scale):
    """The antithetic score function's term of each pair, (J(+) - J(-)) e / (2 s): ``plus``
    and ``minus`` the objective at mean +- s e (float[...]), ``e`` the perturbation
    (float[..., d]); float[..., d]. NumPy arrays in, NumPy out (the tuner's host steps),
    jax arrays in, jax out (:func:`score_grad`, the gradient check)."""
    return ((plus - minus) / (2 * scale))[..., None] * e


def score_grad(fn, mean, key, n_pairs: int, scale, richardson: bool = False):
    """Antithetic Gaussian score-function estimate of d/d mean E_e[fn(mean + scale e, k)].

    ``fn(params, key) -> scalar`` is evaluated with hard triggers (no gradient of the
    simulation is taken); ``mean`` is a flat vector.  For pair i, e_i ~ N(0, I) and the
    same seed k_i (common random numbers) are used for +e_i and -e_i; the estimate is

        g = 1/n sum_i (fn(mean + s e_i, k_i) - fn(mean - s e_i, k_i)) e_i / (2 s),

    i.e. REINFORCE with the antithetic partner as baseline: unbiased for the gradient of
    the smoothed objective, variance O(dim / n).  Returns (mean of all 2n values, g).

    With ``richardson``, each pair is also run at 2 s (the same e_i and k_i) and the
    estimate is (4 g(s) - g(2 s)) / 3: the smoothing bias c s^2 + O(s^4) of g(s) for the
    gradient of E fn(mean, k) becomes O(s^4) (Richardson extrapolation,
    :mod:`jaxnc.tune.check`); 4n simulations, the value the mean of the 2n at scale s.
    """
    ke, kk = jax.random.split(key)
    eps = jax.random.normal(ke, (n_pairs, mean.shape[0]), mean.dtype)
    keys = jax.random.split(kk, n_pairs)

    def at(sc):
        plus = jax.vmap(lambda e, k: fn(mean + sc * e, k))(eps, keys)
        minus = jax.vmap(lambda e, k: fn(mean - sc * e, k))(eps, keys)
        return 0.5 * (jnp.mean(plus) + jnp.mean(minus)), jnp.mean(score_terms(plus, minus, eps, sc), axis=0)
    v, g = at(scale)
    if richardson:
        g = (4.0 * g - at(2.0 * scale)[1]) / 3.0
    return v, g
