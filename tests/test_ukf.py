"""UKF kernels against filterpy's UnscentedKalmanFilter (float64) and the Kalman filter."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from jax.test_util import check_grads

from jaxnc.estimators import Gaussian, ekf_predict, ekf_update, merwe_sigma_points, ukf_predict, ukf_update

DT = 0.1
Q = np.diag([1e-3, 4e-3])
R = np.diag([0.05, 0.02])


def g(x, u):
    """A damped pendulum with a torque input (Euler step): angle, rate."""
    return jnp.stack([x[0] + DT * x[1], x[1] + DT * (-9.81 * jnp.sin(x[0]) - 0.3 * x[1] + u[0])])


def f(x, u, w):
    return g(x, u) + w


def hh(x):
    """Horizontal position of the bob and a quadratic of the rate: strongly nonlinear."""
    return jnp.stack([jnp.sin(x[0]), x[1] + 0.2 * x[1] ** 2])


def h(x, v):
    return hh(x) + v


def _data(steps=40):
    rng = np.random.default_rng(7)
    x = np.array([1.2, 0.0])
    us, zs = rng.normal(size=(steps, 1)), []
    for k in range(steps):
        x = np.asarray(g(jnp.asarray(x), jnp.asarray(us[k]))) + rng.multivariate_normal(np.zeros(2), Q)
        zs.append(np.asarray(hh(jnp.asarray(x))) + rng.multivariate_normal(np.zeros(2), R))
    return us, np.array(zs)


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (0.3, 0.0, 3.0 - 2.0)])
def test_ukf_matches_filterpy(alpha, beta, kappa):
    us, zs = _data()
    with jax.enable_x64(True):
        ref = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=DT, hx=lambda x: np.asarray(hh(jnp.asarray(x))),
                                    fx=lambda x, dt, u: np.asarray(g(jnp.asarray(x), jnp.asarray(u))),
                                    points=MerweScaledSigmaPoints(2, alpha=alpha, beta=beta, kappa=kappa))
        ref.x, ref.P, ref.Q, ref.R = np.array([1.0, 0.2]), np.diag([0.3, 0.5]), Q, R
        means, covs = [], []
        for u, z in zip(us, zs):
            ref.predict(u=u)
            # the update's sigma points drawn from the predicted belief (filterpy 2's predict
            # does this itself; older versions reuse the propagated points)
            ref.sigmas_f = ref.points_fn.sigma_points(ref.x, ref.P)
            ref.update(z)
            means.append(ref.x.copy())
            covs.append(ref.P.copy())

        kw = dict(alpha=alpha, beta=beta, kappa=kappa)

        def body(b, uz):
            u, z = uz
            b = ukf_update(h, ukf_predict(f, b, u, Q, 2, **kw), z, R, 2, **kw)
            return b, b

        b0 = Gaussian(jnp.array([1.0, 0.2]), jnp.diag(jnp.array([0.3, 0.5])))
        _, out = jax.jit(lambda b, us, zs: jax.lax.scan(body, b, (us, zs)))(b0, jnp.asarray(us), jnp.asarray(zs))
    np.testing.assert_allclose(np.asarray(out.mean), np.array(means), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.cov), np.array(covs), rtol=1e-9, atol=1e-12)
    # the estimate is a filter, not a copy of the model: it moved away from the prior
    assert np.max(np.abs(np.diff(np.asarray(out.mean), axis=0))) > 0.05


def test_sigma_points_match_filterpy():
    P = np.array([[0.4, 0.1, 0.0], [0.1, 0.3, -0.05], [0.0, -0.05, 0.2]])
    x = np.array([0.5, -1.0, 2.0])
    ref = MerweScaledSigmaPoints(3, alpha=0.4, beta=2.0, kappa=0.5)
    with jax.enable_x64(True):
        sp = merwe_sigma_points(Gaussian(jnp.asarray(x), jnp.asarray(P)), alpha=0.4, beta=2.0, kappa=0.5)
    np.testing.assert_allclose(np.asarray(sp.points), ref.sigma_points(x, P), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(sp.wm), ref.Wm, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(sp.wc), ref.Wc, rtol=1e-12)


@pytest.mark.parametrize("alpha, kappa", [(1.0, 0.0), (0.1, 1.0)])
def test_ukf_equals_kf_on_a_linear_model(alpha, kappa):
    """Linear f and h with noise through non-identity matrices: the UT is exact, so the UKF is
    the Kalman filter (the EKF on a linear model) step for step."""
    A = jnp.array([[1.0, 0.1, 0.0], [0.0, 0.95, 0.1], [-0.2, 0.0, 0.9]])
    B = jnp.array([[0.0], [0.1], [0.05]])
    G = jnp.array([[0.1, 0.0], [1.0, 0.0], [0.0, 0.5]])
    C = jnp.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    M = jnp.array([[1.0, 0.0], [0.5, 1.0]])                  # full rank: the posterior stays PD
    fl = lambda x, u, w: A @ x + B @ u + G @ w
    hl = lambda x, v: C @ x + M @ v
    rng = np.random.default_rng(1)
    us, zs = rng.normal(size=(25, 1)), rng.normal(size=(25, 2))
    Qv, Rv = jnp.array([0.2, 0.05]), jnp.array([[0.3, 0.1], [0.1, 0.2]])
    kw = dict(alpha=alpha, beta=2.0, kappa=kappa)
    with jax.enable_x64(True):
        def body(c, uz):
            bu, bk = c
            u, z = uz
            bu = ukf_update(hl, ukf_predict(fl, bu, u, Qv, 2, **kw), z, Rv, 2, **kw)
            bk = ekf_update(hl, ekf_predict(fl, bk, u, Qv, 2), z, Rv, 2)
            return (bu, bk), (bu, bk)

        b0 = Gaussian(jnp.zeros(3), jnp.eye(3))
        _, (u_out, k_out) = jax.jit(lambda us, zs: jax.lax.scan(body, (b0, b0), (us, zs)))(
            jnp.asarray(us), jnp.asarray(zs))
    np.testing.assert_allclose(np.asarray(u_out.mean), np.asarray(k_out.mean), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(np.asarray(u_out.cov), np.asarray(k_out.cov), rtol=1e-8, atol=1e-10)


def test_ukf_float32_covariance_symmetric_psd_and_vmap():
    us, zs = _data(60)
    b0 = Gaussian(jnp.array([1.0, 0.2], jnp.float32), jnp.diag(jnp.array([0.3, 0.5], jnp.float32)))

    def run(zs):
        def body(b, uz):
            b = ukf_update(h, ukf_predict(f, b, uz[0], Q, 2), uz[1], R, 2)
            return b, b.cov
        return jax.lax.scan(body, b0, (jnp.asarray(us, jnp.float32), zs))[1]

    covs = np.asarray(jax.jit(jax.vmap(run))(jnp.asarray(np.stack([zs, zs + 0.1]), jnp.float32)))
    assert covs.dtype == np.float32 and covs.shape == (2, 60, 2, 2)
    np.testing.assert_array_equal(covs, np.swapaxes(covs, -1, -2))
    assert np.all(np.linalg.eigvalsh(covs) > 0)


def test_ukf_gradient():
    """The posterior is differentiable in the prior mean, the measurement and R (reverse mode
    against central finite differences)."""
    us, zs = _data(3)
    with jax.enable_x64(True):
        def loss(m0, z, r):
            b = ukf_predict(f, Gaussian(m0, jnp.diag(jnp.array([0.3, 0.5]))), jnp.asarray(us[0]), Q, 2, alpha=0.5)
            b = ukf_update(h, b, z, r, 2, alpha=0.5)
            return jnp.sum(b.mean ** 2) + jnp.trace(b.cov)
        check_grads(jax.jit(loss), (jnp.array([1.0, 0.2]), jnp.asarray(zs[0]), jnp.asarray(np.diag(R))), order=1,
                    modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_ukf_bad_inputs():
    b = Gaussian(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(ValueError, match="Q must be"):
        ukf_predict(f, b, jnp.zeros(1), np.eye(3), 2)
    with pytest.raises(ValueError, match="R must be positive definite"):
        ukf_update(h, b, jnp.zeros(2), np.zeros(2), 2)
    with pytest.raises(ValueError, match="z must have the shape"):
        ukf_update(h, b, jnp.zeros(3), R, 2)
    with pytest.raises(ValueError, match="noise_dim"):
        ukf_predict(f, b, jnp.zeros(1), Q, 0)
