"""Structural sparsity of the EKF Jacobians: detection, and the structured EKF steps
against the dense ones (float64: the skipped terms are exact zeros, so the two agree to
rounding) and against the Mecanum Jacobians written out by hand from seed 000 eq. (1)-(2)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update_diag
from jaxnc.estimators.sparsity import EKFStructure, Pattern, detect_structure, embed, take
from jaxnc.plants.mecanum import INPUT_DIM, OUTPUT_DIM, PROCESS_NOISE_DIM, STATE_DIM, Mecanum, MecanumNoise
from jaxnc import montecarlo
from jaxnc.schemes import mecanum as mec

TOL64 = 1e-12


def test_mecanum_structure_is_the_one_of_eq_1_and_2():
    st = mec.ekf_structure(Mecanum())
    A = np.zeros((6, 6), bool)
    A[3, [3, 5]] = A[4, [4, 5]] = A[5, 5] = True        # X, Y, psi rows: x + T R(psi) v
    L = np.zeros((6, 7), bool)
    L[:, :4] = True                                      # wheel-speed noise enters everything
    L[3, 4] = L[4, 5] = L[5, 6] = True                   # pose slip
    H = np.zeros((9, 6), bool)
    H[:4, :3] = True                                     # encoders: eq. (9) of the velocities
    H[4, 5] = True                                       # yaw
    H[5:, 3:5] = True                                    # beacon distances, eq. (2)
    np.testing.assert_array_equal(st.A.array, A)
    np.testing.assert_array_equal(st.L.array, L)
    np.testing.assert_array_equal(st.H.array, H)
    assert st.A.rows == (3, 4, 5) and st.A.cols == (3, 4, 5) and st.H.row(4) == (5,)
    assert hash(st) == hash(mec.ekf_structure(Mecanum()))       # static: usable as a jit key


def test_detection_finds_a_random_linear_models_exact_pattern():
    rng = np.random.default_rng(0)
    n, nu, nw, m = 7, 2, 3, 5
    masks = [rng.random(s) < 0.4 for s in ((n, n), (n, nw), (m, n))]
    A, L, H = (jnp.asarray(rng.normal(size=k.shape) * k) for k in masks)
    B = jnp.asarray(rng.normal(size=(n, nu)))
    st = detect_structure(lambda x, u, w: A @ x + B @ u + L @ w, lambda x, v: H @ x + v, n, nu, nw, m)
    for pat, mask in zip(st, masks):
        np.testing.assert_array_equal(pat.array, mask)


def test_bad_dimensions_are_named():
    f, h = Mecanum().dynamics, Mecanum().measure
    with pytest.raises(ValueError, match="meas_dim"):
        detect_structure(f, h, STATE_DIM, INPUT_DIM, PROCESS_NOISE_DIM, 0)
    with pytest.raises(ValueError, match="state_dim=5"):
        detect_structure(f, h, STATE_DIM - 1, INPUT_DIM, PROCESS_NOISE_DIM, OUTPUT_DIM)


def test_a_traced_plant_is_refused():
    def build(R):
        return mec.ekf_structure(Mecanum(R=R))
    with pytest.raises(ValueError, match="traced"):
        jax.jit(build)(0.05)


def test_take_and_embed_are_inverse_on_non_contiguous_indices():
    x = jnp.arange(24.0).reshape(4, 6)
    idx = (0, 2, 3, 5)
    t = take(x, idx, axis=1)
    np.testing.assert_array_equal(t, np.asarray(x)[:, list(idx)])
    e = embed(t, idx, 6, axis=1)
    want = np.asarray(x).copy()
    want[:, [1, 4]] = 0
    np.testing.assert_array_equal(e, want)
    assert take(x, range(6), axis=1) is x


def _beliefs(key, n, k=4):
    kx, kp = jax.random.split(key)
    X = jax.random.normal(kp, (k, n, n))
    return Gaussian(jax.random.normal(kx, (k, n)), jnp.einsum("bij,bkj->bik", X, X) + jnp.eye(n)[None])


@pytest.mark.parametrize("diag_q", [True, False])
def test_structured_prediction_equals_dense_float64(diag_q):
    with jax.enable_x64(True):
        plant, st = Mecanum(), mec.ekf_structure(Mecanum())
        b = _beliefs(jax.random.key(1), STATE_DIM)
        u = 4.0 + jax.random.normal(jax.random.key(2), (4, INPUT_DIM))
        q = MecanumNoise().process_std().astype(jnp.float64) ** 2
        Q = q if diag_q else jnp.diag(q)

        def run(structure, b, u):
            return ekf_predict(plant.dynamics, b, u, Q, PROCESS_NOISE_DIM, structure=structure)
        sparse = jax.jit(jax.vmap(lambda b, u: run(st, b, u)))(b, u)
        dense = jax.jit(jax.vmap(lambda b, u: run(None, b, u)))(b, u)
        np.testing.assert_allclose(sparse.cov, dense.cov, rtol=TOL64, atol=TOL64)
        np.testing.assert_array_equal(sparse.mean, dense.mean)
        # ... and their gradients (through the Jacobians too) with respect to the belief and input
        # ... and their gradients (through the Jacobians too) with respect to the belief and
        # input. The structured kernel reads a symmetric P's upper triangle only, so its
        # gradient with respect to P sits there (entry (i, j) carries both (i, j) and (j, i));
        # along every symmetric direction, the only ones a covariance moves in, the two agree.
        loss = lambda structure: lambda b, u: jnp.sum(jnp.sin(run(structure, b, u).cov))
        sym = lambda g: g + g.T - np.diag(np.diag(g))          # (i, j) and (j, i) summed, upper
        b0 = jax.tree.map(lambda a: a[0], b)
        (gbs, gus), (gbd, gud) = (jax.jit(jax.grad(loss(s), argnums=(0, 1)))(b0, u[0]) for s in (st, None))
        for a, c in ((gbs.mean, gbd.mean), (gus, gud), (np.triu(sym(np.asarray(gbs.cov))), np.triu(sym(np.asarray(gbd.cov))))):
            assert np.max(np.abs(c)) > 0
            np.testing.assert_allclose(a, c, rtol=1e-10, atol=1e-12)


def test_structured_update_equals_dense_float64_with_a_state_free_output():
    """An output that does not depend on the state (its H row is zero) is skipped: it
    cannot correct anything."""
    with jax.enable_x64(True):
        plant = Mecanum()

        def h(x, v):
            return jnp.concatenate([plant.measure(x, v[:OUTPUT_DIM]), v[OUTPUT_DIM:] + 1.0])
        st = mec.ekf_structure(plant)
        st = EKFStructure(st.A, st.L, detect_structure(plant.dynamics, h, 6, 4, 7, OUTPUT_DIM + 1).H)
        assert st.H.row(OUTPUT_DIM) == ()
        b = _beliefs(jax.random.key(3), STATE_DIM)
        z = jax.random.normal(jax.random.key(4), (4, OUTPUT_DIM + 1))
        r = jnp.full((OUTPUT_DIM + 1,), 0.01)
        run = lambda s: jax.jit(jax.vmap(lambda b, z: ekf_update_diag(h, b, z, r, OUTPUT_DIM + 1, structure=s)))
        sparse, dense = run(st)(b, z), run(None)(b, z)
        np.testing.assert_allclose(sparse.mean, dense.mean, rtol=TOL64, atol=TOL64)
        np.testing.assert_allclose(sparse.cov, dense.cov, rtol=TOL64, atol=TOL64)
        assert np.max(np.abs(np.asarray(sparse.mean - b.mean))) > 1e-3      # it did correct


def test_sparse_and_dense_closed_loops_agree():
    """The DRHE loop with and without the structure: the same packets are sent and the
    trajectories agree to float32 rounding (the loop is float32). The sparse loop's program
    is tests/test_mecanum_loop.py's short-run program (the persistent cache shares it)."""
    from tests.test_mecanum_loop import short_runs
    keys = montecarlo.seed_keys(5, 8)
    loop = mec.mecanum_loop("DRHE", 4, 0.3, horizon_s=8.0, full=True)
    assert loop.estimator.structure is not None
    a = short_runs("DRHE", keys, dp=0.3)
    b = short_runs("DRHE", keys, dp=0.3, sparse=False)
    np.testing.assert_array_equal(a.sent_sc, b.sent_sc)
    assert np.max(np.abs(np.asarray(a.x - b.x))) < 1e-4
    assert np.max(np.abs(np.asarray(a.parts["estimator"] - b.parts["estimator"]))) < 1e-4
    assert mec.mecanum_loop("DRHE", 5, 0.3, sparse=False).estimator.structure is None


def test_batch_last_and_reduction_corrections_close_the_same_loop():
    """DRHE's EKF correcting with the seed axis last (the builder's default) and with the
    reductions (``batch_last=False``, the numbers stored before): the same packets are sent
    and the trajectories and estimates agree to float32 rounding."""
    from tests.test_mecanum_loop import short_runs
    keys = montecarlo.seed_keys(6, 8)
    assert mec.mecanum_loop("DRHE", 4, 0.3).estimator.batch_last
    a = short_runs("DRHE", keys, dp=0.3)
    b = short_runs("DRHE", keys, dp=0.3, batch_last=False)
    np.testing.assert_array_equal(a.sent_sc, b.sent_sc)
    assert np.max(np.abs(np.asarray(a.x - b.x))) < 1e-4
    assert np.max(np.abs(np.asarray(a.parts["estimator"] - b.parts["estimator"]))) < 1e-4


def test_saved_configuration_shows_the_structure():
    import json

    from jaxnc.experiments.mecanum import loop_config
    cfg = json.loads(json.dumps(loop_config(mec.mecanum_loop("DRHE", 5, 0.3))))
    assert cfg["estimator"]["structure"]["A"] == "....../....../....../...x.x/....xx/.....x"
    assert loop_config(mec.mecanum_loop("DRHE", 5, 0.3, sparse=False))["estimator"]["structure"] is None


def test_pattern_from_lists_is_hashable_and_checked():
    p = Pattern([[1, 0], [0, 1]])
    assert p == Pattern(((True, False), (False, True))) and hash(p) == hash(Pattern.of(np.eye(2)))
    assert p.rows == (0, 1) and p.row(1) == (1,) and p.nnz == 2
    with pytest.raises(ValueError, match="same length"):
        Pattern([[1, 0], [1]])


def test_a_structure_of_the_wrong_shape_is_refused():
    st = mec.ekf_structure(Mecanum())
    b = Gaussian(jnp.zeros(6), jnp.eye(6))
    bad = EKFStructure(Pattern.dense(5, 5), st.L, st.H)
    with pytest.raises(ValueError, match="structure.A"):
        ekf_predict(Mecanum().dynamics, b, jnp.zeros(4), jnp.ones(7), 7, structure=bad)
    with pytest.raises(ValueError, match="structure.H"):
        ekf_update_diag(Mecanum().measure, b, jnp.zeros(9), jnp.ones(9), 9,
                        structure=EKFStructure(st.A, st.L, Pattern.dense(8, 6)))



@pytest.mark.parametrize("sparse", [True, False])
def test_batch_last_drop_ins_equal_the_per_seed_steps_float64(sparse):
    """ekf_batched's ekf_predict / ekf_update_diag with and without the Mecanum structure
    (with it, what ``EKF(batch_last=True)`` runs in DRHE's loop), vmapped over seeds with a
    diagonal Q (a vector of variances, which the batch-last kernel once read as a matrix once
    the seed axis was appended), against ekf's: values and gradients (through the kernels'
    custom_vjp) to float64 rounding."""
    from jaxnc.estimators import ekf_batched as batched
    with jax.enable_x64(True):
        plant, st = Mecanum(), (mec.ekf_structure(Mecanum()) if sparse else None)
        b = _beliefs(jax.random.key(5), STATE_DIM)
        u = 4.0 + jax.random.normal(jax.random.key(6), (4, INPUT_DIM))
        z = jax.random.normal(jax.random.key(7), (4, OUTPUT_DIM))
        q = MecanumNoise().process_std().astype(jnp.float64) ** 2
        r = MecanumNoise().measurement_std().astype(jnp.float64) ** 2

        def step(predict, update):
            def one(b, u, z, q):
                b = predict(plant.dynamics, b, u, q, PROCESS_NOISE_DIM, structure=st)
                return update(plant.measure, b, z, r, OUTPUT_DIM, structure=st)
            return one

        def loss(fns):
            return lambda b, q: jnp.sum(jnp.sin(jax.vmap(step(*fns), in_axes=(0, 0, 0, None))(b, u, z, q).cov))
        fns = {"last": (batched.ekf_predict, batched.ekf_update_diag), "ref": (ekf_predict, ekf_update_diag)}
        out = {k: jax.jit(jax.vmap(step(*f), in_axes=(0, 0, 0, None)))(b, u, z, q) for k, f in fns.items()}
        # summation order only (the update's sums unrolled): float64 rounding, amplified by the
        # correction of these wide random beliefs to ~1e-11 relative
        np.testing.assert_allclose(out["last"].mean, out["ref"].mean, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out["last"].cov, out["ref"].cov, rtol=1e-9, atol=1e-11)
        assert np.max(np.abs(np.asarray(out["ref"].mean - b.mean))) > 1e-3
        (gb, gq), (gb_ref, gq_ref) = (jax.jit(jax.grad(loss(f), argnums=(0, 1)))(b, q) for f in fns.values())
        for a, c in ((gb.mean, gb_ref.mean), (gb.cov, gb_ref.cov), (gq, gq_ref)):
            assert np.max(np.abs(np.asarray(c))) > 0
            np.testing.assert_allclose(a, c, rtol=1e-9, atol=1e-11)
        # forward mode (a custom_jvp: jax.jvp works, where the former custom_vjp refused it)
        tb = jax.tree.map(lambda a: jnp.cos(jnp.arange(a.size, dtype=a.dtype)).reshape(a.shape), b)
        jv = {k: jax.jit(lambda b, t, f=f: jax.jvp(lambda b: loss(f)(b, q), (b,), (t,)))(b, tb) for k, f in fns.items()}
        assert abs(float(jv["ref"][1])) > 0
        np.testing.assert_allclose(jv["last"][1], jv["ref"][1], rtol=1e-9, atol=1e-11)
