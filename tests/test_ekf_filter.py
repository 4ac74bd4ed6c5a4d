"""``ekf_batched.ekf_filter`` (whole filter, seed axis last) against vmap of the per-seed EKF.

The two run the same algorithm (predict, then sequential scalar corrections at the
prior mean, skipped where the measurement was dropped) with a different summation
order: in float64 they agree to rounding (TOL64), in float32 to a few hundred ulps of
the covariance scale over the run (TOL32, as in test_ekf_batched.py).

In float64 each implementation's filter outputs and gradient come from one compiled
program (:func:`_float64_run`: the gradient's forward pass is the filter), which the
filter and the gradient tests share (the suite's cost is its compilations).
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.estimators import ekf
from jaxnc.estimators.ekf_batched import ekf_filter
from jaxnc.estimators.sparsity import EKFStructure, Pattern
from jaxnc.plants.mecanum import OUTPUT_DIM, PROCESS_NOISE_DIM, Mecanum, MecanumNoise
from jaxnc.schemes.mecanum import ekf_structure

B, K = 5, 30
STRUCTURE = ekf_structure(Mecanum())
TOL64 = 1e-10
TOL32 = 2e-5


def _close(a, b, tol):
    a, b = np.asarray(a, float), np.asarray(b, float)
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * max(np.max(np.abs(b)), 1e-30))


def _data(dtype):
    """Per-seed inputs around the cruise speed, noisy measurements of a true run, 30 % drops."""
    return Mecanum(), *_arrays(dtype)


@functools.partial(jax.jit, static_argnums=0)
def _arrays(dtype):
    """:func:`_data`'s arrays (one compiled program per dtype)."""
    plant, noise = Mecanum(), MecanumNoise()
    ku, kw, kv, kd = jax.random.split(jax.random.key(3), 4)
    us = (4.0 + jax.random.normal(ku, (B, K, 4))).astype(dtype)
    ws = (noise.process_std()[None, None] * jax.random.normal(kw, (B, K, PROCESS_NOISE_DIM))).astype(dtype)
    vs = (noise.measurement_std()[None, None] * jax.random.normal(kv, (B, K, OUTPUT_DIM))).astype(dtype)

    def truth(u, w, v):
        def step(x, inp):
            x = plant.dynamics(x, *inp[:2])
            return x, plant.measure(x, inp[2])
        return jax.lax.scan(step, jnp.zeros(6, dtype), (u, w, v))[1]
    zs = jax.vmap(truth)(us, ws, vs)
    valid = jax.random.uniform(kd, (B, K)) >= 0.3
    mean0 = jnp.zeros((B, 6), dtype) + jnp.arange(B, dtype=dtype)[:, None] * 0.01
    cov0 = jnp.broadcast_to(jnp.eye(6, dtype=dtype) * 1e-3, (B, 6, 6))
    Q, r = noise.Q().astype(dtype), (noise.measurement_std() ** 2).astype(dtype)
    return ekf.Gaussian(mean0, cov0), us, zs, valid, Q, r


def _loss(run, args, s):
    """A Monte-Carlo estimation error (mean squared position estimate) of ``run``'s filter with
    the process noise scaled by ``s``; the filter's outputs as auxiliary data."""
    plant, b0, us, zs, valid, Q, r = args
    out = run(plant, b0, us, zs, valid, Q * s, r)
    return jnp.mean(jnp.sum(out[1][..., 3:5] ** 2, axis=-1)), out


@functools.cache
def _float64_run(run):
    """float64: ``run``'s (filter, means) at the data's Q and d loss / d s at s = 1, one program."""
    with jax.enable_x64(True):
        args = _data(jnp.float64)
        (_, out), g = jax.jit(jax.value_and_grad(functools.partial(_loss, run, args), has_aux=True))(1.0)
        return out, g


def _reference(plant, b0, us, zs, valid, Q, r):
    def one(b, u, z, ok):
        def step(b, inp):
            u, z, ok = inp
            b = ekf.ekf_predict(plant.dynamics, b, u, Q, PROCESS_NOISE_DIM)
            c = ekf.ekf_update_diag(plant.measure, b, z, r, OUTPUT_DIM)
            b = jax.tree.map(lambda p, q: jnp.where(ok, q, p), b, c)
            return b, b.mean
        return jax.lax.scan(step, b, (u, z, ok))
    return jax.vmap(one)(b0, us, zs, valid)


def _ours(plant, b0, us, zs, valid, Q, r):
    return ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid, Q, r,
                      noise_dim=PROCESS_NOISE_DIM, return_means=True)


def _ours_structured(plant, b0, us, zs, valid, Q, r):
    """With the Mecanum Jacobians' sparsity and the diagonal Q as a vector of variances."""
    return ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid, jnp.diag(Q), r,
                      noise_dim=PROCESS_NOISE_DIM, return_means=True, structure=STRUCTURE)


@pytest.mark.parametrize("ours", [_ours, _ours_structured])
@pytest.mark.parametrize("dtype, tol", [(jnp.float32, TOL32), (jnp.float64, TOL64)])
def test_filter_matches_vmapped_per_seed_ekf(dtype, tol, ours):
    with jax.enable_x64(dtype == jnp.float64):
        if dtype == jnp.float64:
            (fa, ma), (fb, mb) = _float64_run(ours)[0], _float64_run(_reference)[0]
        else:
            args = _data(dtype)
            (fa, ma), (fb, mb) = jax.jit(ours)(*args), jax.jit(_reference)(*args)
        assert fa.cov.dtype == dtype and ma.shape == (B, K, 6)
        _close(ma, mb, tol)
        _close(fa.mean, fb.mean, tol)
        _close(fa.cov, fb.cov, tol)
        # the filter did something: the covariance shrank from its initial 1e-3 in position
        assert np.all(np.asarray(fa.cov[:, 3, 3]) < 1e-3)
        np.testing.assert_array_equal(np.asarray(fa.cov), np.swapaxes(np.asarray(fa.cov), -1, -2))


@pytest.mark.parametrize("ours", [_ours, _ours_structured])
def test_gradient_matches_vmapped_per_seed_ekf_float64(ours):
    """Reverse mode through the batch-last scan: d/dQ-scale of a Monte-Carlo estimation error."""
    with jax.enable_x64(True):
        ga, gb = _float64_run(ours)[1], _float64_run(_reference)[1]
        assert ga.dtype == jnp.float64
        assert abs(float(gb)) > 1e-8
        np.testing.assert_allclose(float(ga), float(gb), rtol=1e-8)


def test_model_that_does_not_broadcast_over_a_trailing_batch_axis_is_refused():
    plant, b0, us, zs, valid, Q, r = _data(jnp.float32)
    M = jnp.eye(6)

    def per_seed_only(x, u, w):          # x @ M contracts the batch axis for x of shape (6, B)
        return x @ M
    with pytest.raises(ValueError, match="batch-last"):
        ekf_filter(per_seed_only, plant.measure, b0, us, zs, valid, Q, r, noise_dim=PROCESS_NOISE_DIM)


def test_inconsistent_shapes_are_refused_before_tracing():
    plant, b0, us, zs, valid, Q, r = _data(jnp.float32)
    with pytest.raises(ValueError, match="valid"):
        ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid[:, :-1], Q, r, noise_dim=PROCESS_NOISE_DIM)
    with pytest.raises(ValueError, match="Q must be"):
        ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid, Q[:6, :6], r, noise_dim=PROCESS_NOISE_DIM)
    with pytest.raises(ValueError, match="structure.H"):
        st = STRUCTURE
        ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid, Q, r, noise_dim=PROCESS_NOISE_DIM,
                   structure=EKFStructure(st.A, st.L, Pattern.dense(6, 6)))


def test_a_per_seed_model_is_refused_even_when_the_batch_equals_the_state_size():
    """A row-vector model ``x @ A.T`` (right for one seed) runs without a shape error on a batch of
    B = n seeds, mixing the seeds; the check's batch differs from every model size, so it is refused."""
    A = jnp.asarray([[1.0, 0.1], [0.0, 1.0]])
    f = lambda x, u, w: x @ A.T + w            # per seed only: for x (2, B) it contracts the batch axis
    h = lambda x, v: x[:1] + v
    b0 = ekf.Gaussian(jnp.zeros((2, 2)), jnp.broadcast_to(jnp.eye(2), (2, 2, 2)))
    us, zs, valid = jnp.zeros((2, 5, 1)), jnp.ones((2, 5, 1)), jnp.ones((2, 5), bool)
    with pytest.raises(ValueError, match="batch-last"):
        ekf_filter(f, h, b0, us, zs, valid, jnp.eye(2), jnp.ones(1), noise_dim=2)


def _pend_f(x, u, w):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (-jnp.sin(x[0]) + u[0]) + w[0]])


def _pend_h(x, v):
    return jnp.stack([jnp.sin(x[0])]) + v


def test_ekf_filter_called_eagerly_compiles_once_per_model_and_shapes():
    """Outside jit the filter's scan compiled again at every call (a new body each time, 0.2 s);
    now a call with other data of the same shapes compiles nothing, and gives the jitted
    filter's numbers bit for bit."""
    from jaxnc.cache import compile_clock
    b0 = ekf.Gaussian(jnp.zeros((8, 2)), jnp.tile(jnp.eye(2), (8, 1, 1)))

    def call(seed, fn=ekf_filter):
        rng = np.random.default_rng(seed)
        us, zs = (jnp.asarray(rng.normal(size=(8, 20, 1)), jnp.float32) for _ in range(2))
        return fn(_pend_f, _pend_h, b0, us, zs, jnp.asarray(rng.random((8, 20)) < 0.7), jnp.array([1e-3]),
                  jnp.array([1e-2]), noise_dim=1)

    call(0)
    before = compile_clock()
    eager = call(1)
    assert (compile_clock() - before).compilations == 0
    jitted = call(1, jax.jit(ekf_filter, static_argnums=(0, 1), static_argnames=("noise_dim",)))
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
