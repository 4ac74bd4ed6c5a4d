"""Estimation at the slow (sensing) period over a plant run at the fast period.

A slow sensor (seed 004's camera, period NT) and fast actuation (period T, or a finer
grid) call for a filter that corrects once per slow period and predicts over the whole
period in one step, with the plant's *lifted* model: the state after the period given the
fast actions applied in it,

    xi_{k+1} = F(xi_k, u_{kN}, ..., u_{kN+N-1}) + n1_k,     n1_k ~ N(0, Q)      (seed 004 eq. 8)

(:class:`AbstractLiftedPlant.period`). :class:`PeriodEKF` is the EKF of seed 004
eq. (9)-(13) on that model (:func:`jaxnc.estimators.ekf.ekf_predict` /
:func:`~jaxnc.estimators.ekf.ekf_update`; Jacobians by forward differentiation), with the
newest delivered measurement. Unlike :class:`jaxnc.loop.EKF`, which propagates fast period
by fast period with the plant's ``dynamics`` and a Q per fast period, its Q is the
covariance of the lifted model's additive noise over one slow period (model error
included).
"""
from __future__ import annotations

import abc
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxnc._validate import array_fields, check_choice, check_finite, check_given, check_instance, concrete
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.loop.base import AbstractEstimator, AbstractPlant, Inbox, blend
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["AbstractLiftedPlant", "PeriodEKF", "PeriodEKFState"]


class AbstractLiftedPlant(AbstractPlant):
    """A plant that also declares its slow-period (lifted) model."""

    @abc.abstractmethod
    def period(self, x, us, w):
        """The state float[n] one slow period after x float[n], with the fast actions
        ``us`` float[M, m] applied in order and the additive noise w float[n]."""


class PeriodEKFState(NamedTuple):
    """The state of a :class:`PeriodEKF`: the belief before and after this instant's measurement."""

    prior: Gaussian     # belief at this slow instant before its measurement
    post: Gaussian      # corrected belief (the estimate)


@_dataclass
class PeriodEKF(AbstractEstimator):
    """EKF at the slow period with a lifted model (module docstring).

    Attributes:
      model: an :class:`AbstractLiftedPlant` (its ``period`` and ``measure``).
      Q: float[n, n], covariance of the lifted model's additive noise per slow period.
      R: float[p, p], measurement noise covariance.
      mean0: float[n]; cov0: float[n, n], the prior at t = 0.
      inputs: static, ``"applied"`` (a filter collocated with the actuator: the actions
        it applied) or ``"believed"`` (the controller's own packets as if delivered at once).

    ``correct``: the newest delivered measurement (eq. 9-11); none delivered: the prior.
    ``predict``: the prior of the next slow instant from the period's actions (eq. 12-13).

    Raises:
      ValueError: a model that is not an AbstractLiftedPlant, a non-finite or ill-shaped
        covariance or mean, an unknown ``inputs``.
    """

    model: Any
    Q: Any
    R: Any
    mean0: Any
    cov0: Any
    inputs: str = _static("applied")

    def __post_init__(self):
        check_instance("PeriodEKF.model", self.model, AbstractLiftedPlant,
                       "a plant with a lifted model (a jaxnc.loop.AbstractLiftedPlant, e.g. DiffDrive)")
        for n in ("Q", "R", "mean0", "cov0"):
            check_given(f"PeriodEKF.{n}", getattr(self, n), "a number or an array of numbers")
            check_finite(f"PeriodEKF.{n}", getattr(self, n))
        array_fields(self, "Q", "R", "mean0", "cov0")
        object.__setattr__(self, "inputs", check_choice("PeriodEKF.inputs", self.inputs, ("applied", "believed")))
        if not concrete(self.Q, self.R, self.mean0, self.cov0):
            return
        n, p = self.model.state_dim, self.model.output_dim
        for name, shape in (("mean0", (n,)), ("cov0", (n, n)), ("Q", (n, n)), ("R", (p, p))):
            got = np.shape(getattr(self, name))
            if got != shape:
                raise ValueError(f"PeriodEKF.{name} must have shape {shape} (the model's dimensions), got {got}")
        for name in ("cov0", "Q", "R"):
            M = np.asarray(getattr(self, name), float)
            if not np.allclose(M, M.T, atol=1e-6 * max(1.0, float(np.abs(M).max()))) \
                    or np.linalg.eigvalsh(M).min() < 0:
                raise ValueError(f"PeriodEKF.{name} must be symmetric positive semi-definite")

    def init(self, ctx) -> PeriodEKFState:
        g = Gaussian(jnp.asarray(self.mean0, jnp.float32), jnp.asarray(self.cov0, jnp.float32))
        return PeriodEKFState(g, g)

    def correct(self, state: PeriodEKFState, inbox: Inbox, k):
        z, _, w = inbox.newest()
        post = blend(w, ekf_update(self.model.measure, state.prior, z, self.R, self.model.output_dim), state.prior)
        return state._replace(post=post), post.mean

    def predict(self, state: PeriodEKFState, u_applied, u_believed, k) -> PeriodEKFState:
        us = u_applied if self.inputs == "applied" else u_believed
        prior = ekf_predict(self.model.period, state.post, us, self.Q, self.model.state_dim)
        return state._replace(prior=prior)
