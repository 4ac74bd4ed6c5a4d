"""Packet buffer at the smart actuator (seed 000 section 2.4)."""
import numpy as np
import jax
import jax.numpy as jnp

from jaxnc.controllers.actuator import PacketBuffer, current_action, empty_buffer, install


def test_index_by_time_stamp_and_hold_last():
    pkt = PacketBuffer(jnp.arange(5.0)[:, None] * jnp.ones((1, 4)), jnp.int32(10))
    buf = install(empty_buffer(5, 4), pkt, 1.0)
    f = jax.jit(current_action)
    assert float(f(buf, 12)[0]) == 2.0          # t - stamp = 2
    assert float(f(buf, 14)[0]) == 4.0
    assert float(f(buf, 30)[0]) == 4.0          # exhausted: hold the last action


def test_lost_packet_keeps_old_buffer():
    old = install(empty_buffer(3, 4), PacketBuffer(jnp.ones((3, 4)), jnp.int32(0)), 1.0)
    new = PacketBuffer(2 * jnp.ones((3, 4)), jnp.int32(3))
    kept = install(old, new, 0.0)
    np.testing.assert_array_equal(kept.u, old.u)
    assert int(kept.stamp) == 0
    replaced = install(old, new, 1.0)
    np.testing.assert_array_equal(replaced.u, new.u)
    assert int(replaced.stamp) == 3
