"""Tuning by gradient and by Monte-Carlo: thresholds (delta, sigma), horizons, PI gains.

* :mod:`jaxnc.tune.estimators` -- gradients through events (sigmoid relaxation,
  straight-through, score function) and how to pick one;
* :mod:`jaxnc.tune.gradient` -- :func:`tune`, optax on a Monte-Carlo objective with
  reparametrised constraints, temperature annealing and a progress bar;
* :mod:`jaxnc.tune.search` -- grid / random search and successive halving with common
  random numbers, the best point with its interval, and hard-trigger evaluation.

For objectives dominated by rare failures (a PETC loop that can leave its tube), search
first and refine by gradient inside the winner's neighbourhood: ``autotune-mecanum``'s
default, docs/tuning.md.
"""
from jaxnc.tune.estimators import (ESTIMATORS, RelaxedPetcTrigger, annealed_temperature, bernoulli_fires,
                                   relax_trigger, score_grad, score_surrogate, sigmoid_relaxation,
                                   straight_through)
from jaxnc.tune.gradient import Interval, Positive, TuneHistory, TuneResult, Unconstrained, constrain, \
    simulations_per_step, tune, unconstrain
from jaxnc.tune.search import (SearchResult, evaluate, grid, halving_schedule, mean_ci, paired_ci, random_points,
                              search, successive_halving)

__all__ = [
    "ESTIMATORS", "RelaxedPetcTrigger", "annealed_temperature", "bernoulli_fires", "relax_trigger", "score_grad",
    "score_surrogate", "sigmoid_relaxation", "straight_through",
    "Interval", "Positive", "TuneHistory", "TuneResult", "Unconstrained", "constrain", "simulations_per_step", "tune",
    "unconstrain",
    "SearchResult", "evaluate", "grid", "halving_schedule", "mean_ci", "paired_ci", "random_points", "search",
    "successive_halving",
]
