"""The shape contract of a Loop (issue 33), beyond the battery of bad inputs in
tests/test_bad_inputs.py (``LOOP_FIT``): what fits is accepted, a state that changes shape
is named, a plain function is a cost, and an allowed but lossy link is visible."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.loop.estimators import PassthroughState

_PLANT = nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]], T=0.1)      # n = 2, m = 1, p = 1
_EKF = nc.EKF(_PLANT, Q=np.eye(2), R=np.eye(1), mean0=[0.0, 0.0], cov0=np.eye(2))


def _loop(**kw):
    base = dict(plant=_PLANT, trigger=nc.Periodic(), uplink=nc.Link(), estimator=_EKF,
                controller=nc.StateFeedback(K=[[1.0, 0.5]]), downlink=nc.Link(), actuator=nc.HoldLast(), T=0.1)
    return nc.Loop(**{**base, **kw})


def test_a_numpy_period_is_accepted_and_matching_periods_build():
    loop = _loop(T=np.float32(0.1))
    assert isinstance(loop.T, float) and loop.T == pytest.approx(0.1)
    _loop(plant=nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]]))          # no T of its own: the loop's
    _loop(trigger=nc.Petc(sigma=[0.1], delta=0.2))                                 # one output: (1,) fits


def test_a_state_that_changes_shape_between_steps_is_named():
    class Growing(nc.Passthrough):
        def correct(self, state, inbox, k):
            z, _, w = inbox.newest()
            return state._replace(z=jnp.concatenate([state.z, z])), state.z

    with pytest.raises(ValueError, match=r"Loop.estimator's correct returns a state of \(float32\[2\], int32\[\]\), "
                                         r"but its init gave \(float32\[1\], int32\[\]\)"):
        _loop(estimator=nc.pytree_dataclass(Growing)(), controller=nc.StateFeedback(K=[[1.0]]))


def _plain_cost(x, u):
    return jnp.mean(x[:, 0] ** 2) + 0.1 * jnp.mean(u[:, 0] ** 2)


def test_a_plain_function_is_a_cost_through_run_batched():
    """``Loop(cost=fn)`` with a plain function (documented as allowed) runs through
    ``run_batched`` and equals the same cost as a Quadratic."""
    from jaxnc import montecarlo
    keys = montecarlo.seed_keys(0, 8)
    plain = _loop(cost=_plain_cost, plant=nc.LTI(A=np.eye(2) * 0.9, B=[[0.0], [1.0]], C=[[1.0, 0.0]], T=0.1,
                                                 x0=[1.0, 0.0], w_std=0.1, v_std=0.1))
    quad = _loop(cost=nc.Quadratic(Q=[1.0, 0.0], R=[0.1]), plant=plain.plant)
    a = montecarlo.run_batched(nc.run_seed, keys, args=(plain,), progress=False)
    b = montecarlo.run_batched(nc.run_seed, keys, args=(quad,), progress=False)
    assert np.all(np.isfinite(a.cost))
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-5)


def test_an_unbounded_delay_without_tau_max_is_allowed_and_said_once():
    """Allowed but visible (issue 33): a delay law with no bound and no tau_max loses the
    packets still in flight when their slot is reused; the Loop warns when built."""
    with pytest.warns(UserWarning, match=r"Loop.uplink: the delay model ShiftedExponential has no bound"):
        _loop(uplink=nc.Link(delay=nc.ShiftedExponential(eta=0.0, phi=0.05), capacity=3))
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _loop(uplink=nc.Link(delay=nc.ShiftedExponential(eta=0.0, phi=0.05), tau_max=0.2, capacity=3))


def test_a_plant_is_traced_once_for_the_loops_that_share_it(monkeypatch):
    """The plant's part of the fit check (its init, state vector, step, noise and measurement,
    traced) runs once per plant and numbers: loops that share a plant (a paper's schemes, the
    MJX robot's costly settling) do not trace it again; a plant with other numbers runs its
    ``init`` again (where a plant may check its numbers)."""
    from jaxnc.loop import runner
    traced = []
    stage = runner._stage
    monkeypatch.setattr(runner, "_stage", lambda name, what, fn: (traced.append((name, what)), stage(name, what, fn))[1])
    plant = nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]], x0=[0.25, 0.0], T=0.1)
    plant_stages = lambda: [w for n, w in traced if n == "Loop.plant"]
    _loop(plant=plant)
    assert "cannot build its initial state" in plant_stages() and any(w.startswith("cannot step") for w in plant_stages())
    traced.clear()
    _loop(plant=plant, controller=nc.StateFeedback(K=[[2.0, 0.5]]), steps=37)     # another loop, the same plant
    assert plant_stages() == []
    _loop(plant=nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]], x0=[0.5, 0.0], T=0.1), steps=37)
    assert plant_stages() == ["cannot build its initial state"]     # new numbers, a checked structure
