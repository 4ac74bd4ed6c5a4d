"""The direct cart-pole baseline of benchmarks/ computes the runner's run (issue 32): a
speed ratio against it means something only if the arithmetic is the same."""
import pathlib
import sys

import jax
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))

from benchmarks.direct_cartpole import direct_cost  # noqa: E402
from examples.cartpole import cartpole  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402


def test_direct_baseline_equals_the_runner_on_the_same_draws():
    loop = cartpole()
    keys = montecarlo.seed_keys(3, 16)
    # the runner's run through the 16-seed program tests/test_cartpole_example.py and the
    # build-your-own-loop notebook compile for this loop (one program for the suite)
    ours = np.asarray(montecarlo.run_batched(nc.run_seed, keys, args=(loop,), chunk_size=16, progress=False).cost)
    direct = np.asarray(jax.jit(jax.vmap(lambda k: direct_cost(loop, k)))(keys))
    assert np.all(np.isfinite(ours)) or np.any(np.isinf(ours))
    np.testing.assert_array_equal(np.isinf(direct), np.isinf(ours))
    ok = np.isfinite(ours)
    assert ok.sum() >= 8
    np.testing.assert_allclose(direct[ok], ours[ok], rtol=2e-4)


def test_servo_baselines_equal_the_runner_on_the_same_draws():
    """The issue-32 servo: the runner, the direct loop on the library's kernels and the
    hand-written one (closed-form scalar filter) give the same cost seed by seed."""
    from benchmarks.direct_servo import direct_cost as servo_direct, hand_cost, servo
    loop = servo(steps=400)
    keys = montecarlo.seed_keys(5, 16)
    ours = np.asarray(jax.jit(jax.vmap(lambda k: nc.run(loop, k).cost))(keys))
    assert np.all(np.isfinite(ours))
    for fn in (servo_direct, hand_cost):
        other = np.asarray(jax.jit(jax.vmap(lambda k: fn(loop, k)))(keys))
        np.testing.assert_allclose(other, ours, rtol=1e-4)
    # the runs differ from seed to seed (the draws reach the cost)
    assert np.ptp(ours) > 1e-3 * np.mean(ours)
