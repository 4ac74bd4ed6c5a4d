"""Tuning by gradient and by Monte-Carlo: thresholds (delta, sigma), horizons, PI gains.

* :mod:`jaxnc.tune.estimators` -- gradients through events (sigmoid relaxation,
  straight-through, score function) and how to pick one;
* :mod:`jaxnc.tune.gradient` -- :func:`tune`, optax on a Monte-Carlo objective with
  reparametrised constraints, temperature annealing and a progress bar;
* :mod:`jaxnc.tune.search` -- grid / random search and successive halving with common
  random numbers, the best point with its interval, and hard-trigger evaluation;
* :mod:`jaxnc.tune.check` -- :func:`gradient_check`: which estimator agrees with finite
  differences on *your* loop, on every coordinate (each resolved, or the report says how
  many seeds it would need; optional doubling of the seeds), and which to use;
* :mod:`jaxnc.tune.jump` -- the corrected pathwise gradient with hard PETC triggers
  (pathwise with the decisions held, plus the jump term of the decisions theta moves);
* :mod:`jaxnc.tune.loop_tune` -- :func:`tune_loop`: tune any :class:`jaxnc.loop.Loop` by
  naming its leaves (search for static integers, gradient for the rest, hard-trigger
  evaluation on fresh seeds); :func:`mc_mean`, a differentiable chunked Monte-Carlo mean.

For objectives dominated by rare failures (a PETC loop that can leave its tube), search
first and refine by gradient inside the winner's neighbourhood: ``autotune-mecanum``'s
default, docs/tuning.md.
"""
from jaxnc.tune.estimators import (ESTIMATORS, annealed_temperature, bernoulli_fires,
                                   relax_trigger, score_grad, score_surrogate, sigmoid_relaxation,
                                   straight_through)
from jaxnc.tune.gradient import Interval, Positive, TuneHistory, TuneResult, Unconstrained, constrain, \
    simulations_per_step, tune, unconstrain
from jaxnc.tune.check import GradientCheck, gradient_check, objective_total
from jaxnc.tune.jump import corrected_grad, corrected_supported
from jaxnc.tune.loop_tune import (LoopTuneResult, check_loop, get_path, has_temperature, mc_mean, param_paths,
                                  point_objective, set_paths, tune_loop, with_temperature)
from jaxnc.tune.search import (SearchResult, evaluate, grid, halving_schedule, mean_ci, paired_ci, random_points,
                              search, successive_halving)

__all__ = [
    "ESTIMATORS", "annealed_temperature", "bernoulli_fires", "relax_trigger", "score_grad",
    "score_surrogate", "sigmoid_relaxation", "straight_through",
    "Interval", "Positive", "TuneHistory", "TuneResult", "Unconstrained", "constrain", "simulations_per_step", "tune",
    "unconstrain",
    "SearchResult", "evaluate", "grid", "halving_schedule", "mean_ci", "paired_ci", "random_points", "search",
    "successive_halving",
    "GradientCheck", "gradient_check", "objective_total", "corrected_grad", "corrected_supported",
    "LoopTuneResult", "get_path", "mc_mean", "point_objective", "set_paths", "tune_loop",
    "check_loop", "with_temperature", "has_temperature", "param_paths",
]
