"""Structural sparsity of an EKF's Jacobians: detected once, used as static patterns.

Many plant models have Jacobians with entries that are zero at every operating point.
The Mecanum kinematics of seed 000 eq. (1) are the example: the body velocities come
from the wheel commands alone, so A = df/dxi has three zero rows and three zero columns,
and its pose block is [[1, 0, a35], [0, 1, a45], [0, 0, 1]]; each measurement of eq.
(2) and (9) depends on two or three of the six states. An EKF that knows this computes
Jacobian columns only along the directions that matter and multiplies only the entries
that can be nonzero (seed 000 eq. 11-16 unchanged; the skipped terms are
exact zeros).

A :class:`Pattern` is a hashable tuple of booleans, so it can be a static field of a
configuration (one compilation per pattern). :func:`detect_structure` finds the
patterns of a concrete model numerically: the union of the nonzero entries of the
Jacobians at random points. That is the usual numerical sparsity detection; it can miss
an entry that is nonzero only on a set the random points do not reach (e.g. a branch of
``jnp.where`` taken only in a corner of the state space). Such models should pass a
pattern by hand or none (``structure=None``: dense, always correct).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Pattern", "EKFStructure", "check_shape", "detect_structure", "jacobian_columns", "take", "embed"]


@dataclasses.dataclass(frozen=True)
class Pattern:
    """Where a matrix can be nonzero: ``mask[i][j]`` is False when entry (i, j) is zero
    at every point. Hashable, so it can be static."""

    mask: tuple[tuple[bool, ...], ...]

    def __post_init__(self):
        # any nested sequence of truth values -> a tuple of tuples of bools (hashable)
        object.__setattr__(self, "mask", tuple(tuple(bool(v) for v in row) for row in self.mask))
        widths = {len(r) for r in self.mask}
        if len(widths) > 1:
            raise ValueError(f"Pattern.mask rows must all have the same length, got lengths {sorted(widths)}")

    @classmethod
    def of(cls, mask) -> "Pattern":
        """From any 2-D boolean (or numeric: nonzero = True) array."""
        m = np.asarray(mask)
        if m.ndim != 2:
            raise ValueError(f"Pattern.of: mask must be 2-D, got shape {m.shape}")
        return cls(tuple(tuple(bool(v) for v in row) for row in m != 0))

    @classmethod
    def dense(cls, rows: int, cols: int) -> "Pattern":
        return cls(((True,) * cols,) * rows)

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.mask), (len(self.mask[0]) if self.mask else 0)

    @property
    def array(self) -> np.ndarray:
        return np.asarray(self.mask, dtype=bool).reshape(self.shape)

    @property
    def rows(self) -> tuple[int, ...]:
        """Rows with at least one possible nonzero."""
        return tuple(int(i) for i in np.flatnonzero(self.array.any(axis=1)))

    @property
    def cols(self) -> tuple[int, ...]:
        """Columns with at least one possible nonzero."""
        return tuple(int(j) for j in np.flatnonzero(self.array.any(axis=0)))

    def row(self, i: int) -> tuple[int, ...]:
        """The columns row ``i`` can be nonzero in."""
        return tuple(int(j) for j in np.flatnonzero(self.array[i]))

    @property
    def nnz(self) -> int:
        return int(self.array.sum())

    def describe(self) -> str:
        """Rows separated by '/', 'x' where an entry can be nonzero, '.' where it is zero."""
        return "/".join("".join("x" if v else "." for v in r) for r in self.mask)

    def __repr__(self):
        return f"Pattern({self.shape[0]}x{self.shape[1]}: {self.describe()})"


class EKFStructure(NamedTuple):
    """Patterns of the EKF's Jacobians (seed 000 eq. 11-16): A = df/dxi, L = df/dn1
    (process noise) and H = dh/dxi."""

    A: Pattern
    L: Pattern
    H: Pattern

    def describe(self) -> dict:
        """JSON-friendly: each pattern as :meth:`Pattern.describe` writes it."""
        return {name: pat.describe() for name, pat in zip(self._fields, self)}


def check_shape(where: str, name: str, pattern: Pattern, want: tuple) -> None:
    """Refuse ``pattern`` unless its shape is ``want``. Shapes are static, so a structure
    detected for another model fails at trace time, naming the pattern."""
    if pattern.shape != tuple(want):
        raise ValueError(f"{where}: structure.{name} has shape {pattern.shape}, expected {tuple(want)} "
                         f"(a structure detected for another model?)")


def detect_structure(f: Callable, h: Callable, state_dim: int, input_dim: int, noise_dim: int, meas_dim: int, *,
                     points: int = 16, seed: int = 0, scale: float = 1.0) -> EKFStructure:
    """The patterns of A = df/dxi, L = df/dn1 (at n1 = 0) and H = dh/dxi (at n2 = 0):
    the union of the Jacobians' nonzeros at ``points`` random (xi, u) drawn N(0, scale^2)
    (float64 when enabled, else float32).

    ``f(x, u, w)`` and ``h(x, v)`` are the model's functions as the EKF calls them, e.g.
    bound methods of a concrete model. Call this when a configuration is built, outside
    ``jit``: a model holding traced values raises a ValueError.
    """
    for name, v, lo in (("state_dim", state_dim, 1), ("input_dim", input_dim, 0), ("noise_dim", noise_dim, 0),
                        ("meas_dim", meas_dim, 1), ("points", points, 1)):
        if not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"detect_structure: {name} must be an integer >= {lo}, got {v!r}")
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32

    def jacs(x, u):
        w0, v0 = jnp.zeros((noise_dim,), dtype), jnp.zeros((meas_dim,), dtype)
        return (jax.jacfwd(f, argnums=0)(x, u, w0), jax.jacfwd(f, argnums=2)(x, u, w0),
                jax.jacfwd(h, argnums=0)(x, v0))

    def at_random_points(key):
        kx, ku = jax.random.split(key)
        xs = scale * jax.random.normal(kx, (points, state_dim), dtype)
        us = scale * jax.random.normal(ku, (points, input_dim), dtype)
        return jax.vmap(jacs)(xs, us)

    try:
        # one compiled program (run eagerly, each of the model's operations compiled its own)
        jacobians = jax.jit(lambda s: at_random_points(jax.random.key(s)))(np.uint32(seed))
        A, L, H = (np.asarray(J) for J in jacobians)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            jax.errors.UnexpectedTracerError) as e:
        raise ValueError("detect_structure: the model holds traced values; detect the structure when the "
                         "configuration is built, outside jit/vmap, or use structure=None") from e
    except (TypeError, ValueError, IndexError) as e:
        raise ValueError(f"detect_structure: evaluating the model's Jacobians with state_dim={state_dim}, "
                         f"input_dim={input_dim}, noise_dim={noise_dim}, meas_dim={meas_dim} failed ({e}); "
                         f"check these sizes against the model") from e
    want = {"A": (state_dim, state_dim), "L": (state_dim, noise_dim), "H": (meas_dim, state_dim)}
    pats = []
    for name, J in (("A", A), ("L", L), ("H", H)):
        if J.shape[1:] != want[name]:
            raise ValueError(f"detect_structure: the Jacobian {name} has shape {J.shape[1:]}, expected {want[name]}; "
                             f"check state_dim, noise_dim and meas_dim")
        if not np.all(np.isfinite(J)):
            raise ValueError(f"detect_structure: the Jacobian {name} is not finite at some random point; "
                             f"try a smaller scale (got {scale})")
        pats.append(Pattern.of(np.any(J != 0, axis=0)))
    return EKFStructure(*pats)


# -- static gathers and scatters: slices and concatenations, which XLA fuses --------------
def _runs(idx) -> list[tuple[int, int]]:
    """Contiguous runs [a, b) of sorted indices."""
    runs = []
    for i in idx:
        if runs and runs[-1][1] == i:
            runs[-1] = (runs[-1][0], i + 1)
        else:
            runs.append((i, i + 1))
    return runs


def take(x, idx, axis: int):
    """``x`` at the static, sorted indices ``idx`` along ``axis``, as slices (no gather)."""
    idx = tuple(idx)
    n = x.shape[axis]
    if idx == tuple(range(n)):
        return x
    parts = [jax.lax.slice_in_dim(x, a, b, axis=axis) for a, b in _runs(idx)]
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=axis)


def embed(x, idx, n: int, axis: int):
    """The inverse of :func:`take`: a length-``n`` axis holding ``x`` at ``idx``, zeros elsewhere."""
    idx = tuple(idx)
    if idx == tuple(range(n)):
        return x
    parts, pos, at = [], 0, 0
    for a, b in _runs(idx):
        if a > at:
            parts.append(jnp.zeros(x.shape[:axis % x.ndim] + (a - at,) + x.shape[axis % x.ndim + 1:], x.dtype))
        parts.append(jax.lax.slice_in_dim(x, pos, pos + b - a, axis=axis))
        pos, at = pos + b - a, b
    if at < n:
        parts.append(jnp.zeros(x.shape[:axis % x.ndim] + (n - at,) + x.shape[axis % x.ndim + 1:], x.dtype))
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=axis)


def jacobian_columns(fn: Callable, x, cols, *, axis: int = 1):
    """Columns ``cols`` of d fn / d x, stacked on ``axis`` of the result: one forward-mode
    product per listed direction (``jacfwd`` is this over every direction).

    ``x`` may carry trailing batch axes (n, *batch); the directions then lead, so the
    batch axis stays minor (as :mod:`jaxnc.estimators.ekf_batched` needs).
    """
    n = x.shape[0]
    eye = np.eye(n, dtype=np.dtype(x.dtype))[list(cols)]
    basis = jnp.broadcast_to(jnp.asarray(eye).reshape(eye.shape + (1,) * (x.ndim - 1)), (len(cols),) + x.shape)
    return jax.vmap(lambda t: jax.jvp(fn, (x,), (t,))[1], out_axes=axis)(basis)
