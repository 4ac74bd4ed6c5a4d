"""Balancing robot over Wi-Fi at 1 kHz (seed 001, sections 2, 3 and 5): two loops on the runner.

Both designs are configurations of :class:`jaxnc.loop.Loop` at one rate (``N = 1``, the
fast period is the robot's 1 ms step) and replay the same pair of one-way network traces
(:mod:`jaxnc.wifi`): ``sc`` for robot -> controller packets (one measurement per step) and
``ca`` for controller -> robot packets (one command per step). The traces go into the
runner's :class:`~jaxnc.loop.Draws` as the links' delays (:func:`draws`), so every design
meets the identical network and noise.

**Model-based** (``design="model"``, section 2):

* uplink: every measurement is sent (``Periodic``); the link keeps a ring of
  ``N_buf + 2`` packets and delivers all of them (``order="all"``);
* estimator: :class:`BufferedKalman`, the buffered Kalman filter of eq. 9-15
  (:mod:`jaxnc.estimators.buffered_kf`) over the ring: at step k the slots
  ``t = k - N_buf .. k - 1`` with ``gamma_t^k`` = "packet t has arrived by k"; a
  measurement later than ``N_buf`` steps is lost. It returns ``x_{k|k-1}`` and
  propagates with the commands the controller sent for each step (eq. 14);
* controller: :class:`LeadFeedback` predicts ``lead`` steps along its plan of the
  commands already sent and sends ``u_{k+lead} = sat(L (x_{k+lead} - x_ref))`` stamped
  ``k + lead`` (eq. 16; ``L`` hold-aware, eq. 17-19, or plain LQR);
* actuator: :class:`~jaxnc.loop.PacketActuator` with one action per packet: the
  command stamped k if it arrived in time (``theta_k^k = 1``, delay <= ``lead``),
  otherwise hold the last applied (eq. 4) or zero. In the first ``lead`` steps no
  command exists yet and it applies 0.

**Emulation** (``design="emulation"``, eq. 5 and section 5): no time stamps. Both links
use ``order="arrival"``: the receiver takes whatever arrives now, even an older packet
than the one it holds (a packet later than ``ring - 1`` steps is lost: its slot of the
ring is reused). :class:`DirtyDerivative` holds the most recently arrived
measurement (eq. 5) and gets the rates by *simple differentiation* (``derivative="simple"``,
the default: the paper's "simple differentiation of the corresponding angular
measurements", section 5), the backward difference of the held measurement over one
period, ``(zbar_k - zbar_{k-1}) / Ts``, or, as an option (``derivative="filtered"``), by a
first-order ("dirty") derivative with time constant ``tau_d``. With nothing new arriving
the held measurement does not change and the simple difference is 0; the next arrival's
whole change since the last one is divided by one period (the observer has no time
stamps and detects no loss, section 2). :class:`LeadFeedback` with
``lead = 0`` applies the LQR designed for the ideal loop; :class:`ArrivalHold` applies the
most recently arrived command and holds it (0 before the first).

Start-up: both estimators know the first measurement ``y_0`` at k = 0 (a handshake), the
robot at rest: the filter's prior mean is ``C' y_0``, the observer holds ``y_0``.

Scenario (section 5): initial tilt 5 deg, wheel-angle step at 15 s for a 0.1 m
translation (:class:`StepReference`). A run *falls* when |theta| exceeds ``tilt_limit``
(30 deg) or the state is not finite; the runner's :class:`~jaxnc.loop.Monitor` freezes
the plant at its last state from then on (divergence is data, never an exception).
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc import wifi
from jaxnc._validate import check_int, check_nonneg, check_positive, check_range
from jaxnc.controllers.hold_lq import dlqr, hold_lq_gain
from jaxnc.estimators.buffered_kf import BufferedKF, BufferedKFState, bkf_estimate, bkf_init, bkf_push
from jaxnc.estimators.ekf import Gaussian
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.plants.balancing import Balancing

__all__ = ["DESIGNS", "DERIVATIVES", "W_LQ", "U_LQ", "SEVERITIES", "NOISE_LEVELS", "Robot", "StepReference",
           "BufferedKalman", "DirtyDerivative", "LeadFeedback", "ArrivalHold", "balancing_loop", "draws", "traces",
           "simulate", "reference", "metrics", "run", "run_seed", "Metrics", "KF_TILT_NOISES", "SWEEP_AXES", "delay_law", "sweep_channel",
           "MAX_DELAY_INDEX"]

DESIGNS = ("model", "emulation")
DERIVATIVES = ("simple", "filtered")   # the emulation observer's rates (DirtyDerivative)
KF_TILT_NOISES = ("design", "sensor")   # the model-based filter's tilt variance R[1, 1] (balancing_loop)
# LQ weights: 0.5 rad of wheel angle, 0.05 rad of tilt, 5 and 0.5 rad/s, 100 rad/s^2 of input
W_LQ = np.diag([1 / 0.5**2, 1 / 0.05**2, 1 / 5.0**2, 1 / 0.5**2])
U_LQ = np.array([[1 / 100.0**2]])
_F32 = jnp.float32


# ----------------------------------------------------------------------------- plant


@_dataclass
class Robot(nc.AbstractPlant):
    """The nonlinear robot of :mod:`jaxnc.plants.balancing` as a loop plant.

    ``x = (delta, theta, delta', theta')``, ``u`` float[1] (wheel acceleration),
    ``w`` float[2] (servo error, tilt acceleration; rad/s^2), measurement
    ``z = (encoder-quantised delta, theta + e)`` (``v[0]`` unused: the encoder's error is
    its quantisation): with the robot's ``tilt_sensor="complementary"`` ``e = v[1]``, the
    complementary filter's error in rad (:func:`draws` draws the sequence with
    :meth:`~jaxnc.plants.balancing.Balancing.tilt_error`), with ``"white"``
    ``e = sigma_theta v[1]``, ``v[1]`` standard normal. Starts at rest with tilt
    ``theta0`` (rad).
    """

    robot: Balancing
    theta0: Any

    state_dim = 4
    input_dim = 1
    noise_dim = 2
    output_dim = 2

    def dynamics(self, x, u, w):
        return self.robot.dynamics(x, u, w)

    def measure(self, x, v):
        return self.robot.measure(x, v[1])

    def process_std(self):
        return jnp.stack([self.robot.w_servo, self.robot.w_theta]).astype(_F32)

    def measurement_std(self):
        # v[1] in units of sigma_theta (white), or in rad (complementary: the runner's own
        # draws would give a white error of the filter's stationary std; draws() colours it)
        s = 1.0 if self.robot.tilt_sensor == "white" else self.robot.tilt_error_std()
        return jnp.asarray([0.0, s], _F32)

    def init(self, key):
        th = jnp.asarray(self.theta0, _F32)
        return jnp.stack([0.0 * th, th, 0.0 * th, 0.0 * th])


@_dataclass
class StepReference:
    """Wheel-angle step of ``step_m`` metres (``step_m / r`` rad) at ``t_step`` seconds:
    ``x_ref(k) = (d(k), 0, 0, 0)`` at step k of period ``Ts`` (static)."""

    step_m: Any
    t_step: Any
    r: Any
    Ts: float = _static(1e-3)

    def wheel(self, k):
        """float[...]: the wheel-angle reference at steps ``k`` (int)."""
        on = jnp.asarray(k).astype(_F32) * self.Ts >= self.t_step
        return jnp.where(on, self.step_m / self.r, 0.0)

    def __call__(self, k):
        d = self.wheel(k)
        return jnp.stack([d, 0.0 * d, 0.0 * d, 0.0 * d])


# ----------------------------------------------------------------------------- estimators


class BufferedKalmanState(NamedTuple):
    buf: BufferedKFState   # base x_{k-N|k-N-1} and the slots t = k-N .. k-1
    pred: Gaussian         # x_{k|k-1}, the estimate at this step
    next_base: Gaussian    # x_{k-N+1|k-N}, the base after this step


@_dataclass
class BufferedKalman(nc.AbstractEstimator):
    """Buffered Kalman filter (seed 001 eq. 9-15) over the uplink's ring, one rate (N = 1).

    At step k it re-runs the slots ``t = k - kf.N .. k - 1`` (:func:`bkf_estimate`), using
    the measurement of slot t where its packet has arrived by k (``Inbox.arrived`` and
    the stamp t in the ring), and returns ``x_{k|k-1}``; then it drops the oldest slot and
    appends step k with the command the controller sent for it (``inputs="believed"``,
    eq. 14). The uplink's capacity must be >= ``kf.N + 1``. At k = 0 the prior mean is
    ``C' y_0`` (the first measurement, robot at rest) with covariance ``cov0``.

    Attributes: kf, the :class:`~jaxnc.estimators.buffered_kf.BufferedKF` (model and
    buffer length); cov0 float[n, n].
    """

    kf: BufferedKF
    cov0: Any

    inputs = "believed"

    def init(self, ctx) -> BufferedKalmanState:
        if ctx.N != 1:
            raise ValueError(f"BufferedKalman runs at one rate: the loop's N must be 1, got {ctx.N}")
        n, p, m = ctx.state_dim, ctx.output_dim, ctx.input_dim
        buf = bkf_init(jnp.zeros((n,), _F32), jnp.asarray(self.cov0, _F32), self.kf.N, p, m)
        return BufferedKalmanState(buf, buf.base, buf.base)

    def correct(self, state: BufferedKalmanState, inbox: nc.Inbox, k):
        buf = state.buf
        C = inbox.stamp.shape[0]
        if C < self.kf.N + 1:
            raise ValueError(f"BufferedKalman needs an uplink capacity >= N_buf + 1 = {self.kf.N + 1}, got {C}")
        idx = jnp.mod(buf.t, C)
        y = inbox.data[idx]
        gamma = inbox.arrived[idx] & (inbox.stamp[idx] == buf.t)
        start = self.kf.C.T @ inbox.data[0]
        base = buf.base._replace(mean=jnp.where(k == 0, start, buf.base.mean))
        buf = buf._replace(base=base, y=y)
        pred, next_base = bkf_estimate(self.kf, buf, gamma)
        return BufferedKalmanState(buf, pred, next_base), pred.mean

    def predict(self, state: BufferedKalmanState, u_applied, u_believed, k) -> BufferedKalmanState:
        p = state.buf.y.shape[1]
        buf = bkf_push(state.buf, state.next_base, jnp.zeros((p,), _F32), u_believed[0], k)
        return state._replace(buf=buf)


class DirtyDerivativeState(NamedTuple):
    z: jax.Array      # float[p] the held measurement
    rate: jax.Array   # float[p] its filtered derivative


@_dataclass
class DirtyDerivative(nc.AbstractEstimator):
    """The differentiating observer of the emulation design (seed 001 eq. 5 and section 5).

    Holds the newest delivered measurement ``zbar`` (with the uplink's ``order="arrival"``,
    the most recently arrived) and filters its difference,
    ``r_k = a r_{k-1} + (1 - a) (zbar_k - zbar_{k-1}) / Ts``, ``a = exp(-Ts / tau_d)``.
    ``tau_d = 0`` gives ``a = 0``, the simple differentiation of section 5,
    ``r_k = (zbar_k - zbar_{k-1}) / Ts`` (0 on a step where nothing arrives; an arrival
    after a gap divides the whole change by one period). The estimate is ``(zbar, r)``
    (for the robot: delta, theta and their rates). At k = 0 it holds ``y_0`` (``r_0 = 0``).

    Attributes: tau_d (s, >= 0); Ts, static period (s).
    """

    tau_d: Any
    Ts: float = _static(1e-3)

    inputs = "applied"

    def __post_init__(self):
        check_nonneg("DirtyDerivative.tau_d", self.tau_d)
        check_positive("DirtyDerivative.Ts", self.Ts)

    def init(self, ctx) -> DirtyDerivativeState:
        z = jnp.zeros((ctx.output_dim,), _F32)
        return DirtyDerivativeState(z, z)

    def correct(self, state: DirtyDerivativeState, inbox: nc.Inbox, k):
        prev = jnp.where(k == 0, inbox.data[0], state.z)
        z, _, w = inbox.newest()
        z = jnp.where(w > 0.5, z, prev)
        tau = jnp.asarray(self.tau_d, _F32)
        a = jnp.where(tau > 0, jnp.exp(-self.Ts / jnp.maximum(tau, 1e-9)), 0.0)
        rate = a * state.rate + (1.0 - a) * (z - prev) / self.Ts
        return DirtyDerivativeState(z, rate), jnp.concatenate([z, rate])

    def predict(self, state, u_applied, u_believed, k):
        return state


# ----------------------------------------------------------------------------- controller


@_dataclass
class LeadFeedback(nc.AbstractController):
    """State feedback on the estimate predicted ``lead`` steps ahead (seed 001 eq. 16).

    ``x_{k+lead} = A^lead xhat_k + sum_i A^(lead-1-i) B u_{k+i}`` along the plan of the
    commands already sent for steps ``k .. k+lead-1`` (the controller's state, zeros
    before the first), then ``u_{k+lead} = clip(gain (x_{k+lead} - x_ref(k+lead)),
    -u_max, u_max)`` is sent in a packet of one action stamped ``k + lead`` and appended
    to the plan. ``lead = 0``: ``u_k = clip(gain (xhat_k - x_ref(k)))`` stamped k.

    Attributes: gain float[m, n] (u = gain (x - x_ref)); A float[n, n], B float[n, m],
    the model of the prediction; reference, a :class:`StepReference`; u_max (> 0); lead,
    static int >= 0.
    """

    gain: Any
    A: Any
    B: Any
    reference: StepReference
    u_max: Any
    lead: int = _static(2)

    horizon = 1

    def __post_init__(self):
        check_int("LeadFeedback.lead", self.lead, 0, 50)
        check_positive("LeadFeedback.u_max", self.u_max)

    def init(self, ctx):
        return jnp.zeros((self.lead,), _F32)

    def step(self, plan, xhat, fresh, k, ctx):
        xh = xhat
        for i in range(self.lead):
            xh = self.A @ xh + self.B[:, 0] * plan[i]
        u = jnp.clip((self.gain @ (xh - self.reference(k + self.lead)))[0], -self.u_max, self.u_max)
        if self.lead:
            plan = jnp.concatenate([plan[1:], u[None]])
        stamp = (k * ctx.N + self.lead).astype(jnp.int32)
        return plan, nc.Packet(u[None, None], stamp), jnp.ones((), _F32)


# ----------------------------------------------------------------------------- actuator


@_dataclass
class ArrivalHold(nc.AbstractActuator):
    """Applies the action of the packet delivered last (with ``order="arrival"``, the most
    recently arrived, whatever its stamp) and holds it; 0 before the first. No time stamps
    (the emulation design)."""

    def init(self, ctx):
        return jnp.zeros((ctx.input_dim,), _F32)

    def receive(self, u, inbox: nc.Inbox):
        data, _, w = inbox.newest()
        return jnp.where(w > 0.5, data[0], u)

    def output(self, u, t):
        return u, u                 # (state, action): the held action is both


# ----------------------------------------------------------------------------- configuration


def balancing_loop(design: str = "model", *, plant: Balancing | None = None, gain: str = "hold",
                   theta: float | None = None, ca: wifi.WifiChannel = wifi.NOMINAL,
                   sc: wifi.WifiChannel | None = None, hold: bool = True, N_buf: int = 10, lead: int = 2,
                   derivative: str = "simple", tau_d: float | None = None, kf_tilt: str = "design",
                   horizon_s: float = 25.0,
                   theta0_deg: float = 5.0, step_m: float = 0.1, t_step: float = 15.0,
                   tilt_limit_deg: float = 30.0, ring: int = 32) -> nc.Loop:
    """The loop of one design as a :class:`jaxnc.loop.Loop` (validated, plain Python).

    Args:
      design: ``"model"`` or ``"emulation"`` (module docstring).
      plant: the robot's parameters and tilt sensor (default
        :class:`~jaxnc.plants.balancing.Balancing`, the complementary-filter sensor).
      gain: model design, ``"hold"`` (eq. 17-19 with ``theta`` = P(command applied in
        time), by default computed from the ``ca`` channel for the given ``lead``) or
        ``"lqr"``.
      ca, sc: the controller -> robot and robot -> controller channels (``sc`` defaults
        to ``ca``): the links' delay models, which :func:`run` replays by default.
      hold: model design's actuator on a missing command: hold (True) or zero.
      N_buf: the filter's buffer (steps a measurement may be late); lead: steps of
        prediction (the stamp's lead), >= 1.
      derivative: the emulation observer's rates, ``"simple"`` (backward difference over
        one period, the paper's) or ``"filtered"`` (first-order filter of time constant
        ``tau_d``, > 0, default 0.005 s); ``tau_d`` is refused with ``"simple"``.
      kf_tilt: the model-based filter's tilt measurement variance (its R, eq. 12-13, for a
        white noise as eq. 1 assumes): ``"design"`` the robot's ``sigma_theta``^2 (0.1 deg),
        whatever the sensor; ``"sensor"`` the stationary variance of the plant's tilt
        sensor error (:meth:`~jaxnc.plants.balancing.Balancing.tilt_error_std`; the same
        as ``"design"`` for the white sensor). Neither models the complementary filter's
        correlation in time.
      ring: the emulation links' ring (a packet later than ``ring - 1`` steps is lost).
      horizon_s, theta0_deg, step_m, t_step, tilt_limit_deg: the scenario.

    Raises:
      ValueError: naming the bad argument.
    """
    plant = plant or Balancing()
    sc = ca if sc is None else sc
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {', '.join(DESIGNS)}, got {design!r}")
    if gain not in ("hold", "lqr"):
        raise ValueError(f"gain must be one of hold, lqr, got {gain!r}")
    check_positive("horizon_s", horizon_s)
    check_range("theta0_deg", theta0_deg, -45.0, 45.0)
    check_int("lead", lead, 1, 50)
    check_int("N_buf", N_buf, 1, 10_000)
    check_int("ring", ring, 2, 10_000)
    if kf_tilt not in KF_TILT_NOISES:
        raise ValueError(f"kf_tilt must be one of {', '.join(KF_TILT_NOISES)}, got {kf_tilt!r}")
    if derivative not in DERIVATIVES:
        raise ValueError(f"derivative must be one of {', '.join(DERIVATIVES)}, got {derivative!r}")
    if derivative == "simple":
        if tau_d is not None:
            raise ValueError(f"tau_d applies to derivative='filtered' only, got tau_d={tau_d!r} "
                             "with derivative='simple'")
        tau_d = 0.0
    else:
        tau_d = 0.005 if tau_d is None else tau_d
        check_positive("tau_d", tau_d)
    check_range("tilt_limit_deg", tilt_limit_deg, 0.0, 90.0, low_open=True)
    Ts = float(plant.Ts)
    steps = int(round(horizon_s / Ts))
    check_int("steps (horizon_s / Ts)", steps, 1)
    A, B, C = plant.discrete()
    K = dlqr(A, B, W_LQ, U_LQ)[0]
    f32 = lambda a: jnp.asarray(a, _F32)
    robot = Robot(plant, f32(np.deg2rad(theta0_deg)))
    ref = StepReference(f32(step_m), f32(t_step), f32(plant.r), Ts=Ts)
    bounds = np.array([np.inf, np.deg2rad(tilt_limit_deg), np.inf, np.inf], np.float32)
    common = dict(plant=robot, trigger=nc.Periodic(), monitor=nc.Monitor(bounds=bounds), N=1, steps=steps, T=Ts)
    if design == "model":
        if gain == "lqr":
            L = -K
        else:
            th = wifi.delivery_probability(ca, lead) if theta is None else float(theta)
            L = hold_lq_gain(A, B, W_LQ, U_LQ, th)[0]
        Q, R = plant.kalman_QR()
        if kf_tilt == "sensor" and plant.tilt_sensor == "complementary":
            R[1, 1] = float(plant.tilt_error_std()) ** 2
        kf = BufferedKF(f32(A), f32(B), f32(C), f32(Q), f32(R), N=N_buf)
        P0 = f32(np.diag([1e-6, np.deg2rad(10.0) ** 2, 0.1, 0.1]))
        # tau_max half a period above the last useful delay: the float32 comparison of
        # d T with tau_max never discards a packet of exactly N_buf (lead) periods
        return nc.Loop(
            **common,
            uplink=nc.Link(delay=nc.WifiModel(sc), tau_max=(N_buf + 0.5) * Ts, order="all", capacity=N_buf + 2),
            estimator=BufferedKalman(kf, P0),
            controller=LeadFeedback(f32(L), kf.A, kf.B, ref, f32(plant.u_max), lead=lead),
            downlink=nc.Link(delay=nc.WifiModel(ca), tau_max=(lead + 0.5) * Ts, order="all", capacity=lead + 2),
            actuator=nc.PacketActuator(horizon=1, capacity=lead + 1, on_exhausted="hold" if hold else "zero"))
    return nc.Loop(
        **common,
        uplink=nc.Link(delay=nc.WifiModel(sc), order="arrival", capacity=ring),
        estimator=DirtyDerivative(f32(tau_d), Ts=Ts),
        controller=LeadFeedback(f32(-K), f32(A), f32(B), ref, f32(plant.u_max), lead=0),
        downlink=nc.Link(delay=nc.WifiModel(ca), order="arrival", capacity=ring),
        actuator=ArrivalHold())


# ----------------------------------------------------------------------------- runs


def traces(key, sc_channel: wifi.WifiChannel, ca_channel: wifi.WifiChannel, steps: int):
    """The seed's pair of one-way traces (robot -> controller, controller -> robot) from
    ``fold_in(key, 1)``: int32[steps] delays in steps, ``wifi.LOST`` where lost."""
    k_sc, k_ca = jax.random.split(jax.random.fold_in(key, 1))
    return wifi.sample_trace(k_sc, sc_channel, steps), wifi.sample_trace(k_ca, ca_channel, steps)


def draws(loop: nc.Loop, sc, ca, key) -> nc.Draws:
    """The runner's :class:`~jaxnc.loop.Draws` replaying the traces ``sc``, ``ca``
    (int[>= steps], ``wifi.LOST`` = lost) as the links' delays, with the noise from ``key``
    (split in two): ``w`` float[K, 1, 2], the servo and tilt disturbances (standard normals
    times the robot's stds), and ``v`` float[K, 2] with the tilt sensor's error in
    ``v[:, 1]``: the complementary filter's error sequence in rad
    (:meth:`~jaxnc.plants.balancing.Balancing.tilt_error`), or for the ``"white"`` sensor
    a standard normal (:class:`Robot` scales it)."""
    K = loop.steps
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (K, 2), _F32) * loop.plant.process_std()[None, :]
    robot = loop.plant.robot
    if robot.tilt_sensor == "complementary":
        v = robot.tilt_error(kv, K)
        v = jnp.stack([0.0 * v, v], axis=1)
    else:
        v = jax.random.normal(kv, (K,), _F32)
        v = jnp.stack([0.0 * v, v], axis=1) * loop.plant.measurement_std()[None, :]
    sc = jnp.asarray(sc, jnp.int32)[:K]
    ca = jnp.asarray(ca, jnp.int32)[:K]
    return nc.Draws(w.reshape(K, 1, 2), v, nc.LinkDraws(sc), nc.LinkDraws(ca), key)


def simulate(loop: nc.Loop, sc, ca, key) -> nc.Trajectory:
    """One run replaying the one-way traces ``sc``, ``ca`` (int32, ``wifi.LOST`` = lost; at
    least ``loop.steps`` long); ``key`` draws the plant and sensor noise only
    (:func:`draws`). Returns the runner's :class:`~jaxnc.loop.Trajectory`: ``x`` float[K, 4]
    true state before each step, ``u`` float[K, 1] applied, ``xhat`` the controller's
    estimate, ``failed`` (fallen)."""
    return nc.simulate(loop, key, draws(loop, sc, ca, key))


class Metrics(NamedTuple):
    upright: jax.Array        # bool
    tilt_rms_deg: jax.Array   # RMS tilt over the run (inf when fallen)
    track_rms_mm: jax.Array   # RMS position error over the last 5 s (inf when fallen)
    tilt_max_deg: jax.Array


def reference(loop: nc.Loop) -> jax.Array:
    """float[K]: the wheel-angle reference (rad) at each step of the run."""
    return loop.controller.reference.wheel(jnp.arange(loop.steps, dtype=jnp.int32))


def metrics(loop: nc.Loop, tr: nc.Trajectory) -> Metrics:
    """Upright flag, tilt RMS (deg), RMS position error over the last 5 s (mm), max tilt."""
    r = loop.plant.robot.r
    th = tr.x[:, 1]
    err = r * (tr.x[:, 0] + th) - r * reference(loop)
    tail = int(round(5.0 / loop.T))
    inf = jnp.float32(jnp.inf)
    up = ~tr.failed
    return Metrics(
        upright=up,
        tilt_rms_deg=jnp.where(up, jnp.rad2deg(jnp.sqrt(jnp.mean(th**2))), inf),
        track_rms_mm=jnp.where(up, 1e3 * jnp.sqrt(jnp.mean(err[-tail:] ** 2)), inf),
        tilt_max_deg=jnp.rad2deg(jnp.max(jnp.abs(th))))


def run(loop: nc.Loop, key, sc_channel: wifi.WifiChannel | None = None,
        ca_channel: wifi.WifiChannel | None = None) -> Metrics:
    """Metrics of one seed: network traces from ``fold_in(key, 1)`` (by default from the
    loop's own channels), noise from ``fold_in(key, 2)``. Common random numbers: every
    design run with the same key and channels sees the same network and noise."""
    sc_channel = loop.uplink.delay.channel if sc_channel is None else sc_channel
    ca_channel = loop.downlink.delay.channel if ca_channel is None else ca_channel
    sc, ca = traces(key, sc_channel, ca_channel, loop.steps)
    return metrics(loop, simulate(loop, sc, ca, jax.random.fold_in(key, 2)))


def run_seed(key, loop: nc.Loop) -> Metrics:
    """:func:`run` with the key first and the loop's channels, for
    ``montecarlo.run_batched(run_seed, keys, args=(loop,))`` (one compilation per design)."""
    return run(loop, key)


def _pmf(d: dict, size: int = 19) -> np.ndarray:
    p = np.zeros(size, np.float32)
    for k, q in d.items():
        p[k] = q
    return p / p.sum()


# Network severities of the experiment (both directions alike).  "nominal" is the Table 1
# fit; "loss" adds long deep bursts (400 ms at 90 % loss, about one a second of good
# regime: one-way loss 29.6 %; 200 ms until the severity sweep, docs/balancing.md);
# "delay" moves the one-way delay law to a median of 7 steps (loop-back ~12).
SEVERITIES = {
    "nominal": wifi.NOMINAL,
    "loss": dataclasses.replace(wifi.NOMINAL, p_gb=1e-3, p_bg=1 / 400, loss_bad=0.9),
    "delay": dataclasses.replace(wifi.NOMINAL, delay_pmf=_pmf(
        {1: .05, 2: .1, 3: .1, 4: .1, 5: .1, **{k: .55 / 13 for k in range(6, 19)}})),
}

# The three noise levels of section 4 / Fig. 5 (both directions alike). "no noise" is the
# Table 1 fit; the paper gives no statistics for -21 and -19 dBm ("a small degradation"),
# so the interferer's probability of spoiling an attempt (wifi.interfered: one retry, a
# step later; lost if both attempts are spoilt) is ours: 0.1 and 0.2.
NOISE_LEVELS = {
    "no noise": wifi.NOMINAL,
    "-21 dBm": wifi.interfered(wifi.NOMINAL, 0.1),
    "-19 dBm": wifi.interfered(wifi.NOMINAL, 0.2),
}


# ----------------------------------------------------------------------------- severity sweep

# The severity sweep (experiment ``balancing-sweep``, docs/balancing.md): one network
# parameter at a time made harsher, both directions alike. The two loss axes pass through
# the *loss* severity (the other burst parameters at its values), the delay axis through
# *nominal* (lambda = 0) and *delay* (lambda = 1). Per axis: (what it varies, default
# points, the main table's severity on it, the former *loss* severity's value on it or
# None: 200 ms bursts until the sweep showed it at the emulation design's transition).
_LOSS = SEVERITIES["loss"]
SWEEP_AXES = {
    "burst_length": (f"mean burst length 1/p_bg (packets = ms; p_gb = {_LOSS.p_gb:g}, loss_bad = {_LOSS.loss_bad:g})",
                     (25.0, 50.0, 100.0, 200.0, 400.0, 800.0, 1600.0), 1.0 / _LOSS.p_bg, 200.0),
    "burst_loss": (f"loss in a burst, loss_bad (1/p_bg = {1 / _LOSS.p_bg:g} ms, p_gb = {_LOSS.p_gb:g})",
                   (0.23, 0.5, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0), _LOSS.loss_bad, None),
    "delay": ("delay-law index lambda (0: Table-1 fit, 1: the delay severity, > 1: stretched)",
              (0.0, 0.15, 0.3, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75), 1.0, None),
}
#: the largest delay-law index: its longest delay, 1 + 17 lambda steps, stays within the
#: emulation links' ring (31 steps)
MAX_DELAY_INDEX = 1.75


def delay_law(lam: float) -> np.ndarray:
    """float32[D]: the one-way delay pmf of index ``lam`` (steps), both directions.

    ``0 <= lam <= 1``: the mixture ``(1 - lam) p_nominal + lam p_delay`` of the Table-1
    fit and the *delay* severity's law (exactly each at 0 and 1). ``lam > 1``: the delay
    severity's law stretched about one step, a delay d becoming ``1 + lam (d - 1)`` with
    its mass split linearly between the two neighbouring whole steps (the median grows
    from 7 steps at 1 to 11 at 1.75, the longest delay from 18 to 31 steps).

    Raises:
      ValueError: ``lam`` outside [0, MAX_DELAY_INDEX].
    """
    check_range("lambda (delay-law index)", lam, 0.0, MAX_DELAY_INDEX)
    lam = float(lam)
    p0 = np.asarray(SEVERITIES["nominal"].delay_pmf, np.float64)
    p1 = np.asarray(SEVERITIES["delay"].delay_pmf, np.float64)
    if lam <= 1.0:
        return ((1.0 - lam) * p0 + lam * p1).astype(np.float32)
    d = 1.0 + lam * (np.arange(p1.size) - 1.0)
    out = np.zeros(int(np.ceil(d[-1])) + 1)
    for q, x in zip(p1[1:], d[1:]):        # p1[0] = 0 (no zero delay)
        lo = int(np.floor(x))
        out[lo] += q * (1.0 - (x - lo))
        if x > lo:
            out[lo + 1] += q * (x - lo)
    return (out / out.sum()).astype(np.float32)


def sweep_channel(axis: str, value: float) -> wifi.WifiChannel:
    """The channel of point ``value`` on sweep axis ``axis`` (:data:`SWEEP_AXES`):
    ``burst_length`` (1/p_bg in packets, >= 1) and ``burst_loss`` (loss_bad in [0, 1]) from
    the *loss* severity, ``delay`` (:func:`delay_law`) from the Table-1 fit.

    Raises:
      ValueError: an unknown axis or a value outside its range, naming it.
    """
    if axis not in SWEEP_AXES:
        raise ValueError(f"sweep axis must be one of {', '.join(SWEEP_AXES)}, got {axis!r}")
    if axis == "burst_length":
        check_range("burst_length (1/p_bg, packets)", value, 1.0, 1e6)
        return dataclasses.replace(SEVERITIES["loss"], p_bg=1.0 / float(value))
    if axis == "burst_loss":
        check_range("burst_loss (loss_bad)", value, 0.0, 1.0)
        return dataclasses.replace(SEVERITIES["loss"], loss_bad=float(value))
    return dataclasses.replace(SEVERITIES["nominal"], delay_pmf=delay_law(value))
