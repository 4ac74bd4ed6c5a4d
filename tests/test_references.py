"""jaxnc.references against numpy closed forms."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import references as rf

T = 0.05
K = 200
TIMES = T * np.arange(K)


def _run(ref, steps=K):
    return np.asarray(jax.jit(rf.evaluate, static_argnums=1)(ref, steps, T))


def test_step():
    ref = rf.Step(amplitude=[2.0, -1.0], time=0.5, initial=[0.0, 3.0])
    r = _run(ref)
    assert r.shape == (K, 2) and ref.dim == 2
    want = np.where(TIMES[:, None] >= 0.5 - 1e-9, [2.0, 2.0], [0.0, 3.0])
    np.testing.assert_allclose(r, want, rtol=1e-6)
    assert r[10, 0] == 2.0 and r[9, 0] == 0.0          # t T = 0.5 exactly on instant 10
    # a step time per channel
    r = _run(rf.Step(amplitude=1.0, time=[0.2, 1.0]))
    np.testing.assert_allclose(r, np.stack([TIMES >= 0.2 - 1e-9, TIMES >= 1.0 - 1e-9], axis=1).astype(float))
    # gradient of a ramp with respect to its start: -slope once started
    g = jax.jit(jax.grad(lambda t0: rf.Ramp(jnp.array([2.0]), t0).at(40, T)[0]))(jnp.array([0.5]))
    np.testing.assert_allclose(np.asarray(g), [-2.0])
    # scalar: one channel
    assert _run(rf.Step(1.0)).shape == (K, 1)


def test_step_onset_is_where_at_switches():
    """Step.onset: the first instant at which ``at`` gives the stepped value (a time on a
    sample instant included), per channel; ``steps`` when the step comes after the run."""
    ref = rf.Step(amplitude=1.0, time=[0.0, 0.5, 0.52, 3.0, 20.0])
    onset = np.asarray(jax.jit(ref.onset, static_argnums=0)(K, T))
    r = _run(ref)
    want = [int(np.argmax(r[:, j] > 0)) if np.any(r[:, j] > 0) else K for j in range(5)]
    assert onset.tolist() == want == [0, 10, 11, 60, K]
    # a traced step time
    times = jnp.asarray([[0.5], [1.0]])
    got = jax.jit(jax.vmap(lambda t: rf.Step(jnp.ones(1), t).onset(K, T)))(times)
    assert np.asarray(got).tolist() == [[10], [20]]


def test_ramp_and_sine():
    r = _run(rf.Ramp(slope=[1.0, -0.5], time=1.0, initial=2.0))
    want = 2.0 + np.array([1.0, -0.5]) * np.maximum(TIMES - 1.0, 0.0)[:, None]
    np.testing.assert_allclose(r, want, rtol=1e-6, atol=1e-6)
    r = _run(rf.Sine(amplitude=[1.0, 2.0], frequency=[0.5, 2.0], phase=[0.0, 0.3], offset=1.0))
    want = 1.0 + np.array([1.0, 2.0]) * np.sin(2 * np.pi * np.array([0.5, 2.0]) * TIMES[:, None] + [0.0, 0.3])
    np.testing.assert_allclose(r, want, rtol=1e-5, atol=2e-5)


def test_piecewise_linear_matches_numpy_interp():
    times = [0.0, 1.0, 2.5, 4.0]
    values = [[0.0, 1.0], [1.0, 1.0], [1.0, -2.0], [3.0, 0.0]]
    r = _run(rf.PiecewiseLinear(times, values), 120)     # runs to 5.95 s: held after 4 s
    want = np.stack([np.interp(TIMES[:120], times, np.asarray(values)[:, j]) for j in range(2)], axis=1)
    np.testing.assert_allclose(r, want, rtol=1e-5, atol=1e-6)
    # gradient with respect to the values: the interpolation weights
    ref = rf.PiecewiseLinear(jnp.asarray(times), jnp.asarray(values))
    g = jax.jit(jax.grad(lambda v: rf.PiecewiseLinear(ref.times, v).at(30, T)[0]))(ref.values)  # 1.5 s
    want = np.zeros((4, 2))
    want[1, 0], want[2, 0] = 2.0 / 3.0, 1.0 / 3.0
    np.testing.assert_allclose(np.asarray(g), want, rtol=1e-5)


def test_recorded_holds_last():
    values = np.random.default_rng(0).normal(size=(30, 3)).astype(np.float32)
    r = _run(rf.Recorded(values), 50)
    np.testing.assert_array_equal(r[:30], values)
    np.testing.assert_array_equal(r[30:], np.broadcast_to(values[-1], (20, 3)))
    np.testing.assert_array_equal(_run(rf.Recorded(values[:, 0]), 5), values[:5, :1])
    np.testing.assert_array_equal(_run(rf.Recorded(jnp.asarray(values[:, 0])), 5), values[:5, :1])
    pl = rf.PiecewiseLinear(jnp.array([0.0, 1.0]), jnp.array([0.0, 2.0]))   # one channel, JAX arrays
    assert pl.dim == 1
    np.testing.assert_allclose(_run(pl, 30)[:, 0], np.minimum(2.0 * TIMES[:30], 2.0), rtol=1e-6)


def test_numpy_float64_numbers_give_a_float64_reference_under_x64():
    """Numpy float64 scalars (e.g. a setpoint computed with numpy) keep float64, as float64 arrays
    do: under jax_enable_x64 r is float64 and equals the float64 closed form to 1e-15. They used to
    become float32 (r = 0.1 + 1/3 rounded by 1e-8, and a float32 reference under x64)."""
    a, r0, f = np.float64(1.0 / 3.0), np.float64(0.1), np.float64(0.7)
    with jax.enable_x64(True):
        refs = {"Step": (rf.Step(a, time=np.float64(0.5), initial=r0), r0 + a),
                "Ramp": (rf.Ramp(a, time=np.float64(0.5), initial=r0), r0 + a * (0.75 - 0.5)),
                "Sine": (rf.Sine(a, f, phase=r0, offset=r0), r0 + a * np.sin(2 * np.pi * f * 0.75 + r0))}
        for name, (ref, want) in refs.items():
            r = jax.jit(ref.at)(15, T)                                      # t T = 0.75 s
            assert r.dtype == jnp.float64, name
            np.testing.assert_allclose(np.asarray(r), [want], rtol=1e-15, atol=0, err_msg=name)
        assert rf.Step(1.0).at(0, T).dtype == jnp.float32                    # Python numbers: float32


def test_leaves_are_differentiable_and_vmappable():
    """d r / d amplitude of a sine is sin(.); vmap over a batch of steps' amplitudes."""
    ref = rf.Sine(amplitude=jnp.ones(1), frequency=jnp.full(1, 0.5))
    g = jax.jit(jax.grad(lambda a: jnp.sum(rf.evaluate(rf.Sine(a, ref.frequency), K, T))))(ref.amplitude)
    np.testing.assert_allclose(float(g[0]), np.sum(np.sin(np.pi * TIMES)), rtol=1e-4, atol=1e-4)
    amplitudes = jnp.arange(1.0, 4.0)[:, None]                           # a batch of 3 one-channel steps
    out = jax.jit(jax.vmap(lambda a: rf.evaluate(rf.Step(a, 0.1), 10, T)))(amplitudes)
    np.testing.assert_allclose(np.asarray(out[:, -1, 0]), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.asarray(out[:, 0, 0]), [0.0, 0.0, 0.0])


@pytest.mark.parametrize("build, match", [
    (lambda: rf.Step([1.0, 2.0], initial=[0.0, 1.0, 2.0]), "same number of channels"),
    (lambda: rf.Step(1.0, time=-1.0), "Step.time"),
    (lambda: rf.Step(float("nan")), "Step.amplitude"),
    (lambda: rf.Sine(1.0, frequency=-2.0), "Sine.frequency"),
    (lambda: rf.PiecewiseLinear([0.0, 2.0, 1.0], [0.0, 1.0, 2.0]), "strictly increasing"),
    (lambda: rf.PiecewiseLinear([0.0, 1.0], [0.0, 1.0, 2.0]), "one row per time"),
    (lambda: rf.Recorded(np.zeros((0, 2))), "at least one row"),
    (lambda: rf.Ramp("fast"), "Ramp.slope"),
    (lambda: rf.evaluate(rf.Step(1.0), 0, T), "steps"),
    (lambda: rf.Step(1.0).onset(0, T), "Step.onset: steps"),
])
def test_bad_inputs(build, match):
    with pytest.raises(ValueError, match=match):
        build()
