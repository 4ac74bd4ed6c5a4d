"""EKF against an independent float64 NumPy reference, and KF identities."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update, ekf_update_diag
from jaxnc.plants.mecanum import Mecanum, MecanumNoise

TOL = 1e-6


def np_measure_jac(x, R, L, beacons, dz):
    """Analytic H = dh/dxi of the Mecanum output (eq. 2, 9), written independently."""
    H = np.zeros((9, 6))
    H[0, :3] = [1, -1, -L]
    H[1, :3] = [1, 1, L]
    H[2, :3] = [1, 1, -L]
    H[3, :3] = [1, -1, L]
    H[:4] /= R
    H[4, 5] = 1
    for i, (bx, by) in enumerate(beacons):
        d = np.sqrt((bx - x[3]) ** 2 + (by - x[4]) ** 2 + dz ** 2)
        H[5 + i, 3] = (x[3] - bx) / d
        H[5 + i, 4] = (x[4] - by) / d
    return H


def np_measure(x, R, L, beacons, dz):
    vx, vy, w = x[:3]
    om = np.array([vx - vy - L * w, vx + vy + L * w, vx + vy - L * w, vx - vy + L * w]) / R
    d = [np.sqrt((bx - x[3]) ** 2 + (by - x[4]) ** 2 + dz ** 2) for bx, by in beacons]
    return np.concatenate([om, [x[5]], d])


def np_update(x, P, z, Rn, plant):
    L = plant.Lx + plant.Ly
    dz = plant.z_fb - plant.z_mb
    b = np.asarray(plant.beacons, float)
    H = np_measure_jac(x, plant.R, L, b, dz)
    S = H @ P @ H.T + Rn
    K = P @ H.T @ np.linalg.inv(S)
    xn = x + K @ (z - np_measure(x, plant.R, L, b, dz))
    IKH = np.eye(6) - K @ H
    return xn, IKH @ P @ IKH.T + K @ Rn @ K.T


def np_predict(x, P, u, Qn, plant):
    """Eq. (1) and its analytic Jacobians, float64."""
    R, T, L = plant.R, plant.T, plant.Lx + plant.Ly
    G = np.array([[1, 1, 1, 1], [-1, 1, 1, -1], [-1 / L, 1 / L, -1 / L, 1 / L]]) * R / 4
    v = G @ u
    a = x[5] + v[2] * T
    c, s = np.cos(a), np.sin(a)
    xn = np.concatenate([v, [x[3] + T * (v[0] * c - v[1] * s), x[4] + T * (v[0] * s + v[1] * c), x[5] + v[2] * T]])
    A = np.zeros((6, 6))
    A[3, 3] = A[4, 4] = A[5, 5] = 1
    A[3, 5] = T * (-v[0] * s - v[1] * c)
    A[4, 5] = T * (v[0] * c - v[1] * s)
    # d/dw: wheel noise enters like u, pose slip additively
    dv = G
    da = dv[2] * T
    Lw = np.zeros((6, 7))
    Lw[:3, :4] = dv
    Lw[3, :4] = T * (dv[0] * c - dv[1] * s) + T * (-v[0] * s - v[1] * c) * da
    Lw[4, :4] = T * (dv[0] * s + dv[1] * c) + T * (v[0] * c - v[1] * s) * da
    Lw[5, :4] = da
    Lw[3, 4] = Lw[4, 5] = Lw[5, 6] = 1
    Lw *= min(1.0, np.mean(np.abs(u)) / 4.0)   # noise scales with the commanded wheel speed
    return xn, A @ P @ A.T + Lw @ Qn @ Lw.T


def _data(seed=0):
    rng = np.random.default_rng(seed)
    x = np.array([0.15, -0.05, 0.1, 0.4, -0.3, 0.2])
    A = rng.normal(size=(6, 6)) * 0.05
    P = A @ A.T + 1e-3 * np.eye(6)
    u = rng.normal(size=4) * 2
    return x, P, u, rng


def test_ekf_update_matches_float64_reference():
    with jax.enable_x64(True):
        plant = Mecanum()
        noise = MecanumNoise()
        x, P, _, rng = _data()
        Rn = np.asarray(noise.R(), float)
        z = np_measure(x, plant.R, plant.Lx + plant.Ly, np.asarray(plant.beacons, float), plant.z_fb - plant.z_mb)
        z = z + rng.normal(size=9) * 0.05
        ref_x, ref_P = np_update(x, P, z, Rn, plant)
        f = jax.jit(lambda b, z, R: ekf_update(plant.measure, b, z, R, 9))
        out = f(Gaussian(jnp.asarray(x), jnp.asarray(P)), jnp.asarray(z), jnp.asarray(Rn))
        assert out.mean.dtype == jnp.float64
        np.testing.assert_allclose(out.mean, ref_x, atol=TOL, rtol=0)
        np.testing.assert_allclose(out.cov, ref_P, atol=TOL, rtol=0)


def test_ekf_predict_matches_float64_reference():
    with jax.enable_x64(True):
        plant = Mecanum()
        noise = MecanumNoise()
        x, P, u, _ = _data(1)
        Qn = np.asarray(noise.Q(), float)
        ref_x, ref_P = np_predict(x, P, u, Qn, plant)
        f = jax.jit(lambda b, u, Q: ekf_predict(plant.dynamics, b, u, Q, 7))
        out = f(Gaussian(jnp.asarray(x), jnp.asarray(P)), jnp.asarray(u), jnp.asarray(Qn))
        np.testing.assert_allclose(out.mean, ref_x, atol=TOL, rtol=0)
        np.testing.assert_allclose(out.cov, ref_P, atol=TOL, rtol=0)


class Linear:
    """x' = A x + B u + w, z = C x + v: the EKF must be exactly the Kalman filter."""

    def __init__(self, A, B, C):
        self.A, self.B, self.C = A, B, C

    def dynamics(self, x, u, w):
        return self.A @ x + self.B @ u + w

    def measure(self, x, v):
        return self.C @ x + v


def test_ekf_on_linear_model_is_steady_state_kalman_filter():
    """Iterating predict/update converges to the DARE solution (scipy, independent)."""
    scipy_linalg = pytest.importorskip("scipy.linalg")
    with jax.enable_x64(True):
        A = np.array([[1.0, 0.1], [0.0, 1.0]])
        B = np.array([[0.0], [0.1]])
        C = np.array([[1.0, 0.0]])
        Q = np.diag([1e-3, 1e-2])
        R = np.array([[0.05]])
        m = Linear(jnp.asarray(A), jnp.asarray(B), jnp.asarray(C))

        def step(b, _):
            b = ekf_update(m.measure, b, jnp.zeros(1), jnp.asarray(R), 1)
            b = ekf_predict(m.dynamics, b, jnp.zeros(1), jnp.asarray(Q), 2)
            return b, None

        b, _ = jax.jit(lambda b: jax.lax.scan(step, b, None, length=500))(Gaussian(jnp.zeros(2), jnp.eye(2)))
        P_dare = scipy_linalg.solve_discrete_are(A.T, C.T, Q, R)   # prior covariance
        np.testing.assert_allclose(b.cov, P_dare, rtol=1e-8, atol=1e-10)


def test_joseph_update_keeps_covariance_spd_in_float32():
    plant = Mecanum()
    noise = MecanumNoise()
    P = jnp.diag(jnp.array([1e-4, 1e-4, 1e-4, 4e-4, 4e-4, 1e-4]))
    b = Gaussian(jnp.array([0.2, 0.0, 0.0, 0.1, 0.1, 0.0]), P)
    f = jax.jit(lambda b: ekf_update(plant.measure, b, plant.measure(b.mean, jnp.zeros(9)), noise.R(), 9))
    for _ in range(20):
        b = f(b)
    np.testing.assert_array_equal(b.cov, b.cov.T)
    assert np.all(np.linalg.eigvalsh(np.asarray(b.cov, float)) > 0)


def test_sequential_diagonal_update_matches_float64_reference():
    """Processing independent measurements one scalar at a time gives the batch update."""
    with jax.enable_x64(True):
        plant = Mecanum()
        noise = MecanumNoise()
        x, P, _, rng = _data(3)
        Rn = np.asarray(noise.R(), float)
        z = np_measure(x, plant.R, plant.Lx + plant.Ly, np.asarray(plant.beacons, float), plant.z_fb - plant.z_mb)
        z = z + rng.normal(size=9) * 0.05
        ref_x, ref_P = np_update(x, P, z, Rn, plant)
        f = jax.jit(lambda b, z, r: ekf_update_diag(plant.measure, b, z, r, 9))
        out = f(Gaussian(jnp.asarray(x), jnp.asarray(P)), jnp.asarray(z), jnp.asarray(np.diag(Rn)))
        assert out.mean.dtype == jnp.float64
        np.testing.assert_allclose(out.mean, ref_x, atol=TOL, rtol=0)
        np.testing.assert_allclose(out.cov, ref_P, atol=TOL, rtol=0)


def test_sequential_update_keeps_covariance_spd_in_float32():
    plant = Mecanum()
    noise = MecanumNoise()
    b = Gaussian(jnp.array([0.2, 0.0, 0.0, 0.1, 0.1, 0.0]), jnp.diag(jnp.array([1e-4, 1e-4, 1e-4, 4e-4, 4e-4, 1e-4])))
    r = noise.measurement_std() ** 2
    f = jax.jit(lambda b: ekf_update_diag(plant.measure, b, plant.measure(b.mean, jnp.zeros(9)), r, 9))
    for _ in range(20):
        b = f(b)
    np.testing.assert_array_equal(b.cov, b.cov.T)
    assert np.all(np.linalg.eigvalsh(np.asarray(b.cov, float)) > 0)


def test_jacobian_grad_false_holds_the_jacobians_constant():
    """Same values; the gradient of the predicted covariance w.r.t. the mean vanishes (A, L
    held constant: P' = A P A' + L Q L' does not depend on it), and w.r.t. the prior
    covariance it is the exact A' G A either way. The update's H likewise (float64)."""
    with jax.enable_x64(True):
        plant = Mecanum()
        x, P, u, _ = _data(3)
        Q = jnp.asarray(MecanumNoise().Q(), jnp.float64)
        b = Gaussian(jnp.asarray(x), jnp.asarray(P))
        z = plant.measure(b.mean, jnp.zeros(9)) + 0.01
        G = jnp.asarray(np.random.default_rng(1).normal(size=(6, 6)))      # cotangent of P'
        # every step compiled whole (eagerly, each primitive is a program of its own: 345 of them)
        plain = jax.jit(lambda b: ekf_predict(plant.dynamics, b, jnp.asarray(u), Q, 7))(b)
        A = np.asarray(jax.jit(jax.jacfwd(plant.dynamics))(b.mean, jnp.asarray(u), jnp.zeros(7)))
        for exact in (True, False):
            pred = lambda b: ekf_predict(plant.dynamics, b, jnp.asarray(u), Q, 7, jacobian_grad=exact)
            out = jax.jit(pred)(b)
            np.testing.assert_array_equal(out.mean, plain.mean)
            np.testing.assert_array_equal(out.cov, plain.cov)
            g = jax.jit(jax.grad(lambda b: jnp.sum(G * pred(b).cov)))(b)
            Gs = 0.5 * (np.asarray(G) + np.asarray(G).T)                   # the prediction symmetrises P'
            np.testing.assert_allclose(g.cov, A.T @ Gs @ A, rtol=1e-12, atol=1e-12)
            if exact:
                assert np.max(np.abs(g.mean)) > 1e-6        # P' moves with the heading the model is linearised at
            else:
                np.testing.assert_array_equal(g.mean, 0.0)
        r = jnp.full(9, 0.01)
        for exact in (True, False):
            upd = lambda m: ekf_update_diag(plant.measure, Gaussian(m, b.cov), z, r, 9,
                                            jacobian_grad=exact).cov
            g = jax.jit(jax.grad(lambda m: jnp.sum(G * upd(m))))(b.mean)
            if exact:
                assert np.max(np.abs(g)) > 1e-6
            else:
                np.testing.assert_array_equal(g, 0.0)


def test_spd_solve_equals_cho_solve_bit_for_bit_on_scalar_innovations():
    """The closed-form scalar gain of ekf_update (spd_solve, p = 1) is LAPACK's Cholesky
    solve exactly, under vmap, on random positive numbers of many magnitudes."""
    import jax.scipy.linalg as jsl
    from jaxnc.estimators.ekf import spd_solve
    rng = np.random.default_rng(0)
    S = (10.0 ** rng.uniform(-6, 6, (4000, 1, 1))).astype(np.float32)
    B = (rng.standard_normal((4000, 1, 3)) * 10.0 ** rng.uniform(-3, 3, (4000, 1, 1))).astype(np.float32)
    ref = jax.jit(jax.vmap(lambda s, b: jsl.cho_solve(jsl.cho_factor(s, lower=True), b)))(S, B)
    got = jax.jit(jax.vmap(spd_solve))(S, B)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))
    S2 = np.array([[2.0, 0.5], [0.5, 1.0]], np.float32)
    np.testing.assert_allclose(np.asarray(spd_solve(S2, np.eye(2, dtype=np.float32))), np.linalg.inv(S2), rtol=1e-5)


def test_small_products_equal_matmul():
    """_mm and matvec (written-out sums, no dot) equal @ to float32 rounding, for inner
    sizes 0 (zeros), within the written-out range and beyond it."""
    from jaxnc.estimators.ekf import SMALL_MATVEC, _mm, matvec
    rng = np.random.default_rng(1)
    for k in (0, 1, 3, SMALL_MATVEC, SMALL_MATVEC + 5):
        a = rng.standard_normal((4, k)).astype(np.float32)
        b = rng.standard_normal((k, 3)).astype(np.float32)
        x = rng.standard_normal(k).astype(np.float32)
        np.testing.assert_allclose(np.asarray(jax.jit(_mm)(a, b)), a @ b, atol=1e-5)
        np.testing.assert_allclose(np.asarray(jax.jit(matvec)(a, x)), a @ x, atol=1e-5)
