"""[Reference copy of jaxnc/schemes/hdd.py at 227619d, the hand-written loop, kept for the
old-vs-new equality test of the runner port; not part of the package.]

Closed loops of seed 003 section 5 (HDD servo), Cases 1-6, one ``lax.scan`` each.

Every fast period T (k = 0..steps-1):

1. The sensor measures y_k = C x_k + v_k. It sends (beta_k = 1) every period in TTS
   (Case 1); otherwise when the PET condition (eq. 6), ||ybar_{k-1} - y_k||^2 >
   sigma_s ||y_k||^2 + delta_s, holds, or when the time-triggered safety condition
   (eq. 7) k - k_lm >= k_max holds (k_max = 0: off, as in the paper's example). The
   first sample is always sent. ybar follows eq. (5). The network is ideal (no loss,
   no delay), as in the paper's TrueTime study.
2. On arrival the control side works (only then, section 2):
   * without estimator (Cases 1-2): e_k = r_k - y_k and one MRCI step (eq. 19, Fig. 4);
   * with NUMRE (Cases 3-6): multiplicity N = k - k_ls (eq. 9), correction with K(N)
     (eq. 11-12), then the cascade (eq. 14-15): for l = 0..h, yhat = C xhat(k+l|k),
     dhat = Cbar xhat(k+l|k) (Cases 3-5, disturbance model known) or the DOB output
     (Case 6, eq. 16), u_{k+l} = MRCI(r_{k+l} - yhat) - dhat, xhat <- A xhat + B u.
     The control action *compensates* the disturbance: eq. (1) adds d to u, so the
     estimate is subtracted (the paper says "summed", which we read as summed with sign).
3. The controller-side condition (eq. 21-22), ||ubar_{k-1} - u_k||^2 > sigma_c ||u_k||^2 +
   delta_c, decides whether the packet {u_k..u_{k+h}} goes to the actuator (gamma_k);
   TTS always sends. The actuator applies the current action of the newest packet, or
   the future one for the present instant (section 3.2.4), holding the last beyond h.
4. The controller's own state at the next arrival is the one its last cascade reached
   at that instant (the MRCI and DOB states along the cascade are kept). The estimator's
   prior x(k|k-N) is propagated with the actions actually applied (the control side
   knows them: the network is ideal); this is eq. (14) evaluated period by period.

Cases (section 5): 1 TTS; 2 PETC; 3 PETC + NUMRE; 4 = 3 + noise + disturbance;
5 = 4 with narrower thresholds; 6 = 5 with a DOB instead of the disturbance model.
Noises are drawn up front from the key (common random numbers across cases).
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, check_nonneg, check_range
from jaxnc.design import mrci as mrci_mod
from jaxnc.design.mrci import Mrci, MrciState, mrci_init, mrci_step
from jaxnc.disturbance import Dob, DobState, dob_design, dob_init, dob_output, dob_update
from jaxnc.estimators.numre import NumreTables, numre_correct, numre_tables
from jaxnc.plants import hdd as hdd_plant

__all__ = ["CASES", "PAPER_THRESHOLDS", "NARROW_THRESHOLDS", "HddLoop", "hdd_loop", "simulate", "run",
           "Trajectory", "Metrics", "ise", "isep", "gpi", "cc", "petc_fires", "controller_fires"]

CASES = (1, 2, 3, 4, 5, 6)
# Section 5: delta_s = sigma_s = 100e-7, delta_c = sigma_c = 1.32e-2 (the GPI optimum, Fig. 5);
# Case 5 (and 6): delta_s = sigma_s = 1e-7, delta_c = sigma_c = 1e-4.
PAPER_THRESHOLDS = (100e-7, 1.32e-2)
NARROW_THRESHOLDS = (1e-7, 1e-4)
# Eq. (33).
CD_GAIN, CD_ZEROS, CD_POLES = 1.0882, (0.9813, 0.9681, -1.0), (1.0, 0.8496, 0.6137)
STEPS = 464              # N_TTS = 464 in Case 1: the study lasts 464 periods (9.28 ms)
H_DEFAULT = 64           # cascade horizon h (ours; the paper gives none)
# Filter design covariances (ours). The filter's process noise is the true one plus a
# floor on the disturbance slope state x1 (eq. 32 drives only x2): without it the
# filter stops adapting to a ramp. Measurement noise V = (3e-4)^2 even when the
# simulation has none (Cases 1-3), so K(N) is defined.
FILTER_SLOPE_STD = 1e-6
FILTER_V = hdd_plant.V_STD ** 2


def filter_disturbance_var(w_std: float) -> float:
    """Variance of the disturbance noise the filter assumes (Cases 3-5): the true one,
    floored at the default level so that the filter keeps adapting when the truth has less."""
    return max(w_std, hdd_plant.W_STD) ** 2


# Case 6: the plant-only filter models the unknown disturbance as input noise of this std.
FILTER_INPUT_STD = 1e-2


def petc_fires(ybar, y, sigma, delta):
    """Eq. (6): ||ybar_{k-1} - y_k||^2 > sigma ||y_k||^2 + delta."""
    return (ybar - y) ** 2 > sigma * y * y + delta


def controller_fires(ubar, u, sigma, delta):
    """Eq. (22): ||ubar_{k-1} - u_k||^2 > sigma ||u_k||^2 + delta."""
    return (ubar - u) ** 2 > sigma * u * u + delta


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
    h: int = dataclasses.field(metadata=dict(static=True), default=H_DEFAULT)
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


def hdd_loop(case: int, *, thresholds=None, reading: str = "sum", h: int = H_DEFAULT, k_max: int = 0,
             m: int = 2, steps: int = STEPS, w_std: float = hdd_plant.W_STD, v_std: float = hdd_plant.V_STD,
             we_form: str = "white", dob_f_hz: float = 300.0, r: float = 1.0) -> HddLoop:
    """Validated configuration of Case ``case`` (section 5); ``thresholds`` = (d_s = s_s, d_c = s_c)."""
    check_int("case", case, 1, 6)
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


class CtrlState(NamedTuple):
    mrci: MrciState
    dob: DobState


class Carry(NamedTuple):
    x: jax.Array           # true augmented state
    ybar: jax.Array        # eq. (5)
    k_lm: jax.Array        # last instant the sensor sent
    xhat: jax.Array        # filter prior x(k|k_lm), propagated with the applied actions
    P: jax.Array           # filter posterior covariance at k_lm
    cas: CtrlState         # controller states along the last cascade (leading axis h + 1)
    ctrl: CtrlState        # controller state (no-estimator cases)
    packet: jax.Array      # (h + 1,) actions of the newest packet at the actuator
    k_pkt: jax.Array       # its time stamp
    ubar: jax.Array        # eq. (21)


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


def _ctrl_law(loop: HddLoop, cs: CtrlState, k, r, yhat, dhat_model):
    """One period of the control side: (u, next CtrlState, dhat)."""
    if loop.use_dob:
        dhat = dob_output(loop.dob, cs.dob, yhat)
    else:
        dhat = dhat_model
    uc, ms = mrci_step(loop.ctrl, cs.mrci, k, r - yhat)
    u = uc - dhat
    ds = dob_update(loop.dob, cs.dob, u, yhat) if loop.use_dob else cs.dob
    return u, CtrlState(ms, ds), dhat


def _cascade(loop: HddLoop, x0, cs0: CtrlState, k):
    """Eq. (14)-(15) with the MRCI: actions u_k..u_{k+h} and the controller states at k..k+h."""
    def body(c, l):
        x, cs = c
        u, cs_next, dhat = _ctrl_law(loop, cs, k + l, loop.r, loop.tables.C @ x, loop.Cbarf @ x)
        return (loop.Af @ x + loop.Bf * u, cs_next), (u, cs, dhat)
    _, (us, css, dh) = jax.lax.scan(body, (x0, cs0), jnp.arange(loop.h + 1))
    return us, css, dh[0]


def _init_ctrl(loop: HddLoop) -> CtrlState:
    return CtrlState(mrci_init(loop.ctrl), dob_init(loop.dob))


def simulate(loop: HddLoop, key) -> Trajectory:
    """One run of ``loop.steps`` fast periods; pure, jit- and vmap-able."""
    m = loop.model
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (loop.steps,)) * m.w_std * loop.noise
    v = jax.random.normal(kv, (loop.steps,)) * m.v_std * loop.noise
    nx, nf, h = m.A.shape[0], loop.Af.shape[0], loop.h
    c0 = _init_ctrl(loop)
    carry = Carry(x=jnp.zeros(nx), ybar=jnp.zeros(()), k_lm=jnp.zeros((), jnp.int32),
                  xhat=jnp.zeros(nf), P=jnp.eye(nf) * 1e-6,
                  cas=jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (h + 1, *a.shape)), c0),
                  ctrl=c0, packet=jnp.zeros(h + 1), k_pkt=jnp.zeros((), jnp.int32), ubar=jnp.zeros(()))
    Cp = m.C

    def step(c: Carry, inp):
        k, wk, vk = inp
        y = Cp @ c.x + vk
        if loop.tts:
            beta = jnp.bool_(True)
        else:
            beta = petc_fires(c.ybar, y, loop.sigma_s, loop.delta_s) | (k == 0)
            if loop.k_max > 0:
                beta = beta | (k - c.k_lm >= loop.k_max)                      # eq. (7)
        N = jnp.clip(k - c.k_lm, 1, h)
        if loop.numre:
            xpost, Ppost, _ = numre_correct(loop.tables, c.xhat, c.P, y, N)
            cs0 = jax.tree_util.tree_map(lambda a: a[N], c.cas)
            cs0 = jax.tree_util.tree_map(lambda a, b: jnp.where(k == 0, b, a), cs0, _init_ctrl(loop))
            us, css, dhat = _cascade(loop, xpost, cs0, k)
            u_new = us[0]
            new_packet = us
            yhat = loop.tables.C @ jnp.where(beta, xpost, c.xhat)
            cas = jax.tree_util.tree_map(lambda a, b: jnp.where(beta, a, b), css, c.cas)
            ctrl = c.ctrl
        else:
            u_new, cs1, dhat = _ctrl_law(loop, c.ctrl, k, loop.r, y, jnp.zeros(()))
            ctrl = jax.tree_util.tree_map(lambda a, b: jnp.where(beta, a, b), cs1, c.ctrl)
            new_packet = jnp.full(h + 1, u_new)        # no future actions: the actuator holds
            yhat = jnp.full((), jnp.nan)
            cas = c.cas
            xpost, Ppost = c.xhat, c.P
        if loop.tts:
            gamma = beta
        else:
            gamma = beta & controller_fires(c.ubar, u_new, loop.sigma_c, loop.delta_c)
        packet = jnp.where(gamma, new_packet, c.packet)
        k_pkt = jnp.where(gamma, k, c.k_pkt)
        ubar = jnp.where(gamma, u_new, c.ubar)
        u = packet[jnp.clip(k - k_pkt, 0, h)]
        x_now = jnp.where(beta, xpost, c.xhat)
        out = Trajectory(y=Cp @ c.x, y_meas=y, yhat=yhat, u=u, d=m.Cbar @ c.x,
                         dhat=jnp.where(beta, dhat, jnp.nan), beta=beta, gamma=gamma,
                         N=jnp.where(beta, k - c.k_lm, 0), current=(k == k_pkt))
        c = Carry(x=m.step(c.x, u, wk), ybar=jnp.where(beta, y, c.ybar), k_lm=jnp.where(beta, k, c.k_lm),
                  xhat=loop.Af @ x_now + loop.Bf * u, P=jnp.where(beta, Ppost, c.P), cas=cas, ctrl=ctrl,
                  packet=packet, k_pkt=k_pkt, ubar=ubar)
        return c, out

    ks = jnp.arange(loop.steps, dtype=jnp.int32)
    _, traj = jax.lax.scan(step, carry, (ks, w, v))
    return traj


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
                   n_sc=n_sc, n_ca=n_ca, unstable=unstable)


def tts_reference(steps: int = STEPS, reading: str = "sum", m: int = 2):
    """y^TTS and ISE of Case 1 (deterministic: no noise, no disturbance)."""
    loop = hdd_loop(1, steps=steps, reading=reading, m=m, h=1)
    traj = jax.jit(simulate)(loop, jax.random.PRNGKey(0))
    return traj.y, ise(traj.y, loop.r)


def run(loop: HddLoop, key, y_tts, ise_tts, cs: float, W=(0.45, 0.45, 0.1)) -> Metrics:
    """simulate + metrics; key -> Metrics (vmap over keys for Monte-Carlo)."""
    return metrics(loop, simulate(loop, key), y_tts, ise_tts, cs, W)
