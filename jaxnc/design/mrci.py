"""Multi-rate controller with interlacing (MRCI), seed 003 section 3.2.3, eq. (19)-(20).

Design time (numpy/scipy, plain Python): a proper SISO controller C(z) = b(z)/a(z) at the
fast period T is split into partial fractions, one *mode* per real pole and one
second-order real block per complex-conjugate pair. Modes whose pole radius is at least
``slow_radius`` are *slow*; the others, together with the direct term D, are the *fast*
part. Each slow mode {A_i, B_i, C_i, D_i} is converted to the m-times slower rate by
eq. (19),

    C^s_i(z^m) = C_i (z^m I - A_i^m)^{-1} (sum_{j=0}^{m-1} A_i^{m-1-j} B_i) + D_i,

i.e. its state is updated once every m fast periods with the (down-sampled, held) error;
its output is held by a ZOH. Slow mode i (1-based) is updated at the fast instants
k = m j + i - 1 (interlacing, Fig. 4), so the slow work is spread over the m phases.
Computation saving, eq. (20): CS = (m - 1)/(m + n), n the number of fast modes, for m
slow modes (:func:`computation_saving` counts any number of them).

Run time (JAX): :func:`mrci_step` is one fast period of the interlaced controller; with
m = 1 every mode is updated every period and the sum of the modes is exactly C(z).

Repeated poles are not supported (a ValueError): they would need Jordan blocks, and
no controller of the seeds has them.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_finite, check_int, check_range

__all__ = ["Mode", "MrciDesign", "Mrci", "MrciState", "partial_fractions", "decompose",
           "computation_saving", "mrci_init", "mrci_step"]


@dataclasses.dataclass(frozen=True)
class Mode:
    """One partial-fraction mode in state-space form (numpy), with its pole(s)."""
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: float
    poles: np.ndarray

    @property
    def radius(self) -> float:
        return float(np.max(np.abs(self.poles)))

    def slow_rate(self, m: int) -> "Mode":
        """Eq. (19): the mode at period mT, A -> A^m, B -> sum_j A^{m-1-j} B."""
        Am = np.linalg.matrix_power(self.A, m)
        Bm = sum(np.linalg.matrix_power(self.A, m - 1 - j) @ self.B for j in range(m))
        return Mode(Am, Bm, self.C, self.D, self.poles ** m)

    def tf(self) -> tuple[np.ndarray, np.ndarray]:
        """(num, den), polynomials in the mode's own shift variable (z, or z^m after slow_rate)."""
        import scipy.signal
        num, den = scipy.signal.ss2tf(self.A, self.B.reshape(-1, 1), self.C.reshape(1, -1),
                                         np.array([[self.D]]))
        return np.real_if_close(num[0]), np.real_if_close(den)


def partial_fractions(num, den, *, tol: float = 1e-8) -> tuple[list[Mode], float]:
    """C(z) = num(z)/den(z) (positive powers of z, proper) -> (modes, direct term D).

    A real pole p with residue r gives the mode (A, B, C) = (p, 1, r); a complex pair
    p, conj(p) gives the real block with characteristic polynomial z^2 - 2 Re(p) z + |p|^2
    in controllable canonical form. Raises ValueError for non-finite coefficients, an
    improper C or repeated poles.
    """
    import scipy.signal
    for name, c in (("num", num), ("den", den)):
        check_finite(name, c)
    num = np.trim_zeros(np.atleast_1d(np.asarray(num, float)), "f")
    den = np.trim_zeros(np.atleast_1d(np.asarray(den, float)), "f")
    if len(num) > len(den):
        raise ValueError(f"controller must be proper: numerator degree {len(num) - 1} > denominator degree {len(den) - 1}")
    r, p, k = scipy.signal.residue(num, den)
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            if abs(p[i] - p[j]) < 1e-6 * max(1.0, abs(p[i])):
                raise ValueError(f"repeated pole {p[i]:.6g}: MRCI decomposition supports distinct poles only")
    D = float(np.real(k[0])) if len(k) else 0.0
    modes = []
    used = np.zeros(len(p), bool)
    for i, (ri, pi) in enumerate(zip(r, p)):
        if used[i]:
            continue
        used[i] = True
        if abs(pi.imag) <= tol * max(1.0, abs(pi)):
            modes.append(Mode(np.array([[pi.real]]), np.array([1.0]), np.array([ri.real]), 0.0,
                              np.array([pi.real])))
            continue
        j = next(j for j in range(len(p)) if not used[j] and abs(p[j] - np.conj(pi)) < 1e-6 * abs(pi))
        used[j] = True
        # r/(z-p) + conj(r)/(z-conj p) = (b1 z + b0) / (z^2 + a1 z + a0)
        b1, b0 = 2 * ri.real, -2 * (ri * np.conj(pi)).real
        a1, a0 = -2 * pi.real, abs(pi) ** 2
        modes.append(Mode(np.array([[0.0, 1.0], [-a0, -a1]]), np.array([0.0, 1.0]), np.array([b0, b1]), 0.0,
                          np.array([pi, np.conj(pi)])))
    return modes, D


def computation_saving(m: int, n: int, n_slow: int | None = None) -> float:
    """Computation saving, as a fraction: the share of the mode updates per fast period that
    running ``n_slow`` slow modes once every ``m`` periods (and ``n`` fast dynamics every
    period) saves, n_slow (m - 1) / (m (n_slow + n)).  With ``n_slow = m`` (the default,
    one slow mode per phase) it is eq. (20), CS = (m - 1)/(m + n); with m = 1 it is 0."""
    n_slow = m if n_slow is None else n_slow
    total = n_slow + n
    return 0.0 if total == 0 else n_slow * (m - 1) / (m * total)


@dataclasses.dataclass(frozen=True)
class MrciDesign:
    """Result of :func:`decompose` (numpy): slow modes at period mT, fast modes at T."""
    m: int
    slow: tuple            # Mode at the slow rate (after eq. 19), in interlacing order
    slow_fast_rate: tuple  # the same modes before conversion
    fast: tuple            # Mode at the fast rate
    D: float               # direct term, part of the fast controller

    @property
    def n_fast(self) -> int:
        """Number of fast dynamics n of eq. (20): the fast modes, or 1 for a lone direct term."""
        return max(len(self.fast), 1 if self.D != 0.0 else 0)

    @property
    def cs(self) -> float:
        """Computation saving CS of eq. (20), a fraction: :func:`computation_saving` of this
        design's rate ratio m, its slow modes and its fast dynamics (eq. 20 itself when there
        are m slow modes; 0 for m = 1, where every mode runs every period)."""
        return computation_saving(self.m, self.n_fast, len(self.slow))

    def fast_tf(self) -> tuple[np.ndarray, np.ndarray]:
        """C^f(z): the sum of the fast modes and D, as (num, den) in z."""
        num, den = np.array([self.D]), np.array([1.0])
        for md in self.fast:
            n_i, d_i = md.tf()
            num = np.polyadd(np.polymul(num, d_i), np.polymul(n_i, den))
            den = np.polymul(den, d_i)
        return np.trim_zeros(num, "f"), den

    def slow_tfs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """[C^s_i(z^m)] as (num, den) polynomials in z^m, eq. (19)/(34)."""
        return [md.tf() for md in self.slow]

    def as_jax(self, dtype=jnp.float32) -> "Mrci":
        """The runtime arrays (float32 by default; float64 inside ``jax.enable_x64``)."""
        return _pack(self, dtype)


def decompose(num, den, m: int, *, slow_radius: float = 0.8) -> MrciDesign:
    """Split C(z) into slow modes (pole radius >= slow_radius) at rate 1/(mT) and fast modes.

    Seed 003 eq. (33) with m = 2 and the default slow_radius gives eq. (34).
    """
    check_int("m", m, 1)
    check_range("slow_radius", slow_radius, 0.0, None)
    modes, D = partial_fractions(num, den)
    slow = [md for md in modes if md.radius >= slow_radius]
    fast = [md for md in modes if md.radius < slow_radius]
    slow.sort(key=lambda md: -md.radius)     # the slowest first: C^s_1 is the integrator in eq. (34)
    return MrciDesign(m=m, slow=tuple(md.slow_rate(m) for md in slow), slow_fast_rate=tuple(slow),
                      fast=tuple(fast), D=D)


# ----------------------------------------------------------------------------- JAX runtime


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mrci:
    """Interlaced controller as arrays: slow modes stacked block-diagonally, fast part as one system.

    Slow: states ``xs`` with ``As`` (block-diag of A_i^m), ``Bs``; ``Cs`` maps them to the
    per-mode outputs, ``Ds`` the per-mode direct terms; ``state_phase``/``mode_phase`` give
    the phase (k mod m) at which a state/mode is updated. Fast: ``Af, Bf, Cf, Df``.
    """
    As: jax.Array
    Bs: jax.Array
    Cs: jax.Array
    Ds: jax.Array
    state_phase: jax.Array
    mode_phase: jax.Array
    Af: jax.Array
    Bf: jax.Array
    Cf: jax.Array
    Df: jax.Array
    m: int = dataclasses.field(metadata=dict(static=True), default=1)


class MrciState(NamedTuple):
    xs: jax.Array      # slow-mode states
    us: jax.Array      # held slow-mode outputs (ZOH at period T)
    xf: jax.Array      # fast-part state


def _blockdiag(blocks, n):
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        k = b.shape[0]
        out[i:i + k, i:i + k] = b
        i += k
    return out


def _pack(d: MrciDesign, dtype) -> Mrci:
    ns = sum(md.A.shape[0] for md in d.slow)
    nm = len(d.slow)
    As = _blockdiag([md.A for md in d.slow], ns)
    Bs = np.concatenate([md.B for md in d.slow]) if nm else np.zeros(0)
    Cs = np.zeros((nm, ns))
    sp = np.zeros(ns, np.int32)
    i = 0
    for j, md in enumerate(d.slow):
        k = md.A.shape[0]
        Cs[j, i:i + k] = md.C
        sp[i:i + k] = j % d.m
        i += k
    nf = sum(md.A.shape[0] for md in d.fast)
    Af = _blockdiag([md.A for md in d.fast], nf)
    Bf = np.concatenate([md.B for md in d.fast]) if d.fast else np.zeros(0)
    Cf = np.concatenate([md.C for md in d.fast]) if d.fast else np.zeros(0)
    f32 = lambda a: jnp.asarray(a, dtype)
    return Mrci(As=f32(As), Bs=f32(Bs), Cs=f32(Cs), Ds=f32([md.D for md in d.slow]),
                state_phase=jnp.asarray(sp), mode_phase=jnp.asarray(np.arange(nm, dtype=np.int32) % d.m),
                Af=f32(Af), Bf=f32(Bf), Cf=f32(Cf), Df=f32(d.D + sum(md.D for md in d.fast)), m=d.m)


def mrci_init(c: Mrci, dtype=jnp.float32) -> MrciState:
    return MrciState(jnp.zeros(c.As.shape[0], dtype), jnp.zeros(c.Ds.shape[0], dtype),
                     jnp.zeros(c.Af.shape[0], dtype))


def mrci_step(c: Mrci, s: MrciState, k, e) -> tuple[jax.Array, MrciState]:
    """One fast period at instant k with error e_k = r_k - yhat_k -> (u_k, next state).

    Slow mode i outputs C_i x_i + D_i e_k and updates x_i <- A_i^m x_i + B_i^m e_k only at
    k = m j + phase_i (Fig. 4); otherwise its output is held. The fast part runs every period.
    ``e`` is one number (shape () or (1,): the controller is SISO); ValueError otherwise (a
    vector broadcast into the modes' states). It computes in the state's dtype (``mrci_init``'s:
    a float64 ``e`` under x64 made a float32 state float64 and a scan over k failed).
    """
    if jnp.size(e) != 1:
        raise ValueError(f"mrci_step: e must be a single number (the controller is SISO), got shape {jnp.shape(e)}")
    e = jnp.asarray(e, jnp.result_type(s.us))
    ph = jnp.mod(k, c.m)
    upd_x = c.state_phase == ph
    upd_u = c.mode_phase == ph
    us = jnp.where(upd_u, c.Cs @ s.xs + c.Ds * e, s.us)
    xs = jnp.where(upd_x, c.As @ s.xs + c.Bs * e, s.xs)
    uf = c.Cf @ s.xf + c.Df * e
    xf = c.Af @ s.xf + c.Bf * e
    return uf + jnp.sum(us), MrciState(xs, us, xf)
