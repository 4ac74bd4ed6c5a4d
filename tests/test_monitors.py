"""The path monitor (jaxnc.loop.PathMonitor) against closed forms on a straight path."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.paths import from_waypoints, track_index

LINE = from_waypoints(np.array([[0.0, 0.0], [10.0, 0.0]]), "line", ds=0.1)     # 101 points on y = 0
CTX = nc.Context(N=1, steps=10, T=0.1, state_dim=2, input_dim=1, output_dim=2)


def _watch(monitor, xs):
    """(failed, done, dist) after each state of xs [K, n] (the state after fast period t = 0, 1, ...),
    by the monitor's step in a scan."""
    def body(s, tx):
        t, x = tx
        s, failed, done = monitor.step(s, x, jnp.zeros(1), t)
        return s, (failed, done, s.dist)
    run = lambda xs: jax.lax.scan(body, monitor.init(CTX), (jnp.arange(xs.shape[0], dtype=jnp.int32), xs))[1]
    return jax.jit(run)(jnp.asarray(xs, jnp.float32))


def test_leaving_the_tube_fails_at_the_first_state_beyond_max_dev():
    """p_t = (0.05 t, 0.12 t): the distance to y = 0 is 0.12 t, beyond max_dev = 0.5 from t = 5 on."""
    t = np.arange(10)
    failed, done, dist = _watch(nc.PathMonitor(LINE, max_dev=0.5, xy=0), np.stack([0.05 * t, 0.12 * t], 1))
    np.testing.assert_allclose(dist, 0.12 * t, atol=1e-5)
    np.testing.assert_array_equal(failed, t >= 5)
    assert not np.any(done)


def test_completion_at_the_end_and_no_tube_afterwards():
    """A plant on the path reaches its end (10, 0) at t = 10 (done from then on; not before,
    though (9, 0) is in the last tenth, 1 m from the end); leaving sideways afterwards is no failure."""
    xs = np.concatenate([np.stack([np.arange(11.0), np.zeros(11)], 1), [[10.0, 3.0]]])
    failed, done, _ = _watch(nc.PathMonitor(LINE, max_dev=0.5, end_tol=0.1, window=32, xy=0), xs)
    np.testing.assert_array_equal(done, np.arange(12) >= 10)
    assert not np.any(failed)


def test_every_checks_tube_and_end_after_each_multiple_and_holds_between():
    """every = 3: the tube and the end are checked after fast periods t = 2, 5, 8, ... (t + 1 a
    multiple of 3), the distance and completion held in between. p_t = (t, 0.12 t) leaves the
    0.5 m tube at t = 5 (0.6 m) and is first seen there; the end (10, 0) is reached at t = 10,
    first checked at t = 11. A non-finite state fails at once, between checks too."""
    t = np.arange(12)
    failed, _, dist = _watch(nc.PathMonitor(LINE, max_dev=0.5, every=3, xy=0), np.stack([0.5 * t, 0.12 * t], 1))
    checked = np.maximum((t + 1) // 3 * 3 - 1, -1)                 # the last checked instant (-1: none yet)
    np.testing.assert_allclose(dist, np.where(checked >= 0, 0.12 * checked, 0.0), atol=1e-5)
    np.testing.assert_array_equal(failed, (checked >= 5) & ((t + 1) % 3 == 0))
    xs = np.concatenate([np.stack([np.arange(11.0), np.zeros(11)], 1), [[10.0, 0.0]]])
    _, done, _ = _watch(nc.PathMonitor(LINE, end_tol=0.1, window=32, every=3, xy=0), xs)
    np.testing.assert_array_equal(done, t >= 11)
    xs = np.stack([0.1 * t, 0.0 * t], 1)
    xs[4, 0] = np.nan                                              # t = 4 is not a check
    failed, _, _ = _watch(nc.PathMonitor(LINE, every=3, xy=0), xs)
    np.testing.assert_array_equal(failed, t == 4)


def test_position_index_and_non_finite_state():
    """``xy`` picks the position inside a longer state; a non-finite entry anywhere fails."""
    ctx = CTX._replace(state_dim=4)
    m = nc.PathMonitor(LINE, xy=1)
    s0 = m.init(ctx)
    _, failed, _ = m.step(s0, jnp.asarray([9.0, 1.0, 0.2, 7.0]), jnp.zeros(1), 0)
    assert not bool(failed)
    _, failed, _ = m.step(s0, jnp.asarray([jnp.nan, 1.0, 0.2, 7.0]), jnp.zeros(1), 0)
    assert bool(failed)


def test_in_a_loop_the_runner_records_first_failure_and_completion():
    """A plant at constant velocity (1, vy) m/s, T = 0.1, from the start of a 2 m line: after
    step t its position is (0.1, 0.1 vy) (t + 1). With vy = 0.3 it leaves the 0.5 m tube at
    t + 1 = 17 and never completes; with vy = 0 it reaches the end (within 0.06 m) at
    t + 1 = 20 and never fails (K = 30 is the runner's "never"); the distance is recorded."""
    line = from_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), "line2", ds=0.01)
    A = np.array([[1.0, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]])

    def run(vy):
        plant = nc.LTI(A=A, B=np.zeros((4, 1)), C=np.eye(4), x0=[0.0, 0.0, 1.0, vy], T=0.1)
        loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                       controller=nc.StateFeedback(np.zeros((1, 4))), downlink=nc.Link(), actuator=nc.HoldLast(),
                       monitor=nc.PathMonitor(line, max_dev=0.5, end_tol=0.06, xy=0), N=1, steps=30, T=0.1,
                       record=nc.Record(signals=("x",), monitor=nc.path_distance))
        return jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))

    off, on = run(0.3), run(0.0)
    assert (bool(off.failed), int(off.fail_step), bool(off.done), int(off.done_step)) == (True, 17, False, 30)
    assert (bool(on.failed), int(on.fail_step), bool(on.done), int(on.done_step)) == (False, 30, True, 20)
    np.testing.assert_allclose(off.parts["monitor"][:19], 0.03 * np.arange(1, 20), atol=1e-5)
    np.testing.assert_allclose(on.parts["monitor"][:20], 0.0, atol=1e-6)    # on the line up to its end


@pytest.mark.parametrize("ds, v, done_step", [(0.01, 4.0, 10), (0.01, 8.0, 5), (0.001, 0.5, 80)])
def test_a_plant_faster_than_the_window_is_followed_not_failed(ds, v, done_step):
    """A plant exactly on a 4 m line at v m/s, T = 0.1, checked with the default window of 32
    points: it moves 0.1 v m per check, more than the window's 31 ds (0.31 m at ds = 0.01 m,
    31 mm at ds = 1 mm). It reaches the end (4, 0) at t + 1 = 40 / v and never leaves the
    line. The progress used to fall behind by 0.1 v - 31 ds per check and the distance to its
    segments grew with the lead: at 4 m/s recorded 0.08, 0.17, ... m for a plant on the line,
    failed at t + 1 = 6 and never completed (at 8 m/s failed at 2; at ds = 1 mm, 0.5 m/s failed at 27)."""
    line = from_waypoints(np.array([[0.0, 0.0], [4.0, 0.0]]), "line4", ds=ds)
    A = np.array([[1.0, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]])
    plant = nc.LTI(A=A, B=np.zeros((4, 1)), C=np.eye(4), x0=[0.0, 0.0, v, 0.0], T=0.1)
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                   controller=nc.StateFeedback(np.zeros((1, 4))), downlink=nc.Link(), actuator=nc.HoldLast(),
                   monitor=nc.PathMonitor(line, max_dev=0.5, end_tol=0.05, xy=0), N=1, steps=100, T=0.1,
                   record=nc.Record(signals=("x",), monitor=nc.path_distance))
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
    assert (bool(tr.failed), bool(tr.done), int(tr.done_step)) == (False, True, done_step)
    np.testing.assert_allclose(tr.parts["monitor"][:done_step], 0.0, atol=1e-5)


def test_a_path_of_two_points():
    """from_waypoints with ds >= the length gives a path of two points (one segment): the
    distance is to that segment (it failed in the trace: the distance read three points).
    p_t = (0.25 t, 0.1): 0.1 m from the segment throughout, complete at its end (t = 4)."""
    seg = from_waypoints(np.array([[0.0, 0.0], [1.0, 0.0]]), "segment", ds=1.0)
    assert seg.M == 2
    t = np.arange(6)
    failed, done, dist = _watch(nc.PathMonitor(seg, max_dev=0.5, end_tol=0.2, xy=0), np.stack([0.25 * t, 0.1 + 0 * t], 1))
    np.testing.assert_allclose(dist, np.where(t <= 4, 0.1, np.hypot(0.25 * t - 1.0, 0.1)), atol=1e-6)
    np.testing.assert_array_equal(done, t >= 4)
    assert not np.any(failed)


def test_track_index_is_the_nearest_point_ahead_on_a_curve():
    """On a quarter circle of radius 1 (ds = 0.01, 158 points), points near the arc at angles
    far beyond a window of 8 points from the start: the progress is the nearest path point
    (numpy, over the whole path), found from index 0 in one call; a point before the
    progress keeps it (monotone)."""
    th = np.linspace(0.0, 0.5 * np.pi, 2001)
    arc = from_waypoints(np.stack([np.cos(th), np.sin(th)], 1), "arc", ds=0.01)
    pts = np.asarray(arc.points, np.float64)
    for ang, r in ((0.3, 1.05), (0.9, 0.97), (1.5, 1.0), (1.57, 1.2)):
        p = np.array([r * np.cos(ang), r * np.sin(ang)])
        want = int(np.argmin(np.sum((pts - p) ** 2, axis=1)))
        got = int(jax.jit(track_index, static_argnums=3)(arc, jnp.asarray(p, jnp.float32), 0, 8))
        assert got == want, (ang, r, got, want)
    assert int(track_index(arc, jnp.asarray([1.0, 0.0]), 100, 8)) == 100


@pytest.mark.parametrize("kw, match", [
    (dict(max_dev=0.0), "PathMonitor.max_dev"),
    (dict(end_tol=-1.0), "PathMonitor.end_tol"),
    (dict(window=1), r"PathMonitor.window must be an integer in \[2, inf\)"),
    (dict(xy=-1), "PathMonitor.xy"),
    (dict(every=0), "PathMonitor.every"),
])
def test_bad_fields_name_themselves(kw, match):
    with pytest.raises(ValueError, match=match):
        nc.PathMonitor(LINE, **kw)


def test_refuses_a_non_path_and_a_position_beyond_the_state():
    with pytest.raises(ValueError, match="PathMonitor.path"):
        nc.PathMonitor(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="PathMonitor.xy"):
        nc.PathMonitor(LINE, xy=1).init(CTX)


@nc.pytree_dataclass
class _BandCount(nc.AbstractMonitor):
    """A user's monitor with state: counts the fast periods after which |x0| > band, fails
    when |x0| > bound, complete once the count reaches `enough` (freeze: the declared default)."""
    band: float = 0.5
    bound: float = 1.0
    enough: int = nc.static_field(6)

    def init(self, ctx):
        return jnp.zeros((), jnp.int32)

    def step(self, count, x, u, t):
        count = count + (jnp.abs(x[0]) > self.band).astype(jnp.int32)
        return count, jnp.abs(x[0]) > self.bound, count >= self.enough


def _count(monitor, state):
    return state


def test_a_freezing_monitor_stops_once_the_run_failed():
    """x+ = 1.2 x from x0 = 0.1 without control: x_t = 0.1 1.2^t exceeds the band 0.5 from t = 9
    and the bound 1 at t = 13 (fail_step 13; the plant is frozen at x_12 = 0.892). The monitor's
    count reaches 5 (t = 9..13) and must stay there: after the failure the runner used to step it
    on a state the frozen plant never had (a step from x_12 each period), so the count kept
    growing (to 1 + steps - 9) and the run was marked complete at step 14, after its failure."""
    plant = nc.LTI(A=[[1.2]], B=[[0.0]], C=[[1.0]], x0=[0.1], T=0.1)
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                   controller=nc.StateFeedback(np.zeros((1, 1))), downlink=nc.Link(), actuator=nc.HoldLast(),
                   monitor=_BandCount(), N=1, steps=30, T=0.1, record=nc.Record(signals=("x",), monitor=_count))
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(0))
    t = np.arange(30)
    x = 0.1 * 1.2 ** np.minimum(t, 12)                      # frozen at the last good state from t = 13 on
    np.testing.assert_allclose(np.asarray(tr.x)[:, 0], x, rtol=1e-5)
    assert (bool(tr.failed), int(tr.fail_step)) == (True, 13)
    count = np.cumsum(0.1 * 1.2 ** (t + 1) > 0.5)           # after fast period t: the state x_{t+1}
    np.testing.assert_array_equal(np.asarray(tr.parts["monitor"]), np.minimum(count, 5))
    assert (bool(tr.done), int(tr.done_step)) == (False, 30)


def test_a_failed_runs_transmissions_and_rates_stop_at_the_failure():
    """x+ = 1.2 x from 0.1, N = 2, Monitor(bounds=[1]): the state leaves the bound after fast period 12
    (fail_step 13), in slow period 6, so the run lived 7 of its 15 slow periods. A PETC sensor (no
    noise) sends at k = 0, 2, 4, 6 while x grows and nothing once the plant is held: 4 sends in 7
    periods, rate 4/7. The rates used to count the 8 periods of the frozen plant (4/15 = 0.267, and
    15 controller sends for 7 periods lived); Trajectory's tx_sc/tx_ca stay the whole run's counts
    (as its records); a run that does not fail is unchanged (15 periods)."""
    plant = nc.LTI(A=[[1.2]], B=[[0.0]], C=[[1.0]], x0=[0.1], T=0.1)

    def loop(bound):
        return nc.Loop(plant=plant, trigger=nc.Petc(sigma=0.1), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                       controller=nc.StateFeedback(np.zeros((1, 1))), downlink=nc.Link(), actuator=nc.HoldLast(),
                       monitor=nc.Monitor(bounds=[bound]), N=2, steps=30, T=0.1)

    lp = loop(1.0)
    tr = jax.jit(nc.simulate)(lp, jax.random.PRNGKey(0))
    assert (bool(tr.failed), int(tr.fail_step)) == (True, 13)
    np.testing.assert_array_equal(np.asarray(tr.sent_sc)[:7], [1, 0, 1, 0, 1, 0, 1])
    m = nc.evaluate(lp, tr)
    assert float(m.rate_sc) == pytest.approx(4 / 7) and float(m.rate_ca) == 1.0 and bool(m.unstable)
    assert (float(tr.tx_sc), float(tr.tx_ca)) == (4.0, 15.0)             # the record: the whole run
    assert int(nc.live_periods(tr.failed, tr.fail_step, 2, 15)) == 7
    ok = jax.jit(nc.simulate)(loop(1e6), jax.random.PRNGKey(0))          # never fails: every period counts
    assert not bool(ok.failed) and int(nc.live_periods(ok.failed, ok.fail_step, 2, 15)) == 15
    assert float(ok.tx_ca) == 15.0 and float(nc.evaluate(loop(1e6), ok).rate_ca) == 1.0
    assert float(nc.evaluate(loop(1e6), ok).rate_sc) == pytest.approx(float(np.sum(ok.sent_sc)) / 15)


def _nan_beyond_half(params, xhat):
    return jnp.where(jnp.abs(xhat[0]) > 0.5, jnp.nan, params * xhat[0])


def test_the_run_tells_a_non_finite_action_from_the_plant_leaving_its_bounds():
    """x+ = 1.2 x from 0.1, N = 1, Monitor(bounds=[1]): the plant leaves the bound after fast period
    12 (fail_step 13). A controller that returns NaN once its estimate exceeds 0.5 (x_9 = 0.516, read
    at k = 9 without delay) fails the run at 10 instead, by its action: Trajectory.fail_action and
    Metrics.unstable_action say so (they used to look the same as the plant's divergence); the
    controller that never breaks fails by the plant's state, fail_action False."""
    plant = nc.LTI(A=[[1.2]], B=[[0.0]], C=[[1.0]], x0=[0.1], T=0.1)

    def loop(fn):
        return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                       controller=nc.Function(params=0.0, fn=fn), downlink=nc.Link(), actuator=nc.HoldLast(),
                       monitor=nc.Monitor(bounds=[1.0]), N=1, steps=30, T=0.1)

    breaks, holds = loop(_nan_beyond_half), loop(lambda p, xhat: p * xhat[0])
    run = jax.jit(jax.vmap(nc.simulate, in_axes=(None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    for lp, step, by_action in ((breaks, 10, True), (holds, 13, False)):
        tr = run(lp, keys)
        np.testing.assert_array_equal(np.asarray(tr.fail_step), [step, step])
        np.testing.assert_array_equal(np.asarray(tr.fail_action), [by_action] * 2)
        m = jax.vmap(nc.evaluate, in_axes=(None, 0))(lp, tr)
        np.testing.assert_array_equal(np.asarray(m.unstable), [True, True])
        np.testing.assert_array_equal(np.asarray(m.unstable_action), [by_action] * 2)
        assert f"unstable_action  {float(by_action):.4g} of the runs" in repr(m)
    ok = jax.jit(nc.simulate)(dataclasses.replace(holds, monitor=nc.Monitor(bounds=[1e6])), keys[0])
    assert not bool(ok.failed) and not bool(ok.fail_action)


def test_a_path_monitor_reads_the_position_its_plant_declares():
    """A DiffDrive, state (w_r, w_l, x, y, psi), coasting from wheel speeds (10, 10) rad/s at
    the origin along +x (no command): its position stays on the line y = 0. PathMonitor(line)
    without ``xy`` reads (x, y) = state[2:4], the plant's declared position_index, the same
    run bit for bit as xy=2 given. It used to default to xy = 0 and read the wheel speeds
    (10, 10) as the position, 10 m off the line: failed after the first fast period (fail_step 1)."""
    line = from_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), "line2", ds=0.01)
    plant = nc.DiffDrive(x0=(10.0, 10.0, 0.0, 0.0, 0.0), T=0.1, sub=10)

    def loop(monitor):
        return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                       controller=nc.StateFeedback(np.zeros((2, 5))), downlink=nc.Link(), actuator=nc.HoldLast(),
                       monitor=monitor, N=10, steps=50, T=0.01, record=nc.Record(signals=("x",), monitor=nc.path_distance))

    declared, given = loop(nc.PathMonitor(line, max_dev=0.5)), loop(nc.PathMonitor(line, max_dev=0.5, xy=2))
    assert nc.DiffDrive.position_index == 2 and declared.monitor.xy == 2
    sim = jax.jit(nc.simulate)
    a, b = sim(declared, jax.random.PRNGKey(0)), sim(given, jax.random.PRNGKey(0))
    x = np.asarray(a.x)
    assert x[-1, 2] > 0.02 and np.abs(x[:, 3]).max() < 1e-9       # it moved along the line
    assert (bool(a.failed), int(a.fail_step)) == (False, 50)
    np.testing.assert_array_equal(np.asarray(a.parts["monitor"]), np.asarray(b.parts["monitor"]))
    assert (int(a.fail_step), int(a.done_step)) == (int(b.fail_step), int(b.done_step))


def test_a_loop_rebuilt_with_another_plant_fills_the_position_from_that_plant():
    """``dataclasses.replace(loop, plant=other)``: the xy a Loop filled from its DiffDrive (2) is
    filled again from the new plant; an LTI declares no position, so that loop is refused (it
    used to keep xy = 2 and read an unrelated plant's state[2:4] as the position). An xy the
    user gave is the user's: kept."""
    import dataclasses
    line = from_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), "line2", ds=0.01)
    loop = lambda **kw: nc.Loop(plant=nc.DiffDrive(T=0.1, sub=10), trigger=nc.Periodic(), uplink=nc.Link(),
                                estimator=nc.Passthrough(0.0), controller=nc.StateFeedback(np.zeros((2, 5))),
                                downlink=nc.Link(), actuator=nc.HoldLast(), monitor=nc.PathMonitor(line, **kw),
                                N=10, steps=50, T=0.01)
    lti = nc.LTI(A=np.eye(5), B=np.zeros((5, 2)), C=np.eye(5), T=0.01)
    filled, given = loop(), loop(xy=2)
    assert filled.monitor.xy == 2 and dataclasses.replace(filled, steps=60).monitor.xy == 2
    with pytest.raises(ValueError, match="Loop.monitor.xy must be given"):
        dataclasses.replace(filled, plant=lti)
    assert dataclasses.replace(given, plant=lti).monitor.xy == 2


def test_the_declared_positions_are_the_vehicles_planar_positions():
    """Each vehicle's position_index points at the (x, y) of its initial pose in the state
    vector (DiffDrive: (w_r, w_l, x, y, psi); Mecanum: (Vx, Vy, W, X, Y, psi)); a wrapped
    plant declares its inner plant's; a plant without a planar position declares None."""
    from jaxnc.plants.mecanum import Mecanum

    key = jax.random.PRNGKey(0)
    for plant in (nc.DiffDrive(x0=(0.0, 0.0, 1.5, -0.5, 0.3)),
                  Mecanum(x0=np.asarray([0.0, 0.0, 0.0, 1.5, -0.5, 0.3], np.float32)),
                  nc.LimitedSensor(nc.DiffDrive(x0=(0.0, 0.0, 1.5, -0.5, 0.3)), nc.Saturation(-9.0, 9.0))):
        i = plant.position_index
        np.testing.assert_array_equal(np.asarray(plant.state_vector(plant.init(key)))[i:i + 2], [1.5, -0.5])
    assert nc.LTI(A=[[1.0]], B=[[1.0]], C=[[1.0]]).position_index is None


def test_a_loop_refuses_a_path_monitor_without_xy_on_a_plant_without_a_position():
    """An LTI declares no planar position: PathMonitor(line) without xy is refused when the
    Loop is built, naming xy; with xy given it is built; outside a Loop, init refuses xy None."""
    A = np.array([[1.0, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]])
    plant = nc.LTI(A=A, B=np.zeros((4, 1)), C=np.eye(4), T=0.1)
    loop = lambda **kw: nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0),
                                controller=nc.StateFeedback(np.zeros((1, 4))), downlink=nc.Link(),
                                actuator=nc.HoldLast(), monitor=nc.PathMonitor(LINE, **kw), T=0.1, steps=10)
    with pytest.raises(ValueError, match="Loop.monitor.xy must be given: PathMonitor watches a planar position"):
        loop()
    assert loop(xy=0).monitor.xy == 0
    with pytest.raises(ValueError, match="PathMonitor.xy must be given"):
        nc.PathMonitor(LINE).init(CTX)
