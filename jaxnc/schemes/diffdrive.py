"""Closed loops of seed 004, scenarios a-e (section 5.2), as configurations of :mod:`jaxnc.loop`.

The robot follows a path of four right angles by standard pure pursuit (eq. 15-20);
the wheel-speed loops are PI (eq. 27) in one of two forms:

* **a** single rate at T = 0.1 s (eq. 30): sensing, pure pursuit and PI every T;
* **b** single rate at NT = 0.2 s (eq. 31): everything every NT, the action held;
* **c** dual rate (eq. 21-22, 28-29): sensing and pure pursuit every NT, G1 at NT, G2
  gives N actions at T;
* **d** c with network delays: the local side computes when the reference packet of
  period k arrives, tau_rl after kNT, and only then starts the period's N actions
  (each lasting T); until then the actuator holds its last action;
* **e** c with delays, EKF (eq. 8-13) and h-step-ahead prediction (eq. 14), packet-based
  control (section 2.2) and low noise (F = 0.1): at kNT the actuator starts the actions
  the previous computation predicted for period k (u_{k|k-1}); when the reference packet
  arrives the local side corrects the state with the EKF, computes u_{k|k}, ... and the
  actuator switches to them, indexed by time stamp.  The local side sends the remote the
  h+1 estimates (xi_{k|k}, xi_{k+1|k}, ..., xi_{k+h|k}) (Table 1).  The EKF's prediction
  and the prediction stage use the slow-period model ``DiffDriveLoop.prediction``:
  "integrated" (default; the true plant's integrator with the fine commands applied, or
  to be applied, including u_{k|k-1} until the packet arrives) or "eq1" (eq. 1 as printed).

Timing and network.  The network carries references remote -> local and estimates
local -> remote, one packet each per sensing period (T for a, NT otherwise), so b-e use
half the packets of a.  Delays follow a shifted ("generalised") exponential, eq. (7) of
seed 000, truncated at tau_max = 0.17 s < NT (section 5.1), so packets never overtake
one another.  The packet's content (path references) is static, so only its timing
matters.  The true plant runs at the fine period T/sub (delays are quantised up to it).

All randomness is drawn per fast slot T from the key (:func:`draw`), so every scenario
meets the same noise and delays at the same times (common random numbers).  A run is
*unstable* when the robot leaves a ``max_dev`` tube around the path, a state is
non-finite, or it does not reach the end within the horizon; its indexes are then inf.
Once the path is complete the motors receive zero from the next sensing instant.

On the runner (:func:`runner_loop`): its fast period is the fine step dt = T/sub, so one
slow period is ns * sub fine steps (ns = 1 for a, N otherwise), the controller's packet
holds each action over sub fine steps, the downlink's delay (d, e) is the reference
packet's, quantised up to dt, and the wheel noise enters at the first fine step of each
slot T (:func:`runner_draws`).  The roles: :class:`Robot` (the true plant and its
completion / tube monitor, recorded by :func:`robot_trace`), Passthrough or
:class:`DiffDriveEKF`, :class:`DiffDriveController`, and a packet actuator by time stamp
or :class:`ArrivalActuator` (d).
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import control
import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_choice, check_int, check_nonneg, check_positive, check_range
from jaxnc.design.dualrate import DiscreteSS, DualRateController, DualRateState, dualrate_design, pi_controller, \
    single_rate_pi
from jaxnc.controllers.prediction import predict_periods
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.loop import runner
from jaxnc.loop.actuators import PacketActuator
from jaxnc.loop.base import (AbstractActuator, AbstractController, AbstractEstimator, AbstractPlant, Inbox, Packet,
                             blend)
from jaxnc.loop.estimators import Passthrough
from jaxnc.loop.links import Link, LinkDraws, TruncatedExponential, truncated_exponential
from jaxnc.loop.triggers import Periodic
from jaxnc.metrics import distance_to_path, distance_to_points
from jaxnc.network import quantise_delay
from jaxnc.paths import Path, closest_index, from_waypoints, point_at
from jaxnc.plants.diffdrive import (K_MOTOR, OUTPUT_DIM, PROCESS_NOISE_DIM, STATE_DIM, TAU_MOTOR, DiffDrive,
                                    DiffDriveNoise, lifted_wheel_var)

SCENARIOS = ("a", "b", "c", "d", "e")
#: scenario e's slow-period model (EKF prediction and prediction stage): "integrated", the
#: true plant's integrator over the period with the fine commands it will receive (the
#: paper's "accurate system model", section 2.2); "eq1", eq. (1)-(3), (7) as printed.
PREDICTIONS = ("integrated", "eq1")
KP, TI = 6.0, 0.12                 # section 5.1
TAU_MAX = 0.17                     # s, section 5.1
# Delay law (ours; the paper gives only tau_max): eta + phi Exp(1), truncated at tau_max.
DELAY_ETA, DELAY_PHI = 0.08, 0.04
V_REF = 0.14                       # m/s: 3 m in ~22 s, the paper's J3
LAD = 0.12                         # m, look-ahead distance

# Four right angles (left, right, left, right), 0.6 m legs, 3.0 m in all (ours: the
# paper shows the shape in Figs. 5-9 without dimensions).
STAIRS = ((0.0, 0.0), (0.6, 0.0), (0.6, 0.6), (1.2, 0.6), (1.2, 1.2), (1.8, 1.2))


def four_right_angles(ds: float = 0.005) -> Path:
    return from_waypoints(np.asarray(STAIRS), "four_right_angles", ds)


def pure_pursuit(path: Path, pose, idx_prev, *, lad, v_ref, window: int):
    """Standard pure pursuit, eq. (15)-(19): returns ((v_ref, omega_ref), idx).

    The target is the path point an arc length ``lad`` beyond the nearest point (a
    monotone windowed search from ``idx_prev``); the curvature is eq. (18),

        k = 2 ((y_t - y) cos psi - (x_t - x) sin psi) / ((x_t - x)^2 + (y_t - y)^2),

    and omega_ref = v_ref k (eq. 19).
    """
    idx, _ = closest_index(path, pose[2:4], idx_prev, window)
    target = point_at(path, path.s[idx] + lad)
    dx, dy = target[0] - pose[2], target[1] - pose[3]
    c, s = jnp.cos(pose[4]), jnp.sin(pose[4])
    kappa = 2.0 * (dy * c - dx * s) / (dx * dx + dy * dy + 1e-9)
    return (v_ref, v_ref * kappa), idx


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiffDriveLoop:
    """One scenario's configuration.  Static: scenario, N, h, n_slow (sensing periods at NT),
    prediction (scenario e's slow-period model, one of :data:`PREDICTIONS`)."""

    plant: DiffDrive
    noise: DiffDriveNoise          # true noise (F inside)
    path: Path
    sr: DiscreteSS                 # single-rate PI at the sensing period (a: eq. 30, b: eq. 31)
    dr: DualRateController         # dual-rate PI (eq. 28-29), scenarios c-e
    Q: jax.Array                   # EKF process-noise covariance (5x5, of n1 at NT)
    R: jax.Array                   # EKF measurement-noise covariance (5x5)
    P0_std: jax.Array
    v_ref: jax.Array = V_REF
    lad: jax.Array = LAD
    w_max: jax.Array = 15.0        # rad/s, wheel-speed command limit of the pure pursuit
    eta: jax.Array = DELAY_ETA
    phi: jax.Array = DELAY_PHI
    tau_max: jax.Array = TAU_MAX
    max_dev: jax.Array = 0.3       # m: leaving this tube = unstable
    end_tol: jax.Array = 0.03      # m: the path is complete within this of its end
    scenario: str = dataclasses.field(default="e", metadata=dict(static=True))
    N: int = dataclasses.field(default=2, metadata=dict(static=True))
    h: int = dataclasses.field(default=1, metadata=dict(static=True))
    n_slow: int = dataclasses.field(default=100, metadata=dict(static=True))
    window: int = dataclasses.field(default=40, metadata=dict(static=True))
    prediction: str = dataclasses.field(default="integrated", metadata=dict(static=True))

    def __post_init__(self):
        if self.scenario not in SCENARIOS:
            raise ValueError(f"DiffDriveLoop.scenario must be one of {', '.join(SCENARIOS)}, got {self.scenario!r}")
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"DiffDriveLoop.prediction must be one of {', '.join(PREDICTIONS)}, "
                             f"got {self.prediction!r}")
        check_int("DiffDriveLoop.N", self.N, 1, 50)
        check_int("DiffDriveLoop.h", self.h, 1, 100)
        check_int("DiffDriveLoop.n_slow", self.n_slow, 1)
        check_positive("DiffDriveLoop.v_ref", self.v_ref)
        check_positive("DiffDriveLoop.lad", self.lad)
        check_nonneg("DiffDriveLoop.eta", self.eta)
        check_nonneg("DiffDriveLoop.phi", self.phi)
        check_range("DiffDriveLoop.tau_max", self.tau_max, 0.0, self.N * self.plant.T, high_open=True)
        if self.delayed:
            check_range("DiffDriveLoop.eta", self.eta, 0.0, self.tau_max)

    @property
    def ns(self) -> int:
        """Fast periods per sensing period: 1 for a, N otherwise."""
        return 1 if self.scenario == "a" else self.N

    @property
    def delayed(self) -> bool:
        return self.scenario in ("d", "e")

    @property
    def steps(self) -> int:
        """Fast periods T simulated."""
        return self.n_slow * self.N


def diffdrive_loop(scenario: str = "e", *, N: int = 2, h: int = 1, F: float | None = None,
                   Kp: float = KP, Ti: float = TI, T: float = 0.1, tau_max: float = TAU_MAX,
                   eta: float = DELAY_ETA, phi: float = DELAY_PHI, v_ref: float = V_REF, lad: float = LAD,
                   path: Path | None = None, horizon_s: float | None = None,
                   noise: DiffDriveNoise | None = None, prediction: str = "integrated") -> DiffDriveLoop:
    """A validated configuration with the paper's defaults (section 5.1).

    ``F`` is the noise factor: None means the paper's choice (0 for a-d, which the paper
    runs noise-free, 0.1 for e).  The controllers are designed here, at configuration
    time: ``single_rate_pi`` at T (a) or NT (b) and ``dualrate_design`` (c-e).
    ``prediction`` is scenario e's slow-period model (:data:`PREDICTIONS`): "integrated"
    (default, :meth:`DiffDrive.integrated`) or "eq1" (eq. 1 as printed, the former default);
    a-d do not use it.  Raises ValueError naming the parameter for a bad value.
    """
    scenario = check_choice("scenario", scenario, SCENARIOS)
    prediction = check_choice("prediction", prediction, PREDICTIONS)
    check_int("N", N, 1, 50)
    check_int("h", h, 1, 100)
    F = (0.1 if scenario == "e" else 0.0) if F is None else F
    check_range("F", F, 0.0, 5.0)
    plant = DiffDrive(T=T)
    noise = dataclasses.replace(noise or DiffDriveNoise(), F=F)
    path = path or four_right_angles()
    Gp = control.tf([K_MOTOR], [TAU_MOTOR, 1.0])
    ns = 1 if scenario == "a" else N
    sr = DiscreteSS.from_tf(single_rate_pi(Kp, Ti, ns * T))
    dr = DualRateController.from_design(dualrate_design(Gp, pi_controller(Kp, Ti), T, N))
    # EKF design covariances: the true measurement noise (floored so that F = 0 stays
    # well-conditioned) and the true wheel noise lifted to NT (eq. 7), plus the error of
    # the NT kinematic model eq. (1) (3 mm, 0.01 rad per NT: ours).
    Ff = max(F, 0.02)
    std = np.asarray(dataclasses.replace(noise, F=Ff).measurement_std())
    R = np.diag(std ** 2).astype(np.float32)
    wv = float(lifted_wheel_var(plant, Ff * float(noise.wheel), N))
    Q = np.diag([wv, wv, 0.003 ** 2, 0.003 ** 2, 0.01 ** 2]).astype(np.float32)
    if horizon_s is None:
        horizon_s = 1.5 * float(path.length) / v_ref + 5.0
    n_slow = math.ceil(horizon_s / (N * T))
    return DiffDriveLoop(plant=plant, noise=noise, path=path, sr=sr, dr=dr, Q=Q, R=R,
                         P0_std=np.asarray([0.1, 0.1, 0.005, 0.005, 0.01], np.float32),
                         v_ref=v_ref, lad=lad, eta=eta, phi=phi, tau_max=tau_max,
                         scenario=scenario, N=N, h=h, n_slow=n_slow, prediction=prediction)


class Draws(NamedTuple):
    """Randomness of one run, per fast slot T (common random numbers across scenarios)."""

    w: jax.Array       # [K, 2] standard normal: wheel process noise n1 (eq. 4)
    v: jax.Array       # [K, 5] standard normal: measurement noise n2
    u_rl: jax.Array    # [K] uniforms: remote -> local delay
    u_lr: jax.Array    # [K] uniforms: local -> remote delay


def draw(key, steps: int) -> Draws:
    """The run's standard draws for ``steps`` fast slots T: ``key`` split into 4 streams
    (wheel noise, measurement noise, remote -> local and local -> remote delay uniforms)."""
    kw, kv, kr, kl = jax.random.split(key, 4)
    return Draws(jax.random.normal(kw, (steps, 2)), jax.random.normal(kv, (steps, OUTPUT_DIM)),
                 jax.random.uniform(kr, (steps,)), jax.random.uniform(kl, (steps,)))


#: Inverse CDF of eta + phi Exp(1) truncated to [eta, tau_max] at uniforms u (never beyond
#: tau_max, so never out of order when tau_max < NT): the loop's
#: :func:`jaxnc.loop.links.truncated_exponential`.
truncated_delay = truncated_exponential


class Trajectory(NamedTuple):
    x: jax.Array          # [K, 5] true state at the start of every fast slot T
    u: jax.Array          # [K, 2] command applied at the start of every fast slot
    w_com: jax.Array      # [n_sense, 2] wheel-speed references (eq. 20)
    est: jax.Array        # [n_sense, h+1, 5] e: the estimates packet (xi_{k|k}, ..., xi_{k+h|k})
    delay: jax.Array      # [n_sense] remote -> local delay applied, s (0 for a-c)
    u_plan: jax.Array     # [n_sense, ns, 2] actions computed for the period (u_{k|k})
    u_prior: jax.Array    # [n_sense, N, 2] e: actions predicted for it one period earlier (u_{k|k-1})
    l: jax.Array          # fast slots until the path was completed (K if never)
    done: jax.Array
    bad: jax.Array


def _wheel_ref(loop: DiffDriveLoop, pose, idx):
    (v, om), idx = pure_pursuit(loop.path, pose, idx, lad=loop.lad, v_ref=loop.v_ref, window=loop.window)
    w = jnp.clip(loop.plant.wheel_command(v, om), -loop.w_max, loop.w_max)
    return w, idx


def _control(loop: DiffDriveLoop, est, idx, sr, dr):
    """Pure pursuit (eq. 15-20) + the scenario's PI from the estimate ``est``:
    returns (actions [ns, 2], w_com, idx, sr, dr)."""
    w_com, idx = _wheel_ref(loop, est, idx)
    e = w_com - est[:2]
    if loop.scenario in ("a", "b"):
        u, sr = loop.sr.step(sr, e)
        U = jnp.broadcast_to(u, (loop.ns, 2))
    else:
        U, dr = loop.dr(dr, e)
    return U, w_com, idx, sr, dr


def predict_stage(loop: DiffDriveLoop, mean, idx, dr: DualRateState, u_prev=None, arrival=None):
    """h-step-ahead prediction stage (section 3.2, items 1-4, eq. 14) from the corrected
    state: pure pursuit, dual-rate controller and the NT model iterated in open loop
    (:func:`jaxnc.controllers.prediction.predict_periods`).

    ``loop.prediction`` picks the model: "eq1", eq. (1) as printed with the N actions
    (``u_prev`` and ``arrival`` unused); "integrated", :meth:`DiffDrive.integrated` with
    the fine commands the actuator will apply: in period k, ``u_prev`` (float[N, 2], the
    actions u_{k|k-1} it plays from kNT) for the first ``arrival`` fine steps (int, the
    instant the new packet arrives, fine steps after kNT; None: 0), then the period's own
    actions by time stamp; in the later periods their own actions throughout.

    Returns (states [h+1, 5] = xi_{k|k} .. xi_{k+h|k}, actions [h+1, N, 2] for periods
    k .. k+h, and the controller state / path progress after the first period).
    """
    sr0 = jnp.zeros((2, loop.sr.order), jnp.float32)
    if loop.prediction == "eq1":
        def law(c, s):
            i, d = c
            U, _, i, _, d = _control(loop, s, i, sr0, d)
            return U, (i, d)

        states, Us, (idxs, drs) = predict_periods(law, loop.plant.dynamics, mean, (idx, dr), loop.h + 1,
                                                  PROCESS_NOISE_DIM)
        first = jax.tree.map(lambda a: a[0], (idxs, drs))
        return states, Us, first[0], first[1]

    sub = loop.plant.sub
    nf = loop.ns * sub
    prev = jnp.zeros((nf, 2), jnp.float32) if u_prev is None else jnp.repeat(u_prev, sub, axis=0)
    early = jnp.arange(nf)[:, None] < (0 if arrival is None else arrival)      # before the packet arrives

    def law_fine(c, s):
        i, d, first = c
        U, _, i, _, d = _control(loop, s, i, sr0, d)
        Uf = jnp.repeat(U, sub, axis=0)
        return (U, jnp.where(first & early, prev, Uf)), (i, d, jnp.zeros((), bool))

    model = lambda x, UU, w: loop.plant.integrated(x, UU[1], w)
    states, (Us, _), (idxs, drs, _) = predict_periods(law_fine, model, mean, (idx, dr, jnp.ones((), bool)),
                                                      loop.h + 1, PROCESS_NOISE_DIM)
    first = jax.tree.map(lambda a: a[0], (idxs, drs))
    return states, Us, first[0], first[1]


# ----------------------------------------------------------------------------- the loop's roles
#
# The runner's fast period is the true plant's fine step dt = T/sub (Loop.N = ns * sub fine
# steps per sensing period), so the reference packet's delay, quantised up to dt, can start
# the period's actions in the middle of a slot T, and the actions are held over sub fine steps.


def _x0(loop: DiffDriveLoop):
    return jnp.concatenate([jnp.zeros(2), loop.path.points[0], jnp.zeros(1)]).astype(jnp.float32)


class RobotState(NamedTuple):
    """The true robot and its completion / tube monitor (scalars unless shown)."""

    x: jax.Array        # float[5] state
    t: jax.Array        # int32 fine steps taken
    idx: jax.Array      # int32 progress of the true position along the path (updated every T)
    done: jax.Array     # bool: the path was completed (within end_tol of its end)
    stop: jax.Array     # bool: motors stopped (done at the last sensing instant)
    l: jax.Array        # int32 slots T until completion (K if never)
    bad: jax.Array      # bool: left the max_dev tube or non-finite before completion
    x_in: jax.Array     # float[5] the state entering the last fine step (with its slot's noise)
    u: jax.Array        # float[2] the command the motors received in the last fine step


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot(AbstractPlant):
    """The true plant of scenarios a-e at the fine period dt = T/sub (runner's fast period).

    ``step``: at the first fine step of each slot T the wheel noise n1 (eq. 4) is added to
    the wheel speeds (``w`` float[2], zero elsewhere in the runner's draws); then one
    :meth:`DiffDrive.substep`. At the last fine step of each slot the monitor advances:
    the path progress (monotone windowed search), tube failure (distance > max_dev or a
    non-finite state, before completion), the completion slot l and ``done``. From the
    first sensing instant after completion the motors receive zero (``stop``).
    ``measure`` returns (xi + n2, done) float[6]: the measurement eq. (8) and the local
    side's completion flag.
    """

    loop: DiffDriveLoop
    state_dim = STATE_DIM
    input_dim = 2
    noise_dim = 2
    output_dim = OUTPUT_DIM + 1

    def init(self, key) -> RobotState:
        x0 = _x0(self.loop)
        z = jnp.zeros((), jnp.int32)
        f = jnp.zeros((), bool)
        return RobotState(x0, z, z, f, f, jnp.asarray(self.loop.steps, jnp.int32), f, x0, jnp.zeros(2, jnp.float32))

    def dynamics(self, x, u, w):
        """One fine step of the state vector: noise w float[2] on the wheel speeds, then the substep."""
        return self.loop.plant.substep(x.at[:2].add(w), u)

    def step(self, s: RobotState, u, w) -> RobotState:
        lp = self.loop
        sub = lp.plant.sub
        nf = lp.ns * sub
        path, M = lp.path, lp.path.M
        i = jnp.mod(s.t, sub)
        stop = jnp.where(jnp.mod(s.t, nf) == 0, s.done, s.stop)
        u = jnp.where(stop, 0.0, u)
        x = jnp.where(i == 0, s.x.at[:2].add(w), s.x)
        x1 = lp.plant.substep(x, u)

        def monitor(_):
            idx, dist = closest_index(path, x1[2:4], s.idx, lp.window)
            at_end = (idx >= (9 * M) // 10) & (jnp.sum((x1[2:4] - path.points[-1]) ** 2) < lp.end_tol ** 2)
            bad = s.bad | (~s.done & ((dist > lp.max_dev) | ~jnp.all(jnp.isfinite(x1))))
            l = jnp.where(s.done, s.l, s.t // sub + 1)
            return idx, s.done | at_end, l, bad

        # the monitor advances at the end of each slot T (a cond: t is the same in every run of a batch)
        idx, done, l, bad = jax.lax.cond(i == sub - 1, monitor, lambda _: (s.idx, s.done, s.l, s.bad), None)
        return RobotState(x1, s.t + 1, idx, done, stop, l, bad, x, u)

    def measure(self, s: RobotState, v):
        return jnp.concatenate([self.loop.plant.measure(s.x, v[:OUTPUT_DIM]), s.done.astype(jnp.float32)[None]])

    def process_std(self):
        return self.loop.noise.process_std()

    def measurement_std(self):
        return jnp.concatenate([self.loop.noise.measurement_std(), jnp.zeros((1,), jnp.float32)])

    def state_vector(self, s: RobotState):
        return s.x



class EkfState(NamedTuple):
    prior: Gaussian     # belief for this sensing instant
    post: Gaussian      # corrected belief (the estimate)
    stop: jax.Array     # bool: the motors are stopped this period


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiffDriveEKF(AbstractEstimator):
    """Scenario e's EKF (eq. 8-13) at the sensing period NT.

    ``correct``: :func:`ekf_update` with the delivered measurement (xi + n2, eq. 8);
    ``predict``: :func:`ekf_predict` with the fine commands the motors received
    (``u_applied`` float[N*sub, 2]; zero once the robot has stopped) and the loop's model:
    "integrated", :meth:`DiffDrive.integrated` over those commands; "eq1", eq. (1)-(3), (7)
    with, per slot T, their mean."""

    loop: DiffDriveLoop
    inputs = "applied"

    def init(self, ctx) -> EkfState:
        g = Gaussian(_x0(self.loop), jnp.diag(jnp.asarray(self.loop.P0_std, jnp.float32) ** 2))
        return EkfState(g, g, jnp.zeros((), bool))

    def correct(self, state: EkfState, inbox: Inbox, k):
        z, _, w = inbox.newest()
        post = ekf_update(self.loop.plant.measure, state.prior, z[:OUTPUT_DIM], self.loop.R, OUTPUT_DIM)
        post = blend(w, post, state.prior)
        return EkfState(state.prior, post, blend(w, z[OUTPUT_DIM] > 0.5, state.stop)), post.mean

    def predict(self, state: EkfState, u_applied, u_believed, k) -> EkfState:
        lp = self.loop
        u = jnp.where(state.stop, 0.0, u_applied)
        if lp.prediction == "integrated":
            prior = ekf_predict(lp.plant.integrated, state.post, u, lp.Q, PROCESS_NOISE_DIM)
        else:
            u_eff = jnp.mean(u.reshape(lp.ns, lp.plant.sub, 2), axis=1)
            prior = ekf_predict(lp.plant.dynamics, state.post, u_eff, lp.Q, PROCESS_NOISE_DIM)
        return state._replace(prior=prior)


class CtrlState(NamedTuple):
    sr: jax.Array           # [2, n] single-rate PI states
    dr: DualRateState       # dual-rate states, [2, n] each
    idx: jax.Array          # pure-pursuit progress (local side)
    u_pred: jax.Array       # [N, 2] e: actions predicted for the next period
    w_com: jax.Array        # [2] the last wheel-speed references (eq. 20)
    est: jax.Array          # [h+1, 5] the last estimates packet
    U: jax.Array            # [ns, 2] the last period's actions u_{k|k}
    u_prior: jax.Array      # [N, 2] the actions predicted for that period one period earlier


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiffDriveController(AbstractController):
    """Pure pursuit (eq. 15-20) and the scenario's PI, one packet per sensing period.

    a, b: single-rate PI (eq. 30-31), its action held over the period; c, d: dual rate
    (eq. 21-22, 28-29), N actions at T; e: the h-step-ahead prediction stage
    (:func:`predict_stage`, eq. 14), the actions of periods k .. k+h. The packet carries
    them at the fine period (each action repeated sub times), stamped kN sub.

    ``arrival`` (e, prediction "integrated"): int32[S], fine steps after kNT at which the
    reference packet of period k reaches the local side, where the computation runs
    (section 2.2): its own clock tells it how long the actuator played u_{k|k-1}, so the
    prediction stage integrates that mix. None: as if it arrived at kNT."""

    loop: DiffDriveLoop
    arrival: jax.Array | None = None

    @property
    def horizon(self) -> int:
        lp = self.loop
        return lp.ns * lp.plant.sub * (lp.h + 1 if lp.scenario == "e" else 1)

    def init(self, ctx) -> CtrlState:
        lp = self.loop
        z2 = jnp.zeros(2, jnp.float32)
        return CtrlState(jnp.zeros((2, lp.sr.order), jnp.float32), lp.dr.init((2,)), jnp.zeros((), jnp.int32),
                         jnp.zeros((lp.N, 2), jnp.float32), z2, jnp.zeros((lp.h + 1, STATE_DIM), jnp.float32),
                         jnp.zeros((lp.ns, 2), jnp.float32), jnp.zeros((lp.N, 2), jnp.float32))

    def step(self, state: CtrlState, xhat, fresh, k, ctx):
        lp = self.loop
        est = xhat[:STATE_DIM]
        if lp.scenario == "e":
            arrival = None if self.arrival is None else self.arrival[k]
            states, Us, idx, dr = predict_stage(lp, est, state.idx, state.dr, state.u_pred, arrival)
            U = Us[0]
            w_com, _ = _wheel_ref(lp, est, state.idx)
            sr, u_pred = state.sr, Us[1]
            acts = Us.reshape(-1, 2)
        else:
            U, w_com, idx, sr, dr = _control(lp, est, state.idx, state.sr, state.dr)
            states = jnp.broadcast_to(est, (lp.h + 1, STATE_DIM))
            u_pred, acts = state.u_pred, U
        new = CtrlState(sr, dr, idx, u_pred, w_com, states, U, state.u_pred)
        pkt = Packet(jnp.repeat(acts, lp.plant.sub, axis=0), (k * ctx.N).astype(jnp.int32))
        return new, pkt, jnp.ones((), jnp.float32)


def robot_trace(robot: Robot, s: RobotState):
    """(x_in float[5], u float[2], l, done, bad) after each fine step (a
    :class:`jaxnc.loop.Record` function)."""
    return s.x_in, s.u, s.l, s.done, s.bad


def controller_trace(c: DiffDriveController, state: CtrlState):
    """(w_com [2], est [h+1, 5], U [ns, 2], u_prior [N, 2]) after each step."""
    return state.w_com, state.est, state.U, state.u_prior


class ArrivalState(NamedTuple):
    u: jax.Array         # float[H, m] the newest packet's actions
    stamp: jax.Array     # int32 its time stamp (the start of its period)
    start: jax.Array     # int32 fine instant its first action started (_EMPTY: none yet)
    pending: jax.Array   # bool: a packet was received and starts at the next output
    last: jax.Array      # float[m] the last action applied


_EMPTY = -(2**30)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ArrivalActuator(AbstractActuator):
    """Scenario d's actuator: a packet's actions (float[H, m], stamped with the start of
    its period of H fast instants) start when it arrives, ``data[t - arrival]``, and stop
    at the end of its period; outside that window the last action applied is held (zero
    before the first packet). ``horizon``: static H."""

    horizon: int = dataclasses.field(default=1, metadata=dict(static=True))

    def init(self, ctx) -> ArrivalState:
        m = ctx.input_dim
        e = jnp.asarray(_EMPTY, jnp.int32)
        return ArrivalState(jnp.zeros((self.horizon, m), jnp.float32), e, e, jnp.zeros((), bool),
                            jnp.zeros((m,), jnp.float32))

    def receive(self, state: ArrivalState, inbox: Inbox) -> ArrivalState:
        data, stamp, w = inbox.newest()
        take = w > 0.5
        return state._replace(u=blend(w, jnp.asarray(data, jnp.float32), state.u),
                              stamp=jnp.where(take, stamp, state.stamp), pending=state.pending | take)

    def output(self, state: ArrivalState, t):
        start = jnp.where(state.pending, t, state.start)
        live = (start != _EMPTY) & (t < state.stamp + self.horizon)
        u = jnp.where(live, state.u[jnp.clip(t - start, 0, self.horizon - 1)], state.last)
        return state._replace(start=start, pending=jnp.zeros((), bool), last=u), u


def runner_loop(loop: DiffDriveLoop, draws: runner.Draws | None = None) -> runner.Loop:
    """The scenario as a :class:`jaxnc.loop.Loop` at the fine period dt = T/sub.

    ``draws`` (:func:`runner_draws`): the run's draws, whose downlink delays are the
    arrival instants the local side reads in scenario e with ``prediction="integrated"``
    (:class:`DiffDriveController`), where they are required (ValueError without them).

    Uplink without delay (the measurement is used at its sampling instant), downlink with
    the truncated exponential delay (d, e) quantised up to dt; Passthrough estimate (a-d)
    or :class:`DiffDriveEKF` (e); :class:`DiffDriveController`; actuator: the packet's
    actions by time stamp (a-c; e: u_{k|k-1} of the previous packet until the new one
    arrives), :class:`ArrivalActuator` (d). No failure freeze (the tube monitor lives in
    :class:`Robot`)."""
    sub = loop.plant.sub
    nf = loop.ns * sub
    arrival = None
    if loop.scenario == "e" and loop.prediction == "integrated":
        if draws is None:
            raise ValueError("runner_loop: scenario e with prediction='integrated' needs draws= (runner_draws(loop, "
                             "key)): the local side integrates the actions played until each packet arrives")
        arrival = jnp.asarray(draws.downlink.delay, jnp.int32)
    ctrl = DiffDriveController(loop, arrival)
    if loop.delayed:
        down = Link(delay=TruncatedExponential(loop.eta, loop.phi, loop.tau_max))
    else:
        down = Link()
    if loop.scenario == "d":
        act = ArrivalActuator(horizon=ctrl.horizon)
    else:
        act = PacketActuator(horizon=ctrl.horizon, capacity=1, on_exhausted="hold")
    est = DiffDriveEKF(loop) if loop.scenario == "e" else Passthrough(0.0)
    return runner.Loop(plant=Robot(loop), trigger=Periodic(), uplink=Link(), estimator=est, controller=ctrl,
                       downlink=down, actuator=act, monitor=runner.Monitor(freeze=False), N=nf,
                       steps=loop.steps * sub, T=float(loop.plant.dt),
                       record=runner.Record(plant=robot_trace, controller=controller_trace))


def runner_draws(loop: DiffDriveLoop, key) -> runner.Draws:
    """The runner's draws from :func:`draw` (``key`` split into 4): the wheel noise at the
    first fine step of each slot T (zero at the others), the measurement noise of each
    sensing instant (and 0 for the completion flag), the remote -> local delay of each
    sensing period (:func:`truncated_delay`, quantised up to dt; 0 for a-c)."""
    return _runner_draws(loop, draw(key, loop.steps), key)


def _runner_draws(loop: DiffDriveLoop, d: Draws, key) -> runner.Draws:
    ns, sub = loop.ns, loop.plant.sub
    S = loop.steps // ns
    w = (d.w * loop.noise.process_std()[None, :]).reshape(S, ns, 1, 2)
    w = jnp.concatenate([w, jnp.zeros((S, ns, sub - 1, 2), jnp.float32)], axis=2).reshape(S, ns * sub, 2)
    v = (d.v * loop.noise.measurement_std()[None, :])[::ns]
    v = jnp.concatenate([v, jnp.zeros((S, 1), jnp.float32)], axis=1)
    if loop.delayed:
        delay = quantise_delay(_tau(loop, d), loop.plant.dt)
    else:
        delay = jnp.zeros((S,), jnp.int32)
    zero = jnp.zeros((S,), jnp.int32)
    return runner.Draws(w, v, LinkDraws(zero), LinkDraws(delay), key)


def _tau(loop: DiffDriveLoop, d: Draws):
    if loop.delayed:
        return truncated_delay(d.u_rl[::loop.ns], loop.eta, loop.phi, loop.tau_max)
    return jnp.zeros((loop.steps // loop.ns,), jnp.float32)


def simulate(loop: DiffDriveLoop, key) -> Trajectory:
    """One closed-loop run of ``loop.scenario`` on the runner (:func:`runner_loop`,
    :func:`runner_draws`, :func:`jaxnc.loop.simulate`), as the scheme's Trajectory.
    Pure function of (loop, key); vmap it over keys."""
    sub = loop.plant.sub
    d = draw(key, loop.steps)
    rd = _runner_draws(loop, d, key)
    tr = runner.simulate(runner_loop(loop, rd), key, draws=rd)
    x_in, u, l, done, bad = tr.parts["plant"]
    w_com, est, U, u_prior = tr.parts["controller"]
    l, done = l[-1], done[-1]
    # a non-finite action (zeroed by the runner) before completion is a failure too
    bad = bad[-1] | (tr.failed & ((tr.fail_step - 1) // sub < l))
    return Trajectory(x=x_in[::sub], u=u[::sub], w_com=w_com, est=est, delay=_tau(loop, d),
                      u_plan=U, u_prior=u_prior, l=l, done=done, bad=bad)


def reference_points(loop: DiffDriveLoop) -> jax.Array:
    """The reference trajectory sampled every NT, (x̄, ȳ)_k'^{NT} of eq. (23)-(24): the path
    point at arc length k' v_ref NT for k' = 0 .. n_slow (clipped at the path's end), so
    consecutive references are v_ref NT apart (28 mm with our defaults)."""
    s = jnp.arange(loop.n_slow + 1, dtype=jnp.float32) * (loop.v_ref * loop.N * loop.plant.T)
    return jax.vmap(lambda si: point_at(loop.path, si))(s)


class Metrics(NamedTuple):
    """Cost indexes of section 4 on the NT grid (eq. 23-25), and network use.

    J1, J2 measure the distance to the path itself (the polyline). Eq. (23)-(24) as
    printed take it to the nearest NT sample of the reference trajectory
    (:func:`reference_points`); J1_ref, J2_ref are those. Between two references v_ref NT
    apart a robot exactly on the path is up to half that spacing from the nearest one, so
    the printed indexes carry a floor that depends on where along the path the robot's
    NT samples fall (docs/diffdrive.md)."""

    J1: jax.Array         # eq. (23) against the path: sum over NT instants of the distance, mm
    J1_mean: jax.Array    # the same as a mean distance, mm
    J2: jax.Array         # eq. (24) against the path: max distance, mm
    J1_ref: jax.Array     # eq. (23) as printed: distance to the nearest NT reference point, summed, mm
    J2_ref: jax.Array     # eq. (24) as printed: its maximum, mm
    J3: jax.Array         # eq. (25): time to reach the end, s
    packets: jax.Array    # packets sent (both directions) until the end
    l: jax.Array
    unstable: jax.Array


def evaluate(loop: DiffDriveLoop, traj: Trajectory) -> Metrics:
    """Eq. (23)-(25) from the true positions every NT (all scenarios on the same grid)."""
    N, T, ns = loop.N, loop.plant.T, loop.ns
    xy = traj.x[::N, 2:4]
    dist = distance_to_path(loop.path, xy) * 1000.0
    t = jnp.arange(xy.shape[0]) * N
    mask = t < traj.l
    unstable = traj.bad | ~traj.done
    inf = jnp.asarray(jnp.inf, jnp.float32)
    j1 = jnp.sum(jnp.where(mask, dist, 0.0))
    n = jnp.maximum(jnp.sum(mask), 1)
    j2 = jnp.max(jnp.where(mask, dist, 0.0))
    dref = distance_to_points(reference_points(loop), xy) * 1000.0
    j1_ref = jnp.sum(jnp.where(mask, dref, 0.0))
    j2_ref = jnp.max(jnp.where(mask, dref, 0.0))
    sense = jnp.ceil(traj.l / ns)
    return Metrics(J1=jnp.where(unstable, inf, j1), J1_mean=jnp.where(unstable, inf, j1 / n),
                   J2=jnp.where(unstable, inf, j2), J1_ref=jnp.where(unstable, inf, j1_ref),
                   J2_ref=jnp.where(unstable, inf, j2_ref), J3=jnp.where(unstable, inf, traj.l * T),
                   packets=2.0 * sense, l=traj.l, unstable=unstable)


def run(loop: DiffDriveLoop, key) -> Metrics:
    """simulate + evaluate: the per-seed function the Monte-Carlo engine vmaps."""
    return evaluate(loop, simulate(loop, key))
