"""jaxnc.loop.LinearController against python-control's simulation of the same loop, PID's
back-calculation, and a float64 recursion of its equations in a lossy saturated loop."""
import dataclasses

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import references as refs

H = 0.05


def _servo_loop(controller, *, steps=120, uplink=None, N=1, T=H, reference_free=False):
    """A DC motor's position (1 / (s (0.5 s + 1)), exact ZOH at T) over an ideal or lossy uplink."""
    motor = control.tf([1.0], [0.5, 1.0, 0.0])
    plant = nc.LTI.from_control(motor, T, realization="observable", x0=[0.0, 0.0])
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=uplink or nc.Link(), estimator=nc.Passthrough(),
                   controller=controller, downlink=nc.Link(), actuator=nc.HoldLast(), T=T, N=N, steps=steps)


def test_a_lead_compensator_loop_equals_python_control_forced_response():
    """A lead compensator 8 (0.5 s + 1) / (0.1 s + 1), Tustin at h, in unity feedback on the motor with a unit
    step at 0.5 s: the loop's position equals python-control's simulation of feedback(C P) driven by r."""
    K = 120
    lead = control.tf([4.0, 8.0], [0.1, 1.0])
    ref = refs.Step(1.0, time=10 * H)
    ctrl = nc.LinearController.from_control(lead, H, reference=ref)
    assert ctrl.dt == H and np.shape(ctrl.A) == (1, 1)
    x = np.asarray(jax.jit(nc.simulate)(_servo_loop(ctrl, steps=K), jax.random.PRNGKey(0)).x[:, 0])
    Cd = control.c2d(lead, H, "tustin")
    P = control.c2d(control.tf([1.0], [0.5, 1.0, 0.0]), H, "zoh")
    r = np.asarray(refs.evaluate(ref, K, H))[:, 0]
    # u_k depends on y_k (D != 0), the plant's output at k; the actuator applies u_k over [k, k+1)
    y = control.forced_response(control.feedback(P * Cd, 1), timepts=H * np.arange(K), inputs=r).outputs
    np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5)
    assert 0.9 < y[-1] < 1.1 and np.ptp(y) > 0.9


def test_a_pi_in_state_space_form_is_pid_back_calculation_float64():
    """A = 1, B = h Ki, C = 1, D = Kp, K_aw = h Kb is PID's back-calculation (hold=False): in a saturated
    loop over a lossy uplink, the two loops' actions and states agree to float64 rounding."""
    Kp, Ki, Kb, lo, hi = 3.0, 4.0, 2.0, -1.0, 1.0
    with jax.enable_x64(True):
        f = lambda v: np.asarray(v, np.float64)
        ref = refs.Step(f([2.0]), time=f([0.2]))
        lin = nc.LinearController(A=f([[1.0]]), B=f([[H * Ki]]), C=f([[1.0]]), D=f([[Kp]]), K_aw=f([[H * Kb]]),
                                  u_min=f([lo]), u_max=f([hi]), reference=ref)
        pid = nc.PID(Kp=f([Kp]), Ki=f([Ki]), Kb=f([Kb]), u_min=f([lo]), u_max=f([hi]), reference=ref,
                     anti_windup="back_calculation", hold=False)
        up = nc.Link(nc.Bernoulli(0.3))
        a, b = (jax.device_get(jax.jit(nc.simulate)(_servo_loop(c, uplink=up), jax.random.PRNGKey(1)))
                for c in (lin, pid))
    ua, ub = np.asarray(a.u)[:, 0], np.asarray(b.u)[:, 0]
    assert ua.max() == hi and np.any(ua < hi)                 # saturated, then not
    np.testing.assert_allclose(ua, ub, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.x), np.asarray(b.x), rtol=1e-12, atol=1e-12)


def _reference_run(A, B, C, D, Kaw, lo, hi, ys, rs):
    """The module docstring's equations in float64 Python: u_k from y_k and r_k."""
    x, us = np.zeros(A.shape[0]), []
    for y, r in zip(ys, rs):
        e = r - y
        v = C @ x + D @ e
        u = np.clip(v, lo, hi)
        x = A @ x + B @ e + Kaw @ (u - v)
        us.append(u)
    return np.asarray(us)


def test_a_two_state_compensator_on_a_lossy_loop_equals_its_equations():
    """A second-order compensator (a PI with a lag, two states) at N = 2 over an uplink losing 40 %
    (Passthrough holds the last measurement): the actions equal the equations driven by the run's own
    measurements, to float32 rounding."""
    A = np.array([[1.0, 0.0], [0.05, 0.8]], np.float32)
    B = np.array([[0.2], [0.1]], np.float32)
    C = np.array([[0.5, 1.5]], np.float32)
    D = np.array([[2.0]], np.float32)
    Kaw = np.array([[0.3], [0.0]], np.float32)
    ref = refs.Sine(amplitude=0.5, frequency=0.2, offset=0.3)
    ctrl = nc.LinearController(A=A, B=B, C=C, D=D, K_aw=Kaw, u_min=-2.0, u_max=2.0, reference=ref)
    loop = _servo_loop(ctrl, uplink=nc.Link(nc.Bernoulli(0.4)), N=2, T=H / 2, steps=200)
    tr = jax.device_get(jax.jit(nc.simulate)(loop, jax.random.PRNGKey(4)))
    assert 0.3 < np.mean(np.asarray(tr.recv_sc)) < 0.9
    # what the estimator output at each slow instant: the last delivered measurement (0 before any)
    fresh, z = np.asarray(tr.recv_sc) > 0.5, np.asarray(tr.z[:, 0], np.float64)
    held, ys = 0.0, []
    for k in range(len(fresh)):
        held = z[k] if fresh[k] else held
        ys.append([held])
    rs = np.asarray(refs.evaluate(ref, loop.steps, loop.T), np.float64)[::2]
    u = _reference_run(*(m.astype(np.float64) for m in (A, B, C, D, Kaw)), -2.0, 2.0, np.asarray(ys), rs)
    assert np.abs(u).max() == 2.0
    np.testing.assert_allclose(np.asarray(tr.u)[::2], u, rtol=1e-5, atol=1e-5)


def test_the_matrices_are_differentiable_leaves():
    """d(mean squared tracking error)/dD through the loop equals central differences."""
    loop = _servo_loop(nc.LinearController(A=[[0.9]], B=[[0.1]], C=[[1.0]], D=[[2.0]],
                                           reference=refs.Step(1.0)), steps=40)

    def cost(d):
        x = nc.simulate(dataclasses.replace(loop, controller=dataclasses.replace(loop.controller, D=d)),
                        jax.random.PRNGKey(0)).x[:, 0]
        return jnp.mean((x - 1.0) ** 2)

    d0, eps = jnp.asarray([[2.0]]), 1e-2
    g = jax.jit(jax.grad(cost))(d0)
    fd = (cost(d0 + eps) - cost(d0 - eps)) / (2 * eps)
    assert abs(float(fd)) > 1e-3
    np.testing.assert_allclose(float(g[0, 0]), float(fd), rtol=2e-2)


def test_a_compensator_designed_for_another_period_or_with_the_wrong_size_is_refused():
    ctrl = nc.LinearController.from_control(control.tf([1.0, 1.0], [0.1, 1.0]), 2 * H)
    with pytest.raises(ValueError, match="LinearController.dt"):
        _servo_loop(ctrl)                                              # the loop runs at H
    _servo_loop(ctrl, N=2)                                            # N T = 2 H: accepted
    two = nc.LinearController(A=[[0.5]], B=[[1.0]], C=[[1.0], [1.0]], D=[[0.0], [0.0]])
    with pytest.raises(ValueError, match="Loop.controller"):
        _servo_loop(two)                                              # 2 actions, 1 plant input
    with pytest.raises(ValueError, match="LinearController.index"):
        _servo_loop(nc.LinearController(A=[[0.5]], B=[[1.0]], C=[[1.0]], index=5))


def _freq(ctrl, w):
    """C (e^{jwh} I - A)^-1 B + D of a SISO compensator, in complex128 from its stored matrices."""
    z = np.exp(1j * w * ctrl.dt)
    A, B, C, D = (np.asarray(m, np.float64) for m in (ctrl.A, ctrl.B, ctrl.C, ctrl.D))
    return (C @ np.linalg.solve(z * np.eye(A.shape[0]) - A, B) + D).item()


def test_a_prewarped_tustin_notch_keeps_its_centre():
    """A notch (s^2 + w0^2) / (s^2 + 2 zeta w0 s + w0^2) at 10 Hz, h = 10 ms. Tustin maps s = j w to
    z = e^{j (2/h) atan(w h / 2) h}: the plain notch moves to 60.9 rad/s and passes 11 % at w0; prewarped at
    w0 (s = (w0 / tan(w0 h / 2)) (z - 1) / (z + 1)) it maps s = j w0 to z = e^{j w0 h} exactly, zero gain there
    (prewarp_frequency could not be passed: it went to LinearController and failed with a TypeError)."""
    w0, zeta, h = 2 * np.pi * 10, 0.3, 0.01
    notch = control.tf([1.0, 0.0, w0 ** 2], [1.0, 2 * zeta * w0, w0 ** 2])
    plain = nc.LinearController.from_control(notch, h)
    warped = nc.LinearController.from_control(notch, h, prewarp_frequency=w0)
    w_plain = (2 / h) * np.arctan(w0 * h / 2)
    assert abs(_freq(plain, w_plain)) < 1e-5 and abs(_freq(plain, w0)) > 0.1
    assert abs(_freq(warped, w0)) < 1e-5
    assert abs(_freq(warped, 0.0) - 1.0) < 1e-5                      # unit DC gain, as the continuous notch
    with pytest.raises(ValueError, match="prewarp_frequency applies to method='tustin'"):
        nc.LinearController.from_control(notch, h, method="zoh", prewarp_frequency=w0)
    with pytest.raises(ValueError, match=r"prewarp_frequency must be in \(0, 314"):
        nc.LinearController.from_control(notch, h, prewarp_frequency=np.pi / h)


def test_from_control_under_x64_keeps_float64():
    """A lag (s + 0.1) / (s + 0.01), DC gain 10, Tustin at h = 1 ms: its pole 0.99999 rounded to float32
    gave a DC gain of 9.9877 under x64 too (from_control cast to float32 always); under x64 the
    matrices are now float64 (DC gain 10 to 1e-9, the class computes in float64), float32 without."""
    lag = control.tf([1.0, 0.1], [1.0, 0.01])
    with jax.enable_x64(True):
        c64 = nc.LinearController.from_control(lag, 1e-3)
        assert c64.A.dtype == np.float64 and c64.dtype == jnp.float64
        assert abs(_freq(c64, 0.0) - 10.0) < 1e-9
    c32 = nc.LinearController.from_control(lag, 1e-3)
    assert c32.A.dtype == np.float32 and c32.dtype == jnp.float32


def test_from_control_keeps_python_controls_float64_matrices_under_x64():
    """Under jax_enable_x64, from_control's matrices are python-control's float64 c2d ones and the
    compensator computes in float64 (as LinearController given float64 arrays); otherwise float32.
    It used to store float32 always (the lead's pole 0.6 became 0.60000002384)."""
    lead = control.tf([4.0, 8.0], [0.1, 1.0])
    Cd = control.ss(control.c2d(control.ss(lead), H, "tustin"))
    with jax.enable_x64(True):
        ctrl = nc.LinearController.from_control(lead, H)
        assert ctrl.dtype == jnp.float64
        for name in ("A", "B", "C", "D"):
            np.testing.assert_array_equal(getattr(ctrl, name), getattr(Cd, name))
        state, packet, _ = ctrl.step(ctrl.init(_Ctx()), jnp.asarray([0.25]), 1.0, jnp.int32(0), _Ctx())
        np.testing.assert_array_equal(packet.data[0], Cd.D @ [-0.25])       # e = 0 - 0.25, x_c = 0
        np.testing.assert_array_equal(state, Cd.B @ [-0.25])
    with jax.enable_x64(False):
        assert nc.LinearController.from_control(lead, H).dtype == jnp.float32


class _Ctx:
    N, T = 1, H
