"""Estimators and PETC triggers inside a running loop, against float64 NumPy written from the
docs (the et trial, docs/build_your_own_loop.md "An eleventh study").

The kernel tests (tests/test_buffered_kf.py, tests/test_triggers.py) build the uplink's ring
by hand; these run the whole loop and re-derive, from the run's own draws (`nc.draw`) and its
recorded measurements, actions and send decisions, what the docs say the parts do:

* a measurement stamped sN sent with a delay of d fast periods is read at slow instant
  s + ceil(d / N) ("The order of a period"); an `EKF(buffer=D)` uses it iff that is at most
  s + D, and its posterior at k is the Kalman filter re-run from the prior with exactly the
  measurements read by k (the estimators' module docstring);
* `Petc` sends when ||zbar - z||^2 > sigma ||z||^2 + delta (summed over outputs, or per
  output with reading="each"), at the first instant, and after max_silence instants
  without a send (the triggers' module docstring); the controller's trigger does the same on
  the first action of each packet;
* `EKF(rate="slow")` on a user's lifted linear model is the Kalman filter of the slow-period
  system x+ = A^N x + sum A^(N-1-j) B u_j + w, Cov(w) = sum A^j Q A^j'.

The loop is float32, the references float64: the tolerances are float32 rounding over the
run (estimates of order 1).
"""
import dataclasses

import jax
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import stability

T = 0.1
A = np.array([[1.0, T], [0.0, 0.9]])
B = np.array([[0.005], [0.1]])
C = np.array([[1.0, 0.0]])
G = np.array([[0.5 * T * T], [T]])          # one noise input through G (q = 1 < n)
W_STD, V_STD = np.array([0.3]), np.array([0.05])
Q = G @ np.diag(W_STD ** 2) @ G.T
R = np.diag(V_STD ** 2)
P0 = 0.5 * np.eye(2)
K = np.array([[2.0, 1.0]])


def posterior(est, state):
    """Record: the EKF's posterior at each slow instant (a SqrtGaussian's cov is S S')."""
    return state.post.mean, state.post.cov


def _plant(cls=nc.LTI):
    return cls(A, B, C, G=G, x0=[1.0, 0.0], x0_std=[0.5, 0.5], w_std=W_STD, v_std=V_STD, T=T)


def _loop(estimator, N, trigger, controller_trigger=None, steps=60):
    uplink = nc.Link(nc.Bernoulli(0.3), nc.PmfDelay([0.3, 0.2, 0.1, 0.1, 0.1, 0.2]), order="all")
    downlink = nc.Link(nc.Bernoulli(0.3))
    return nc.Loop(plant=estimator.model, trigger=trigger, uplink=uplink, estimator=estimator,
                   controller=nc.StateFeedback(K), downlink=downlink, actuator=nc.HoldLast(),
                   controller_trigger=controller_trigger, N=N, steps=steps, T=T,
                   record=nc.Record(signals=("u", "z", "xhat", "sent_sc", "sent_ca"),
                                    estimator=posterior if isinstance(estimator, nc.EKF) else None))


def _read_at(loop, key, tr):
    """Slow instant at which each measurement is read (a large number: never)."""
    N, S = loop.N, loop.steps // loop.N
    delay = np.asarray(nc.draw(loop, key).uplink.delay)
    sent = np.asarray(tr.sent_sc) > 0.5
    return np.array([s - (-delay[s] // N) if sent[s] and delay[s] >= 0 else 10 ** 9 for s in range(S)])


def _refilter(read_at, z, u, N, D, AN=None, QN=None, lifted=False, noise_period=1):
    """Posterior means and covariances at every slow instant k, re-filtered from the prior
    (lifted: one step of (AN, QN) per slow period; else Q at the fast instants t with
    t % noise_period == 0)."""
    S = len(read_at)
    means, covs = [], []
    for k in range(S):
        m, P = np.zeros(2), P0.copy()
        for s in range(k + 1):
            if read_at[s] <= min(k, s + D):
                Kg = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
                m, P = m + Kg @ (z[s] - C @ m), (np.eye(2) - Kg @ C) @ P
            if s == k:
                break
            for j in range(N):
                m = A @ m + B @ u[s * N + j]
                if not lifted:
                    P = A @ P @ A.T + (Q if (s * N + j) % noise_period == 0 else 0.0)
            if lifted:
                P = AN @ P @ AN.T + QN
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


def _check_against_refiltering(loop, D, seeds, lifted=False):
    N = loop.N
    AN = np.linalg.matrix_power(A, N)
    QN = sum(np.linalg.matrix_power(A, j) @ Q @ np.linalg.matrix_power(A, j).T for j in range(N))
    late_used = dropped = 0
    for seed in seeds:
        key = jax.random.PRNGKey(seed)
        tr = jax.jit(nc.simulate)(loop, key)
        read_at = _read_at(loop, key, tr)
        lateness = read_at - np.arange(len(read_at))
        late_used += int(np.sum((lateness > 0) & (lateness <= D)))
        dropped += int(np.sum((lateness > D) & (read_at < 10 ** 9)))
        m_ref, P_ref = _refilter(read_at, np.asarray(tr.z, float), np.asarray(tr.u, float), N, D, AN, QN, lifted)
        m, P = (np.asarray(a, float) for a in tr.parts["estimator"])
        np.testing.assert_allclose(m, m_ref, atol=2e-5)
        np.testing.assert_allclose(np.asarray(tr.xhat, float), m_ref, atol=2e-5)
        np.testing.assert_allclose(P, P_ref, atol=2e-5 * np.abs(P_ref).max())
    return late_used, dropped


@pytest.mark.parametrize("form", ["joseph", "sqrt"])
def test_buffered_ekf_in_a_loop_equals_refiltering_the_measurements_it_read(form):
    """N = 2, delays 0-5 fast periods (read 0-3 slow periods late), buffer 1, PETC with a
    safety condition, lossy downlink; the filter collocated with the actuator."""
    ekf = nc.EKF(_plant(), Q=W_STD ** 2, R=R, mean0=np.zeros(2), cov0=P0, buffer=1, inputs="applied", form=form)
    loop = _loop(ekf, N=2, trigger=nc.Petc(delta=1e-3, max_silence=3))
    late_used, dropped = _check_against_refiltering(loop, D=1, seeds=range(2))
    assert late_used > 5 and dropped > 5          # the window used some late measurements and dropped others


def _petc_reference(s, sigma, delta, max_silence, reading):
    """Decisions of eq. (3)-(4) with the safety condition, in float64, and |gap| at each instant."""
    sigma, delta = np.broadcast_to(sigma, s.shape[1:]), np.broadcast_to(delta, s.shape[1:])
    send, margin, zbar, last = np.zeros(len(s), bool), np.full(len(s), np.inf), None, 0
    for k in range(len(s)):
        fire = k == 0
        if k:
            per = (zbar - s[k]) ** 2 - (sigma * s[k] ** 2 + delta)
            gap = per.max() if reading == "each" else per.sum()
            margin[k] = abs(gap)
            fire = gap > 0 or (max_silence > 0 and k - last >= max_silence)
        if fire:
            zbar, last = s[k].copy(), k
        send[k] = fire
    return send, margin


@pytest.mark.parametrize("reading", ["sum", "each"])
def test_petc_decisions_in_a_loop_follow_eq4_and_the_safety_condition(reading):
    """Both triggers of one loop (N = 2): the sensor's on z, the controller's on the first
    action u = -K xhat of each packet; decisions away from a float32 tie (|gap| > 1e-6)."""
    sensor = dict(sigma=0.05, delta=2e-3, max_silence=4)
    ctrl = dict(sigma=0.1, delta=0.02, max_silence=3)
    ekf = nc.EKF(_plant(), Q=W_STD ** 2, R=R, mean0=np.zeros(2), cov0=P0, buffer=2)
    loop = _loop(ekf, N=2, trigger=nc.Petc(reading=reading, **sensor),
                 controller_trigger=nc.Petc(reading=reading, **ctrl), steps=120)
    for seed in range(2):
        tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(seed))
        for signal, spec, sent in ((np.asarray(tr.z, float), sensor, tr.sent_sc),
                                   (-np.asarray(tr.xhat, float) @ K.T, ctrl, tr.sent_ca)):
            ref, margin = _petc_reference(signal, reading=reading, **spec)
            sent = np.asarray(sent) > 0.5
            clear = margin > 1e-6
            assert clear.mean() > 0.95
            np.testing.assert_array_equal(sent[clear], ref[clear])
            assert 0.1 < sent.mean() < 0.9              # neither trivial


@nc.pytree_dataclass
class LiftedLTI(nc.LTI, nc.AbstractLiftedPlant):
    """A user's lifted linear model: the state after the slow period's actions, plus w."""

    def period(self, x, us, w):
        for j in range(us.shape[0]):
            x = self.A @ x + self.B @ us[j]
        return x + w


def test_slow_rate_ekf_on_a_users_lifted_model_equals_the_slow_period_kalman_filter():
    """N = 3, buffer 1; Q of the lifted model = the fast noise summed over the period."""
    N = 3
    QN = sum(np.linalg.matrix_power(A, j) @ Q @ np.linalg.matrix_power(A, j).T for j in range(N))
    ekf = nc.PeriodEKF(_plant(LiftedLTI), Q=QN, R=R, mean0=np.zeros(2), cov0=P0, buffer=1)
    loop = _loop(ekf, N=N, trigger=nc.Petc(delta=1e-3, max_silence=3), steps=90)
    late_used, _ = _check_against_refiltering(loop, D=1, seeds=range(2), lifted=True)
    assert late_used > 3
    # the fast-rate EKF on the same plant gives the same estimates (the lift is exact)
    fast = dataclasses.replace(loop, estimator=nc.EKF(_plant(), Q=W_STD ** 2, R=R, mean0=np.zeros(2), cov0=P0,
                                                       buffer=1, inputs="applied"))
    key = jax.random.PRNGKey(0)
    run = jax.jit(nc.simulate)
    np.testing.assert_allclose(np.asarray(run(fast, key).xhat), np.asarray(run(loop, key).xhat), atol=2e-5)


@nc.pytree_dataclass
class CoarseNoiseLTI(nc.LTI):
    """A plant simulated on a grid finer than its disturbance: w enters every 3 fast periods
    (the declared ``noise_period``; the runner draws it at t = 0, 3, 6, ...)."""

    noise_period = 3


@pytest.mark.parametrize("form", ["joseph", "sqrt"])
def test_fast_rate_ekf_adds_the_process_noise_only_where_the_model_declares_it(form):
    """The EKF predicts with Q at the fast instants t = 0, P, 2P, ... of the model's
    ``noise_period`` P (t counted over the run, so at N = 2 the noise instants move within
    the slow period), as the runner draws it: it used to add Q at every fast period, a
    covariance P times too large between measurements."""
    N, D, P = 2, 1, CoarseNoiseLTI.noise_period
    ekf = nc.EKF(_plant(CoarseNoiseLTI), Q=W_STD ** 2, R=R, mean0=np.zeros(2), cov0=P0, buffer=D,
                 inputs="applied", form=form)
    loop = _loop(ekf, N=N, trigger=nc.Petc(delta=1e-3, max_silence=3), steps=60)
    key = jax.random.PRNGKey(0)
    tr = jax.jit(nc.simulate)(loop, key)
    m_ref, P_ref = _refilter(_read_at(loop, key, tr), np.asarray(tr.z, float), np.asarray(tr.u, float), N, D,
                             noise_period=P)
    m, cov = (np.asarray(a, float) for a in tr.parts["estimator"])
    np.testing.assert_allclose(m, m_ref, atol=2e-5)
    np.testing.assert_allclose(cov, P_ref, atol=2e-5 * np.abs(P_ref).max())


def test_steady_state_kf_sums_the_slow_period_noise_only_where_it_enters():
    """N = 3 = noise_period: w enters at the first fast instant of each slow period, so the
    slow-period noise is A^2 G Q G' A^2' (it was the sum over all three instants); scipy's DARE
    on that system gives the gain, and the loop's estimates follow it."""
    import scipy.linalg

    N = 3
    kf = nc.SteadyStateKF(_plant(CoarseNoiseLTI), Q=W_STD ** 2, R=R, inputs="applied")
    A2 = np.linalg.matrix_power(A, 2)
    P_ref = scipy.linalg.solve_discrete_are(np.linalg.matrix_power(A, N).T, C.T, A2 @ Q @ A2.T, R)
    M_ref = P_ref @ C.T @ np.linalg.inv(C @ P_ref @ C.T + R)
    M, P = nc.stationary_gain(kf, N)
    np.testing.assert_allclose(np.asarray(M), M_ref, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(P), P_ref, rtol=1e-4)
    loop = _loop(kf, N=N, trigger=nc.Petc(delta=1e-3, max_silence=3), steps=60)
    key = jax.random.PRNGKey(0)
    tr = jax.jit(nc.simulate)(loop, key)
    read_at = _read_at(loop, key, tr)
    z, u, m, means = np.asarray(tr.z, float), np.asarray(tr.u, float), np.zeros(2), []
    for k in range(len(read_at)):
        if read_at[k] == k:                 # no window: only a measurement read on time
            m = m + M_ref @ (z[k] - C @ m)
        means.append(m)
        for j in range(N):
            m = A @ m + B @ u[k * N + j]
    np.testing.assert_allclose(np.asarray(tr.xhat, float), np.array(means), atol=2e-5)
    with pytest.raises(ValueError, match="N=2 is not a multiple of the model's noise_period=3"):
        nc.stationary_gain(kf, 2)


def test_steady_state_kf_takes_a_noise_input_narrower_than_the_state():
    """One disturbance input through G (q = 1 < n = 2): G Q G' is singular, and formed in
    float32 its smallest eigenvalue rounded below 0, so about half of such models were refused
    ("dlqe: Q must be positive semi-definite") with a valid Q. Each G now gives scipy's gain."""
    import scipy.linalg

    rng = np.random.default_rng(0)
    for i in range(6):
        g = rng.standard_normal((2, 1))
        plant = nc.LTI(A, B, C, G=g, w_std=W_STD, v_std=V_STD, T=T)
        kf = nc.SteadyStateKF(plant, Q=W_STD ** 2, R=R)
        for N in (1, 2) if i == 0 else (1,):
            AN = np.linalg.matrix_power(A, N)
            QN = sum(np.linalg.matrix_power(A, j) @ g @ np.diag(W_STD ** 2) @ g.T @ np.linalg.matrix_power(A, j).T
                     for j in range(N))
            P_ref = scipy.linalg.solve_discrete_are(AN.T, C.T, QN, R)
            M, P = nc.stationary_gain(kf, N)
            np.testing.assert_allclose(np.asarray(P), P_ref, rtol=1e-4, atol=1e-9)
            np.testing.assert_allclose(np.asarray(M), P_ref @ C.T @ np.linalg.inv(C @ P_ref @ C.T + R), rtol=1e-4)


def test_a_singular_textbook_process_noise_is_accepted_and_an_indefinite_one_refused():
    """The discrete white-noise acceleration model's Q = s2 [[T^4/4, T^3/2], [T^3/2, T^2]] has
    rank 1; its zero eigenvalue rounds to about -1e-8 of its scale, and the EKF, the UKF and the
    SteadyStateKF refused it ("Q must be positive semi-definite") for 7 to 14 of these 28
    (T, s2), the stability module's mare_step 20 in float32. Accepted now, with scipy's stationary gain; a Q with a negative eigenvalue of 1e-5
    of its scale is still refused."""
    import scipy.linalg

    plant = nc.LTI(np.array([[1.0, T], [0.0, 1.0]]), B, C, w_std=[0.01, 0.01], v_std=V_STD, T=T)
    for dt in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0):
        for s2 in (0.01, 0.1, 1.0, 9.81):
            Qd = s2 * np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]])
            nc.EKF(plant, Q=Qd, R=R, mean0=np.zeros(2), cov0=Qd)
            nc.UKF(plant, Q=Qd, R=R, mean0=np.zeros(2), cov0=np.eye(2))
            stability.mare_step(np.eye(2), np.asarray(plant.A), C, Qd.astype(np.float32), R, 0.5)   # 20 of 28 refused
            if s2 == 1.0:                  # (the Riccati solution costs 0.1 s a model)
                kf = nc.SteadyStateKF(plant, Q=Qd, R=R)
                P_ref = scipy.linalg.solve_discrete_are(np.asarray(plant.A, float).T, C.T, Qd, R)
                np.testing.assert_allclose(np.asarray(nc.stationary_gain(kf)[1]), P_ref, rtol=1e-3)
    v = np.array([1.0, -1.0]) / np.sqrt(2)
    bad = np.eye(2) - (1 + 1e-5) * np.outer(v, v)          # eigenvalues 1 and -1e-5
    for build in (lambda: nc.EKF(plant, Q=bad, R=R, mean0=np.zeros(2), cov0=np.eye(2)),
                  lambda: nc.SteadyStateKF(plant, Q=bad, R=R)):
        with pytest.raises(ValueError, match="Q must be positive semi-definite"):
            build()
