"""Model-based dual-rate design (seed 004, eq. 21-22, 28-31) against the paper, closed forms
and python-control / scipy references."""
import math

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from jaxnc.design import (DiscreteSS, DualRateController, c2d_zoh, closed_loop, dualrate_design, pi_controller,
                          single_rate_pi)

K_M, TAU_M = 0.1276, 0.1235          # eq. (26)
KP, TI, T, N = 6.0, 0.12, 0.1, 2     # section 5.1


def _gp():
    return control.tf([K_M], [TAU_M, 1.0])


def _coef(sys):
    num, den = control.tfdata(sys)
    return np.trim_zeros(np.asarray(num[0][0], float), "f"), np.asarray(den[0][0], float)


def _half_ulp(printed: str) -> float:
    """Half a unit in the last printed digit: the rounding error of a printed coefficient."""
    dec = len(printed.split(".")[1]) if "." in printed else 0
    return 0.5 * 10.0 ** (-dec) + 1e-12


@pytest.fixture(scope="module")
def design():
    return dualrate_design(_gp(), pi_controller(KP, TI), T, N)


def test_g1_matches_eq28(design):
    num, den = design.coefficients()["G1"]
    paper_num, paper_den = ["1", "-0.4734", "0.05731"], ["1", "-1.191", "0.1914"]
    for ours, txt in zip(np.concatenate([num, den]), paper_num + paper_den):
        assert abs(ours - float(txt)) <= _half_ulp(txt), (ours, txt)
    # integral action: G1 has a pole at z = 1 because M(0) = 1
    assert abs(np.polyval(den, 1.0)) < 1e-9


def test_g2_matches_eq29_up_to_a_transposed_digit(design):
    num, den = design.coefficients()["G2"]
    for ours, txt in zip(num, ["6.576", "-5.78", "1.27"]):
        assert abs(ours - float(txt)) <= _half_ulp(txt), (ours, txt)
    assert den[0] == 1.0
    assert abs(den[2] - 0.2394) <= _half_ulp("0.2394")
    # The paper prints -0.9578 z.  Since G_p^T has no zero, G2's denominator is M^T's,
    # z^2 - (e^{p1 T} + e^{p2 T}) z + e^{(p1 + p2) T} with p1,2 the poles of M(s): closed form.
    p = np.roots(_coef(design.M)[1])
    assert abs(den[1] + np.real(np.exp(p[0] * T) + np.exp(p[1] * T))) < 1e-9
    assert abs(den[2] - np.real(np.exp((p[0] + p[1]) * T))) < 1e-9
    assert abs(den[1] - (-0.9758)) <= _half_ulp("0.9758")   # ours: -0.9758, a transposition of 0.9578
    assert abs(den[1] - (-0.9578)) > 0.01


def test_discretisations_against_scipy_and_closed_form(design):
    # G_p^T: g (1 - a) / (z - a), a = exp(-T / tau)
    a = math.exp(-T / TAU_M)
    num, den = _coef(design.GpT)
    np.testing.assert_allclose(num, [K_M * (1 - a)], rtol=1e-12)
    np.testing.assert_allclose(den, [1.0, -a], rtol=1e-12)
    mn, md = _coef(design.M)
    for sys, Ts in ((design.MT, T), (design.MNT, N * T)):
        bn, bd, _ = scipy.signal.cont2discrete((mn, md), Ts, method="zoh")
        bn = np.trim_zeros(np.asarray(bn).ravel(), "f")
        n, d = _coef(sys)
        np.testing.assert_allclose(d, bd / bd[0], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(n, bn / bd[0], rtol=1e-8, atol=1e-12)
    # M(s) = C Gp / (1 + C Gp) with C = Kp (Ti s + 1) / (Ti s)
    ref = control.feedback(pi_controller(KP, TI) * _gp(), 1)
    w = np.logspace(-1, 2, 7)
    np.testing.assert_allclose(design.M(1j * w), ref(1j * w), rtol=1e-10)


def test_single_rate_eq30_eq31():
    for Ts, paper in ((T, ([6.0, -1.0], [1.0, -1.0])), (N * T, ([6.0, 4.0], [1.0, -1.0]))):
        num, den = _coef(single_rate_pi(KP, TI, Ts))
        np.testing.assert_allclose(num, paper[0], atol=1e-12)
        np.testing.assert_allclose(den, paper[1], atol=1e-12)


def test_discrete_ss_matches_forced_response(design):
    ss = DiscreteSS.from_tf(design.G2)
    e = np.random.default_rng(0).normal(size=40)

    @jax.jit
    def run(e):
        def body(x, ek):
            y, x = ss.step(x, ek)
            return x, y
        return jax.lax.scan(body, ss.init(), e)[1]

    ref = control.forced_response(design.G2, U=e).outputs
    # float32 coefficients and arithmetic; the filter's gain is ~7, so ~1e-5 absolute
    np.testing.assert_allclose(np.asarray(run(jnp.asarray(e, jnp.float32))), ref, atol=2e-5 * np.max(np.abs(ref)))


def _dual_rate_step(design, n_slow):
    """Closed loop of DualRateController with the exact plant G_p^T: slow-instant outputs for r = 1."""
    ctrl = DualRateController.from_design(design)
    plant = DiscreteSS.from_tf(design.GpT)

    @jax.jit
    def run():
        def slow(c, _):
            xp, cs = c
            y = jnp.sum(plant.C * xp)             # strictly proper: D = 0
            us, cs = ctrl(cs, 1.0 - y)
            for j in range(design.N):
                _, xp = plant.step(xp, us[j])
            return (xp, cs), (y, us)
        return jax.lax.scan(slow, (plant.init(), ctrl.init()), None, length=n_slow)[1]

    y, us = run()
    return np.asarray(y), np.asarray(us).reshape(-1)


def test_dual_rate_loop_reproduces_M_at_slow_instants(design):
    """G2 Gp^T = M^T, held input over NT -> M^{NT}; G1 closes it to M^{NT} (Salt & Albertos)."""
    y, _ = _dual_rate_step(design, 30)
    ref = control.step_response(design.MNT, T=np.arange(30) * N * T).outputs
    np.testing.assert_allclose(y, ref, atol=1e-4)
    assert abs(y[-1] - 1.0) < 1e-3          # integral action: zero steady-state error


def test_dual_rate_at_N1_is_the_single_rate_loop():
    """At N = 1 the cascade G1 G2 is one controller at T and the loop is exactly the
    single-rate loop with it (python-control feedback), whose closed loop is M^T."""
    d1 = dualrate_design(_gp(), pi_controller(KP, TI), T, 1)
    y, u = _dual_rate_step(d1, 40)
    C = d1.G1 * d1.G2
    loop = control.feedback(C * d1.GpT, 1)
    t = np.arange(40) * T
    np.testing.assert_allclose(y, control.step_response(loop, T=t).outputs, atol=1e-4)
    np.testing.assert_allclose(y, control.step_response(d1.MT, T=t).outputs, atol=1e-4)
    u_ref = control.step_response(control.feedback(C, d1.GpT), T=t).outputs
    np.testing.assert_allclose(u, u_ref, atol=1e-4 * np.max(np.abs(u_ref)))


def test_design_rejects_unstable_inverse():
    # ZOH of 1/(s+1)^3 has a sampling zero outside the unit circle: G2 would be unstable
    with pytest.raises(ValueError, match="outside the unit circle"):
        dualrate_design(control.tf([1.0], [1.0, 3.0, 3.0, 1.0]), pi_controller(1.0, 1.0), 0.1, 2)
    with pytest.raises(ValueError, match="Kp"):
        pi_controller(-1.0, 0.1)
    with pytest.raises(ValueError, match="N must be"):
        dualrate_design(_gp(), pi_controller(KP, TI), T, 0)


def _lifted_loop_matrix(design, A, B, C):
    """float64 map of the dual-rate loop over one slow period, state [x_plant, x_G1, x_G2], r = 0:
    the plant (A, B, C) at T, G1 on the error at NT, its output held, G2 N times on it."""
    def ss(tf):
        s = control.tf2ss(tf)
        return [np.asarray(a, float) for a in (s.A, s.B, s.C, s.D)]
    (A1, B1, C1, D1), (A2, B2, C2, D2) = ss(design.G1), ss(design.G2)
    n, n1 = A.shape[0], A1.shape[0]

    def period(v):
        x, x1, x2 = v[:n], v[n:n + n1], v[n + n1:]
        e = -(C @ x)
        u1 = C1 @ x1 + D1 @ e
        x1 = A1 @ x1 + B1 @ e
        for _ in range(design.N):
            u = C2 @ x2 + D2 @ u1
            x2 = A2 @ x2 + B2 @ u1
            x = A @ x + B @ u
        return np.concatenate([x, x1, x2])
    size = n + n1 + A2.shape[0]
    return np.stack([period(e) for e in np.eye(size)], 1)


def test_design_of_a_stable_plant_has_a_stable_lifted_loop(design):
    """The eigenvalues of the lifted loop: M^{NT}'s poles and the cancelled G_p^T zeros' and
    poles' N-th powers, all inside the unit circle for the paper's stable motor."""
    s = control.ss(design.GpT)
    Phi = _lifted_loop_matrix(design, np.asarray(s.A, float), np.asarray(s.B, float), np.asarray(s.C, float))
    ev = np.linalg.eigvals(Phi)
    assert np.max(np.abs(ev)) < 1.0
    for p in control.poles(design.MNT):                    # the designed closed loop is in there
        assert np.min(np.abs(ev - p)) < 1e-6


@pytest.mark.parametrize("gp", [control.tf([1.0], [1.0, -1.0]),            # unstable: hidden eigenvalue e^{NT}
                                control.tf([2.0], [0.5, 1.0, 0.0])],        # integrator: hidden eigenvalue 1
                         ids=["unstable", "integrator"])
def test_design_refuses_plants_whose_poles_G2_would_cancel(gp):
    """G2 = M^T / G_p^T cancels G_p^T's poles; for a pole on or outside the unit circle the
    lifted loop keeps it as an eigenvalue (computed here on the design the module returned
    before it refused them), so the reference-to-output map looks like M^{NT} while the loop
    is internally unstable. The design must refuse such a plant, naming Gp."""
    with pytest.raises(ValueError, match="Gp must be stable"):
        dualrate_design(gp, pi_controller(3.0, 0.8), 0.05, 4)


def test_hidden_mode_of_a_cancelled_unstable_pole_is_real():
    """Why the refusal: the same algebra as the design (M, its ZOH, G1, G2) for 1/(s - 1)
    gives a lifted loop with the eigenvalue e^{N T} of the plant's pole."""
    from jaxnc.design.dualrate import DualRateDesign, _num_den, _tf
    gp, T_, N_ = control.tf([1.0], [1.0, -1.0]), 0.05, 4
    M = closed_loop(gp, pi_controller(3.0, 0.8))
    MT, MNT, GpT = c2d_zoh(M, T_), c2d_zoh(M, N_ * T_), c2d_zoh(gp, T_)
    mn, md = _num_den(MNT)
    (tn, td), (pn, pd) = _num_den(MT), _num_den(GpT)
    d = DualRateDesign(M=M, MT=MT, MNT=MNT, GpT=GpT, G1=_tf(md, np.polysub(md, mn), N_ * T_),
                       G2=_tf(np.polymul(tn, pd), np.polymul(td, pn), T_), T=T_, N=N_)
    s = control.ss(GpT)
    ev = np.linalg.eigvals(_lifted_loop_matrix(d, np.asarray(s.A, float), np.asarray(s.B, float),
                                               np.asarray(s.C, float)))
    assert np.min(np.abs(ev - np.exp(N_ * T_))) < 1e-6 and np.max(np.abs(ev)) > 1.2


def test_controller_refuses_N_that_is_not_the_ratio_of_its_periods(design):
    g1, g2 = DiscreteSS.from_tf(design.G1), DiscreteSS.from_tf(design.G2)
    assert DualRateController(g1, g2, N=N).N == N
    with pytest.raises(ValueError, match="DualRateController.N must be G1's period over G2's"):
        DualRateController(g1, g2, N=N + 1)


def test_closed_loop_helpers():
    M = closed_loop(_gp(), pi_controller(KP, TI))
    assert abs(M(0) - 1.0) < 1e-12
    Md = c2d_zoh(M, 0.2)
    assert Md.dt == 0.2


def test_controller_takes_a_float64_error_under_x64(design):
    """Under x64 an error computed in float64 (r - y with NumPy numbers) made G2's state float64
    inside the controller's scan over the N fast periods: a carry type error. It computes in the
    state's dtype (float32 from init) and gives the float32 call's actions."""
    ctrl = DualRateController.from_design(design)
    ref, _ = ctrl(ctrl.init(), 1.0)
    with jax.enable_x64(True):
        for e in (np.float64(1.0), jnp.float64(1.0)):
            us, state = ctrl(ctrl.init(), e)
            assert us.dtype == jnp.float32 and state.g2.dtype == jnp.float32
            np.testing.assert_array_equal(np.asarray(us), np.asarray(ref))
