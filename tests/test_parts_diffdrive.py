"""Library parts of seed 004's loops against closed forms and independent references:
jaxnc.loop.DiffDrive (plant), PeriodEKF (EKF at the sensing period), PursuitPI (controller),
ArrivalActuator, and the two pure-pursuit laws."""
import math

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.controllers.pure_pursuit import pure_pursuit_curvature, pure_pursuit_velocity
from jaxnc.design.dualrate import DiscreteSS, single_rate_pi
from jaxnc.loop.base import Inbox
from jaxnc.loop.runner import Context
from jaxnc.loop.vehicles import K_MOTOR, TAU_MOTOR, eq1, integrated
from jaxnc.paths import from_waypoints

Z5 = jnp.zeros(5)


def test_eq1_lifted_motor_matches_zoh_of_eq26():
    """Eq. (7): the NT model's wheel speeds equal N steps of G_p(s) discretised with a ZOH at T
    (python-control), and the fine-grid true plant gives the same (exact ZOH composes)."""
    plant = nc.DiffDrive()
    U = np.array([[30.0, -10.0], [45.0, 20.0], [-5.0, 60.0]], np.float32)   # N = 3
    w0 = np.array([1.0, -2.0], np.float32)
    x0 = jnp.concatenate([jnp.asarray(w0), jnp.zeros(3)])
    f = jax.jit(lambda *a: eq1(plant, *a))(x0, jnp.asarray(U), Z5)
    ss = control.ss(control.sample_system(control.tf([K_MOTOR], [TAU_MOTOR, 1.0]), plant.T, method="zoh"))
    for wheel in range(2):
        x = np.linalg.solve(np.asarray(ss.C), [w0[wheel]])
        for u in U[:, wheel]:
            x = np.asarray(ss.A) @ x + np.asarray(ss.B).ravel() * u
        ref = float((np.asarray(ss.C) @ x)[0])
        assert abs(float(f[wheel]) - ref) < 1e-4 * max(1.0, abs(ref))
    fine = jax.jit(lambda *a: integrated(plant, *a))(x0, jnp.repeat(jnp.asarray(U), plant.sub, axis=0), Z5)
    np.testing.assert_allclose(np.asarray(fine)[:2], np.asarray(f)[:2], rtol=1e-4, atol=1e-4)


def test_integrated_model_against_the_continuous_ode():
    """DiffDrive.integrated (= period with lifted="integrated") over one period NT with a command
    that changes in the middle of a slot T, against a float64 solution of the continuous model
    (motor eq. 26, kinematics eq. 2-3, scipy DOP853, rtol 1e-12): wheel speeds exact (ZOH), the
    pose within the fine grid's trapezoidal error (~1e-4 rad here). Eq. (1) as printed with the
    slot means is off by far more; n1 is additive at the end (eq. 8)."""
    from scipy.integrate import solve_ivp
    p = nc.DiffDrive()
    sub, N = p.sub, 2
    old = np.array([[40.0, 20.0], [45.0, 15.0]], np.float32)
    new = np.array([[55.0, 10.0], [30.0, 50.0]], np.float32)
    i = np.arange(N * sub)
    uf = np.where((i < 7)[:, None], old[i // sub], new[i // sub]).astype(np.float32)
    x0 = np.array([4.0, 6.5, 0.3, -0.2, 0.4], np.float32)

    def rhs(t, s, u):
        v, om = p.r * (s[0] + s[1]) / 2, p.r * (s[0] - s[1]) / (2 * p.b)
        return [(p.K * u[0] - s[0]) / p.tau, (p.K * u[1] - s[1]) / p.tau, v * np.cos(s[4]), v * np.sin(s[4]), om]
    ref = x0.astype(np.float64)
    for u in uf.astype(np.float64):
        ref = solve_ivp(rhs, (0.0, p.dt), ref, args=(u,), rtol=1e-12, atol=1e-13, method="DOP853").y[:, -1]
    got = np.asarray(jax.jit(p.period)(jnp.asarray(x0), jnp.asarray(uf), Z5), np.float64)
    err = np.abs(got - ref)
    assert np.all(err[:4] < 1e-5) and err[4] < 1e-4, err
    e1 = np.asarray(jax.jit(nc.DiffDrive(lifted="eq1").period)(jnp.asarray(x0), jnp.asarray(uf), Z5))
    np.testing.assert_allclose(e1, np.asarray(eq1(p, jnp.asarray(x0), jnp.asarray(uf.reshape(N, sub, 2).mean(1)), Z5)))
    assert np.abs(e1[4] - ref[4]) > 100 * err[4] and np.linalg.norm(e1[2:4] - ref[2:4]) > 1e-4
    n1 = jnp.asarray([0.1, -0.2, 1e-3, 2e-3, -0.01])
    np.testing.assert_allclose(np.asarray(jax.jit(lambda *a: integrated(p, *a))(jnp.asarray(x0), jnp.asarray(uf), n1)),
                               got + np.asarray(n1), rtol=1e-6, atol=1e-6)


def test_straight_line_and_noise_once_per_T():
    """Equal wheel speeds w and the command holding them: straight motion at v = r w along the
    heading (eq. 1-3). The true plant adds its wheel noise only at the first fine step of each
    T: with u = 0 a noise w0 decays as exp(-t/tau) from there (ZOH), whatever w at the others."""
    p = nc.DiffDrive()
    w = 5.0
    x = jnp.asarray([w, w, 0.0, 0.0, 0.3])
    x1 = jax.jit(lambda *a: eq1(p, *a))(x, jnp.full((2, 2), w / K_MOTOR), Z5)
    d = p.r * w * 2 * p.T
    np.testing.assert_allclose(np.asarray(x1), [w, w, d * math.cos(0.3), d * math.sin(0.3), 0.3], rtol=1e-5, atol=1e-6)

    # the runner draws the wheel noise only at fine steps t = 0, sub, 2 sub, ... (noise_period)
    from jaxnc.schemes.diffdrive import diffdrive_loop
    loop = diffdrive_loop("e", F=0.1)
    assert loop.plant.noise_period == loop.plant.sub
    wd = np.asarray(nc.draw(loop, jax.random.PRNGKey(3)).w).reshape(-1, 2)
    t_fine = np.arange(wd.shape[0])
    assert np.all(wd[t_fine % p.sub != 0] == 0.0) and np.all(wd[t_fine % p.sub == 0] != 0.0)
    np.testing.assert_allclose(wd[t_fine % p.sub == 0].std(), 0.1 * float(p.wheel), rtol=0.15)
    # a noise w0 at t = 0 and at t = sub, none between: with u = 0 it decays as exp(-t/tau) (ZOH)
    noise = jnp.zeros((2 * p.sub, 2)).at[0].set(0.7).at[p.sub].set(0.7)
    x_end, w_r = jax.jit(lambda x, ws: jax.lax.scan(lambda x, wi: (p.dynamics(x, jnp.zeros(2), wi), x[0]), x, ws))(
        jnp.zeros(5), noise)
    a = math.exp(-p.dt / p.tau)
    t = np.arange(1, 2 * p.sub + 1)
    ref = 0.7 * a ** t + np.where(t > p.sub, 0.7 * a ** (t - p.sub), 0.0)
    np.testing.assert_allclose(np.append(np.asarray(w_r)[1:], float(x_end[0])), ref, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(nc.DiffDrive(F=0.1).v_std), [0.1, 0.1, 0.002, 0.002, 0.005],
                               rtol=1e-6)


@pytest.mark.parametrize("N", [1, 2, 5])
def test_lifted_wheel_var_is_the_plants_noise_over_NT(N):
    """The wheel-speed variance at NT that N noises of std s, entering as the plant's do (first
    fine step of each T), leave: s^2 sum_c g_c^2, g_c the wheel speed at NT after a unit noise in
    slot c (u = 0), read from the plant's own steps. It used to be s^2 sum_{c<N} a^{2c}, the
    noise of slot c undecayed by its own slot: a^-2 = 5.05 times the plant's at N = 2 (1.198 s^2
    against 0.237 s^2; an empirical variance over 2e5 draws gave 0.237)."""
    p = nc.DiffDrive()
    step = jax.jit(lambda x, w: p.dynamics(x, jnp.zeros(2), w))
    g = []
    for c in range(N):
        x = jnp.zeros(5)
        for t in range(N * p.sub):
            x = step(x, jnp.asarray([1.0, 0.0]) if t == c * p.sub else jnp.zeros(2))
        g.append(float(x[0]))
    np.testing.assert_allclose(float(nc.lifted_wheel_var(p, 0.3, N)), 0.09 * np.sum(np.square(g)), rtol=1e-5)


def test_diffdrive_validation():
    with pytest.raises(ValueError, match="DiffDrive.lifted must be one of integrated, eq1"):
        nc.DiffDrive(lifted="rk4")
    with pytest.raises(ValueError, match="DiffDrive.r"):
        nc.DiffDrive(r=0.0)
    with pytest.raises(ValueError, match="DiffDrive.F"):
        nc.DiffDrive(F=-1.0)


@pytest.mark.parametrize("theta", [0.3, -0.7, 1.2])
def test_pure_pursuit_curvature_eq18(theta):
    """Target at distance L and bearing theta from a robot heading psi: k = 2 sin(theta) / L."""
    L, psi = 0.25, 0.4
    a = psi + theta
    pts = np.stack([np.linspace(0, 2, 401) * math.cos(a), np.linspace(0, 2, 401) * math.sin(a)], 1)
    path = from_waypoints(pts, "line", 0.005)
    (v, om), idx = jax.jit(lambda xy: pure_pursuit_curvature(path, xy, psi, 0, lad=L, v_ref=0.14, window=20))(
        jnp.zeros(2))
    assert int(idx) == 0
    np.testing.assert_allclose(float(om) / 0.14, 2 * math.sin(theta) / L, rtol=1e-4)


def test_pure_pursuit_velocity_eq8():
    """Seed 000 eq. (8): V_ref towards the target, scaled by D / L_ref inside the look-ahead."""
    path = from_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), "line", 0.01)
    v, idx = pure_pursuit_velocity(path, jnp.asarray([0.5, 0.3]), 0, L_ref=0.4, V_ref=0.2, window=100)
    d = np.array([0.9 - 0.5, -0.3])
    np.testing.assert_allclose(np.asarray(v), 0.2 * d / max(np.linalg.norm(d), 0.4), rtol=1e-5)
    assert int(idx) == 50


class Linear(nc.AbstractLiftedPlant):
    """x' = A x + B sum(us) + w, z = x + v: a linear lifted model (the EKF is then the KF)."""
    state_dim, input_dim, noise_dim, output_dim = 2, 1, 2, 2
    A = np.array([[1.0, 0.1], [0.0, 0.9]], np.float32)
    B = np.array([[0.0], [0.1]], np.float32)

    def dynamics(self, x, u, w):
        return self.A @ x + self.B @ u + w

    def measure(self, x, v):
        return x + v

    def period(self, x, us, w):
        return jnp.asarray(self.A) @ x + jnp.asarray(self.B) @ jnp.sum(us, axis=0) + w


def _inbox(z, w):
    return Inbox(jnp.asarray(z, jnp.float32)[None], jnp.zeros((1,), jnp.int32), jnp.asarray([w], jnp.float32),
                 jnp.ones((1,), bool), jnp.asarray([w], jnp.float32))


def test_period_ekf_is_the_kalman_filter_on_a_linear_model():
    """PeriodEKF (the EKF part with rate="slow") on a linear lifted model: correct = the KF
    update (numpy), predict = A P A' + Q with the period's actions summed; a period without a
    delivered measurement keeps the prior."""
    Q, R = np.diag([0.01, 0.02]), np.diag([0.1, 0.05])
    m0, P0 = np.array([1.0, -1.0]), np.eye(2) * 0.5
    ekf = nc.PeriodEKF(Linear(), Q=Q, R=R, mean0=m0, cov0=P0)
    assert isinstance(ekf, nc.EKF) and (ekf.rate, ekf.buffer, ekf.inputs) == ("slow", 0, "applied")
    ctx = Context(N=3, steps=30, T=0.1, state_dim=2, input_dim=1, output_dim=2)
    us = jnp.asarray([[1.0], [2.0], [-0.5]])
    step = jax.jit(lambda s, z, w: ekf.predict(ekf.correct(s, _inbox(z, w), 0)[0], us, us, 0))
    s = ekf.init(ctx)
    m, P = m0, P0
    for z, w in (([1.2, -0.7], 1.0), ([0.0, 0.0], 0.0), ([1.5, 0.1], 1.0)):
        s1, xhat = jax.jit(lambda s, z, w: ekf.correct(s, _inbox(z, w), 0))(s, z, w)
        if w:
            K = P @ np.linalg.inv(P + R)
            m, P = m + K @ (np.asarray(z) - m), (np.eye(2) - K) @ P
        np.testing.assert_allclose(np.asarray(xhat), m, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(s1.post.cov), P, rtol=1e-4, atol=1e-6)
        s = step(s, z, w)
        A, B = Linear.A.astype(float), Linear.B.astype(float)
        m, P = A @ m + B @ np.asarray(us).sum(0), A @ P @ A.T + Q
        np.testing.assert_allclose(np.asarray(s.base.mean), m, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(s.base.cov), P, rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="EKF.model must be a plant"):
        nc.PeriodEKF(nc.Passthrough(), Q=Q, R=R, mean0=m0, cov0=P0)
    with pytest.raises(ValueError, match="EKF.model must be a plant with a lifted model"):
        nc.PeriodEKF(nc.LTI(A=Linear.A, B=Linear.B, C=np.eye(2)), Q=Q, R=R, mean0=m0, cov0=P0)
    with pytest.raises(ValueError, match=r"EKF.Q must be 2x2 or a vector of 2 variances \(the state's, per slow"):
        nc.PeriodEKF(Linear(), Q=np.eye(3), R=R, mean0=m0, cov0=P0)
    with pytest.raises(ValueError, match="EKF.inputs"):
        nc.PeriodEKF(Linear(), Q=Q, R=R, mean0=m0, cov0=P0, inputs="both")
    with pytest.raises(ValueError, match="EKF.rate must be one of fast, slow"):
        nc.EKF(Linear(), Q=Q, R=R, mean0=m0, cov0=P0, rate="period")


def _ctrl(h=0, assumed_delay=0.0):
    path = from_waypoints(np.array([[0.0, 0.0], [1.0, 0.0]]), "line", 0.005)
    plant = nc.DiffDrive()
    if h == 0:
        pi = DiscreteSS.from_tf(single_rate_pi(6.0, 0.12, 0.2))
        return nc.PursuitPI(path, plant, pi, ns=2, h=0), path
    from jaxnc.design.dualrate import DualRateController, dualrate_design, pi_controller
    pi = DualRateController.from_design(dualrate_design(control.tf([K_MOTOR], [TAU_MOTOR, 1.0]),
                                                        pi_controller(6.0, 0.12), 0.1, 2))
    return nc.PursuitPI(path, plant, pi, ns=2, h=h, assumed_delay=assumed_delay), path


CTX = Context(N=20, steps=200, T=0.01, state_dim=5, input_dim=2, output_dim=5)


def test_pursuit_pi_single_rate_first_step():
    """h = 0, single rate: the packet holds D (w_com - w) (the PI's first output from rest)
    over the period's 2 sub fine steps, stamped k N; w_com from eq. (18)-(20) by hand."""
    c, path = _ctrl()
    x = jnp.asarray([1.0, 2.0, 0.1, 0.05, 0.2])
    s, pkt, send = jax.jit(lambda s, x: c.step(s, x, 1.0, jnp.int32(3), CTX))(c.init(CTX), x)
    tx, ty = 0.1 + 0.12, 0.0                     # nearest point (0.1, 0) plus the look-ahead on the x axis
    dx, dy = tx - 0.1, ty - 0.05
    kappa = 2 * (dy * math.cos(0.2) - dx * math.sin(0.2)) / (dx * dx + dy * dy)
    om = 0.14 * kappa
    w_com = np.array([(0.14 + 0.06 * om) / 0.028, (0.14 - 0.06 * om) / 0.028])
    np.testing.assert_allclose(np.asarray(s.w_com), w_com, rtol=1e-4)
    u = float(c.pi.D) * (w_com - np.array([1.0, 2.0]))
    assert pkt.data.shape == (2 * 10, 2) and int(pkt.stamp) == 3 * 20 and float(send) == 1.0
    np.testing.assert_allclose(np.asarray(pkt.data), np.broadcast_to(u, (20, 2)), rtol=1e-4)
    # at the end of the path (last tenth, within end_tol): zeros from now on
    s2, pkt2, _ = jax.jit(lambda s, x: c.step(s, x, 1.0, jnp.int32(4), CTX))(
        s._replace(idx=jnp.int32(path.M - 2)), jnp.asarray([1.0, 2.0, 0.99, 0.0, 0.0]))
    assert bool(s2.stop) and np.all(np.asarray(pkt2.data) == 0.0)


@pytest.mark.parametrize("assumed_delay", [0.0, 0.05])
def test_pursuit_pi_prediction_stage(assumed_delay):
    """h = 1: the packet's second state is the model's period map of the first under the fine
    commands assumed for period k (the previous packet's u_{k|k-1} for ceil(d / dt) fine steps,
    then u_{k|k}), and the second period's actions are the law applied to that prediction."""
    c, _ = _ctrl(h=1, assumed_delay=assumed_delay)
    x = jnp.asarray([4.0, 5.0, 0.1, 0.02, 0.1])
    s0 = c.init(CTX)._replace(u_next=jnp.asarray([[30.0, 40.0], [35.0, 45.0]]))
    s, pkt, _ = jax.jit(lambda s, x: c.step(s, x, 1.0, jnp.int32(0), CTX))(s0, x)
    U0, _, pi1, idx1 = c.law(s0.pi, s0.idx, x)
    uf = np.repeat(np.asarray(U0), 10, axis=0)
    n_early = math.ceil(assumed_delay / c.model.dt - 1e-6)
    uf[:n_early] = np.repeat(np.asarray(s0.u_next), 10, axis=0)[:n_early]
    x1 = integrated(c.model, x, jnp.asarray(uf), Z5)
    np.testing.assert_allclose(np.asarray(s.est), np.stack([np.asarray(x), np.asarray(x1)]), rtol=1e-5, atol=1e-6)
    U1, _, _, _ = c.law(pi1, idx1, x1)
    np.testing.assert_allclose(np.asarray(pkt.data), np.repeat(np.concatenate([U0, U1]), 10, axis=0), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(s.u_next), np.asarray(U1), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(s.u_prior), np.asarray(s0.u_next))
    assert c.horizon == 40


def test_pursuit_pi_validation():
    c, path = _ctrl()
    with pytest.raises(ValueError, match="PursuitPI.assumed_delay must be in"):
        _ctrl(h=1, assumed_delay=0.3)
    with pytest.raises(ValueError, match="PursuitPI.pi"):
        nc.PursuitPI(path, c.model, 1.0, ns=2)
    with pytest.raises(ValueError, match=r"PursuitPI.pi's N \(2\) must equal ns \(3\)"):
        nc.PursuitPI(path, c.model, _ctrl(h=1)[0].pi, ns=3)


def _deliver(act, state, data, stamp):
    box = Inbox(jnp.asarray(data)[None], jnp.asarray([stamp], jnp.int32), jnp.ones(1), jnp.ones(1, bool), jnp.ones(1))
    return act.receive(state, box)


def test_arrival_actuator_starts_at_arrival():
    """A packet of H = 4 actions stamped 0 arriving at t = 1: held zero at t = 0, data[0..2] at
    t = 1..3 (shifted by the arrival), the period ends at t = 4 and data[2] is held; a
    PacketActuator plays data[t - stamp] instead (data[1] at t = 1)."""
    ctx = Context(N=4, steps=8, T=0.1, state_dim=1, input_dim=1, output_dim=1)
    data = np.array([[1.0], [2.0], [3.0], [4.0]], np.float32)
    act = nc.ArrivalActuator(horizon=4)
    s = act.init(ctx)
    s, u0 = act.output(s, 0)
    s = _deliver(act, s, data, 0)
    us = [float(u0[0])]
    for t in range(1, 7):
        s, u = act.output(s, t)
        us.append(float(u[0]))
    assert us == [0.0, 1.0, 2.0, 3.0, 3.0, 3.0, 3.0]
    pa = nc.PacketActuator(horizon=4)
    ps = _deliver(pa, pa.init(ctx), data, 0)
    assert float(pa.output(ps, 1)[1][0]) == 2.0
    with pytest.raises(ValueError, match="ArrivalActuator.horizon"):
        nc.ArrivalActuator(horizon=0)


def test_arrival_actuator_does_not_play_an_older_packet_arriving_late():
    """Over a link of order="all" the packet stamped 0 can arrive (t = 6) after the one stamped
    4 (t = 4): the newer one's actions go on, 12 and 13 at t = 6, 7 (nx3: the older packet
    replaced it and, its period over, the plant held 11)."""
    ctx = Context(N=4, steps=12, T=0.1, state_dim=1, input_dim=1, output_dim=1)
    act = nc.ArrivalActuator(horizon=4)
    old, new = (np.array([[10.0 * k + j] for j in range(4)], np.float32) for k in (0, 1))
    s, us = act.init(ctx), []
    for t in range(4, 9):
        if t == 4:
            s = _deliver(act, s, new, 4)
        if t == 6:
            s = _deliver(act, s, old, 0)
        s, u = act.output(s, t)
        us.append(float(u[0]))
    assert us == [10.0, 11.0, 12.0, 13.0, 13.0]


def test_truncated_exponential_delay_law():
    """The downlink's delay model (section 5.1): eta + phi Exp(1) truncated to [eta, tau_max]:
    bounds, the mean of the truncated law (closed form) within 4 standard errors, the steps
    the seconds quantised up to the fast period, and the declared bounds."""
    eta, phi, tmax, n, T = 0.08, 0.04, 0.17, 20000, 0.01
    model = nc.TruncatedExponential(eta, phi, tmax)
    steps, tau = jax.jit(lambda k: model.sample(k, n, T))(jax.random.PRNGKey(3))
    tau, steps = np.asarray(tau, np.float64), np.asarray(steps)
    assert tau.min() >= eta - 1e-7 and tau.max() <= tmax + 1e-7
    c = tmax - eta
    mean = eta + phi - c * math.exp(-c / phi) / (1 - math.exp(-c / phi))
    assert abs(tau.mean() - mean) < 4 * tau.std() / math.sqrt(n)
    r = tau / T                                   # ceil up to float32 rounding: r <= steps < r + 1
    assert np.all(steps >= r - 1e-4) and np.all(steps < r + 1)
    assert model.bounds(T) == (8, 17)


def _circle_loop(R, sat=None, u_max=100.0, w_max=15.0, seconds=40.0):
    th = np.linspace(-np.pi / 2, -np.pi / 2 + 6 * np.pi, 12001)            # three laps, from (0, 0) heading +x
    path = from_waypoints(np.stack([R * np.cos(th), R + R * np.sin(th)], 1), "circle", ds=0.005)
    plant = nc.DiffDrive(u_max=u_max)
    ctrl = nc.PursuitPI(path, plant, DiscreteSS.from_tf(single_rate_pi(6.0, 0.12, 0.1)), v_ref=0.14, lad=0.12,
                        w_max=w_max)
    act = nc.PacketActuator(horizon=ctrl.horizon, on_exhausted="hold")
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(0.0), controller=ctrl,
                   downlink=nc.Link(), actuator=act if sat is None else nc.LimitedActuator(act, sat), N=10,
                   steps=int(seconds * 100), T=0.01, record=("x",))


@pytest.mark.parametrize("limit", ["none", "actuator", "plant", "w_max"])
def test_pursuit_on_a_circle_reaches_the_closed_form_steady_circle(limit):
    """Pure pursuit with an arc-length look-ahead lad on a circle of radius R (noise-free,
    integral PI): the steady path is a concentric circle r' where the pursuit's curvature
    kappa(r') = 2 (r' - R cos a) / (R^2 + r'^2 - 2 R r' cos a), a = lad / R, turns the wheel
    speeds into that circle, r' = b (w_r + w_l) / (w_r - w_l) with w_l = v (1 - b kappa) / r.
    Unsaturated: r' = R, w = (v +- b v / R) / r. With the right wheel limited to w_r (its
    command saturated at 40, w_r = K 40; or its reference clipped at w_max = 5) the steady
    circle is outside, 9.46 mm and 11.56 mm; the saturation in a LimitedActuator and in
    DiffDrive.u_max give the same circle."""
    from scipy.optimize import brentq
    R, lad, v, b, r = 0.5, 0.12, 0.14, 0.06, 0.028
    kw = {"none": {}, "actuator": dict(sat=nc.Saturation(-40.0, 40.0)), "plant": dict(u_max=40.0),
          "w_max": dict(w_max=5.0)}[limit]
    x = np.asarray(nc.simulate(_circle_loop(R, **kw), jax.random.PRNGKey(0)).x)[-500:]     # the last 5 s
    radius = np.hypot(x[:, 2], x[:, 3] - R)
    if limit == "none":
        np.testing.assert_allclose(x[-1, :2], [(v + b * v / R) / r, (v - b * v / R) / r], rtol=1e-5)
        assert np.abs(radius - R).max() < 1e-5
        return
    a = lad / R
    kappa = lambda rr: 2 * (rr - R * math.cos(a)) / (R * R + rr * rr - 2 * R * rr * math.cos(a))
    w_r = 5.0 if limit == "w_max" else K_MOTOR * 40.0
    w_l = lambda rr: v * (1 - b * kappa(rr)) / r
    r_ss = brentq(lambda rr: rr - b * (w_r + w_l(rr)) / (w_r - w_l(rr)), R, 2 * R)
    assert abs(radius.mean() - r_ss) < 5e-5, (radius.mean() - R, r_ss - R)     # 9.4577 vs 9.4583 mm
    np.testing.assert_allclose(x[-1, :2], [w_r, w_l(r_ss)], rtol=2e-3)
