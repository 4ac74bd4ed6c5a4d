"""Closed loops of seed 004, scenarios a-e (section 5.2), one ``lax.scan`` each.

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
  h+1 estimates (xi_{k|k}, xi_{k+1|k}, ..., xi_{k+h|k}) (Table 1).

Timing and network.  The network carries references remote -> local and estimates
local -> remote, one packet each per sensing period (T for a, NT otherwise), so b-e use
half the packets of a.  Delays follow a shifted ("generalised") exponential, eq. (7) of
seed 000, truncated at tau_max = 0.17 s < NT (section 5.1), so packets never overtake
one another.  The packet's content (path references) is static, so only its timing
matters.  The true plant runs at the fine period T/sub (delays are quantised up to it).

All randomness is drawn per fast slot T from the key, so every scenario meets the same
noise and delays at the same times (common random numbers).  A run is *unstable* when the
robot leaves a ``max_dev`` tube around the path, a state is non-finite, or it does not
reach the end within the horizon; its indexes are then inf.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import control
import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, check_nonneg, check_positive, check_range
from jaxnc.design.dualrate import DiscreteSS, DualRateController, DualRateState, dualrate_design, pi_controller, \
    single_rate_pi
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.metrics import distance_to_path, distance_to_points
from jaxnc.network import quantise_delay
from jaxnc.paths import Path, closest_index, from_waypoints, point_at
from jaxnc.plants.diffdrive import (K_MOTOR, OUTPUT_DIM, PROCESS_NOISE_DIM, STATE_DIM, TAU_MOTOR, DiffDrive,
                                    DiffDriveNoise, lifted_wheel_var)

SCENARIOS = ("a", "b", "c", "d", "e")
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
    """One scenario's configuration.  Static: scenario, N, h, n_slow (sensing periods at NT)."""

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

    def __post_init__(self):
        if self.scenario not in SCENARIOS:
            raise ValueError(f"DiffDriveLoop.scenario must be one of {', '.join(SCENARIOS)}, got {self.scenario!r}")
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
                   noise: DiffDriveNoise | None = None) -> DiffDriveLoop:
    """A validated configuration with the paper's defaults (section 5.1).

    ``F`` is the noise factor: None means the paper's choice (0 for a-d, which the paper
    runs noise-free, 0.1 for e).  The controllers are designed here, at configuration
    time: ``single_rate_pi`` at T (a) or NT (b) and ``dualrate_design`` (c-e).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
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
                         scenario=scenario, N=N, h=h, n_slow=n_slow)


class Draws(NamedTuple):
    """Randomness of one run, per fast slot T (common random numbers across scenarios)."""

    w: jax.Array       # [K, 2] standard normal: wheel process noise n1 (eq. 4)
    v: jax.Array       # [K, 5] standard normal: measurement noise n2
    u_rl: jax.Array    # [K] uniforms: remote -> local delay
    u_lr: jax.Array    # [K] uniforms: local -> remote delay


def draw(key, steps: int) -> Draws:
    kw, kv, kr, kl = jax.random.split(key, 4)
    return Draws(jax.random.normal(kw, (steps, 2)), jax.random.normal(kv, (steps, OUTPUT_DIM)),
                 jax.random.uniform(kr, (steps,)), jax.random.uniform(kl, (steps,)))


def truncated_delay(u, eta, phi, tau_max):
    """Inverse CDF of eta + phi Exp(1) truncated to [eta, tau_max] (never beyond tau_max,
    so never out of order when tau_max < NT)."""
    m = -jnp.expm1(-(tau_max - eta) / jnp.maximum(phi, 1e-12))
    return jnp.where(phi > 0, eta - phi * jnp.log1p(-u * m), eta)


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


class _Carry(NamedTuple):
    x: jax.Array
    sr: jax.Array           # [2, n] single-rate PI states
    dr: DualRateState       # dual-rate states, [2, n] each
    idx: jax.Array          # pure-pursuit progress (local side)
    belief: Gaussian        # EKF prior for this sensing instant
    u_pred: jax.Array       # [N, 2] e: actions predicted at k-1 for period k
    u_last: jax.Array       # [2] last applied command (d holds it)
    idx_true: jax.Array
    done: jax.Array
    l: jax.Array
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


def predict_stage(loop: DiffDriveLoop, mean, idx, dr: DualRateState):
    """h-step-ahead prediction stage (section 3.2, items 1-4, eq. 14) from the corrected
    state: pure pursuit, dual-rate controller and the NT model iterated in open loop.

    Returns (states [h+1, 5] = xi_{k|k} .. xi_{k+h|k}, actions [h+1, N, 2] for periods
    k .. k+h, and the controller state / path progress after the first period).
    """
    plant = loop.plant
    n0 = jnp.zeros((PROCESS_NOISE_DIM,), jnp.float32)

    def body(c, _):
        s, i, d = c
        U, _, i, _, d = _control(loop, s, i, jnp.zeros((2, loop.sr.order), jnp.float32), d)
        return (plant.dynamics(s, U, n0), i, d), (s, U, i, d)

    _, (states, Us, idxs, drs) = jax.lax.scan(body, (mean, idx, dr), None, length=loop.h + 1)
    first = jax.tree.map(lambda a: a[0], (idxs, drs))
    return states, Us, first[0], first[1]


def simulate(loop: DiffDriveLoop, key) -> Trajectory:
    """One closed-loop run of ``loop.scenario``: a ``lax.scan`` over sensing periods with
    the fine plant steps inside.  Pure function of (loop, key); vmap it over keys."""
    plant, N, ns, sub = loop.plant, loop.N, loop.ns, loop.plant.sub
    K = loop.steps
    n_sense = K // ns
    nf = ns * sub                                   # fine steps per sensing period
    dt = plant.dt
    d = draw(key, K)
    w_noise = (d.w * loop.noise.process_std()[None, :]).reshape(n_sense, ns, 2)
    v_noise = (d.v * loop.noise.measurement_std()[None, :])[::ns]
    if loop.delayed:
        tau = truncated_delay(d.u_rl[::ns], loop.eta, loop.phi, loop.tau_max)
    else:
        tau = jnp.zeros((n_sense,), jnp.float32)
    d_fine = quantise_delay(tau, dt)
    path = loop.path
    end = path.points[-1]
    M = path.M
    x0 = jnp.concatenate([jnp.zeros(2), path.points[0], jnp.zeros(1)]).astype(jnp.float32)
    belief0 = Gaussian(x0, jnp.diag(jnp.asarray(loop.P0_std, jnp.float32) ** 2))
    fine_i = jnp.arange(nf)
    slot = fine_i // sub

    def step(c: _Carry, inp):
        k, w_k, v_k, df, tau_k = inp
        z = plant.measure(c.x, v_k)
        if loop.scenario == "e":
            corrected = ekf_update(plant.measure, c.belief, z, loop.R, OUTPUT_DIM)
            est = corrected.mean
            states, Us, idx, dr = predict_stage(loop, est, c.idx, c.dr)
            U = Us[0]
            w_com, _ = _wheel_ref(loop, est, c.idx)
            sr = c.sr
        else:
            est = z
            U, w_com, idx, sr, dr = _control(loop, est, c.idx, c.sr, c.dr)
            states = jnp.broadcast_to(est, (loop.h + 1, STATE_DIM))
            Us = None
        # command at every fine step of the period (section 2.2 for d and e)
        before = df > fine_i
        if loop.scenario == "d":
            u_new = U[jnp.clip((fine_i - df) // sub, 0, ns - 1)]
            u_seq = jnp.where(before[:, None], c.u_last[None, :], u_new)
        elif loop.scenario == "e":
            u_seq = jnp.where(before[:, None], c.u_pred[slot], U[slot])
        else:
            u_seq = U[slot]
        u_seq = jnp.where(c.done, 0.0, u_seq)

        def fast(fc, j):
            x, idx_true, done, l, bad = fc
            x = x.at[:2].add(w_k[j])                    # n1, every T (eq. 4)
            x_start = x

            def fine(x, i):
                return plant.substep(x, u_seq[j * sub + i]), None

            x, _ = jax.lax.scan(fine, x, jnp.arange(sub))
            idx_true, dist = closest_index(path, x[2:4], idx_true, loop.window)
            t = k * ns + j
            at_end = (idx_true >= (9 * M) // 10) & (jnp.sum((x[2:4] - end) ** 2) < loop.end_tol ** 2)
            bad = bad | (~done & ((dist > loop.max_dev) | ~jnp.all(jnp.isfinite(x))))
            l = jnp.where(done, l, t + 1)
            done = done | at_end
            return (x, idx_true, done, l, bad), (x_start, u_seq[j * sub])

        fc, (xs, us) = jax.lax.scan(fast, (c.x, c.idx_true, c.done, c.l, c.bad), jnp.arange(ns))
        x, idx_true, done, l, bad = fc
        if loop.scenario == "e":
            u_eff = jnp.mean(u_seq.reshape(ns, sub, 2), axis=1)   # what the motors received per slot
            belief = ekf_predict(plant.dynamics, corrected, u_eff, loop.Q, PROCESS_NOISE_DIM)
            u_pred = Us[1]
        else:
            belief, u_pred = c.belief, c.u_pred
        new = _Carry(x, sr, dr, idx, belief, u_pred, u_seq[-1], idx_true, done, l, bad)
        return new, (xs, us, w_com, states, tau_k, U, c.u_pred)

    carry0 = _Carry(x0, jnp.zeros((2, loop.sr.order), jnp.float32), loop.dr.init((2,)),
                    jnp.zeros((), jnp.int32), belief0, jnp.zeros((N, 2), jnp.float32), jnp.zeros(2, jnp.float32),
                    jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.asarray(K, jnp.int32), jnp.zeros((), bool))
    xs_in = (jnp.arange(n_sense), w_noise, v_noise, d_fine, tau)
    final, (xs, us, w_com, est, tau, U, u_prior) = jax.lax.scan(step, carry0, xs_in)
    return Trajectory(x=xs.reshape(K, STATE_DIM), u=us.reshape(K, 2), w_com=w_com, est=est, delay=tau, u_plan=U, u_prior=u_prior,
                      l=final.l, done=final.done, bad=final.bad)


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
