"""Bit-identity of a seed in every lane of a chunk (run_batched), on the loops of all four
papers and the runner, for chunk sizes that are and are not multiples of the vector width
(montecarlo.LANES): chunk_size 20 (rounded up to 32 lanes, two vector groups) over 40 seeds,
so one compiled program per loop shows the first lane, the first of the second vector group,
the last lane and a lane of the padded second chunk; the runner's loop also at 16 (the runner's
per-seed function and loop are those of the Quadratic-cost test, so its programs at 16 and 20
serve both)."""
import jax
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc import montecarlo


def _runner_loop():
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 0.95]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                   w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([1e-4, 4e-4]), R=np.eye(1) * 0.0025, mean0=[0.0, 0.0], cov0=np.eye(2), buffer=2)
    up = nc.Link(nc.Bernoulli(0.3), nc.PmfDelay([0.5, 0.3, 0.2]), order="all", capacity=4)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=1e-3), uplink=up, estimator=ekf,
                   controller=nc.StateFeedback([[3.0, 1.5]]), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=100, T=0.1)


def _runner_fn(k, lp):
    """nc.run's cost (evaluate of simulate), with the trajectory it is computed on."""
    from jaxnc.loop.runner import evaluate
    t = nc.simulate(lp, k)
    return evaluate(lp, t).cost_raw, t.x, t.u


def _runner():
    return _runner_fn, _runner_loop()


def _mecanum():
    from jaxnc.schemes import mecanum as mec
    return (lambda k, lp: mec.tracking_cost(lp, k)), mec.mecanum_loop("DRHE", N=4, dp=0.5, horizon_s=12.0)


def _hdd():
    from jaxnc.schemes import hdd
    y, ise = hdd.tts_reference(steps=120)
    return (lambda k, lp: hdd.run(lp, k, y_tts=y, ise_tts=ise, cs=0.5).ISEP), hdd.hdd_loop(4, steps=120)


def _balancing():
    from jaxnc.schemes import balancing as bal
    return (lambda k, lp: bal.run(lp, k).tilt_max_deg), bal.balancing_loop("model", horizon_s=0.5)


def _diffdrive():
    from jaxnc.schemes import diffdrive as dd
    return (lambda k, lp: nc.simulate(lp, k).x[-1]), dd.diffdrive_loop("e", horizon_s=4.0)


LOOPS = {"runner": _runner, "mecanum": _mecanum, "hdd": _hdd, "balancing": _balancing, "diffdrive": _diffdrive}


def _check_lanes(name, chunk, n, lanes):
    fn, loop = LOOPS[name]()
    keys = montecarlo.seed_keys(0, n)
    run = lambda ks: [np.asarray(a) for a in jax.tree.leaves(montecarlo.run_batched(fn, ks, args=(loop,),
                                                                                      chunk_size=chunk, progress=False))]
    full = run(keys)
    for i in lanes:
        alone = run(keys[i:i + 1])
        for f, a in zip(full, alone, strict=True):
            np.testing.assert_array_equal(f[i], a[0], err_msg=f"{name}, seed {i} at chunk_size {chunk}")
    for f, r in zip(full, run(keys[::-1]), strict=True):
        np.testing.assert_array_equal(r[::-1], f, err_msg=f"{name}: reversing the seeds changes a seed")


@pytest.mark.parametrize("name", list(LOOPS))
def test_every_lane_is_bit_identical_to_the_seed_alone(name):
    """chunk_size 20 -> 32 lanes; 40 seeds: two chunks, the second padded (8 seeds + 24 copies
    of the last). One program per loop (each loop's costliest part is its compile)."""
    assert montecarlo.chunk_lanes(20, 40, 0) == 32
    _check_lanes(name, 20, 40, (0, 16, 31, 32, 39))


def test_every_lane_is_bit_identical_at_a_chunk_of_one_vector_group():
    """chunk_size = LANES = 16 (a multiple: no rounding), 16 seeds: one chunk, no padding."""
    _check_lanes("runner", 16, 16, (0, 8, 15))


def test_a_quadratic_cost_is_the_same_bits_at_every_lane_count_where_the_trajectory_is():
    """Another chunk size is another compiled program; the runner loop's trajectories (100
    steps) are the same bits at 16, 32 and 48 lanes, and so must be its Quadratic cost
    (jnp.mean over the run's instants rounded differently at 48 lanes than at 32: in 22 of
    these 40 seeds; at 200 steps at 16 lanes, in 26). Checked against the cost summed in
    float64 from the trajectory."""
    fn, loop = _runner()        # nc.run's cost (evaluate of simulate), with the run it is computed on; 100 steps
    assert loop.steps == 100
    keys = montecarlo.seed_keys(0, 40)
    runs = {c: montecarlo.run_batched(fn, keys, args=(loop,), chunk_size=c, progress=False) for c in (16, 20, 48)}
    cost, x, u = (np.asarray(a) for a in runs[20])
    for c in (16, 48):
        np.testing.assert_array_equal(np.asarray(runs[c][1]), x, err_msg=f"trajectories at chunk_size {c}")
        np.testing.assert_array_equal(np.asarray(runs[c][0]), cost, err_msg=f"cost at chunk_size {c}")
    x64, u64 = x.astype(np.float64), u.astype(np.float64)
    ref = np.mean(x64[..., 0] ** 2 + 0.1 * x64[..., 1] ** 2 + 0.01 * u64[..., 0] ** 2, axis=1)
    np.testing.assert_allclose(cost, ref, rtol=5e-7)
