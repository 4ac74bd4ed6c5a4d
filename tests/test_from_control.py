"""LTI.from_control: state coordinates kept, realisations chosen, state names carried."""
import dataclasses
import warnings

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.loop import LTI

T = 0.05
# mass-spring-damper in physical coordinates (position, velocity), measured position
AC = np.array([[0.0, 1.0], [-4.0, -0.6]])
BC = np.array([[0.0], [2.0]])
CC = np.array([[1.0, 0.0]])


def _markov(A, B, C, k=8):
    return np.array([C @ np.linalg.matrix_power(A, i) @ B for i in range(k)]).ravel()


def test_state_space_keeps_its_coordinates_and_names():
    sys = control.ss(AC, BC, CC, 0, states=["pos", "vel"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")                       # no warning for a state-space model
        lti = LTI.from_control(sys, T, x0={"pos": 0.3}, w_std={"vel": 0.1}, v_std=0.01)
    ref = LTI.from_continuous(AC, BC, CC, T)                 # the same coordinates, scipy's expm
    np.testing.assert_allclose(lti.A, ref.A, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(lti.B, ref.B, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(lti.C, CC)
    assert lti.state_names == ("pos", "vel")
    np.testing.assert_array_equal(lti.x0, np.float32([0.3, 0.0]))
    np.testing.assert_array_equal(lti.w_std, np.float32([0.0, 0.1]))
    # the names are static: not a leaf, and the plant still compiles and steps
    assert len(jax.tree_util.tree_leaves(lti)) == len(jax.tree_util.tree_leaves(ref))
    x = jax.jit(lambda p: p.dynamics(p.x0, jnp.ones(1), jnp.zeros(2)))(lti)
    np.testing.assert_allclose(np.asarray(x), lti.A @ lti.x0 + lti.B[:, 0], rtol=1e-6)
    # a discrete state-space model is used as it is
    d = control.c2d(sys, T)
    np.testing.assert_array_equal(LTI.from_control(d).A, np.float32(d.A))


def test_transfer_function_warns_and_keeps_the_former_realisation():
    tf = control.tf([2.0], [1.0, 0.6, 4.0])
    with pytest.warns(UserWarning, match="reachable"):
        lti = LTI.from_control(tf, T)
    ref = control.c2d(control.ss(tf), T, "zoh")
    np.testing.assert_allclose(lti.A, ref.A, rtol=1e-6)
    np.testing.assert_allclose(lti.C, ref.C, rtol=1e-6)
    assert lti.state_names is None
    # None is the reachable canonical form, said so in the warning
    tf3 = control.tf([2.0, 1.0], [3.0, 1.0, 0.5, 2.0])
    with pytest.warns(UserWarning):
        default = LTI.from_control(tf3, T)
    reach = LTI.from_control(tf3, T, realization="reachable")
    for name in "ABC":
        np.testing.assert_allclose(getattr(default, name), getattr(reach, name), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("realization", ["observable", "reachable", "Observable"])
def test_transfer_function_realisations(realization):
    """Either canonical form has the transfer function's input-output behaviour (its Markov
    parameters equal those of the physical model discretised); the observable one measures x[0]."""
    tf = control.tf([2.0], [1.0, 0.6, 4.0])                  # = CC (sI - AC)^-1 BC
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lti = LTI.from_control(tf, T, realization=realization)
    phys = LTI.from_continuous(AC, BC, CC, T)
    np.testing.assert_allclose(_markov(lti.A, lti.B, lti.C), _markov(phys.A, phys.B, phys.C), rtol=1e-5, atol=1e-7)
    if realization.lower() == "observable":
        np.testing.assert_array_equal(lti.C, [[1.0, 0.0]])
    assert lti.state_names is None


def test_from_control_bad_inputs():
    tf = control.tf([1.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="realization must be one of observable, reachable"):
        LTI.from_control(tf, T, realization="modal")
    mimo = control.ss(AC, np.eye(2), CC, 0)
    with pytest.raises(ValueError, match="single-input single-output"):
        LTI.from_control(mimo, T, realization="observable")
    sys = control.ss(AC, BC, CC, 0, states=["pos", "vel"])
    with pytest.raises(ValueError, match=r"unknown state\(s\) \['speed'\]"):
        LTI.from_control(sys, T, x0={"speed": 1.0})
    with pytest.raises(ValueError, match="not named"):
        LTI.from_control(tf, T, realization="observable", x0={"x[0]": 1.0})
    with pytest.raises(ValueError, match="state_names must name the 2 states"):
        LTI(A=np.eye(2), B=np.ones((2, 1)), C=np.ones((1, 2)), state_names=("a",))
    with pytest.raises(ValueError, match="distinct strings"):
        LTI(A=np.eye(2), B=np.ones((2, 1)), C=np.ones((1, 2)), state_names=("a", "a"))


def test_from_continuous_against_scipy_and_refuses_a_transposed_B():
    """ZOH of a 3-state, 2-input model equals scipy's cont2discrete. A B given transposed
    (2 x 3 for n = 3) was reshaped into 3 x 2 without an error: a plant with scrambled
    input columns. It is refused now, naming B; a 1-D B of n entries is one input."""
    import scipy.signal
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    B = np.array([[0.0, 1.0], [0.0, 0.0], [1.0, 0.5]])
    C = np.array([[1.0, 0.0, 0.0]])
    Ad, Bd, *_ = scipy.signal.cont2discrete((A, B, C, np.zeros((1, 2))), T, "zoh")
    p = LTI.from_continuous(A, B, C, T)
    np.testing.assert_allclose(p.A, Ad, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(p.B, Bd, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(LTI.from_continuous(A, B[:, 0], C, T).B[:, 0], Bd[:, 0], rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match=r"from_continuous: B must have 3 rows .* got shape \(2, 3\)"):
        LTI.from_continuous(A, B.T, C, T)
    with pytest.raises(ValueError, match=r"from_continuous: A must be square"):
        LTI.from_continuous(A[:2], B, C, T)


def test_a_discrete_model_of_unspecified_period_takes_the_loops():
    """python-control's dt=True (a discrete model, period unspecified) became T = 1 s, and a Loop at
    T = 0.05 s refused the plant ("must equal the plant's step period (... = 1 s)"). Its T is now None
    (the loop's), or the T given."""
    sysd = control.ss([[0.9]], [[1.0]], [[1.0]], 0, dt=True)
    assert LTI.from_control(sysd).T is None
    assert LTI.from_control(sysd, 0.05).T == 0.05
    from jaxnc import loop as nc
    loop = nc.Loop(plant=LTI.from_control(sysd), trigger=nc.Periodic(), uplink=nc.Link(),
                   estimator=nc.Passthrough(), controller=nc.StateFeedback(K=[[0.5]]), downlink=nc.Link(),
                   actuator=nc.HoldLast(), T=0.05, N=1, steps=4)
    x = np.asarray(nc.simulate(dataclasses.replace(loop, plant=dataclasses.replace(loop.plant, x0=[1.0])),
                               jax.random.PRNGKey(0)).x[:, 0])
    np.testing.assert_allclose(x, 0.4 ** np.arange(4), rtol=1e-6)   # x_k from x_0 = 1, x+ = 0.9 x - 0.5 x
