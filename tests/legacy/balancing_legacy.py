# Test-only reference: the hand-written seed-001 loops as they were before the port onto
# jaxnc.loop (jaxnc/schemes/balancing.py at commit 8da48da), kept verbatim below for the
# equality tests in tests/test_balancing_runner.py.
"""Balancing robot over Wi-Fi at 1 kHz (seed 001, sections 2, 3 and 5): two closed loops.

Both loops replay the same pair of one-way network traces (``jaxnc.wifi``): ``sc`` for
robot -> controller packets (one measurement per step) and ``ca`` for controller ->
robot packets (one command per step), so every design meets the identical network.

**Model-based** (section 2): the controller runs the buffered Kalman filter (eq. 9-15,
buffer ``N_buf``) to get ``x_{k|k-1}``, predicts ``lead`` steps ahead with the commands
already sent, and sends ``u_{k+lead} = L (x_{k+lead} - x_ref)`` stamped ``k + lead``
(eq. 16; ``L`` hold-aware, eq. 17-19, or plain LQR).  The actuator applies the command
stamped ``k`` if it arrived in time (``theta_k^k = 1``), otherwise it holds the last one
(eq. 4) or applies zero (zero strategy); out-of-time packets are discarded.  The filter
assumes the stamped commands were applied (eq. 14).

**Emulation** (section 2, eq. 5; section 5): no time stamps.  The controller uses the
most recently arrived measurement, held when nothing new arrives (eq. 5), gets the rates
by differentiating it (a first-order "dirty" derivative, time constant ``tau_d``; with
``tau_d = 0`` the plain difference) and applies the LQR designed for the ideal loop.  The
actuator applies the most recently arrived command and holds it.

Scenario (section 5): initial tilt 5 deg, wheel-angle step at 15 s for a 0.1 m
translation.  A run *falls* when |theta| exceeds ``tilt_limit`` (30 deg) at any step;
the plant is frozen from then on (divergence is data, never an exception).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import wifi
from jaxnc._validate import check_int, check_nonneg, check_positive, check_range
from jaxnc.controllers.hold_lq import dlqr, hold_lq_gain
from jaxnc.estimators.buffered_kf import BufferedKF, bkf_estimate, bkf_init, bkf_push
from jaxnc.plants.balancing import Balancing

DESIGNS = ("model", "emulation")
# LQ weights: 0.5 rad of wheel angle, 0.05 rad of tilt, 5 and 0.5 rad/s, 100 rad/s^2 of input
W_LQ = np.diag([1 / 0.5**2, 1 / 0.05**2, 1 / 5.0**2, 1 / 0.5**2])
U_LQ = np.array([[1 / 100.0**2]])
_BIG = 2**30


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BalancingLoop:
    """One closed-loop configuration; build it with :func:`balancing_loop`."""

    plant: Balancing
    kf: BufferedKF
    L: jax.Array            # (1, 4) model-based gain, u = L (x - x_ref)
    K: jax.Array            # (1, 4) LQR gain of the emulation design, u = -K (x - x_ref)
    P0: jax.Array           # (4, 4) prior covariance of the filter
    tau_d: jax.Array        # differentiating observer time constant, s
    theta0: jax.Array       # initial tilt, rad
    step_m: jax.Array       # translation of the reference step, m
    t_step: jax.Array       # time of the step, s
    tilt_limit: jax.Array   # fallen when |theta| exceeds this, rad
    design: str = dataclasses.field(default="model", metadata=dict(static=True))
    hold: bool = dataclasses.field(default=True, metadata=dict(static=True))
    lead: int = dataclasses.field(default=2, metadata=dict(static=True))
    ring: int = dataclasses.field(default=32, metadata=dict(static=True))
    steps: int = dataclasses.field(default=25_000, metadata=dict(static=True))

    def __post_init__(self):
        if self.design not in DESIGNS:
            raise ValueError(f"design must be one of {', '.join(DESIGNS)}, got {self.design!r}")
        check_int("lead", self.lead, 1, 50)
        check_int("ring", self.ring, 2, 10_000)
        check_int("steps", self.steps, 1)
        check_nonneg("tau_d", self.tau_d)
        check_range("tilt_limit", self.tilt_limit, 0.0, np.pi / 2, low_open=True)


def balancing_loop(design: str = "model", *, plant: Balancing | None = None, gain: str = "hold",
                   theta: float | None = None, ca: wifi.WifiChannel = wifi.NOMINAL, hold: bool = True,
                   N_buf: int = 10, lead: int = 2, tau_d: float = 0.005, horizon_s: float = 25.0,
                   theta0_deg: float = 5.0, step_m: float = 0.1, t_step: float = 15.0,
                   tilt_limit_deg: float = 30.0, ring: int = 32) -> BalancingLoop:
    """Validated configuration (plain Python, before tracing).

    ``gain``: ``"hold"`` (eq. 17-19 with ``theta`` = P(command applied in time), by default
    computed from the ``ca`` channel model for the given ``lead``) or ``"lqr"``.
    """
    plant = plant or Balancing()
    if gain not in ("hold", "lqr"):
        raise ValueError(f"gain must be one of hold, lqr, got {gain!r}")
    check_positive("horizon_s", horizon_s)
    check_range("theta0_deg", theta0_deg, -45.0, 45.0)
    A, B, C = plant.discrete()
    Q, R = plant.kalman_QR()
    K = dlqr(A, B, W_LQ, U_LQ)[0]
    if gain == "lqr":
        L = -K
    else:
        th = wifi.delivery_probability(ca, lead) if theta is None else float(theta)
        L = hold_lq_gain(A, B, W_LQ, U_LQ, th)[0]
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    kf = BufferedKF(f32(A), f32(B), f32(C), f32(Q), f32(R), N=N_buf)
    return BalancingLoop(
        plant=plant, kf=kf, L=f32(L), K=f32(K),
        P0=f32(np.diag([1e-6, np.deg2rad(10.0) ** 2, 0.1, 0.1])),
        tau_d=f32(tau_d), theta0=f32(np.deg2rad(theta0_deg)), step_m=f32(step_m), t_step=f32(t_step),
        tilt_limit=f32(np.deg2rad(tilt_limit_deg)), design=design, hold=hold, lead=lead, ring=ring,
        steps=int(round(horizon_s / plant.Ts)))


class Trajectory(NamedTuple):
    x: jax.Array          # (steps, 4) true state before each step
    u: jax.Array          # (steps,) applied wheel acceleration
    xhat: jax.Array       # (steps, 4) the controller's state estimate at k
    ref: jax.Array        # (steps,) wheel-angle reference, rad
    fallen: jax.Array     # bool: |theta| exceeded the limit


class Metrics(NamedTuple):
    upright: jax.Array        # bool
    tilt_rms_deg: jax.Array   # RMS tilt over the run (inf when fallen)
    track_rms_mm: jax.Array   # RMS position error over the last 5 s (inf when fallen)
    tilt_max_deg: jax.Array


def _noises(loop: BalancingLoop, key):
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (loop.steps, 2), jnp.float32) * jnp.stack([loop.plant.w_servo, loop.plant.w_theta]).astype(jnp.float32)[None, :]
    v = jax.random.normal(kv, (loop.steps,), jnp.float32)
    return w, v


def _ref(loop: BalancingLoop, k):
    on = k.astype(jnp.float32) * loop.plant.Ts >= loop.t_step
    d = jnp.where(on, loop.step_m / loop.plant.r, 0.0)
    return jnp.stack([d, 0.0 * d, 0.0 * d, 0.0 * d])


def _x0(loop):
    return jnp.stack([0.0 * loop.theta0, loop.theta0, 0.0 * loop.theta0, 0.0 * loop.theta0])


def _advance(loop, x, u, w, fallen):
    x_new = loop.plant.dynamics(x, u[None], w)
    fallen = fallen | (jnp.abs(x_new[1]) > loop.tilt_limit) | ~jnp.all(jnp.isfinite(x_new))
    return jnp.where(fallen, x, x_new), fallen


def _clip(loop, u):
    return jnp.clip(u, -loop.plant.u_max, loop.plant.u_max)


def _simulate_model(loop: BalancingLoop, sc, ca, key) -> Trajectory:
    kf, N = loop.kf, loop.kf.N
    w, v = _noises(loop, key)
    a_sc = jnp.concatenate([jnp.full(N, _BIG, jnp.int32), wifi.arrival_steps(sc, max_delay=N)])
    # theta_k^k: the command stamped k was sent at k - lead and arrived within lead steps
    ok = (ca >= 0) & (ca <= loop.lead)
    theta_k = jnp.concatenate([jnp.ones(loop.lead, bool), ok])[: loop.steps]
    x0 = _x0(loop)
    y0 = loop.plant.measure(x0, v[0])
    state0 = bkf_init(jnp.stack([y0[0], y0[1], 0.0 * y0[0], 0.0 * y0[0]]), loop.P0, N, 2, 1)
    carry0 = (x0, state0, jnp.zeros(loop.lead, jnp.float32), jnp.float32(0.0), jnp.asarray(False))

    def step(carry, inp):
        x, st, plan, u_prev, fallen = carry
        k, wk, vk, th = inp
        y = loop.plant.measure(x, vk)
        avail = jax.lax.dynamic_slice(a_sc, (k,), (N,)) <= k
        pred, nb = bkf_estimate(kf, st, avail)
        xh = pred.mean
        for i in range(loop.lead):                       # x_{k+lead|k-1} along the sent plan
            xh = kf.A @ xh + kf.B[:, 0] * plan[i]
        u_new = _clip(loop, (loop.L @ (xh - _ref(loop, k + loop.lead)))[0])
        u_app = jnp.where(th, plan[0], u_prev if loop.hold else 0.0)
        x_next, fallen = _advance(loop, x, u_app, wk, fallen)
        st = bkf_push(st, nb, y, plan[:1], k)
        plan = jnp.concatenate([plan[1:], u_new[None]])
        return (x_next, st, plan, u_app, fallen), (x, u_app, pred.mean, _ref(loop, k)[0])

    ks = jnp.arange(loop.steps, dtype=jnp.int32)
    (_, _, _, _, fallen), (xs, us, xh, ref) = jax.lax.scan(step, carry0, (ks, w, v, theta_k))
    return Trajectory(xs, us, xh, ref, fallen)


def _simulate_emulation(loop: BalancingLoop, sc, ca, key) -> Trajectory:
    w, v = _noises(loop, key)
    R = loop.ring
    last_sc = wifi.newest_arrival(sc, max_delay=R - 1)
    last_ca = wifi.newest_arrival(ca, max_delay=R - 1)
    a = jnp.exp(-loop.plant.Ts / jnp.maximum(loop.tau_d, 1e-9))
    a = jnp.where(loop.tau_d > 0, a, 0.0)
    x0 = _x0(loop)
    y0 = loop.plant.measure(x0, v[0])
    yring = jnp.zeros((R, 2), jnp.float32)               # yring[i] = y_{k-i}
    uring = jnp.zeros((R,), jnp.float32)                 # uring[i] = u_{k-i}
    carry0 = (x0, yring, uring, y0, jnp.zeros(2, jnp.float32), jnp.float32(0.0), jnp.asarray(False))

    def step(carry, inp):
        x, yring, uring, ybar, vel, u_prev, fallen = carry
        k, wk, vk, ls, lc = inp
        y = loop.plant.measure(x, vk)
        yring = jnp.concatenate([y[None], yring[:-1]])
        new = ls >= 0
        ybar_new = jnp.where(new, yring[jnp.clip(k - ls, 0, R - 1)], ybar)          # eq. (5)
        vel = a * vel + (1.0 - a) * (ybar_new - ybar) / loop.plant.Ts
        xt = jnp.stack([ybar_new[0], ybar_new[1], vel[0], vel[1]])
        u = _clip(loop, -(loop.K @ (xt - _ref(loop, k)))[0])
        uring = jnp.concatenate([u[None], uring[:-1]])
        u_app = jnp.where(lc >= 0, uring[jnp.clip(k - lc, 0, R - 1)], u_prev if loop.hold else 0.0)
        x_next, fallen = _advance(loop, x, u_app, wk, fallen)
        return (x_next, yring, uring, ybar_new, vel, u_app, fallen), (x, u_app, xt, _ref(loop, k)[0])

    ks = jnp.arange(loop.steps, dtype=jnp.int32)
    out, (xs, us, xt, ref) = jax.lax.scan(step, carry0, (ks, w, v, last_sc, last_ca))
    return Trajectory(xs, us, xt, ref, out[-1])


def simulate(loop: BalancingLoop, sc, ca, key) -> Trajectory:
    """One run replaying the one-way traces ``sc``, ``ca`` (int32, ``wifi.LOST`` = lost;
    at least ``loop.steps`` long); ``key`` draws the plant and sensor noise only."""
    sc = jnp.asarray(sc, jnp.int32)[: loop.steps]
    ca = jnp.asarray(ca, jnp.int32)[: loop.steps]
    if loop.design == "model":
        return _simulate_model(loop, sc, ca, key)
    return _simulate_emulation(loop, sc, ca, key)


def metrics(loop: BalancingLoop, tr: Trajectory) -> Metrics:
    """Upright flag, tilt RMS (deg), RMS position error over the last 5 s (mm), max tilt."""
    th = tr.x[:, 1]
    pos = loop.plant.r * (tr.x[:, 0] + th)
    err = pos - loop.plant.r * tr.ref
    tail = int(round(5.0 / loop.plant.Ts))
    inf = jnp.float32(jnp.inf)
    up = ~tr.fallen
    return Metrics(
        upright=up,
        tilt_rms_deg=jnp.where(up, jnp.rad2deg(jnp.sqrt(jnp.mean(th**2))), inf),
        track_rms_mm=jnp.where(up, 1e3 * jnp.sqrt(jnp.mean(err[-tail:] ** 2)), inf),
        tilt_max_deg=jnp.rad2deg(jnp.max(jnp.abs(th))))


def traces(key, sc_channel: wifi.WifiChannel, ca_channel: wifi.WifiChannel, steps: int):
    """The seed's pair of one-way traces (robot -> controller, controller -> robot)."""
    k_sc, k_ca = jax.random.split(jax.random.fold_in(key, 1))
    return wifi.sample_trace(k_sc, sc_channel, steps), wifi.sample_trace(k_ca, ca_channel, steps)


def run(loop: BalancingLoop, key, sc_channel=wifi.NOMINAL, ca_channel=wifi.NOMINAL) -> Metrics:
    """Metrics of one seed: network traces from ``fold_in(key, 1)``, noise from ``fold_in(key, 2)``
    (common random numbers: every design run with the same key sees the same network and noise)."""
    sc, ca = traces(key, sc_channel, ca_channel, loop.steps)
    return metrics(loop, simulate(loop, sc, ca, jax.random.fold_in(key, 2)))


def _pmf(d: dict, size: int = 19) -> np.ndarray:
    p = np.zeros(size, np.float32)
    for k, q in d.items():
        p[k] = q
    return p / p.sum()


# Network severities of the experiment (both directions alike).  "nominal" is the Table 1
# fit; "loss" adds long deep bursts (200 ms at 90 % loss, about one a second: one-way loss
# 19.5 %); "delay" moves the one-way delay law to a median of 6 steps (loop-back ~12).
SEVERITIES = {
    "nominal": wifi.NOMINAL,
    "loss": dataclasses.replace(wifi.NOMINAL, p_gb=1e-3, p_bg=1 / 200, loss_bad=0.9),
    "delay": dataclasses.replace(wifi.NOMINAL, delay_pmf=_pmf(
        {1: .05, 2: .1, 3: .1, 4: .1, 5: .1, **{k: .55 / 13 for k in range(6, 19)}})),
}
