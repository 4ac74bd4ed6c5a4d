"""Tests for jaxnc.paths: lengths vs independent numpy/scipy, sampling, queries."""
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad

from jaxnc import paths as P

DS = 0.01


def _lissajous_len():
    f = lambda t: np.hypot(1.2 * np.cos(t), 1.2 * np.cos(2 * t))
    return quad(f, 0.0, 2 * np.pi, limit=200, epsabs=1e-10)[0]


def _lane_change_len():
    def dy(x):  # derivative of y(x) of the lane change
        g = lambda u: 0.5 * np.pi * np.sin(np.pi * u) / 1.2 if 0.0 <= u <= 1.0 else 0.0
        return 0.6 * (g((x + 1.6) / 1.2) - g((x - 0.4) / 1.2))
    f = lambda x: np.sqrt(1.0 + dy(x) ** 2)
    return quad(f, -2.0, 2.0, points=[-1.6, -0.4, 0.4, 1.6], limit=200, epsabs=1e-10)[0]


EXPECTED = {
    "lissajous": dict(length=_lissajous_len(), start=(0.0, 0.0), end=(0.0, 0.0)),
    "lane_change": dict(length=_lane_change_len(), start=(-2.0, -0.3), end=(2.0, -0.3)),
    "turn180": dict(length=2.0 + np.pi * 0.5 + 2.0, start=(-1.25, -0.5), end=(-1.25, 0.5)),
}


@pytest.fixture(scope="module", params=sorted(P.PATHS))
def named(request):
    return request.param, P.get_path(request.param)


def test_length_matches_closed_form(named):
    name, path = named
    assert path.name == name
    assert path.points.dtype == jnp.float32 and path.s.dtype == jnp.float32
    assert path.points.shape == (path.M, 2) and path.s.shape == (path.M,)
    np.testing.assert_allclose(float(path.length), EXPECTED[name]["length"], atol=1e-3)
    # the stored resampled polyline has (almost) the same length
    pts = np.asarray(path.points, np.float64)
    np.testing.assert_allclose(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)), float(path.length), atol=1e-3)


def test_uniform_spacing_and_endpoints(named):
    name, path = named
    s = np.asarray(path.s, np.float64)
    assert s[0] == 0.0
    assert np.max(np.abs(np.diff(s) - DS)) < 1e-4
    # consecutive points are ~ds apart in the plane too
    step = np.linalg.norm(np.diff(np.asarray(path.points, np.float64), axis=0), axis=1)
    assert np.max(np.abs(step - DS)) < 1e-4
    np.testing.assert_allclose(np.asarray(path.points[0]), EXPECTED[name]["start"], atol=1e-6)
    np.testing.assert_allclose(np.asarray(path.points[-1]), EXPECTED[name]["end"], atol=1e-6)
    assert np.all(np.abs(np.asarray(path.points)) <= 2.0 + 1e-6)


def test_path_lengths_in_expected_range():
    assert 6.0 < float(P.get_path("lissajous").length) < 8.0
    lc = P.get_path("lane_change")
    assert np.ptp(np.asarray(lc.points[:, 1])) == pytest.approx(0.6, abs=1e-5)


def test_get_path_unknown_name():
    with pytest.raises(ValueError) as e:
        P.get_path("nope")
    for n in ("lissajous", "lane_change", "turn180"):
        assert n in str(e.value)


def test_from_waypoints_resamples_polyline():
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.5]])  # repeated point dropped
    path = P.from_waypoints(xy, "L", ds=0.1)
    assert path.M == 16
    np.testing.assert_allclose(np.asarray(path.s), np.linspace(0, 1.5, 16), atol=1e-6)
    np.testing.assert_allclose(np.asarray(path.points[10]), [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(path.points[-1]), [1.0, 0.5], atol=1e-7)
    with pytest.raises(ValueError):
        P.from_waypoints(np.zeros((3, 2)), "bad")


def test_closest_index_straight_segment():
    path = P.get_path("turn180")  # first 2 m: y = -0.5, x = -1.25 + s
    f = jax.jit(P.closest_index, static_argnums=3)
    p = jnp.array([-1.25 + 0.731, -0.45], jnp.float32)
    idx, dist = f(path, p, jnp.int32(10), 200)
    assert idx.dtype == jnp.int32 and int(idx) == 73
    np.testing.assert_allclose(float(dist), np.hypot(0.001, 0.05), rtol=1e-4)
    # monotone: a point behind idx_prev is mapped to idx_prev, never before
    idx, _ = f(path, p, jnp.int32(120), 50)
    assert int(idx) == 120
    # window clipped at the end of the path, still >= idx_prev
    M = path.M
    idx, _ = f(path, jnp.array([-0.5, 0.5], jnp.float32), jnp.int32(M - 3), 50)  # behind M - 3
    assert int(idx) == M - 3
    idx, _ = f(path, path.points[-1] + 1.0, jnp.int32(M - 30), 50)
    assert M - 30 <= int(idx) <= M - 1


def test_closest_index_vmap_monotone():
    path = P.get_path("turn180")
    p = jnp.asarray(np.random.default_rng(0).uniform(-2.0, 2.0, (64, 2)).astype(np.float32))
    prev = jnp.arange(64, dtype=jnp.int32) * 8
    f = jax.jit(jax.vmap(lambda q, i: P.closest_index(path, q, i, 40)))
    idx, dist = f(p, prev)
    idx, prev = np.asarray(idx), np.asarray(prev)
    assert np.all(idx >= prev) and np.all(idx <= np.minimum(prev + 39, path.M - 1))
    # brute-force reference over the same window
    pts = np.asarray(path.points)
    for k in range(64):
        lo, hi = prev[k], min(prev[k] + 40, path.M)
        dd = np.linalg.norm(pts[lo:hi] - np.asarray(p[k])[None, :], axis=1)
        assert idx[k] == lo + np.argmin(dd)
        np.testing.assert_allclose(float(dist[k]), dd.min(), rtol=1e-5, atol=1e-6)


class _Pts(NamedTuple):      # the two fields closest_index reads
    points: jax.Array
    M: int


@pytest.mark.parametrize("window", [2, 16, 32, 130])
def test_closest_index_first_minimum_ties_and_nan(window):
    """The search's index is np.argmin's over the window (float32 squares as written): the
    first of equal distances, and for a non-finite position the first NaN (the window's
    start), as jnp.argmin gave; batched under vmap."""
    rng = np.random.default_rng(window)
    pts = np.round(rng.uniform(-1, 1, (300, 2)) * 4) / 4          # a coarse grid: many exact ties
    pts = pts.astype(np.float32)
    path = _Pts(jnp.asarray(pts), 300)
    q = (np.round(rng.uniform(-1, 1, (64, 2)) * 8) / 8).astype(np.float32)
    q[:4] = np.nan
    q[4, 0] = np.inf
    prev = rng.integers(0, 300, 64).astype(np.int32)
    idx, _ = jax.jit(jax.vmap(lambda a, i: P.closest_index(path, a, i, window)))(jnp.asarray(q), jnp.asarray(prev))
    for k in range(64):
        start = min(prev[k], 300 - window)
        d = pts[start:start + window] - q[k][None, :]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
        d2[np.arange(start, start + window) < prev[k]] = np.inf
        assert int(idx[k]) == start + int(np.argmin(d2)), k
    tie = _Pts(jnp.asarray([[-1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], jnp.float32), 3)
    assert int(P.closest_index(tie, jnp.zeros(2), 0, 3)[0]) == 0
    assert int(P.closest_index(tie, jnp.asarray([1.0, 0.5]), 1, 2)[0]) == 1


def test_closest_index_distance_is_differentiable():
    """The distance returned is the minimum read at the index found (the search reduces the
    squares' bit patterns as int32): its gradient is the unit vector from the nearest point."""
    path = P.get_path("turn180")
    q = jnp.asarray([0.3, -0.7], jnp.float32)
    i, _ = P.closest_index(path, q, 0, 60)
    g = jax.grad(lambda a: P.closest_index(path, a, 0, 60)[1])(q)
    d = np.asarray(q) - np.asarray(path.points[int(i)])
    np.testing.assert_allclose(np.asarray(g), d / np.linalg.norm(d), rtol=1e-5)

def test_closest_index_lissajous_crossing_stays_on_branch():
    path = P.get_path("lissajous")
    M = path.M
    pts = np.asarray(path.points)
    # middle crossing at the origin (t = pi, half length)
    mid = int(np.argmin(np.linalg.norm(pts[M // 4: 3 * M // 4], axis=1))) + M // 4
    assert np.linalg.norm(pts[mid]) < 0.01
    # on the first branch, 5 cm before the crossing (the branch the path ends on)
    q = jnp.asarray(-pts[5])
    assert np.linalg.norm(pts[-6] - np.asarray(q)) < 1e-3
    f = jax.jit(P.closest_index, static_argnums=3)
    idx, _ = f(path, q, jnp.int32(mid - 10), 50)
    assert mid - 10 <= int(idx) <= mid + 10  # stays on the second branch, near the crossing
    # an unlimited forward search would jump to the path end (the first branch again)
    idx_all, _ = f(path, q, jnp.int32(mid - 10), M)
    assert int(idx_all) > M - 10


def test_point_at_interpolates_and_gradient_is_tangent():
    path = P.get_path("turn180")
    pa = jax.jit(P.point_at)
    for s in (0.0, 0.7, 0.7049, 1.9):
        np.testing.assert_allclose(np.asarray(pa(path, jnp.float32(s))), [-1.25 + s, -0.5], atol=2e-6)
    # beyond the ends: clipped
    np.testing.assert_allclose(np.asarray(pa(path, jnp.float32(-1.0))), [-1.25, -0.5], atol=1e-7)
    np.testing.assert_allclose(np.asarray(pa(path, jnp.float32(100.0))), [-1.25, 0.5], atol=1e-6)
    # on the last straight (going -X)
    np.testing.assert_allclose(np.asarray(pa(path, path.length - 0.5)), [-0.75, 0.5], atol=2e-5)
    jac = jax.jit(jax.jacfwd(P.point_at, argnums=1))
    np.testing.assert_allclose(np.asarray(jac(path, jnp.float32(0.7049))), [1.0, 0.0], atol=1e-3)
    g = jax.jit(jax.grad(lambda s: P.point_at(path, s)[1]))
    np.testing.assert_allclose(float(g(jnp.float32(1.3))), 0.0, atol=1e-6)
    # on the semicircle the derivative is a unit tangent
    t = np.asarray(jac(path, jnp.float32(2.0 + 0.25 * np.pi)))  # top of... quarter of the arc
    np.testing.assert_allclose(np.linalg.norm(t), 1.0, atol=1e-3)
    np.testing.assert_allclose(t, [0.0, 1.0], atol=2e-2)


def test_point_at_vmap_matches_numpy_interp():
    path = P.get_path("lissajous")
    s = jnp.linspace(-0.1, float(path.length) + 0.1, 333).astype(jnp.float32)
    got = np.asarray(jax.jit(jax.vmap(P.point_at, in_axes=(None, 0)))(path, s))
    sp, pts = np.asarray(path.s), np.asarray(path.points)
    ref = np.stack([np.interp(np.asarray(s), sp, pts[:, 0]), np.interp(np.asarray(s), sp, pts[:, 1])], axis=1)
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_heading_at():
    path = P.get_path("turn180")
    h = jax.jit(P.heading_at)
    assert float(h(path, 0)) == pytest.approx(0.0, abs=1e-6)
    assert abs(float(h(path, path.M - 1))) == pytest.approx(np.pi, abs=1e-6)
    liss = P.get_path("lissajous")
    assert float(h(liss, 0)) == pytest.approx(np.pi / 4, abs=1e-2)


def test_scaled_path_shrinks_length_and_points():
    p = P.get_path("lissajous")
    q = P.scaled(p, 0.5)
    assert float(q.length) == pytest.approx(0.5 * float(p.length), rel=1e-4)
    assert q.name == "lissajous_x0.5"
    np.testing.assert_allclose(np.asarray(q.points).max(axis=0), [0.6, 0.3], atol=1e-3)
    assert float(q.spacing) == pytest.approx(0.01, abs=1e-4)
    with pytest.raises(ValueError, match="factor"):
        P.scaled(p, 0.0)
