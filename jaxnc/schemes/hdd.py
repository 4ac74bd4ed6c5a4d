"""Seed 003 section 5 (HDD servo), Cases 1-6: :func:`hdd_loop` builds each case's
:class:`jaxnc.loop.Loop` from library parts, and the paper's metrics (eq. 23-29) are
computed on the runner's :class:`jaxnc.loop.Trajectory`.

One period T is the loop's slow period (N = 1). The parts, in the runner's order:

1. Plant: the augmented model of eq. (4), :func:`jaxnc.plants.hdd.hdd_model` (an
   :class:`~jaxnc.loop.LTI`); measurement noise and the disturbance's noise only in
   Cases 4-6 (the runner draws them from the plant's stds).
2. Sensor trigger: every period in TTS (Case 1, :class:`~jaxnc.loop.Periodic`); otherwise
   the PET condition (eq. 5-6) with the time-triggered safety condition (eq. 7, ``k_max``;
   0: off, as in the paper), :class:`~jaxnc.loop.Petc`. The network is ideal both ways.
3. Estimator: none in Cases 1-2 (:class:`~jaxnc.loop.Passthrough`); NUMRE in Cases 3-6
   (:class:`~jaxnc.loop.Numre`, eq. 9-13), on the augmented model (Cases 3-5) or the plant
   alone (Case 6). It propagates with the actions of the packets it sent (``believed``),
   which the ideal downlink delivers at once.
4. Controller: :class:`~jaxnc.loop.Cascade` with the law :class:`MrciLaw`,
   u = MRCI(r - yhat) - dhat (eq. 19; dhat = Cbar x or the DOB's, eq. 16), computed only
   on arrival; with NUMRE the packet is the eq. (14-15) cascade of h + 1 actions, without
   it one action on the measurement, held by the actuator.
5. Controller-side condition (eq. 21-22): ``Loop.controller_trigger`` = Petc(sigma_c,
   delta_c) on the first action, evaluated only when the controller works (section 3.2.4:
   "evaluated only when a measurement is received"); its k = 0 send is the first packet
   (no u-bar before it). TTS sends every packet.
6. Actuator: :class:`~jaxnc.loop.PacketActuator` (h + 1 actions by time stamp; holds past
   the packet's end).

The horizon h defaults to steps - 1 (:func:`whole_run_horizon`, the rule h >= N_max of
section 3.2.1 for any gap; docs/hdd.md). Case 2 of section 5 is PETC; 3 adds NUMRE; 4
noise and disturbance; 5 narrower thresholds; 6 the DOB instead of the disturbance model.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxnc.loop as jl
from jaxnc._validate import check_int, check_range
from jaxnc.design import mrci as mrci_mod
from jaxnc.design.mrci import Mrci, mrci_init, mrci_step
from jaxnc.disturbance import Dob, dob_design, dob_init, dob_output, dob_update
from jaxnc.plants import hdd as hdd_plant

__all__ = ["CASES", "STEPS", "PAPER_THRESHOLDS", "NARROW_THRESHOLDS", "hdd_loop", "MrciLaw", "controller_design",
           "whole_run_horizon", "output", "disturbance", "held", "controller_record", "Metrics", "ise", "isep",
           "cc", "gpi", "metrics", "run", "tts_reference"]

CASES = (1, 2, 3, 4, 5, 6)
PAPER_THRESHOLDS = (100e-7, 1.32e-2)      # section 5: delta_s = sigma_s, delta_c = sigma_c (Fig. 5's optimum)
NARROW_THRESHOLDS = (1e-7, 1e-4)          # Cases 5 and 6
CD_GAIN, CD_ZEROS, CD_POLES = 1.0882, (0.9813, 0.9681, -1.0), (1.0, 0.8496, 0.6137)      # eq. (33)
STEPS = 464              # N_TTS = 464: the study lasts 464 periods (9.28 ms)
# The filter's design (ours, docs/hdd.md): V = (3e-4)^2 in every case, a 1e-6 noise floor on the
# disturbance's slope state, P0 = 1e-6 I; Case 6 models the unknown disturbance as input noise.
FILTER_SLOPE_STD = 1e-6
FILTER_V = hdd_plant.V_STD ** 2
P0_SCALE, FILTER_INPUT_STD = 1e-6, 1e-2


def whole_run_horizon(steps: int = STEPS) -> int:
    """h = steps - 1 (at least 1): a packet sent at k = 0 covers the run, so h >= N_max."""
    check_int("steps", steps, 1)
    return max(steps - 1, 1)


def filter_disturbance_var(w_std: float) -> float:
    """The disturbance noise variance the filter assumes (Cases 3-5): w_std^2, floored at W_STD^2."""
    return max(w_std, hdd_plant.W_STD) ** 2


def controller_design(m: int = 2):
    """MRCI design of eq. (33) at ratio m (eq. 34 for m = 2)."""
    return mrci_mod.decompose(CD_GAIN * np.poly(CD_ZEROS), np.poly(CD_POLES), m)


class MrciLawState(NamedTuple):
    mrci: Any      # MrciState
    dob: Any       # DobState


@jl.pytree_dataclass
class MrciLaw:
    """The law of :class:`~jaxnc.loop.Cascade`: yhat = C x, u = MRCI(r - yhat) - dhat with
    dhat = Cbar x, or the DOB's output on yhat (``use_dob``; eq. 16). Eq. (1) adds d to u,
    so the estimate is subtracted. ``step(s, k, x) -> (u, s_next, dhat)``; C, Cbar float[n]."""

    ctrl: Mrci
    dob: Dob
    C: Any
    Cbar: Any
    r: Any
    use_dob: bool = jl.static_field(False)

    def init(self):
        return MrciLawState(mrci_init(self.ctrl), dob_init(self.dob))

    def step(self, s, k, x):
        yhat = self.C @ x
        dhat = dob_output(self.dob, s.dob, yhat) if self.use_dob else self.Cbar @ x
        uc, ms = mrci_step(self.ctrl, s.mrci, k, self.r - yhat)
        u = uc - dhat
        ds = dob_update(self.dob, s.dob, u, yhat) if self.use_dob else s.dob
        return u, MrciLawState(ms, ds), dhat


def controller_record(c: jl.Cascade, state: jl.CascadeState):
    """(dhat, N): the law's disturbance estimate of the last packet and the multiplicity at
    an arrival (0 otherwise); a :class:`jaxnc.loop.Record` function."""
    return state.aux, state.gap


def hdd_loop(case: int, *, thresholds=None, reading: str = "sum", h: int | None = None, k_max: int = 0, m: int = 2,
             steps: int = STEPS, w_std: float = hdd_plant.W_STD, v_std: float = hdd_plant.V_STD,
             we_form: str = "white", dob_f_hz: float = 300.0, r: float = 1.0) -> jl.Loop:
    """Returns the :class:`jaxnc.loop.Loop` of Case ``case`` (module docstring; N = 1, T = 20 us).

    Args:
      case: 1..6. thresholds: (delta_s = sigma_s, delta_c = sigma_c) >= 0; None: the paper's
        (narrow ones in Cases 5-6). reading: eq. (30)'s reading. h: the cascade horizon
        (packets of h + 1 actions), None: steps - 1. k_max: eq. (7), 0: off, <= h. m: MRCI
        ratio. steps: periods. w_std, v_std: noise stds (Cases 4-6). we_form: NUMRE's We(N).
        dob_f_hz: the DOB's cut-off (Case 6). r: the step reference.

    Raises:
      ValueError naming the argument: case outside 1..6, h outside [1, 10000], k_max
      outside [0, h], thresholds that are not a pair of numbers >= 0, negative stds,
      dob_f_hz outside (0, 25000) Hz (Nyquist), an unknown reading or we_form.
    """
    check_int("case", case, 1, 6)
    check_int("steps", steps, 1)
    h = whole_run_horizon(steps) if h is None else h
    check_int("h", h, 1, 10_000)
    check_int("k_max", k_max, 0, h)
    if thresholds is not None and np.shape(thresholds) != (2,):
        raise ValueError(f"thresholds must be a pair (delta_s = sigma_s, delta_c = sigma_c) or None, got {thresholds!r}")
    ts, tc = (NARROW_THRESHOLDS if case >= 5 else PAPER_THRESHOLDS) if thresholds is None else thresholds
    check_range("dob_f_hz", dob_f_hz, 0.0, 0.5 / hdd_plant.T, low_open=True, high_open=True)
    for name, v, low in (("delta_s = sigma_s", ts, 0.0), ("delta_c = sigma_c", tc, 0.0), ("w_std", w_std, 0.0),
                         ("v_std", v_std, 0.0), ("r", r, None)):
        check_range(name, v, low, None)
    plant = hdd_plant.hdd_model(reading, w_std=w_std * (case >= 4), v_std=v_std * (case >= 4))
    f = lambda a: jnp.asarray(a, jnp.float32)
    ctrl, dob = controller_design(m).as_jax(), dob_design(hdd_plant.T, dob_f_hz)
    if case <= 2:      # the law acts on the measurement itself
        law = MrciLaw(ctrl, dob, f([1.0]), f([0.0]), f(r))
        est, controller, H = jl.Passthrough(), jl.Cascade(law, horizon=1), 1
    else:
        Ap, Bp, Cp = hdd_plant.plant_matrices(reading)
        if case == 6:
            A, B, C, Cbar, Bw, W = Ap, Bp, Cp, np.zeros(Ap.shape[0]), Bp, FILTER_INPUT_STD ** 2
        else:
            A, B, Bw0, C, Cbar = hdd_plant.augment(Ap, Bp, Cp, *hdd_plant.disturbance_matrices())
            Bw = np.zeros((A.shape[0], 2))
            Bw[:, 0], Bw[-2, 1] = Bw0, 1.0
            W = np.diag([filter_disturbance_var(w_std), FILTER_SLOPE_STD ** 2])
        est = jl.Numre.design(A, B, Bw, C, W, FILTER_V, h, cov0=np.eye(A.shape[0]) * P0_SCALE, we_form=we_form)
        law = MrciLaw(ctrl, dob, f(C), f(Cbar), f(r), use_dob=case == 6)
        controller, H = jl.Cascade(law, f(A), f(B), horizon=h + 1), h + 1
    tts = case == 1
    return jl.Loop(plant=plant, trigger=jl.Periodic() if tts else jl.Petc(f(ts), f(ts), max_silence=k_max),
                   uplink=jl.Link(), estimator=est, controller=controller, downlink=jl.Link(),
                   actuator=jl.PacketActuator(horizon=H), controller_trigger=None if tts else jl.Petc(f(tc), f(tc)),
                   monitor=jl.Monitor(freeze=False), N=1, steps=steps, T=hdd_plant.T,
                   record=jl.Record(signals=("x", "u", "z", "xhat", "sent_sc", "sent_ca", "recv_ca"),
                                    controller=controller_record))


def output(loop: jl.Loop, tr: jl.Trajectory):
    """The noise-free output y_k = C x_k, float[steps]."""
    return tr.x @ loop.plant.C[0]


def disturbance(tr: jl.Trajectory):
    """The true disturbance d_k = Cbar x_k (eq. 3), float[steps]."""
    return tr.x @ jnp.asarray(hdd_plant.DISTURBANCE_OUTPUT, tr.x.dtype)


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
    n_held: jax.Array      # periods the actuator had no live action (no packet yet, or past its end)


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


def held(loop: jl.Loop, tr: jl.Trajectory):
    """bool[steps]: the actuator had no live action (no packet yet, or k - k_pkt >= H) and
    held; packets of one action (Cases 1-2) are held by design and never counted."""
    k = jnp.arange(loop.steps)
    if loop.actuator.horizon == 1:
        return k < 0
    k_pkt = jax.lax.cummax(jnp.where(tr.recv_ca > 0, k, -1))
    return (k_pkt < 0) | (k - k_pkt >= loop.actuator.horizon)


def metrics(loop: jl.Loop, tr: jl.Trajectory, *, y_tts, ise_tts, cs: float, W=(0.45, 0.45, 0.1)) -> Metrics:
    """Eq. (23)-(29) of one run against the noise-free TTS output ``y_tts`` (Case 1) and
    its ISE; ``cs`` is the MRCI's computation saving (eq. 20). Uc, Ua: transmissions per
    period (TTS sends every period)."""
    y, r, n_sc, n_ca = output(loop, tr), loop.controller.law.r, jnp.sum(tr.sent_sc), jnp.sum(tr.sent_ca)
    uc_, ua_ = n_sc / loop.steps, n_ca / loop.steps
    unstable = ~jnp.all(jnp.isfinite(y)) | (jnp.max(jnp.abs(y)) > 100.0 * r)
    e = jnp.where(unstable, jnp.inf, isep(y, y_tts))
    ne = e / ise_tts
    return Metrics(ISE=ise(y, r), ISEP=e, NE=ne, Uc=uc_, Ua=ua_, Cc=cc(uc_, cs),
                   GPI=jnp.where(unstable, jnp.inf, gpi(uc_, ua_, ne, W)), n_sc=n_sc, n_ca=n_ca,
                   unstable=unstable, N_max=jnp.max(tr.parts["controller"][1]), n_held=jnp.sum(held(loop, tr)))


#: the per-seed function ``run(loop, key, *, y_tts, ise_tts, cs, W=...) -> Metrics``:
#: :func:`jaxnc.loop.run` with :func:`metrics`
run = functools.partial(jl.run, metrics=metrics)


def tts_reference(steps: int = STEPS, reading: str = "sum", m: int = 2):
    """(y^TTS float[steps], its ISE) of Case 1 (deterministic: no noise, no disturbance)."""
    loop = hdd_loop(1, steps=steps, reading=reading, m=m)
    y = output(loop, jax.jit(jl.simulate)(loop, jax.random.PRNGKey(0)))
    return y, ise(y, loop.controller.law.r)
