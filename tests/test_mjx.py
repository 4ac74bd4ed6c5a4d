"""The MJX multibody Mecanum platform (issue: a MuJoCo MJX drop-in plant).

Skipped, with the reason, when the optional extra is not installed
(``pip install 'jaxnc[mjx]'``; ``make test`` installs it, so CI runs these).
"""
import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

mjx = pytest.importorskip("mujoco.mjx", reason="MuJoCo MJX not installed: pip install 'jaxnc[mjx]'")

from jaxnc.plants.mecanum import Mecanum, body_velocity, distances  # noqa: E402
from jaxnc.plants.mecanum_mjx import mjx_mecanum  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc.schemes import mecanum as mec  # noqa: E402

SECONDS = 5.0
LANES = 16        # the open-loop tests' lanes: one compiled program serves the three of them


@pytest.fixture(scope="module")
def nominal():
    """Nominal friction and mass (no randomisation)."""
    return mjx_mecanum(friction_range=(0.8, 0.8), mass_range=(1.0, 1.0))


@jax.jit
def _open_loop(plant, keys, U):
    """Per lane (``keys`` [LANES], ``U`` [LANES, 4]): the start drawn from its key, then
    constant wheel-speed references for SECONDS; the start's friction and mass factor, and
    the kinematic state and the noise-free measurement after every period ([LANES, k, 6], [LANES, k, 9]).
    The plant is an argument: the tests' plants (values of one structure) share the program."""
    steps = int(round(SECONDS / Mecanum().T))

    def one(key, u):
        s = plant.init(key)

        def body(s, _):
            s = plant.dynamics(s, u, jnp.zeros(7))
            return s, (plant.state_vector(s), plant.measure(s, jnp.zeros(9)))

        return s.friction, s.mass_scale, *jax.lax.scan(body, s, None, length=steps)[1]

    return jax.vmap(one)(keys, U)


def _lanes(rows):
    """[LANES, 4]: ``rows`` repeated to fill the lanes."""
    rows = jnp.asarray(rows, jnp.float32)
    return jnp.concatenate([rows, jnp.broadcast_to(rows[-1], (LANES - len(rows), 4))])


def test_holonomy_matches_kinematic_model(nominal):
    """(-,+,+,-) sideways, (+,+,+,+) forward, (-,+,-,+) rotation in place: the mean body
    velocity over 5 s is within 10 % of eq. (1)'s, and the other components stay ~0."""
    kin = Mecanum()
    U = jnp.asarray([[4.0, 4, 4, 4], [-4.0, 4, 4, -4], [-4.0, 4, -4, 4]])
    keys = jnp.broadcast_to(jax.random.PRNGKey(0), (LANES, 2))     # at rest at the origin (kin.x0)
    xs = np.asarray(_open_loop(nominal, keys, _lanes(U))[2])[:3]   # [mode, k, 6]
    for mode, (u, axis) in enumerate(zip(np.asarray(U), (0, 1, 2))):
        v_kin = np.asarray(body_velocity(kin, jnp.asarray(u)))
        v_mjx = xs[mode, :, :3].mean(axis=0)
        ratio = v_mjx[axis] / v_kin[axis]
        assert 0.9 <= ratio <= 1.1, (u, v_mjx, v_kin)
        others = np.delete(v_mjx, axis)
        assert np.all(np.abs(others) < 0.02 * np.abs(v_kin[axis]) + 1e-3), (u, v_mjx)
    # the rotation stays in place, the translations keep their heading
    assert np.hypot(*xs[2, -1, 3:5]) < 0.02
    assert np.abs(xs[:2, -1, 5]).max() < 0.02


def test_measurements_are_quantised_and_noisy(nominal):
    """After the first period from a start away from the origin: whole encoder counts, the
    yaw, and the beacon distances of the position."""
    x0 = np.asarray([0, 0, 0, 1.0, -0.5, 0.3], np.float32)
    plant = dataclasses.replace(nominal, kin=dataclasses.replace(nominal.kin, x0=x0))
    keys = jnp.broadcast_to(jax.random.PRNGKey(1), (LANES, 2))
    _, _, xs, zs = _open_loop(plant, keys, _lanes([[3.0, 4, 5, 6]]))
    x, z = np.asarray(xs[0, 0]), np.asarray(zs[0, 0])
    res = 2 * np.pi / (float(nominal.cpr) * nominal.T)
    assert np.abs(z[:4]).min() > 10 * res                                          # the wheels turn
    np.testing.assert_allclose(z[:4] / res, np.round(z[:4] / res), atol=1e-3)   # whole counts per period
    np.testing.assert_allclose(z[4], x[5], atol=1e-6)
    np.testing.assert_allclose(z[5:], np.asarray(distances(Mecanum(), jnp.asarray(x[3:5]))), atol=1e-5)


def test_domain_randomisation_per_seed():
    """Friction and mass factor drawn per seed within their ranges (16 seeds: the lanes of
    the open-loop program; 0.05 is under half the ranges' uniform std of 0.115)."""
    plant = mjx_mecanum()
    keys = jax.random.split(jax.random.PRNGKey(0), LANES)
    mu, ms = (np.asarray(a) for a in _open_loop(plant, keys, _lanes([[0.0, 0, 0, 0]]))[:2])
    assert mu.min() >= 0.6 and mu.max() <= 1.0 and mu.std() > 0.05
    assert ms.min() >= 0.8 and ms.max() <= 1.2 and ms.std() > 0.05


def test_closed_loop_runs_unchanged_on_mjx_plant():
    """The schemes run unchanged with the MJX plant as the truth: same key, same run;
    finite states; a short DRHE run starts following the path."""
    loop = mec.mecanum_loop("DRHE", 5, 0.3, truth=mjx_mecanum(), horizon_s=4.0, full=True)
    assert loop.monitor.xy == 3           # the path monitor reads (X, Y), the MJX plant's declared position_index
    sim = jax.jit(jax.vmap(nc.simulate, in_axes=(None, 0)))
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    a, b = sim(loop, keys), sim(loop, keys)
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert np.all(np.isfinite(np.asarray(a.x)))
    travelled = np.hypot(*(np.asarray(a.x[:, -1, 3:5]) - np.asarray(a.x[:, 0, 3:5])).T)
    assert np.all(travelled > 0.3), travelled          # about V_ref * 4 s
    assert np.all(np.asarray(a.parts["monitor"]).max(axis=1) < 0.2)


def test_bad_configuration_is_rejected_before_tracing():
    with pytest.raises(ValueError, match="timestep"):
        mjx_mecanum(timestep=0.003)          # does not divide T = 0.1
    with pytest.raises(ValueError, match="friction_range"):
        mjx_mecanum(friction_range=(1.0, 0.5))
    with pytest.raises(ValueError, match="kv"):
        mjx_mecanum(kv=-1.0)


def test_jaxnc_imports_without_mujoco():
    """The extra is optional: jaxnc and the MJX module import without MuJoCo, and asking
    for the MJX plant says what to install."""
    code = (
        "import sys; sys.modules['mujoco'] = None; sys.modules['mujoco.mjx'] = None\n"
        "import jaxnc, jaxnc.schemes.mecanum, jaxnc.experiments\n"
        "from jaxnc.plants import mecanum_mjx\n"
        "try:\n    mecanum_mjx.mjx_mecanum()\nexcept ImportError as e:\n    print('ERR', e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "pip install 'jaxnc[mjx]'" in out.stdout


def test_experiment_option_builds_mjx_loops():
    """``jaxnc run mecanum --set plant=mjx``: every loop (the nominal run included) runs on
    the MJX robot and the saved configuration describes it by its parameters."""
    import json

    from jaxnc.experiment import get_experiment
    from jaxnc.experiments import mecanum as exp
    from jaxnc.plants.mecanum_mjx import MjxMecanum

    settings = get_experiment("mecanum").parse_settings(["plant=mjx", "case=DRHE"])
    loops = exp.build_loops(settings)
    assert set(loops) == {"SR nominal", "DRHE"}
    assert all(isinstance(l.plant, MjxMecanum) for l in loops.values())
    cfg = exp.loop_config(loops["DRHE"])
    assert cfg["plant"]["plant"] == "mjx" and cfg["plant"]["substeps"] == 20
    json.dumps(cfg)
