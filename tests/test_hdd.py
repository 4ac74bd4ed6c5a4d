"""Seed 003 HDD plant, triggers, metrics and Cases 1-6 (short runs, few seeds)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

from jaxnc import montecarlo
from jaxnc.loop.triggers import petc_gap
from jaxnc.disturbance import dob_design, dob_init, dob_output, dob_update, rigid_nominal
from jaxnc.plants import hdd as plant
from jaxnc.schemes import hdd


def test_plant_matches_transfer_function_and_is_tenth_order():
    """The 10-state realisation equals ZOH(eq. 30, 'sum' reading) x notch(eq. 31) built independently."""
    A, B, C = plant.plant_matrices("sum")
    assert A.shape == (10, 10)
    w = 2 * np.pi * np.array(plant.TABLE2["f_hz"])
    num = np.array([plant.RIGID_NUM])
    den = np.array(plant.RIGID_DEN)
    # rigid * (1 + sum k w^2/(s^2 + 2 zeta w s + w^2)) as one rational function
    d1 = [1, 2 * 0.03 * w[0], w[0] ** 2]
    d2 = [1, 2 * 0.01 * w[1], w[1] ** 2]
    inner_num = np.polyadd(np.polyadd(np.polymul(d1, d2), 0.02 * w[0] ** 2 * np.array(d2)), 0.01 * w[1] ** 2 * np.array(d1))
    Nc = np.polymul(num, inner_num)
    # ZOH is linear: sum over the (distinct) poles of ZOH(r/(s - p)) = r (e^{pT} - 1)/p / (z - e^{pT})
    poles = np.concatenate([np.roots(den), np.roots(d1), np.roots(d2)])
    res = [np.polyval(Nc, p) / np.prod(np.delete(p - poles, i)) for i, p in enumerate(poles)]
    f = np.array([100.0, 1000.0, 4000.0, 7000.0, 12000.0])
    z = np.exp(1j * 2 * np.pi * f * plant.T)
    zoh = sum(r * (np.exp(p * plant.T) - 1) / p / (z - np.exp(p * plant.T)) for r, p in zip(res, poles))
    notch = np.ones_like(z)
    for al, be, wi in zip(plant.TABLE2["alpha"], plant.TABLE2["beta"], w):
        q = 1 / z
        notch *= (1 - 2 * al * np.cos(wi * plant.T) * q + al ** 2 * q ** 2) / (1 - 2 * be * np.cos(wi * plant.T) * q + be ** 2 * q ** 2)
    ref = zoh * notch
    _, G = plant.frequency_response("sum", f)
    np.testing.assert_allclose(G, ref, rtol=1e-6)
    assert np.max(np.abs(np.linalg.eigvals(A))) < 1


def test_literal_reading_scales_dc_gain():
    dc = lambda r: plant.frequency_response(r, [1e-3])[1][0].real
    assert dc("literal") == pytest.approx(dc("unit") * 0.02 * 0.01, rel=1e-6)
    wT = 2 * np.pi * np.array(plant.TABLE2["f_hz"]) * plant.T
    al, be = np.array(plant.TABLE2["alpha"]), np.array(plant.TABLE2["beta"])
    notch_dc = np.prod((1 - 2 * al * np.cos(wT) + al ** 2) / (1 - 2 * be * np.cos(wT) + be ** 2))
    assert dc("unit") == pytest.approx(7.153e6 / 1.011e6 * notch_dc, rel=1e-4)


def test_augmentation_eq3():
    Ap, Bp, Cp = plant.plant_matrices()
    Ad, Bd, Cd = plant.disturbance_matrices()
    A, B, Bw, C, Cbar = plant.augment(Ap, Bp, Cp, Ad, Bd, Cd)
    np.testing.assert_array_equal(A[:10, 10:], np.outer(Bp, Cd))
    np.testing.assert_array_equal(A[10:, :10], 0)
    # scaled disturbance: same d as eq. (32) (Bd * Cd product unchanged)
    np.testing.assert_allclose(Bd[1] * Cd[1], 0.1508e-3 * 1e5)


def test_dob_recovers_constant_disturbance_on_nominal_model():
    num, den = rigid_nominal(plant.T)
    g = num.sum()
    n = 1500
    u = np.random.default_rng(0).normal(size=n) * 0.1
    _, y = scipy.signal.dlsim((np.array([g, 0.0]), den, 1.0), u + 0.3)
    def step(s, uy):
        dh = dob_output(d64, s, uy[1])
        return dob_update(d64, s, uy[0], uy[1]), dh
    with jax.enable_x64(True):
        d64 = dob_design(plant.T, 1000.0, dtype=jnp.float64)
        _, dh = jax.jit(lambda uy: jax.lax.scan(step, dob_init(d64, jnp.float64), uy))(jnp.stack([u, y[:, 0]], 1))
    np.testing.assert_allclose(np.asarray(dh)[-100:], 0.3, rtol=1e-6)


def test_triggers_eq6_eq22():
    """Eq. (6) and (22), ||ybar - y||^2 > sigma ||y||^2 + delta, on one output: the PETC gap."""
    fires = lambda last, s, sigma, delta: bool(petc_gap(jnp.array([last]), jnp.array([s]), sigma, delta) > 0)
    assert fires(1.0, 1.1, 0.0, 0.0099)
    assert not fires(1.0, 1.1, 0.0, 0.0101)
    assert not fires(1.0, 1.1, 1.0, 0.0)     # 0.01 < 1.21
    assert fires(0.0, 0.5, 0.0, 0.2)


def test_metric_formulas():
    y = jnp.array([0.0, 0.5, 1.0])
    assert float(hdd.ise(y, 1.0)) == pytest.approx(np.sqrt(1.25))
    assert float(hdd.isep(y, jnp.array([0.0, 0.0, 1.0]))) == pytest.approx(0.5)
    assert float(hdd.cc(0.54, 1 / 3)) == pytest.approx(0.36)
    assert float(hdd.gpi(0.5, 0.2, 0.1)) == pytest.approx(0.45 * 0.5 + 0.45 * 0.2 + 0.01)


def test_tts_mrci_m1_is_undecomposed_loop():
    """Case 1 with m = 1 is the plant in feedback with eq. (33) (python-control reference)."""
    import control as ct
    loop = hdd.hdd_loop(1, m=1, h=1, steps=300)
    y = np.asarray(jax.jit(hdd.simulate)(loop, jax.random.PRNGKey(0)).y)
    A, B, C = plant.plant_matrices()
    G = ct.ss(A, B.reshape(-1, 1), C.reshape(1, -1), 0, plant.T)
    K = ct.tf(hdd.CD_GAIN * np.poly(hdd.CD_ZEROS), np.poly(hdd.CD_POLES), plant.T)
    _, ref = ct.step_response(ct.feedback(K * G, 1), T=np.arange(300) * plant.T)
    # float32 simulation of a loop with poles at radius 0.99: a few float32 ulps per step, accumulated
    np.testing.assert_allclose(y, ref, atol=300 * 300 * np.finfo(np.float32).eps)


@pytest.fixture(scope="module")
def case_metrics():
    y_tts, ise_tts = hdd.tts_reference()
    cs = hdd.controller_design().cs
    keys = montecarlo.seed_keys(0, 8)
    f = jax.jit(jax.vmap(hdd.run, in_axes=(None, 0, None, None, None)), static_argnums=(4,))
    return {c: jax.device_get(f(hdd.hdd_loop(c), keys, y_tts, ise_tts, cs)) for c in hdd.CASES}, float(ise_tts)


def test_case_orderings(case_metrics):
    """Acceptance of the issue: the paper's qualitative results, 8 seeds (noise-free cases are
    deterministic; cases 4-6 differ by far more than their seed-to-seed spread)."""
    m, ise_tts = case_metrics
    assert 3.5 < ise_tts < 4.5                                       # paper: 3.75
    assert m[1].Uc.mean() == 1.0 and m[1].Ua.mean() == 1.0
    assert m[2].Uc.mean() < 1 and m[2].Ua.mean() < 1 and m[2].NE.mean() > 0
    assert m[3].NE.mean() < m[2].NE.mean() and m[3].Uc.mean() <= m[2].Uc.mean()
    assert m[5].Uc.mean() > m[4].Uc.mean() and m[5].Ua.mean() > m[4].Ua.mean()
    assert m[5].NE.mean() < m[4].NE.mean()
    # Case 6 (DOB, no disturbance model): resources like Case 5 and NE above Case 5's but
    # within 2.5x (docs/hdd.md, finding 2: 1.8x at our disturbance level, 2.9x at the
    # 22x faster one of 2026-11-24; without the DOB 1.3x, so this bound does not single
    # out the DOB)
    assert abs(m[6].Uc.mean() - m[5].Uc.mean()) < 0.1 and abs(m[6].Ua.mean() - m[5].Ua.mean()) < 0.1
    assert m[5].NE.mean() < m[6].NE.mean() < 2.5 * m[5].NE.mean()
    assert not any(bool(np.any(v.unstable)) for v in m.values())


def test_packet_actuator_applies_packet_index():
    """The actuator of the loop (PacketActuator, h + 1 actions) applies
    u_k = packet[clip(k - k_pkt, 0, h)] of the newest packet, zero before the first."""
    import jaxnc.loop as jl
    h, steps = 3, 40
    rng = np.random.default_rng(0)
    gamma = rng.random(steps) < 0.2
    gamma[:3] = False
    packets = rng.normal(size=(steps, h + 1)).astype(np.float32)
    act = jl.PacketActuator(horizon=h + 1)
    ctx = jl.Context(N=1, steps=steps, T=1.0, state_dim=1, input_dim=1, output_dim=1)

    @jax.jit
    def apply(s, pkt, g, k):
        s = act.install(s, pkt[:, None], k, g.astype(jnp.float32))
        return act.output(s, k)

    s = act.init(ctx)
    packet, k_pkt = np.zeros(h + 1, np.float32), 0
    for k in range(steps):
        s, u = apply(s, jnp.asarray(packets[k]), jnp.asarray(gamma[k]), jnp.int32(k))
        if gamma[k]:
            packet, k_pkt = packets[k], k
        assert float(u[0]) == packet[min(max(k - k_pkt, 0), h)]


def test_runner_loop_semantics():
    """Case 4 with the safety condition (eq. 7, k_max = 5): the first sample is sent, the
    sensor is never silent for k_max periods, the controller sends only when it works
    (eq. 21-22 gated by arrivals), N is the gap since the last arrival (eq. 9), dhat and
    yhat exist at arrivals, and 'current' marks the packets' own instants."""
    loop = hdd.hdd_loop(4, h=8, k_max=5, steps=120)
    tr = jax.device_get(jax.jit(hdd.simulate)(loop, jax.random.PRNGKey(3)))
    beta, gamma, N = np.asarray(tr.beta), np.asarray(tr.gamma), np.asarray(tr.N)
    assert beta[0] and not np.any(gamma & ~beta)
    sent = np.flatnonzero(beta)
    assert np.max(np.diff(sent)) <= 5
    np.testing.assert_array_equal(N[sent[1:]], np.diff(sent))
    assert N[0] == 0 and np.all(N[~beta] == 0)
    assert np.all(np.isfinite(tr.dhat[beta])) and np.all(np.isnan(tr.dhat[~beta]))
    assert np.all(np.isfinite(tr.yhat))
    np.testing.assert_array_equal(tr.current[1:], gamma[1:])


def test_controller_side_condition_only_on_arrival():
    """Without an arrival the controller neither sends nor changes state (eq. 21-22 are
    evaluated only when it works; nothing is forced at k = 0)."""
    import jaxnc.loop as jl
    loop = hdd.hdd_loop(2, h=4, thresholds=(1e-7, 1e6), steps=10)
    rl = hdd.runner_loop(loop)
    c, ctx = rl.controller, rl.ctx
    s0 = c.init(ctx)
    step = jax.jit(lambda s, y, f, k: c.step(s, jnp.array([y], jnp.float32), jnp.float32(f), jnp.int32(k), ctx))
    s1, pkt, send = step(s0, 0.0, 1.0, 0)            # arrival, but eq. (22) does not hold
    assert float(send) == 0.0 and float(s1.ubar) == 0.0 and int(s1.k_last) == 0
    s2, pkt, send = step(s1, 0.3, 0.0, 1)            # no arrival
    assert float(send) == 0.0 and int(s2.N) == 0 and np.isnan(float(s2.dhat))
    for a, b in zip(jax.tree_util.tree_leaves((s1.ctrl, s1.ubar, s1.k_last)),
                    jax.tree_util.tree_leaves((s2.ctrl, s2.ubar, s2.k_last))):
        np.testing.assert_array_equal(a, b)
    assert isinstance(rl.actuator, jl.PacketActuator) and rl.actuator.horizon == loop.h + 1


@pytest.fixture(scope="module")
def case3_by_horizon():
    """Case 3 (noise-free, deterministic) at the default whole-run horizon and at the former h = 64."""
    y_tts, ise_tts = hdd.tts_reference()
    cs = hdd.controller_design().cs
    key = jax.random.PRNGKey(0)
    out = {}
    for h in (None, 64):
        loop = hdd.hdd_loop(3, h=h)
        tr = jax.device_get(jax.jit(hdd.simulate)(loop, key))
        out[h] = loop, tr, jax.device_get(jax.jit(hdd.run, static_argnums=(4,))(loop, key, y_tts, ise_tts, cs))
    m2 = jax.device_get(jax.jit(hdd.run, static_argnums=(4,))(hdd.hdd_loop(2), key, y_tts, ise_tts, cs))
    return out, m2, np.asarray(y_tts)


def test_default_horizon_covers_every_gap(case3_by_horizon):
    """Section 3.2.1's rule h >= N_max: by default h = steps - 1, so in Case 3 the longest gap
    between samples is within h and the actuator never runs out of its packet; at the
    former h = 64 it did (the packet is played past its end in the final silence)."""
    out, _, _ = case3_by_horizon
    loop, tr, m = out[None]
    assert loop.h == hdd.STEPS - 1 == hdd.whole_run_horizon()
    assert 0 < int(m.N_max) <= loop.h
    assert int(m.n_held) == 0 and not np.any(tr.held)
    loop64, tr64, m64 = out[64]
    assert int(m64.n_held) > 0
    # where the actuator holds, it applies the previous period's action
    k = np.flatnonzero(tr64.held)
    k = k[k > 0]
    np.testing.assert_array_equal(tr64.u[k], tr64.u[k - 1])


def test_case3_reaches_the_time_triggered_output(case3_by_horizon):
    """Case 3 with the whole-run horizon: with the exact model and no noise the NUMRE's
    predictions are exact, so the actions, and the output, are those of TTS (Case 1) up to
    float32 rounding: NE 0 in exact arithmetic (the paper: 'the desired performance'; the
    issue's bound is NE <= 0.01), with fewer transmissions than Case 2. At the former h = 64
    NE was 0.079 (docs/hdd.md)."""
    out, m2, y_tts = case3_by_horizon
    loop, tr, m = out[None]
    assert float(m.NE) < 1e-3
    # float32 rounding of a loop with poles at radius ~0.99 (as in test_tts_mrci_m1_is_undecomposed_loop)
    np.testing.assert_allclose(tr.y, y_tts, atol=loop.steps ** 2 * np.finfo(np.float32).eps)
    assert float(m.Uc) < float(m2.Uc) and float(m.Ua) < float(m2.Ua)
    assert float(out[64][2].NE) > 0.05


def test_explicit_horizon_is_validated():
    with pytest.raises(ValueError, match="h must be an integer in \\[1, 10000\\]"):
        hdd.hdd_loop(3, h=0)
    with pytest.raises(ValueError, match="k_max must be an integer in \\[0, 20\\]"):
        hdd.hdd_loop(3, h=20, k_max=21)
    assert hdd.hdd_loop(3, steps=50).h == 49


def test_hdd_experiment_writes_figs_10_and_12(tmp_path):
    """The ``hdd`` experiment writes Fig. 10 (Case 4) with the resolved whole-run h in its
    configuration; Fig. 12 (Case 5) is the same function on Case 5's trajectory."""
    import json
    from experiments import hdd as ex
    from jaxnc.experiment import get_experiment
    settings = dict(get_experiment("hdd").defaults(), case="4")
    ex.run(settings, seeds=2, out=tmp_path, progress=False)
    assert (tmp_path / "fig10_case4_disturbance_N.png").stat().st_size > 10_000
    cfg = json.loads((tmp_path / "results.json").read_text())["config"]
    assert cfg["h"] == {"4": hdd.STEPS - 1}
    loop = hdd.hdd_loop(5, steps=120)
    tr = jax.device_get(jax.jit(hdd.simulate)(loop, jax.random.PRNGKey(0)))
    assert np.all(np.isfinite(tr.dpred))
    assert ex.plot_disturbance_n(loop, tr, tmp_path, 5).name == "fig12_case5_disturbance_N.png"
