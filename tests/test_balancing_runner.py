"""Seed 001 on the one runner (jaxnc.loop) against the hand-written loops it replaced.

The reference is the old scheme, kept verbatim in tests/legacy/balancing_legacy.py. Both
are compiled with jit and replay the same traces and noise; the comparisons are exact
(the same float32 operations in the same order). The old scheme had a white tilt noise
and a filtered derivative in the emulation design (tau_d = 5 ms; tau_d = 0, the simple
difference, as an option). Since issue 23 the defaults are the complementary-filter
sensor and the simple difference (docs/balancing.md), so both loops get the white-sensor
plant ``WHITE`` (the former plant; the old loop takes its measurement from the plant)
and the new one the old one's derivative by name (``new_kw``). The one intended
difference: the old emulation loop read the held measurement / command from a ring of the last ``ring``
steps by index, clipped to the ring, so after an outage longer than ``ring - 1`` steps it
used ``y_{k - ring + 1}`` (``u_{k - ring + 1}``) instead of holding the last arrival. The
new loop holds it (eq. 5); the old loop is compared up to the first such step, and
``test_emulation_holds_through_a_long_outage`` checks the hold.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnc import wifi
from jaxnc.plants.balancing import Balancing
from jaxnc.schemes import balancing as bal
from tests.legacy import balancing_legacy as legacy

HORIZON, T_STEP = 2.0, 1.0        # s: short runs with the reference step inside
SEEDS = (0, 1)
WHITE = Balancing(tilt_sensor="white")     # the legacy loops' sensor
CASES = [("model", {}), ("model", dict(hold=False)), ("model", dict(gain="lqr", lead=3, N_buf=5)),
         ("emulation", {}), ("emulation", dict(tau_d=0.0))]


def new_kw(design, kw):
    """The new loop's arguments for the legacy loop's ``kw``: the white sensor, and the
    emulation design's derivative named (legacy ``tau_d = 0`` is the simple difference)."""
    kw = dict(kw, plant=WHITE)
    if design == "emulation":
        tau = kw.pop("tau_d", 0.005)
        kw.update(dict(derivative="simple") if tau == 0 else dict(derivative="filtered", tau_d=tau))
    return kw

_old_sim, _new_sim = jax.jit(legacy.simulate), jax.jit(bal.simulate)


def _first_stale(trace, ring):
    """First step at which the old emulation loop's ring index was clipped (len if none)."""
    na = np.asarray(wifi.newest_arrival(trace, max_delay=ring - 1))
    k = np.arange(na.size)
    bad = np.where((na >= 0) & (k - na > ring - 1))[0]
    return int(bad[0]) if bad.size else na.size


@pytest.mark.parametrize("severity", tuple(bal.SEVERITIES))
@pytest.mark.parametrize("design,kw", CASES, ids=[f"{d}-{'-'.join(f'{a}={b}' for a, b in k.items()) or 'default'}"
                                                  for d, k in CASES])
def test_runner_loop_equals_the_hand_written_loop(severity, design, kw):
    ch = bal.SEVERITIES[severity]
    old_cfg = legacy.balancing_loop(design, ca=ch, horizon_s=HORIZON, t_step=T_STEP, plant=WHITE, **kw)
    new_cfg = bal.balancing_loop(design, ca=ch, horizon_s=HORIZON, t_step=T_STEP, **new_kw(design, kw))
    for s in SEEDS:
        key = jax.random.PRNGKey(s)
        sc, ca = bal.traces(key, ch, ch, new_cfg.steps)
        nk = jax.random.fold_in(key, 2)
        a, b = _old_sim(old_cfg, sc, ca, nk), _new_sim(new_cfg, sc, ca, nk)
        k0 = new_cfg.steps
        if design == "emulation":
            k0 = min(_first_stale(sc, old_cfg.ring), _first_stale(ca, old_cfg.ring))
        np.testing.assert_array_equal(np.asarray(b.x)[: k0 + 1], np.asarray(a.x)[: k0 + 1])
        np.testing.assert_array_equal(np.asarray(b.u)[:k0, 0], np.asarray(a.u)[:k0])
        np.testing.assert_array_equal(np.asarray(b.xhat)[:k0], np.asarray(a.xhat)[:k0])
        if k0 == new_cfg.steps:
            assert bool(b.failed) == bool(a.fallen)
            for old_m, new_m in zip(legacy.metrics(old_cfg, a), bal.metrics(new_cfg, b)):
                np.testing.assert_array_equal(np.asarray(new_m), np.asarray(old_m))


def test_equal_on_a_full_run_with_the_step_and_a_run_that_falls():
    """25 s (the experiment's horizon, step at 15 s), and a blackout that makes both fall."""
    key = jax.random.PRNGKey(5)
    for design in bal.DESIGNS:
        old_cfg = legacy.balancing_loop(design, plant=WHITE)
        new_cfg = bal.balancing_loop(design, **new_kw(design, {}))
        sc, ca = bal.traces(key, wifi.NOMINAL, wifi.NOMINAL, new_cfg.steps)
        if design == "emulation":             # the nominal channel has no outage of a ring's length
            assert _first_stale(sc, old_cfg.ring) == _first_stale(ca, old_cfg.ring) == new_cfg.steps
        nk = jax.random.fold_in(key, 2)
        a, b = _old_sim(old_cfg, sc, ca, nk), _new_sim(new_cfg, sc, ca, nk)
        np.testing.assert_array_equal(np.asarray(b.x), np.asarray(a.x))
        np.testing.assert_array_equal(np.asarray(b.u)[:, 0], np.asarray(a.u))
        for old_m, new_m in zip(legacy.metrics(old_cfg, a), bal.metrics(new_cfg, b)):
            np.testing.assert_array_equal(np.asarray(new_m), np.asarray(old_m))
    old_cfg = legacy.balancing_loop("model", horizon_s=1.0, plant=WHITE)
    new_cfg = bal.balancing_loop("model", horizon_s=1.0, plant=WHITE)
    lost = np.full(new_cfg.steps, wifi.LOST, np.int32)
    a, b = _old_sim(old_cfg, lost, lost, key), _new_sim(new_cfg, lost, lost, key)
    assert bool(a.fallen) and bool(b.failed)
    np.testing.assert_array_equal(np.asarray(b.x), np.asarray(a.x))          # frozen at the same state
    assert int(b.fail_step) < new_cfg.steps


def test_emulation_holds_through_a_long_outage():
    """eq. 5: with no packet for 60 steps the observer holds the last arrived measurement
    (its rates decay by a = exp(-Ts / tau_d) per step) and the actuator the last command."""
    cfg = bal.balancing_loop("emulation", horizon_s=0.4, derivative="filtered")
    K = cfg.steps
    sc = np.ones(K, np.int32)
    ca = np.ones(K, np.int32)
    sc[100:160] = wifi.LOST                   # packets 100..159 lost: 99 arrives at 100, 160 at 161
    ca[200:260] = wifi.LOST
    tr = _new_sim(cfg, sc, ca, jax.random.PRNGKey(0))
    z, xhat, u = np.asarray(tr.z), np.asarray(tr.xhat), np.asarray(tr.u)[:, 0]
    np.testing.assert_array_equal(xhat[100:161, :2], np.broadcast_to(z[99], (61, 2)))
    assert not np.array_equal(xhat[161, :2], z[99])
    a = np.float32(np.exp(-cfg.T / 0.005))
    np.testing.assert_allclose(xhat[101:161, 2:], a * xhat[100:160, 2:], rtol=1e-6)
    np.testing.assert_array_equal(u[200:261], np.full(61, u[200]))    # command sent at 199, held
    assert u[261] != u[200]


def test_model_actuator_applies_the_command_stamped_k_only_if_in_time():
    """theta_k^k: the command for k, sent at k - lead, is applied iff its delay <= lead;
    otherwise the last applied one is held (or zero); 0 in the first lead steps."""
    for hold in (True, False):
        cfg = bal.balancing_loop("model", horizon_s=0.2, hold=hold)
        K, lead = cfg.steps, cfg.controller.lead
        ca = np.asarray(jax.random.randint(jax.random.PRNGKey(2), (K,), -1, 5), np.int32)   # -1 lost .. 4
        sc = np.ones(K, np.int32)
        tr = _new_sim(cfg, sc, ca, jax.random.PRNGKey(1))
        u = np.asarray(tr.u)[:, 0]
        # the commands the controller sent, from a run in which every command is in time
        ref = _new_sim(cfg, sc, np.zeros(K, np.int32), jax.random.PRNGKey(1))
        assert np.all(u[:lead] == 0.0)
        ok = (ca >= 0) & (ca <= lead)
        assert not ok[: K - lead].all()
        first_late = lead + int(np.argmin(ok[: K - lead]))
        np.testing.assert_array_equal(u[:first_late], np.asarray(ref.u)[:first_late, 0])
        expect = u[first_late - 1] if hold else 0.0
        assert u[first_late] == expect
