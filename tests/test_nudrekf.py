"""Prediction stage of the NUDREKF (seed 000, section 3.3.1): the lazily advanced
packet chain yields exactly the actions and controller states of the materialised packet."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.controllers.path_following import PathFollower
from jaxnc.estimators.nudrekf import advance_chain, exhausted_chain, predict_horizon, start_chain
from jaxnc.paths import get_path
from jaxnc.plants.mecanum import PROCESS_NOISE_DIM, Mecanum


@pytest.mark.parametrize("hold", [1, 3])
def test_chain_reproduces_predict_horizon(hold):
    plant, fol = Mecanum(), PathFollower(get_path("lissajous"))
    Ts = plant.T * hold
    ctrl = lambda m, c: fol(plant, m, c, Ts)
    nxt = lambda m, c: fol(plant, m, c, Ts, narrow=True)
    H = 12
    mean = jnp.array([0.05, -0.02, 0.1, 0.01, -0.03, 0.2], jnp.float32)
    c0 = fol.init()._replace(integ=jnp.array([0.01, -0.02, 0.03], jnp.float32))

    @jax.jit
    def both():
        _, us, cs = predict_horizon(plant, ctrl, mean, c0, H, hold, PROCESS_NOISE_DIM, nxt)

        def body(ch, _):
            return advance_chain(plant, nxt, ch, H, hold, PROCESS_NOISE_DIM), (ch.u, ch.c_before)
        # H + 5 positions: past the horizon the last action is held
        _, (u_chain, c_chain) = jax.lax.scan(body, start_chain(ctrl, mean, c0), None, length=H + 5)
        return us, cs, u_chain, c_chain

    us, cs, u_chain, c_chain = both()
    np.testing.assert_allclose(u_chain[:H], us, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(u_chain[H:], np.broadcast_to(us[-1], (5, 4)), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(c_chain.idx[:H + 1], cs.idx)
    np.testing.assert_allclose(c_chain.integ[:H + 1], cs.integ, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(c_chain.integ[H + 1:], np.broadcast_to(cs.integ[-1], (4, 3)), rtol=1e-5, atol=1e-6)
    assert not np.allclose(us[0], us[-1])                   # the packet does vary
    if hold > 1:
        np.testing.assert_array_equal(us[1:hold], np.broadcast_to(us[0], (hold - 1, 4)))


def test_exhausted_chain_holds_its_action():
    plant, fol = Mecanum(), PathFollower(get_path("turn180"))
    nxt = lambda m, c: fol(plant, m, c, plant.T, narrow=True)
    u = jnp.array([1.0, 2.0, 3.0, 4.0], jnp.float32)
    ch = exhausted_chain(jnp.zeros(6, jnp.float32), u, fol.init(), 5)
    for _ in range(3):
        ch = advance_chain(plant, nxt, ch, 5, 1, PROCESS_NOISE_DIM)
        np.testing.assert_array_equal(ch.u, u)
        assert int(ch.j) == 5
