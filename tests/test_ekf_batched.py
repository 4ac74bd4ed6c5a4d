"""Batch-last EKF kernels (``ekf_batched``) against the reference ``ekf`` functions.

The two implement the same algorithm with a different summation order, so in float64
they agree to a few ulps of float64 (TOL64); in float32 to a few hundred float32 ulps of
the covariance scale over 50 steps (TOL32). Gradients go through custom_vjp /
custom_vmap in the new functions and through plain autodiff in the old ones: both must
give the same numbers.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.estimators import ekf as old
from jaxnc.estimators import ekf_batched as new
from jaxnc.plants.mecanum import OUTPUT_DIM, PROCESS_NOISE_DIM, Mecanum, MecanumNoise

# experimental module, not on any closed loop's path: the whole file is slow (~70 s)
pytestmark = pytest.mark.slow

STEPS = 50
B = 16
TOL64 = 1e-12          # relative to the array's scale; summation-order rounding only
TOLGRAD = 1e-9        # gradients: rounding amplified through 50 steps of the adjoint
TOL32 = 2e-5           # ~ STEPS * 2 * 1.2e-7 relative growth, with margin for rank-one downdates


def _close(a, b, tol):
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(np.max(np.abs(b)), 1e-30)
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * scale)


def _belief(key, dtype):
    km, kp = jax.random.split(key)
    mean = jnp.array([0.15, -0.05, 0.1, 0.4, -0.3, 0.2], dtype) + 0.05 * jax.random.normal(km, (6,), dtype)
    Aj = 0.05 * jax.random.normal(kp, (6, 6), dtype)
    return old.Gaussian(mean, Aj @ Aj.T + 1e-3 * jnp.eye(6, dtype=dtype))


def _filter(mod, plant, steps=STEPS):
    """Per-seed filter over ``steps``: predict, then update on 70 % of the steps."""
    def run(key, Q, r, m0):
        ku, kv, kd = jax.random.split(key, 3)
        dtype = m0.dtype
        us = 4.0 + jax.random.normal(ku, (steps, 4), dtype)
        vs = 0.02 * jax.random.normal(kv, (steps, OUTPUT_DIM), dtype)
        keep = jax.random.uniform(kd, (steps,)) < 0.7
        b0 = old.Gaussian(m0, jnp.diag(jnp.array([1e-4, 1e-4, 1e-4, 4e-4, 4e-4, 1e-4], dtype)))

        def body(b, inp):
            u, v, k = inp
            b = mod.ekf_predict(plant.dynamics, b, u, Q, PROCESS_NOISE_DIM)
            z = plant.measure(b.mean, v) + 0.01
            c = mod.ekf_update_diag(plant.measure, b, z, r, OUTPUT_DIM)
            b = jax.tree.map(lambda x, y: jnp.where(k, y, x), b, c)
            return b, b
        return jax.lax.scan(body, b0, (us, vs, keep))[1]
    return run


def _cost(mod, plant):
    run = _filter(mod, plant)

    def cost(Q, m0, key, r):
        traj = run(key, Q, r, m0)
        return jnp.sum(traj.mean[:, 3:5] ** 2) + 1e3 * jnp.sum(jnp.trace(traj.cov, axis1=-2, axis2=-1))
    return cost


def test_single_seed_predict_and_update_match_reference_float64():
    with jax.enable_x64(True):
        plant, noise = Mecanum(), MecanumNoise()
        b = _belief(jax.random.key(0), jnp.float64)
        u = jnp.array([3.0, 4.5, 5.0, 2.0])
        Q = noise.Q().astype(jnp.float64)
        r = (noise.measurement_std() ** 2).astype(jnp.float64)
        z = plant.measure(b.mean, jnp.zeros(9)) + 0.03

        pa = jax.jit(lambda b: new.ekf_predict(plant.dynamics, b, u, Q, 7))(b)
        pb = jax.jit(lambda b: old.ekf_predict(plant.dynamics, b, u, Q, 7))(b)
        assert pa.cov.dtype == jnp.float64
        _close(pa.mean, pb.mean, TOL64)
        _close(pa.cov, pb.cov, TOL64)
        ua = jax.jit(lambda b: new.ekf_update_diag(plant.measure, b, z, r, 9))(b)
        ub = jax.jit(lambda b: old.ekf_update_diag(plant.measure, b, z, r, 9))(b)
        _close(ua.mean, ub.mean, TOL64)
        _close(ua.cov, ub.cov, TOL64)
        # the update must actually change the belief (the test could fail)
        assert np.max(np.abs(np.asarray(ua.cov - b.cov))) > 1e-6


@pytest.mark.slow
def test_nested_vmap_matches_reference():
    """vmap over configurations (batched Q) of vmap over seeds: the rule runs per level."""
    plant, noise = Mecanum(), MecanumNoise()
    keys = jax.random.split(jax.random.key(4), 6).reshape(2, 3)
    beliefs = jax.vmap(jax.vmap(lambda k: _belief(k, jnp.float32)))(keys)
    Qs = noise.Q()[None] * jnp.array([1.0, 3.0])[:, None, None]
    r = noise.measurement_std() ** 2
    u = jnp.array([3.0, 4.5, 5.0, 2.0])

    def step(mod):
        def one(b, Q):
            b = mod.ekf_predict(plant.dynamics, b, u, Q, 7)
            return mod.ekf_update_diag(plant.measure, b, plant.measure(b.mean, jnp.zeros(9)) + 0.02, r, 9)
        return jax.jit(jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(0, 0)))
    a, b = step(new)(beliefs, Qs), step(old)(beliefs, Qs)
    assert a.cov.shape == (2, 3, 6, 6)
    _close(a.mean, b.mean, TOL32)
    _close(a.cov, b.cov, TOL32)


def test_vmapped_filter_matches_reference_float32_and_is_symmetric():
    plant, noise = Mecanum(), MecanumNoise()
    keys = jax.random.split(jax.random.key(1), B)
    m0 = jax.vmap(lambda k: _belief(k, jnp.float32).mean)(keys)
    # Q shared (unbatched), r per seed (batched): both kinds of operand
    Q = noise.Q()
    r = (noise.measurement_std() ** 2)[None, :] * jnp.linspace(0.5, 2.0, B)[:, None]
    steps = 20                     # compile time; the 50-step runs are in the gradient tests
    fa = jax.jit(jax.vmap(_filter(new, plant, steps), in_axes=(0, None, 0, 0)))
    fb = jax.jit(jax.vmap(_filter(old, plant, steps), in_axes=(0, None, 0, 0)))
    ta, tb = fa(keys, Q, r, m0), fb(keys, Q, r, m0)
    assert ta.cov.shape == (B, steps, 6, 6)
    _close(ta.mean, tb.mean, TOL32)
    _close(ta.cov, tb.cov, TOL32)
    # exactly symmetric covariances, positive definite
    np.testing.assert_array_equal(np.asarray(ta.cov), np.swapaxes(np.asarray(ta.cov), -1, -2))
    assert np.all(np.linalg.eigvalsh(np.asarray(ta.cov[:, -1], float)) > 0)


def _grad_inputs():
    """float64 inputs of the gradient tests (call inside ``jax.enable_x64``): the plant,
    four seed keys, their initial means, the process noise Q and the measurement variances."""
    plant, noise = Mecanum(), MecanumNoise()
    keys = jax.random.split(jax.random.key(2), 4)
    m0 = jax.vmap(lambda k: _belief(k, jnp.float64).mean)(keys)
    Q = noise.Q().astype(jnp.float64)
    r = (noise.measurement_std() ** 2).astype(jnp.float64)
    return plant, keys, m0, Q, r


def test_gradients_through_scan_under_vmap_match_reference_float64():
    """vmap(grad) per seed w.r.t. Q and the initial mean."""
    with jax.enable_x64(True):
        plant, keys, m0, Q, r = _grad_inputs()
        per_seed = {}
        for name, mod in (("new", new), ("old", old)):
            cost = _cost(mod, plant)
            g = jax.jit(jax.vmap(jax.grad(cost, argnums=(0, 1)), in_axes=(None, 0, 0, None)))(Q, m0, keys, r)
            per_seed[name] = g
        (gQa, gma), (gQb, gmb) = per_seed["new"], per_seed["old"]
        assert gQa.shape == (4, 7, 7) and gma.shape == (4, 6)
        assert np.max(np.abs(np.asarray(gQb))) > 0 and np.max(np.abs(np.asarray(gmb))) > 0
        _close(gQa, gQb, TOLGRAD)
        _close(gma, gmb, TOLGRAD)


@pytest.mark.slow
def test_gradient_of_monte_carlo_mean_matches_reference_float64():
    """grad(mean(vmap)): the cotangent of the shared Q is summed over seeds."""
    with jax.enable_x64(True):
        plant, keys, m0, Q, r = _grad_inputs()

        def mc(mod):
            cost = _cost(mod, plant)
            return lambda Q, m0: jnp.mean(jax.vmap(cost, in_axes=(None, 0, 0, None))(Q, m0, keys, r))
        va, ga = jax.jit(jax.value_and_grad(mc(new), argnums=(0, 1)))(Q, m0)
        vb, gb = jax.jit(jax.value_and_grad(mc(old), argnums=(0, 1)))(Q, m0)
        _close(va, vb, TOL64)
        _close(ga[0], gb[0], TOLGRAD)
        _close(ga[1], gb[1], TOLGRAD)


@pytest.mark.slow
def test_gradient_matches_central_finite_difference():
    """Independent of the reference implementation: d cost / d Q[0, 0] by central differences."""
    with jax.enable_x64(True):
        plant, noise = Mecanum(), MecanumNoise()
        key = jax.random.key(3)
        m0 = _belief(key, jnp.float64).mean
        Q = noise.Q().astype(jnp.float64)
        r = (noise.measurement_std() ** 2).astype(jnp.float64)
        cost = jax.jit(_cost(new, plant))
        g = jax.jit(jax.grad(_cost(new, plant)))(Q, m0, key, r)
        eps = 1e-6 * float(Q[0, 0])
        E = jnp.zeros_like(Q).at[0, 0].set(1.0)
        fd = (cost(Q + eps * E, m0, key, r) - cost(Q - eps * E, m0, key, r)) / (2 * eps)
        # central difference error O(eps^2 f''') plus rounding ~1e-16 |f| / eps
        assert float(g[0, 0]) == pytest.approx(float(fd), rel=1e-5)
