"""The buffered Kalman filter of seed 001 (eq. 9-15), jaxnc.loop.EKF(buffer=N) on a linear
model, against brute-force NumPy references.

The reference re-filters the whole sequence from the prior at every step k with the
measurements the buffer can hold in place: y_t is used iff its packet has arrived by k
and its delay is at most N; the EKF's estimate at k is the posterior x_{k|k}. The reference
is float64; the EKF keeps its state in float32, so the tolerance is float32 rounding
accumulated over the run (relative 2e-4 of the estimate's scale).
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import wifi

K_STEPS = 60
N_BUF = 6
RTOL = 2e-4


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
    """x_{k|k}: standard KF from the prior over t <= k with the mask gamma (length k + 1)."""
    x, P = x0.copy(), P0.copy()
    for t in range(len(gamma)):
        if t:
            x = A @ x + B @ u[t - 1]
            P = A @ P @ A.T + Q
        if gamma[t]:
            S = C @ P @ C.T + R
            K = P @ C.T @ np.linalg.inv(S)
            x = x + K @ (y[t] - C @ x)
            P = P - K @ C @ P
    return x, P


@jax.jit
def _filter(ekf, u, y, trace):
    """The EKF's estimates and covariances over K_STEPS instants; the uplink's ring (capacity
    N + 2, slot s mod C holds y_s stamped s) built from the delays ``trace`` (< 0: lost)."""
    ctx = nc.Context(N=1, steps=K_STEPS, T=1.0, state_dim=4, input_dim=1, output_dim=2)
    cap = N_BUF + 2

    def step(state, k):
        s = k - jnp.mod(k - jnp.arange(cap), cap)                      # the stamp in each slot
        ok = s >= 0
        d = trace[jnp.maximum(s, 0)]
        box = nc.Inbox(y[jnp.maximum(s, 0)], jnp.where(ok, s, -1), ok.astype(jnp.float32),
                       ok & (d >= 0) & (s + d <= k), jnp.zeros(cap))
        state, xhat = ekf.correct(state, box, k)
        return ekf.predict(state, u[k][None], u[k][None], k), (xhat, state.post.cov)

    return jax.lax.scan(step, ekf.init(ctx), jnp.arange(K_STEPS))[1]


def _run_buffered(model, trace):
    A, B, C, Q, R, x0, P0, u, y = (np.asarray(a, np.float32) for a in model)
    ekf = nc.EKF(nc.LTI(A=A, B=B, C=C), Q=Q, R=R, mean0=x0, cov0=P0, buffer=N_BUF)
    means, covs = _filter(ekf, u, y, jnp.asarray(trace, jnp.int32))
    return np.asarray(means, np.float64), np.asarray(covs, np.float64)


def _gamma(trace, k):
    t = np.arange(k + 1)
    tr = np.asarray(trace)[:k + 1]
    return (tr >= 0) & (tr <= N_BUF) & (t + tr <= k)


def _close(a, ref):
    np.testing.assert_allclose(a, ref, rtol=RTOL, atol=RTOL * max(1.0, np.abs(ref).max()))


def test_no_loss_no_delay_equals_standard_kalman_filter():
    model = _model(0)
    means, covs = _run_buffered(model, np.zeros(K_STEPS, np.int32))
    A, B, C, Q, R, x0, P0, u, y = model
    x, P = x0.copy(), P0.copy()                               # one-pass standard KF, x_{k|k}
    for k in range(K_STEPS):
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x, P = x + K @ (y[k] - C @ x), P - K @ C @ P
        _close(means[k], x)
        _close(covs[k], P)
        x, P = A @ x + B @ u[k], A @ P @ A.T + Q


@pytest.mark.parametrize("seed", [1, 2])
def test_delayed_and_lost_packets_equal_brute_force_refiltering(seed):
    model = _model(seed)
    rng = np.random.default_rng(100 + seed)
    trace = rng.integers(0, 2 * N_BUF, K_STEPS).astype(np.int32)   # some beyond the buffer
    trace[rng.random(K_STEPS) < 0.2] = wifi.LOST
    means, covs = _run_buffered(model, trace)
    for k in range(K_STEPS):
        x, P = _reference(*model, _gamma(trace, k))
        _close(means[k], x)
        _close(covs[k], P)


@pytest.mark.parametrize("d", [1, 3, N_BUF])
def test_one_late_measurement_changes_the_estimate_as_refiltering(d):
    """y_j arriving d steps late: before arrival the estimate is that without y_j; from
    step j + d on it is that of re-filtering the whole sequence with y_j in place."""
    model = _model(3)
    j = 20
    trace = np.zeros(K_STEPS, np.int32)
    trace[j] = d
    means, _ = _run_buffered(model, trace)
    for k in range(j, K_STEPS):
        gamma = np.ones(k + 1, bool)
        gamma[j] = k >= j + d
        x, _ = _reference(*model, gamma)
        _close(means[k], x)
    # and the late packet does change it (the test could fail)
    without = _reference(*model, np.r_[np.ones(j, bool), False, np.ones(K_STEPS - j - 1, bool)])[0]
    assert np.max(np.abs(means[K_STEPS - 1] - without)) > 1e-6


def test_packet_later_than_buffer_counts_as_lost():
    model = _model(4)
    j = 20
    late = np.zeros(K_STEPS, np.int32)
    late[j] = N_BUF + 1
    lost = np.zeros(K_STEPS, np.int32)
    lost[j] = wifi.LOST
    np.testing.assert_allclose(_run_buffered(model, late)[0], _run_buffered(model, lost)[0], atol=0, rtol=0)
