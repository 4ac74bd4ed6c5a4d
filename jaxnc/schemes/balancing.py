"""Balancing robot over Wi-Fi at 1 kHz (seed 001, sections 2, 3 and 5): a builder of two loops.

:func:`balancing_loop` returns a :class:`jaxnc.loop.Loop` at one rate (``N = 1``, the
robot's 1 ms step) built from library parts; both links draw loss and delay from their
:class:`~jaxnc.loop.WifiModel` (:mod:`jaxnc.wifi`), the plant's noises from its stds, all
through the runner's :func:`jaxnc.loop.draw`, so two designs run with one key meet the
same network and noise (common random numbers). The plant is
:class:`~jaxnc.plants.balancing.Balancing`.

* **Model-based** (section 2): every measurement sent; uplink ``order="all"`` (ring of
  ``N_buf + 2``); :class:`~jaxnc.loop.EKF` with ``buffer=N_buf`` on the linear model, the
  buffered Kalman filter of eq. 9-15 (a measurement later than ``N_buf`` steps is lost),
  propagated with the commands sent (eq. 14); :class:`~jaxnc.loop.LeadFeedback`, the
  command for ``k + lead`` stamped ``k + lead`` (eq. 16; gain hold-aware, eq. 17-19, or
  LQR); :class:`~jaxnc.loop.PacketActuator` applies it if it arrived in time, else holds
  (eq. 4) or zeros.
* **Emulation** (eq. 5, section 5): no time stamps, both links ``order="arrival"``;
  :class:`~jaxnc.loop.DirtyDerivative` (simple difference, or filtered with ``tau_d``),
  LQR for the ideal loop (``lead = 0``), :class:`~jaxnc.loop.ArrivalHold`.

Scenario: tilt ``theta0_deg``, wheel-angle step for ``step_m`` at ``t_step`` (:class:`jaxnc.references.Step`);
a run falls when |theta| > ``tilt_limit_deg`` or the state is not finite (the Monitor freezes the plant).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc import references, wifi
from jaxnc._validate import check_bool, check_choice, check_instance, check_int, check_positive, check_range
from jaxnc.controllers.hold_lq import dlqr, hold_lq_gain
from jaxnc.plants import balancing as bmodel
from jaxnc.plants.balancing import Balancing

__all__ = ["DESIGNS", "DERIVATIVES", "KF_TILT_NOISES", "W_LQ", "U_LQ", "SEVERITIES", "NOISE_LEVELS",
           "balancing_loop", "Metrics", "metrics", "reference", "run", "SWEEP_AXES", "MAX_DELAY_INDEX",
           "delay_law", "sweep_channel"]

DESIGNS = ("model", "emulation")
DERIVATIVES = ("simple", "filtered")      # the emulation observer's rates
KF_TILT_NOISES = ("design", "sensor")     # the model-based filter's tilt variance R[1, 1]
# LQ weights: 0.5 rad of wheel angle, 0.05 rad of tilt, 5 and 0.5 rad/s, 100 rad/s^2 of input
W_LQ = np.diag([1 / 0.5**2, 1 / 0.05**2, 1 / 5.0**2, 1 / 0.5**2])
U_LQ = np.array([[1 / 100.0**2]])
# the filter's prior: at rest near upright, tilt std 10 deg (the robot starts within it)
P0 = np.diag([1e-6, np.deg2rad(10.0) ** 2, 0.1, 0.1])


def balancing_loop(design: str = "model", *, plant: Balancing | None = None, gain: str = "hold",
                   theta: float | None = None, ca: wifi.WifiChannel = wifi.NOMINAL,
                   sc: wifi.WifiChannel | None = None, hold: bool = True, N_buf: int = 10, lead: int = 2,
                   derivative: str = "simple", tau_d: float | None = None, kf_tilt: str = "design",
                   horizon_s: float = 25.0, theta0_deg: float = 5.0, step_m: float = 0.1, t_step: float = 15.0,
                   tilt_limit_deg: float = 30.0, ring: int = 32, record=("x",)) -> nc.Loop:
    """The loop of one design (module docstring), validated.

    Args:
      design: ``"model"`` or ``"emulation"``.
      plant: the robot's parameters and tilt sensor (default :class:`Balancing`, the
        complementary-filter sensor); its ``theta0`` is replaced by ``theta0_deg``.
      gain: model design, ``"hold"`` (eq. 17-19, ``theta`` = P(command in time), default
        from the ``ca`` channel and ``lead``) or ``"lqr"``.
      ca, sc: the controller -> robot and robot -> controller channels (``sc``: ``ca``).
      hold: model design's actuator on a missing command: hold (True) or zero. The
        ``"hold"`` gain is designed for the hold actuator (eq. 4, 17-19) whatever ``hold``:
        with ``hold=False`` it is not the optimal gain of the zero strategy.
      N_buf: the filter's buffer (steps a measurement may be late), >= 1; lead: steps of
        prediction (the stamp's lead), >= 1.
      derivative: the emulation observer's rates, ``"simple"`` (the paper's) or
        ``"filtered"`` (time constant ``tau_d`` > 0, default 0.005 s; refused with simple).
      kf_tilt: the filter's tilt variance (eq. 12-13): ``"design"`` ``sigma_theta^2``,
        ``"sensor"`` the tilt sensor's stationary error variance.
      ring: the emulation links' ring (a packet later than ``ring - 1`` steps is lost).
      horizon_s, theta0_deg, step_m, t_step, tilt_limit_deg: the scenario.
      record: the loop's :class:`~jaxnc.loop.Record`; it must keep ``"x"`` (the metrics').

    Returns:
      a :class:`jaxnc.loop.Loop` with ``steps = horizon_s / Ts``, ``T = Ts``.

    Raises:
      ValueError: naming the bad argument and its allowed values.
    """
    plant = Balancing() if plant is None else plant
    check_instance("plant", plant, Balancing, "a jaxnc.plants.balancing.Balancing")
    sc = ca if sc is None else sc
    for name, ch in (("ca", ca), ("sc", sc)):
        check_instance(name, ch, wifi.WifiChannel, "a jaxnc.wifi.WifiChannel")
    design, gain = check_choice("design", design, DESIGNS), check_choice("gain", gain, ("hold", "lqr"))
    kf_tilt, derivative = check_choice("kf_tilt", kf_tilt, KF_TILT_NOISES), check_choice("derivative", derivative, DERIVATIVES)
    check_positive("horizon_s", horizon_s)
    check_range("theta0_deg", theta0_deg, -45.0, 45.0)
    check_range("step_m", step_m, -10.0, 10.0)
    check_range("t_step", t_step, 0.0, None)
    check_range("tilt_limit_deg", tilt_limit_deg, 0.0, 90.0, low_open=True)
    check_int("lead", lead, 1, 50)
    check_int("N_buf", N_buf, 1, 10_000)
    check_int("ring", ring, 2, 10_000)
    check_bool("hold", hold)
    if "x" not in nc.Record.of(record).signals:
        raise ValueError(f"record must keep the signal 'x' (the metrics need it), got {record!r}")
    if theta is not None:
        check_range("theta", theta, 0.0, 1.0, low_open=True)
    if derivative == "simple" and tau_d is not None:
        raise ValueError(f"tau_d applies to derivative='filtered' only, got tau_d={tau_d!r} with derivative='simple'")
    tau_d = 0.0 if derivative == "simple" else (0.005 if tau_d is None else tau_d)
    if derivative == "filtered":
        check_positive("tau_d", tau_d)
    Ts = float(plant.Ts)
    steps = int(round(horizon_s / Ts))
    check_int("steps (horizon_s / Ts)", steps, 1)
    robot = dataclasses.replace(plant, theta0=np.float32(np.deg2rad(theta0_deg)))
    A, B, C = bmodel.discrete(plant)
    K = dlqr(A, B, W_LQ, U_LQ)[0]
    ref = references.Step(amplitude=np.array([step_m / float(plant.r), 0, 0, 0], np.float32), time=t_step)
    bounds = np.array([np.inf, np.deg2rad(tilt_limit_deg), np.inf, np.inf], np.float32)
    common = dict(plant=robot, trigger=nc.Periodic(), monitor=nc.Monitor(bounds=bounds), N=1, steps=steps, T=Ts,
                  record=record)
    model = nc.LTI(A=A, B=B, C=C, G=bmodel.noise_input(plant), T=Ts)
    u_max = np.float32(plant.u_max)
    if design == "emulation":
        return nc.Loop(**common, uplink=nc.Link(delay=nc.WifiModel(sc), order="arrival", capacity=ring),
                       estimator=nc.DirtyDerivative(np.float32(tau_d)),
                       controller=nc.LeadFeedback(K, model, ref, u_max, lead=0),
                       downlink=nc.Link(delay=nc.WifiModel(ca), order="arrival", capacity=ring),
                       actuator=nc.ArrivalHold())
    if gain == "hold":                                           # u = L x, so K = -L
        K = -hold_lq_gain(A, B, W_LQ, U_LQ, wifi.delivery_probability(ca, lead) if theta is None else theta)[0]
    _, R = bmodel.kalman_QR(plant)
    if kf_tilt == "sensor" and plant.tilt_sensor == "complementary":
        R[1, 1] = float(bmodel.tilt_error_std(plant)) ** 2
    ekf = nc.EKF(model, Q=bmodel.filter_noise_std(plant) ** 2, R=R, mean0=np.zeros(4), cov0=P0, buffer=N_buf)
    # tau_max half a period above the last useful delay (the link compares whole periods)
    return nc.Loop(
        **common,
        uplink=nc.Link(delay=nc.WifiModel(sc), tau_max=(N_buf + 0.5) * Ts, order="all", capacity=N_buf + 2),
        estimator=ekf, controller=nc.LeadFeedback(K, model, ref, u_max, lead=lead),
        downlink=nc.Link(delay=nc.WifiModel(ca), tau_max=(lead + 0.5) * Ts, order="all", capacity=lead + 2),
        actuator=nc.PacketActuator(horizon=1, capacity=lead + 1, on_exhausted="hold" if hold else "zero"))


class Metrics(NamedTuple):
    """The paper's outcomes of one run (section 5)."""

    upright: jax.Array        # bool: |theta| stayed within the limit
    tilt_rms_deg: jax.Array   # RMS tilt over the run, deg (inf when fallen)
    track_rms_mm: jax.Array   # RMS position error over the last 5 s (the whole run if shorter), mm (inf when fallen)
    tilt_max_deg: jax.Array   # max |theta|, deg
    UNITS = {"tilt_rms_deg": "deg", "track_rms_mm": "mm", "tilt_max_deg": "deg"}


def reference(loop: nc.Loop) -> jax.Array:
    """float[K]: the wheel-angle reference (rad) at each step of ``loop``'s run."""
    return references.evaluate(loop.controller.reference, loop.steps, loop.T)[:, 0]


def metrics(loop: nc.Loop, tr: nc.Trajectory) -> Metrics:
    """:class:`Metrics` of the runner's trajectory ``tr`` of ``loop`` (``tr.x`` float[K, 4]:
    the position error is ``r (delta + theta - wheel reference)``)."""
    r = loop.plant.r
    th = tr.x[:, 1]
    err = r * (tr.x[:, 0] + th - reference(loop))
    tail = min(int(round(5.0 / loop.T)), loop.steps)
    inf = jnp.float32(jnp.inf)
    up = ~tr.failed
    return Metrics(upright=up, tilt_rms_deg=jnp.where(up, jnp.rad2deg(jnp.sqrt(jnp.mean(th**2))), inf),
                   track_rms_mm=jnp.where(up, 1e3 * jnp.sqrt(jnp.mean(err[-tail:] ** 2)), inf),
                   tilt_max_deg=jnp.rad2deg(jnp.max(jnp.abs(th))))


#: the per-seed function ``run(loop, key) -> Metrics``: :func:`jaxnc.loop.run` with :func:`metrics`
run = functools.partial(nc.run, metrics=metrics)


def _pmf(d: dict, size: int = 19) -> np.ndarray:
    p = np.asarray([d.get(k, 0.0) for k in range(size)], np.float32)
    return p / p.sum()


# Network severities (both directions alike, docs/balancing.md): the Table 1 fit; long deep
# bursts (400 ms at 90 % loss, one-way loss 29.6 %); a one-way delay median of 7 steps.
SEVERITIES = {
    "nominal": wifi.NOMINAL,
    "loss": dataclasses.replace(wifi.NOMINAL, p_gb=1e-3, p_bg=1 / 400, loss_bad=0.9),
    "delay": dataclasses.replace(wifi.NOMINAL, delay_pmf=_pmf(
        {1: .05, 2: .1, 3: .1, 4: .1, 5: .1, **{k: .55 / 13 for k in range(6, 19)}})),
}
# The noise levels of section 4 / Fig. 5; the interferer's probability of spoiling an
# attempt (wifi.interfered) at -21 and -19 dBm is ours (the paper gives no statistics).
NOISE_LEVELS = {"no noise": wifi.NOMINAL, "-21 dBm": wifi.interfered(wifi.NOMINAL, 0.1),
                "-19 dBm": wifi.interfered(wifi.NOMINAL, 0.2)}

# The severity sweep (experiment balancing-sweep): per axis (what it varies, default points,
# the main table's severity on it, the earlier loss severity's value on it or None).
_LOSS = SEVERITIES["loss"]
SWEEP_AXES = {
    "burst_length": (f"mean burst length 1/p_bg (packets = ms; p_gb = {_LOSS.p_gb:g}, loss_bad = {_LOSS.loss_bad:g})",
                     (25.0, 50.0, 100.0, 200.0, 400.0, 800.0, 1600.0), 1.0 / _LOSS.p_bg, 200.0),
    "burst_loss": (f"loss in a burst, loss_bad (1/p_bg = {1 / _LOSS.p_bg:g} ms, p_gb = {_LOSS.p_gb:g})",
                   (0.23, 0.5, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0), _LOSS.loss_bad, None),
    "delay": ("delay-law index lambda (0: Table-1 fit, 1: the delay severity, > 1: stretched)",
              (0.0, 0.15, 0.3, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75), 1.0, None),
}
#: the largest delay-law index: its longest delay, 1 + 17 lambda steps, fits the emulation ring
MAX_DELAY_INDEX = 1.75


def delay_law(lam: float) -> np.ndarray:
    """float32[D]: the one-way delay pmf of index ``lam`` (steps): for ``lam <= 1`` the
    mixture ``(1 - lam) p_nominal + lam p_delay``; above, the delay law stretched about one
    step (d -> ``1 + lam (d - 1)``, mass split linearly between neighbouring steps).

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
    """The channel of point ``value`` on sweep axis ``axis`` (:data:`SWEEP_AXES`).

    Raises:
      ValueError: an unknown axis or a value outside its range, naming it.
    """
    check_choice("sweep axis", axis, tuple(SWEEP_AXES))
    if axis == "burst_length":
        check_range("burst_length (1/p_bg, packets)", value, 1.0, 1e6)
        return dataclasses.replace(SEVERITIES["loss"], p_bg=1.0 / float(value))
    if axis == "burst_loss":
        check_range("burst_loss (loss_bad)", value, 0.0, 1.0)
        return dataclasses.replace(SEVERITIES["loss"], loss_bad=float(value))
    return dataclasses.replace(SEVERITIES["nominal"], delay_pmf=delay_law(value))
