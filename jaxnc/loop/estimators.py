"""Estimators for a loop: the measurement itself, and an EKF with time-stamped measurements.

:class:`EKF` is the extended Kalman filter of seed 000 eq. (11)-(16) (Jacobians by
forward differentiation of the model; a linear model gives the Kalman filter) with
intermittent observations and a bounded buffer for delayed ones. It keeps the inputs of
the last ``buffer`` slow periods and the prior at the start of that window; at every slow
instant it re-runs the window, correcting at each instant whose measurement has arrived by
now (``Inbox.arrived``) and propagating with the stored inputs, so the estimate is the one
an on-time filter would have had with the same measurements (seed 001 eq. 9-15, the
buffered Kalman filter, extended to a nonlinear model and to N fast periods a slow one). A
measurement older than the window is lost. ``buffer=0`` is the plain intermittent filter:
only a measurement stamped now is used. ``rate="slow"`` predicts once per slow period with
the plant's lifted model instead (:class:`~jaxnc.loop.AbstractLiftedPlant`, seed 004
eq. 8-13; :func:`jaxnc.loop.PeriodEKF`). Seed 000's remote NUDREKF (section 3.3.1) is
``EKF(form="sequential", output="weighted", keep_means=True)``.

:class:`Passthrough` uses the newest delivered measurement as the estimate and holds it
(eq. 5 of seed 001, no model): for controllers that act on the output.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import (array_fields, check_bool, check_finite, check_given, check_instance, check_int,
                             concrete, psd_rounding)
from jaxnc.estimators import ekf_batched as batched
from jaxnc.estimators.ekf import (Gaussian, SqrtGaussian, ekf_predict, ekf_predict_sqrt, ekf_update, ekf_update_diag,
                                  ekf_update_sqrt)
from jaxnc.estimators.sparsity import EKFStructure
from jaxnc.estimators.ukf import ukf_predict, ukf_update
from jaxnc.loop.base import AbstractEstimator, AbstractLiftedPlant, AbstractPlant, Inbox, blend, check_weight
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static

__all__ = ["EKF", "EKFState", "Passthrough", "PassthroughState", "WeightedEstimate", "period_means",
           "period_means_finite"]


class EKFState(NamedTuple):
    """Gaussians, or :class:`~jaxnc.estimators.ekf.SqrtGaussian` with ``EKF(form="sqrt")``."""

    base: Gaussian      # prior at the first instant of the window (k - buffer)
    u: jax.Array        # float[buffer, N, m] inputs of the window's periods
    post: Gaussian      # posterior at the current instant (the estimate)
    next_base: Gaussian  # prior at k - buffer + 1 (becomes base after predict)
    means: Any = None   # float[N, n] with keep_means: the mean after each fast period of the last prediction


class WeightedEstimate(NamedTuple):
    """The estimate of ``EKF(output="weighted")``.

    ``mean`` float[n] is the posterior mean had the measurement of now been used (computed
    whether or not one arrived); ``weight`` the 0/1 float "the measurement of now arrived and
    was used" (with the trigger's gradient). A controller that acts only on a new measurement
    (seed 000's :class:`~jaxnc.loop.ChainController`) blends by it."""

    mean: jax.Array
    weight: jax.Array


def period_means(estimator, state: EKFState):
    """float[N, n]: the means after each fast period of the last prediction of an
    ``EKF(keep_means=True)`` (a :class:`jaxnc.loop.Record` function of the estimator): after
    slow period k, entry j is the predicted mean of the state at fast instant kN + j + 1
    (recorded over a run: [steps / N, N, n], flattened it lags ``Trajectory.x`` by one)."""
    return state.means


def period_means_finite(estimator, state: EKFState):
    """bool: the means of :func:`period_means` are all finite (a cheaper Record function)."""
    return jnp.all(jnp.isfinite(state.means))


def _recomputed_predict(f, g: Gaussian, u, Q, noise_dim: int, jacobian_grad: bool = True,
                        structure=None) -> Gaussian:
    """:func:`~jaxnc.estimators.ekf.ekf_predict` under ``jax.checkpoint`` (nothing saved):
    the same values, and a program without differentiation is unchanged (bit for bit), but
    reverse mode recomputes the prediction from (g, u, Q) instead of storing the
    intermediates of its Jacobian's forward-mode products for every step of the run
    (docs/design_notes.md, "The exact gradient: hard decisions, a recomputed prediction")."""
    # prevent_cse=False: it is always called inside a scan (:meth:`EKF._predict_period`'s),
    # which keeps XLA from merging the recomputation with the forward pass (JAX's advice)
    return jax.checkpoint(lambda g, u, Q: ekf_predict(f, g, u, Q, noise_dim, jacobian_grad=jacobian_grad,
                                                      structure=structure),
                          policy=jax.checkpoint_policies.nothing_saveable, prevent_cse=False)(g, u, Q)


class PassthroughState(NamedTuple):
    z: jax.Array        # float[p] the held measurement
    stamp: jax.Array    # int32: its time stamp (-1 before the first)


@_dataclass
class EKF(AbstractEstimator):
    """EKF with intermittent, time-stamped measurements (module docstring).

    Attributes:
      model: an :class:`~jaxnc.loop.base.AbstractPlant` (its ``dynamics`` and ``measure``).
      Q: float[q, q] or float[q] (diagonal), process noise covariance of the model's w,
        per fast period, added where it enters: every fast period, or every ``noise_period``
        of a model that declares one (t = 0, P, 2P, ... over the run, as the runner draws it)
        (``rate="slow"``: q = n, the lifted model's additive noise per slow period).
      R: float[p, p], measurement noise covariance of v (``form="sequential"``: or float[p],
        the variances of a diagonal one).
      mean0: float[n]; cov0: float[n, n], the prior at t = 0.
      buffer: static int >= 0, slow periods a measurement may be late.
      inputs: static, ``"believed"`` (the actions of the controller's own packets, what a
        remote filter knows) or ``"applied"`` (a filter collocated with the actuator).
      form: static, ``"joseph"`` (the reference: :func:`~jaxnc.estimators.ekf.ekf_update`'s
        Joseph form) or ``"sqrt"`` (the square-root form, a factor S with P = S S' updated
        by QR: :func:`~jaxnc.estimators.ekf.ekf_update_sqrt`; positive semi-definite in
        float32 also with zero process noise and very precise measurements, where the Joseph
        form can lose definiteness; the state's Gaussians are then
        :class:`~jaxnc.estimators.ekf.SqrtGaussian`) or ``"unscented"`` (the unscented
        Kalman filter: :func:`~jaxnc.estimators.ukf.ukf_predict` and
        :func:`~jaxnc.estimators.ukf.ukf_update` with Merwe's sigma points, the same window
        of late measurements; :func:`jaxnc.loop.UKF` builds it) or ``"sequential"`` (the
        Joseph-form prediction, and the correction processed one scalar measurement at a
        time, :func:`~jaxnc.estimators.ekf.ekf_update_diag`: the same posterior in exact
        arithmetic, no factorisation; R must be diagonal, a vector of p variances or a
        diagonal matrix; the form of seed 000's NUDREKF).
      sigma_points: static (alpha, beta, kappa) of the unscented form's sigma points.
      rate: static, ``"fast"`` (predict every fast period with the model's ``dynamics``) or
        ``"slow"`` (once per slow period with its lifted ``period(x, us, w)``: the model must
        be an :class:`~jaxnc.loop.AbstractLiftedPlant`).
      structure: static :class:`~jaxnc.estimators.sparsity.EKFStructure` or None, the
        model's Jacobian sparsity (:func:`~jaxnc.estimators.sparsity.detect_structure`):
        products with structural zeros skipped (``form="sequential"`` only).
      jacobian_grad: static bool; False holds the Jacobians constant under differentiation
        (an approximate, cheaper gradient, as in :func:`~jaxnc.estimators.ekf.ekf_predict`;
        ``form="sequential"`` only).
      weight: static, how the measurement of slow instant k is weighed: ``"slot"`` (the
        default: the weight of the uplink's ring slot k mod C unless the packet there was
        sent and has not arrived yet: with a hard trigger the sent packet's, and at an
        instant where the sensor stays silent a 0 that carries the trigger's gradient,
        straight-through or relaxed; a relaxed trigger's β weighs the correction also where
        β <= 1/2 and nothing is sent, at once, where a sent packet waits for its delay) or
        ``"stamp"`` (the packet stamped kN if it has arrived, else a constant 0: the same
        runs with a hard trigger, but a silent instant's gradient is cut, which gave the
        straight-through d/dδ of a servo the wrong sign, docs/tuning.md). With ``buffer`` D
        the window's instants read their slots too (the Loop sizes the ring to C > D, so
        slot s mod C still holds instant s's packet).
      output: static, ``"mean"`` (the estimate is the posterior mean float[n]) or
        ``"weighted"`` (a :class:`WeightedEstimate`: the mean had the measurement of now been
        used, and its weight; ``buffer=0`` only).
      keep_means: static bool, keep the mean after each fast period of the last prediction
        in the state (``EKFState.means``, for :func:`period_means`; ``rate="fast"``,
        ``buffer=0`` only).
      batch_last: static bool; True runs the correction's covariance arithmetic with the
        seed axis last where the loop is ``vmap``-ped over seeds
        (:func:`jaxnc.estimators.ekf_batched.ekf_update_diag`, its sums unrolled; alone, one
        seed, it runs the unrolled form too): the same filter, its values and gradients equal
        to the default's up to float32 summation order, not bit for bit; faster where the
        correction weighs (benchmarks/RESULTS.md, "Helper lay"); both modes of
        differentiation. ``form="sequential"`` only.
    """

    by_stamp = True

    model: Any
    Q: Any
    R: Any
    mean0: Any
    cov0: Any
    buffer: int = _static(0)
    inputs: str = _static("believed")
    form: str = _static("joseph")
    sigma_points: tuple = _static((1.0, 2.0, 0.0))
    rate: str = _static("fast")
    structure: Any = _static(None)
    jacobian_grad: bool = _static(True)
    weight: str = _static("slot")
    output: str = _static("mean")
    keep_means: bool = _static(False)
    batch_last: bool = _static(False)

    def __post_init__(self):
        check_instance("EKF.model", self.model, AbstractPlant, "a plant (a jaxnc.loop.AbstractPlant: LTI, Discrete, ...)")
        if self.rate not in ("fast", "slow"):
            raise ValueError(f"EKF.rate must be one of fast, slow, got {self.rate!r}")
        if self.rate == "slow":
            check_instance("EKF.model", self.model, AbstractLiftedPlant,
                           "a plant with a lifted model (a jaxnc.loop.AbstractLiftedPlant, e.g. DiffDrive) for rate='slow'")
        for n in ("Q", "R", "mean0", "cov0"):
            check_given(f"EKF.{n}", getattr(self, n), "a number or an array of numbers")
            check_finite(f"EKF.{n}", getattr(self, n))
        array_fields(self, "Q", "R", "mean0", "cov0")
        check_int("EKF.buffer", self.buffer, 0, 10_000)
        if self.inputs not in ("believed", "applied"):
            raise ValueError(f"EKF.inputs must be one of believed, applied, got {self.inputs!r}")
        if self.form not in ("joseph", "sqrt", "unscented", "sequential"):
            raise ValueError(f"EKF.form must be one of joseph, sqrt, unscented, sequential, got {self.form!r}")
        check_weight("EKF", self.weight)
        if self.output not in ("mean", "weighted"):
            raise ValueError(f"EKF.output must be one of mean, weighted, got {self.output!r}")
        check_bool("EKF.jacobian_grad", self.jacobian_grad)
        check_bool("EKF.keep_means", self.keep_means)
        check_bool("EKF.batch_last", self.batch_last)
        if self.structure is not None and not isinstance(self.structure, EKFStructure):
            raise ValueError(f"EKF.structure must be None or an EKFStructure (jaxnc.estimators.sparsity."
                             f"detect_structure), got {type(self.structure).__name__}")
        if (self.structure is not None or not self.jacobian_grad) and self.form != "sequential":
            raise ValueError(f"EKF.structure and EKF.jacobian_grad=False need form='sequential', "
                             f"got form={self.form!r}")
        if self.batch_last and self.form != "sequential":
            raise ValueError(f"EKF.batch_last=True needs form='sequential' (the diagonal update), "
                             f"got form={self.form!r}")
        if self.buffer and (self.output, self.keep_means) != ("mean", False):
            raise ValueError(f"EKF.output='weighted' and keep_means=True need buffer=0 (one measurement per "
                             f"instant), got buffer={self.buffer}")
        if self.keep_means and self.rate != "fast":
            raise ValueError("EKF.keep_means=True needs rate='fast' (the means after each fast period)")
        sp = self.sigma_points
        if not (isinstance(sp, tuple) and len(sp) == 3 and all(isinstance(v, (int, float)) for v in sp)
                and np.all(np.isfinite(sp)) and sp[0] > 0):
            raise ValueError(f"EKF.sigma_points must be (alpha > 0, beta, kappa), three numbers, got {sp!r}")
        n_state = self.model.state_dim
        if self.form == "unscented" and not n_state + sp[2] > 0:
            # n + lambda = alpha^2 (n + kappa): zero divides the weights, negative has no Cholesky factor
            raise ValueError(f"EKF.sigma_points' kappa must be > -n = {-n_state} (n + kappa > 0, n the model's "
                             f"state), got {sp[2]!r}")
        if not concrete(self.Q, self.R, self.mean0, self.cov0):     # the model's sizes are class data
            return
        n, q, p = self.model.state_dim, self.model.noise_dim, self.model.output_dim
        q = n if self.rate == "slow" else q
        m0 = np.asarray(self.mean0, np.float32)
        if m0.shape != (n,):
            raise ValueError(f"EKF.mean0 must have {n} entries (the model's state), got shape {m0.shape}")
        P0 = np.asarray(self.cov0, np.float32)
        if P0.shape != (n, n):
            raise ValueError(f"EKF.cov0 must be {n}x{n}, got shape {P0.shape}")
        Q = np.asarray(self.Q, np.float32)
        if Q.shape not in ((q,), (q, q)):
            what = "the state's, per slow period" if self.rate == "slow" else "the model's noise_dim"
            raise ValueError(f"EKF.Q must be {q}x{q} or a vector of {q} variances ({what}), got shape {Q.shape}")
        R = np.asarray(self.R, np.float32)
        if self.form == "sequential":
            if R.shape == (p,):
                if not R.min() > 0:
                    raise ValueError("EKF.R's variances must be > 0")
                R = np.diag(R)
            elif R.shape == (p, p) and np.any(R != np.diag(np.diag(R))):
                raise ValueError("EKF.R must be diagonal with form='sequential' (a vector of variances or a "
                                 "diagonal matrix)")
        if R.shape != (p, p):
            raise ValueError(f"EKF.R must be {p}x{p} (the model's output_dim)"
                             + (f" or a vector of {p} variances" if self.form == "sequential" else "")
                             + f", got shape {R.shape}")
        for name, M in (("cov0", P0), ("R", R)) + ((("Q", Q),) if Q.ndim == 2 else ()):
            if not np.allclose(M, M.T, atol=1e-6 * max(1.0, float(np.abs(M).max()))):
                raise ValueError(f"EKF.{name} must be symmetric")
            if np.linalg.eigvalsh(M.astype(float)).min() < -psd_rounding(M):
                raise ValueError(f"EKF.{name} must be positive semi-definite")
        if np.linalg.eigvalsh(R.astype(float)).min() <= 0:
            raise ValueError("EKF.R must be positive definite")
        if self.form == "unscented" and np.linalg.eigvalsh(P0.astype(float)).min() <= 0:
            raise ValueError("EKF.cov0 must be positive definite with form='unscented' (the sigma points use its "
                             "Cholesky factor)")
        if Q.ndim == 1 and Q.min() < 0:
            raise ValueError("EKF.Q's variances must be >= 0")
        if self.form == "sequential":
            R = np.diag(R).copy()        # the variances
        for name, M in (("Q", Q), ("R", R), ("mean0", m0), ("cov0", P0)):   # the state's dtype, also under x64
            object.__setattr__(self, name, M)

    @property
    def lookback(self) -> int:
        """The window: a measurement up to ``buffer`` slow periods late is used."""
        return self.buffer

    def init(self, ctx) -> EKFState:
        """The prior at t = 0 and an empty window. Raises ValueError when the model does not
        take the plant's actions or give its measurements, or when the uplink's ring is too
        short for the window (a measurement already used would be dropped when re-run)."""
        mdl = self.model
        if (mdl.input_dim, mdl.output_dim) != (ctx.input_dim, ctx.output_dim):
            raise ValueError(f"EKF.model takes {mdl.input_dim} inputs and gives {mdl.output_dim} outputs, the plant "
                             f"takes {ctx.input_dim} and gives {ctx.output_dim}")
        if ctx.uplink_capacity and ctx.uplink_capacity <= self.buffer:
            raise ValueError(f"EKF.buffer={self.buffer} re-runs {self.buffer} slow periods of measurements, so the "
                             f"uplink's capacity must be >= {self.buffer + 1}, got {ctx.uplink_capacity}")
        g = Gaussian(jnp.asarray(self.mean0, jnp.float32), jnp.asarray(self.cov0, jnp.float32))
        if self.form == "sqrt":
            g = SqrtGaussian.of(g)
        u = jnp.zeros((self.buffer, ctx.N, ctx.input_dim), jnp.float32)
        means = jnp.zeros((ctx.N, g.mean.shape[0]), jnp.float32) if self.keep_means else None
        return EKFState(g, u, g, g, means)

    def _sigma(self):
        return dict(zip(("alpha", "beta", "kappa"), self.sigma_points))

    def _predict_period(self, g: Gaussian, us, s):
        """Propagate over slow period s (actions us [N, m]). At the fast rate the model's w
        enters at the fast instants t = sN + j with t % noise_period == 0 (where the runner
        draws it, :func:`jaxnc.loop.draw`): Q there, none at the others. Returns (the
        Gaussian, the means after each fast period float[N, n] with ``keep_means``, else
        None)."""
        if self.rate == "slow":          # one step of the lifted model over the period's actions us [N, m]
            n = self.model.state_dim
            if self.form == "unscented":
                return ukf_predict(self.model.period, g, us, self.Q, n, **self._sigma()), None
            return (ekf_predict_sqrt if self.form == "sqrt" else ekf_predict)(self.model.period, g, us, self.Q, n), None

        P = int(self.model.noise_period)
        N = us.shape[0]

        def body(g, xs):
            u, Q = xs if P != 1 else (xs, self.Q)
            if self.form == "unscented":
                g = ukf_predict(self.model.dynamics, g, u, Q, self.model.noise_dim, **self._sigma())
            elif self.form == "sqrt":
                g = ekf_predict_sqrt(self.model.dynamics, g, u, Q, self.model.noise_dim)
            else:
                g = _recomputed_predict(self.model.dynamics, g, u, Q, self.model.noise_dim, self.jacobian_grad,
                                        self.structure)
            return g, (g.mean if self.keep_means else None)
        if P == 1:                       # every fast period (the same program as without noise_period)
            return jax.lax.scan(body, g, us)
        Q = jnp.asarray(self.Q)
        enters = ((s * N + jnp.arange(N)) % P == 0).astype(Q.dtype)          # [N]
        return jax.lax.scan(body, g, (us, enters.reshape((N,) + (1,) * Q.ndim) * Q[None]))

    def _correct_at(self, g: Gaussian, inbox: Inbox, s, N):
        """Correct with the measurement of slow instant s (stamp sN), if it has arrived.
        Returns (the posterior, the corrected Gaussian had the measurement been used, its
        weight)."""
        z, w = inbox.measurement(s, s * N, self.weight)
        p = self.model.output_dim
        if self.form == "unscented":
            post = ukf_update(self.model.measure, g, z, self.R, p, **self._sigma())
        elif self.form == "sequential":
            r = jnp.diagonal(self.R) if jnp.ndim(self.R) == 2 else self.R
            update = batched.ekf_update_diag if self.batch_last else ekf_update_diag
            post = update(self.model.measure, g, z, r, p, jacobian_grad=self.jacobian_grad, structure=self.structure)
        else:
            post = (ekf_update_sqrt if self.form == "sqrt" else ekf_update)(self.model.measure, g, z, self.R, p)
        return blend(w, post, g), post, w

    def correct(self, state: EKFState, inbox: Inbox, k) -> tuple[EKFState, jax.Array]:
        """Re-run the window k - D .. k - 1 (D = ``buffer``) from ``state.base``, correcting
        at each instant whose measurement has arrived, then correct at k.

        Returns (the state with the posterior at k and the next window's base, the
        posterior mean float[n], or with ``output="weighted"`` a :class:`WeightedEstimate`).
        The window is a ``lax.scan`` over its D instants, not D unrolled copies
        (docs/design_notes.md, "The buffered EKF's window as a scan")."""
        N = state.u.shape[1]                             # fast periods per slow period
        D = self.buffer

        def instant(carry, xs):
            g, next_base = carry
            i, us = xs
            s = k - D + i
            g1, _ = self._predict_period(self._correct_at(g, inbox, s, N)[0], us, s)
            g = blend((s >= 0).astype(jnp.float32), g1, g)
            next_base = jax.tree.map(lambda a, b: jnp.where(i == 0, a, b), g, next_base)   # prior at k - D + 1
            return (g, next_base), None

        g = next_base = state.base
        if D:
            (g, next_base), _ = jax.lax.scan(instant, (g, next_base), (jnp.arange(D), state.u))
        post, corrected, w = self._correct_at(g, inbox, k, N)
        out = WeightedEstimate(corrected.mean, w) if self.output == "weighted" else post.mean
        return state._replace(post=post, next_base=next_base), out

    def predict(self, state: EKFState, u_applied, u_believed, k) -> EKFState:
        us = u_believed if self.inputs == "believed" else u_applied
        if self.buffer == 0:
            g, means = self._predict_period(state.post, us, k)
            return state._replace(base=g, next_base=g, means=means)
        u = jnp.concatenate([state.u[1:], us[None]], axis=0)
        return state._replace(base=state.next_base, u=u)


@_dataclass
class Passthrough(AbstractEstimator):
    """The newest delivered measurement by time stamp, held (no model). ``z0``: float[p] before
    the first. A measurement older than the one it holds (delivered after it by a link of
    ``order="all"`` or ``"arrival"``) is ignored (receivers without time stamps, which take every
    arrival: :mod:`jaxnc.loop.unstamped`)."""

    field_shapes = {"z0": ((), ("output",))}

    z0: Any = 0.0

    def __post_init__(self):
        check_given("Passthrough.z0", self.z0)
        check_finite("Passthrough.z0", self.z0)

    def init(self, ctx):
        return PassthroughState(jnp.broadcast_to(jnp.asarray(self.z0, jnp.float32), (ctx.output_dim,)),
                                jnp.asarray(-1, jnp.int32))

    def correct(self, state, inbox: Inbox, k):
        z, stamp, w = inbox.newest()
        w = w * (stamp > state.stamp)           # only a newer measurement replaces the held one
        z = blend(w, z, state.z)
        return PassthroughState(z, jnp.where(w > 0.5, stamp, state.stamp).astype(jnp.int32)), z

    def predict(self, state, u_applied, u_believed, k):
        return state
