"""Closed loops SR, DR, DRH and DRHE of seed 000 (section 4.1), as configurations of the
one runner :mod:`jaxnc.loop` (:func:`build_loop`).

Roles: the true robot with the path monitor (:class:`Robot`), the sensor's trigger
(:func:`sensor_trigger`), an uplink with losses only, the remote NUDREKF
(:class:`~jaxnc.estimators.nudrekf.NudrekfEstimator`) and controller
(:class:`~jaxnc.estimators.nudrekf.ChainController`), a downlink with losses and the lumped
round-trip delay (:class:`~jaxnc.loop.RoundTrip`), and the actuator
(:class:`~jaxnc.estimators.nudrekf.ChainActuator`), whose packets are prediction chains.

Timing (fast period T, slow period NT, k the slow index, t = kN the fast instant):

1. The sensor samples z_k = h(xi_t) + n2 and, in DRHE, sends only when the PETC
   condition (eq. 4) holds; the other cases send every NT. The first sample is
   always sent (zbar_0 = z_0).
2. A sent packet is lost with probability p_sc (eq. 5). When it arrives, the remote
   NUDREKF corrects (eq. 13) and its prediction stage computes h*N estimates and
   actions from instant t on (section 3.3.1); they are sent as one packet, stamped t.
3. The controller-to-actuator packet is lost with probability p_ca; otherwise it
   reaches the actuator after the round-trip delay tau (eq. 6-7) quantised up to
   whole fast periods. Packets later than tau_max (default NT, so there is never
   disorder, as the paper arranges) are discarded.
4. Every fast period the actuator applies the action of its buffer indexed by time
   stamp and holds the last when the buffer is exhausted (section 2.4); the plant
   moves (eq. 1) and the remote filter propagates its belief (eq. 11) along the
   actions it sent.

Cases (section 4.1):

* SR   single rate: the controller runs once per NT and its action is held (h = 1);
* DR   dual rate: N fast actions per packet (h = 1), hold the last on loss;
* DRH  dual rate + h-step prediction: h*N actions per packet;
* DRHE DRH + PETC at the sensor (eq. 4).

The network draws (losses, delays) and the noises are the runner's
(:func:`jaxnc.loop.draw`: one stream per purpose from the key, drawn up front): the
noises scaled by the robot's ``process_std`` / ``measurement_std``, the losses and
delays from the links' models. The four cases of one N therefore meet the same
realisation (common random numbers); runs at different N draw different ones.

A run is *unstable* when the robot leaves a tube of ``max_dev`` (0.5 m) around the
path, a state becomes non-finite, or it has not reached the end of the path within
the simulated horizon (1.6 x the nominal path time + 10 s). Its indexes are inf.
(The runner applies zero in place of a non-finite action and marks the run failed; such
a run is unstable.)
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_choice, check_int, check_range
from jaxnc.controllers.path_following import PathFollower
from jaxnc.estimators.nudrekf import (ChainActuator, ChainController, NudrekfEstimator, PacketChain, belief_finite,
                                     belief_means)
from jaxnc.estimators.sparsity import EKFStructure, detect_structure
from jaxnc.metrics import J1, J2, local_distance
from jaxnc.loop import (AbstractPlant, Bernoulli, Link, Loop, Monitor, Petc, Record, RoundTrip,
                        ShiftedExponential)
from jaxnc.loop import simulate as run_loop
from jaxnc.network import Channel
from jaxnc.paths import Path, closest_index, get_path
from jaxnc.plants.mecanum import INPUT_DIM, OUTPUT_DIM, PROCESS_NOISE_DIM, STATE_DIM, Mecanum, MecanumNoise

CASES = ("SR", "DR", "DRH", "DRHE")

# Paper, section 4.1: delta(i) = 0.1; sigma(i) = 0.1 for the four wheel speeds, 0.05 else.
PAPER_SIGMA = (0.1, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05, 0.05, 0.05)
PAPER_DELTA = (0.1,) * 9
# Our default sigma(i) = 0 (eq. 4 text: sigma(i) in {0, 1}), delta(i) as in the paper.
# With the paper's sigma in SI units the relative term sum sigma(i) z(i)^2 is about 8
# (wheel speeds of 4 rad/s, beacon distances of 3 m): the sensor then fires on a few
# per cent of slow instants (J4 ~ 0.02) and DRHE loses the path at every N (README,
# EXPERIMENTS.md). With sigma = 0 the firing rates are the paper's (J4 0.07-0.19).
DEFAULT_SIGMA = (0.0,) * 9
PAPER_ETA, PAPER_PHI = 0.01, 0.02   # delay distribution, eq. (7), section 4.1
# The filter's wheel-speed process noise (rad/s), 15x the true 0.2 rad/s: the remote
# side propagates its belief along the actions it *sent*, and a lost control packet
# leaves the robot doing something else. A filter tuned to the true noise becomes
# overconfident after a few lost packets and a correction then moves it only part of
# the way (the robot cuts across the path); this Q keeps corrections decisive and
# costs nothing in the nominal case (J1 4.24 vs 4.19 cm, 32 seeds).
FILTER_OMEGA_STD = 3.0
# Path points searched ahead of the robot's progress each fast period: it moves at most
# omega_max R T = 0.1 m (10 points at the 1 cm spacing) per period.
TRACK_WINDOW = 32


def default_h(case: str, N: int, dp: float, n_slow: int) -> int:
    """Prediction horizon h in slow periods: our reading of section 4.1.

    The paper asks h*N to cover the longest run of missing data. A slow period
    delivers nothing with probability q = 1 - (1 - DP)^2 (either direction lost);
    over n_slow periods the longest such run reaches r with probability about
    1 - exp(-n_slow (1 - q) q^r) (Erdos-Renyi law of runs). DRH takes h = r + 1 with
    that probability at 5 %; DRHE, whose sensor is also silent between events, takes
    at least hN = 100 fast periods as in the paper (hN in {100, 156}). SR and DR: h = 1.
    The paper's DRH range hN in [10, 50] is smaller: with our kinematic plant,
    whose held actions drive it straight off the path, that range leaves DRH
    unstable at DP = 0.5 (see README).
    """
    if case in ("SR", "DR"):
        return 1
    q = 1.0 - (1.0 - dp) ** 2
    if q > 0:
        r = math.log(-math.log(0.95) / (n_slow * (1.0 - q))) / math.log(q)
        h_drh = max(1, math.ceil(r) + 1)
    else:
        h_drh = 1
    if case == "DRH":
        return h_drh
    return max(math.ceil(100 / N), h_drh)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MecanumLoop:
    """Everything one closed-loop run needs.

    Static (they shape arrays): N and steps. Everything else is a leaf, the scheme and
    the horizon h included, so the four cases and every DP of a given N share one
    compiled program (the grid experiment passes the configuration as an argument).
    """

    plant: Mecanum
    noise: MecanumNoise            # true process / measurement noise
    filter_noise: MecanumNoise     # the covariances the NUDREKF assumes
    follower: PathFollower
    trigger: Petc                  # the sensor's PETC (eq. 3-4); build_loop sets its max_silence
    sc: Channel                    # sensor -> controller
    ca: Channel                    # controller -> actuator (carries the lumped round-trip delay)
    tau_max: jax.Array             # s; later packets are discarded
    P0_std: jax.Array              # initial estimation uncertainty (std per state)
    max_dev: jax.Array = 0.5       # m; leaving this tube around the path = unstable
    end_tol: jax.Array = 0.1       # m; the path is complete within this of its end
    scheme: jax.Array = 3          # index into CASES (SR, DR, DRH, DRHE)
    # DRHE only: the sensor also sends when it has been silent for this many slow
    # periods (a time-triggered safety condition like seed 003 eq. 7; not in seed 000,
    # whose eq. 4 alone lets a resting robot's sensor fall silent for good). 0 = off.
    max_silence: jax.Array = 0
    h: jax.Array = 1               # prediction horizon in slow periods: h*N actions per packet
    # The plant the robot really is, when it differs from the model ``plant`` the
    # estimator and controller use (e.g. jaxnc.plants.mecanum_mjx.MjxMecanum, the
    # multibody robot of the paper's section 4). None: the kinematic model itself.
    truth: Any = None
    N: int = dataclasses.field(default=1, metadata=dict(static=True))
    # False: gradients hold the EKF's Jacobians constant (values unchanged): reverse mode
    # about 2x cheaper, gradient of a tracking cost 0.3-4.8 % from exact (benchmarks/RESULTS.md).
    jacobian_grad: bool = dataclasses.field(default=True, metadata=dict(static=True))
    # The sparsity patterns of the EKF's Jacobians (``ekf_structure(plant)``): the filter
    # then skips products with structural zeros (same values up to float32 rounding).
    # None: dense.
    structure: EKFStructure | None = dataclasses.field(default=None, metadata=dict(static=True))
    steps: int = dataclasses.field(default=100, metadata=dict(static=True))

    def __post_init__(self):
        check_int("MecanumLoop.N", self.N, 1, 100)
        check_int("MecanumLoop.steps", self.steps, self.N)
        if self.steps % self.N:
            raise ValueError(f"MecanumLoop.steps must be a multiple of N={self.N}, got {self.steps}")
        check_range("MecanumLoop.scheme", self.scheme, 0, len(CASES) - 1)
        check_range("MecanumLoop.h", self.h, 1, 1000)
        check_range("MecanumLoop.max_silence", self.max_silence, 0, 100_000)
        check_range("MecanumLoop.tau_max", self.tau_max, 0.0, self.N * self.plant.T * (1 + 1e-6), low_open=True)
        if self.truth is not None and abs(float(self.truth.T) - float(self.plant.T)) > 1e-9:
            raise ValueError(f"MecanumLoop.truth must have the model's period T={self.plant.T}, got {self.truth.T}")

    @property
    def case(self) -> str:
        """The scheme's name (needs a concrete, unbatched ``scheme``)."""
        return CASES[int(self.scheme)]

    @property
    def single_rate(self):
        return jnp.asarray(self.scheme) == 0

    @property
    def horizon(self):
        """Actions per packet: h*N."""
        return jnp.asarray(self.h, jnp.int32) * self.N

    @property
    def Ts(self):
        """Controller period: NT for SR, T otherwise."""
        return jnp.where(self.single_rate, self.N * self.plant.T, self.plant.T)

    @property
    def hold(self):
        """Fast periods each controller action is held inside a packet: N for SR, else 1."""
        return jnp.where(self.single_rate, self.N, 1).astype(jnp.int32)

    @property
    def event_triggered(self):
        """The sensor uses the PETC condition, eq. (4) (DRHE)."""
        return jnp.asarray(self.scheme) == 3


def mecanum_loop(case: str = "DRHE", N: int = 10, dp: float = 0.0, path: str | Path = "lissajous", *,
                 h: int | None = None, sigma=None, delta=None, eta: float = PAPER_ETA, phi: float = PAPER_PHI,
                 tau_max: float | None = None, noise: MecanumNoise | None = None,
                 filter_noise: MecanumNoise | None = None,
                 plant: Mecanum | None = None, follower_kw: dict | None = None,
                 trigger_temperature: float = 0.0, horizon_s: float | None = None,
                 max_silence: int = 0, truth=None, jacobian_grad: bool = True, sparse: bool = True) -> MecanumLoop:
    """Build a validated configuration with the paper's defaults (section 4.1).

    ``dp`` is the dropout probability of both directions, DP = p_sc = p_ca. ``truth``
    is the true plant when it is not the kinematic model (e.g. ``mjx_mecanum()``).
    ``jacobian_grad=False`` makes gradients hold the EKF's Jacobians constant (the
    simulation is unchanged; reverse mode about 2x cheaper, an approximate gradient).
    ``sparse=False`` runs the EKF dense instead of with the model's Jacobian sparsity
    (:func:`ekf_structure`; same values up to float32 rounding, about 1.3x slower).

    ``case`` is matched as on the command line (exact, else ignoring case: "drhe" is
    DRHE). Every argument is checked here, before anything is built: ValueError naming
    the argument and its allowed range.
    """
    case = check_choice("case", case, CASES)
    check_int("N", N, 1, 100)
    check_range("dp", dp, 0.0, 1.0, high_open=True)
    check_range("eta", eta, 0.0, None)
    check_range("phi", phi, 0.0, None)
    check_range("trigger_temperature", trigger_temperature, 0.0, None)
    if horizon_s is not None:
        check_range("horizon_s", horizon_s, 0.0, None, low_open=True)
    plant = plant or Mecanum()
    noise = noise or MecanumNoise()
    if filter_noise is None:
        # the filter's design covariances, independent of the true noise (which may be 0)
        filter_noise = MecanumNoise(omega=FILTER_OMEGA_STD)
    p = path if isinstance(path, Path) else get_path(path)
    follower = PathFollower(path=p, **(follower_kw or {}))
    if h is None:
        n_slow = math.ceil(float(p.length) / float(follower.V_ref) / (N * plant.T))
        h = default_h(case, N, float(dp), n_slow)
    check_int("h", h, 1, 1000)
    check_int("max_silence", max_silence, 0, 100_000)
    for name, v in (("sigma", sigma), ("delta", delta)):
        check_range(name, v, 0.0, None)                   # None: the paper's
    sigma = np.asarray(DEFAULT_SIGMA if sigma is None else sigma, np.float32)
    delta = np.asarray(PAPER_DELTA if delta is None else delta, np.float32)
    for name, v in (("sigma", sigma), ("delta", delta)):
        if v.shape not in ((), (1,), (OUTPUT_DIM,)):
            raise ValueError(f"{name} must be a scalar or have {OUTPUT_DIM} entries (one per output), got shape {v.shape}")
    sigma = np.broadcast_to(sigma, (OUTPUT_DIM,)).copy()
    delta = np.broadcast_to(delta, (OUTPUT_DIM,)).copy()
    T = plant.T
    if tau_max is not None:          # (0, N T]: no packet disorder (seed 000 section 2.3)
        check_range("tau_max", tau_max, 0.0, N * float(T) * (1 + 1e-6), low_open=True)
    tau_max = N * T if tau_max is None else tau_max
    if horizon_s is None:
        horizon_s = 1.6 * float(p.length) / float(follower.V_ref) + 10.0
    steps = N * math.ceil(horizon_s / (N * T))
    return MecanumLoop(
        plant=plant, noise=noise, filter_noise=filter_noise, follower=follower,
        trigger=Petc(sigma=sigma, delta=delta, temperature=trigger_temperature),
        sc=Channel(p_loss=dp), ca=Channel(p_loss=dp, eta=eta, phi=phi), tau_max=tau_max,
        P0_std=np.asarray([0.01, 0.01, 0.01, 0.02, 0.02, 0.01], np.float32),
        scheme=np.int32(CASES.index(case)), h=np.int32(h), max_silence=np.int32(max_silence), truth=truth,
        N=N, steps=steps, jacobian_grad=bool(jacobian_grad), structure=ekf_structure(plant) if sparse else None)


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


class Trajectory(NamedTuple):
    """Per fast instant: true state, estimate (remote belief), applied action;
    per slow instant: sent / received flags; and run summaries."""

    x: jax.Array          # [K, 6]
    mean: jax.Array       # [K, 6]
    u: jax.Array          # [K, 4]
    dist: jax.Array       # [K] distance to the path (robot's own branch, metrics.local_distance)
    sent: jax.Array       # [K/N] sensor transmissions (beta)
    received: jax.Array   # [K/N] sensor packet reached the controller (a control packet was sent)
    l: jax.Array          # fast steps until the path was completed (K if never)
    done: jax.Array       # bool: path completed
    bad: jax.Array        # bool: left the tube or non-finite


class Track(NamedTuple):
    """The path-tracking monitor of a run (kept in :class:`Robot`'s state, recorded per fast period)."""

    xv: jax.Array         # float[6] kinematic state after the period
    idx: jax.Array        # int32, the robot's progress along the path (closest_index)
    dist: jax.Array       # distance to the path (metrics.local_distance)
    done: jax.Array       # bool: path completed
    l: jax.Array          # int32: fast steps until the path was completed (K if never)
    bad: jax.Array        # bool: left the tube (before completion) or non-finite state
    t: jax.Array          # int32: fast periods simulated


class RobotState(NamedTuple):
    s: Any                # the true plant's state (kinematic float[6], or the MJX state)
    track: Track


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot(AbstractPlant):
    """The true robot as the loop's plant, with the path monitor of section 4.1 in its state.

    ``truth`` is the kinematic model (eq. 1) or another plant with its interface (``init(key,
    x0)``, ``step``, ``state``, ``measure``, e.g. the MJX robot). Each fast period, after the
    step, the monitor advances the robot's progress along the path (``closest_index`` in a
    window of TRACK_WINDOW points), its distance to the path, completion (within ``end_tol``
    of the end, past 90 % of the points; ``l`` = the steps taken until then) and ``bad``
    (left the ``max_dev`` tube before completion, or a non-finite state). ``noise`` is the
    true process (n1, 7) and measurement (n2, 9) noise: the runner scales its standard
    normal draws by :meth:`process_std` and :meth:`measurement_std`.
    """

    truth: Any
    path: Path
    x0: Any               # float[6], the start pose on the path, at rest
    max_dev: Any
    end_tol: Any
    noise: MecanumNoise
    steps: int = dataclasses.field(default=1, metadata=dict(static=True))
    state_dim = STATE_DIM
    input_dim = INPUT_DIM
    noise_dim = PROCESS_NOISE_DIM
    output_dim = OUTPUT_DIM

    def process_std(self):
        return self.noise.process_std()

    def measurement_std(self):
        return self.noise.measurement_std()

    def init(self, key) -> RobotState:
        s0 = self.truth.init(key, self.x0)
        z = jnp.zeros((), jnp.int32)
        no = jnp.zeros((), bool)
        track = Track(self.truth.state(s0), z, jnp.zeros((), jnp.float32), no, jnp.asarray(self.steps, jnp.int32),
                      no, z)
        return RobotState(s0, track)

    def dynamics(self, x: RobotState, u, w) -> RobotState:
        s = self.truth.step(x.s, u, w)
        xv = self.truth.state(s)
        tr, path = x.track, self.path
        idx, _ = closest_index(path, xv[3:5], tr.idx, TRACK_WINDOW)
        dist = local_distance(path, xv[3:5], idx)
        n_path = path.points.shape[0]
        at_end = (idx >= (9 * n_path) // 10) & (jnp.sum((xv[3:5] - path.points[-1]) ** 2) < self.end_tol ** 2)
        l = jnp.where(tr.done, tr.l, tr.t + 1)
        done = tr.done | at_end
        # only until the path is complete: afterwards the robot may coast off the end
        off = (dist > self.max_dev) & ~done
        bad = tr.bad | off | ~jnp.all(jnp.isfinite(xv))
        return RobotState(s, Track(xv, idx, dist, done, l, bad, tr.t + 1))

    def measure(self, x: RobotState, v):
        return self.truth.measure(x.s, v)

    def state_vector(self, x: RobotState):
        return self.truth.state(x.s)



def robot_track(robot: Robot, x: RobotState) -> Track:
    """The monitor after each fast period (a :class:`jaxnc.loop.Record` function)."""
    return x.track


def robot_dist(robot: Robot, x: RobotState):
    """The monitor's distance to the path alone (what the metrics need)."""
    return x.track.dist


def sensor_trigger(loop: MecanumLoop) -> Petc:
    """The sensor of section 4.1: PETC (eq. 3-4) with the optional safety condition
    ``max_silence`` in DRHE; every other case sends at every slow instant (max_silence 1).
    The first instant always sends. A leaf choice, so every case shares one program."""
    ms = jnp.where(loop.event_triggered, jnp.asarray(loop.max_silence, jnp.int32), 1)
    return dataclasses.replace(loop.trigger, max_silence=ms)


def build_loop(loop: MecanumLoop, full: bool = True) -> Loop:
    """The configuration ``loop`` as a :class:`jaxnc.loop.Loop` (module docstring).

    Sensor :func:`sensor_trigger`; uplink: Bernoulli(p_sc) loss, no delay (the round trip is
    lumped downstream), first exchange delivered; remote side
    :class:`~jaxnc.estimators.nudrekf.NudrekfEstimator` and
    :class:`~jaxnc.estimators.nudrekf.ChainController`; downlink: Bernoulli(p_ca) loss,
    :class:`~jaxnc.loop.RoundTrip` delay, packets later than ``tau_max`` discarded, first exchange
    delivered; actuator :class:`~jaxnc.estimators.nudrekf.ChainActuator` (h*N actions held
    by the prediction chain, the last one held beyond). Plant :class:`Robot`."""
    plant, fol, N, K = loop.plant, loop.follower, loop.N, loop.steps
    truth = plant if loop.truth is None else loop.truth   # the robot; ``plant`` is the model
    dtype = jnp.float32
    start = fol.path.points[0]
    x0 = jnp.concatenate([jnp.zeros(3, dtype), start.astype(dtype), jnp.zeros(1, dtype)])
    Ts, hold, H = loop.Ts, loop.hold, loop.horizon
    estimator = NudrekfEstimator(
        model=plant, Q=loop.filter_noise.process_std() ** 2, R=loop.filter_noise.measurement_std() ** 2,
        mean0=x0, cov0=jnp.diag(jnp.asarray(loop.P0_std, dtype) ** 2),
        noise_dim=PROCESS_NOISE_DIM, jacobian_grad=loop.jacobian_grad, structure=loop.structure)
    actuator = ChainActuator(plant, fol, Ts, H, hold, x0, noise_dim=PROCESS_NOISE_DIM)
    return Loop(
        plant=Robot(truth, fol.path, x0, loop.max_dev, loop.end_tol, loop.noise, steps=K),
        trigger=sensor_trigger(loop),
        uplink=Link(loss=Bernoulli(loop.sc.p_loss), reliable_first=True, capacity=1),
        estimator=estimator,
        controller=ChainController(actuator),
        downlink=Link(loss=Bernoulli(loop.ca.p_loss), delay=RoundTrip(ShiftedExponential(loop.ca.eta, loop.ca.phi),
                                                                      ShiftedExponential(loop.sc.eta, loop.sc.phi)),
                      tau_max=loop.tau_max,
                      reliable_first=True, capacity=2),
        actuator=actuator,
        monitor=Monitor(freeze=False), N=N, steps=K, T=float(plant.T),
        record=Record(plant=robot_track, estimator=belief_means) if full else
        Record(signals=("sent_sc", "recv_sc"), plant=robot_dist, estimator=belief_finite))


def simulate(loop: MecanumLoop, key, full: bool = True) -> Trajectory:
    """One closed-loop run of ``loop.case``: :func:`build_loop` run by :func:`jaxnc.loop.simulate`
    on the runner's own draws. Pure function of (loop, key); vmap it over keys. ``full=False``
    records only what the metrics need (``x``, ``mean`` and ``u`` come back empty; the
    rest is bit for bit the same).

    Packets are carried as prediction chains (:class:`PacketChain`): the remote side's
    copy of its last sent packet and the actuator's installed packet each advance one
    fast period at a time and yield the action the packet holds for that instant, so
    a run costs O(K) controller evaluations whatever h (materialising h*N actions per
    packet would cost O(K h)); the actions are the same.
    """
    return _simulate(loop, key, full=full)


def _simulate(loop: MecanumLoop, key, full: bool) -> Trajectory:
    """:func:`simulate`; ``full=False`` leaves x, mean and u empty (:func:`build_loop`)."""
    K, N = loop.steps, loop.N
    tr = run_loop(build_loop(loop, full), key)
    end = tr.final_plant.track
    if full:
        track = tr.parts["plant"]
        mean = tr.parts["estimator"].reshape(K, STATE_DIM)
        finite = jnp.all(jnp.isfinite(mean))
        x, dist, u = track.xv, track.dist, tr.u
    else:
        mean = x = u = jnp.zeros((0, STATE_DIM), jnp.float32)
        finite = jnp.all(tr.parts["estimator"])
        dist = tr.parts["plant"]
    bad = end.bad | ~finite | tr.failed
    return Trajectory(x=x, mean=mean, u=u, dist=dist, sent=tr.sent_sc, received=tr.recv_sc,
                      l=end.l, done=end.done, bad=bad)


class Metrics(NamedTuple):
    """Per-run cost indexes, seed 000 eq. (21)-(24) (J4 is formed against the nominal run)."""

    J1: jax.Array         # mean distance to the path, m
    J2: jax.Array         # max distance to the path, m
    J3: jax.Array         # time to complete the path, s
    tx_sc: jax.Array      # sensor transmissions up to completion
    tx_ca: jax.Array      # controller transmissions up to completion
    l: jax.Array          # fast steps to completion
    unstable: jax.Array   # bool


def evaluate(loop: MecanumLoop, traj: Trajectory) -> Metrics:
    """Cost indexes of one run; inf when it is unstable."""
    K, N, T = loop.steps, loop.N, loop.plant.T
    dist = traj.dist
    mask = jnp.arange(K) < traj.l
    unstable = traj.bad | ~traj.done
    inf = jnp.asarray(jnp.inf, jnp.float32)
    slow_mask = (jnp.arange(K // N) * N) < traj.l
    tx_sc = jnp.sum(traj.sent * slow_mask)
    tx_ca = jnp.sum(traj.received * slow_mask)
    return Metrics(
        J1=jnp.where(unstable, inf, J1(dist, mask)),
        J2=jnp.where(unstable, inf, J2(dist, mask)),
        J3=jnp.where(unstable, inf, traj.l * T),
        tx_sc=tx_sc, tx_ca=tx_ca, l=traj.l, unstable=unstable)


def tracking_cost(loop: MecanumLoop, key):
    """Mean distance to the path over the whole horizon: a smooth objective for
    gradients (no instability mask, no completion time)."""
    return jnp.mean(_simulate(loop, key, full=False).dist)


def run(loop: MecanumLoop, key) -> Metrics:
    """simulate + evaluate: the per-seed function the Monte-Carlo engine vmaps (recording
    only what the metrics need)."""
    return evaluate(loop, _simulate(loop, key, full=False))
