"""A plain Python function as a loop's cost (issue 34): static, accepted by run_batched."""
import dataclasses

import jax
import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo


def _mean_square(x, u):
    return (x ** 2).mean() + 0.5 * (u ** 2).mean()


def _loop(cost):
    plant = nc.LTI(A=[[0.9]], B=[[0.1]], C=[[1.0]], x0=[1.0], w_std=0.1)
    return nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(), estimator=nc.Passthrough(),
                   controller=nc.StateFeedback([[1.0]]), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=cost, steps=20)


def test_a_plain_function_is_a_static_cost_and_equals_the_quadratic_through_run_batched():
    keys = montecarlo.seed_keys(0, 8)
    m_fn = montecarlo.run_batched(nc.run_seed, keys, args=(_loop(_mean_square),), progress=False, chunk_size=8)
    m_q = montecarlo.run_batched(nc.run_seed, keys, args=(_loop(nc.Quadratic(Q=[1.0], R=[0.5])),), progress=False,
                                 chunk_size=8)
    np.testing.assert_allclose(m_fn.cost, m_q.cost, rtol=1e-6)
    assert np.all(np.isfinite(m_fn.cost)) and np.ptp(m_fn.cost) > 0     # the noise differs by seed


def test_a_lambda_cost_has_no_leaves_and_the_same_function_shares_the_structure():
    a, b = _loop(lambda x, u: x.sum()), _loop(_mean_square)
    assert not any(callable(v) for v in jax.tree.leaves(a))
    assert jax.tree.structure(b) == jax.tree.structure(_loop(_mean_square))
    assert b.cost.fn is _mean_square
    # jax rebuilding the loop keeps the wrapper (no second wrapping)
    c = jax.tree.map(lambda v: v, b)
    assert c.cost.fn is _mean_square and dataclasses.replace(b, steps=40).cost.fn is _mean_square
