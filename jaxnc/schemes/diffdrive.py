"""Seed 004 (Cuenca et al., Sensors 2019), scenarios a-e of section 5.2, as loops of library parts.

The robot (:class:`jaxnc.loop.DiffDrive`, at the fine period dt = T/sub) follows a path of
four right angles by pure pursuit (eq. 15-20) with wheel-speed PI (:class:`jaxnc.loop.PursuitPI`):

* **a** single rate at T = 0.1 s (eq. 30): sensing, pure pursuit and PI every T;
* **b** single rate at NT = 0.2 s (eq. 31): everything every NT, the action held;
* **c** dual rate (eq. 21-22, 28-29): sensing and pure pursuit every NT, N actions at T;
* **d** c with remote -> local delays; the local side starts the period's actions when
  the reference packet arrives (:class:`jaxnc.loop.ArrivalActuator`);
* **e** c with delays, the EKF at NT (eq. 8-13, :func:`jaxnc.loop.PeriodEKF`, collocated
  with the actuator), the h-step-ahead prediction stage (eq. 14) and packet-based control
  by time stamp (u_{k|k-1} until the new packet arrives), low noise F = 0.1.

The downlink's delay (d, e) is the reference packet's, eta + phi Exp(1) truncated at
tau_max = 0.17 s < NT (eq. 7 of seed 000; section 5.1), quantised up to dt; the noises are
the plant's, every draw the runner's own (:func:`jaxnc.loop.draw`). Completion (the true
position in the last tenth of the path and within ``END_TOL`` of its end) and failure
(farther than ``MAX_DEV`` from the path before completion) are the runner's, checked every T
by :class:`jaxnc.loop.PathMonitor`; the metrics (eq. 23-25) are computed on its trajectory.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc._validate import check_choice, check_int, check_range
from jaxnc.design.dualrate import DiscreteSS, DualRateController, dualrate_design, pi_controller, single_rate_pi
from jaxnc.loop.vehicles import LIFTED_MODELS
from jaxnc.metrics import distance_to_path, distance_to_points
from jaxnc.paths import Path, from_waypoints, point_at

SCENARIOS = ("a", "b", "c", "d", "e")
PREDICTIONS = LIFTED_MODELS        # e's slow-period model: "integrated" or "eq1" (eq. 1 as printed)
KP, TI = 6.0, 0.12                 # section 5.1
TAU_MAX = 0.17                     # s, section 5.1
DELAY_ETA, DELAY_PHI = 0.08, 0.04  # s, the delay law (ours; the paper gives only tau_max)
V_REF = 0.14                       # m/s (ours: 3 m in ~22 s, the paper's J3)
LAD = 0.12                         # m, look-ahead distance (ours)
SUB = 10                           # fine steps per T
END_TOL, MAX_DEV = 0.03, 0.3       # m: complete within END_TOL of the end; unstable beyond MAX_DEV of the path
#: four right angles, 0.6 m legs (ours: Figs. 5-9 show the shape without dimensions)
STAIRS = ((0.0, 0.0), (0.6, 0.0), (0.6, 0.6), (1.2, 0.6), (1.2, 1.2), (1.8, 1.2))


def four_right_angles(ds: float = 0.005) -> Path:
    return from_waypoints(np.asarray(STAIRS), "four_right_angles", ds)


def diffdrive_loop(scenario: str = "e", *, N: int = 2, h: int = 1, F: float | None = None, Kp: float = KP,
                   Ti: float = TI, T: float = 0.1, tau_max: float = TAU_MAX, eta: float = DELAY_ETA,
                   phi: float = DELAY_PHI, v_ref: float = V_REF, lad: float = LAD, path: Path | None = None,
                   horizon_s: float | None = None, prediction: str = "integrated",
                   assumed_delay: float = 0.0) -> nc.Loop:
    """Scenario ``scenario`` as a :class:`jaxnc.loop.Loop` at the fast period T/10, paper defaults (section 5.1).

    Args:
      scenario: one of a-e. N: the multiplicity (sensing at NT). h: e's prediction horizon.
      F: the noise factor (None: 0 for a-d, which the paper runs noise-free, 0.1 for e).
      Kp, Ti: the PI (eq. 27); single rate at T (a) or NT (b), dual rate designed at T, N (c-e).
      T: the actuation period, s. tau_max, eta, phi: the delay law, s (d, e).
      v_ref, lad: pure pursuit's speed (m/s) and look-ahead (m). path: default the four right angles.
      horizon_s: simulated time (None: 1.5 times the path at v_ref, plus 5 s), rounded up to NT.
      prediction: e's slow-period model for the EKF and the prediction stage (:data:`PREDICTIONS`).
      assumed_delay: e's prediction stage assumes u_{k|k-1} plays this long each period (s, in [0, NT]).

    Returns:
      the Loop; its record keeps x and u (fast rows) and the controller's
      :func:`controller_trace` (slow rows).

    Raises:
      ValueError: naming the argument, for a value outside its range (tau_max must be < NT).
    """
    scenario = check_choice("scenario", scenario, SCENARIOS)
    prediction = check_choice("prediction", prediction, PREDICTIONS)
    check_int("N", N, 1, 50)
    check_int("h", h, 1, 100)
    F = (0.1 if scenario == "e" else 0.0) if F is None else F
    check_range("F", F, 0.0, 5.0)
    for name, v in (("Kp", Kp), ("Ti", Ti), ("T", T), ("v_ref", v_ref), ("lad", lad)):
        check_range(name, v, 0.0, None, low_open=True)
    check_range("tau_max", tau_max, 0.0, N * T, high_open=True)
    check_range("eta", eta, 0.0, tau_max)
    check_range("phi", phi, 0.0, None)
    check_range("assumed_delay", assumed_delay, 0.0, N * T)
    path = four_right_angles() if path is None else path
    horizon_s = 1.5 * float(path.length) / v_ref + 5.0 if horizon_s is None else horizon_s
    check_range("horizon_s", horizon_s, 0.0, None, low_open=True)
    x0 = np.concatenate([[0.0, 0.0], np.asarray(path.points[0]), [0.0]]).astype(np.float32)
    plant = nc.DiffDrive(x0=x0, F=F, T=T, sub=SUB, lifted=prediction)
    ns = 1 if scenario == "a" else N
    if scenario in "ab":
        pi = DiscreteSS.from_tf(single_rate_pi(Kp, Ti, ns * T))
    else:
        import control
        Gp = control.tf([float(plant.K)], [float(plant.tau), 1.0])
        pi = DualRateController.from_design(dualrate_design(Gp, pi_controller(Kp, Ti), T, N))
    # the progress search covers the arc travelled in a sensing period (40 points unless that is short of it)
    window = max(40, math.ceil(v_ref * ns * T / float(path.spacing)) + 2)
    ctrl = nc.PursuitPI(path, plant, pi, v_ref=v_ref, lad=lad, end_tol=END_TOL, assumed_delay=assumed_delay, ns=ns,
                        h=h if scenario == "e" else 0, window=window)
    if scenario == "e":
        # the true measurement noise (floored so that F = 0 stays well-conditioned) and wheel noise
        # lifted to NT (eq. 7), plus a margin for the model's error (3 mm, 0.01 rad per NT: ours)
        Ff = max(F, 0.02)
        std = np.asarray(nc.DiffDrive(F=Ff).v_std)
        wv = float(nc.lifted_wheel_var(plant, Ff * float(plant.wheel), N))
        Q = np.diag([wv, wv, 0.003 ** 2, 0.003 ** 2, 0.01 ** 2])
        P0 = np.diag(np.asarray([0.1, 0.1, 0.005, 0.005, 0.01]) ** 2)
        est = nc.PeriodEKF(plant, Q=Q, R=np.diag(std ** 2), mean0=x0, cov0=P0, inputs="applied")
    else:
        est = nc.Passthrough(0.0)
    delayed = scenario in "de"
    down = nc.Link(delay=nc.TruncatedExponential(eta, phi, tau_max)) if delayed else nc.Link()
    H = ctrl.horizon
    act = nc.ArrivalActuator(horizon=H) if scenario == "d" else nc.PacketActuator(horizon=H, on_exhausted="hold")
    n_slow = math.ceil(horizon_s / (N * T))
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=est, controller=ctrl,
                   downlink=down, actuator=act, N=ns * SUB,
                   monitor=nc.PathMonitor(path, max_dev=MAX_DEV, end_tol=END_TOL, window=ctrl.window, every=SUB),
                   steps=n_slow * N * SUB, T=T / SUB, record=nc.Record(("x", "u"), controller=controller_trace))


def controller_trace(ctrl: nc.PursuitPI, state: nc.PursuitState):
    """(w_com float[2], est float[h+1, 5], U float[ns, 2], u_prior float[ns, 2]) after each
    sensing instant: the references, the estimates packet (Table 1), u_{k|k} and u_{k|k-1}."""
    return state.w_com, state.est, state.U, state.u_prior


def reference_points(loop: nc.Loop, N: int = 2) -> jax.Array:
    """(x̄, ȳ)_k'^{NT} of eq. (23)-(24), float[S+1, 2]: the path point at arc length k' v_ref NT,
    k' = 0 .. S (S sensing periods NT in the run; clipped at the path's end)."""
    ctrl, T = loop.controller, loop.plant.T
    S = loop.steps // (N * loop.plant.sub)
    s = jnp.arange(S + 1, dtype=jnp.float32) * (ctrl.v_ref * N * T)
    return jax.vmap(lambda si: point_at(ctrl.path, si))(s)


class Metrics(NamedTuple):
    """Cost indexes of section 4 on the NT grid (eq. 23-25), and network use; inf when unstable.

    J1, J2 measure the distance to the path (the polyline); J1_ref, J2_ref as printed, to
    the nearest NT sample of the reference trajectory (:func:`reference_points`), which
    carries a floor of up to half their spacing (docs/diffdrive.md)."""

    J1: jax.Array         # eq. (23): sum over NT instants of the distance to the path, mm
    J1_mean: jax.Array    # the same as a mean distance, mm
    J2: jax.Array         # eq. (24): max distance, mm
    J1_ref: jax.Array     # eq. (23) as printed, mm
    J2_ref: jax.Array     # eq. (24) as printed, mm
    J3: jax.Array         # eq. (25): time to reach the end, s
    packets: jax.Array    # packets sent (both directions) until the end
    l: jax.Array          # periods T until the end
    unstable: jax.Array

    #: the fields' units (jaxnc.results.save_per_seed, jaxnc.load)
    UNITS = {"J1": "mm", "J1_mean": "mm", "J2": "mm", "J1_ref": "mm", "J2_ref": "mm", "J3": "s",
             "packets": "packets", "l": "actuation periods T"}   # T = plant.T, not the runner's T / sub


def metrics(loop: nc.Loop, traj: nc.Trajectory, *, N: int = 2) -> Metrics:
    """Eq. (23)-(25) from the true positions every NT (every scenario on the same grid; ``N``
    the multiplicity of that grid), up to completion l T (l = ``traj.done_step`` / sub: the
    path monitor checks every T); unstable when the run failed before completion or never
    completed."""
    sub, T, ns = loop.plant.sub, loop.plant.T, loop.controller.ns
    l = traj.done_step // sub
    xy = traj.x[::N * sub, 2:4]
    mask = jnp.arange(xy.shape[0]) * N < l
    dist = distance_to_path(loop.controller.path, xy) * 1000.0
    dref = distance_to_points(reference_points(loop, N), xy) * 1000.0
    unstable = (traj.failed & ((traj.fail_step - 1) // sub < l)) | ~traj.done
    inf = lambda v: jnp.where(unstable, jnp.asarray(jnp.inf, jnp.float32), v)
    j1 = jnp.sum(jnp.where(mask, dist, 0.0))
    return Metrics(J1=inf(j1), J1_mean=inf(j1 / jnp.maximum(jnp.sum(mask), 1)),
                   J2=inf(jnp.max(jnp.where(mask, dist, 0.0))), J1_ref=inf(jnp.sum(jnp.where(mask, dref, 0.0))),
                   J2_ref=inf(jnp.max(jnp.where(mask, dref, 0.0))), J3=inf(l * T),
                   packets=2.0 * jnp.ceil(l / ns), l=l, unstable=unstable)


#: the per-seed function ``run(loop, key, *, N=2) -> Metrics``: :func:`jaxnc.loop.run` with :func:`metrics`
run = functools.partial(nc.run, metrics=metrics)
