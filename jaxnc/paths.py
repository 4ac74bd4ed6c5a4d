"""Reference paths of seed 000, section 4.1, and nearest-point queries on them.

The paper tracks three paths at V_ref = 0.2 m/s (a Lissajous curve, a double
lane change manoeuvre, a path with a 180 deg turn; Figs. 4-6) but gives no
dimensions.  The choices made here (all inside the 4 m x 4 m area [-2, 2]^2
centred on the origin, lengths in metres):

* ``lissajous``: figure-eight X = 1.2 sin t, Y = 0.6 sin 2t, t in [0, 2 pi].
  Closed, starts and ends at (0, 0), initial heading 45 deg (tangent (1.2, 1.2)),
  self-crossing at the origin (t = pi, heading 135 deg); length ~7.32 m.
* ``lane_change``: x from -2.0 to 2.0, y = -0.3 then +0.3 then -0.3; straight
  0.4 m, cosine-profile lateral shift of +0.6 m over 1.2 m in x, straight 0.8 m,
  shift back over 1.2 m, straight 0.4 m.  Starts at (-2.0, -0.3), ends at
  (2.0, -0.3); max curvature 0.3 pi^2 / 1.2^2 ~ 2.06 1/m (radius ~0.49 m, like
  the turn); length ~4.34 m.  (4 m in x rather than ~5 m so that it fits the area.)
* ``turn180``: straight 2.0 m along +X from (-1.25, -0.5), left semicircle of
  radius 0.5 m centred at (0.75, 0), straight 2.0 m along -X to (-1.25, 0.5);
  length 4 + 0.5 pi ~ 5.571 m.

A :class:`Path` holds points resampled at uniform arc-length spacing.  All
queries are pure JAX and work under ``jax.jit`` / ``jax.vmap``.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Path",
    "from_waypoints",
    "lissajous",
    "double_lane_change",
    "turn_180",
    "PATHS",
    "get_path",
    "scaled",
    "closest_index",
    "track_index",
    "point_at",
    "heading_at",
]

_DTYPE = jnp.float32


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Path:
    """A planar path sampled at uniform arc length.

    Attributes:
      points: float32[M, 2] (X, Y); ``points[-1]`` is the path end exactly.
      s: float32[M] cumulative arc length, ``s[0] = 0``, ``s[-1] = length``.
      name: static label, e.g. ``"lissajous"``.
    """

    points: jax.Array
    s: jax.Array
    name: str = dataclasses.field(default="path", metadata=dict(static=True))

    @property
    def length(self) -> jax.Array:
        """Total arc length ``s[-1]`` (m)."""
        return self.s[-1]

    @property
    def M(self) -> int:
        """Number of points (static)."""
        return int(self.points.shape[0])

    @property
    def spacing(self) -> jax.Array:
        """Arc-length spacing between consecutive points, ``length / (M - 1)``."""
        return self.s[-1] / (self.M - 1)


def from_waypoints(xy, name: str, ds: float = 0.01) -> Path:
    """Resample a (densely sampled) polyline at uniform arc length, by linear interpolation.

    The number of intervals is ``round(length / ds)`` (at least 1), so the actual
    spacing ``length / (M - 1)`` is within ``ds / (2 (M - 1))`` of ``ds`` and the
    last point is the polyline's end exactly.  Repeated consecutive waypoints are
    dropped.  Computed in float64 NumPy, stored as float32.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 2:
        raise ValueError(f"waypoints must have shape [K >= 2, 2], got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise ValueError("waypoints must be finite")
    if not (np.isfinite(ds) and ds > 0):
        raise ValueError(f"ds must be a positive number, got {ds!r}")
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 0.0])
    xy, seg = xy[keep], seg[seg > 0.0]
    if xy.shape[0] < 2:
        raise ValueError("waypoints have zero total length")
    s_in = np.concatenate([[0.0], np.cumsum(seg)])
    length = s_in[-1]
    n = max(int(round(length / ds)), 1)
    s = np.linspace(0.0, length, n + 1)
    pts = np.stack([np.interp(s, s_in, xy[:, 0]), np.interp(s, s_in, xy[:, 1])], axis=1)
    pts[0], pts[-1] = xy[0], xy[-1]
    # device_put: jnp.asarray would compile a copy program per shape
    return Path(points=jax.device_put(pts.astype(_DTYPE)), s=jax.device_put(s.astype(_DTYPE)), name=name)


# Dense sampling of the analytic curves before resampling (chord error ~1e-8 m).
_DENSE = 20001


def lissajous(ds: float = 0.01) -> Path:
    """Figure-eight X = 1.2 sin t, Y = 0.6 sin 2t, t in [0, 2 pi] (Fig. 4; sizes ours).

    Starts and ends at the origin, initial heading 45 deg; crosses itself at the
    origin at half length.
    """
    t = np.linspace(0.0, 2.0 * np.pi, _DENSE)
    xy = np.stack([1.2 * np.sin(t), 0.6 * np.sin(2.0 * t)], axis=1)
    xy[-1] = 0.0  # close exactly (sin(2 pi) round-off)
    return from_waypoints(xy, "lissajous", ds)


def double_lane_change(ds: float = 0.01) -> Path:
    """Double lane change (Fig. 5; sizes ours): y(x) for x in [-2, 2].

    y = -0.3 + 0.6 [c((x + 1.6) / 1.2) - c((x - 0.4) / 1.2)],
    c(u) = (1 - cos(pi clip(u, 0, 1))) / 2 (smooth cosine shift).
    Straight 0.4 m, shift +0.6 m over 1.2 m, straight 0.8 m, shift back, straight 0.4 m.
    """
    x = np.linspace(-2.0, 2.0, _DENSE)
    c = lambda u: 0.5 * (1.0 - np.cos(np.pi * np.clip(u, 0.0, 1.0)))
    y = -0.3 + 0.6 * (c((x + 1.6) / 1.2) - c((x - 0.4) / 1.2))
    return from_waypoints(np.stack([x, y], axis=1), "lane_change", ds)


def turn_180(ds: float = 0.01) -> Path:
    """180 deg turn (Fig. 6; sizes ours): 2 m along +X, left semicircle R = 0.5 m, 2 m along -X.

    Starts at (-1.25, -0.5), ends at (-1.25, 0.5); length 4 + 0.5 pi.
    """
    R, L, x0, y0 = 0.5, 2.0, -1.25, -0.5
    th = np.linspace(-0.5 * np.pi, 0.5 * np.pi, _DENSE)
    arc = np.stack([x0 + L + R * np.cos(th), y0 + R + R * np.sin(th)], axis=1)
    xy = np.concatenate([[[x0, y0]], arc, [[x0, y0 + 2.0 * R]]], axis=0)
    return from_waypoints(xy, "turn180", ds)


PATHS: dict[str, Callable[[], Path]] = {
    "lissajous": lissajous,
    "lane_change": double_lane_change,
    "turn180": turn_180,
}


@functools.lru_cache(maxsize=None)
def _cached(name: str, ds: float) -> Path:
    return PATHS[name](ds)


def get_path(name: str, ds: float = 0.01) -> Path:
    """The named path of :data:`PATHS` (cached); ValueError on an unknown name."""
    if name not in PATHS:
        raise ValueError(f"unknown path {name!r}; allowed names: {', '.join(sorted(PATHS))}")
    return _cached(name, float(ds))


def scaled(path: Path, factor: float, ds: float = 0.01) -> Path:
    """``path`` shrunk (or grown) by ``factor`` about the origin, resampled at spacing ``ds``;
    named ``<name>_x<factor>``. Seed 000, section 5: the experiments track a reduced-size
    reference because of the workspace (the paper gives no size). ValueError unless
    0 < factor <= 10."""
    factor = float(factor)
    if not (math.isfinite(factor) and 0.0 < factor <= 10.0):
        raise ValueError(f"factor must be in (0, 10], got {factor!r}")
    return from_waypoints(np.asarray(path.points, np.float64) * factor, f"{path.name}_x{factor:g}", ds)


def closest_index(path: Path, p, idx_prev, window: int):
    """Monotone windowed nearest-point search.

    Searches only indices ``idx_prev .. idx_prev + window - 1`` (clipped to
    ``M - 1``) for the path point nearest to ``p`` (float[2]); returns
    ``(index int32, distance float32)``.  Monotone progress (index >= idx_prev)
    keeps the search on the current branch where the Lissajous curve crosses
    itself.  ``window`` is a static int; ties go to the lower index.
    """
    M = path.M
    w = max(1, min(int(window), M))
    idx_prev = jnp.clip(jnp.asarray(idx_prev, jnp.int32), 0, M - 1)
    start = jnp.clip(idx_prev, 0, M - w)
    pts = jax.lax.dynamic_slice(path.points, (start, jnp.zeros((), jnp.int32)), (w, 2))
    # the two squares added as written, not a sum over the last axis: XLA:CPU hands such a
    # reduction to a library (YNNPACK) call per use, slow on a few entries per lane
    p = jnp.asarray(p, _DTYPE)
    dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
    d2 = dx * dx + dy * dy
    i = jnp.arange(w, dtype=jnp.int32)
    d2 = jnp.where(start + i >= idx_prev, d2, jnp.inf)  # near the end the slice starts before idx_prev
    # jnp.argmin(d2) as two plain reductions (XLA:CPU runs a batched argmin as a scalar loop):
    # the first minimum; a NaN (a non-finite position) counts as the smallest, as in argmin.
    # Both reductions on int32: d2 is +0, positive or +-inf, whose float32 bit patterns as
    # int32 keep their order (-inf, the only negative, is below every other), so the minimum
    # is at the same place; a float32 min over the window is a library (YNNPACK) call per use
    # on XLA:CPU, an int32 one is inline code. The minimum itself is read at j (differentiable).
    d2 = jnp.where(jnp.isnan(d2), -jnp.inf, d2)
    bits = jax.lax.bitcast_convert_type(d2, jnp.int32)
    j = jnp.min(jnp.where(bits == jnp.min(bits), i, w))
    d2j = d2[j]
    pos = d2j > 0.0
    dist = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2j, 1.0)), 0.0)
    return start + j, dist.astype(_DTYPE)


def track_index(path: Path, p, idx_prev, window: int):
    """The monotone progress of a plant at ``p`` float[2]: :func:`closest_index`
    from ``idx_prev`` over ``window`` (static, >= 2) points, repeated from its result while
    that is the window's last point and not the path's end (the distance still falls there:
    the plant is beyond the window). Returns the index, int32. Each repeat advances at least
    ``min(window, M) - 1`` points, so it ends.
    """
    w = min(int(window), path.M)
    if w < 2:
        raise ValueError(f"track_index: window must be >= 2 (and the path have 2 points), got {window}")

    def ahead(c):
        prev, idx = c
        return (idx == prev + (w - 1)) & (idx < path.M - 1)

    def again(c):
        return c[1], closest_index(path, p, c[1], w)[0]

    idx_prev = jnp.clip(jnp.asarray(idx_prev, jnp.int32), 0, path.M - 1)
    return jax.lax.while_loop(ahead, again, (idx_prev, closest_index(path, p, idx_prev, w)[0]))[1]


def point_at(path: Path, s) -> jax.Array:
    """Point (float[2]) at arc length ``s``, clipped to [0, length]; linear interpolation.

    Differentiable in ``s``: the derivative is the segment's unit tangent.
    """
    M = path.M
    s = jnp.clip(jnp.asarray(s, _DTYPE), 0.0, path.s[-1])
    # uniform arc length: the segment index is s / spacing (O(1), no search); at a
    # segment boundary either neighbour interpolates to the same point
    i = jnp.clip(jnp.floor(s / path.spacing).astype(jnp.int32), 0, M - 2)
    s0, s1 = path.s[i], path.s[i + 1]
    frac = (s - s0) / (s1 - s0)
    return path.points[i] + frac * (path.points[i + 1] - path.points[i])


def heading_at(path: Path, idx) -> jax.Array:
    """Tangent angle (rad) at index ``idx`` by a central difference (one-sided at the ends)."""
    M = path.M
    idx = jnp.asarray(idx, jnp.int32)
    a = path.points[jnp.clip(idx - 1, 0, M - 1)]
    b = path.points[jnp.clip(idx + 1, 0, M - 1)]
    d = b - a
    return jnp.arctan2(d[1], d[0])
