"""Observers as estimator parts (jaxnc.loop.observers): the steady-state KF is the limit of
the time-varying filter, the Luenberger error decays as (A_N - L C)^k, the UKF equals the
Kalman filter on a linear model; intermittent measurements."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.estimators.steady_state import dlqe

A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
C = np.array([[1.0, 0.0]])
K = np.array([[2.0, 1.0]])
Q, R = np.array([1e-4, 4e-4]), np.array([[2.5e-3]])


def _plant(noise=True):
    return nc.LTI(A=A, B=B, C=C, x0=[1.0, -0.5], w_std=np.sqrt(Q) if noise else 0.0,
                  v_std=np.sqrt(R[0]) if noise else 0.0)


def _loop(estimator, N=1, trigger=None, uplink=None, noise=True, steps=200):
    return nc.Loop(plant=_plant(noise), trigger=trigger or nc.Periodic(), uplink=uplink or nc.Link(capacity=1),
                   estimator=estimator, controller=nc.StateFeedback(K), downlink=nc.Link(),
                   actuator=nc.HoldLast(), N=N, T=0.1, steps=steps)


def _xhat(loop, seed=0):
    tr = jax.jit(nc.simulate)(loop, jax.random.PRNGKey(seed))
    return np.asarray(tr.xhat), np.asarray(tr.x), tr


@pytest.mark.parametrize("N", [1, 2])
def test_steady_state_kf_equals_the_time_varying_filter_started_at_its_covariance(N):
    sskf = nc.SteadyStateKF(_plant(), Q=Q, R=R)
    _, P = nc.stationary_gain(sskf, N)
    ekf = nc.EKF(_plant(), Q=Q, R=R, mean0=np.zeros(2), cov0=np.asarray(P))      # P: a fixed point of the Riccati map
    a, _, _ = _xhat(_loop(sskf, N), seed=3)
    b, _, _ = _xhat(_loop(ekf, N), seed=3)
    np.testing.assert_allclose(a, b, atol=2e-5)


def test_steady_state_kf_is_the_limit_of_the_time_varying_filter():
    sskf = nc.SteadyStateKF(_plant(), Q=Q, R=R)
    ekf = nc.EKF(_plant(), Q=Q, R=R, mean0=np.zeros(2), cov0=np.eye(2))
    a, _, _ = _xhat(_loop(sskf, steps=300))
    b, _, _ = _xhat(_loop(ekf, steps=300))
    d = np.abs(a - b).max(axis=1)
    assert d[:5].max() > 1e-2 and d[-100:].max() < 1e-5, (d[:5], d[-100:].max())


def test_steady_state_kf_gain_is_dlqe_filter_gain():
    sskf = nc.SteadyStateKF(_plant(), Q=Q, R=R)
    with jax.enable_x64(True):
        L, P, _ = dlqe(A, np.eye(2), C, np.diag(Q), R)
    M, P1 = nc.stationary_gain(sskf, 1)
    np.testing.assert_allclose(P1, P, rtol=1e-4)
    np.testing.assert_allclose(A @ np.asarray(M), L, rtol=1e-4)        # predictor gain L = A M


@pytest.mark.parametrize("N, every", [(1, 1), (2, 1), (1, 2)])
def test_luenberger_error_decays_as_the_closed_loop_observer_matrix(N, every):
    A_N = np.linalg.matrix_power(A, N)
    L = np.array([[0.9], [1.2]]) if N == 1 else np.array([[1.0], [1.5]])
    assert np.max(np.abs(np.linalg.eigvals(A_N - L @ C))) < 1
    obs = nc.Luenberger(_plant(), L=L, mean0=[0.0, 0.0])
    xhat, x, _ = _xhat(_loop(obs, N, trigger=nc.Periodic(every), noise=False, steps=40))
    e = x[::N] - xhat                                   # x at the slow instants
    e_ref = [e[0]]
    for k in range(len(e) - 1):                           # corrected only at the instants a measurement is sent
        M = A_N - L @ C if k % every == 0 else A_N
        e_ref.append(M @ e_ref[-1])
    np.testing.assert_allclose(e, np.asarray(e_ref), atol=1e-5)
    assert np.abs(e[-1]).max() < 1e-2 * np.abs(e[0]).max()


@pytest.mark.parametrize("N", [1, 2])
def test_ukf_equals_the_kalman_filter_on_a_linear_model_with_losses(N):
    est = dict(Q=Q, R=R, mean0=np.zeros(2), cov0=np.eye(2) * 0.5)
    up = nc.Link(nc.Bernoulli(0.4), capacity=1)
    a, _, tr = _xhat(_loop(nc.UKF(_plant(), **est), N, uplink=up), seed=5)
    b, _, _ = _xhat(_loop(nc.EKF(_plant(), **est), N, uplink=up), seed=5)
    assert 0.4 < float(np.mean(np.asarray(tr.recv_sc))) < 0.8          # intermittent
    np.testing.assert_allclose(a, b, atol=2e-5)


def test_a_late_measurement_is_not_used():
    """No late-measurement buffer: with half the packets one period late the filter equals
    the one that lost exactly those; a link that delays every packet is refused when the
    loop is built (the filter would never correct: it used to run open loop silently)."""
    sskf = nc.SteadyStateKF(_plant(), Q=Q, R=R)
    half = _loop(sskf, uplink=nc.Link(delay=nc.PmfDelay([0.5, 0.5]), capacity=2), steps=20)
    late = np.asarray(nc.draw(half, jax.random.PRNGKey(0)).uplink.delay) != 0
    lost = _loop(sskf, uplink=nc.Link(loss=nc.TraceLoss(late), capacity=2), steps=20)
    (a, _, ta), (b, _, tb) = _xhat(half), _xhat(lost)
    assert 0 < late.sum() < 20 and float(np.sum(ta.recv_sc)) > float(np.sum(tb.recv_sc))
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r"SteadyStateKF\) uses a measurement at most 0 slow periods late.*never correct"):
        _loop(sskf, uplink=nc.Link(delay=nc.PmfDelay([0.0, 1.0]), capacity=2), steps=20)


@pytest.mark.parametrize("build, field", [
    (lambda: nc.Luenberger(nc.HoldLast(), L=[[1.0], [1.0]]), "Luenberger.model"),
    (lambda: nc.Luenberger(_plant(), L=[[1.0, 2.0]]), "Luenberger.L"),
    (lambda: nc.Luenberger(_plant(), L=[[1.0], [1.0]], mean0=[0.0]), "Luenberger.mean0"),
    (lambda: nc.SteadyStateKF(_plant(), Q=Q, R=[[-1.0]]), "SteadyStateKF.R"),
    (lambda: nc.SteadyStateKF(_plant(), Q=[1.0], R=R), "SteadyStateKF.Q"),
    (lambda: nc.SteadyStateKF(nc.LTI(A=[[2.0]], B=[[1.0]], C=[[0.0]]), Q=[1.0], R=[[1.0]]), "SteadyStateKF"),
    (lambda: nc.UKF(_plant(), Q=Q, R=R, mean0=np.zeros(2), cov0=-np.eye(2)), "UKF.cov0"),
    (lambda: nc.UKF(_plant(), Q=Q, R=R, mean0=np.zeros(2), cov0=np.eye(2), inputs="x"), "UKF.inputs"),
])
def test_bad_observers_name_the_field(build, field):
    with pytest.raises(ValueError, match=field):
        build()


def test_the_ukf_has_the_ekfs_window_of_late_measurements():
    """UKF(buffer=3) is the EKF part with form="unscented": on a linear plant with
    measurements up to 3 periods late it equals the EKF with the same window (the unscented
    transform is exact for a linear model), and both differ from the filters without the
    window (which drop the late measurements)."""
    plant = _plant()
    est = dict(Q=np.eye(2) * 1e-3, R=np.eye(1) * 0.01, mean0=np.zeros(2), cov0=np.eye(2))
    up = nc.Link(nc.Bernoulli(0.2), nc.PmfDelay([0.4, 0.3, 0.3]), order="all", capacity=4)
    def xhat(e):
        return np.asarray(jax.jit(nc.simulate)(_loop(e, 1, uplink=up), jax.random.PRNGKey(7)).xhat)
    u3, e3 = xhat(nc.UKF(plant, buffer=3, **est)), xhat(nc.EKF(plant, buffer=3, **est))
    u0 = xhat(nc.UKF(plant, **est))
    np.testing.assert_allclose(u3, e3, rtol=2e-4, atol=2e-5)
    assert np.max(np.abs(u3 - u0)) > 1e-3


def test_a_gain_that_does_not_converge_is_refused_also_after_one_of_the_same_shape_that_does():
    """The Loop checks each loop once (jaxnc.loop.runner._FITTED); keyed on shapes alone, a
    Luenberger L = 0 (A_N - L C with a mode at 1) built after a good L of the same shape was
    accepted, and its estimate never converged (nx3). Both orders refuse it now."""
    good, bad = np.array([[0.6], [0.8]]), np.zeros((2, 1))
    for first in (good, bad):
        for L in (first, bad if first is good else good):
            if L is bad:
                with pytest.raises(ValueError, match="Luenberger.L: A_N - L C .* spectral radius 1"):
                    _loop(nc.Luenberger(_plant(), L=L), steps=20)
            else:
                _loop(nc.Luenberger(_plant(), L=L), steps=20)


def test_a_loop_of_a_checked_shape_with_new_numbers_runs_only_the_value_checks(monkeypatch):
    """The fit check (every role traced once, ``runner._check_fit``) runs once per structure:
    a loop of the same tree, leaf shapes and dtypes with new numbers runs only
    ``runner._check_values`` (the roles' ``init(ctx)``, where the Luenberger gain is checked
    against N, and the links' draws), so a bad gain is still refused; a new static field is
    another structure, traced again."""
    from jaxnc.loop import runner
    calls = []
    check = runner._check_fit
    monkeypatch.setattr(runner, "_check_fit", lambda lp: (calls.append(1), check(lp)))
    L0 = np.array([[0.61], [0.79]], np.float32)
    _loop(nc.Luenberger(_plant(), L=L0), steps=21)
    assert len(calls) == 1
    for s in (0.9, 1.1):                                    # new numbers, same shapes: not traced again
        _loop(nc.Luenberger(_plant(), L=L0 * np.float32(s)), steps=21)
    assert len(calls) == 1
    with pytest.raises(ValueError, match="Luenberger.L: A_N - L C .* spectral radius 1"):   # but still checked
        _loop(nc.Luenberger(_plant(), L=np.zeros((2, 1), np.float32)), steps=21)
    assert len(calls) == 1
    _loop(nc.Luenberger(_plant(), L=L0), steps=22)          # a new static field: another structure
    assert len(calls) == 2


def test_the_exact_gradient_through_a_lossy_steady_state_kf_loop_equals_float64_differences_of_a_numpy_loop():
    """A 3-state servo at N = 2 (fast period 0.05 s), a SteadyStateKF over a 30 %-lossy uplink,
    state feedback: the gradient of the mean cost over 8 seeds in K, the filter's Q and R (through
    its stationary gain, dlqe) and the plant's noise stds equals central differences in float64
    of the same loop written in NumPy (scipy's Riccati solution for the gain) on the run's draws."""
    import control
    import scipy.linalg as sl
    from jaxnc import montecarlo
    T, N, steps, seeds = 0.05, 2, 40, 8
    Ac, Bc = np.array([[0, 1, 0], [0, -0.5, 1], [0, 0, -5.0]]), np.array([[0], [0], [5.0]])
    plant = nc.LTI.from_control(control.ss(Ac, Bc, [[1, 0, 0]], [[0]]), T, x0=[1.0, 0, 0],
                                w_std=[0.01, 0.02, 0.05], v_std=[0.02])
    th0 = np.array([4.0, 3.0, 0.5, 1e-4, 4e-4, 2.5e-3, 4e-4, 0.01, 0.02, 0.05, 0.02])   # K, Q, R, w_std, v_std

    def loop_of(th):
        kf = nc.SteadyStateKF(plant, Q=th[3:6], R=jnp.reshape(th[6], (1, 1)))
        return nc.Loop(plant=dataclasses.replace(plant, w_std=th[7:10], v_std=th[10:11]), trigger=nc.Periodic(1),
                       uplink=nc.Link(nc.Bernoulli(0.3)), estimator=kf,
                       controller=nc.StateFeedback(jnp.reshape(th[:3], (1, 3))),
                       downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 0.1, 0.0], R=[0.01]),
                       T=T, N=N, steps=steps)

    keys = montecarlo.seed_keys(3, seeds)
    th32 = jnp.asarray(th0, jnp.float32)
    mean_cost = lambda th: jax.vmap(lambda k: nc.run(loop_of(th), k).cost_raw)(keys).mean()
    grad = np.asarray(jax.jit(jax.grad(mean_cost))(th32))
    draws = jax.vmap(lambda k: nc.draw(loop_of(th32), k))(keys)
    wn = np.asarray(draws.w, np.float64) / th0[7:10]            # the standard normals (float32-rounded)
    vn = np.asarray(draws.v, np.float64)[:, :, 0] / th0[10]
    arrived = np.asarray(draws.uplink.delay) >= 0
    A, B = np.asarray(plant.A, np.float64), np.asarray(plant.B, np.float64)[:, 0]
    AN, BN = A @ A, A @ B + B

    def cost(th):
        K, Q, R, ws, vs = th[:3], th[3:6], th[6], th[7:10], th[10]
        P = sl.solve_discrete_are(AN.T, np.array([[1.0], [0], [0]]), np.diag(Q) + A @ np.diag(Q) @ A.T, [[R]])
        M = P[:, 0] / (P[0, 0] + R)
        total = 0.0
        for s in range(seeds):
            x, xh = np.array([1.0, 0, 0]), np.zeros(3)
            for k in range(steps // N):
                z = x[0] + vs * vn[s, k]
                xh = xh + M * (z - xh[0]) if arrived[s, k] else xh
                u = -K @ xh
                for j in range(N):
                    total += x[0] ** 2 + 0.1 * x[1] ** 2 + 0.01 * u ** 2
                    x = A @ x + B * u + ws * wn[s, k, j]
                xh = AN @ xh + BN * u
        return total / (steps * seeds)

    fd = np.array([(cost(th0 + e) - cost(th0 - e)) / (2 * e[i]) for i, e in enumerate(np.diag(1e-5 * th0))])
    np.testing.assert_allclose(grad, fd, rtol=2e-5)       # float32 gradient; measured within 1.5e-6 at 80 steps


def test_the_exact_gradient_through_an_ekf_with_late_measurements_equals_float64_differences_of_a_numpy_loop():
    """The servo above with an EKF (buffer 5) over a lossy uplink that delays packets by 1-6 fast
    periods (late measurements used by their stamps): the gradient of the mean cost in K, Q, R
    and the noise stds equals float64 central differences of a NumPy Kalman filter re-run at each
    instant over the measurements arrived by then. Compared as d/d log(value): R moves the cost
    by 10^-5 of itself, so its coordinate is held to the float32 cost's resolution."""
    import control
    from jaxnc import montecarlo
    T, N, steps, seeds = 0.05, 2, 40, 8
    Ac, Bc = np.array([[0, 1, 0], [0, -0.5, 1], [0, 0, -5.0]]), np.array([[0], [0], [5.0]])
    plant = nc.LTI.from_control(control.ss(Ac, Bc, [[1, 0, 0]], [[0]]), T, x0=[1.0, 0, 0],
                                w_std=[0.01, 0.02, 0.05], v_std=[0.02])
    th0 = np.array([4.0, 3.0, 0.5, 1e-4, 4e-4, 2.5e-3, 4e-4, 0.01, 0.02, 0.05, 0.02])   # K, Q, R, w_std, v_std
    P0 = 0.1 * np.eye(3)

    def loop_of(th):
        ekf = nc.EKF(plant, Q=jnp.diag(th[3:6]), R=jnp.reshape(th[6], (1, 1)), mean0=jnp.zeros(3, jnp.float32),
                     cov0=jnp.asarray(P0, jnp.float32), buffer=5)
        link = nc.Link(nc.Bernoulli(0.2), nc.ShiftedExponential(eta=0.01, phi=0.05), tau_max=0.4, order="all")
        return nc.Loop(plant=dataclasses.replace(plant, w_std=th[7:10], v_std=th[10:11]), trigger=nc.Periodic(1),
                       uplink=link, estimator=ekf, controller=nc.StateFeedback(jnp.reshape(th[:3], (1, 3))),
                       downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 0.1, 0.0], R=[0.01]),
                       T=T, N=N, steps=steps)

    keys = montecarlo.seed_keys(5, seeds)
    th32 = jnp.asarray(th0, jnp.float32)
    mean_cost = lambda th: jax.vmap(lambda k: nc.run(loop_of(th), k).cost_raw)(keys).mean()
    cost32, grad = jax.jit(jax.value_and_grad(mean_cost))(th32)
    draws = jax.vmap(lambda k: nc.draw(loop_of(th32), k))(keys)
    wn = np.asarray(draws.w, np.float64) / th0[7:10]
    vn = np.asarray(draws.v, np.float64)[:, :, 0] / th0[10]
    delay = np.asarray(draws.uplink.delay)
    assert (delay >= N).sum() > 20                                  # late measurements are used
    A, B = np.asarray(plant.A, np.float64), np.asarray(plant.B, np.float64)[:, 0]

    def cost(th):
        K, Q, R, ws, vs = th[:3], np.diag(th[3:6]), th[6], th[7:10], th[10]
        total = 0.0
        for s in range(seeds):
            x, us, zs = np.array([1.0, 0, 0]), [], []
            for k in range(steps // N):
                zs.append(x[0] + vs * vn[s, k])
                m, P = np.zeros(3), P0.copy()
                for j in range(k + 1):
                    if 0 <= delay[s, j] and j * N + delay[s, j] <= k * N:
                        gain = P[:, 0] / (P[0, 0] + R)
                        m, P = m + gain * (zs[j] - m[0]), P - np.outer(gain, P[0, :])
                    for _ in range(N if j < k else 0):
                        m, P = A @ m + B * us[j], A @ P @ A.T + Q
                us.append(-K @ m)
                for i in range(N):
                    total += x[0] ** 2 + 0.1 * x[1] ** 2 + 0.01 * us[k] ** 2
                    x = A @ x + B * us[k] + ws * wn[s, k, i]
        return total / (steps * seeds)

    fd = np.array([(cost(th0 + e) - cost(th0 - e)) / (2 * e[i]) for i, e in enumerate(np.diag(1e-5 * th0))])
    assert abs(float(cost32) - cost(th0)) < 1e-6 * cost(th0)
    np.testing.assert_allclose(th0 * np.asarray(grad), th0 * fd, rtol=2e-5, atol=1e-6 * float(cost32))


@pytest.mark.parametrize("weight", ["stamp", "slot"])
def test_a_relaxed_petc_sends_only_soft_decisions_above_one_half_and_its_gradient_is_exact_between_them(weight):
    """docs/tuning.md, "Limitation": with `Petc(relaxed=True)` z̄ is blended by the soft decision
    β, and the link sends the packet, with weight β, only where β > 1/2. A SteadyStateKF servo
    over a 30 %-lossy uplink equals a NumPy loop written so (float64), and its gradient in δ and
    K equals that loop's central differences (steps that move no β across 1/2). With
    ``weight="slot"`` (the default) the filter blends by β also where β <= 1/2 (nothing sent):
    the reference without the gate."""
    import control
    import scipy.linalg as sl
    from jaxnc import montecarlo
    T, N, steps, seeds, tau = 0.05, 2, 40, 8, 1e-3
    Ac, Bc = np.array([[0, 1, 0], [0, -0.5, 1], [0, 0, -5.0]]), np.array([[0], [0], [5.0]])
    plant = nc.LTI.from_control(control.ss(Ac, Bc, [[1, 0, 0]], [[0]]), T, x0=[1.0, 0, 0],
                                w_std=[0.01, 0.02, 0.05], v_std=[0.02])
    Q, R = np.array([1e-4, 4e-4, 2.5e-3]), 4e-4
    th0 = np.array([1e-3, 4.0, 3.0, 0.5])                              # delta, K

    def loop_of(th):
        return nc.Loop(plant=plant, trigger=nc.Petc(delta=th[0], temperature=tau, relaxed=True),
                       uplink=nc.Link(nc.Bernoulli(0.3)), estimator=nc.SteadyStateKF(plant, Q=Q, R=[[R]], weight=weight),
                       controller=nc.StateFeedback(jnp.reshape(th[1:], (1, 3))), downlink=nc.Link(),
                       actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 0.1, 0.0], R=[0.01]), T=T, N=N, steps=steps)

    keys = montecarlo.seed_keys(3, seeds)
    th32 = jnp.asarray(th0, jnp.float32)
    mean_cost = lambda th: jax.vmap(lambda k: nc.run(loop_of(th), k).cost_raw)(keys).mean()
    cost32, grad = jax.jit(jax.value_and_grad(mean_cost))(th32)
    draws = jax.vmap(lambda k: nc.draw(loop_of(th32), k))(keys)
    w, v = np.asarray(draws.w, np.float64), np.asarray(draws.v, np.float64)[:, :, 0]
    arrived = np.asarray(draws.uplink.delay) >= 0
    A, B = np.asarray(plant.A, np.float64), np.asarray(plant.B, np.float64)[:, 0]
    AN, BN = A @ A, A @ B + B
    P = sl.solve_discrete_are(AN.T, np.array([[1.0], [0], [0]]), np.diag(Q) + A @ np.diag(Q) @ A.T, [[R]])
    M = P[:, 0] / (P[0, 0] + R)
    gates = []

    def cost(th):
        delta, K = th[0], th[1:]
        total, gates_here = 0.0, []
        gates.append(gates_here)
        for s in range(seeds):
            x, xh, zbar = np.array([1.0, 0, 0]), np.zeros(3), 0.0
            for k in range(steps // N):
                z = x[0] + v[s, k]
                beta = 1.0 if k == 0 else 1.0 / (1.0 + np.exp(-((zbar - z) ** 2 - delta) / tau))
                gates_here.append((beta > 0.5, 0.01 < beta < 0.99))
                zbar = beta * z + (1 - beta) * zbar
                gate = beta > 0.5 if weight == "stamp" else True
                xh = xh + (beta * M * (z - xh[0]) if gate and arrived[s, k] else 0.0)
                u = -K @ xh
                for j in range(N):
                    total += x[0] ** 2 + 0.1 * x[1] ** 2 + 0.01 * u ** 2
                    x = A @ x + B * u + w[s, k, j]
                xh = AN @ xh + BN * u
        return total / (steps * seeds)

    c0 = cost(th0)
    fd = np.array([(cost(th0 + e) - cost(th0 - e)) / (2 * e[i]) for i, e in enumerate(np.diag(1e-5 * th0))])
    assert all(g == gates[0] for g in gates)                     # no step moves a beta across 1/2
    assert sum(soft for _, soft in gates[0]) > 10                 # many soft decisions
    assert abs(float(cost32) - c0) < 1e-6 * c0
    np.testing.assert_allclose(np.asarray(grad), fd, rtol=1e-4)
