"""Model-based dual-rate controller design (Salt & Albertos 2005; seed 004, eq. 21-22, 28-31).

Given a continuous plant G_p(s), a continuous controller C(s) (here the PI of eq. 27),
the fast period T and the multiplicity N, the desired closed loop is

    M(s) = C(s) G_p(s) / (1 + C(s) G_p(s))

and the dual-rate controller is the cascade of (section 3.4)

* a slow sub-controller at NT, driven by the error sampled at NT,
      G_1(z^N) = 1 / (1 - M^{NT}(z^N))                                   (eq. 21)
* a hold that repeats its output N times (H(z) = (1 - z^-N)/(1 - z^-1)),
* a fast sub-controller at T,
      G_2(z) = M^T(z) / G_p^T(z)                                          (eq. 22)

with M^T, M^{NT}, G_p^T the ZOH discretisations.  Why it works: G_2 G_p^T = M^T, so the
path from the held slow signal to the plant output is M(s) sampled with a ZOH of NT,
i.e. M^{NT}; closing the slow loop through G_1 gives G_1 M^{NT} / (1 + G_1 M^{NT}) =
M^{NT}: at the sensing instants the loop reproduces the continuous design exactly.

The transfer-function algebra runs once, at configuration time, with python-control and
numpy (float64).  What runs inside a ``lax.scan`` is :class:`DiscreteSS` (a state-space
realisation with float32 leaves) and :class:`DualRateController`.

Conventions: a discrete transfer function is a pair of coefficient arrays in descending
powers of z (python-control's), normalised so that the denominator is monic.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_int, check_positive

if TYPE_CHECKING:
    import control

__all__ = [
    "pi_controller", "closed_loop", "c2d_zoh", "DualRateDesign", "dualrate_design",
    "single_rate_pi", "DiscreteSS", "DualRateController", "DualRateState",
]

# Leading coefficients below this (relative to the largest) are round-off of exact zeros.
_TRIM_RTOL = 1e-10


def _control():
    """python-control, imported on first use."""
    import control
    return control


def _trim(p) -> np.ndarray:
    p = np.atleast_1d(np.asarray(p, np.float64))
    scale = np.max(np.abs(p)) if p.size else 0.0
    nz = np.nonzero(np.abs(p) > _TRIM_RTOL * scale)[0]
    return p[nz[0]:] if nz.size else np.zeros(1)


def _num_den(sys) -> tuple[np.ndarray, np.ndarray]:
    num, den = _control().tfdata(sys)
    return _trim(num[0][0]), _trim(den[0][0])


def _monic(num, den) -> tuple[np.ndarray, np.ndarray]:
    num, den = _trim(num), _trim(den)
    return num / den[0], den / den[0]


def _tf(num, den, dt=None) -> control.TransferFunction:
    num, den = _monic(num, den)
    return _control().tf(num, den) if dt is None else _control().tf(num, den, dt)


def _check_continuous_siso(name: str, sys) -> None:
    """ValueError naming ``name`` unless ``sys`` is a continuous-time SISO python-control system."""
    ct = _control()
    if not isinstance(sys, (ct.TransferFunction, ct.StateSpace)):
        raise ValueError(f"dualrate_design: {name} must be a python-control TransferFunction or StateSpace, "
                         f"got {type(sys).__name__}")
    if sys.ninputs != 1 or sys.noutputs != 1:
        raise ValueError(f"dualrate_design: {name} must be SISO, got {sys.noutputs} outputs x {sys.ninputs} inputs")
    if ct.isdtime(sys, strict=True):
        raise ValueError(f"dualrate_design: {name} must be continuous-time (dt = 0), got dt = {sys.dt}")


def pi_controller(Kp: float, Ti: float) -> control.TransferFunction:
    """Continuous PI of eq. (27): C(s) = Kp (1 + 1/(Ti s)) = Kp (Ti s + 1) / (Ti s)."""
    check_positive("Kp", Kp)
    check_positive("Ti", Ti)
    return _control().tf([Kp * Ti, Kp], [Ti, 0.0])


def closed_loop(Gp: control.TransferFunction, C: control.TransferFunction) -> control.TransferFunction:
    """M(s) = C Gp / (1 + C Gp) by polynomial algebra (no cancellation is attempted)."""
    nc, dc = _num_den(C)
    ng, dg = _num_den(Gp)
    num = np.polymul(nc, ng)
    den = np.polyadd(np.polymul(dc, dg), num)
    return _tf(num, den)


def c2d_zoh(sys: control.TransferFunction, Ts: float) -> control.TransferFunction:
    """ZOH discretisation at period Ts (python-control ``sample_system``), monic denominator."""
    check_positive("Ts", Ts)
    num, den = _num_den(_control().sample_system(sys, Ts, method="zoh"))
    return _tf(num, den, Ts)


@dataclasses.dataclass(frozen=True)
class DualRateDesign:
    """Result of :func:`dualrate_design` (configuration time, python-control objects)."""

    M: control.TransferFunction      # desired closed loop M(s)
    MT: control.TransferFunction     # M^T(z), ZOH at T
    MNT: control.TransferFunction    # M^{NT}(z^N), ZOH at NT (a polynomial in the NT operator)
    GpT: control.TransferFunction    # G_p^T(z), ZOH at T, eq. (5)
    G1: control.TransferFunction     # eq. (21), runs at NT
    G2: control.TransferFunction     # eq. (22), runs at T
    T: float
    N: int

    def coefficients(self) -> dict:
        """Monic numerator/denominator coefficients of G1 and G2 (compare with eq. 28-29)."""
        g1n, g1d = _num_den(self.G1)
        g2n, g2d = _num_den(self.G2)
        return {"G1": (g1n, g1d), "G2": (g2n, g2d)}


def dualrate_design(Gp: control.TransferFunction, C: control.TransferFunction, T: float, N: int) -> DualRateDesign:
    """Salt & Albertos' model-based dual-rate design, eq. (21)-(22).

    ``Gp`` and ``C`` are continuous SISO transfer functions (``Gp`` nonzero), ``T`` the
    fast (actuation) period and ``N`` the multiplicity (sensing period NT).  G_2 inverts
    G_p^T, so G_p^T must have relative degree 1 (G_2 proper), its zeros must lie inside
    the unit circle (G_2 stable) and so must its poles: G_2 = M^T / G_p^T has G_p^T's
    poles as zeros, which cancel them, and a cancelled pole on or outside the unit circle
    stays in the loop as a hidden mode (a closed-loop eigenvalue e^{p N T} of the lifted
    loop for a plant pole p; for an integrator, a pole at 1: under a constant input
    disturbance the controller's states ramp without bound and the output keeps an
    offset), so ``Gp`` must be stable (poles in the open left half-plane), and ``C`` must
    stabilise it (M's poles in the open left half-plane: the loop reproduces M).  Otherwise
    ValueError.  G_1 has a pole at z = 1 whenever M(0) = 1 (C has integral action): the
    integral action of the dual-rate loop.
    """
    check_positive("T", T)
    check_int("N", N, 1, 1000)
    for name, sys in (("Gp", Gp), ("C", C)):
        _check_continuous_siso(name, sys)
    gn, gd = _num_den(Gp)
    if not np.any(gn):
        raise ValueError("dualrate_design: Gp must be nonzero (G2 = M^T / Gp^T inverts it)")
    if len(gn) > len(gd):
        raise ValueError(f"dualrate_design: Gp must be proper, got numerator degree {len(gn) - 1} > denominator "
                         f"degree {len(gd) - 1}")
    poles = np.roots(gd)
    if np.any(np.real(poles) >= 0.0):
        raise ValueError(f"dualrate_design: Gp must be stable (poles in the open left half-plane), got poles {poles}: "
                         f"G2 = M^T / Gp^T cancels Gp^T's poles {np.exp(poles * T)} on or outside the unit circle, "
                         "and the loop keeps them as hidden modes (internally unstable)")
    M = closed_loop(Gp, C)
    m_poles = np.roots(_num_den(M)[1])
    if np.any(np.real(m_poles) >= 0.0):
        raise ValueError(f"dualrate_design: C must stabilise Gp: the closed loop M = C Gp / (1 + C Gp) has poles "
                         f"{m_poles}, not all in the open left half-plane (the dual-rate loop reproduces M)")
    MT, MNT, GpT = c2d_zoh(M, T), c2d_zoh(M, N * T), c2d_zoh(Gp, T)
    mn, md = _num_den(MNT)
    g1_den = np.polysub(md, mn)
    G1 = _tf(md, g1_den, N * T)
    tn, td = _num_den(MT)
    pn, pd = _num_den(GpT)
    rel_p = len(pd) - len(pn)
    rel_m = len(td) - len(tn)
    if rel_m < rel_p:
        raise ValueError(f"G2 = M^T / Gp^T is improper: Gp^T has relative degree {rel_p}, M^T only {rel_m}")
    zeros = np.roots(pn) if len(pn) > 1 else np.zeros(0)
    if np.any(np.abs(zeros) >= 1.0):
        raise ValueError(f"G2 = M^T / Gp^T would be unstable: Gp^T has zeros {zeros} outside the unit circle")
    G2 = _tf(np.polymul(tn, pd), np.polymul(td, pn), T)
    return DualRateDesign(M=M, MT=MT, MNT=MNT, GpT=GpT, G1=G1, G2=G2, T=float(T), N=int(N))


def single_rate_pi(Kp: float, Ti: float, Ts: float) -> control.TransferFunction:
    """PI of eq. (27) discretised by forward rectangular integration at Ts, eq. (30)-(31):

        G_r(z) = Kp (z - 1 + Ts/Ti) / (z - 1),

    e.g. (6z - 1)/(z - 1) at T = 0.1 s and (6z + 4)/(z - 1) at NT = 0.2 s for Kp = 6, Ti = 0.12.
    """
    check_positive("Kp", Kp)
    check_positive("Ti", Ti)
    check_positive("Ts", Ts)
    return _control().tf([Kp, Kp * (Ts / Ti - 1.0)], [1.0, -1.0], Ts)


# ----------------------------------------------------------------------------- runtime (JAX)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiscreteSS:
    """x' = A x + B e, y = C x + D e (single input, single output), float32 leaves.

    Built from a proper discrete transfer function by :meth:`from_tf` (controllable
    canonical form of ``scipy.signal.tf2ss`` via python-control), which keeps its sampling
    period as ``dt`` (static, seconds; None: not known), so that a part running it can check
    it runs at that period.  ``step`` works on a batch of independent channels (e.g. the
    two wheels): ``x[..., n]``, ``e[...]``.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array
    dt: float | None = dataclasses.field(default=None, metadata=dict(static=True))

    @staticmethod
    def from_tf(sys: control.TransferFunction) -> "DiscreteSS":
        num, den = _num_den(sys)
        if len(num) > len(den):
            raise ValueError("DiscreteSS.from_tf: the transfer function is improper")
        ss = _control().tf2ss(_tf(num, den, sys.dt))
        f = lambda a: np.asarray(a, np.float32)
        dt = None if sys.dt in (None, True) else float(sys.dt)
        return DiscreteSS(A=f(ss.A), B=f(ss.B).reshape(-1), C=f(ss.C).reshape(-1), D=f(ss.D).reshape(()), dt=dt)

    @property
    def order(self) -> int:
        return int(self.A.shape[0])

    def init(self, batch: tuple = ()) -> jax.Array:
        return jnp.zeros(batch + (self.order,), jnp.float32)

    def step(self, x, e):
        """One sample: returns (y, x_next), in the state's dtype (float32 from :meth:`init`; a
        float64 ``e`` under x64 made x_next float64 and a scan over steps failed)."""
        e = jnp.asarray(e, jnp.result_type(x))
        y = jnp.einsum("...j,j->...", x, self.C) + self.D * e
        x_next = jnp.einsum("ij,...j->...i", self.A, x) + jnp.einsum("i,...->...i", self.B, e)
        return y, x_next


class DualRateState(NamedTuple):
    g1: jax.Array   # [..., n1] slow sub-controller state
    g2: jax.Array   # [..., n2] fast sub-controller state


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DualRateController:
    """Runtime form of the dual-rate controller: G1 at NT, hold, G2 at T (section 3.4).

    Raises ValueError for N outside [1, 1000] or, when G1 and G2 know their periods
    (``DiscreteSS.dt``), an N that is not G1's period over G2's."""

    G1: DiscreteSS
    G2: DiscreteSS
    N: int = dataclasses.field(default=1, metadata=dict(static=True))

    def __post_init__(self):
        check_int("DualRateController.N", self.N, 1, 1000)
        d1, d2 = getattr(self.G1, "dt", None), getattr(self.G2, "dt", None)
        if d1 is not None and d2 is not None and abs(d1 - self.N * d2) > 1e-9 * max(d1, self.N * d2):
            raise ValueError(f"DualRateController.N must be G1's period over G2's, {d1:g} s / {d2:g} s = "
                             f"{d1 / d2:g}, got N={self.N}")

    @staticmethod
    def from_design(design: DualRateDesign) -> "DualRateController":
        return DualRateController(G1=DiscreteSS.from_tf(design.G1), G2=DiscreteSS.from_tf(design.G2), N=design.N)

    def init(self, batch: tuple = ()) -> DualRateState:
        return DualRateState(self.G1.init(batch), self.G2.init(batch))

    def __call__(self, state: DualRateState, e):
        """Slow-period step from the error e_k^{NT} (shape [...]): returns the N fast
        actions u_{k..k+N-1} (shape [N, ...]) and the new state.  G1 runs once; its
        output is held (expanded + digital hold) and G2 runs N times on it."""
        u1, g1 = self.G1.step(state.g1, e)

        def fast(x2, _):
            u, x2 = self.G2.step(x2, u1)
            return x2, u

        g2, us = jax.lax.scan(fast, state.g2, None, length=self.N)
        return us, DualRateState(g1, g2)
