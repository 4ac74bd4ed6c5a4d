"""Tuning a runner loop by naming its leaves (jaxnc.tune.loop_tune)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.tune import Positive
from jaxnc.tune.loop_tune import get_path, is_static, mc_mean, set_paths, tune_loop

A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
C = np.array([[1.0, 0.0]])


def _loop(K=(3.0, 1.5), buffer=0, pmf=(1.0,), delta=1e-3):
    plant = nc.LTI(A=A, B=B, C=C, x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05**2, mean0=[0.0, 0.0], cov0=np.eye(2),
                 buffer=buffer)
    up = nc.Link(nc.Bernoulli(0.2), nc.PmfDelay(list(pmf)), order="all", capacity=5)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=up, estimator=ekf,
                   controller=nc.StateFeedback(np.asarray([K])), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=40, T=0.1)


def test_paths_get_set_and_static():
    lp = _loop()
    assert float(get_path(lp, "trigger.delta")) == pytest.approx(1e-3)
    assert is_static(lp, "estimator.buffer") and not is_static(lp, "controller.K")
    lp2 = set_paths(lp, {"trigger.delta": 0.5, "uplink.loss.p": 0.1})
    assert float(lp2.trigger.delta) == 0.5 and float(lp2.uplink.loss.p) == 0.1 and float(lp.uplink.loss.p) == 0.2


def test_bad_input_is_refused_before_tracing():
    lp = _loop()
    with pytest.raises(ValueError, match=r"'trigger.dleta'.*no field 'dleta'.*fields: sigma, delta"):
        tune_loop(lp, {"trigger.dleta": Positive()})
    with pytest.raises(ValueError, match=r"'estimator.buffer' is static.*search="):
        tune_loop(lp, {"estimator.buffer": Positive()})
    with pytest.raises(ValueError, match=r"steps must be an integer in \[1"):
        tune_loop(lp, {"trigger.delta": Positive()}, steps=0)
    with pytest.raises(ValueError, match="must return a scalar per seed"):
        tune_loop(lp, {"trigger.delta": Positive()}, lambda m: jnp.stack([m.cost_raw, m.rate_sc]))
    with pytest.raises(ValueError, match="attribute path"):
        tune_loop(lp, {"trigger..delta": Positive()})


def test_mc_mean_is_the_vmap_mean_in_value_and_gradient():
    lp = _loop()
    keys = montecarlo.seed_keys(0, 10)

    def f(k_gain, key):
        return nc.run(dataclasses.replace(lp, controller=nc.StateFeedback(k_gain)), key).cost_raw

    K = jnp.asarray([[3.0, 1.5]])
    direct = jax.value_and_grad(lambda g: jnp.mean(jax.vmap(lambda k: f(g, k))(keys)))(K)
    chunked = jax.value_and_grad(lambda g: mc_mean(lambda k: f(g, k), keys, chunk_size=4))(K)   # 3 chunks, padded
    np.testing.assert_allclose(chunked[0], direct[0], rtol=1e-5)
    np.testing.assert_allclose(chunked[1], direct[1], rtol=1e-4, atol=1e-7)


def test_tune_loop_improves_the_gain_on_fresh_seeds():
    """A deliberately sluggish gain is tuned by gradient: the tuned point beats the start on
    fresh seeds with the paired 95 % interval below zero."""
    lp = _loop(K=(0.5, 0.3))
    r = tune_loop(lp, {"controller.K": Positive()}, steps=25, batch=8, learning_rate=0.2, check_seeds=16,
                  eval_seeds=64, progress=False)
    assert r.estimator in ("straight_through", "score") and r.check is not None
    assert r.paired_diff[0] + r.paired_diff[1] < 0, r.summary()
    assert r.params["controller.K"].shape == (1, 2)


def test_search_over_a_static_buffer_length_prefers_using_late_measurements():
    """Measurements arrive 0-3 periods late; a filter buffer of 3 uses them, of 0 drops the
    late ones: successive halving over the static buffer length picks 3."""
    lp = _loop(pmf=(0.2, 0.3, 0.3, 0.2), delta=0.0)
    r = tune_loop(lp, search={"estimator.buffer": [0, 3]}, search_budget=64, eval_seeds=64, progress=False)
    assert r.params["estimator.buffer"] == 3
    assert r.tune is None and r.paired_diff[0] < 0
