"""Estimation at the slow (sensing) period over a plant run at the fast period.

A slow sensor (seed 004's camera, period NT) and fast actuation (period T, or a finer
grid) call for a filter that corrects once per slow period and predicts over the whole
period in one step, with the plant's *lifted* model: the state after the period given the
fast actions applied in it,

    xi_{k+1} = F(xi_k, u_{kN}, ..., u_{kN+N-1}) + n1_k,     n1_k ~ N(0, Q)      (seed 004 eq. 8)

(:class:`~jaxnc.loop.AbstractLiftedPlant.period`). :func:`PeriodEKF` builds the EKF of seed
004 eq. (9)-(13) on that model: the :class:`jaxnc.loop.EKF` part with ``rate="slow"``
(:func:`jaxnc.estimators.ekf.ekf_predict` once per slow period, Q the covariance of the
lifted model's additive noise over one slow period, model error included).
"""
from __future__ import annotations

from jaxnc.loop.base import AbstractLiftedPlant
from jaxnc.loop.estimators import EKF

__all__ = ["AbstractLiftedPlant", "PeriodEKF"]


def PeriodEKF(model, Q, R, mean0, cov0, *, buffer: int = 0, inputs: str = "applied") -> EKF:
    """The EKF at the slow period on a lifted model: ``EKF(..., rate="slow")`` (module docstring).

    Args: model (an :class:`~jaxnc.loop.AbstractLiftedPlant`: its ``period`` and ``measure``),
    Q float[n, n] per slow period, R float[p, p], mean0 float[n], cov0 float[n, n]; buffer,
    inputs as the EKF's (default ``"applied"``: a filter collocated with the actuator).

    Raises: ValueError naming the EKF's field (``EKF.model`` not an AbstractLiftedPlant, ...).
    """
    return EKF(model, Q, R, mean0, cov0, buffer=buffer, inputs=inputs, rate="slow")
