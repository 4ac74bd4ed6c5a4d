"""The library parts seed 003 is built from (jaxnc.loop.Numre, jaxnc.loop.Cascade, the HDD
plant as an LTI), each against a closed form or an independent reference."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnc.loop as jl
from jaxnc.loop.cascade import cascade
from jaxnc.plants import hdd as hdd_plant

A2 = np.array([[1.0, 0.1], [0.0, 0.95]])
B2 = np.array([0.005, 0.1])
C2 = np.array([1.0, 0.0])
W_STD, V_STD = np.array([0.01, 0.02]), 0.05
CTX = jl.Context(N=1, steps=10, T=1.0, state_dim=2, input_dim=1, output_dim=1)


def _numre_loop(steps=80, p_loss=0.5, inputs="believed", N=1, delay=None):
    plant = jl.LTI(A=A2, B=B2[:, None], C=C2[None], x0=[1.0, 0.0], w_std=W_STD, v_std=[V_STD], T=0.1)
    est = jl.Numre.design(A2, B2, np.eye(2), C2, np.diag(W_STD ** 2), V_STD ** 2, steps, cov0=np.eye(2),
                          mean0=[0.5, 0.0], inputs=inputs)
    uplink = jl.Link(jl.Bernoulli(p_loss)) if delay is None else jl.Link(jl.Bernoulli(p_loss), delay)
    return jl.Loop(plant=plant, trigger=jl.Periodic(), uplink=uplink, estimator=est,
                   controller=jl.StateFeedback([[3.0, 1.5]]), downlink=jl.Link(), actuator=jl.HoldLast(),
                   N=N, steps=steps, T=0.1)


@pytest.mark.parametrize("inputs", ["believed", "applied"])
def test_numre_is_the_kalman_filter_with_intermittent_corrections(inputs):
    """With white lifted noise (We(N) = sum_c A^c Q A^c', eq. 13 for white w) the NUMRE's
    correction after a gap of N periods (eq. 11-12) equals a Kalman filter that predicts
    every period and corrects only at arrivals: a float64 numpy filter run on the loop's
    own measurements, arrivals and actions (half the packets lost)."""
    loop = _numre_loop(inputs=inputs)
    tr = jax.device_get(jax.jit(jl.simulate)(loop, jax.random.PRNGKey(4)))
    got = np.asarray(tr.recv_sc) > 0.5
    assert 20 < got.sum() < 60 and not got.all()
    xs, _ = _float64_kf(tr, np.array([0.5, 0.0]), np.eye(2))
    np.testing.assert_allclose(np.asarray(tr.xhat), xs, rtol=2e-4, atol=2e-5)


def _float64_kf(tr, mean0, cov0):
    """The Kalman filter of (A2, B2, C2) that predicts every period and corrects at the run's
    arrivals, in float64 on its measurements and actions: (x(k|k or k-1) float[K, 2], the
    covariance after each instant's correction float[K, 2, 2])."""
    got, z, u = np.asarray(tr.recv_sc) > 0.5, np.asarray(tr.z)[:, 0], np.asarray(tr.u)[:, 0]
    x, P, Q, xs, Ps = np.asarray(mean0, float), np.asarray(cov0, float), np.diag(W_STD ** 2), [], []
    for k in range(got.size):
        if got[k]:
            K = P @ C2 / (C2 @ P @ C2 + V_STD ** 2)
            x, P = x + K * (z[k] - C2 @ x), (np.eye(2) - np.outer(K, C2)) @ P
        xs.append(x)
        Ps.append(P)
        x, P = A2 @ x + B2 * u[k], A2 @ P @ A2.T + Q
    return np.asarray(xs), np.asarray(Ps)


def _numre_cov(est, state):
    return state.cov


_PRIOR_STD = np.array([0.01, 0.02])     # cov0 = diag(_PRIOR_STD^2), of the order of one period's noise


def _numre_periodic_loop(every, steps, drawn=False):
    """The 2-state plant sampled every ``every`` periods (no loss, the first at k = 0);
    its initial state drawn from the filter's prior N(mean0, cov0) when ``drawn``."""
    plant = jl.LTI(A=A2, B=B2[:, None], C=C2[None], x0=[0.5, 0.0], x0_std=_PRIOR_STD if drawn else None,
                   w_std=W_STD, v_std=[V_STD], T=0.1)
    cov0 = np.diag(_PRIOR_STD ** 2)
    est = jl.Numre.design(A2, B2, np.eye(2), C2, np.diag(W_STD ** 2), V_STD ** 2, steps, cov0=cov0,
                          mean0=[0.5, 0.0])
    return jl.Loop(plant=plant, trigger=jl.Periodic(every), uplink=jl.Link(), estimator=est,
                   controller=jl.StateFeedback([[3.0, 1.5]]), downlink=jl.Link(), actuator=jl.HoldLast(),
                   steps=steps, T=0.1, record=jl.Record(estimator=_numre_cov)), cov0


def test_numre_with_a_measurement_at_k0_starts_from_the_prior_cov0():
    """mean0, cov0 are the prior at k = 0: a measurement arriving at k = 0 is corrected with
    M = cov0 (no period of dynamics or noise before it), later ones after N periods, as the
    float64 Kalman filter that predicts every period. The first correction used to inflate
    cov0 to A cov0 A' + We(1) while leaving mean0 where it was (here the posterior variances
    at k = 0 were 1.9e-4 and 7.6e-4 instead of 9.6e-5 and 4.0e-4)."""
    loop, cov0 = _numre_periodic_loop(3, 30)
    tr = jax.device_get(jax.jit(jl.simulate)(loop, jax.random.PRNGKey(1)))
    got = np.asarray(tr.recv_sc) > 0.5
    assert got[0] and got.sum() == 10
    xs, Ps = _float64_kf(tr, np.array([0.5, 0.0]), cov0)
    np.testing.assert_allclose(np.asarray(tr.parts["estimator"])[got], Ps[got], rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(np.asarray(tr.xhat), xs, rtol=2e-4, atol=2e-5)


def test_numre_posterior_covariance_is_the_error_covariance_over_seeds():
    """With the initial state drawn from the filter's prior, the estimation error at each
    arrival is N(0, P) with P the filter's posterior covariance: the mean NEES e' P^-1 e over
    S seeds is 2 (n = 2) within 4 standard errors, sqrt(2 n / S) each, at k = 0 (1.11 before
    the fix of the first correction) and at later arrivals."""
    S = 1024
    loop, _ = _numre_periodic_loop(3, 31, drawn=True)
    tr = jax.device_get(jax.jit(jax.vmap(jl.simulate, in_axes=(None, 0)))(loop, jax.random.split(jax.random.PRNGKey(5), S)))
    e = np.asarray(tr.x, float) - np.asarray(tr.xhat, float)
    P = np.asarray(tr.parts["estimator"], float)
    for k in (0, 3, 15, 30):
        nees = np.einsum("si,sij,sj->s", e[:, k], np.linalg.inv(P[:, k]), e[:, k])
        assert abs(nees.mean() - 2.0) < 4 * np.sqrt(2 * 2 / S), (k, nees.mean())


def test_numre_takes_v_as_a_number_or_a_one_by_one_covariance():
    """V for the single output as a number, float[1] or float[1, 1] (as R elsewhere) gives the
    same filter; [V] and [[V]] failed with numpy's "only 0-dimensional arrays can be converted"."""
    tabs = [jl.Numre.design(A2, B2, np.eye(2), C2, np.diag(W_STD ** 2), V, 5, cov0=np.eye(2)).tables
            for V in (V_STD ** 2, [V_STD ** 2], [[V_STD ** 2]])]
    for t in tabs[1:]:
        assert float(t.V) == float(tabs[0].V) == pytest.approx(V_STD ** 2)
        np.testing.assert_array_equal(t.We, tabs[0].We)


def test_numre_validation():
    with pytest.raises(ValueError, match="Numre.n_max"):
        jl.Numre.design(A2, B2, np.eye(2), C2, np.eye(2), 1.0, 0, cov0=np.eye(2))
    with pytest.raises(ValueError, match="Numre.C must be one output row"):
        jl.Numre.design(A2, B2, np.eye(2), np.eye(2), np.eye(2), 1.0, 5, cov0=np.eye(2))
    with pytest.raises(ValueError, match="Numre.V"):
        jl.Numre.design(A2, B2, np.eye(2), C2, np.eye(2), -1.0, 5, cov0=np.eye(2))
    with pytest.raises(ValueError, match="Numre.inputs"):
        jl.Numre.design(A2, B2, np.eye(2), C2, np.eye(2), 1.0, 5, cov0=np.eye(2), inputs="both")
    with pytest.raises(ValueError, match="Loop.N = 1"):
        _numre_loop(steps=20, N=2)
    # the newest arrival is taken as the measurement of its arrival instant: a delayed one
    # used to be corrected with silently (the filter's gain and innovation for the wrong instant)
    for delay in (jl.PmfDelay([0.5, 0.5]), jl.PmfDelay([0.0, 0.0, 1.0])):
        with pytest.raises(ValueError, match=r"Loop.estimator \(Numre\) takes the newest arrival .* must not delay"):
            _numre_loop(steps=20, delay=delay)
    _numre_loop(steps=20, delay=jl.PmfDelay([1.0]))       # a law that never delays is allowed


@jl.pytree_dataclass
class _Feedback:
    """u = -K x + s with the integrator s+ = s + g (r - C x); aux: k."""
    K: object
    g: object = 0.0

    def init(self):
        return jnp.zeros((), jnp.float32)

    def step(self, s, k, x):
        return -(self.K @ x) + s, s + self.g * (1.0 - x[0]), k


def test_cascade_is_eq14_15():
    """The cascade iterates x <- A x + B u with u from a stateful law, and returns the law's
    state *before* each action (closed form by a Python loop)."""
    A = np.array([[1.0, 0.1], [0.0, 0.9]])
    B = np.array([0.0, 0.5])
    K = np.array([0.4, -0.3])
    x0 = np.array([0.3, -0.1])

    def law(s, k, x):
        u = -(jnp.asarray(K) @ x) + s
        return u, s + 0.5 * k, 10.0 * k

    with jax.enable_x64(True):
        us, ss, aux = jax.jit(lambda x0, s0, k: cascade(law, jnp.asarray(A), jnp.asarray(B), x0, s0, k, 5))(
            jnp.asarray(x0), jnp.asarray(0.2), jnp.asarray(3))
    x, s = x0.copy(), 0.2
    for l in range(5):
        assert float(ss[l]) == pytest.approx(s, abs=1e-15)
        assert float(aux[l]) == 10.0 * (3 + l)
        u = -(K @ x) + s
        assert float(us[l]) == pytest.approx(u, abs=1e-14)
        x, s = A @ x + B * u, s + 0.5 * (3 + l)


def test_cascade_packet_is_the_closed_loop_prediction():
    """A memoryless law u = -K x along x+ = A x + B u: the packet is u_l = -K (A - B K)^l x0."""
    K = np.array([0.4, -0.3])
    c = jl.Cascade(_Feedback(jnp.asarray(K, jnp.float32)), jnp.asarray(A2, jnp.float32),
                   jnp.asarray(B2, jnp.float32), horizon=6)
    x0 = np.array([0.3, -0.1])
    s, pkt, send = jax.jit(lambda s, x: c.step(s, x, jnp.float32(1), jnp.int32(2), CTX))(
        c.init(CTX), jnp.asarray(x0, jnp.float32))
    Acl = A2 - np.outer(B2, K)
    ref = [-K @ np.linalg.matrix_power(Acl, l) @ x0 for l in range(6)]
    np.testing.assert_allclose(np.asarray(pkt.data)[:, 0], ref, rtol=1e-5, atol=1e-7)
    assert int(pkt.stamp) == 2 and float(send) == 1.0 and int(s.gap) == 2 and int(s.aux) == 2


def test_cascade_restarts_the_law_where_its_last_cascade_was():
    """At the next arrival, N periods later, the law starts from the state its previous
    cascade reached at that instant (s_N, or s_H past the packet); without an arrival
    nothing changes and nothing is sent."""
    K = jnp.asarray([0.4, -0.3], jnp.float32)
    c = jl.Cascade(_Feedback(K, 0.5), jnp.asarray(A2, jnp.float32), jnp.asarray(B2, jnp.float32), horizon=4)
    step = jax.jit(lambda s, x, f, k: c.step(s, x, jnp.float32(f), jnp.int32(k), CTX))
    x0 = jnp.asarray([0.3, -0.1], jnp.float32)
    s1, _, _ = step(c.init(CTX), x0, 1.0, 0)
    s_quiet, _, send = step(s1, x0, 0.0, 1)
    assert float(send) == 0.0 and int(s_quiet.gap) == 0
    for a, b in zip(jax.tree.leaves((s1.law, s1.k_last)), jax.tree.leaves((s_quiet.law, s_quiet.k_last))):
        np.testing.assert_array_equal(a, b)
    # the integrator along the first cascade, by hand
    x, s, ss = np.asarray(x0, float), 0.0, []
    for l in range(5):
        ss.append(s)
        u = -(np.asarray(K) @ x) + s
        x, s = A2 @ x + B2 * u, s + 0.5 * (1.0 - x[0])
    for k_next, idx in ((3, 3), (9, 4)):            # within the packet, and past its end (H = 4)
        _, pkt, _ = step(s_quiet, x0, 1.0, k_next)
        assert float(pkt.data[0, 0]) == pytest.approx(-(np.asarray(K) @ np.asarray(x0)) + ss[idx], rel=1e-5)


@pytest.mark.parametrize("N, H, p_loss", [(1, 3, 0.0), (2, 2, 0.0), (2, 4, 0.0), (3, 3, 0.0), (2, 24, 0.3)])
def test_cascade_in_a_loop_runs_its_law_every_fast_period(N, H, p_loss):
    """Noise-free plant, exact model: the cascade's predictions are the plant's states, so the
    actions equal the law run directly every fast period on the true state (the module
    docstring's 'as if it had run every period'), at any N and with lost measurements while
    a packet still covers the gap. At N > 1 the law used to restart from the state one
    action into its last packet per slow period instead of N (|u| off by 0.29 at N = 2)."""
    a, b, steps = 0.95, 0.1, 24
    plant = jl.LTI([[a]], [[b]], [[1.0]], x0=[0.0], w_std=[0.0], v_std=[0.0], T=0.1)
    law = _Feedback(jnp.asarray([0.5], jnp.float32), 0.3)
    loop = jl.Loop(plant=plant, trigger=jl.Periodic(), uplink=jl.Link(jl.Bernoulli(p_loss)),
                   estimator=jl.Passthrough(),
                   controller=jl.Cascade(law, jnp.asarray([[a]], jnp.float32), jnp.asarray([b], jnp.float32), horizon=H),
                   downlink=jl.Link(), actuator=jl.PacketActuator(horizon=H), T=0.1, steps=steps, N=N, record=True)
    traj = jax.jit(jl.simulate)(loop, jax.random.PRNGKey(0))
    if p_loss:
        assert float(jnp.mean(traj.recv_sc)) < 0.9          # the losses are there
    first = int(np.argmax(np.asarray(traj.recv_sc) > 0)) * N      # nothing is played before the first arrival
    x, s, us = 0.0, 0.0, []
    for t in range(steps):
        u = -0.5 * x + s if t >= first else 0.0
        us.append(u)
        x, s = a * x + b * u, (s + 0.3 * (1.0 - x) if t >= first else s)
    np.testing.assert_allclose(np.asarray(traj.u)[:, 0], us, atol=1e-5)


@pytest.mark.parametrize("x64", [False, True])
def test_cascade_takes_a_model_given_as_lists_or_float64_arrays(x64):
    """A model as a user writes it: A a float64 numpy array, B a list (and the reverse).
    On a noise-free 2-state plant with the exact model the actions equal the law run every
    fast period on the true state (N = 2, H = 6, 30 % of the measurements lost). B as a list
    failed in the controller's trace ("unsupported operand type(s) for *: 'list'"), and under
    jax_enable_x64 a float64 A or B with a scan carry-type error."""
    A, b, K, steps, N = np.array([[1.0, 0.1], [0.0, 0.9]]), np.array([0.0, 0.1]), np.array([0.8, 0.3]), 30, 2
    plant = jl.LTI(A, b[:, None], np.eye(2), x0=[0.5, 0.0], w_std=[0.0, 0.0], v_std=[0.0, 0.0], T=0.1)
    with jax.enable_x64(x64):
        for Am, Bm in ((A, b.tolist()), (A.tolist(), b)):
            law = _Feedback(jnp.asarray(K, jnp.float32), 0.2)
            loop = jl.Loop(plant=plant, trigger=jl.Periodic(), uplink=jl.Link(jl.Bernoulli(0.3)),
                           estimator=jl.Passthrough(), controller=jl.Cascade(law, Am, Bm, horizon=6), downlink=jl.Link(),
                           actuator=jl.PacketActuator(horizon=6), T=0.1, steps=steps, N=N)
            traj = jax.device_get(jax.jit(jl.simulate)(loop, jax.random.PRNGKey(0)))
            recv = np.asarray(traj.recv_sc) > 0
            assert 0 < recv.mean() < 1
            first = int(np.argmax(recv)) * N
            x, s, us = np.array([0.5, 0.0]), 0.0, []
            for t in range(steps):
                u = -(K @ x) + s if t >= first else 0.0
                s = s + 0.2 * (1.0 - x[0]) if t >= first else s
                us.append(u)
                x = A @ x + b * u
            np.testing.assert_allclose(np.asarray(traj.u)[:, 0], us, atol=1e-5)


def test_cascade_on_the_measurement_and_validation():
    """A = None, H = 1: one law step on the measurement itself; its state after that step
    is where the next arrival starts."""
    c = jl.Cascade(_Feedback(jnp.asarray([2.0], jnp.float32), 0.5), horizon=1)
    ctx = CTX._replace(state_dim=5)            # the estimate is the measurement, not the plant's state
    step = jax.jit(lambda s, y, k: c.step(s, jnp.asarray([y], jnp.float32), jnp.float32(1), jnp.int32(k), ctx))
    s1, p1, _ = step(c.init(ctx), 0.2, 0)
    _, p2, _ = step(s1, 0.4, 2)
    assert float(p1.data[0, 0]) == pytest.approx(-0.4) and p1.data.shape == (1, 1)
    assert float(p2.data[0, 0]) == pytest.approx(-0.8 + 0.5 * 0.8)
    with pytest.raises(ValueError, match="Cascade.law must have init"):
        jl.Cascade(object(), horizon=1)
    with pytest.raises(ValueError, match="Cascade.horizon"):
        jl.Cascade(_Feedback(jnp.zeros(2)), horizon=0)


def test_hdd_model_is_the_augmented_lti_of_eq4():
    """hdd_model is an LTI with x+ = A x + B u + Bw w, y = C x + v of eq. (3)-(4), and the
    disturbance d = Cbar x (float64 matrices, float32 plant)."""
    A, B, Bw, C, Cbar = hdd_plant.augment(*hdd_plant.plant_matrices("unit"), *hdd_plant.disturbance_matrices())
    p = hdd_plant.hdd_model("unit", w_std=2e-5, v_std=1e-3)
    assert isinstance(p, jl.LTI) and (p.state_dim, p.input_dim, p.noise_dim, p.output_dim) == (12, 1, 1, 1)
    rng = np.random.default_rng(0)
    x, u, w, v = rng.normal(size=12), rng.normal(size=1), rng.normal(size=1), rng.normal(size=1)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    np.testing.assert_allclose(p.dynamics(f32(x), f32(u), f32(w)), A @ x + B * u + Bw * w, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(p.measure(f32(x), f32(v)), C @ x + v, rtol=1e-5)
    np.testing.assert_array_equal(hdd_plant.DISTURBANCE_OUTPUT, Cbar)
    np.testing.assert_allclose(p.w_std, [2e-5])
    np.testing.assert_allclose(p.v_std, [1e-3])
    with pytest.raises(ValueError, match="v_std"):
        hdd_plant.hdd_model(v_std=-1.0)
