"""Seed 000 on the one runner: jaxnc.schemes.mecanum (a configuration of jaxnc.loop) against
the hand-written loop it replaced (tests/legacy/mecanum_legacy.py), on fixed seeds.

The rebuilt loop evaluates the same operations in the same order on the same draws (the
runner's ``draws=`` carries the hand-written loop's streams bit for bit), so trajectories
and metrics are compared for exact equality; gradients to float32 rounding (see there).
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc.schemes import mecanum as mec
from tests.legacy import mecanum_legacy as legacy

KEYS = jax.random.split(jax.random.PRNGKey(7), 3)


def _batched(mod, fn):
    return jax.jit(jax.vmap(lambda loop, k: getattr(mod, fn)(loop, k), in_axes=(None, 0)))


def _assert_same(a, b):
    for f in a._fields:
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.shape == y.shape, (f, x.shape, y.shape)
        np.testing.assert_array_equal(x, y, err_msg=f)


@pytest.mark.parametrize("N,dp", [(2, 0.2), (5, 0.5)])
def test_every_case_is_bit_identical_to_the_hand_written_loop(N, dp):
    """SR, DR, DRH, DRHE: every Trajectory field (states, estimates, actions, distances,
    sent/received/delivered flags, l, done, bad) and every metric, bit for bit. The case
    and DP are leaves: one compiled program per N for both implementations."""
    old_sim, new_sim = _batched(legacy, "simulate"), _batched(mec, "simulate")
    for case in mec.CASES:
        loop = mec.mecanum_loop(case, N, dp, horizon_s=5.0, max_silence=3 if case == "DRHE" else 0)
        a, b = old_sim(loop, KEYS), new_sim(loop, KEYS)
        _assert_same(a, b)
        ev = jax.vmap(lambda t, loop=loop: mec.evaluate(loop, t))
        _assert_same(ev(a), ev(b))          # J1-J3, transmissions, l, unstable


@pytest.mark.parametrize("N,dp", [(3, 0.4)])
def test_the_metrics_only_run_is_bit_identical_to_the_hand_written_loop(N, dp):
    """``run`` and ``tracking_cost`` record only what the metrics need (build_loop(full=False));
    the metrics and the cost equal the hand-written loop's bit for bit."""
    for case in mec.CASES:
        loop = mec.mecanum_loop(case, N, dp, horizon_s=5.0)
        _assert_same(_batched(legacy, "run")(loop, KEYS), _batched(mec, "run")(loop, KEYS))
        np.testing.assert_array_equal(np.asarray(_batched(legacy, "tracking_cost")(loop, KEYS)),
                                      np.asarray(_batched(mec, "tracking_cost")(loop, KEYS)), err_msg=case)


def test_variants_are_bit_identical():
    """Dense EKF, Jacobians held constant, a paper-sigma trigger, a short tau_max (late
    packets discarded) and a horizon h beyond the default."""
    loops = [mec.mecanum_loop("DRHE", 4, 0.3, horizon_s=5.0, sparse=False),
             mec.mecanum_loop("DRHE", 4, 0.3, horizon_s=5.0, jacobian_grad=False, sigma=mec.PAPER_SIGMA),
             mec.mecanum_loop("DRH", 4, 0.3, horizon_s=5.0, tau_max=0.15, h=7)]
    for loop in loops:
        _assert_same(_batched(legacy, "simulate")(loop, KEYS), _batched(mec, "simulate")(loop, KEYS))


def test_straight_through_gradients_agree():
    """d tracking_cost / d(Kp, delta) through the straight-through trigger: the send
    decision reaches the remote filter, the packet and the actuator with the same weights
    as in the hand-written loop, also at the instants the sensor stays silent."""
    base = mec.mecanum_loop("DRHE", 2, 0.2, horizon_s=4.0, sigma=0.0, trigger_temperature=0.05)

    def cost(mod):
        def f(kp, delta):
            loop = dataclasses.replace(base, follower=dataclasses.replace(base.follower, Kp=kp),
                                       trigger=dataclasses.replace(base.trigger, delta=delta))
            return jnp.mean(jax.vmap(lambda k: mod.tracking_cost(loop, k))(KEYS))
        return jax.jit(jax.grad(f, argnums=(0, 1)))(jnp.full(3, 0.2), jnp.full(9, 0.1))

    # The forward passes are bit-identical; reverse mode adds the same cotangent terms in
    # another order (the belief propagation is its own scan after the fast periods, the
    # actuator's packet weight comes through the link's ring), so the gradients differ by
    # float32 rounding of sums over the run's K = 40 steps: relative 1e-5 observed, 1e-4
    # (a few hundred float32 ulps of accumulation) allowed. A lost gradient path would
    # change them by tens of per cent.
    for g_old, g_new in zip(cost(legacy), cost(mec)):
        g_old, g_new = np.asarray(g_old, np.float64), np.asarray(g_new, np.float64)
        assert np.linalg.norm(g_new - g_old) <= 1e-4 * np.linalg.norm(g_old), (g_old, g_new)


def test_the_scheme_is_a_runner_configuration():
    """build_loop gives a jaxnc.loop.Loop and the scheme module has no loop of its own."""
    import inspect

    from jaxnc.loop import Loop
    assert isinstance(mec.build_loop(mec.mecanum_loop("DR", 2, 0.1, horizon_s=2.0)), Loop)
    assert "lax.scan" not in inspect.getsource(mec)
