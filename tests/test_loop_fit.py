"""The shape contract of a Loop (issue 33): parts that do not fit each other are refused
when the Loop is built, with a message naming the part, the field and both sizes; none of
these reaches a JAX error inside tracing or a silently wrong run."""
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


def _f_int(x, u, w):
    return (x > 0).astype(jnp.int32)


def _f_tuple(x, u, w):
    return x, x


def _f_complex(x, u, w):
    return x * (1 + 1j)


def _h_half(x, v):
    return (x[:1] + v).astype(jnp.float16)


def _f(x, u, w):
    return x + w


def _h(x, v):
    return x[:1] + v


def _discrete(**kw):
    return nc.Discrete(**{**dict(x0=[0.0, 0.0], w_std=0.0, v_std=0.0, f=_f, h=_h, input_dim=1, noise_dim=2,
                                 output_dim=1), **kw})


_MODEL3 = nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=np.eye(2), T=0.1)       # two outputs


def _cost_vector(x, u):
    return jnp.sum(x, axis=0)


CASES = [
    # an EKF re-running its window on a ring too short for it
    (lambda: _loop(estimator=nc.EKF(_PLANT, Q=np.eye(2), R=np.eye(1), mean0=[0.0, 0.0], cov0=np.eye(2), buffer=2),
                   uplink=nc.Link(capacity=2)), "EKF.buffer=2 re-runs 2 slow periods"),
    # a minimum delay that outlives the ring (no tau_max)
    (lambda: _loop(uplink=nc.Link(delay=nc.ShiftedExponential(eta=0.5), capacity=2)),
     "Loop.uplink.capacity must be >= 6: every packet is delayed at least 5"),
    # vectors longer than the signal they apply to
    (lambda: _loop(trigger=nc.Petc(sigma=[0.1, 0.1, 0.1])), "Loop.trigger.sigma has shape (3,)"),
    (lambda: _loop(trigger=nc.Petc(delta=[0.1, 0.1], reading="each")), "Loop.trigger.delta has shape (2,)"),
    (lambda: _loop(controller_trigger=nc.Petc(sigma=[0.1, 0.2])), "Loop.controller_trigger.sigma has shape (2,)"),
    # the loop's period and the plant's
    (lambda: _loop(T=0.05), "Loop.T (0.05 s) must equal the plant's step period (LTI.step_period = 0.1 s)"),
    (lambda: _loop(plant=nc.Continuous(x0=[0.0, 0.0], w_std=0.0, v_std=0.0, f=_f, h=_h, input_dim=1, noise_dim=2,
                                       output_dim=1, T=0.02)), "must equal the plant's step period"),
    # a state that is not a vector, dynamics of the wrong type
    (lambda: _discrete(x0=[[0.0], [1.0]]), "Discrete.x0 must be a vector"),
    (lambda: _discrete(f=_f_int), "f(x, u, w) must return float32 values"),
    (lambda: _discrete(f=_f_tuple), "f(x, u, w) must return one array"),
    (lambda: _discrete(f=_f_complex), "f(x, u, w) must return float32 values"),
    (lambda: _discrete(h=_h_half), "h(x, v) must return float32 values"),
    # a cost that cannot be computed from what is recorded, or is not a scalar
    (lambda: _loop(cost=nc.Quadratic(Q=[1.0, 1.0], R=[0.1]), record=("u",)), "Loop.cost needs the signals x and u"),
    (lambda: _loop(cost=_cost_vector), "Loop.cost must return a scalar"),
    # sizes of the parts' fields against the loop's
    (lambda: _loop(monitor=nc.Monitor(bounds=[1.0, 1.0, 1.0])), "Loop.monitor.bounds has shape (3,)"),
    (lambda: _loop(cost=nc.Quadratic(Q=np.eye(3), R=[0.1])), "Loop.cost.Q has shape (3, 3)"),
    (lambda: _loop(cost=nc.Quadratic(Q=[1.0, 1.0], R=[0.1, 0.1])), "Loop.cost.R has shape (2,)"),
    (lambda: _loop(cost=nc.Quadratic(Q=[1.0, 1.0], R=[0.1], x_ref=[0.0, 0.0, 0.0])), "Loop.cost.x_ref has shape (3,)"),
    (lambda: _loop(controller=nc.StateFeedback(K=[[1.0, 0.5, 0.1]])), "Loop.controller.K has shape (1, 3)"),
    (lambda: _loop(controller=nc.StateFeedback(K=[[1.0, 0.5]], x_ref=[0.0, 0.0, 1.0])),
     "Loop.controller.x_ref has shape (3,)"),
    (lambda: _loop(controller=nc.StateFeedback(K=[[1.0, 0.5]], u_min=[-1.0, -1.0])), "Loop.controller.u_min has shape (2,)"),
    (lambda: _loop(estimator=nc.Passthrough(z0=[0.0, 0.0]), controller=nc.StateFeedback(K=[[1.0]])),
     "Loop.estimator.z0 has shape (2,)"),
    # an estimator's model that does not take the plant's actions or give its measurements
    (lambda: _loop(estimator=nc.EKF(_MODEL3, Q=np.eye(2), R=np.eye(2), mean0=[0.0, 0.0], cov0=np.eye(2))),
     "EKF.model takes 1 inputs and gives 2 outputs, the plant takes 1 and gives 1"),
    # a predictive law for another state size
    (lambda: _loop(controller=nc.Predictive(nc.StateFeedback(K=[[1.0, 0.5, 0.2]]), _PLANT, horizon=2),
                   actuator=nc.PacketActuator(horizon=2)), "Loop.controller cannot act on the estimator's estimate"),
    # loss and delay parameters are single numbers
    (lambda: nc.Bernoulli(p=[0.1, 0.2]), "Bernoulli.p must be a single number"),
    (lambda: nc.ShiftedExponential(eta=[0.1, 0.2]), "ShiftedExponential.eta must be a single number"),
    (lambda: nc.GilbertElliott(p_gb=[0.1, 0.1]), "GilbertElliott.p_gb must be a single number"),
    (lambda: nc.TruncatedExponential(eta=0.0, phi=[0.1, 0.1], tau_max=0.5), "TruncatedExponential.phi must be a single"),
    (lambda: nc.Link(tau_max=[0.1, 0.2]), "Link.tau_max must be a single number"),
    (lambda: nc.Petc(max_silence=[1, 2]), "Petc.max_silence"),
    # records
    (lambda: _loop(record=("x", "plant")), "Loop.record must be True, False, a tuple of names"),
    (lambda: nc.Record(estimator=3), "Record.estimator must be"),
]


@pytest.mark.parametrize("call, fragment", CASES)
def test_parts_that_do_not_fit_are_refused_when_the_loop_is_built(call, fragment):
    with pytest.raises(ValueError) as e:
        call()
    assert fragment in str(e.value), str(e.value)


def test_a_numpy_period_is_accepted_and_matching_periods_build():
    loop = _loop(T=np.float32(0.1))
    assert isinstance(loop.T, float) and loop.T == pytest.approx(0.1)
    _loop(plant=nc.LTI(A=np.eye(2), B=[[0.0], [1.0]], C=[[1.0, 0.0]]))          # no T of its own: the loop's
    _loop(trigger=nc.Petc(sigma=[0.1], delta=0.2))                                 # one output: (1,) fits


def test_a_state_that_changes_shape_between_steps_is_named():
    class Growing(nc.Passthrough):
        def correct(self, state, inbox, k):
            z, _, w = inbox.newest()
            return PassthroughState(jnp.concatenate([state.z, z])), state.z

    with pytest.raises(ValueError, match=r"Loop.estimator's correct returns a state of float32\[2\], but its init "
                                         r"gave float32\[1\]"):
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
