"""Tests for jaxnc.metrics against brute-force numpy references (seed 000 eq. 21-24)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import metrics as Mx
from jaxnc.paths import get_path

dist_fn = jax.jit(Mx.distance_to_path, static_argnums=2)


def _np_dist(points, xy):
    """Brute-force float64 point-to-segment distance, min over all segments."""
    a, b = points[:-1], points[1:]
    d = b - a
    p = xy[:, None, :]
    t = np.clip(np.sum((p - a[None]) * d[None], -1) / np.sum(d * d, -1)[None], 0.0, 1.0)
    r = p - (a[None] + t[..., None] * d[None])
    return np.sqrt(np.min(np.sum(r * r, -1), axis=1))


@pytest.mark.parametrize("name", ["lissajous", "lane_change", "turn180"])
def test_distance_matches_numpy(name):
    path = get_path(name)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-2.0, 2.0, (300, 2)).astype(np.float32)
    ref = _np_dist(np.asarray(path.points, np.float64), xy.astype(np.float64))
    got = dist_fn(path, jnp.asarray(xy))
    assert got.dtype == jnp.float32 and got.shape == (300,)
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-5)
    # chunked search gives the same answer, also with a remainder block
    got_c = dist_fn(path, jnp.asarray(xy), 64)
    np.testing.assert_allclose(np.asarray(got_c), np.asarray(got), atol=1e-7)


def test_distance_segments_not_vertices():
    path = get_path("turn180")
    # midway between two vertices on the first straight, 3 cm off: exact 0.03
    p = jnp.array([[-1.25 + 0.105, -0.47]], jnp.float32)
    np.testing.assert_allclose(np.asarray(dist_fn(path, p)), [0.03], atol=1e-6)
    # inside the semicircle: distance to the circle of radius 0.5 around (0.75, 0)
    c = jnp.array([[0.75 + 0.2, 0.1]], jnp.float32)
    np.testing.assert_allclose(float(dist_fn(path, c)[0]), 0.5 - np.hypot(0.2, 0.1), atol=1e-4)


def test_distance_zero_on_path_and_finite_gradient():
    path = get_path("lissajous")
    on = path.points[::37]
    mid = 0.5 * (path.points[10:400:41] + path.points[11:401:41])  # segment midpoints
    xy = jnp.concatenate([on, mid], axis=0)
    d = dist_fn(path, xy)
    assert float(jnp.max(d)) < 1e-5
    g = jax.jit(jax.grad(lambda q: jnp.sum(Mx.distance_to_path(path, q))))(xy)
    assert bool(jnp.all(jnp.isfinite(g)))
    # off the path the gradient is the unit normal direction
    off = jnp.array([[0.3, 0.9], [1.9, -1.7], [0.0, 0.0], [-0.5, 0.2]], jnp.float32)
    g = np.asarray(jax.jit(jax.grad(lambda q: jnp.sum(Mx.distance_to_path(path, q))))(off))
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(np.linalg.norm(g[[0, 1, 3]], axis=1), 1.0, atol=1e-4)
    # finite differences
    eps = 1e-3
    q = np.array([0.3, 0.9], np.float32)
    e = np.eye(2, dtype=np.float32) * eps
    dp, dm = np.asarray(dist_fn(path, jnp.asarray(q[None, :] + e))), np.asarray(dist_fn(path, jnp.asarray(q[None, :] - e)))
    fd = (dp - dm) / (2 * eps)
    np.testing.assert_allclose(g[0], fd, atol=2e-3)


def test_distance_shapes_and_vmap():
    path = get_path("lane_change")
    xy = jnp.asarray(np.random.default_rng(3).uniform(-2.0, 2.0, (4, 5, 2)).astype(np.float32))
    d = dist_fn(path, xy)
    assert d.shape == (4, 5)
    dv = jax.jit(jax.vmap(lambda q: Mx.distance_to_path(path, q)))(xy)
    np.testing.assert_allclose(np.asarray(dv), np.asarray(d), atol=1e-7)
    assert dist_fn(path, xy[0, 0]).shape == ()


def test_J1_J2_masked_against_numpy():
    rng = np.random.default_rng(0)
    dist = rng.uniform(0.0, 0.2, (3, 50)).astype(np.float32)
    mask = rng.uniform(size=(3, 50)) < 0.6
    mask[2] = False
    j1 = np.asarray(jax.jit(Mx.J1)(dist, mask))
    j2 = np.asarray(jax.jit(Mx.J2)(dist, mask))
    for k in range(2):
        np.testing.assert_allclose(j1[k], dist[k][mask[k]].mean(), rtol=1e-6)
        np.testing.assert_allclose(j2[k], dist[k][mask[k]].max(), rtol=0)
    assert j1[2] == 0.0 and j2[2] == 0.0
    # prefix mask (steps before completion l), via vmap
    l = jnp.array([10, 50, 0])
    m = jnp.arange(50)[None, :] < l[:, None]
    j1v = jax.jit(jax.vmap(Mx.J1))(jnp.asarray(dist), m)
    np.testing.assert_allclose(np.asarray(j1v), [dist[0, :10].mean(), dist[1].mean(), 0.0], rtol=1e-6)
    # gradients: finite even for the all-False row
    g1 = jax.jit(jax.grad(lambda d: jnp.sum(Mx.J1(d, mask))))(jnp.asarray(dist))
    g2 = jax.jit(jax.grad(lambda d: jnp.sum(Mx.J2(d, mask))))(jnp.asarray(dist))
    assert bool(jnp.all(jnp.isfinite(g1))) and bool(jnp.all(jnp.isfinite(g2)))
    np.testing.assert_allclose(np.asarray(g1[0]), mask[0] / mask[0].sum(), rtol=1e-6)
    assert float(jnp.sum(g2[2])) == 0.0 and float(jnp.sum(g2[0])) == 1.0


def test_J3_J4():
    assert float(jax.jit(Mx.J3)(360, 0.1)) == pytest.approx(36.0, rel=1e-6)
    # the case sends every 2nd step, the nominal run every step, same duration
    assert float(jax.jit(Mx.J4)(180, 360, 360, 360)) == pytest.approx(0.5, rel=1e-6)
    # a longer run at the same rate is not charged for the extra time
    assert float(jax.jit(Mx.J4)(200, 400, 360, 360)) == pytest.approx(0.5, rel=1e-6)
    assert float(jax.jit(Mx.J4)(360, 360, 360, 360)) == pytest.approx(1.0)


def test_ci95():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    m, h = Mx.ci95(x)
    assert m == pytest.approx(2.5)
    assert h == pytest.approx(1.96 * np.std(x, ddof=1) / 2.0)
    m, h = Mx.ci95(np.array([3.0]))
    assert m == 3.0 and np.isnan(h)


@pytest.mark.parametrize("name", ["turn180", "lane_change"])
def test_local_distance_equals_global_near_the_path(name):
    """Near a path that does not cross itself, the distance to the two segments at
    the nearest point is the distance to the whole polyline."""
    from jaxnc.paths import closest_index
    path = get_path(name)
    rng = np.random.default_rng(0)
    i = rng.integers(0, path.M, 200)
    xy = np.asarray(path.points)[i] + rng.normal(0, 0.05, (200, 2)).astype(np.float32)

    @jax.jit
    def local(p, i0):
        idx, _ = closest_index(path, p, jnp.maximum(i0 - 20, 0), 40)
        return Mx.local_distance(path, p, idx)

    loc = jax.vmap(local)(jnp.asarray(xy), jnp.asarray(i, jnp.int32))
    glob = Mx.distance_to_path(path, jnp.asarray(xy))
    np.testing.assert_allclose(loc, glob, atol=2e-6)
