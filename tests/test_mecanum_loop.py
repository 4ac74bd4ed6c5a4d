"""Closed loops of seed 000 (SR, DR, DRH, DRHE): determinism, tracking, gradients, errors."""
import dataclasses

import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.plants.mecanum import MecanumNoise
from jaxnc.schemes import mecanum as mec

SHORT = 8.0  # s of simulated time for the quick tests
# The short-run tests share one compiled program (the cold suite's cost is its compilations):
# the whole trajectory (full record) of loops of this N, the loop an argument with uniform
# dtypes, in chunks of this many lanes. The behaviours they check do not depend on N > 2.
N_SHORT, CHUNK = 4, 16


def _traj(key, loop):                 # module level, the loop an argument: one program per N
    return nc.simulate(loop, key)


def short_runs(case, keys, **kw):
    """Trajectories (numpy, leading seed axis) of ``keys`` on ``case`` at N_SHORT over SHORT s."""
    loop = mec.mecanum_loop(case, N_SHORT, kw.pop("dp", 0.0), horizon_s=SHORT, full=True, **kw)
    return montecarlo.run_batched(_traj, keys, args=(montecarlo.uniform_dtypes(loop),), chunk_size=CHUNK, progress=False)


def test_seed_is_bit_identical_alone_and_in_a_batch_of_100():
    keys = montecarlo.seed_keys(3, 100)
    batch = short_runs("DRHE", keys, dp=0.3, sigma=0.0)           # 7 chunks, the last padded
    alone = short_runs("DRHE", keys[7:8], dp=0.3, sigma=0.0)
    for a, b in zip(jax.tree.leaves(batch), jax.tree.leaves(alone)):
        np.testing.assert_array_equal(a[7], b[0])
    assert not np.array_equal(batch.x[7], batch.x[8])   # different seeds differ


def test_noise_free_nominal_loop_tracks_the_path():
    from experiments.mecanum import run_seed     # the grid experiment's program for N = 1
    loop = mec.mecanum_loop("SR", 1, 0.0, path="turn180", noise=MecanumNoise().scaled(0.0))
    m = jax.tree.map(lambda a: a[0], montecarlo.run_batched(run_seed, jax.random.PRNGKey(0)[None],
                                                            args=(montecarlo.uniform_dtypes(loop),), chunk_size=CHUNK,
                                                            progress=False))
    assert not bool(m.unstable)
    assert float(m.J1) < 0.03          # mean distance to the path, m
    assert float(m.J2) < 0.10
    nominal_time = float(loop.monitor.path.length) / 0.2
    # finishing within end_tol of the end and cutting the turn save a little time
    assert nominal_time - 2.0 < float(m.J3) < 1.3 * nominal_time


def test_every_case_dp_h_and_max_silence_of_one_N_share_one_compiled_program():
    """The grid experiment's premise: the case, DP, h and max_silence are leaves, so loops of
    one N (passed as arguments, uniform dtypes) trace once; another N traces again. (Traced,
    not compiled: jit compiles one program per trace, and the compilations are the cost.)"""
    traces = []

    @jax.jit
    def run(loop, key):
        traces.append(1)
        return mec.run(loop, key).l

    key = jax.random.PRNGKey(0)
    kw = dict(path="turn180", horizon_s=1.0)
    loops = [mec.mecanum_loop(c, 2, dp, **kw) for c in mec.CASES for dp in (0.0, 0.4)]
    loops += [mec.mecanum_loop("DRHE", 2, 0.2, h=7, max_silence=3, **kw)]
    for loop in loops:
        run.trace(montecarlo.uniform_dtypes(loop), key)
    assert len(traces) == 1
    run.trace(montecarlo.uniform_dtypes(mec.mecanum_loop("DR", 5, 0.0, **kw)), key)
    assert len(traces) == 2


def test_dr_and_drh_coincide_without_dropouts():
    """Section 4.3: 'except when DP = 0, since both approaches coincide' -- exactly so
    without delay (with delay DRH also bridges the first fast periods of each NT with
    predicted actions where DR holds its last one)."""
    keys = jax.random.PRNGKey(1)[None]
    a = short_runs("DR", keys, eta=0.0, phi=0.0)
    b = short_runs("DRH", keys, h=3, eta=0.0, phi=0.0)
    np.testing.assert_allclose(a.x, b.x, atol=1e-5)


def test_single_rate_holds_each_action_for_NT():
    u = np.asarray(short_runs("SR", jax.random.PRNGKey(2)[None]).u[0])
    # actions change at most once per NT (the delay shifts the instant, not the rate)
    changes = np.flatnonzero(np.any(np.diff(u, axis=0) != 0, axis=1))
    assert len(changes) > 1
    assert len(changes) <= len(u) // N_SHORT + 1
    assert np.all(np.diff(changes) >= N_SHORT)


def _unstable(key, loop):
    return mec.run(loop, key).unstable


def test_transmissions_J4_ordering():
    keys = montecarlo.seed_keys(0, 8)
    rate = {}
    for case in ("SR", "DRH", "DRHE"):
        tr = short_runs(case, keys)
        rate[case] = tr.sent_sc.sum(axis=1).mean() / tr.u.shape[1]      # packets per fast period
    assert rate["SR"] == pytest.approx(1 / N_SHORT)   # one packet per NT
    assert rate["DRH"] == pytest.approx(1 / N_SHORT)  # one packet (a chain of actions) per NT
    assert rate["DRHE"] < rate["DRH"]                 # events save transmissions


def test_paper_qualitative_stability_at_N6_DP02():
    """Acceptance: at N = 6, DP = 0.2 SR is unstable (most runs) while DRH is stable."""
    keys = montecarlo.seed_keys(0, 16)
    res = {}
    for case in ("SR", "DRH"):                 # one program for both (the case is a leaf)
        loop = mec.mecanum_loop(case, 6, 0.2)
        res[case] = montecarlo.run_batched(_unstable, keys, args=(montecarlo.uniform_dtypes(loop),), chunk_size=16,
                                           progress=False)
    assert res["SR"].mean() > 0.5
    assert res["DRH"].mean() == 0.0


def test_gradients_of_mean_J1_are_finite():
    """d J1/d(Kp) and d/d(delta) (J1: the mean distance, eq. 21) through the straight-through
    trigger, on a completed run; the fixed-horizon smooth objective's gradient is checked the
    same way in test_jacobian_grad_false_same_run_close_gradient. One seed, not a vmapped
    batch: tracing the gradient (the test's cost once its program is cached) takes half as
    long; a batch's gradient through this loop is what notebooks/autotuning.ipynb's tuner takes."""
    base = mec.mecanum_loop("DRHE", 2, 0.2, path="turn180", sigma=0.0, trigger_temperature=0.05)
    key = montecarlo.seed_keys(0, 1)[0]

    def cost(kp, delta):
        loop = mec.with_follower(dataclasses.replace(base, trigger=dataclasses.replace(base.trigger, delta=delta)),
                                 Kp=kp)
        return mec.run(loop, key).J1

    # one program for the value and the gradient
    value, (g_kp, g_delta) = jax.jit(jax.value_and_grad(cost, argnums=(0, 1)))(jnp.full(3, 0.2), jnp.full(9, 0.1))
    assert np.isfinite(float(value))                  # the run completed
    assert np.all(np.isfinite(g_kp)) and np.all(np.isfinite(g_delta))
    assert np.any(g_kp != 0) and np.any(g_delta != 0)


@pytest.mark.parametrize("kw, name", [
    (dict(case="XX"), "case"),
    (dict(N=0), "N"),
    (dict(dp=1.0), "dp"),
    (dict(dp=-0.1), "dp"),
    (dict(h=0), "h"),
    (dict(sigma=[0.1, 0.2]), "sigma"),
    (dict(delta=-0.1), "delta"),
    (dict(N=2, tau_max=0.5), "tau_max"),
])
def test_bad_configuration_names_the_parameter(kw, name):
    args = dict(case="DRHE", N=2, dp=0.1) | kw
    with pytest.raises(ValueError, match=name):
        mec.mecanum_loop(**args)


def test_default_horizon_rule():
    n = 37
    assert mec.default_h("DR", 10, 0.5, n) == 1
    assert mec.default_h("DRH", 10, 0.0, n) == 1
    h = mec.default_h("DRH", 10, 0.5, n)
    q = 0.75
    # the longest run of silent slow periods reaches h with probability <= 5 %
    assert 1 - np.exp(-n * (1 - q) * q ** (h - 1)) <= 0.05 + 1e-9
    assert mec.default_h("DRHE", 10, 0.0, n) * 10 >= 100


def test_time_triggered_safety_condition_bounds_sensor_silence():
    """With thresholds the sensor never crosses, eq. 4 alone sends only the first sample;
    max_silence = 5 makes it send every 5th slow period."""
    keys = jax.random.PRNGKey(4)[None]
    silent = short_runs("DRHE", keys, sigma=0.0, delta=1e6).sent_sc[0]
    safe = short_runs("DRHE", keys, sigma=0.0, delta=1e6, max_silence=5).sent_sc[0]
    n = len(safe)
    assert n == round(SHORT / 0.1) // N_SHORT
    assert float(silent.sum()) == 1.0
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(safe)), np.arange(0, n, 5))


def test_jacobian_grad_false_same_run_close_gradient():
    """``jacobian_grad=False``: the simulation is bit-identical and the gradient of the
    smooth objective is an approximation of the exact one (0.3 % on the benchmark's 8 and
    64 seeds, 4.8 % on 512; here, on one seed, 1.3 %, checked at 5 %), not the exact one itself.

    The simulation: the two forward programs lower to the same StableHLO (``stop_gradient``
    lowers to nothing), so they are one compiled program and their runs are identical bit
    for bit; only if they differ are the two runs compiled and compared leaf by leaf. One
    seed, not a vmapped batch: each gradient's trace is half a batch's (the suite's cost)."""
    key = montecarlo.seed_keys(0, 1)[0]
    grads, forward = {}, {}
    for exact in (True, False):
        base = mec.mecanum_loop("DRHE", 2, 0.2, horizon_s=6.0, sigma=0.0, trigger_temperature=0.05,
                                jacobian_grad=exact, full=True)
        forward[exact] = jax.jit(lambda k, base=base: nc.simulate(base, k)).lower(key)
        if not exact and forward[True].as_text(debug_info=False) != forward[False].as_text(debug_info=False):
            for a, b in zip(jax.tree.leaves(forward[True].compile()(key)), jax.tree.leaves(forward[False].compile()(key))):
                np.testing.assert_array_equal(a, b)

        def cost(kp, delta, base=base):
            loop = mec.with_follower(dataclasses.replace(base, trigger=dataclasses.replace(base.trigger, delta=delta)),
                                     Kp=kp)
            return mec.tracking_cost(loop, key)
        # value and gradient: with jacobian_grad the program notebooks/quickstart.ipynb's gradient cell compiles
        # in its quick mode
        _, (g_kp, g_delta) = jax.jit(jax.value_and_grad(cost, argnums=(0, 1)))(jnp.full(3, 0.2), jnp.full(9, 0.1))
        assert np.any(g_kp != 0) and np.any(g_delta != 0)           # both leaves reach the smooth objective
        grads[exact] = np.concatenate([np.ravel(g_kp), np.ravel(g_delta)])
    assert np.all(np.isfinite(grads[True])) and np.all(np.isfinite(grads[False]))
    diff = np.linalg.norm(grads[True] - grads[False]) / np.linalg.norm(grads[True])
    assert 0 < diff < 0.05, diff
