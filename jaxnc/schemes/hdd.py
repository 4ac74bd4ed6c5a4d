"""Closed loops of seed 003 section 5 (HDD servo), Cases 1-6, as configurations of
:mod:`jaxnc.loop` (N = 1: the slow period is the fast period T).

Every period T (k = 0..steps-1), in the runner's order (:mod:`jaxnc.loop.base`):

1. Sensor (:class:`HddPlant`, trigger): y_k = C x_k + v_k. It sends every period in TTS
   (Case 1, :class:`~jaxnc.loop.Periodic`); otherwise when the PET condition (eq. 6),
   ||ybar_{k-1} - y_k||^2 > sigma_s ||y_k||^2 + delta_s, holds, or when the time-triggered
   safety condition (eq. 7) k - k_lm >= k_max holds (k_max = 0: off, as in the paper's
   example) (:class:`~jaxnc.loop.Petc`). The first sample is always sent; ybar follows
   eq. (5). The network is ideal both ways (:class:`~jaxnc.loop.Link`, no loss, no
   delay), as in the paper's TrueTime study.
2. Estimator, on arrival: none in Cases 1-2 (:class:`~jaxnc.loop.Passthrough`, the
   controller uses y_k); NUMRE in Cases 3-6 (:class:`NumreFilter`): multiplicity
   N = k - k_lm (eq. 9), correction with K(N) (eq. 11-12). Its prior x(k|k-N) is
   propagated with the actions actually applied (the control side knows them: the
   network is ideal); this is eq. (14) evaluated period by period.
3. Controller (:class:`HddController`), which works only when a measurement arrives
   (section 2):
   * without estimator (Cases 1-2): e_k = r_k - y_k and one MRCI step (eq. 19, Fig. 4);
   * with NUMRE (Cases 3-6) the cascade (eq. 14-15): for l = 0..h, yhat = C xhat(k+l|k),
     dhat = Cbar xhat(k+l|k) (Cases 3-5, disturbance model known) or the DOB output
     (Case 6, eq. 16), u_{k+l} = MRCI(r_{k+l} - yhat) - dhat, xhat <- A xhat + B u.
     The control action *compensates* the disturbance: eq. (1) adds d to u, so the
     estimate is subtracted (the paper says "summed", which we read as summed with sign).
   Its own state at the next arrival is the one its last cascade reached at that
   instant (the MRCI and DOB states along the cascade are kept).
   The controller-side condition (eq. 21-22), ||ubar_{k-1} - u_k||^2 > sigma_c ||u_k||^2 +
   delta_c, evaluated only when the controller works, decides whether the packet
   {u_k..u_{k+h}} goes to the actuator (gamma_k); TTS always sends.
4. Actuator (:class:`~jaxnc.loop.PacketActuator`, h + 1 actions by time stamp): the
   current action of the newest packet, or the future one for the present instant
   (section 3.2.4), u_k = packet[min(k - k_pkt, h)], holding the last beyond h.

The horizon h: section 3.2.1 requires h >= N_max, the longest gap between samples, so
that x(k+N|k) exists at the next correction; and the actuator plays a packet's future
actions until the next packet, which may come several samples later (eq. 22). Neither
gap has a static bound (eq. 7 bounds only the sensor's, and is off in the paper), so by
default h = steps - 1 (:func:`whole_run_horizon`): a packet covers the rest of the run,
no gap is ever longer, and the actuator never runs out. A smaller h may be given; then
gaps longer than h are clipped (K(N) of N = h, the controller's state at index h) and the
actuator holds (``Trajectory.held``, ``Metrics.n_held``).

Cases (section 5): 1 TTS; 2 PETC; 3 PETC + NUMRE; 4 = 3 + noise + disturbance;
5 = 4 with narrower thresholds; 6 = 5 with a DOB instead of the disturbance model.
Noises are drawn up front from the key (common random numbers across cases,
:func:`draws`).
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxnc.loop as jl
from jaxnc._validate import check_int, check_nonneg, check_range
from jaxnc.design import mrci as mrci_mod
from jaxnc.design.mrci import Mrci, MrciState, mrci_init, mrci_step
from jaxnc.disturbance import Dob, DobState, dob_design, dob_init, dob_output, dob_update
from jaxnc.estimators.numre import NumreTables, cascade, numre_correct, numre_tables
from jaxnc.loop.triggers import petc_gap
from jaxnc.loop.base import AbstractController, AbstractEstimator, AbstractPlant, Inbox, Packet
from jaxnc.plants import hdd as hdd_plant

__all__ = ["CASES", "PAPER_THRESHOLDS", "NARROW_THRESHOLDS", "HddLoop", "hdd_loop", "simulate", "run",
           "Trajectory", "Metrics", "ise", "isep", "gpi", "cc",
           "HddPlant", "NumreFilter", "NumreState", "HddController", "HddControllerState", "CtrlState",
           "runner_loop", "draws"]

CASES = (1, 2, 3, 4, 5, 6)
# Section 5: delta_s = sigma_s = 100e-7, delta_c = sigma_c = 1.32e-2 (the GPI optimum, Fig. 5);
# Case 5 (and 6): delta_s = sigma_s = 1e-7, delta_c = sigma_c = 1e-4.
PAPER_THRESHOLDS = (100e-7, 1.32e-2)
NARROW_THRESHOLDS = (1e-7, 1e-4)
# Eq. (33).
CD_GAIN, CD_ZEROS, CD_POLES = 1.0882, (0.9813, 0.9681, -1.0), (1.0, 0.8496, 0.6137)
STEPS = 464              # N_TTS = 464 in Case 1: the study lasts 464 periods (9.28 ms)


def whole_run_horizon(steps: int = STEPS) -> int:
    """The default cascade horizon h = steps - 1 (at least 1): a packet sent at k = 0 covers
    the whole run, so h >= N_max (section 3.2.1) and no packet runs out, whatever the gaps."""
    check_int("steps", steps, 1)
    return max(steps - 1, 1)


# Filter design covariances (ours). The filter's process noise is the true one plus a
# floor on the disturbance slope state x1 (eq. 32 drives only x2): without it the
# filter stops adapting to a ramp. Measurement noise V = (3e-4)^2 even when the
# simulation has none (Cases 1-3), so K(N) is defined.
FILTER_SLOPE_STD = 1e-6
FILTER_V = hdd_plant.V_STD ** 2
P0_SCALE = 1e-6          # the filter's initial covariance, P0 = 1e-6 I


def filter_disturbance_var(w_std: float) -> float:
    """Variance of the disturbance noise the filter assumes (Cases 3-5): the true one,
    floored at the default level so that the filter keeps adapting when the truth has less."""
    return max(w_std, hdd_plant.W_STD) ** 2


# Case 6: the plant-only filter models the unknown disturbance as input noise of this std.
FILTER_INPUT_STD = 1e-2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HddLoop:
    """One case: true model, filter model and tables, controller, DOB, thresholds."""
    model: hdd_plant.HddModel
    Af: jax.Array          # filter model (augmented in Cases 3-5, plant-only in Case 6)
    Bf: jax.Array
    Cbarf: jax.Array       # disturbance output of the filter model (zeros: plant-only)
    tables: NumreTables
    ctrl: Mrci
    dob: Dob
    sigma_s: jax.Array
    delta_s: jax.Array
    sigma_c: jax.Array
    delta_c: jax.Array
    r: jax.Array           # step reference amplitude
    noise: jax.Array       # 0./1.: measurement noise and disturbance on
    case: int = dataclasses.field(metadata=dict(static=True), default=1)
    h: int = dataclasses.field(metadata=dict(static=True), default=STEPS - 1)
    k_max: int = dataclasses.field(metadata=dict(static=True), default=0)
    steps: int = dataclasses.field(metadata=dict(static=True), default=STEPS)

    def __post_init__(self):
        check_int("case", self.case, 1, 6)
        check_int("h", self.h, 1, 10_000)
        check_int("k_max", self.k_max, 0, 10_000)
        check_int("steps", self.steps, 1)
        for n in ("sigma_s", "delta_s", "sigma_c", "delta_c"):
            check_nonneg(n, getattr(self, n))

    @property
    def tts(self) -> bool:
        return self.case == 1

    @property
    def numre(self) -> bool:
        return self.case >= 3

    @property
    def use_dob(self) -> bool:
        return self.case == 6


def controller_design(m: int = 2):
    """MRCI design of eq. (33) at ratio m (eq. 34 for m = 2)."""
    return mrci_mod.decompose(CD_GAIN * np.poly(CD_ZEROS), np.poly(CD_POLES), m)


def hdd_loop(case: int, *, thresholds=None, reading: str = "sum", h: int | None = None, k_max: int = 0,
             m: int = 2, steps: int = STEPS, w_std: float = hdd_plant.W_STD, v_std: float = hdd_plant.V_STD,
             we_form: str = "white", dob_f_hz: float = 300.0, r: float = 1.0) -> HddLoop:
    """Validated configuration of Case ``case`` (section 5); ``thresholds`` = (d_s = s_s, d_c = s_c).

    ``h`` is the cascade horizon (packets of h + 1 actions); ``None`` (default) is
    :func:`whole_run_horizon` (steps - 1). Raises ValueError for a case outside 1..6,
    h outside [1, 10000], k_max outside [0, h], or negative thresholds."""
    check_int("case", case, 1, 6)
    check_int("steps", steps, 1)
    h = whole_run_horizon(steps) if h is None else h
    check_int("h", h, 1, 10_000)
    check_int("k_max", k_max, 0, h)
    if thresholds is None:
        thresholds = NARROW_THRESHOLDS if case >= 5 else PAPER_THRESHOLDS
    ts, tc = thresholds
    check_range("delta_s = sigma_s", ts, 0.0, None)
    check_range("delta_c = sigma_c", tc, 0.0, None)
    model = hdd_plant.hdd_model(reading, w_std=w_std, v_std=v_std)
    Ap, Bp, Cp = hdd_plant.plant_matrices(reading)
    if case == 6:
        A, B, C = Ap, Bp, Cp
        Cbar = np.zeros(Ap.shape[0])
        Bw, W = Bp, FILTER_INPUT_STD ** 2
    else:
        A, B, Bw0, C, Cbar = hdd_plant.augment(Ap, Bp, Cp, *hdd_plant.disturbance_matrices())
        n = A.shape[0]
        Bw = np.zeros((n, 2))
        Bw[:, 0] = Bw0
        Bw[n - 2, 1] = 1.0
        W = np.diag([filter_disturbance_var(w_std), FILTER_SLOPE_STD ** 2])
    tables = numre_tables(A, Bw, C, W, FILTER_V, h, we_form=we_form)
    f = lambda a: jnp.asarray(a, jnp.float32)
    return HddLoop(model=model, Af=f(A), Bf=f(B), Cbarf=f(Cbar), tables=tables,
                   ctrl=controller_design(m).as_jax(), dob=dob_design(hdd_plant.T, dob_f_hz),
                   sigma_s=f(ts), delta_s=f(ts), sigma_c=f(tc), delta_c=f(tc), r=f(r),
                   noise=f(1.0 if case >= 4 else 0.0), case=case, h=h, k_max=k_max, steps=steps)


# ----------------------------------------------------------------------------- the loop's roles


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HddPlant(AbstractPlant):
    """The augmented HDD model of eq. (4) (:class:`~jaxnc.plants.hdd.HddModel`) as a loop
    plant: x float[12], u float[1], w float[1] (the broadband w_k of eq. 2), y float[1]."""

    model: hdd_plant.HddModel

    input_dim = 1
    noise_dim = 1
    output_dim = 1

    @property
    def state_dim(self) -> int:
        return int(self.model.A.shape[0])

    def init(self, key):
        return jnp.zeros((self.state_dim,), self.model.A.dtype)

    def dynamics(self, x, u, w):
        return self.model.step(x, u[0], w[0])

    def measure(self, x, v):
        return self.model.measure(x, v[0])[None]

    def process_std(self):
        return jnp.reshape(self.model.w_std, (1,))

    def measurement_std(self):
        return jnp.reshape(self.model.v_std, (1,))


class NumreState(NamedTuple):
    x: jax.Array       # float[n]: x(k|k) after a correction, else the prior x(k|k_lm)
    xk: jax.Array      # float[n]: the estimate used at the last slow instant (x after correct)
    P: jax.Array       # float[n, n]: posterior covariance at k_lm
    k_lm: jax.Array    # int32: the last instant a measurement arrived


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NumreFilter(AbstractEstimator):
    """NUMRE (eq. 9-15) as a loop estimator, single output, ideal network.

    A measurement delivered at slow instant k is taken as y_k (stamped now). On arrival:
    N = clip(k - k_lm, 1, n_max) (eq. 9) and the correction with K(N) (eq. 11-12,
    :func:`~jaxnc.estimators.numre.numre_correct`); otherwise the prior is kept. Between
    instants the mean is propagated with the actions the actuator *applied*
    (``inputs = "applied"``), x <- A x + B u_t for each fast period t.

    Attributes:
      tables: :class:`~jaxnc.estimators.numre.NumreTables` (A^N, We(N), C, V).
      A: float[n, n]; B: float[n], the filter model.
      P0: float[n, n], the initial covariance (the initial mean is 0).
      Cbar: float[n], the disturbance output of the filter model (eq. 15; zeros when the
        model has none, Case 6).

    """

    tables: NumreTables
    A: Any
    B: Any
    P0: Any
    Cbar: Any

    inputs = "applied"

    def init(self, ctx) -> NumreState:
        n = self.A.shape[0]
        x0 = jnp.zeros((n,), self.A.dtype)
        return NumreState(x0, x0, jnp.asarray(self.P0), jnp.zeros((), jnp.int32))

    def correct(self, state: NumreState, inbox: Inbox, k) -> NumreState:
        z, _, w = inbox.newest()
        fresh = w > 0.5
        N = jnp.clip(k - state.k_lm, 1, self.tables.n_max)
        xpost, Ppost, _ = numre_correct(self.tables, state.x, state.P, z[0], N)
        x = jnp.where(fresh, xpost, state.x)
        return NumreState(x, x, jnp.where(fresh, Ppost, state.P), jnp.where(fresh, k, state.k_lm)), x

    def predict(self, state: NumreState, u_applied, u_believed, k) -> NumreState:
        x = state.x
        for j in range(u_applied.shape[0]):           # the N fast periods (static)
            x = self.A @ x + self.B * u_applied[j, 0]
        return state._replace(x=x)



def output_and_disturbance(plant: HddPlant, x):
    """(y, d) = (C x, Cbar x) of a plant state: the noise-free output and the disturbance
    (a :class:`jaxnc.loop.Record` function)."""
    return plant.model.C @ x, plant.model.Cbar @ x


def estimated_output_and_disturbance(f: NumreFilter, state: NumreState):
    """(C x, Cbar x) of the estimate used at the instant (after its correction; between
    arrivals the predictions of eq. 15), float scalars (a Record function)."""
    return f.tables.C @ state.xk, f.Cbar @ state.xk


def controller_disturbance_and_multiplicity(c: HddController, state: HddControllerState):
    """(dhat, N): the disturbance estimate and the multiplicity at the last arrival."""
    return state.dhat, state.N


class CtrlState(NamedTuple):
    mrci: MrciState
    dob: DobState


class HddControllerState(NamedTuple):
    cas: CtrlState        # controller states along the last cascade (leading axis h + 1)
    ctrl: CtrlState       # controller state (no-estimator cases)
    ubar: jax.Array       # eq. (21): the last action sent
    k_last: jax.Array     # int32: the last instant the controller worked
    dhat: jax.Array       # disturbance estimate used at k (NaN when it did not work)
    N: jax.Array          # int32: k - k_last at an arrival, 0 otherwise


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HddController(AbstractController):
    """The control side of seed 003: MRCI (eq. 19), the cascade (eq. 14-15) with the
    disturbance model or the DOB (eq. 16), and the controller-side condition (eq. 21-22).

    It works only at an arrival (``fresh``). Without NUMRE (``numre=False``) the estimate
    is the measurement float[1] and one MRCI step gives u_k; the packet repeats it h + 1
    times. With NUMRE the estimate is x(k|k) float[n] and the packet is the cascade's
    u_k..u_{k+h}, started from the law's state at index N = clip(k - k_last, 1, h) of the
    previous cascade (the state it had reached at k). The packet is sent when the
    controller worked and, unless ``tts``, eq. (22) holds on u_k (ubar follows eq. 21).

    Attributes:
      ctrl: :class:`~jaxnc.design.mrci.Mrci`; dob: :class:`~jaxnc.disturbance.Dob`.
      A: float[n, n]; B, C, Cbar: float[n], the prediction model (NUMRE's).
      r: the reference (scalar, constant); sigma_c, delta_c: eq. (22) thresholds.
      h: static horizon (packets of h + 1 actions); numre, use_dob, tts: static switches.

    Records: :func:`controller_disturbance_and_multiplicity` gives (dhat, N) of the instant.
    """

    ctrl: Mrci
    dob: Dob
    A: Any
    B: Any
    C: Any
    Cbar: Any
    r: Any
    sigma_c: Any
    delta_c: Any
    h: int = dataclasses.field(metadata=dict(static=True), default=STEPS - 1)
    numre: bool = dataclasses.field(metadata=dict(static=True), default=True)
    use_dob: bool = dataclasses.field(metadata=dict(static=True), default=False)
    tts: bool = dataclasses.field(metadata=dict(static=True), default=False)

    def __post_init__(self):
        check_int("HddController.h", self.h, 1, 10_000)
        check_nonneg("HddController.sigma_c", self.sigma_c)
        check_nonneg("HddController.delta_c", self.delta_c)

    @property
    def horizon(self) -> int:
        return self.h + 1

    def _init_law(self) -> CtrlState:
        return CtrlState(mrci_init(self.ctrl), dob_init(self.dob))

    def init(self, ctx) -> HddControllerState:
        c0 = self._init_law()
        cas = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (self.h + 1, *a.shape)), c0)
        return HddControllerState(cas, c0, jnp.zeros(()), jnp.zeros((), jnp.int32),
                                  jnp.full((), jnp.nan), jnp.zeros((), jnp.int32))

    def law(self, cs: CtrlState, k, yhat, dhat_model):
        """One period of the control law: (u, next CtrlState, dhat),
        u = MRCI(r - yhat) - dhat, dhat the DOB's output or ``dhat_model``."""
        dhat = dob_output(self.dob, cs.dob, yhat) if self.use_dob else dhat_model
        uc, ms = mrci_step(self.ctrl, cs.mrci, k, self.r - yhat)
        u = uc - dhat
        ds = dob_update(self.dob, cs.dob, u, yhat) if self.use_dob else cs.dob
        return u, CtrlState(ms, ds), dhat

    def _predicted_law(self, cs, k, x):
        return self.law(cs, k, self.C @ x, self.Cbar @ x)

    def step(self, state: HddControllerState, xhat, fresh, k, ctx):
        beta = fresh > 0.5
        h = self.h
        N = jnp.clip(k - state.k_last, 1, h)
        if self.numre:
            cs0 = jax.tree_util.tree_map(lambda a: a[N], state.cas)
            cs0 = jax.tree_util.tree_map(lambda a, b: jnp.where(k == 0, b, a), cs0, self._init_law())
            us, css, dh = cascade(self._predicted_law, self.A, self.B, xhat, cs0, k, h + 1)
            u_new, packet, dhat = us[0], us, dh[0]
            cas = jax.tree_util.tree_map(lambda a, b: jnp.where(beta, a, b), css, state.cas)
            ctrl = state.ctrl
        else:
            u_new, cs1, dhat = self.law(state.ctrl, k, xhat[0], jnp.zeros(()))
            ctrl = jax.tree_util.tree_map(lambda a, b: jnp.where(beta, a, b), cs1, state.ctrl)
            packet = jnp.full(h + 1, u_new)        # no future actions: the actuator holds
            cas = state.cas
        gamma = beta if self.tts else beta & (petc_gap(state.ubar[None], u_new[None], self.sigma_c, self.delta_c) > 0)   # eq. (22)
        new = HddControllerState(cas, ctrl, jnp.where(gamma, u_new, state.ubar), jnp.where(beta, k, state.k_last),
                                 jnp.where(beta, dhat, jnp.nan), jnp.where(beta, k - state.k_last, 0))
        return new, Packet(packet[:, None], (k * ctx.N).astype(jnp.int32)), gamma.astype(jnp.float32)


def runner_loop(loop: HddLoop) -> jl.Loop:
    """The :class:`jaxnc.loop.Loop` of a case (module docstring); traceable (thresholds
    may be tracers, e.g. in the GPI grid)."""
    ctrl = HddController(ctrl=loop.ctrl, dob=loop.dob, A=loop.Af, B=loop.Bf, C=loop.tables.C, Cbar=loop.Cbarf,
                         r=loop.r, sigma_c=loop.sigma_c, delta_c=loop.delta_c, h=loop.h, numre=loop.numre,
                         use_dob=loop.use_dob, tts=loop.tts)
    if loop.numre:
        nf = loop.Af.shape[0]
        est = NumreFilter(loop.tables, loop.Af, loop.Bf, jnp.eye(nf) * P0_SCALE, loop.Cbarf)
    else:
        est = jl.Passthrough()
    trigger = jl.Periodic() if loop.tts else jl.Petc(loop.sigma_s, loop.delta_s, max_silence=loop.k_max)
    # eq. (21)-(22) live in the controller, not in Loop.controller_trigger: that trigger sees
    # every instant (it would move ubar when nothing arrived) and always sends at k = 0
    return jl.Loop(plant=HddPlant(loop.model), trigger=trigger, uplink=jl.Link(), estimator=est, controller=ctrl,
                   downlink=jl.Link(), actuator=jl.PacketActuator(horizon=loop.h + 1),
                   monitor=jl.Monitor(freeze=False), N=1, steps=loop.steps, T=hdd_plant.T,
                   record=jl.Record(plant=output_and_disturbance, controller=controller_disturbance_and_multiplicity,
                                    estimator=estimated_output_and_disturbance if loop.numre else None))


def draws(loop: HddLoop, key, rl: jl.Loop | None = None) -> jl.Draws:
    """The run's draws (:class:`jaxnc.loop.Draws`): ``kw, kv = split(key)``,
    w_k = w_std N(0, 1) and v_k = v_std N(0, 1) (times ``loop.noise``), float[steps] each;
    the links' draws from the runner's streams (:data:`jaxnc.loop.STREAMS`)."""
    rl = runner_loop(loop) if rl is None else rl
    m, S = loop.model, loop.steps
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (S,)) * m.w_std * loop.noise
    v = jax.random.normal(kv, (S,)) * m.v_std * loop.noise
    stream = lambda name: jax.random.fold_in(key, jl.STREAMS.index(name))
    return jl.Draws(w.reshape(S, 1, 1), v.reshape(S, 1), rl.uplink.draw(stream("uplink"), S, rl.T),
                    rl.downlink.draw(stream("downlink"), S, rl.T), stream("plant_init"))


class Trajectory(NamedTuple):
    y: jax.Array           # noise-free output C_p x_k
    y_meas: jax.Array      # measured output
    yhat: jax.Array        # control-side output estimate at k (NaN without estimator)
    u: jax.Array           # applied action
    d: jax.Array           # true disturbance
    dhat: jax.Array        # disturbance estimate at arrival (NaN otherwise)
    beta: jax.Array        # sensor sent
    gamma: jax.Array       # controller sent
    N: jax.Array           # multiplicity at arrival (0 when nothing arrives)
    current: jax.Array     # actuator applies the current action of a packet (k = k_pkt)
    dpred: jax.Array       # the filter's disturbance estimate Cbar x at k (eq. 15; NaN without NUMRE)
    held: jax.Array        # the actuator had no live action (no packet yet, or k - k_pkt > h) and held


def simulate(loop: HddLoop, key) -> Trajectory:
    """One run of ``loop.steps`` periods on :func:`jaxnc.loop.simulate`; pure, jit- and
    vmap-able. ``current`` is True where a packet reached the actuator, and at k = 0
    (k_pkt starts at 0). ``held`` is True where the newest packet to reach the actuator
    (k_pkt) is older than h periods, or none has reached it: there the actuator holds
    its last action."""
    rl = runner_loop(loop)
    tr = jl.simulate(rl, key, draws=draws(loop, key, rl))
    # the plant's record holds (y, d) after each period's step: row k is instant k + 1
    y0, d0 = output_and_disturbance(rl.plant, rl.plant.init(key))
    y = jnp.concatenate([y0[None], tr.parts["plant"][0][:-1]])
    d = jnp.concatenate([d0[None], tr.parts["plant"][1][:-1]])
    nan = jnp.full((loop.steps,), jnp.nan)
    yhat, dpred = tr.parts["estimator"] if loop.numre else (nan, nan)
    dhat, N = tr.parts["controller"]
    k = jnp.arange(loop.steps)
    k_pkt = jax.lax.cummax(jnp.where(tr.recv_ca > 0, k, -1))
    held = (k_pkt < 0) | (k - k_pkt > loop.h)
    return Trajectory(y=y, y_meas=tr.z[:, 0], yhat=yhat, u=tr.u[:, 0], d=d, dhat=dhat, beta=tr.sent_sc > 0.5,
                      gamma=tr.sent_ca > 0.5, N=N, current=(tr.recv_ca > 0) | (k == 0), dpred=dpred, held=held)


# ----------------------------------------------------------------------------- metrics, eq. (23)-(29)


class Metrics(NamedTuple):
    ISE: jax.Array
    ISEP: jax.Array
    NE: jax.Array
    Uc: jax.Array
    Ua: jax.Array
    Cc: jax.Array
    GPI: jax.Array
    n_sc: jax.Array
    n_ca: jax.Array
    unstable: jax.Array
    N_max: jax.Array       # the longest gap between two arrivals (max N, eq. 9)
    n_held: jax.Array      # periods the actuator held for want of a live action (Trajectory.held)


def ise(y, r):
    """Eq. (23): sqrt(sum_k (r_k - y_k)^2)."""
    return jnp.sqrt(jnp.sum((r - y) ** 2))


def isep(y_ets, y_tts):
    """Eq. (24): sqrt(sum_k |y^ETS_k - y^TTS_k|^2)."""
    return jnp.sqrt(jnp.sum((y_ets - y_tts) ** 2))


def cc(uc, cs):
    """Eq. (28): Cc = Uc (1 - CS), as a fraction."""
    return uc * (1.0 - cs)


def gpi(uc, ua, ne, W=(0.45, 0.45, 0.1)):
    """Eq. (29): W1 Uc + W2 Ua + W3 NE (weights of section 5 by default)."""
    return W[0] * uc + W[1] * ua + W[2] * ne


def metrics(loop: HddLoop, traj: Trajectory, y_tts, ise_tts, cs: float, W=(0.45, 0.45, 0.1)) -> Metrics:
    """Eq. (23)-(29) of one run against the noise-free TTS output y_tts (Case 1)."""
    n_sc = jnp.sum(traj.beta)
    n_ca = jnp.sum(traj.gamma)
    uc_ = n_sc / loop.steps                 # N_TTS = steps: TTS sends every period
    ua_ = n_ca / loop.steps
    e = isep(traj.y, y_tts)
    ne = e / ise_tts
    unstable = ~jnp.all(jnp.isfinite(traj.y)) | (jnp.max(jnp.abs(traj.y)) > 100.0 * loop.r)
    inf = jnp.inf
    ne = jnp.where(unstable, inf, ne)
    return Metrics(ISE=ise(traj.y, loop.r), ISEP=jnp.where(unstable, inf, e), NE=ne, Uc=uc_, Ua=ua_,
                   Cc=cc(uc_, cs), GPI=jnp.where(unstable, inf, gpi(uc_, ua_, ne, W)),
                   n_sc=n_sc, n_ca=n_ca, unstable=unstable, N_max=jnp.max(traj.N), n_held=jnp.sum(traj.held))


def tts_reference(steps: int = STEPS, reading: str = "sum", m: int = 2):
    """y^TTS and ISE of Case 1 (deterministic: no noise, no disturbance)."""
    loop = hdd_loop(1, steps=steps, reading=reading, m=m, h=1)
    traj = jax.jit(simulate)(loop, jax.random.PRNGKey(0))
    return traj.y, ise(traj.y, loop.r)


def run(loop: HddLoop, key, y_tts, ise_tts, cs: float, W=(0.45, 0.45, 0.1)) -> Metrics:
    """simulate + metrics; key -> Metrics (vmap over keys for Monte-Carlo)."""
    return metrics(loop, simulate(loop, key), y_tts, ise_tts, cs, W)
