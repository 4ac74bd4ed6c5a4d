"""Seed 000 (Carbonell et al., ISA Trans. 2024), loops SR, DR, DRH and DRHE of section 4.1.

:func:`mecanum_loop` returns a :class:`jaxnc.loop.Loop`: the robot
(:class:`~jaxnc.plants.mecanum.Mecanum`, eq. 1-2, or another true plant such as
:class:`~jaxnc.plants.mecanum_mjx.MjxMecanum`), the sensor's PETC (:class:`~jaxnc.loop.Petc`,
eq. 3-4), an uplink with Bernoulli(p_sc) losses (eq. 5), the remote NUDREKF (a
:class:`~jaxnc.loop.EKF`, eq. 11-16) and controller
(:class:`~jaxnc.loop.ChainController`, section 3.3.1), a downlink with
Bernoulli(p_ca) losses and the lumped round-trip delay (:class:`~jaxnc.loop.RoundTrip`,
eq. 6-7; packets later than tau_max, default NT, discarded, so never out of order), the
actuator (:class:`~jaxnc.loop.ChainActuator`, section 2.4: packets are
prediction chains of h*N actions, the last held beyond) and the path tube
(:class:`~jaxnc.loop.PathMonitor`). The first exchange of both links is delivered.

Cases (section 4.1), all leaves of one compiled program per N:

* SR   single rate: the controller runs once per NT and its action is held (h = 1);
* DR   dual rate: N fast actions per packet (h = 1), hold the last on loss;
* DRH  dual rate + h-step prediction: h*N actions per packet (:func:`default_h`);
* DRHE DRH + PETC at the sensor (eq. 4); the other cases send every NT.

Every draw is the runner's (:func:`jaxnc.loop.draw`), so the four cases of one N meet the
same realisation. A run is *unstable* when the robot leaves a tube of 0.5 m around the
path before completing it, a state or the belief becomes non-finite, or it has not
completed the path (within 0.1 m of its end) in the horizon (1.6 x the nominal path
time + 10 s); its indexes (:func:`metrics`, eq. 21-24) are then inf.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc._validate import check_choice, check_int, check_range
from jaxnc.controllers.path_following import PathFollower
from jaxnc.estimators.sparsity import EKFStructure, detect_structure
from jaxnc.metrics import J1, J2
from jaxnc.paths import Path, get_path
from jaxnc.plants.mecanum import INPUT_DIM, OUTPUT_DIM, PROCESS_NOISE_DIM, STATE_DIM, Mecanum, MecanumNoise

CASES = ("SR", "DR", "DRH", "DRHE")
# Paper, section 4.1: delta(i) = 0.1; sigma(i) = 0.1 for the four wheel speeds, 0.05 else.
PAPER_SIGMA = (0.1, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05, 0.05, 0.05)
PAPER_DELTA = (0.1,) * 9
# Ours sigma(i) = 0 (eq. 4 allows it): with the paper's in SI units DRHE loses the path (README).
DEFAULT_SIGMA = (0.0,) * 9
PAPER_ETA, PAPER_PHI = 0.01, 0.02   # delay distribution, eq. (7), section 4.1
# The filter's wheel-speed process noise (rad/s), 15x the true 0.2: the remote side propagates
# along the actions it *sent*; with the true Q a lost control packet leaves it overconfident.
FILTER_OMEGA_STD = 3.0
P0_STD = (0.01, 0.01, 0.01, 0.02, 0.02, 0.01)   # initial estimation uncertainty (std per state)
MAX_DEV, END_TOL = 0.5, 0.1                      # m: the path tube, and completion's distance to the end
TRACK_WINDOW = 32   # path points searched per period: the robot moves at most 10 (omega_max R T = 0.1 m)

#: what a Monte-Carlo run records: what :func:`metrics` reads
METRICS_RECORD = nc.Record(signals=("sent_sc", "recv_sc"), monitor=nc.path_distance, estimator=nc.period_means_finite)
#: ... and the true states x, actions u and the belief's means after each fast period
#: (``parts["estimator"]`` [S, N, 6]): figures and the stability pass (``full=True``)
FULL_RECORD = nc.Record(signals=("x", "u", "sent_sc", "recv_sc"), monitor=nc.path_distance,
                        estimator=nc.period_means)


def default_h(case: str, N: int, dp: float, n_slow: int) -> int:
    """Prediction horizon h in slow periods: our reading of section 4.1.

    The paper asks h*N to cover the longest run of missing data. A slow period delivers
    nothing with probability q = 1 - (1 - DP)^2 (either direction lost); over n_slow
    periods the longest such run reaches r with probability about
    1 - exp(-n_slow (1 - q) q^r) (Erdos-Renyi law of runs). DRH takes h = r + 1 with that
    probability at 5 %; DRHE, whose sensor is also silent between events, at least
    hN = 100 fast periods as in the paper. SR and DR: h = 1."""
    if case in ("SR", "DR"):
        return 1
    q = 1.0 - (1.0 - dp) ** 2
    h_drh = max(1, math.ceil(math.log(-math.log(0.95) / (n_slow * (1.0 - q))) / math.log(q)) + 1) if q > 0 else 1
    return h_drh if case == "DRH" else max(math.ceil(100 / N), h_drh)


def mecanum_loop(case: str = "DRHE", N: int = 10, dp: float = 0.0, path: str | Path = "lissajous", *,
                 h: int | None = None, sigma=None, delta=None, eta: float = PAPER_ETA, phi: float = PAPER_PHI,
                 tau_max: float | None = None, noise: MecanumNoise | None = None,
                 filter_noise: MecanumNoise | None = None, plant: Mecanum | None = None,
                 follower_kw: dict | None = None, trigger_temperature: float = 0.0, horizon_s: float | None = None,
                 max_silence: int = 0, truth=None, jacobian_grad: bool = True, sparse: bool = True,
                 batch_last: bool = True, full: bool = False) -> nc.Loop:
    """Case ``case`` at multiplicity N and dropout probability DP = p_sc = p_ca = ``dp`` as a
    :class:`jaxnc.loop.Loop`, the paper's defaults (section 4.1).

    Args:
      case: SR, DR, DRH or DRHE (exact, else ignoring case). N: fast periods per slow one.
      path: a path name (:data:`jaxnc.paths.PATHS`) or a :class:`~jaxnc.paths.Path`.
      h: the horizon in slow periods (None: :func:`default_h`). sigma, delta: the PETC's
        thresholds (DRHE; scalar or 9 values). eta, phi: the delay law (eq. 7), s.
      tau_max: later control packets are discarded, in (0, NT] (default NT).
      noise: the true noise; filter_noise: the covariances the NUDREKF assumes.
      plant: the kinematic model of the estimator and controller (also the robot when
        ``truth`` is None). truth: the robot when it is another plant with the model's
        period (e.g. :func:`jaxnc.plants.mecanum_mjx.mjx_mecanum`; its ``kin`` gets the
        start pose and noise). follower_kw: :class:`PathFollower` options.
      trigger_temperature: > 0 gives the PETC a straight-through gradient.
      horizon_s: simulated time (default 1.6 x the nominal path time + 10 s).
      max_silence: DRHE's sensor also sends after this many silent slow periods (0: off;
        a time-triggered safety condition like seed 003 eq. 7, not in seed 000).
      jacobian_grad: False holds the EKF's Jacobians constant in gradients (same values).
      sparse: the EKF skips the model's structural zeros (:func:`ekf_structure`).
      batch_last: ``EKF(batch_last=True)``, the correction with the seed axis last (faster; equal
        up to float32 rounding; False: as reductions, the numbers stored before 2026-12-04).
      full: record x, u and the belief means too (:data:`FULL_RECORD`), else only what
        :func:`metrics` needs (:data:`METRICS_RECORD`).

    The case, DP, h and max_silence are leaves: every case and DP of one N share one
    compiled program when the loop is an argument (``run_batched(..., args=(loop,))``).

    Raises:
      ValueError: naming the argument and its allowed range, before anything is built.
    """
    case = check_choice("case", case, CASES)
    check_int("N", N, 1, 100)
    check_range("dp", dp, 0.0, 1.0, high_open=True)
    for name, v in (("eta", eta), ("phi", phi), ("trigger_temperature", trigger_temperature)):
        check_range(name, v, 0.0, None)
    if horizon_s is not None:
        check_range("horizon_s", horizon_s, 0.0, None, low_open=True)
    plant = plant or Mecanum()
    noise = noise or MecanumNoise()
    filter_noise = MecanumNoise(omega=FILTER_OMEGA_STD) if filter_noise is None else filter_noise
    p = path if isinstance(path, Path) else get_path(path)
    follower = PathFollower(path=p, **(follower_kw or {}))
    length = float(np.asarray(p.s)[-1])                  # p.length, read on the host
    T = float(plant.T)
    if h is None:
        h = default_h(case, N, float(dp), math.ceil(length / float(follower.V_ref) / (N * T)))
    check_int("h", h, 1, 1000)
    check_int("max_silence", max_silence, 0, 100_000)
    thresholds = {}
    for name, v, default in (("sigma", sigma, DEFAULT_SIGMA), ("delta", delta, PAPER_DELTA)):
        check_range(name, v, 0.0, None)                   # None: the default
        v = np.asarray(default if v is None else v, np.float32)
        if v.shape not in ((), (1,), (OUTPUT_DIM,)):
            raise ValueError(f"{name} must be a scalar or have {OUTPUT_DIM} entries (one per output), got shape {v.shape}")
        thresholds[name] = np.broadcast_to(v, (OUTPUT_DIM,)).copy()
    if tau_max is not None:          # (0, N T]: no packet disorder (seed 000 section 2.3)
        check_range("tau_max", tau_max, 0.0, N * T * (1 + 1e-6), low_open=True)
    if truth is not None and abs(float(truth.T) - T) > 1e-9:
        raise ValueError(f"truth must have the model's period T={T}, got {truth.T}")
    horizon_s = 1.6 * length / float(follower.V_ref) + 10.0 if horizon_s is None else horizon_s
    steps = N * math.ceil(horizon_s / (N * T))
    x0 = np.concatenate([np.zeros(3), np.asarray(p.points)[0], np.zeros(1)]).astype(np.float32)   # at rest
    if truth is None:
        robot = dataclasses.replace(plant, x0=x0, noise=noise)
    else:
        robot = dataclasses.replace(truth, kin=dataclasses.replace(truth.kin, x0=x0, noise=noise))
    single = case == "SR"
    Ts = np.float32(N * T if single else T)              # the controller's period
    hold = np.int32(N if single else 1)                  # fast periods each action of a packet is held
    # the remote side and the actuator, built as one block (the sender's packet copy lives here)
    estimator = nc.EKF(plant, np.square(filter_noise.process_std()), np.square(filter_noise.measurement_std()), x0,
                       np.diag(np.square(np.asarray(P0_STD, np.float32))), form="sequential", weight="slot",
                       output="weighted", keep_means=True, jacobian_grad=bool(jacobian_grad),
                       structure=ekf_structure(plant) if sparse else None, batch_last=batch_last)
    actuator = nc.ChainActuator(plant, follower, Ts, np.int32(h * N), hold, x0, noise_dim=PROCESS_NOISE_DIM)
    controller = nc.ChainController(actuator)            # keeps its copy of the packets it sent
    return nc.Loop(
        plant=robot,
        trigger=nc.Petc(sigma=thresholds["sigma"], delta=thresholds["delta"], temperature=trigger_temperature,
                        max_silence=max_silence if case == "DRHE" else 1),
        uplink=nc.Link(loss=nc.Bernoulli(dp), reliable_first=True, capacity=1),
        estimator=estimator, controller=controller,
        # the round trip lumped on the downlink: this direction's law, the uplink's none
        downlink=nc.Link(loss=nc.Bernoulli(dp), delay=nc.RoundTrip(nc.ShiftedExponential(eta, phi),
                                                                    nc.ShiftedExponential(0.0, 0.0)),
                         tau_max=N * T if tau_max is None else tau_max, reliable_first=True, capacity=2),
        actuator=actuator,
        monitor=nc.PathMonitor(p, max_dev=MAX_DEV, end_tol=END_TOL, window=TRACK_WINDOW),
        N=N, steps=steps, T=T, record=FULL_RECORD if full else METRICS_RECORD)


_STRUCTURES: dict = {}


def ekf_structure(plant: Mecanum) -> EKFStructure:
    """The sparsity patterns of the NUDREKF's Jacobians for this (concrete) model, detected
    once per distinct parameter set (:func:`jaxnc.estimators.sparsity.detect_structure`).

    For the kinematics of eq. (1) A = df/dxi is nonzero only in its pose block, on the
    diagonal and in the yaw column; H = dh/dxi has the encoder rows on the velocities,
    the yaw row on psi and the beacon rows on (X, Y)."""
    leaves, treedef = jax.tree.flatten(plant)
    try:
        key = (type(plant), treedef, tuple(np.asarray(v).tobytes() for v in leaves))
    except jax.errors.TracerArrayConversionError as e:
        raise ValueError("ekf_structure: the plant holds traced values; build the loop outside jit/vmap, "
                         "or pass sparse=False") from e
    if key not in _STRUCTURES:
        _STRUCTURES[key] = detect_structure(plant.dynamics, plant.measure, STATE_DIM, INPUT_DIM,
                                            PROCESS_NOISE_DIM, OUTPUT_DIM)
    return _STRUCTURES[key]


class Metrics(NamedTuple):
    """Per-run cost indexes, seed 000 eq. (21)-(24) (J4 is formed against the nominal run)."""

    J1: jax.Array         # mean distance to the path, m
    J2: jax.Array         # max distance to the path, m
    J3: jax.Array         # time to complete the path, s
    tx_sc: jax.Array      # sensor transmissions up to completion
    tx_ca: jax.Array      # controller transmissions (measurements received) up to completion
    l: jax.Array          # fast steps to completion (all of them if never)
    unstable: jax.Array   # bool
    UNITS = {"J1": "m", "J2": "m", "J3": "s", "tx_sc": "transmissions", "tx_ca": "transmissions", "l": "fast periods"}


def metrics(loop: nc.Loop, traj: nc.Trajectory) -> Metrics:
    """Eq. (21)-(24) of one run of a :func:`mecanum_loop` loop (either record); inf when unstable.

    Reads the path monitor's distance (``parts["monitor"]``) up to completion
    (``done_step``), the transmissions, and the belief (``parts["estimator"]``)."""
    K, N = loop.steps, loop.N
    dist, l, est = traj.parts["monitor"], traj.done_step, traj.parts["estimator"]
    finite = jnp.all(jnp.isfinite(est)) if jnp.issubdtype(est.dtype, jnp.floating) else jnp.all(est)
    unstable = traj.failed | ~finite | ~traj.done
    mask, slow_mask = jnp.arange(K) < l, (jnp.arange(K // N) * N) < l
    inf = jnp.asarray(jnp.inf, jnp.float32)
    return Metrics(J1=jnp.where(unstable, inf, J1(dist, mask)), J2=jnp.where(unstable, inf, J2(dist, mask)),
                   J3=jnp.where(unstable, inf, l * loop.T), tx_sc=jnp.sum(traj.sent_sc * slow_mask),
                   tx_ca=jnp.sum(traj.recv_sc * slow_mask), l=l, unstable=unstable)


def with_follower(loop: nc.Loop, **changes) -> nc.Loop:
    """``loop`` with fields of its :class:`PathFollower` replaced (e.g. ``Kp=``) where the law
    lives: the actuator's and the controller's (its copy of the actuator) prediction chains."""
    actuator = dataclasses.replace(loop.actuator, law=dataclasses.replace(loop.actuator.law, **changes))
    return dataclasses.replace(loop, controller=dataclasses.replace(loop.controller, actuator=actuator),
                               actuator=actuator)


#: the per-seed function ``run(loop, key) -> Metrics``: :func:`jaxnc.loop.run` with :func:`metrics`
run = functools.partial(nc.run, metrics=metrics)


def tracking_cost(loop: nc.Loop, key):
    """Mean distance to the path over the whole horizon: a smooth objective for gradients
    (no instability mask, no completion time)."""
    return jnp.mean(nc.simulate(loop, key).parts["monitor"])
