"""Observers as estimator parts: Luenberger, steady-state Kalman filter, unscented Kalman filter.

Each is an :class:`~jaxnc.loop.base.AbstractEstimator` on the runner's inbox with
intermittent measurements: at slow instant k it corrects with the measurement stamped kN
if that packet has arrived (sent and not lost: its 0/1 ``Inbox.weight``, so a trigger's
straight-through gradient passes), and otherwise only predicts. A measurement that
arrives late (stamped before kN) is not used: these parts have no late-measurement
buffer (the :class:`~jaxnc.loop.EKF` has one).

The two linear observers work on the slow-period system of an :class:`~jaxnc.loop.LTI`
model (x+ = A x + B u + G w, z = C x + v at the fast period T, N fast periods per slow
period h = N T):

    x_{k+1} = A_N x_k + B_N [u_kN; ...; u_kN+N-1] + w_N,   A_N = A^N,
    B_N = [A^{N-1} B, ..., A B, B],   Q_N = sum_{j<N} A^j G Q G' A^j'   (cov of w_N)

A model with constant terms (``LTI(offset=c, z_offset=d)``, e.g. :meth:`~jaxnc.loop.LTI.linearize`
of a nonlinear plant around its operating point) adds c_N = sum_{j<N} A^j c to each
prediction and d to each predicted measurement: the observers then estimate the plant's own
state, not its deviation from the operating point.

* :class:`Luenberger` (predictor form, :func:`jaxnc.estimators.steady_state.luenberger_step`
  on that system): x̂_{k+1} = A_N x̂_k + B_N u + gamma_k L (z_k - C x̂_k), gamma_k = 1
  when z_k arrived; the controller uses x̂_k (from measurements up to k - 1). Without
  noise and with every measurement the error obeys e_{k+1} = (A_N - L C) e_k.
* :class:`SteadyStateKF` (current, filter form): x̂_k = x̂_k^- + gamma_k M (z_k - C x̂_k^-),
  x̂_{k+1}^- = A_N x̂_k + B_N u, with the stationary gain M = P C' (C P C' + R)^-1 and P
  the prior covariance of :func:`~jaxnc.estimators.steady_state.dlqe` (A_N, I, C, Q_N, R),
  computed in :meth:`SteadyStateKF.init` (differentiable in the model, Q and R). With a
  measurement at every instant it is the limit of the time-varying Kalman filter
  (:class:`~jaxnc.loop.EKF` on the same LTI model), and equal to it from the start when
  that filter starts at ``cov0 = P``.
* :func:`UKF`: the unscented Kalman filter of :mod:`jaxnc.estimators.ukf`, built as the
  :class:`~jaxnc.loop.EKF` part with ``form="unscented"`` (so with its window of late
  measurements), on any plant model.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from jaxnc._validate import (array_fields, check_finite, check_given, check_instance, check_int, concrete,
                             fields_concrete, psd_rounding)
from jaxnc.estimators.ekf import Gaussian
from jaxnc.estimators.steady_state import _SCHUR_MARGIN, dlqe, luenberger_step
from jaxnc.loop.base import AbstractEstimator, AbstractPlant, Inbox, blend, check_weight
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop.estimators import EKF
from jaxnc.loop.plants import LTI

__all__ = ["Luenberger", "LuenbergerState", "SteadyStateKF", "SteadyStateKFState", "UKF",
           "slow_system", "stationary_gain"]


def slow_system(A, B, N: int, *, hold: bool = False):
    """(A_N float[n, n], B_N float[n, N m]): x_{k+1} = A_N x_k + B_N [u_0; ...; u_{N-1}]
    over N fast periods (N static, an integer >= 1: ValueError otherwise; N = 0 returned
    A itself). ``hold=True``: (A_N, sum_{j<N} A^j B float[n, m]), the system whose one action
    is held over the N fast periods (a ``HoldLast`` actuator, or any zero-order hold at the
    slow period): what an LQR gain for a ``StateFeedback`` at the slow instants is designed on."""
    check_int("slow_system: N", N, 1)
    A, B = jnp.asarray(A), jnp.asarray(B)
    powers = [jnp.eye(A.shape[0], dtype=A.dtype)]
    for _ in range(N - 1):
        powers.append(A @ powers[-1])
    if hold:
        return A @ powers[-1], sum(P @ B for P in powers)
    return A @ powers[-1], jnp.concatenate([P @ B for P in reversed(powers)], axis=1)


def _slow_noise(A, G, Q, N: int, P: int = 1):
    """(G_N, Q_N) with G_N Q_N G_N' = sum_j A^j G Q G' A^j', the noise of the slow period: G_N
    stacks the columns A^j G of the j whose fast instant N - 1 - j carries noise (every one,
    or every P-th when it enters every P fast periods, a model's ``noise_period``; N a multiple
    of P), Q_N is block-diagonal in Q (float[q, q], or float[q] variances). Kept as a factor
    and the user's Q so that :func:`dlqe` checks Q itself: the product G Q G' of a noise
    input narrower than the state (q < n) is singular and in float32 its smallest eigenvalue
    rounds below 0 (a valid model was refused as "Q must be positive semi-definite")."""
    A, G, Q = jnp.asarray(A), jnp.asarray(G), jnp.asarray(Q)
    Q = jnp.diag(Q) if Q.ndim == 1 else Q
    cols, term = [], G
    for j in range(N):
        if j:
            term = A @ term
        if (N - 1 - j) % P == 0:
            cols.append(term)
    return jnp.concatenate(cols, axis=1), jax.scipy.linalg.block_diag(*([Q] * len(cols)))


def _slow_offset(model, N: int):
    """c_N = sum_{j<N} A^j c float[n], the constant term of the slow-period system of a model
    with ``offset`` c (None for a model without)."""
    if model.offset is None:
        return None
    c = jnp.asarray(model.offset, jnp.float32)
    return slow_system(jnp.asarray(model.A, jnp.float32), c[:, None], N, hold=True)[1][:, 0]   # c held as an input


def _predicted_z(model, x):
    """C x (+ the model's z_offset): the measurement the model predicts from x, noise-free."""
    z = jnp.asarray(model.C, jnp.float32) @ x
    return z if model.z_offset is None else z + jnp.asarray(model.z_offset, jnp.float32)


def _check_linear(owner, obj):
    """The LTI model and ``inputs`` of a linear observer; mean0 None becomes zeros."""
    check_instance(f"{owner}.model", obj.model, LTI, "a linear plant model (a jaxnc.loop.LTI)")
    _check_inputs(owner, obj.inputs)
    if obj.mean0 is None:
        object.__setattr__(obj, "mean0", np.zeros(obj.model.state_dim, np.float32))


def _check_vector(owner, name, v, n):
    check_given(f"{owner}.{name}", v)
    check_finite(f"{owner}.{name}", v)
    if not isinstance(v, jax.Array) and np.shape(v) != (n,):
        raise ValueError(f"{owner}.{name} must have {n} entries (the model's state), got shape {np.shape(v)}")


def _check_inputs(owner, inputs):
    if inputs not in ("believed", "applied"):
        raise ValueError(f"{owner}.inputs must be one of believed, applied, got {inputs!r}")


class LuenbergerState(NamedTuple):
    """x̂_k (float[n]), the measurement used at k (C x̂_k where none arrived, float[p]) and
    t = kN (int32, the stamp of the measurement expected now)."""

    xhat: jax.Array
    z: jax.Array
    t: jax.Array


@_dataclass
class Luenberger(AbstractEstimator):
    """Predictor-form Luenberger observer on the slow-period system (module docstring).

    Attributes:
      model: a :class:`~jaxnc.loop.LTI` (A, B, C used).
      L: float[n, p], the gain of the slow-period system (A_N - L C Schur for convergence;
        for N = 1, of (A, C)).
      mean0: float[n], x̂_0 (default 0).
      inputs: static, ``"believed"`` (the controller's own packets) or ``"applied"``.
      weight: static, ``"slot"`` (the default) or ``"stamp"``: how a measurement is weighed,
        as :class:`~jaxnc.loop.EKF`'s ``weight`` (``"slot"``: the trigger's gradient also
        where the sensor is silent; a relaxed trigger's β everywhere).

    Raises: ValueError naming the field for a model that is not an LTI, a non-finite or
    mis-shaped L or mean0, or an unknown ``inputs`` or ``weight``.
    """

    by_stamp = True

    model: Any
    L: Any
    mean0: Any = None
    inputs: str = _static("believed")
    weight: str = _static("slot")

    def __post_init__(self):
        _check_linear("Luenberger", self)
        check_weight("Luenberger", self.weight)
        n, p = self.model.state_dim, self.model.output_dim
        check_given("Luenberger.L", self.L, "a gain matrix (n x p)")
        check_finite("Luenberger.L", self.L)
        array_fields(self, "L", "mean0")
        _check_vector("Luenberger", "mean0", self.mean0, n)
        if fields_concrete(self):
            if np.shape(self.L) != (n, p):
                raise ValueError(f"Luenberger.L must be {n}x{p} (state x output), got shape {np.shape(self.L)}")
            object.__setattr__(self, "L", np.asarray(self.L, np.float32))     # the state's dtype, also under x64

    def init(self, ctx) -> LuenbergerState:
        """x̂_0. Raises ValueError (when the model and L are concrete, e.g. as a ``Loop`` is
        built) if A_N - L C, the error's matrix with a measurement at every instant, has a
        spectral radius not below 1 - 1e-5 (the margin of :func:`dlqe`): the estimate would not
        converge even with every measurement (a mode within 1e-5 of the unit circle does not
        decay in float32)."""
        if concrete(self.model.A, self.model.C, self.L):
            A_N = np.linalg.matrix_power(np.asarray(self.model.A, float), ctx.N)
            rho = float(np.max(np.abs(np.linalg.eigvals(A_N - np.asarray(self.L, float) @ np.asarray(self.model.C, float)))))
            if not rho < 1.0 - _SCHUR_MARGIN:
                raise ValueError(f"Luenberger.L: A_N - L C of the slow-period system (N={ctx.N}, A_N = A^{ctx.N}) has "
                                 f"spectral radius {rho:.8g}, not below 1 - {_SCHUR_MARGIN:g} (as dlqe), so the "
                                 f"estimate would not converge in float32; design L for "
                                 f"A_N (slow_system(A, B, N)), e.g. A_N M with M from stationary_gain")
        x = jnp.asarray(self.mean0, jnp.float32)
        return LuenbergerState(x, _predicted_z(self.model, x), jnp.zeros((), jnp.int32))

    def correct(self, state: LuenbergerState, inbox: Inbox, k):
        z, gamma = inbox.measurement(k, state.t, self.weight)
        z = blend(gamma, jnp.asarray(z, jnp.float32), _predicted_z(self.model, state.xhat))
        return state._replace(z=z), state.xhat

    def predict(self, state: LuenbergerState, u_applied, u_believed, k) -> LuenbergerState:
        us = u_believed if self.inputs == "believed" else u_applied
        A_N, B_N = slow_system(self.model.A, self.model.B, us.shape[0])
        z = state.z if self.model.z_offset is None else state.z - jnp.asarray(self.model.z_offset, jnp.float32)
        x = luenberger_step(A_N, B_N, jnp.asarray(self.model.C), jnp.asarray(self.L), state.xhat, us.reshape(-1), z)
        c_N = _slow_offset(self.model, us.shape[0])
        return state._replace(xhat=x if c_N is None else x + c_N, t=state.t + us.shape[0])



class SteadyStateKFState(NamedTuple):
    """The prior x̂_k^- (float[n]) before the correction at k, and after it the
    posterior; the stationary gain M (float[n, p]); t = kN (int32)."""

    mean: jax.Array
    gain: jax.Array
    t: jax.Array


def _check_covariances(owner, model, Q, R):
    q, p = model.noise_dim, model.output_dim
    for name, v in (("Q", Q), ("R", R)):
        check_given(f"{owner}.{name}", v, "a covariance matrix (or a vector of variances for Q)")
        check_finite(f"{owner}.{name}", v)
    if isinstance(Q, jax.Array) or isinstance(R, jax.Array):
        return
    Qa, Ra = np.asarray(Q, float), np.asarray(R, float)
    if Qa.shape not in ((q,), (q, q)):
        raise ValueError(f"{owner}.Q must be {q}x{q} or a vector of {q} variances (the model's noise_dim), "
                         f"got shape {Qa.shape}")
    if Ra.shape != (p, p):
        raise ValueError(f"{owner}.R must be {p}x{p} (the model's output_dim), got shape {Ra.shape}")
    if Qa.ndim == 2 and not np.allclose(Qa, Qa.T):
        raise ValueError(f"{owner}.Q must be symmetric (a covariance)")
    if (Qa.ndim == 1 and Qa.min() < 0) or (Qa.ndim == 2 and np.linalg.eigvalsh((Qa + Qa.T) / 2).min() < -psd_rounding(Qa)):
        raise ValueError(f"{owner}.Q must be positive semi-definite")
    if not np.allclose(Ra, Ra.T) or np.linalg.eigvalsh((Ra + Ra.T) / 2).min() <= 0:
        raise ValueError(f"{owner}.R must be symmetric positive definite")


@_dataclass
class SteadyStateKF(AbstractEstimator):
    """Steady-state (stationary-gain) Kalman filter in current form (module docstring).

    Attributes:
      model: a :class:`~jaxnc.loop.LTI` (A, B, C, G used).
      Q: float[q, q] or float[q] (variances), covariance of the model's w per fast period
        (where it enters: every ``noise_period`` fast periods of a model that declares one).
      R: float[p, p], covariance of v.
      mean0: float[n], the prior mean at k = 0 (default 0).
      inputs: static, ``"believed"`` or ``"applied"``.
      weight: static, ``"slot"`` (the default) or ``"stamp"``, as :class:`~jaxnc.loop.EKF`'s.

    Raises: ValueError naming the field for an unknown ``weight``, a loop's N that is not a
    multiple of the model's ``noise_period``, a model that is not an LTI, Q, R of the wrong
    shape, Q not PSD or R not PD, a mis-shaped mean0, or no stabilising Riccati solution
    (from :func:`~jaxnc.estimators.steady_state.dlqe`; checked at N = 1 when built and at
    the loop's N when a ``Loop`` is built, :meth:`init`).
    """

    by_stamp = True

    model: Any
    Q: Any
    R: Any
    mean0: Any = None
    inputs: str = _static("believed")
    weight: str = _static("slot")

    def __post_init__(self):
        _check_linear("SteadyStateKF", self)
        check_weight("SteadyStateKF", self.weight)
        n = self.model.state_dim
        array_fields(self, "Q", "R", "mean0")
        _check_covariances("SteadyStateKF", self.model, self.Q, self.R)
        _check_vector("SteadyStateKF", "mean0", self.mean0, n)
        if fields_concrete(self):
            try:
                stationary_gain(self, int(self.model.noise_period))     # 1 but for a model of coarser noise
            except ValueError as e:
                raise ValueError(f"SteadyStateKF: {e}") from None

    def init(self, ctx) -> SteadyStateKFState:
        """The prior mean0 and the stationary gain at the loop's N. Raises ValueError (when
        its numbers are concrete, e.g. as a ``Loop`` is built) if the slow-period system at
        that N has no stabilising Riccati solution, e.g. (A^N, C) not detectable where (A, C)
        is (an oscillation sampled at a multiple of its half period): the gain would be
        computed from a covariance that does not converge."""
        if ctx.N != 1 and fields_concrete(self):       # N = 1 is checked when built
            with jax.ensure_compile_time_eval():
                try:
                    M, _ = stationary_gain(self, ctx.N)
                except ValueError as e:
                    raise ValueError(f"SteadyStateKF at the loop's N={ctx.N} (the slow-period system A_N = "
                                     f"A^{ctx.N}): {e}") from None
        else:
            M, _ = stationary_gain(self, ctx.N)
        return SteadyStateKFState(jnp.asarray(self.mean0, jnp.float32), M.astype(jnp.float32),
                                  jnp.zeros((), jnp.int32))

    def correct(self, state: SteadyStateKFState, inbox: Inbox, k):
        z, gamma = inbox.measurement(k, state.t, self.weight)
        post = state.mean + gamma * (state.gain @ (jnp.asarray(z, jnp.float32) - _predicted_z(self.model, state.mean)))
        return state._replace(mean=post), post

    def predict(self, state: SteadyStateKFState, u_applied, u_believed, k) -> SteadyStateKFState:
        us = u_believed if self.inputs == "believed" else u_applied
        A_N, B_N = slow_system(self.model.A, self.model.B, us.shape[0])
        mean = A_N @ state.mean + B_N @ us.reshape(-1)
        c_N = _slow_offset(self.model, us.shape[0])
        return state._replace(mean=mean if c_N is None else mean + c_N, t=state.t + us.shape[0])


def stationary_gain(kf: SteadyStateKF, N: int = 1):
    """(M float[n, p], P float[n, n]): the filter gain and the prior covariance of the
    slow-period system with N fast periods per slow period (an integer >= 1, and a multiple
    of the model's ``noise_period``: ValueError naming N otherwise)."""
    check_int("stationary_gain: N", N, 1)
    P = int(kf.model.noise_period)
    if N % P:
        raise ValueError(f"stationary_gain: N={N} is not a multiple of the model's noise_period={P} (its w enters "
                         f"every {P} fast periods, at other instants of each slow period: no stationary gain)")
    A, C, G = jnp.asarray(kf.model.A), jnp.asarray(kf.model.C), jnp.asarray(kf.model.G)
    A_N, _ = slow_system(A, jnp.asarray(kf.model.B), N)
    G_N, Q_N = _slow_noise(A, G, kf.Q, N, P)
    _, P, _ = dlqe(A_N, G_N, C, Q_N.astype(A.dtype), jnp.asarray(kf.R, A.dtype))
    S = C @ P @ C.T + jnp.asarray(kf.R, A.dtype)
    return jnp.linalg.solve(S, C @ P).T, P             # P C' S^-1 (P, S symmetric)



def UKF(model, Q, R, mean0, cov0, alpha=1.0, beta=2.0, kappa=0.0, *, buffer: int = 0,
        inputs: str = "believed") -> EKF:
    """The unscented Kalman filter with intermittent, time-stamped measurements: the
    :class:`~jaxnc.loop.EKF` part with ``form="unscented"`` (Merwe's sigma points,
    :func:`~jaxnc.estimators.ukf.ukf_predict` every fast period and
    :func:`~jaxnc.estimators.ukf.ukf_update` at the slow instants), so it has the EKF's window
    of ``buffer`` slow periods of late measurements too.

    Args: model (an :class:`~jaxnc.loop.base.AbstractPlant`), Q float[q, q] or float[q], R
    float[p, p], mean0 float[n], cov0 float[n, n] (positive definite: the sigma points use
    its Cholesky factor); alpha > 0, beta, kappa > -n (static numbers); buffer, inputs as the EKF's.

    Raises: ValueError naming the field (``UKF.cov0`` not positive definite, ``UKF.inputs``,
    ``UKF.alpha`` <= 0, ``UKF.kappa`` <= -n, and the EKF's own checks).
    """
    _check_inputs("UKF", inputs)
    for n, v in (("alpha", alpha), ("beta", beta), ("kappa", kappa)):
        check_given(f"UKF.{n}", v)
        check_finite(f"UKF.{n}", v)
        if np.ndim(v) != 0:
            raise ValueError(f"UKF.{n} must be a single number, got shape {np.shape(v)}")
    if float(alpha) <= 0:
        raise ValueError(f"UKF.alpha must be > 0, got {float(alpha):g}")
    if not model.state_dim + float(kappa) > 0:
        raise ValueError(f"UKF.kappa must be > -n = {-model.state_dim} (n + kappa > 0, n the model's state: the "
                         f"sigma points' spread alpha^2 (n + kappa)), got {float(kappa):g}")
    check_given("UKF.cov0", cov0)
    check_finite("UKF.cov0", cov0)
    if not isinstance(cov0, jax.Array):
        P0 = np.asarray(cov0, float)
        n = model.state_dim
        if P0.shape != (n, n):
            raise ValueError(f"UKF.cov0 must be {n}x{n}, got shape {P0.shape}")
        if not np.allclose(P0, P0.T) or np.linalg.eigvalsh((P0 + P0.T) / 2).min() <= 0:
            raise ValueError("UKF.cov0 must be symmetric positive definite")
    return EKF(model, Q, R, mean0, cov0, buffer=buffer, inputs=inputs, form="unscented",
               sigma_points=(float(alpha), float(beta), float(kappa)))
