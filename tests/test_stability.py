"""Theorem 1 machinery and intermittent-observation Kalman filtering against closed forms,
hand-computed bounds and NumPy / SciPy references."""
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from jaxnc import stability as st
from jaxnc.estimators.ekf import Gaussian, ekf_update, ekf_update_terms
from jaxnc.plants.mecanum import Mecanum, MecanumNoise

SINOPOLI_A = np.array([[1.25, 1.0, 0.0], [0.0, 0.9, 7.0], [0.0, 0.0, 0.6]])   # Sinopoli et al. 2004, example
SINOPOLI_C = np.array([[1.0, 0.0, 1.0]])
SINOPOLI_Q = 20.0 * np.eye(3)
SINOPOLI_R = np.array([[2.5]])


@dataclasses.dataclass(frozen=True)
class Scalar:
    """x' = a x + u + l w,  z = c x + m v: every Jacobian bound of eq. (18) is known by hand."""
    a: float = 1.2
    c: float = 2.0
    l: float = 0.5
    m: float = 1.5

    def dynamics(self, x, u, w):
        return self.a * x + u + self.l * w

    def measure(self, x, v):
        return self.c * x + self.m * v


def test_update_terms_are_the_update_and_its_jacobians():
    """ekf_update_terms (the correction estimator_pass records): its posterior is
    ekf_update's, H and M are the measurement's Jacobians at the prior mean, and K solves
    eq. (15), K (H P H' + M R M') = P H'."""
    plant, noise = Mecanum(), MecanumNoise()
    x = jnp.array([0.1, -0.05, 0.2, 0.7, -0.4, 0.3])
    P = jnp.diag(jnp.array([1e-2, 2e-2, 1e-2, 3e-2, 2e-2, 1e-2]))
    z = plant.measure(x + 0.01, jnp.zeros(9))
    b, H, M, K = jax.jit(lambda b, z: ekf_update_terms(plant.measure, b, z, noise.R(), 9))(Gaussian(x, P), z)
    ref = jax.jit(lambda b, z: ekf_update(plant.measure, b, z, noise.R(), 9))(Gaussian(x, P), z)
    np.testing.assert_array_equal(b.mean, ref.mean)
    np.testing.assert_array_equal(b.cov, ref.cov)
    np.testing.assert_allclose(H, jax.jacfwd(plant.measure, argnums=0)(x, jnp.zeros(9)), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(M, jax.jacfwd(plant.measure, argnums=1)(x, jnp.zeros(9)), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(K @ (H @ P @ H.T + M @ noise.R() @ M.T), P @ H.T, rtol=1e-3, atol=1e-6)


def test_scalar_pass_bounds_by_hand():
    """Bounds of eq. (18) on a linear scalar model: Jacobians exact, P and K equal to a
    float64 NumPy Kalman recursion driven by the same arrival flags."""
    with jax.enable_x64(True):
        mod, Q, R, N, dp, Kn = Scalar(), 0.3, 0.2, 3, 0.3, 3000
        rng = np.random.default_rng(0)
        us = rng.normal(size=(Kn, 1))
        xs = np.zeros((Kn + 1, 1))
        for k in range(Kn):
            xs[k + 1] = mod.dynamics(xs[k], us[k], rng.normal() * math.sqrt(Q))
        xs = xs / np.maximum(1.0, np.abs(xs).max())           # keep the true states tame
        f = jax.jit(lambda key: st.estimator_pass(mod, xs, us, key, N=N, dp=dp, Q=[[Q]], R=[[R]],
                                                  v_std=[math.sqrt(R)], P0=[[0.5]]))
        rec = f(jax.random.PRNGKey(3))
        b = jax.jit(lambda r: st.measure_bounds(r, [[Q]], [[R]]))(rec)
        np.testing.assert_allclose([b.abar, b.h_lo, b.h_hi, b.l_lo, b.l_hi, b.mbar, b.q_lo, b.q_hi, b.rbar],
                                   [mod.a, mod.c, mod.c, mod.l, mod.l, mod.m, Q, Q, R], rtol=1e-12)
        arrived = np.asarray(rec.arrived)
        assert not arrived[np.arange(Kn) % N != 0].any()
        # arrival rate (1 - dp)/N within 4 binomial standard deviations
        n_slow = Kn // N
        p_hat = arrived.sum() / n_slow
        assert abs(p_hat - (1 - dp)) < 4 * math.sqrt(dp * (1 - dp) / n_slow)
        assert float(b.lam) == pytest.approx(arrived.mean(), rel=1e-12)
        # scalar Kalman recursion (independent reference)
        P, post, pred, gains = 0.5, [], [], []
        Rm = mod.m ** 2 * R
        for k in range(Kn):
            K = P * mod.c / (mod.c ** 2 * P + Rm)
            if k % N == 0:
                gains.append(K)
            if arrived[k]:
                P = (1 - K * mod.c) ** 2 * P + K ** 2 * Rm
            post.append(P)
            P = mod.a ** 2 * P + mod.l ** 2 * Q
            pred.append(P)
        np.testing.assert_allclose(rec.P_post[:, 0, 0], post, rtol=1e-10)
        np.testing.assert_allclose(rec.P_pred[:, 0, 0], pred, rtol=1e-10)
        assert float(b.kbar) == pytest.approx(max(gains), rel=1e-10)
        assert float(b.p_lo) == pytest.approx(min(post), rel=1e-10)
        assert float(b.p_hi) == pytest.approx(max(pred), rel=1e-10)
        assert float(b.p_order) >= 0.0


def test_pass_with_petc_sends_when_eq4_holds():
    """With a Petc trigger the pass sends a sample (slow instant k, k mod N = 0) when the
    PETC condition (eq. 4) against the last sample sent holds, and always at k = 0: gamma
    equals a Python loop over the noise-free measurements."""
    from jaxnc.loop import Petc
    mod, N, Kn, sigma, delta = Scalar(), 2, 400, 0.3, 0.5
    rng = np.random.default_rng(1)
    us = rng.normal(size=(Kn, 1)).astype(np.float32)
    xs = np.zeros((Kn + 1, 1), np.float32)
    for k in range(Kn):
        xs[k + 1] = 0.5 * xs[k] + us[k]
    trig = Petc(sigma=sigma, delta=delta)
    rec = jax.jit(lambda key: st.estimator_pass(mod, xs, us, key, N=N, dp=0.0, Q=[[0.3]], R=[[0.2]], v_std=[0.0],
                                                P0=[[0.5]], trigger=trig))(jax.random.PRNGKey(0))
    z = mod.c * xs[:-1, 0]
    last, ref = z[0], []
    for k in range(Kn):
        g = k == 0 or (last - z[k]) ** 2 - (sigma * z[k] ** 2 + delta) > 0
        sent = g and k % N == 0
        last = z[k] if sent else last
        ref.append(sent)
    np.testing.assert_array_equal(np.asarray(rec.gamma), ref)
    assert 0.2 < np.mean(ref[::N]) < 0.9                   # the condition does decide


def _bounds(**kw):
    base = dict(abar=1.1, h_lo=1.0, h_hi=2.0, kbar=0.4, l_lo=0.5, l_hi=0.8, mbar=1.0, p_lo=0.1, p_hi=2.0,
                q_lo=0.3, q_hi=0.6, rbar=0.2, lam=0.4, gamma=1.0, p_order=0.0)
    base.update(kw)
    return st.Bounds(**base)


def test_theorem1_without_events_closed_form():
    """sigma = delta = 0, gamma = 1: (19) reduces to lambda > (abar^2 - 1)/abar^2 (and the printed
    form to lambda > (1 - abar^2)/abar^2); eta -> mu as a3 -> 0; nu and the limit by hand."""
    b = _bounds()
    c = st.check_theorem1(b, sigma=0.0, delta=0.0, N=2)
    a2 = b.abar ** 2
    assert c.lhs19 == pytest.approx((a2 - 1) / a2, rel=1e-9)
    assert c.lhs19_paper == pytest.approx((1 - a2) / a2, rel=1e-9)
    mu = b.l_lo ** 2 * b.q_lo / (a2 * b.p_hi + b.l_lo ** 2 * b.q_lo)
    nu = (a2 * b.kbar ** 2 * b.rbar + b.l_hi ** 2 * b.q_hi) / b.p_hi
    assert c.mu == pytest.approx(mu, rel=1e-12)
    assert c.eta == pytest.approx(mu, rel=1e-5)
    assert c.nu == pytest.approx(nu, rel=1e-12)
    assert c.c1 == pytest.approx(a2 * (1 - b.lam), rel=1e-9)
    assert c.holds and c.holds_paper and not c.vacuous
    assert c.stationary == pytest.approx(nu * b.p_hi * (1 - mu) / mu, rel=1e-4)
    # a trivial scale below the bound makes it vacuous; lambda above 1/N breaks (19)
    assert st.check_theorem1(b, sigma=0.0, delta=0.0, N=2, scale=0.5 * c.stationary).vacuous
    bad = st.check_theorem1(b, sigma=0.0, delta=0.0, N=3)
    assert not bad.holds and "1/N" in bad.reason and math.isinf(bad.stationary)


def test_theorem1_a3_and_a1_optima():
    """delta = 0: best a3 = sqrt(kbar sigma/(1 - mu)), eta = mu - 2 sqrt((1 - mu) kbar sigma);
    gamma < 1: min over a1 of (19)'s numerator terms is X + Y + 2 sqrt(XY) (a2 -> inf)."""
    b = _bounds(abar=1.0, p_hi=0.3 * 0.25, l_lo=0.5, q_lo=0.3)     # mu = 1/2
    sigma, gamma, lam = 0.02, 0.9, 0.45
    c = st.check_theorem1(b, sigma=sigma, delta=0.0, N=2, gamma=gamma, lam=lam)
    mu = 0.5
    assert c.mu == pytest.approx(mu, rel=1e-12)
    assert c.a3 == pytest.approx(math.sqrt(b.kbar * sigma / (1 - mu)), rel=1e-12)
    assert c.eta == pytest.approx(mu - 2 * math.sqrt((1 - mu) * b.kbar * sigma), rel=1e-12)
    X = (1 - gamma) * (1 + b.kbar * b.h_hi) ** 2
    Y = b.kbar ** 2 * sigma * b.h_hi ** 2
    best = (X + Y + 2 * math.sqrt(X * Y)) / gamma
    assert best <= c.lhs19 <= best * 1.01
    # PETC with a large sigma: (20) cannot hold (eta <= mu - 2 sqrt((1-mu) kbar sigma) < 0)
    f = st.check_theorem1(b, sigma=2.0, delta=0.9, N=2, gamma=gamma, lam=lam)
    assert not f.cond20 and not f.holds and f.vacuous and "(20)" in f.reason


def test_bound_a21_geometric_sum():
    eta, nu, p_lo, p_hi, e0 = 0.07, 0.3, 0.2, 1.5, 0.8
    k = np.arange(0, 60)
    got = jax.jit(lambda k: st.bound_a21(k, eta=eta, nu=nu, p_lo=p_lo, p_hi=p_hi, e0=e0))(k)
    ref = [(p_hi / p_lo) * e0 * (1 - eta) ** kk + nu * p_hi * sum((1 - eta) ** i for i in range(1, kk))
           for kk in k]
    np.testing.assert_allclose(got, ref, rtol=1e-5)


# ---------------------------------------------------------------- intermittent observations


def test_mare_step_against_numpy():
    with jax.enable_x64(True):
        rng = np.random.default_rng(1)
        A, C = rng.normal(size=(3, 3)), rng.normal(size=(2, 3))
        G = rng.normal(size=(3, 3))
        P, Q, R = G @ G.T + np.eye(3), np.eye(3) * 0.5, np.diag([0.3, 0.7])
        lam = 0.37
        ref = A @ P @ A.T + Q - lam * A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + R) @ C @ P @ A.T
        got = jax.jit(st.mare_step)(P, A, C, Q, R, lam)
        np.testing.assert_allclose(got, ref, rtol=1e-12)


def test_mare_at_full_arrival_is_the_dare():
    with jax.enable_x64(True):
        P, change = jax.jit(lambda: st.mare_iterate(SINOPOLI_A, SINOPOLI_C, SINOPOLI_Q, SINOPOLI_R, 1.0, 2000))()
        ref = solve_discrete_are(SINOPOLI_A.T, SINOPOLI_C.T, SINOPOLI_Q, SINOPOLI_R)
        np.testing.assert_allclose(P, ref, rtol=1e-9)
        assert float(change) < 1e-12


def test_critical_rate_bounds():
    # scalar and invertible C: lambda_min = 1 - 1/rho^2 is the critical rate, so lambda_max meets it
    assert st.lambda_min(np.array([[1.3]])) == pytest.approx(1 - 1 / 1.69)
    assert st.lambda_min(np.diag([0.5, 0.9])) == 0.0
    tol = 2e-3
    assert st.lambda_max([[1.3]], [[1.0]], [[1.0]], [[1.0]], tol=tol) == pytest.approx(1 - 1 / 1.69, abs=tol)
    A2 = np.array([[1.2, 0.3], [0.0, 0.8]])
    assert st.lambda_max(A2, np.eye(2), np.eye(2), np.eye(2), tol=tol) == pytest.approx(st.lambda_min(A2), abs=tol)
    # Sinopoli's example has one unstable mode, observed: the MARE bound meets the lower one
    lmin = st.lambda_min(SINOPOLI_A)
    assert lmin == pytest.approx(0.36)
    assert st.lambda_max(SINOPOLI_A, SINOPOLI_C, SINOPOLI_Q, SINOPOLI_R, tol=tol) == pytest.approx(lmin, abs=tol)
    # two unstable modes seen through one output: a strict gap lambda_min < lambda_max
    A3 = np.diag([1.3, 1.2])
    assert st.lambda_max(A3, [[1.0, 1.0]], np.eye(2), [[1.0]], tol=tol) > st.lambda_min(A3) + 0.1


def test_critical_rate_is_zero_for_a_stable_plant_and_infinite_for_an_undetectable_one():
    """Stable A: every arrival rate, lambda_max = 0 (it read about tol). An unstable or
    marginal mode the noise excites and C does not see: no rate <= 1 bounds the covariance
    (the Kalman filter's own Riccati iteration diverges), lambda_max = inf (it read 1.0)."""
    assert st.lambda_max(np.diag([0.5, 0.3]), [[1.0, 0.0]], np.eye(2), [[1.0]]) == 0.0
    assert st.lambda_max(np.diag([1.5, 0.5]), [[0.0, 1.0]], np.eye(2), [[1.0]]) == np.inf
    assert st.lambda_max(1.0, 0.0, 1.0, 1.0) == np.inf          # an unobserved random walk
    assert st.lambda_min(1.3) == pytest.approx(1 - 1 / 1.69)     # a scalar is 1 x 1, as in lambda_max


def test_critical_rate_does_not_depend_on_the_noise_scale():
    """The MARE is homogeneous: (Q, R) -> c (Q, R) scales P by c, so lambda_max is the same.
    Its divergence test compared the trace with an absolute 1e12: with Q = R = 1e13 I the
    first iterate already exceeded it, and a stable plant read inf (it is 0), an unstable
    scalar one inf (it is 1 - 1/a^2)."""
    tol = 2e-3
    for c in (1e-12, 1.0, 1e13):
        assert st.lambda_max(0.5, 1.0, c, c, tol=tol) == 0.0
        assert 1 - 1 / 1.69 <= st.lambda_max(1.3, 1.0, c, c, tol=tol) <= 1 - 1 / 1.69 + tol


def test_critical_rate_of_a_slowly_converging_filter_is_not_read_as_infinite():
    """A random walk observed through a precise-enough sensor with tiny process noise
    (a = 1, q = 1e-8, r = 1): the Kalman filter's Riccati iteration converges, at a rate
    1 - 2e-4 per step, so it had not settled within the default 20000 steps and lambda_max
    read inf ("no arrival rate bounds the covariance"; the critical rate is 0). lambda = 1
    is now decided by doubling; where the plain iteration cannot settle, it says so."""
    with pytest.raises(ValueError, match="does not settle within steps=20000 even with every measurement"):
        st.lambda_max(1.0, 1.0, 1e-8, 1.0)
    assert st.lambda_max(1.0, 0.0, 1e-8, 1.0) == np.inf          # unobserved: still inf


def test_critical_rate_upper_bound_for_one_output_closed_form():
    """A diagonal A seen through one output (C with no zero entry): the MARE has a solution
    iff lam > 1 - 1/prod|lambda_u|^2 over the unstable eigenvalues, which lambda_max meets
    from above within tol (two cases: two unstable modes; a sign-changing mode, a stable
    one, another C and Q)."""
    tol = 2e-3
    cases = [(np.diag([1.3, 1.2]), [[1.0, 1.0]], np.eye(2), 1.3 * 1.2),
             (np.diag([1.3, -1.1, 0.5]), [[1.0, 2.0, 1.0]], np.diag([1.0, 3.0, 0.5]), 1.3 * 1.1)]
    for A, C, Q, prod in cases:
        exact = 1 - 1 / prod ** 2
        assert exact <= st.lambda_max(A, C, Q, [[1.0]], tol=tol) <= exact + tol


def test_riccati_maps_refuse_a_scalar_R_for_several_outputs():
    """A scalar R with p = 2 outputs was added to every entry of C P C' (not R I): the
    random Riccati recursion returned a wrong trace (2.74 for 3.09) and the MARE iteration
    NaN, without an error."""
    A, C, Q = np.diag([1.2, 0.5]), np.eye(2), np.eye(2)
    with pytest.raises(ValueError, match="R must be p x p = 2 x 2"):
        st.random_riccati(jax.random.PRNGKey(0), A, C, Q, 1.0, 0.9, 5)
    with pytest.raises(ValueError, match="R must be p x p = 2 x 2"):
        st.mare_iterate(A, C, Q, 1.0, 0.9, 5)
    # a scalar stays a 1 x 1 matrix where p = 1
    P, _ = st.mare_iterate(1.3, 1.0, 1.0, 2.0, 0.8, 500)
    assert P.shape == (1, 1)


def test_random_riccati_scalar_closed_form():
    """R = 0, C = 1: P resets to Q on arrival, so E[P] -> Q / (1 - (1 - lam) a^2)."""
    with jax.enable_x64(True):
        a, Q, lam, n, steps = 1.2, 0.5, 0.7, 4000, 120
        keys = jax.random.split(jax.random.PRNGKey(0), n)
        tr = jax.jit(jax.vmap(lambda k: st.random_riccati(k, [[a]], [[1.0]], [[Q]], [[0.0]], lam, steps)))(keys)
        last = np.asarray(tr[:, -1])
        exact = Q / (1 - (1 - lam) * a ** 2)
        assert abs(last.mean() - exact) < 4 * last.std(ddof=1) / math.sqrt(n)


def test_random_riccati_between_lyapunov_and_mare():
    """Sinopoli et al. Theorem 4: S <= lim E[P_k] <= V for lam above lambda_max."""
    with jax.enable_x64(True):
        lam, n, steps = 0.8, 2000, 150
        keys = jax.random.split(jax.random.PRNGKey(1), n)
        tr = jax.jit(jax.vmap(lambda k: st.random_riccati(k, SINOPOLI_A, SINOPOLI_C, SINOPOLI_Q, SINOPOLI_R,
                                                          lam, steps)))(keys)
        last = np.asarray(tr[:, -1])
        half = 4 * last.std(ddof=1) / math.sqrt(n)
        lower = np.trace(st.lyapunov_lower(SINOPOLI_A, SINOPOLI_Q, lam))
        V, _ = st.mare_iterate(SINOPOLI_A, SINOPOLI_C, SINOPOLI_Q, SINOPOLI_R, lam, 3000)
        upper = float(jnp.trace(V))
        assert lower < upper
        assert lower - half <= last.mean() <= upper + half


def test_eigvalsh_jacobi_against_numpy():
    """The LAPACK-free symmetric eigenvalues used by measure_bounds (jaxlib 0.10.2's
    batched CPU eigvalsh can deadlock its thread pool) match NumPy's, including repeated,
    zero and ill-conditioned spectra."""
    rng = np.random.default_rng(0)
    mats = []
    for n in (1, 2, 3, 6, 9):
        X = rng.normal(size=(n, n))
        mats.append((X @ X.T, n))
        U = np.linalg.qr(rng.normal(size=(n, n)))[0]
        lam = np.repeat([1e-6, 2.0, 2.0, 0.0, 5.0, 1e3, -1.0, 3.0, 3.0], 1)[:n]
        mats.append((U @ np.diag(lam) @ U.T, n))
    with jax.enable_x64(True):
        for S, n in mats:
            got = np.asarray(st._eigvalsh(jnp.asarray(S, jnp.float64)))
            want = np.linalg.eigvalsh(S)
            np.testing.assert_allclose(got, want, atol=1e-12 * max(1.0, np.abs(want).max()))
    batch = jnp.asarray(np.stack([m for m, n in mats if n == 6]), jnp.float32)
    got = np.asarray(jax.jit(st._eigvalsh)(batch))
    want = np.linalg.eigvalsh(np.asarray(batch, np.float64))
    np.testing.assert_allclose(got, want, atol=1e-4 * np.abs(want).max())


def test_critical_rate_of_a_slow_stable_plant_is_exactly_zero():
    """A stable A bounds E[P] with no measurement at all: lambda_max = 0 exactly (its
    docstring's contract). lam = 0 was decided by the plain iteration from 0, which settles
    as rho(A)^2k: a = 0.9999 read 0.00098 (about tol, after 5 s of bisection), and a stable
    A with a slow mode C does not see (0.9999) was refused with "raise steps". The closed
    form: the Lyapunov sum converges iff rho(A) < 1, whatever C."""
    assert st.lambda_max(0.9999, 1.0, 1.0, 1.0) == 0.0
    assert st.lambda_max(np.array([[0.9999, 0.1], [0.0, 0.5]]), [[0.0, 1.0]], np.eye(2), [[1.0]]) == 0.0
    # a mode the noise does not excite stays known exactly, whatever its eigenvalue
    assert st.lambda_max(np.diag([1.5, 0.5]), [[0.0, 1.0]], np.diag([0.0, 1.0]), [[1.0]]) == 0.0
    # a nilpotent A (a shift register) is stable: lambda_min divided by rho = 0
    assert st.lambda_min([[0.0, 1.0], [0.0, 0.0]]) == 0.0


def test_mare_iterate_change_of_a_diverging_iteration_is_not_zero():
    """Scalar a = 2, c = q = r = 1 at lam = 0.5 < lambda_c = 0.75: the iterates grow as
    P+ = a^2 (1 - lam) P + O(1) = 2 P + O(1), so the relative change tends to 1/2. The change
    was a ratio of Frobenius norms, whose square overflowed in float32 once P passed 1.8e19:
    from step 62 on it read 0.0, "converged", for a diverging iteration."""
    for steps in (60, 100):
        P, change = st.mare_iterate(2.0, 1.0, 1.0, 1.0, 0.5, steps)
        assert np.isfinite(float(P[0, 0])) and float(P[0, 0]) > 1e17
        assert float(change) == pytest.approx(0.5, abs=1e-3)


def test_riccati_maps_accept_integers_and_mixed_float_widths():
    """Integer matrices (mare_iterate(2, 1, 1, 1, ...)) failed with "OverflowError: cannot
    convert float infinity to integer", an integer P0 or, under x64, float32 matrices with a
    float64 lam with a scan carry type error. The scalar MARE's fixed point at a = 2,
    q = r = c = 1, lam = 0.9 solves 0.6 P^2 - 4 P - 1 = 0."""
    exact = (4 + math.sqrt(16 + 2.4)) / 1.2
    P, change = st.mare_iterate(2, 1, 1, 1, 0.9, 500)
    assert float(P[0, 0]) == pytest.approx(exact, rel=1e-5) and float(change) < 1e-5
    A, C = np.array([[1.2, 0.3], [0.0, 0.8]], np.float32), np.eye(2, dtype=np.float32)
    ref, _ = st.mare_iterate(A, C, C, C, 0.7, 300)
    P_int, _ = st.mare_iterate(A, C, C, C, 0.7, 300, P0=np.eye(2, dtype=int))
    np.testing.assert_allclose(P_int, ref, rtol=1e-5)
    with jax.enable_x64(True):
        P32, _ = st.mare_iterate(A, C, C, C, np.float64(0.7), 300)
        tr = st.random_riccati(jax.random.PRNGKey(0), A, C, C, C, 0.7, 5, P0=np.eye(2, dtype=int))
    assert P32.dtype == np.float32 and tr.dtype == np.float32
    np.testing.assert_allclose(P32, ref, rtol=1e-5)


def test_eager_riccati_iterations_compile_once_per_shape_not_per_call():
    """A sweep over the arrival rate in a notebook calls these eagerly: each call compiled its
    loop again (a new body each time, 0.13 s); now a call with another rate compiles nothing,
    and gives what the same iteration in NumPy gives."""
    import jax
    from jaxnc import stability as st
    from jaxnc.cache import compile_clock
    A = np.array([[1.2, 0.3], [0.0, 0.9]], np.float32)
    C, Q, R = np.array([[1.0, 0.0]], np.float32), np.eye(2, dtype=np.float32), np.eye(1, dtype=np.float32)
    st.mare_iterate(A, C, Q, R, 0.9, 50)
    st.random_riccati(jax.random.PRNGKey(0), A, C, Q, R, 0.9, 50)
    before = compile_clock()
    P, _ = st.mare_iterate(A, C, Q, R, 0.8, 50)
    tr = st.random_riccati(jax.random.PRNGKey(1), A, C, Q, R, 0.8, 50)
    assert (compile_clock() - before).compilations == 0
    Pr = np.zeros((2, 2))
    for _ in range(50):
        APC = A @ Pr @ C.T
        Pr = A @ Pr @ A.T + Q - 0.8 * APC @ np.linalg.solve(C @ Pr @ C.T + R, APC.T)
    np.testing.assert_allclose(P, Pr, rtol=1e-4)
    assert tr.shape == (50,) and np.all(np.isfinite(np.asarray(tr)))
