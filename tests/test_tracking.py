"""jaxnc.tracking against closed forms and python-control's step_info (float64)."""
import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import tracking as tr

KEYS = {"rise_time": "RiseTime", "settling_time": "SettlingTime", "settling_min": "SettlingMin",
        "settling_max": "SettlingMax", "overshoot": "Overshoot", "undershoot": "Undershoot", "peak": "Peak",
        "peak_time": "PeakTime", "steady_state_value": "SteadyStateValue"}


def test_integral_criteria_closed_form():
    """e_k = c a^k: ISE = T c^2 (1 - a^2K) / (1 - a^2), IAE = T |c| (1 - a^K) / (1 - a),
    ITAE = T^2 |c| sum_{k<K} k a^k = T^2 |c| a (1 - K a^(K-1) + (K-1) a^K) / (1 - a)^2."""
    with jax.enable_x64(True):
        K, T, a = 60, 0.05, 0.9
        c = np.array([1.5, -0.4])
        e = c[None, :] * a ** np.arange(K)[:, None]
        f = jax.jit(lambda e, T: (tr.ise(e, T), tr.iae(e, T), tr.itae(e, T)))
        got = f(jnp.asarray(e), T)
        want_ise = T * c ** 2 * (1 - a ** (2 * K)) / (1 - a ** 2)
        want_iae = T * np.abs(c) * (1 - a ** K) / (1 - a)
        want_itae = T ** 2 * np.abs(c) * a * (1 - K * a ** (K - 1) + (K - 1) * a ** K) / (1 - a) ** 2
        for g, w in zip(got, (want_ise, want_iae, want_itae)):
            assert g.shape == (2,)
            np.testing.assert_allclose(np.asarray(g), w, rtol=1e-12)
        # one channel: scalar results, the first channel's values
        np.testing.assert_allclose(float(jax.jit(tr.itae)(jnp.asarray(e[:, 0]), T)), want_itae[0], rtol=1e-12)


def test_itae_counts_time_from_start():
    """ITAE with start = s per channel: sum_k (k - s)_+ T |e_k| T; e = c a^(k - s) from s on
    gives the geometric closed form over the K - s samples, and the samples before s weigh 0."""
    with jax.enable_x64(True):
        K, T, a = 60, 0.05, 0.9
        c, s = np.array([1.5, -0.4]), np.array([0, 25])
        k = np.arange(K)[:, None]
        e = np.where(k >= s[None, :], c[None, :] * a ** np.maximum(k - s[None, :], 0), 7.0)    # 7 before s
        got = jax.jit(lambda e, s: tr.itae(e, T, start=s))(jnp.asarray(e), jnp.asarray(s))
        L = K - s
        want = T ** 2 * np.abs(c) * a * (1 - L * a ** (L - 1) + (L - 1) * a ** L) / (1 - a) ** 2
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12)
        np.testing.assert_allclose(float(tr.itae(jnp.asarray(e[:, 1]), T, start=25)), want[1], rtol=1e-12)
        with pytest.raises(ValueError, match="itae: start"):
            tr.itae(jnp.asarray(e), T, start=1.5)
        with pytest.raises(ValueError, match="itae: start"):
            tr.itae(jnp.asarray(e), T, start=jnp.zeros(3, jnp.int32))


def test_integral_criteria_gradient():
    with jax.enable_x64(True):
        e = jnp.asarray(np.random.default_rng(0).normal(size=20))
        g = jax.jit(jax.grad(lambda e: tr.ise(e, 0.1)))(e)
        np.testing.assert_allclose(np.asarray(g), 0.2 * np.asarray(e), rtol=1e-12)
        g = jax.jit(jax.grad(lambda e: tr.itae(e, 0.1)))(e)
        np.testing.assert_allclose(np.asarray(g), 0.01 * np.arange(20) * np.sign(np.asarray(e)), rtol=1e-12)


def test_steady_state_error():
    e = jnp.asarray(np.stack([np.linspace(1.0, 0.0, 11), np.full(11, 0.25)], axis=1), jnp.float32)
    got = jax.jit(lambda e: tr.steady_state_error(e, window=3))(e)
    np.testing.assert_allclose(np.asarray(got), [0.1, 0.25], rtol=1e-6)
    with pytest.raises(ValueError, match="window"):
        tr.steady_state_error(e, window=12)


SYSTEMS = {
    "overdamped": control.tf([2.0], [1.0, 3.0, 2.0]),                       # no overshoot, gain 1
    "underdamped": control.tf([4.0], [1.0, 0.8, 4.0]),                      # zeta 0.2
    "lightly_damped_neg": control.tf([-3.0], [1.0, 0.4, 1.0]),              # negative gain
    "nonminimum_phase": control.tf([-1.0, 2.0], [1.0, 2.0, 2.0]),           # undershoot
    "first_order": control.tf([0.5], [2.0, 1.0]),
}


@pytest.mark.parametrize("name", sorted(SYSTEMS))
@pytest.mark.parametrize("T", [0.01, 0.1])
def test_step_info_matches_python_control(name, T):
    sys = SYSTEMS[name]
    K = int(round(30.0 / T))
    t = T * np.arange(K)
    _, y = control.step_response(sys, t)
    want = control.step_info(y, t)
    with jax.enable_x64(True):
        got = jax.jit(tr.step_info)(jnp.asarray(y), T)
    for field, key in KEYS.items():
        np.testing.assert_allclose(float(getattr(got, field)), want[key], rtol=1e-9, atol=1e-12,
                                   err_msg=f"{name} {field}")
    assert np.isnan(float(got.steady_state_error))
    # the final value given (the DC gain, python-control's choice for a system)
    with jax.enable_x64(True):
        dc = float(np.real(sys.dcgain()))
        got = jax.jit(lambda y: tr.step_info(y, T, y_final=dc, reference=1.0, settling_threshold=0.05,
                                             rise_time_limits=(0.05, 0.95)))(jnp.asarray(y))
    want = control.step_info(y, t, final_output=dc, SettlingTimeThreshold=0.05, RiseTimeLimits=(0.05, 0.95))
    for field, key in KEYS.items():
        np.testing.assert_allclose(float(getattr(got, field)), want[key], rtol=1e-9, atol=1e-12,
                                   err_msg=f"{name} {field} y_final")
    np.testing.assert_allclose(float(got.steady_state_error), 1.0 - dc, rtol=1e-12)


def test_step_info_channels_and_vmap():
    """float[K, p] is characterised per channel; vmap over seeds equals the loop."""
    T = 0.05
    t = T * np.arange(400)
    ys = np.stack([control.step_response(SYSTEMS[n], t)[1] for n in ("overdamped", "underdamped")], axis=1)
    with jax.enable_x64(True):
        got = jax.jit(lambda y: tr.step_info(y, T, reference=jnp.array([1.0, 1.0])))(jnp.asarray(ys))
        assert got.overshoot.shape == (2,)
        for j in range(2):
            one = tr.step_info(jnp.asarray(ys[:, j]), T, reference=1.0)
            for a, b in zip(got, one):
                np.testing.assert_allclose(float(a[j]), float(b), rtol=1e-12)
        batch = jnp.asarray(np.stack([ys[:, 1] * s for s in (0.5, 1.0, 2.0)]))
        vm = jax.jit(jax.vmap(lambda y: tr.step_info(y, T)))(batch)
        for i, s in enumerate((0.5, 1.0, 2.0)):
            want = control.step_info(ys[:, 1] * s, t)
            np.testing.assert_allclose(float(vm.overshoot[i]), want["Overshoot"], rtol=1e-9)
            np.testing.assert_allclose(float(vm.settling_time[i]), want["SettlingTime"], rtol=1e-9)


def test_step_info_initial_value_is_a_shift():
    """A response from y_initial = 20 to 25 has the characteristics of 0 -> 5, levels shifted."""
    T = 0.1
    t = T * np.arange(300)
    _, y = control.step_response(5.0 * SYSTEMS["underdamped"], t)
    with jax.enable_x64(True):
        base = tr.step_info(jnp.asarray(y), T)
        shifted = tr.step_info(jnp.asarray(y + 20.0), T, y_initial=20.0)
    for f in ("rise_time", "settling_time", "overshoot", "undershoot", "peak", "peak_time"):
        np.testing.assert_allclose(float(getattr(shifted, f)), float(getattr(base, f)), rtol=1e-12)
    for f in ("settling_min", "settling_max", "steady_state_value"):
        np.testing.assert_allclose(float(getattr(shifted, f)), float(getattr(base, f)) + 20.0, rtol=1e-12)


def test_step_info_not_reached_and_gradient():
    with jax.enable_x64(True):
        y = jnp.linspace(0.0, 0.5, 50)                       # never reaches 0.9 of y_final = 1
        info = tr.step_info(y, 0.1, y_final=1.0)
        assert np.isnan(float(info.rise_time)) and np.isnan(float(info.settling_time))
        flat = tr.step_info(jnp.full(20, 3.0), 0.1, y_initial=3.0)      # no change: nothing to measure
        assert np.isnan(float(flat.rise_time)) and np.isnan(float(flat.overshoot))
        assert float(flat.steady_state_value) == 3.0
        # overshoot is differentiable in y: d/dy_peak of 100 (y_peak - y_f) / y_f
        _, y = control.step_response(SYSTEMS["underdamped"], 0.1 * np.arange(300))
        y = jnp.asarray(y)
        g = jax.jit(jax.grad(lambda y: tr.step_info(y, 0.1, y_final=1.0).overshoot))(y)
        k = int(jnp.argmax(y))
        want = np.zeros(300)
        want[k] = 100.0
        np.testing.assert_allclose(np.asarray(g), want, atol=1e-12)


def test_step_info_bad_inputs():
    y = jnp.zeros(10)
    with pytest.raises(ValueError, match="settling_threshold"):
        tr.step_info(y, 0.1, settling_threshold=1.5)
    with pytest.raises(ValueError, match="rise_time_limits"):
        tr.step_info(y, 0.1, rise_time_limits=(0.9, 0.1))
    with pytest.raises(ValueError, match="float\\[K\\]"):
        tr.step_info(jnp.zeros((2, 3, 4)), 0.1)
