"""Seed 001 balancing robot: plant linearisation, hold-aware gain, and the closed loops."""
import math

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import wifi
from jaxnc.controllers.hold_lq import dlqr, hold_lq_gain
from jaxnc.plants.balancing import Balancing
from jaxnc.schemes import balancing as bal

SHORT = 3.0          # s of simulated time for loop tests (step at 1.5 s)
PERFECT = wifi.WifiChannel(delay_pmf=np.asarray([1.0], np.float32))


def test_linearisation_is_the_jacobian_of_the_nonlinear_model():
    p = Balancing()
    with jax.enable_x64(True):
        x0, u0 = jnp.zeros(4), jnp.float64(0.0)
        Ac = np.asarray(jax.jacfwd(p.derivative, argnums=0)(x0, u0))
        Bc = np.asarray(jax.jacfwd(p.derivative, argnums=1)(x0, u0))
    A_ref, B_ref = p.continuous()
    np.testing.assert_allclose(Ac, A_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(Bc, B_ref[:, 0], rtol=1e-10, atol=1e-10)
    assert np.max(np.linalg.eigvals(A_ref).real) > 1.0          # unstable inverted pendulum


def test_exact_zoh_matches_python_control():
    p = Balancing()
    A, B, _ = p.discrete()
    Ac, Bc = p.continuous()
    sysd = control.c2d(control.ss(Ac, Bc, np.eye(4), np.zeros((4, 1))), p.Ts, method="zoh")
    np.testing.assert_allclose(A, sysd.A, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(B, sysd.B, rtol=1e-9, atol=1e-12)


def test_nonlinear_step_agrees_with_linear_model_near_upright():
    p = Balancing(w_servo=0.0, w_theta=0.0)
    A, B, _ = p.discrete()
    x = np.array([0.0, 1e-4, 0.0, 0.0])
    with jax.enable_x64(True):
        xn = np.asarray(p.dynamics(jnp.asarray(x), jnp.asarray([0.5]), jnp.zeros(2)))
    np.testing.assert_allclose(xn, A @ x + B[:, 0] * 0.5, rtol=1e-6, atol=1e-10)


def test_hold_aware_gain_is_lqr_at_theta_one():
    p = Balancing()
    A, B, _ = p.discrete()
    L, S11 = hold_lq_gain(A, B, bal.W_LQ, bal.U_LQ, 1.0)
    K, S, _ = control.dlqr(A, B, bal.W_LQ, bal.U_LQ)
    np.testing.assert_allclose(L, -K, rtol=1e-6)
    np.testing.assert_allclose(S11, S, rtol=1e-6)


def test_hold_aware_gain_satisfies_its_riccati_equation_and_differs_below_one():
    """Brute-force check on a small system: value iteration of the augmented hold problem."""
    A = np.array([[1.1, 0.2], [0.0, 0.9]])
    B = np.array([[0.0], [1.0]])
    W, U, theta = np.eye(2), np.array([[0.5]]), 0.7
    L, _ = hold_lq_gain(A, B, W, U, theta)
    # independent reference: iterate the Bellman recursion on z = [x; v] with the full S
    n = 2
    S = np.zeros((3, 3))
    for _ in range(5000):
        Fu = np.vstack([np.hstack([A, np.zeros((n, 1))]), np.zeros((1, 3))])  # z -> [Ax; 0]
        Gw = np.vstack([B, np.eye(1)])                                          # + [B; 1] w
        Wz = np.zeros((3, 3)); Wz[:n, :n] = W
        # E over w in {u (theta), v (1 - theta)}; u = Lz x minimises theta * (...)
        Tm = U + Gw.T @ S @ Gw
        Hm = Fu.T @ S @ Gw                                                       # 3 x 1
        Lz = -np.linalg.solve(Tm, Hm.T)                                          # u = Lz z
        Ev = np.zeros((1, 3)); Ev[0, n] = 1.0
        Ku = np.hstack([Lz[:, :n], np.zeros((1, 1))])
        def q(M):  # quadratic form of applying w = M z
            return Wz + Fu.T @ S @ Fu + M.T @ Tm @ M + Hm @ M + M.T @ Hm.T
        S = theta * q(Ku) + (1 - theta) * q(Ev)
    Tm = U + Gw.T @ S @ Gw
    L_ref = -np.linalg.solve(Tm, (Fu.T @ S @ Gw).T)[:, :n]
    np.testing.assert_allclose(L, L_ref, rtol=1e-6)
    K = dlqr(A, B, W, U)[0]
    assert np.max(np.abs(L + K)) > 1e-3                          # differs from LQR for theta < 1


@pytest.mark.parametrize("design", bal.DESIGNS)
def test_perfect_network_balances_and_tracks_the_step(design):
    loop = bal.balancing_loop(design, horizon_s=SHORT, t_step=1.0)
    m = jax.jit(bal.run)(loop, jax.random.PRNGKey(0), PERFECT, PERFECT)
    assert bool(m.upright)
    assert float(m.tilt_max_deg) < 10.0
    tr = jax.jit(bal.simulate)(loop, np.zeros(loop.steps, np.int32), np.zeros(loop.steps, np.int32),
                               jax.random.PRNGKey(1))
    pos = float(loop.plant.robot.r) * (float(tr.x[-1, 0]) + float(tr.x[-1, 1]))
    assert abs(pos - 0.1) < 0.02                                  # within 2 cm of the 0.1 m step after 2 s


def test_same_trace_same_run_and_designs_share_the_network():
    loop = bal.balancing_loop("model", horizon_s=1.0)
    key = jax.random.PRNGKey(3)
    sc, ca = bal.traces(key, wifi.NOMINAL, wifi.NOMINAL, loop.steps)
    f = jax.jit(bal.simulate)
    a, b = f(loop, sc, ca, key), f(loop, np.asarray(sc), np.asarray(ca), key)
    np.testing.assert_array_equal(a.x, b.x)
    sc2 = np.asarray(sc).copy(); sc2[100:300] = wifi.LOST                # a different network differs
    assert not np.array_equal(np.asarray(f(loop, sc2, ca, key).xhat), np.asarray(a.xhat))


def test_total_blackout_makes_it_fall_as_data_not_exception():
    loop = bal.balancing_loop("emulation", horizon_s=2.0)
    lost = np.full(loop.steps, wifi.LOST, np.int32)
    m = bal.metrics(loop, jax.jit(bal.simulate)(loop, lost, lost, jax.random.PRNGKey(0)))
    assert not bool(m.upright) and np.isinf(float(m.tilt_rms_deg))


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="design"):
        bal.balancing_loop("foo")
    with pytest.raises(ValueError, match="gain"):
        bal.balancing_loop(gain="bar")
    with pytest.raises(ValueError, match="theta"):
        hold_lq_gain(np.eye(1), np.eye(1), np.eye(1), np.eye(1), 0.0)


# ----------------------------------------------------------------------------- issue 23: the
# emulation design's simple differentiation, the complementary-filter tilt sensor


def test_simple_derivative_is_the_backward_difference_of_the_held_measurement():
    """Hand computation on 10 steps: packets with delays, a loss and a reordering; the
    observer holds the most recently arrived measurement (eq. 5) and differences it over
    one period (section 5), 0 when nothing new arrives."""
    loop = bal.balancing_loop("emulation", horizon_s=0.010)          # 10 steps, simple by default
    assert float(loop.estimator.tau_d) == 0.0
    LOST = wifi.LOST
    sc = np.array([0, 1, LOST, 0, 3, 0, 0, 1, 0, 0], np.int32)
    # arrivals: p0@0, p1@2, p3@3, p4@7, p5@5, p6@6, p7@8, p8@8, p9@9 (p2 lost); held packet
    # (the latest arrival, the newest of those arriving together):
    held = [0, 0, 1, 3, 3, 5, 6, 4, 8, 9]
    ca = np.zeros(10, np.int32)
    tr = jax.jit(bal.simulate)(loop, sc, ca, jax.random.PRNGKey(4))
    z, xhat = np.asarray(tr.z), np.asarray(tr.xhat)
    ybar = z[held]
    np.testing.assert_array_equal(xhat[:, :2], ybar)
    rate = np.zeros_like(ybar)
    Ts = np.float32(loop.T)
    for k in range(1, 10):
        rate[k] = (ybar[k] - ybar[k - 1]) / Ts
    np.testing.assert_allclose(xhat[:, 2:], rate, rtol=1e-5, atol=1e-4)
    assert np.all(xhat[[0, 1, 4], 2:] == 0.0)                       # start, and nothing new at 1 and 4
    assert np.all(np.abs(xhat[[2, 3, 5, 6, 7, 8, 9], 3]) > 0.0)     # a new tilt sample: a nonzero rate


def test_derivative_option_is_validated():
    with pytest.raises(ValueError, match="derivative must be one of simple, filtered"):
        bal.balancing_loop("emulation", derivative="dirty")
    with pytest.raises(ValueError, match="tau_d applies to derivative='filtered' only"):
        bal.balancing_loop("emulation", tau_d=0.005)
    with pytest.raises(ValueError, match=r"tau_d must be in \(0, inf\), got 0.0"):
        bal.balancing_loop("emulation", derivative="filtered", tau_d=0.0)
    loop = bal.balancing_loop("emulation", derivative="filtered")
    assert float(loop.estimator.tau_d) == pytest.approx(0.005)
    with pytest.raises(ValueError, match="Balancing.tilt_sensor must be one of complementary, white"):
        Balancing(tilt_sensor="gyro")


def _cf_reference_error(seed, K, p):
    """The complementary filter itself, on an IMU with the plant's noises and a moving
    tilt: th^_k = a (th^_{k-1} + Ts g_k) + (1 - a) t_k, the gyro integrated exactly."""
    import scipy.signal
    rng = np.random.default_rng(seed)
    Ts, tau = float(p.Ts), float(p.tau_cf)
    a = tau / (tau + Ts)
    th = 0.05 * np.sin(2 * np.pi * 0.7 * Ts * np.arange(K + 1))
    g = np.diff(th) / Ts + float(p.sigma_gyro) * rng.standard_normal(K)
    acc = th[1:] + float(p.sigma_accel) * rng.standard_normal(K)
    est = scipy.signal.lfilter([1.0], [1.0, -a], a * Ts * g + (1 - a) * acc,
                               zi=[a * th[0]])[0]
    return est - th[1:]


def test_tilt_error_is_the_complementary_filters_error():
    """Stationary std of the filter's error (from the filter itself, independently) and of
    the plant's Gauss-Markov sequence, against tilt_error_std; increments of the sequence
    are i.i.d. with the drive's std. Tolerances: 4 standard errors of each estimate."""
    p = Balancing()
    a, drive = (float(v) for v in p._cf())
    sd = float(p.tilt_error_std())
    R, K = 16, 50_000
    # one run's sample variance of an AR(1) has a relative std of about sqrt(2 (1 + a^2) /
    # ((1 - a^2) K)); over R runs divided by sqrt(R)
    rel = 4 * math.sqrt(2 * (1 + a * a) / ((1 - a * a) * K * R))
    ref = np.concatenate([_cf_reference_error(s, K, p)[5 * 500:] for s in range(R)])
    assert abs(np.var(ref) / sd**2 - 1) < rel
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(7), i))(jnp.arange(R))
    e = np.asarray(jax.jit(jax.vmap(lambda k: p.tilt_error(k, K)))(keys), np.float64)
    assert abs(np.mean(e**2) / sd**2 - 1) < rel
    d = e[:, 1:] - a * e[:, :-1]
    assert abs(np.std(d) / drive - 1) < 4 / math.sqrt(2 * d.size)
    # what makes the simple difference usable: a sample-to-sample change ~1e-3 deg,
    # against 0.14 deg for the white 0.1 deg sensor
    assert np.rad2deg(np.std(np.diff(e, axis=1))) < 0.002


def test_emulation_tilt_rms_is_above_the_model_based_at_the_table1_network():
    """Fixed seeds, common random numbers: the paired difference of the tilt RMS
    (emulation - model) is positive by more than 4 of its standard errors."""
    from jaxnc import montecarlo
    keys = montecarlo.seed_keys(11, 16)
    rms = {}
    for d in bal.DESIGNS:
        loop = bal.balancing_loop(d, horizon_s=10.0, t_step=5.0)
        m = jax.jit(jax.vmap(lambda k, loop=loop: bal.run(loop, k)))(keys)
        assert bool(np.all(m.upright))
        rms[d] = np.asarray(m.tilt_rms_deg, np.float64)
    diff = rms["emulation"] - rms["model"]
    assert diff.mean() > 4 * diff.std(ddof=1) / math.sqrt(diff.size)


def test_simple_difference_of_a_white_tilt_noise_falls_on_a_perfect_network():
    """Why the tilt sensor is the complementary filter's (docs/balancing.md): differenced
    over 1 ms, the white 0.1 deg noise is a 2.5 rad/s rate noise that saturates the input,
    and the emulation design falls with every packet in time; with the complementary
    filter's error it stays upright. Perfect network, 10 s, 8 fixed seeds."""
    from jaxnc import montecarlo
    keys = montecarlo.seed_keys(3, 8)
    up = {}
    for sensor in ("complementary", "white"):
        loop = bal.balancing_loop("emulation", plant=Balancing(tilt_sensor=sensor), ca=PERFECT,
                                  horizon_s=10.0, t_step=5.0)
        up[sensor] = np.asarray(jax.jit(jax.vmap(lambda k, loop=loop: bal.run(loop, k).upright))(keys))
    assert up["complementary"].all()
    assert not up["white"].any()


def test_delay_law_family_passes_through_both_severities_and_grows():
    """The sweep's delay axis (docs/balancing.md): index 0 is the Table-1 fit and 1 the
    *delay* severity, bit for bit; the median and mean grow along the index and the
    longest delay at the largest index fits the emulation links' ring."""
    np.testing.assert_array_equal(bal.delay_law(0.0), bal.SEVERITIES["nominal"].delay_pmf)
    np.testing.assert_array_equal(bal.delay_law(1.0), bal.SEVERITIES["delay"].delay_pmf)
    lams = (0.0, 0.3, 0.75, 1.0, 1.25, 1.5, bal.MAX_DELAY_INDEX)
    med, mean = [], []
    for lam in lams:
        p = bal.delay_law(lam).astype(np.float64)
        assert p.min() >= 0 and abs(p.sum() - 1) < 1e-6 and p[0] == 0
        med.append(int(np.searchsorted(np.cumsum(p), 0.5)))
        mean.append(p @ np.arange(p.size))
    assert np.all(np.diff(med) >= 0) and med[0] == 1 and med[-1] >= 10
    assert np.all(np.diff(mean) > 0)
    # a stretched law keeps the mean's affine map: E[1 + lam (d - 1)] = 1 + lam (E d - 1)
    np.testing.assert_allclose(mean[4], 1 + 1.25 * (mean[3] - 1), rtol=1e-5)
    assert bal.delay_law(bal.MAX_DELAY_INDEX).size - 1 <= 31
    bal.balancing_loop("emulation", ca=bal.sweep_channel("delay", bal.MAX_DELAY_INDEX))   # ring holds it
    with pytest.raises(ValueError, match=r"lambda.*\[0, 1.75\]"):
        bal.delay_law(1.8)


def test_sweep_channels_change_one_parameter():
    loss = bal.SEVERITIES["loss"]
    ch = bal.sweep_channel("burst_length", 400.0)
    assert ch.p_bg == 1 / 400 and (ch.p_gb, ch.loss_bad) == (loss.p_gb, loss.loss_bad)
    ch = bal.sweep_channel("burst_loss", 1.0)
    assert ch.loss_bad == 1.0 and (ch.p_gb, ch.p_bg) == (loss.p_gb, loss.p_bg)
    at_loss = bal.sweep_channel("burst_length", 1 / loss.p_bg)         # the axis passes through it
    assert (at_loss.p_gb, at_loss.p_bg, at_loss.loss_bad) == (loss.p_gb, loss.p_bg, loss.loss_bad)
    assert bal.SWEEP_AXES["burst_length"][2] == 1 / loss.p_bg and bal.SWEEP_AXES["burst_loss"][2] == loss.loss_bad
    assert wifi.stationary_loss(bal.sweep_channel("burst_length", 4 / loss.p_bg)) > wifi.stationary_loss(loss)
    with pytest.raises(ValueError, match="sweep axis must be one of burst_length, burst_loss, delay"):
        bal.sweep_channel("jitter", 1.0)
    with pytest.raises(ValueError, match=r"burst_loss.*\[0, 1\]"):
        bal.sweep_channel("burst_loss", 1.5)


def test_kf_tilt_option_sets_the_filters_tilt_variance():
    R = lambda loop: np.asarray(loop.estimator.kf.R)
    design, sensor = (bal.balancing_loop("model", kf_tilt=k) for k in bal.KF_TILT_NOISES)
    p = Balancing()
    np.testing.assert_allclose(R(design)[1, 1], p.sigma_theta ** 2, rtol=1e-6)
    np.testing.assert_allclose(R(sensor)[1, 1], float(p.tilt_error_std()) ** 2, rtol=1e-6)
    assert R(sensor)[1, 1] < 0.05 * R(design)[1, 1]                       # 0.016 deg against 0.1 deg
    np.testing.assert_array_equal(R(sensor)[0], R(design)[0])            # the encoder's entry as it was
    white = Balancing(tilt_sensor="white")
    np.testing.assert_array_equal(R(bal.balancing_loop("model", plant=white, kf_tilt="sensor")),
                                  R(bal.balancing_loop("model", plant=white)))
    with pytest.raises(ValueError, match="kf_tilt must be one of design, sensor"):
        bal.balancing_loop("model", kf_tilt="coloured")
