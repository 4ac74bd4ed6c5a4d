"""Cost indexes of seed 000, section 4.2, eq. (21)-(24).

J1 (eq. 21) is the mean over the run of the distance from the robot to the
reference path (the paper calls it "root-mean-square error" but its formula is a
plain mean of distances; we follow the formula), J2 (eq. 22) its maximum, J3
(eq. 23) the time to complete the path and J4 (eq. 24) the transmission ratio
against the nominal single-rate run.  The distance is to the polyline (segments),
not just its vertices.  All JAX functions work under ``jax.jit`` / ``jax.vmap``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.montecarlo import mean_ci
from jaxnc.paths import Path

__all__ = ["distance_to_path", "distance_to_points", "local_distance", "J1", "J2", "J3", "J4", "ci95"]

_DTYPE = jnp.float32


def _segment_d2(p, a, d, inv_len2):
    """Squared distance from points p[..., 2] to segments a + t d, t in [0, 1] (broadcasting)."""
    t = jnp.clip(jnp.sum((p - a) * d, axis=-1) * inv_len2, 0.0, 1.0)
    r = p - (a + t[..., None] * d)
    return jnp.sum(r * r, axis=-1)


def distance_to_path(path: Path, xy, chunk: int | None = None) -> jax.Array:
    """Distance from each point ``xy[..., 2]`` to the polyline ``path.points`` (inner min of eq. 21-22).

    min over segments of the point-to-segment distance.  The nearest segment is
    found without gradient (an [L, M-1] search, in blocks of ``chunk`` points via
    ``lax.map`` when ``chunk`` is given) and the distance to it is recomputed
    differentiably, so reverse mode stores only O(L) residuals.  The gradient
    w.r.t. ``xy`` equals that of the min; it is finite everywhere (0 on the path,
    via a safe sqrt).  Returns float32[...].
    """
    xy = jnp.asarray(xy, _DTYPE)
    lead = xy.shape[:-1]
    p = xy.reshape(-1, 2)
    a = path.points[:-1].astype(_DTYPE)
    d = (path.points[1:] - path.points[:-1]).astype(_DTYPE)
    len2 = jnp.sum(d * d, axis=-1)
    inv_len2 = jnp.where(len2 > 0.0, 1.0 / jnp.where(len2 > 0.0, len2, 1.0), 0.0)

    def nearest(q):  # q: [n, 2] -> int32[n]
        d2 = _segment_d2(q[:, None, :], a[None, :, :], d[None, :, :], inv_len2[None, :])
        return jnp.argmin(d2, axis=-1).astype(jnp.int32)

    ps = jax.lax.stop_gradient(p)
    if chunk is None or chunk >= p.shape[0]:
        j = nearest(ps)
    else:
        j = jax.lax.map(lambda q: nearest(q[None, :])[0], ps, batch_size=int(chunk))
    d2 = _segment_d2(p, a[j], d[j], inv_len2[j])
    pos = d2 > 0.0
    dist = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
    return dist.reshape(lead)


def distance_to_points(points, xy) -> jax.Array:
    """Distance from each point ``xy[n, 2]`` to the nearest of ``points[m, 2]``: the inner
    min of seed 004 eq. (23)-(24) as printed, whose references are the NT samples of the
    reference trajectory rather than the path itself.  Dense [n, m]; float32[n]; finite
    gradient everywhere (safe sqrt)."""
    xy = jnp.asarray(xy, _DTYPE)
    q = jnp.asarray(points, _DTYPE)
    d2 = jnp.min(jnp.sum((xy[:, None, :] - q[None, :, :]) ** 2, axis=-1), axis=1)
    pos = d2 > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def _masked(dist, mask):
    dist = jnp.asarray(dist, _DTYPE)
    mask = jnp.broadcast_to(jnp.asarray(mask, bool), dist.shape)
    return dist, mask


def local_distance(path: Path, xy, idx) -> jax.Array:
    """Distance from ``xy[2]`` to the two path segments that meet at point ``idx`` (the
    one segment of a path of two points).

    With ``idx`` the nearest path point (``closest_index``, monotone along the run)
    this is the distance to the polyline on the robot's own branch, O(1) per
    instant; it equals ``distance_to_path`` except where another branch of the path
    (the Lissajous crossing) is nearer than the robot's own (a test measures the
    difference on whole runs). Differentiable in ``xy``; ``idx`` carries no gradient.
    """
    M = path.points.shape[0]
    n = min(3, M)       # a path of two points has one segment
    i0 = jnp.clip(jnp.asarray(idx, jnp.int32) - 1, 0, M - n)
    a = jax.lax.dynamic_slice(path.points, (i0, jnp.zeros((), jnp.int32)), (n, 2)).astype(_DTYPE)
    d = a[1:] - a[:-1]
    len2 = jnp.sum(d * d, axis=-1)
    inv = jnp.where(len2 > 0.0, 1.0 / jnp.where(len2 > 0.0, len2, 1.0), 0.0)
    d2 = jnp.min(_segment_d2(jnp.asarray(xy, _DTYPE)[None, :], a[:-1], d, inv))
    pos = d2 > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def J1(dist, mask) -> jax.Array:
    """Eq. (21): mean of ``dist`` over the steps where ``mask`` is True (last axis); 0 if none."""
    dist, mask = _masked(dist, mask)
    n = jnp.sum(mask, axis=-1)
    total = jnp.sum(jnp.where(mask, dist, 0.0), axis=-1)
    return total / jnp.maximum(n, 1).astype(_DTYPE)


def J2(dist, mask) -> jax.Array:
    """Eq. (22): max of ``dist`` over the steps where ``mask`` is True (last axis); 0 if none."""
    dist, mask = _masked(dist, mask)
    m = jnp.max(jnp.where(mask, dist, -jnp.inf), axis=-1)
    return jnp.where(jnp.any(mask, axis=-1), m, 0.0)


def J3(l, T) -> jax.Array:
    """Eq. (23): time to complete the path, ``l T`` (``l`` fast steps of period ``T``)."""
    return jnp.asarray(l, _DTYPE) * jnp.asarray(T, _DTYPE)


def J4(tx, l, tx_nom, l_nom) -> jax.Array:
    """Eq. (24), as a ratio of transmission rates: ``(tx / l) / (tx_nom / l_nom)``.

    The paper divides packet counts Tr(*) / Tr(nom); we divide packets per step
    so that a run that takes longer to finish is not charged for the extra time
    (equal to the paper's ratio when both runs take the same number of steps).
    """
    f = lambda v: jnp.asarray(v, _DTYPE)
    return (f(tx) / f(l)) / (f(tx_nom) / f(l_nom))


#: (mean, half-width of the normal 95 % interval): :func:`jaxnc.montecarlo.mean_ci`.
ci95 = mean_ci
