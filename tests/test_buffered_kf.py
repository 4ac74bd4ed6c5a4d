"""Buffered Kalman filter of seed 001 (eq. 9-15) against brute-force NumPy references.

The reference re-filters the whole sequence from the prior at every step k with the
measurements the buffer can hold in place: y_t is used iff its packet has arrived by k
and its delay is at most N.  Everything in float64.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import wifi
from jaxnc.estimators.buffered_kf import BufferedKF, bkf_estimate, bkf_init, bkf_push

K_STEPS = 60
N_BUF = 6
TOL = 1e-9


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


def _model(seed=0):
    rng = np.random.default_rng(seed)
    n, m, p = 4, 1, 2
    A = np.eye(n) + 0.05 * rng.standard_normal((n, n))          # mildly unstable is fine
    B = rng.standard_normal((n, m))
    C = rng.standard_normal((p, n))
    G = rng.standard_normal((n, n)) * 0.1
    Q = G @ G.T + 1e-3 * np.eye(n)
    R = np.diag([0.05, 0.02])
    x0, P0 = rng.standard_normal(n), np.eye(n)
    u = rng.standard_normal((K_STEPS, m))
    y = rng.standard_normal((K_STEPS, p))                       # any data: the algebra is what is tested
    return A, B, C, Q, R, x0, P0, u, y


def _reference(A, B, C, Q, R, x0, P0, u, y, gamma):
    """x_{k|k-1}: standard KF from the prior over t < k with the mask gamma (length k)."""
    x, P = x0.copy(), P0.copy()
    for t in range(len(gamma)):
        if gamma[t]:
            S = C @ P @ C.T + R
            K = P @ C.T @ np.linalg.inv(S)
            x = x + K @ (y[t] - C @ x)
            P = P - K @ C @ P
        x = A @ x + B @ u[t]
        P = A @ P @ A.T + Q
    return x, P


def _run_buffered(model, trace):
    A, B, C, Q, R, x0, P0, u, y = model
    kf = BufferedKF(*(jnp.asarray(a) for a in (A, B, C, Q, R)), N=N_BUF)
    arrival = wifi.arrival_steps(jnp.asarray(trace), max_delay=N_BUF)
    pad = jnp.concatenate([jnp.full(N_BUF, 2**30, jnp.int32), arrival])

    @jax.jit
    def run():
        def step(state, k):
            avail = jax.lax.dynamic_slice(pad, (k,), (N_BUF,)) <= k    # slots t = k-N .. k-1
            pred, nb = bkf_estimate(kf, state, avail)
            return bkf_push(state, nb, jnp.asarray(y)[k], jnp.asarray(u)[k], k), (pred.mean, pred.cov)
        s0 = bkf_init(jnp.asarray(x0), jnp.asarray(P0), N_BUF, 2, 1)
        return jax.lax.scan(step, s0, jnp.arange(K_STEPS))[1]

    means, covs = run()
    return np.asarray(means), np.asarray(covs)


def _gamma(trace, k):
    t = np.arange(k)
    tr = np.asarray(trace)[:k]
    return (tr >= 0) & (tr <= N_BUF) & (t + tr <= k)


def test_no_loss_no_delay_equals_standard_kalman_filter():
    model = _model(0)
    means, covs = _run_buffered(model, np.zeros(K_STEPS, np.int32))
    A, B, C, Q, R, x0, P0, u, y = model
    x, P = x0.copy(), P0.copy()                               # one-pass standard KF, x_{k|k-1}
    for k in range(K_STEPS):
        np.testing.assert_allclose(means[k], x, atol=TOL, rtol=TOL)
        np.testing.assert_allclose(covs[k], P, atol=TOL, rtol=TOL)
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x = A @ (x + K @ (y[k] - C @ x)) + B @ u[k]
        P = A @ (P - K @ C @ P) @ A.T + Q


@pytest.mark.parametrize("seed", [1, 2])
def test_delayed_and_lost_packets_equal_brute_force_refiltering(seed):
    model = _model(seed)
    rng = np.random.default_rng(100 + seed)
    trace = rng.integers(0, 2 * N_BUF, K_STEPS).astype(np.int32)   # some beyond the buffer
    trace[rng.random(K_STEPS) < 0.2] = wifi.LOST
    means, covs = _run_buffered(model, trace)
    for k in range(K_STEPS):
        x, P = _reference(*model, _gamma(trace, k))
        np.testing.assert_allclose(means[k], x, atol=TOL, rtol=TOL)
        np.testing.assert_allclose(covs[k], P, atol=TOL, rtol=TOL)


@pytest.mark.parametrize("d", [1, 3, N_BUF])
def test_one_late_measurement_changes_the_estimate_as_refiltering(d):
    """y_j arriving d steps late: before arrival the estimate is that without y_j; from
    step j + d on it is exactly that of re-filtering the whole sequence with y_j in place."""
    model = _model(3)
    j = 20
    trace = np.zeros(K_STEPS, np.int32)
    trace[j] = d
    means, _ = _run_buffered(model, trace)
    for k in range(j + 1, K_STEPS):
        gamma = np.ones(k, bool)
        gamma[j] = k >= j + d
        x, _ = _reference(*model, gamma)
        np.testing.assert_allclose(means[k], x, atol=TOL, rtol=TOL)
    # and the late packet does change it (the test could fail)
    without = _reference(*model, np.r_[np.ones(j, bool), False, np.ones(K_STEPS - j - 2, bool)])[0]
    assert np.max(np.abs(means[K_STEPS - 1] - without)) > 1e-6


def test_packet_later_than_buffer_counts_as_lost():
    model = _model(4)
    j = 20
    late = np.zeros(K_STEPS, np.int32)
    late[j] = N_BUF + 1
    lost = np.zeros(K_STEPS, np.int32)
    lost[j] = wifi.LOST
    np.testing.assert_allclose(_run_buffered(model, late)[0], _run_buffered(model, lost)[0], atol=0, rtol=0)
