"""Actuator and sensor limits (jaxnc.loop.limits) against closed forms and hand-computed
sequences, their gradients, and in a loop."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc

S = jnp.linspace(-3.0, 3.0, 61)


def _apply(lim, s):
    return jax.jit(lambda s: lim.apply(lim.init(s.shape[0], 0.1), s)[1])(s)


def test_stateless_limits_equal_their_closed_forms():
    s = np.asarray(S)
    np.testing.assert_array_equal(_apply(nc.Saturation(-1.0, 2.0), S), np.minimum(np.maximum(s, -1.0), 2.0))
    np.testing.assert_array_equal(_apply(nc.Saturation(high=0.5), S), np.minimum(s, 0.5))
    dz = np.where(s > 1.0, s - 1.0, np.where(s < -0.5, s + 0.5, 0.0))
    np.testing.assert_allclose(_apply(nc.DeadZone(-0.5, 1.0), S), dz, atol=1e-7)
    np.testing.assert_allclose(_apply(nc.Quantizer(0.25), S), 0.25 * np.round(s / 0.25), atol=1e-7)
    # 1.0 / 0.4 = 2.5 rounds half to even, to 2
    np.testing.assert_allclose(_apply(nc.Quantizer(0.4), jnp.asarray([0.19, 0.21, -0.61, 1.0, 1.1])), [0, 0.4, -0.8, 0.8, 1.2],
                               atol=1e-6)


def test_gradients_are_the_almost_everywhere_derivatives_and_straight_through_for_the_quantizer():
    def grad(lim):
        return np.asarray(jax.vmap(jax.grad(lambda x: _apply(lim, x[None])[0]))(S))
    s = np.asarray(S)
    np.testing.assert_array_equal(grad(nc.Saturation(-1.0, 2.0)), ((s > -1.0) & (s < 2.0)).astype(float))
    np.testing.assert_array_equal(grad(nc.DeadZone(-0.5, 1.0)), ((s > 1.0) | (s < -0.5)).astype(float))
    np.testing.assert_array_equal(grad(nc.Quantizer(0.25)), np.ones_like(s))
    # the bounds are leaves: d clip(s, lo, hi) / d hi = 1 where clipped at hi
    g = jax.grad(lambda hi: jnp.sum(nc.Saturation(-1.0, hi).apply((), S)[1]))(2.0)
    assert float(g) == np.sum(s > 2.0)


def test_rate_limit_follows_the_hand_computed_sequence():
    lim = nc.RateLimit(rising=2.0, falling=4.0, initial=0.5)        # T = 0.1: +0.2 / -0.4 per period
    cmd = jnp.asarray([[3.0], [3.0], [0.9], [0.9], [-1.0], [-1.0], [-1.0]])

    def run(cmd):
        def body(st, s):
            st, y = lim.apply(st, s)
            return st, y
        return jax.lax.scan(body, lim.init(1, 0.1), cmd)[1]
    y = np.asarray(jax.jit(run)(cmd))[:, 0]
    np.testing.assert_allclose(y, [0.7, 0.9, 0.9, 0.9, 0.5, 0.1, -0.3], atol=1e-6)


def test_rate_limit_keeps_a_float64_signal_float64_under_x64():
    """init(dim, T, dtype) builds the state in the signal's dtype: under jax_enable_x64 a float64
    command is limited in float64 (state and output), equal to the float64 numpy recursion to
    1e-15, and the scan keeps its carry's type. The state used to be float32 always, so the first
    apply promoted it to float64 and the scan refused the carry (or, outside a scan, rounded
    y_{-1} and the steps to float32)."""
    lim = nc.RateLimit(rising=2.0, falling=4.0, initial=np.float64(1.0 / 3.0))
    cmd = np.asarray([[3.0], [3.0], [0.9], [0.9], [-1.0], [-1.0], [-1.0]]) + 1.0 / 7.0
    want, y = [], 1.0 / 3.0
    for s in cmd[:, 0]:
        y = y + min(max(s - y, -4.0 * 0.1), 2.0 * 0.1)
        want.append(y)
    with jax.enable_x64(True):
        def run(cmd):
            return jax.lax.scan(lambda st, s: lim.apply(st, s), lim.init(1, 0.1, jnp.float64), cmd)
        state, out = jax.jit(run)(jnp.asarray(cmd, jnp.float64))
        assert out.dtype == jnp.float64 and all(a.dtype == jnp.float64 for a in state)
        np.testing.assert_allclose(np.asarray(out)[:, 0], want, rtol=1e-15, atol=0)
        assert all(a.dtype == jnp.float32 for a in lim.init(1, 0.1))      # the default: a loop's float32 actions


def _loop(actuator, plant=None, u=5.0, steps=8):
    plant = plant or nc.LTI(A=[[1.0]], B=[[1.0]], C=[[1.0]], x0=[0.0])
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.Function(jnp.asarray([u]), _const), downlink=nc.Link(), actuator=actuator,
                   T=0.1, steps=steps)


def _const(params, xhat):
    return params


def test_limited_actuator_in_a_loop_saturates_then_rate_limits():
    act = nc.LimitedActuator(nc.HoldLast(), (nc.Saturation(-2.0, 2.0), nc.RateLimit(rising=5.0)))
    tr = jax.jit(nc.simulate)(_loop(act), jax.random.PRNGKey(0))
    u = np.asarray(tr.u)[:, 0]
    np.testing.assert_allclose(u, [0.5, 1.0, 1.5, 2.0, 2.0, 2.0, 2.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(tr.x)[1:, 0], np.cumsum(u)[:-1], atol=1e-5)     # x+ = x + u


def test_limited_actuator_declares_the_inner_horizon_and_the_loop_checks_it():
    """The wrapper's horizon is the inner actuator's declared one (None for one that takes any
    packet); a Loop refuses a wrapped packet actuator whose horizon is not the controller's (1)."""
    sat = nc.Saturation(-1.0, 1.0)
    assert nc.LimitedActuator(nc.PacketActuator(horizon=3), sat).horizon == 3
    assert nc.LimitedActuator(nc.ArrivalHold(), sat).horizon is None and nc.ArrivalHold().horizon is None
    _loop(nc.LimitedActuator(nc.ArrivalHold(), sat))
    with pytest.raises(ValueError, match=r"Loop.actuator.horizon \(3\) must equal the controller's horizon \(1\)"):
        _loop(nc.LimitedActuator(nc.PacketActuator(horizon=3), sat))
    with pytest.raises(ValueError, match=r"Loop.actuator.horizon \(2\)"):
        _loop(nc.ArrivalActuator(horizon=2))


def test_limited_sensor_quantizes_the_measurement():
    inner = nc.LTI(A=[[1.0]], B=[[1.0]], C=[[1.0]], x0=[0.0])
    plant = nc.LimitedSensor(inner, nc.Quantizer(0.5))
    tr = jax.jit(nc.simulate)(_loop(nc.HoldLast(), plant, u=0.3), jax.random.PRNGKey(0))
    x, z = np.asarray(tr.x)[:, 0], np.asarray(tr.z)[:, 0]
    np.testing.assert_allclose(z, 0.5 * np.round(x / 0.5), atol=1e-6)
    assert plant.state_dim == 1 and plant.output_dim == 1 and np.ptp(z) > 0


@pytest.mark.parametrize("build, field", [
    (lambda: nc.Saturation(1.0, 0.0), "Saturation.low"),
    (lambda: nc.DeadZone(1.0, -1.0), "DeadZone.start"),
    (lambda: nc.Quantizer(0.0), "Quantizer.interval"),
    (lambda: nc.RateLimit(rising=-1.0), "RateLimit.rising"),
    (lambda: nc.LimitedActuator(nc.HoldLast(), ()), "LimitedActuator.limits"),
    (lambda: nc.LimitedActuator(nc.HoldLast(), (nc.Saturation(), 3.0)), r"LimitedActuator.limits\[1\]"),
    (lambda: nc.LimitedActuator(nc.Passthrough(), nc.Saturation()), "LimitedActuator.actuator"),
    (lambda: nc.LimitedSensor(nc.LTI(A=[[1.0]], B=[[1.0]], C=[[1.0]]), nc.RateLimit()), r"LimitedSensor.limits\[0\]"),
    (lambda: nc.LimitedSensor(nc.HoldLast(), nc.Quantizer()), "LimitedSensor.plant"),
])
def test_bad_limits_name_the_field(build, field):
    with pytest.raises(ValueError, match=field):
        build()
