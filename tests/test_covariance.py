"""The EKF's covariance kernels (jaxnc.estimators.covariance) against numpy's matrix
formulas in float64: prediction A P A' + L Q L', and the sequential scalar update against
the batch Kalman update with R = diag(r), K = P H' (H P H' + R)^-1."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.estimators.covariance import predict_cov, update_diag
from jaxnc.estimators.sparsity import Pattern

N, M, B = 5, 4, 3
TOL = 1e-12            # float64, a few dozen operations: summation-order rounding only


def _problem(seed):
    rng = np.random.default_rng(seed)
    F = rng.normal(size=(N, N))
    P = F @ F.T + 0.1 * np.eye(N)
    P = 0.5 * (P + P.T)                # exactly symmetric, as a covariance the filter carries
    H = rng.normal(size=(M, N))
    H[1, [0, 3]] = 0.0                 # a sparse row
    H[2] = 0.0                         # an output that does not depend on the state
    e = rng.normal(size=M)
    r = rng.uniform(0.1, 1.0, size=M)
    return P, H, e, r


def _kalman(P, H, e, r):
    S = H @ P @ H.T + np.diag(r)
    K = P @ H.T @ np.linalg.inv(S)
    return K @ e, P - K @ S @ K.T


@pytest.mark.parametrize("unroll", [True, False])
@pytest.mark.parametrize("sparse", [False, True])
def test_update_diag_is_the_batch_kalman_update(unroll, sparse):
    with jax.enable_x64(True):
        P, H, e, r = _problem(0)
        ph = Pattern.of(H) if sparse else None
        f = jax.jit(lambda P, H, e, r: update_diag(P, H, e, r, ph, unroll=unroll))
        delta, Pp = f(jnp.asarray(P), jnp.asarray(H), jnp.asarray(e), jnp.asarray(r))
        want_delta, want_P = _kalman(P, H, e, r)
        np.testing.assert_allclose(np.asarray(delta), want_delta, rtol=0, atol=TOL * np.abs(want_delta).max())
        np.testing.assert_allclose(np.asarray(Pp), want_P, rtol=0, atol=TOL * np.abs(want_P).max())
        assert np.array_equal(np.asarray(Pp), np.asarray(Pp).T)          # exactly symmetric
        assert np.abs(want_P - P).max() > 1e-2                          # the update moved P


def test_update_diag_batch_last_is_per_seed_on_each_slice():
    """Trailing batch axes: each seed's slice is that seed's update (both ways of summing)."""
    with jax.enable_x64(True):
        probs = [_problem(s) for s in range(B)]
        P, H, e, r = (np.stack(a, axis=-1) for a in zip(*probs))
        for unroll in (True, False):
            delta, Pp = jax.jit(lambda *a: update_diag(*a, unroll=unroll))(P, H, e, r)
            assert delta.shape == (N, B) and Pp.shape == (N, N, B)
            for b, (P1, H1, e1, r1) in enumerate(probs):
                want_delta, want_P = _kalman(P1, H1, e1, r1)
                np.testing.assert_allclose(np.asarray(delta[:, b]), want_delta, rtol=0, atol=TOL * np.abs(want_delta).max())
                np.testing.assert_allclose(np.asarray(Pp[..., b]), want_P, rtol=0, atol=TOL * np.abs(want_P).max())


def test_update_diag_without_any_state_dependence_leaves_the_belief():
    P, H, e, r = _problem(1)
    delta, Pp = update_diag(jnp.asarray(P, jnp.float32), jnp.zeros((M, N), jnp.float32), jnp.asarray(e, jnp.float32),
                            jnp.asarray(r, jnp.float32), Pattern.of(np.zeros((M, N))))
    assert np.all(np.asarray(delta) == 0.0) and np.array_equal(np.asarray(Pp), np.asarray(P, np.float32))


@pytest.mark.parametrize("diag_q", [False, True])
def test_predict_cov_is_APA_plus_LQL(diag_q):
    with jax.enable_x64(True):
        rng = np.random.default_rng(2)
        P, _, _, _ = _problem(2)
        A, L = rng.normal(size=(N, N)), rng.normal(size=(N, 2))
        A[0, 1:] = 0.0
        L[3] = 0.0
        Q = rng.uniform(0.1, 1.0, size=2) if diag_q else np.array([[1.0, 0.3], [0.3, 0.5]])
        want = A @ P @ A.T + L @ (np.diag(Q) if diag_q else Q) @ L.T
        got = jax.jit(lambda *a: predict_cov(*a, Pattern.of(A), Pattern.of(L)))(P, A, L, Q)
        np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=TOL * np.abs(want).max())
        assert np.array_equal(np.asarray(got), np.asarray(got).T)


def _prediction_problem():
    rng = np.random.default_rng(3)
    P, _, _, _ = _problem(3)
    A, L = rng.normal(size=(N, N)), rng.normal(size=(N, 2))
    A[0, 1:] = 0.0
    L[3] = 0.0
    return P, A, L, rng.uniform(0.1, 1.0, size=2), rng.normal(size=(N, N))


def test_predict_cov_gradient_is_the_matrix_formulas():
    """Reverse mode through the entry-by-entry prediction equals that of A P A' + L Q L' in
    float64: for A and L on their patterns' entries (the others are structural zeros, never
    read: gradient 0), for Q, and for P along symmetric directions."""
    with jax.enable_x64(True):
        P, A, L, Q, C = _prediction_problem()
        pa, pl = Pattern.of(A), Pattern.of(L)
        sym = lambda S: 0.5 * (S + S.T)
        entries = lambda S, A, L, Q: jnp.sum(C * predict_cov(sym(S), A, L, Q, pa, pl))
        dense = lambda S, A, L, Q: jnp.sum(C * (A @ sym(S) @ A.T + (L * Q[None, :]) @ L.T))
        got = jax.grad(entries, argnums=(0, 1, 2, 3))(P, A, L, Q)
        want = jax.grad(dense, argnums=(0, 1, 2, 3))(P, A, L, Q)
        masks = (np.ones((N, N), bool), pa.array, pl.array, np.ones(2, bool))
        for name, g, w, m in zip("PALQ", got, want, masks):
            g, w = np.asarray(g), np.asarray(w)
            np.testing.assert_allclose(g[m], w[m], rtol=0, atol=TOL * np.abs(w).max(), err_msg=name)
            assert np.all(g[~m] == 0.0), name
        assert np.abs(np.asarray(got[1])).max() > 1e-3         # a gradient that could be wrong


def test_predict_cov_reverse_mode_pads_no_entry():
    """Reverse mode stacks the entries' cotangents back into the matrices (``lax.unstack``'s
    transpose): no entry's cotangent is padded to a whole matrix and summed, which under
    ``vmap`` made one loop fusion of every entry, quadratic in the entries, the largest
    single cost of DRHE's exact gradient (benchmarks/RESULTS.md, helper grad 2026-12-04)."""
    P, A, L, Q, C = (jnp.asarray(a, jnp.float32) for a in _prediction_problem())
    pa, pl = Pattern.of(np.asarray(A)), Pattern.of(np.asarray(L))
    f = lambda P, A, L, Q: jnp.sum(C * predict_cov(P, A, L, Q, pa, pl))
    jaxpr = jax.make_jaxpr(jax.vmap(jax.grad(f, argnums=(0, 1, 2, 3))))(*(jnp.stack([a, a]) for a in (P, A, L, Q)))
    prims = [e.primitive.name for e in jaxpr.jaxpr.eqns]
    assert "stack" in prims and prims.count("pad") == 0, sorted(set(prims))
