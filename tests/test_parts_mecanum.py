"""Library parts seed 000 uses, against closed forms: the round-trip delay model
(:class:`jaxnc.loop.RoundTrip`) and the runner's draws of the Mecanum loop (noise scales,
first exchange delivered, loss rates)."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import loop as nc
from jaxnc.network import quantise_delay
from jaxnc.plants.mecanum import MecanumNoise
from jaxnc.schemes import mecanum as mec

T = 0.1
n = 20_000


def _hypoexp_cdf(x, a, b):
    """P(a E1 + b E2 <= x) for independent standard exponentials, a != b."""
    return 1.0 - (a * np.exp(-x / a) - b * np.exp(-x / b)) / (a - b)


@pytest.mark.parametrize("phi_f, phi_b", [(0.02, 0.05), (0.03, 0.03)])
def test_round_trip_is_the_sum_of_both_directions(phi_f, phi_b):
    """seconds = (eta_f + phi_f E1) + (eta_b + phi_b E2): its CDF is the hypoexponential's
    (Erlang-2 when phi_f = phi_b), checked at several points within 5 binomial SEs; steps
    are the seconds quantised up."""
    eta_f, eta_b = 0.01, 0.02
    rt = nc.RoundTrip(nc.ShiftedExponential(eta_f, phi_f), nc.ShiftedExponential(eta_b, phi_b))
    steps, sec = jax.jit(lambda k: rt.sample(k, n, T))(jax.random.PRNGKey(0))
    sec, steps = np.asarray(sec, float), np.asarray(steps)
    np.testing.assert_array_equal(steps, np.asarray(quantise_delay(jnp.asarray(sec, jnp.float32), T)))
    x = sec - eta_f - eta_b
    assert x.min() >= -1e-6
    for q in (0.02, 0.05, 0.1, 0.2):
        if phi_f == phi_b:
            F = 1.0 - math.exp(-q / phi_f) * (1 + q / phi_f)
        else:
            F = _hypoexp_cdf(q, phi_f, phi_b)
        se = math.sqrt(F * (1 - F) / n)
        assert abs(np.mean(x <= q) - F) <= 5 * se + 1e-12, q


def test_round_trip_bounds_hold_for_the_draws():
    """bounds(T): lo never above a drawn delay; hi the sum of the parts' (None: unbounded)."""
    rt = nc.RoundTrip(nc.ShiftedExponential(0.15, 0.02), nc.ShiftedExponential(0.12, 0.0))
    lo, hi = rt.bounds(T)
    steps, _ = rt.sample(jax.random.PRNGKey(1), 2000, T)
    assert hi is None and 0 < lo <= int(np.min(steps))
    fixed = nc.RoundTrip(nc.NoDelay(), nc.NoDelay())
    assert fixed.bounds(T) == (0, 0)


def test_round_trip_loses_a_packet_lost_in_either_direction():
    """A part whose draw is negative (a recorded loss) loses the packet; the others are the
    quantised sum (they were all delivered: a lost packet's 0 s were added as a delay)."""
    fw, bk = nc.TraceDelay(steps=[-1, 2, -1, 0, 1]), nc.TraceDelay(steps=[3, -1, -1, 0, 2])
    steps, seconds = nc.RoundTrip(fw, bk).sample(jax.random.PRNGKey(0), 5, T)
    np.testing.assert_array_equal(np.asarray(steps), [-1, -1, -1, 0, 3])
    np.testing.assert_allclose(np.asarray(seconds), [0.0, 0.0, 0.0, 0.0, 3 * T], rtol=1e-6)
    steps, _ = nc.RoundTrip(fw, nc.ShiftedExponential(0.0, 0.0)).sample(jax.random.PRNGKey(0), 5, T)
    np.testing.assert_array_equal(np.asarray(steps), [-1, 2, -1, 0, 1])


@pytest.mark.parametrize("a, b", [(3, 4), (1, 6), (2, 5)])
def test_a_round_trip_of_whole_periods_is_kept_up_to_tau_max_as_one_law_of_the_sum(a, b):
    """Two laws in whole fast periods (``in_steps``), a + b = 7 periods, tau_max = 7 T: every
    packet is delivered 7 periods late, as a PmfDelay of 7 periods is, and the declared bounds
    are (7, 7). (nx3: compared in float32 seconds, 3 T + 4 T > 0.7 and every packet was
    discarded; the lower bound 6 let an EKF(buffer=1) at N = 1 behind a 1 + 1 period round trip
    run without ever correcting.)"""
    rt = nc.RoundTrip(nc.PmfDelay([0.0] * a + [1.0]), nc.PmfDelay([0.0] * b + [1.0]))
    assert rt.in_steps and rt.bounds(T) == (7, 7)
    for delay in (rt, nc.PmfDelay([0.0] * 7 + [1.0])):
        d = nc.draw_link(nc.Link(delay=delay, tau_max=7 * T, capacity=9), jax.random.PRNGKey(0), 50, T)
        np.testing.assert_array_equal(np.asarray(d.delay), np.full(50, 7))
    assert not nc.RoundTrip(nc.PmfDelay([0.0, 1.0]), nc.ShiftedExponential(0.1, 0.0)).in_steps


def test_round_trip_refuses_a_non_delay_model():
    with pytest.raises(ValueError, match="RoundTrip.back"):
        nc.RoundTrip(nc.NoDelay(), 0.02)


def test_link_with_round_trip_discards_late_packets_at_the_closed_form_rate():
    """A downlink with Bernoulli(p) loss, a round-trip delay and tau_max: the fraction of
    packets marked -1 is 1 - (1 - p) P(tau <= tau_max) (Erlang-2 for equal phi) within 5
    SEs, and the first packet is delivered (reliable_first)."""
    p, eta, phi, tau_max = 0.3, 0.01, 0.02, 0.05
    link = nc.Link(loss=nc.Bernoulli(p), delay=nc.RoundTrip(nc.ShiftedExponential(eta, phi),
                                                            nc.ShiftedExponential(eta, phi)),
                   tau_max=tau_max, reliable_first=True, capacity=2)
    d = np.asarray(jax.jit(lambda k: nc.draw_link(link, k, n, T))(jax.random.PRNGKey(2)).delay)
    q = tau_max - 2 * eta
    ok = (1 - p) * (1.0 - math.exp(-q / phi) * (1 + q / phi))
    assert d[0] >= 0
    assert abs(np.mean(d[1:] < 0) - (1 - ok)) <= 5 * math.sqrt(ok * (1 - ok) / n)
    assert d.max() <= 1                          # tau_max = T/2: never beyond one period


def test_mecanum_loop_draws_scale_the_robots_noise_and_deliver_the_first_exchange():
    """The runner's draws of the seed-000 loop: process / measurement noise with the
    robot's std (sample std within 5 % on a few thousand draws), first packet of both
    links delivered, uplink loss rate DP within 5 SEs."""
    noise = MecanumNoise(omega=0.3, xy=0.004, dist=0.05)
    loop = mec.mecanum_loop("DRH", 10, 0.4, noise=noise, horizon_s=20.0, sparse=False)
    assert isinstance(loop.downlink.delay, nc.RoundTrip)
    np.testing.assert_array_equal(loop.plant.w_std, noise.process_std())
    np.testing.assert_array_equal(loop.plant.v_std, noise.measurement_std())
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    d = jax.jit(jax.vmap(lambda k: nc.draw(loop, k)))(keys)
    w = np.asarray(d.w).reshape(-1, d.w.shape[-1])
    v = np.asarray(d.v).reshape(-1, d.v.shape[-1])
    np.testing.assert_allclose(w.std(axis=0), noise.process_std(), rtol=0.05)
    np.testing.assert_allclose(v.std(axis=0), noise.measurement_std(), rtol=0.1)
    up, down = np.asarray(d.uplink.delay), np.asarray(d.downlink.delay)
    assert np.all(up[:, 0] >= 0) and np.all(down[:, 0] >= 0)
    lost = np.mean(up[:, 1:] < 0)
    m = up[:, 1:].size
    assert abs(lost - 0.4) <= 5 * math.sqrt(0.4 * 0.6 / m)


def test_path_follower_takes_gains_as_lists():
    """PathFollower's Kp, Ki as Python lists (one per loop: Vx, Vy, W) act as the same arrays
    (a list failed in the trace: 'list' * tracer); the follower's first output by hand: at
    rest at the start of a straight line with V_ref along it, the PI's first action is
    (Kp + Ki Ts) V_ref on Vx, through eq. (9)."""
    from jaxnc.controllers.path_following import PathFollower
    from jaxnc.paths import from_waypoints
    from jaxnc.plants.mecanum import Mecanum, inverse_kinematics
    line = from_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), "line", ds=0.01)
    plant = Mecanum()
    a = PathFollower(line, Kp=[0.2, 0.3, 0.4], Ki=(6.0, 5.0, 4.0))
    b = PathFollower(line, Kp=np.asarray([0.2, 0.3, 0.4], np.float32), Ki=np.asarray([6.0, 5.0, 4.0], np.float32))
    mean = jnp.zeros(6)
    ua, _ = jax.jit(lambda f: f(plant, mean, f.init(), 0.1))(a)
    ub, _ = jax.jit(lambda f: f(plant, mean, f.init(), 0.1))(b)
    np.testing.assert_array_equal(np.asarray(ua), np.asarray(ub))
    want = inverse_kinematics(plant, jnp.asarray([(0.2 + 6.0 * 0.1) * 0.2, 0.0, 0.0]))
    np.testing.assert_allclose(np.asarray(ua), np.asarray(want), rtol=1e-5)
