"""MRCI decomposition (seed 003 eq. 19-20, 33-34) against closed forms and scipy."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from jaxnc.design import mrci

# eq. (33): gain, zeros, poles exactly as printed (4 decimals)
GAIN, ZEROS, POLES = 1.0882, (0.9813, 0.9681, -1.0), (1.0, 0.8496, 0.6137)


def _cd(gain=GAIN, zeros=ZEROS, poles=POLES):
    return gain * np.poly(zeros), np.poly(poles)


def _eq34_coeffs(params):
    g, z1, z2, p2, p3 = params
    d = mrci.decompose(*_cd(g, (z1, z2, -1.0), (1.0, p2, p3)), 2)
    (n1, d1), (n2, d2) = d.slow_tfs()
    nf, df = d.fast_tf()
    return np.array([n1[-1], n2[-1], d2[-1], nf[0], nf[1], df[-1]])


def test_eq34_reproduced_within_rounding_of_eq33():
    """Eq. (34) from eq. (33) with m = 2; tolerance = effect of eq. (33)'s printed rounding
    (half a unit in the 4th decimal of gain, zeros and poles, propagated linearly) plus
    half a unit of eq. (34)'s own last printed digit."""
    p0 = np.array([GAIN, ZEROS[0], ZEROS[1], POLES[1], POLES[2]])
    ours = _eq34_coeffs(p0)
    paper = np.array([0.04484, -1.6365, -0.7218, 1.0882, 1.84, -0.6137])
    half_ulp_paper = np.array([0.5e-5, 0.5e-4, 0.5e-4, 0.5e-4, 0.5e-2, 0.5e-4])
    sens = np.zeros_like(ours)
    for i in range(len(p0)):
        dp = np.zeros_like(p0)
        dp[i] = 1e-7
        sens += np.abs((_eq34_coeffs(p0 + dp) - _eq34_coeffs(p0 - dp)) / 2e-7) * 0.5e-4
    err = np.abs(ours - paper)
    assert np.all(err <= sens + half_ulp_paper), (ours, paper, sens)
    # and the slow denominators are z^2 - 1 and z^2 - 0.8496^2
    d = mrci.decompose(*_cd(), 2)
    assert [len(m.poles) for m in d.slow] == [1, 1] and len(d.fast) == 1
    np.testing.assert_allclose([m.poles[0] for m in d.slow], [1.0, 0.8496 ** 2], rtol=1e-12)


def test_computation_saving_eq20():
    d = mrci.decompose(*_cd(), 2)
    assert d.n_fast == 1
    assert d.cs == pytest.approx(1 / 3)          # the paper's CS = 33 %
    assert mrci.computation_saving(3, 2) == pytest.approx(2 / 5)


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_computation_saving_counts_the_updates_the_runtime_makes(m):
    """CS = the share of mode updates saved per fast period, counted on the runtime's phases:
    over m fast periods the fast dynamics update m times each, slow mode i once (at its
    phase). For m = 2 (two slow modes, one per phase) it is eq. (20)'s 33 %; for m = 1
    nothing is saved (it was 1/3 for every m: the number of slow modes stood for m)."""
    d = mrci.decompose(*_cd(), m)
    c = d.as_jax()
    slow_updates = sum(int(np.sum(np.asarray(c.mode_phase) == k % m)) for k in range(m))
    every = m * (d.n_fast + len(d.slow))
    assert d.cs == pytest.approx(1.0 - (m * d.n_fast + slow_updates) / every)
    assert (d.cs == 0.0) == (m == 1)
    if m == 2:
        assert d.cs == pytest.approx(1 / 3)


def _run(c, e):
    def step(s, ke):
        u, s = mrci.mrci_step(c, s, ke[0], ke[1])
        return s, u
    ks = jnp.arange(e.shape[0])
    return jax.jit(lambda e: jax.lax.scan(step, mrci.mrci_init(c, e.dtype), (ks, e))[1])(e)


@pytest.mark.parametrize("which", ["eq33", "complex"])
def test_m1_equals_undecomposed_controller(which):
    """With m = 1 the interlaced controller is C(z) itself (scipy.signal.dlsim reference)."""
    if which == "eq33":
        num, den = _cd()
    else:   # a controller with a complex pole pair and a real pole, strictly proper part + D
        num = np.poly([0.5, 0.2 + 0.3j, 0.2 - 0.3j]).real * 0.7
        den = np.poly([0.9, 0.6 + 0.5j, 0.6 - 0.5j]).real
    e = np.random.default_rng(0).normal(size=300)
    with jax.enable_x64(True):
        d = mrci.decompose(num, den, 1, slow_radius=0.75)
        c = d.as_jax(jnp.float64)
        u = np.asarray(_run(c, jnp.asarray(e)))
    _, ref = scipy.signal.dlsim((num, den, 1.0), e)
    np.testing.assert_allclose(u, ref[:, 0], rtol=0, atol=1e-9 * np.max(np.abs(ref)))


def test_slow_mode_matches_slow_rate_transfer_function():
    """With m = 2, slow mode i sees e at k = 2j + i - 1 and its output equals C^s_i(z^2)
    driven by that down-sampled error, held for two periods (eq. 19, Fig. 4)."""
    num, den = _cd()
    d = mrci.decompose(num, den, 2)
    e = np.random.default_rng(1).normal(size=200)
    with jax.enable_x64(True):
        c = d.as_jax(jnp.float64)
        u = np.asarray(_run(c, jnp.asarray(e)))
    # reference: each slow mode through scipy at period 2T on its phase, held; fast part at T
    total = np.zeros_like(e)
    for i, (n_i, d_i) in enumerate(d.slow_tfs()):
        ed = e[i::2]
        _, yi = scipy.signal.dlsim((n_i, d_i, 2.0), ed)
        held = np.zeros_like(e)
        for j, v in enumerate(yi[:, 0]):
            held[i + 2 * j: i + 2 * j + 2] = v
        total += held
    nf, df = d.fast_tf()
    _, yf = scipy.signal.dlsim((nf, df, 1.0), e)
    total += yf[:, 0]
    np.testing.assert_allclose(u, total, rtol=0, atol=1e-9 * np.max(np.abs(total)))


def test_repeated_pole_and_improper_rejected():
    with pytest.raises(ValueError, match="repeated pole"):
        mrci.decompose([1.0, 0.0], np.poly([0.9, 0.9]), 2)
    with pytest.raises(ValueError, match="proper"):
        mrci.decompose([1.0, 0.0, 0.0], [1.0, -0.5], 2)
    with pytest.raises(ValueError, match="m must be"):
        mrci.decompose([1.0], [1.0, -0.5], 0)


def test_step_takes_a_float64_error_under_x64():
    """A float32 design and state (as_jax(), mrci_init()) fed a float64 error under x64 made the
    state float64 and a scan over k failed with a carry type error. It computes in the state's
    dtype and gives the float32 run's actions."""
    c = mrci.decompose(*_cd(), 2).as_jax()
    e = np.random.default_rng(1).normal(size=12)

    def run(e):
        def step(s, ke):
            u, s = mrci.mrci_step(c, s, ke[0], ke[1])
            return s, u
        return jax.lax.scan(step, mrci.mrci_init(c), (jnp.arange(12), e))[1]

    ref = run(jnp.asarray(e, jnp.float32))
    with jax.enable_x64(True):
        u = run(jnp.asarray(e, jnp.float64))
    assert u.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(u), np.asarray(ref))
