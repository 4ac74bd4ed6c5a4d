"""Path tracking for a differential-drive robot: pure pursuit, wheel-speed PI, prediction.

:class:`PursuitPI` is the local side's control of seed 004 (sections 2.1, 3): at each
sensing instant kNT, from the estimate xi_k,

1. pure pursuit (:func:`jaxnc.controllers.pure_pursuit.pure_pursuit_curvature`, eq. 15-19)
   gives (v_ref, omega_ref), and eq. (20) the wheel-speed references w^com (clipped to
   +-w_max);
2. a PI on the wheel-speed errors w^com - (w_r, w_l) gives the period's ``ns`` actions:
   single rate (a :class:`~jaxnc.design.dualrate.DiscreteSS`, eq. 30-31, its action held
   over the period) or dual rate (a :class:`~jaxnc.design.dualrate.DualRateController`,
   eq. 21-22 and 28-29: G1 at NT, G2 giving ns actions at T);
3. with ``h >= 1``, the h-step-ahead prediction stage (section 3.2, eq. 14,
   :func:`jaxnc.controllers.prediction.predict_periods`): steps 1-2 and the model's lifted
   map (:meth:`~jaxnc.loop.AbstractLiftedPlant.period`) iterated in open loop,
   giving the estimates (xi_{k|k}, ..., xi_{k+h|k}) and the actions of periods k .. k+h
   (packet-based control); the prediction saturates the commands at ``model.u_max`` only
   (the limits of a :class:`~jaxnc.loop.LimitedActuator` are not in it). The local side does not measure the delay (section 1: "the
   time-varying network-induced delay is not required to be measured"): in period k it
   assumes the actuator plays the actions u_{k|k-1} of its previous packet for a fixed
   ``assumed_delay`` seconds, then u_{k|k} (0: the new actions from kNT, the paper's
   prediction).

The packet holds each action over ``sub`` fine steps (the runner's fast period is the
model's dt = T / sub) and is stamped with kN_fast. Once its estimate has reached the end
of the path (progress in the last tenth, within ``end_tol`` of the end point) the
controller sends zeros: the robot stops.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxnc._validate import check_instance, check_int, check_nonneg, check_positive, concrete, scalar_fields
from jaxnc.controllers.prediction import predict_periods
from jaxnc.controllers.pure_pursuit import pure_pursuit_curvature
from jaxnc.design.dualrate import DiscreteSS, DualRateController
from jaxnc.loop.base import AbstractController, Packet
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop.vehicles import DiffDrive, wheel_command
from jaxnc.paths import Path

__all__ = ["PursuitPI", "PursuitState"]


class PursuitState(NamedTuple):
    """The state of a :class:`PursuitPI` controller: the PI, the path progress and the predicted actions."""

    pi: Any             # PI state: float[2, n] (single rate) or a DualRateState
    idx: jax.Array      # int32 path progress
    u_next: jax.Array   # float[ns, 2] the actions predicted for the next period (u_{k+1|k})
    w_com: jax.Array    # float[2] the wheel-speed references of eq. (20)
    est: jax.Array      # float[h+1, 5] the estimates packet (xi_{k|k}, ..., xi_{k+h|k})
    U: jax.Array        # float[ns, 2] this period's actions u_{k|k}
    u_prior: jax.Array  # float[ns, 2] the actions predicted for this period one period earlier (u_{k|k-1})
    stop: jax.Array     # bool: the end was reached; the motors get zero


def _check_pi_period(pi, ns: int, T: float) -> None:
    """The PI's sampling periods (``DiscreteSS.dt``, kept by ``from_tf``; None: not known)
    are those it runs at: a single-rate PI once per sensing period ns T, a dual-rate one's
    G1 at ns T and G2 at T."""
    parts = [("pi", pi, ns * T)] if isinstance(pi, DiscreteSS) else [("pi.G1", pi.G1, ns * T), ("pi.G2", pi.G2, T)]
    for name, g, runs in parts:
        if g.dt is not None and abs(g.dt - runs) > 1e-6 * runs:
            raise ValueError(f"PursuitPI.{name} was discretised at {g.dt:g} s but runs every {runs:g} s "
                             f"(ns={ns} periods T={T:g} s per sensing period): "
                             f"design it at {runs:g} s")


@_dataclass
class PursuitPI(AbstractController):
    """Pure pursuit, wheel-speed PI and the h-step-ahead prediction stage (module docstring).

    Attributes:
      path: the :class:`~jaxnc.paths.Path` to follow.
      model: the :class:`~jaxnc.loop.vehicles.DiffDrive` (eq. 20 and the lifted model).
      pi: a DiscreteSS (single rate, discretised at ns T) or a DualRateController (its N must
        equal ``ns``; G1 at ns T, G2 at T), e.g. ``DiscreteSS.from_tf(single_rate_pi(Kp, Ti, ns * T))``.
      v_ref: m/s; lad: the look-ahead distance, m; w_max: wheel-speed reference limit, rad/s;
        end_tol: m; assumed_delay: s, in [0, ns T].
      ns: static, actuation periods T per sensing period (a Loop's N must be ``ns * model.sub``,
        :attr:`period_steps`); h: static >= 0, periods
        predicted beyond the current one; window: static, the progress search window in path
        points: (window - 1) times the path's spacing must cover v_ref ns T, the arc travelled
        in one sensing period.

    Raises:
      ValueError: a bad type, a non-positive speed or distance, a number that is not a single
        number, ``pi``'s N != ns, a ``pi``
        discretised at another period than it runs at (its ``dt``), an ``assumed_delay``
        outside [0, ns T], a ``window`` too short for the path's spacing at ``v_ref``.
    """

    path: Path
    model: DiffDrive
    pi: Any
    v_ref: Any = 0.14
    lad: Any = 0.12
    w_max: Any = 15.0
    end_tol: Any = 0.03
    assumed_delay: Any = 0.0
    ns: int = _static(1)
    h: int = _static(0)
    window: int = _static(40)

    def __post_init__(self):
        check_instance("PursuitPI.path", self.path, Path, "a jaxnc.paths.Path")
        check_instance("PursuitPI.model", self.model, DiffDrive, "a jaxnc.loop.DiffDrive")
        check_instance("PursuitPI.pi", self.pi, (DiscreteSS, DualRateController),
                       "a DiscreteSS (single rate) or a DualRateController (jaxnc.design.dualrate)")
        for n in ("v_ref", "lad", "w_max", "end_tol"):
            check_positive(f"PursuitPI.{n}", getattr(self, n))
        scalar_fields(self, "v_ref", "lad", "w_max", "end_tol", "assumed_delay")
        check_int("PursuitPI.ns", self.ns, 1, 1000)
        check_int("PursuitPI.h", self.h, 0, 1000)
        check_int("PursuitPI.window", self.window, 1, 100_000)
        if isinstance(self.pi, DualRateController) and self.pi.N != self.ns:
            raise ValueError(f"PursuitPI.pi's N ({self.pi.N}) must equal ns ({self.ns})")
        _check_pi_period(self.pi, self.ns, self.model.T)
        check_nonneg("PursuitPI.assumed_delay", self.assumed_delay)
        try:
            if float(self.assumed_delay) > self.ns * self.model.T:
                raise ValueError(f"PursuitPI.assumed_delay must be in [0, {self.ns * self.model.T:g}] s (one "
                                 f"sensing period), got {float(self.assumed_delay):g}")
        except TypeError:
            pass
        if concrete(self.path.s, self.path.spacing, self.v_ref, self.model.T):
            spacing, run = float(self.path.spacing), float(self.v_ref) * self.ns * self.model.T
            if (self.window - 1) * spacing < run:
                raise ValueError(f"PursuitPI.window ({self.window} path points, {(self.window - 1) * spacing:.4g} m "
                                 f"of progress per sensing period at the path's spacing {spacing:.4g} m) must cover "
                                 f"the arc the robot travels in one sensing period at v_ref ({run:.4g} m = v_ref ns "
                                 f"T), or its progress falls behind the robot: use window >= "
                                 f"{math.ceil(run / spacing) + 1} or a coarser path")

    @property
    def horizon(self) -> int:
        return self.ns * self.model.sub * (self.h + 1)

    @property
    def period_steps(self) -> int:
        """The sensing period NT in fast periods, ``ns * model.sub``: the loop's N
        (:attr:`~jaxnc.loop.AbstractController.period_steps`)."""
        return self.ns * self.model.sub

    def init(self, ctx) -> PursuitState:
        z = jnp.zeros((self.ns, 2), jnp.float32)
        return PursuitState(self.pi.init((2,)), jnp.zeros((), jnp.int32), z, jnp.zeros(2, jnp.float32),
                            jnp.zeros((self.h + 1, 5), jnp.float32), z, z, jnp.zeros((), bool))

    def law(self, pi, idx, x):
        """Steps 1-2 from the state x float[5]: (actions float[ns, 2], w_com float[2], pi, idx)."""
        (v, om), idx = pure_pursuit_curvature(self.path, x[2:4], x[4], idx, lad=self.lad, v_ref=self.v_ref,
                                              window=self.window)
        w_com = jnp.clip(wheel_command(self.model, v, om), -self.w_max, self.w_max)
        e = w_com - x[:2]
        if isinstance(self.pi, DualRateController):
            U, pi = self.pi(pi, e)
        else:
            u, pi = self.pi.step(pi, e)
            U = jnp.broadcast_to(u, (self.ns, 2))
        return U, w_com, pi, idx

    def step(self, state: PursuitState, xhat, fresh, k, ctx):
        est, sub = xhat[:5], self.model.sub
        if self.h == 0:
            U, w_com, pi, idx = self.law(state.pi, state.idx, est)
            states, acts, u_next = est[None], U, state.u_next
        else:
            nf = self.ns * sub
            early = (jnp.arange(nf) < jnp.ceil(self.assumed_delay / self.model.dt - 1e-6))[:, None]
            prev = jnp.repeat(state.u_next, sub, axis=0)

            def law(c, x):          # the fine commands of a period: u_{k|k-1} until the assumed arrival
                pi, idx, first = c
                U, w_com, pi, idx = self.law(pi, idx, x)
                uf = jnp.repeat(U, sub, axis=0)
                return (U, jnp.where(first & early, prev, uf), w_com), (pi, idx, jnp.zeros((), bool))

            model = lambda x, Uw, w: self.model.period(x, Uw[1], w)
            states, (Us, _, w_coms), (pis, idxs, _), _ = predict_periods(
                law, model, est, (state.pi, state.idx, jnp.ones((), bool)), self.h + 1, 5)
            U, w_com, u_next, acts = Us[0], w_coms[0], Us[1], Us.reshape(-1, 2)
            pi, idx = jax.tree.map(lambda a: a[0], (pis, idxs))
        at_end = (idx >= (9 * self.path.M) // 10) & \
            (jnp.sum((est[2:4] - self.path.points[-1]) ** 2) < self.end_tol ** 2)
        stop = state.stop | at_end
        acts = jnp.where(stop, 0.0, acts)
        new = PursuitState(pi, idx, u_next, w_com, states, U, state.u_next, stop)
        return new, Packet(jnp.repeat(acts, sub, axis=0), (k * ctx.N).astype(jnp.int32)), jnp.ones((), jnp.float32)
