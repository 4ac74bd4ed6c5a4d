"""jaxnc.loop.Tracking: step metrics measured from a Step's instant (float64), against
closed forms and python-control's step_info on the post-step samples."""
import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import references as refs
from jaxnc import tracking as tr

METRICS = jax.jit(lambda tracking, x, T: tracking.metrics(x, T))


def _metrics(tracking, y, T):
    """TrackingMetrics of the response y float[K] or float[K, c] (the state x = y) as float64 numpy."""
    with jax.enable_x64(True):
        x = jnp.asarray(y if np.ndim(y) == 2 else np.asarray(y)[:, None], jnp.float64)
        return jax.tree.map(np.asarray, METRICS(tracking, x, T))


def _itae_geometric(T, c, a, L):
    """sum_{j<L} (j T) |c| a^j T in closed form."""
    return T ** 2 * abs(c) * a * (1 - L * a ** (L - 1) + (L - 1) * a ** L) / (1 - a) ** 2


def test_first_order_step_at_t0_closed_form():
    """y = A (1 - exp(-(t - t0) / tau)) from the step at t0 = 5 s, 0 before: settling and
    rise time and ITAE of the sampled exponential, counted from t0."""
    T, K, A, tau, t0 = 0.5, 120, 30.0, 4.0, 5.0
    k0 = 10                                               # t0 / T
    a = np.exp(-T / tau)
    k = np.arange(K)
    y = np.where(k >= k0, A * (1 - a ** np.maximum(k - k0, 0)), 0.0)
    m = _metrics(nc.Tracking(refs.Step(A, time=t0), index=0), y, T)
    # |y / A - 1| = a^j >= 0.02 for j <= tau ln 50 / T = 31.3: settled from j = 32
    np.testing.assert_allclose(m.settling_time, [T * (np.floor(tau * np.log(50.0) / T) + 1)], rtol=1e-12)
    assert m.settling_time[0] == 16.0
    # first sample at 10 % (a^j <= 0.9) and at 90 % (a^j <= 0.1)
    want_rise = T * (np.ceil(tau * np.log(10.0) / T) - np.ceil(tau * np.log(1 / 0.9) / T))
    np.testing.assert_allclose(m.rise_time, [want_rise], rtol=1e-12)
    assert m.overshoot[0] == 0.0
    np.testing.assert_allclose(m.itae, [_itae_geometric(T, A, a, K - k0)], rtol=1e-10)
    # the same numbers from python-control's step_info of the post-step samples
    info = control.step_info(y[k0:], timepts=T * np.arange(K - k0), yfinal=A)
    np.testing.assert_allclose(m.settling_time, [info["SettlingTime"]], rtol=1e-12)
    np.testing.assert_allclose(m.rise_time, [info["RiseTime"]], rtol=1e-12)
    np.testing.assert_allclose(m.overshoot, [info["Overshoot"]], atol=1e-12)
    # ISE and IAE are over the whole run (e = 0 before the step here)
    np.testing.assert_allclose(m.iae, [T * A * (1 - a ** (K - k0)) / (1 - a)], rtol=1e-10)


def _underdamped(K, k0, T, level, final, zeta=0.3, wn=2.0):
    """``level`` until the step instant k0, then the second-order step response to ``final``."""
    t = T * np.maximum(np.arange(K) - k0, 0)
    wd = wn * np.sqrt(1 - zeta ** 2)
    s = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / np.sqrt(1 - zeta ** 2) * np.sin(wd * t))
    return level + (final - level) * s


@pytest.mark.parametrize("before", ["bump_above_the_setpoint", "decay_from_elsewhere"])
def test_motion_before_the_step_does_not_enter_the_step_metrics(before):
    """A response that moves before a step at 3 s (above the setpoint, or from another
    starting value) has the step metrics of the same response resting until the step."""
    T, K, k0 = 0.05, 400, 60
    clean = _underdamped(K, k0, T, level=2.0, final=10.0)
    k = np.arange(k0)
    moved = clean.copy()
    moved[:k0] = 2.0 + 11.0 * np.sin(np.pi * k / k0) if before == "bump_above_the_setpoint" else 2.0 + 3.0 * (1 - k / k0)
    tracking = nc.Tracking(refs.Step(8.0, time=3.0, initial=2.0), index=0)
    m_clean, m_moved = _metrics(tracking, clean, T), _metrics(tracking, moved, T)
    info = control.step_info(clean[k0:] - 2.0, timepts=T * np.arange(K - k0), yfinal=8.0)
    assert info["Overshoot"] > 30                                        # zeta = 0.3
    for m in (m_moved, m_clean):
        np.testing.assert_allclose(m.overshoot, [info["Overshoot"]], rtol=1e-10)
        np.testing.assert_allclose(m.settling_time, [info["SettlingTime"]], rtol=1e-12)
        np.testing.assert_allclose(m.rise_time, [info["RiseTime"]], rtol=1e-12)
    # ITAE weighs the samples before the step 0; ISE sees the motion
    np.testing.assert_allclose(m_moved.itae, m_clean.itae, rtol=1e-12)
    assert m_moved.ise[0] > m_clean.ise[0] + 1.0


def test_gradient_reaches_no_sample_before_the_step():
    T, K, k0 = 0.05, 400, 60
    tracking = nc.Tracking(refs.Step(1.0, time=3.0), index=0)
    with jax.enable_x64(True):
        y = jnp.asarray(_underdamped(K, k0, T, level=0.0, final=1.0))
        f = lambda y, field: getattr(tracking.metrics(y[:, None], T), field)[0]
        g_os = np.asarray(jax.jit(jax.grad(f), static_argnums=1)(y, "overshoot"))
        g_itae = np.asarray(jax.jit(jax.grad(f), static_argnums=1)(y, "itae"))
    assert np.all(g_os[:k0] == 0.0) and g_os[int(np.argmax(y))] > 0
    e = 1.0 - np.asarray(y)
    want = -np.maximum(np.arange(K) - k0, 0) * T * T * np.sign(e)
    np.testing.assert_allclose(g_itae, want, atol=1e-12)


def test_a_step_time_per_channel_and_vmap_over_step_times():
    """Step(time=[1, 3]) on two channels, each a first-order response from its own step:
    equal settling times; vmap over a batch of step times gives each one's metrics."""
    T, K, tau = 0.1, 200, 0.5
    a = np.exp(-T / tau)
    k = np.arange(K)
    y = np.stack([np.where(k >= k0, 1 - a ** np.maximum(k - k0, 0), 0.0) for k0 in (10, 30)], axis=1)
    tracking = nc.Tracking(refs.Step(1.0, time=[1.0, 3.0]), index=(0, 1))
    m = _metrics(tracking, y, T)
    want_settling = T * (np.floor(tau * np.log(50.0) / T) + 1)
    np.testing.assert_allclose(m.settling_time, [want_settling] * 2, rtol=1e-12)
    np.testing.assert_allclose(m.itae, [_itae_geometric(T, 1.0, a, K - 10), _itae_geometric(T, 1.0, a, K - 30)],
                               rtol=1e-10)
    with jax.enable_x64(True):
        np.testing.assert_array_equal(np.asarray(tracking.step_instant(K, T)), [10, 30])
    # a batch of trackings whose step times are traced leaves
    times = (1.0, 2.0, 3.0)
    batch = jax.tree.map(lambda *v: jnp.stack([jnp.asarray(u) for u in v]),
                         *[nc.Tracking(refs.Step(1.0, time=t), index=0) for t in times])
    with jax.enable_x64(True):
        vm = jax.jit(jax.vmap(lambda tk: tk.metrics(jnp.asarray(y[:, :1]), T)))(batch)
    for i, t in enumerate(times):
        one = _metrics(nc.Tracking(refs.Step(1.0, time=t), index=0), y[:, :1], T)
        for a_, b_ in zip(vm, one):
            np.testing.assert_allclose(np.asarray(a_)[i], b_, rtol=1e-12)


def test_a_step_after_the_run_has_no_step_metrics():
    T, K = 0.1, 50
    y = np.linspace(0.0, 1.0, K)
    m = _metrics(nc.Tracking(refs.Step(1.0, time=K * T + 1.0), index=0), y, T)
    for f in ("itae", "overshoot", "rise_time", "settling_time"):
        assert np.isnan(getattr(m, f)[0]), f
    np.testing.assert_allclose(m.ise, [np.sum(y ** 2) * T], rtol=1e-12)


@pytest.mark.parametrize("reference", [refs.PiecewiseLinear([0.0, 2.0], [0.0, 1.0]),
                                       refs.Recorded(np.linspace(0.0, 1.0, 30)[:, None])])
def test_other_references_measure_from_the_first_sample(reference):
    T, K = 0.1, 80
    y = _underdamped(K, 5, T, level=0.3, final=1.0)
    tracking = nc.Tracking(reference, index=0)
    m = _metrics(tracking, y, T)
    with jax.enable_x64(True):
        assert np.asarray(tracking.step_instant(K, T)).tolist() == [0]
        r = np.asarray(jax.jit(lambda x, T: tracking.signals(x, T))(jnp.asarray(y)[:, None], T)[1])[:, 0]
        info = tr.step_info(jnp.asarray(y), T, y_final=r[-1], y_initial=y[0])
        itae = tr.itae(jnp.asarray(r - y), T)
    for f in ("overshoot", "rise_time", "settling_time"):
        np.testing.assert_allclose(getattr(m, f)[0], float(getattr(info, f)), rtol=1e-12, equal_nan=True)
    np.testing.assert_allclose(m.itae[0], float(itae), rtol=1e-12)


@pytest.mark.parametrize("reference", [refs.Ramp(0.5, time=2.0), refs.Sine(1.0, 0.2, offset=1.0)])
def test_a_reference_that_does_not_settle_has_no_step_metrics(reference):
    # measured toward a Ramp's or a Sine's last sample, the overshoot and rise time of one
    # response changed with where the run stops (a sine tracked by a PI: 0 %, 29 %, 606 %
    # at 110, 120, 125 steps); they are nan, the integral metrics unchanged
    T, K = 0.1, 80
    y = _underdamped(K, 5, T, level=0.3, final=1.0)
    tracking = nc.Tracking(reference, index=0)
    for k in (K - 7, K):
        m = _metrics(tracking, y[:k], T)
        for f in ("overshoot", "rise_time", "settling_time"):
            assert np.isnan(getattr(m, f)[0]), (f, k)
    with jax.enable_x64(True):
        r = np.asarray(jax.jit(lambda x, T: tracking.signals(x, T))(jnp.asarray(y)[:, None], T)[1])[:, 0]
        itae = tr.itae(jnp.asarray(r - y), T)
    np.testing.assert_allclose(m.itae[0], float(itae), rtol=1e-12)
    np.testing.assert_allclose(m.ise[0], np.sum((r - y) ** 2) * T, rtol=1e-9)


@pytest.mark.parametrize("reference", [refs.PiecewiseLinear([0.0, 10.0], [0.0, 1.0]),
                                       refs.Recorded(np.linspace(0.0, 1.0, 120)[:, None])])
def test_a_reference_still_moving_after_the_run_has_no_step_metrics(reference):
    # a profile whose last breakpoint (or record) ends after the run has no final value yet:
    # a perfect tracker of it read rise time 4 s and settling time 4.9 s toward wherever the
    # run stopped; like a Ramp's, its step metrics are nan, the integral metrics unchanged
    T, K = 0.1, 80
    tracking = nc.Tracking(reference, index=0)
    y = np.asarray(refs.evaluate(reference, K, T))[:, 0] + 0.01
    m = _metrics(tracking, y, T)
    for f in ("overshoot", "rise_time", "settling_time"):
        assert np.isnan(getattr(m, f)[0]), f
    np.testing.assert_allclose(m.ise[0], 0.01 ** 2 * K * T, rtol=1e-4)
    assert not bool(refs.held_at_end(reference, K, T)[0])


def test_held_at_end_at_the_boundary_and_traced():
    T, K = 0.1, 80
    last = (K - 1) * T                                  # a breakpoint on the run's last instant is held
    assert bool(refs.held_at_end(refs.PiecewiseLinear([0.0, last], [0.0, 1.0]), K, T)[0])
    assert not bool(refs.held_at_end(refs.PiecewiseLinear([0.0, last + 0.5 * T], [0.0, 1.0]), K, T)[0])
    assert bool(refs.held_at_end(refs.Recorded(np.zeros(K)), K, T)[0])
    assert not bool(refs.held_at_end(refs.Recorded(np.zeros(K + 1)), K, T)[0])
    assert np.asarray(refs.held_at_end(refs.Step([1.0, 1.0], time=[1.0, 9.0]), K, T)).tolist() == [True, False]
    assert not np.any(np.asarray(refs.held_at_end(refs.Sine([1.0, 2.0], 0.0), K, T)))
    ends = jnp.asarray([5.0, 10.0])
    held = jax.jit(jax.vmap(lambda e: refs.held_at_end(refs.PiecewiseLinear(jnp.stack([0.0 * e, e]),
                                                                            jnp.asarray([0.0, 1.0])), K, T)))(ends)
    assert np.asarray(held)[:, 0].tolist() == [True, False]


def test_a_failed_run_is_left_out_of_the_tracking_summary():
    """A run whose state leaves Monitor.bounds (a random initial velocity) has no tracking
    metrics (its integrals inf, the rest nan, as Metrics.cost is inf): print(tm) and
    summarize average the runs that did not fail. Before, the frozen state's numbers were
    averaged in (ISE 2.6x the stable runs', overshoot 0 %)."""
    from jaxnc import montecarlo
    T, N = 0.005, 2
    A, B, C = np.array([[0, 1.0], [0, -10.0]]), np.array([[0.0], [100.0]]), np.array([[1.0, 0]])
    ref = refs.Step(1.0, time=0.02)
    plant = nc.LTI.from_continuous(A, B, C, T=T, x0=[0.0, 0], x0_std=[0.0, 6.0], w_std=np.zeros(2),
                                   v_std=np.zeros(1))
    loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.PID(Kp=2.0, Ki=1.0, Kd=0.05, Tf=0.01, reference=ref, index=0),
                   downlink=nc.Link(), actuator=nc.HoldLast(), monitor=nc.Monitor(bounds=[5.0, 12.0]),
                   N=N, T=T, steps=200, record=True)
    tracking = nc.Tracking(ref, index=0)
    keys = montecarlo.seed_keys(0, 48)
    m, tm = jax.jit(jax.vmap(nc.run_tracking, in_axes=(0, None, None)))(keys, loop, tracking)
    failed = np.asarray(m.unstable)
    assert 0 < failed.sum() < failed.size                  # some runs fail, most do not
    raw = jax.jit(jax.vmap(lambda k: tracking.metrics(nc.simulate(loop, k).x, T)))(keys)   # the frozen runs' numbers
    for f in tm._fields:
        got, frozen = np.asarray(getattr(tm, f))[:, 0], np.asarray(getattr(raw, f))[:, 0]
        np.testing.assert_allclose(got[~failed], frozen[~failed], rtol=1e-5)   # another program: float32 sums rounded otherwise
        want = np.inf if f in ("ise", "iae", "itae") else np.nan
        np.testing.assert_array_equal(got[failed], np.full(failed.sum(), want))
        s = montecarlo.summarize(got, np.zeros_like(failed))   # no unstable flag needed: left out as not finite
        ok = ~failed & np.isfinite(frozen)
        np.testing.assert_allclose(s.mean, frozen[ok].mean(), rtol=1e-5)
        assert s.n_stable == ok.sum()
    assert f"({failed.sum()} left out" in repr(tm).splitlines()[1]      # the ise line
