"""Mecanum kinematics (seed 000 eq. 1, 2, 9)."""
import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxnc.plants.mecanum import Mecanum, MecanumNoise, body_velocity, distances, inverse_kinematics


def test_inverse_kinematics_inverts_forward_kinematics():
    p = Mecanum()
    v = jnp.array([0.3, -0.2, 0.5])
    np.testing.assert_allclose(jax.jit(lambda v: body_velocity(p, inverse_kinematics(p, v)))(v), v, atol=1e-6)


@pytest.mark.parametrize("omega, expected", [
    ((1, 1, 1, 1), (1, 0, 0)),      # forward
    ((-1, 1, 1, -1), (0, 1, 0)),    # sideways (left)
    ((-1, 1, -1, 1), (0, 0, 1)),    # rotate in place
])
def test_wheel_patterns_are_holonomic(omega, expected):
    p = Mecanum()
    v = np.asarray(body_velocity(p, jnp.asarray(omega, jnp.float32)))
    scale = np.array([p.R, p.R, p.R / (p.Lx + p.Ly)])
    np.testing.assert_allclose(v, np.asarray(expected) * scale, atol=1e-7)


def test_straight_line_and_rotated_frame():
    """Driving forward for 1 s at heading psi moves 0.1 m/s * 1 s along (cos psi, sin psi)."""
    p = Mecanum()
    u = inverse_kinematics(p, jnp.array([0.1, 0.0, 0.0]))
    for psi in (0.0, 0.7):
        x = jnp.array([0, 0, 0, 1.0, 2.0, psi])
        step = jax.jit(lambda x: p.dynamics(x, u, jnp.zeros(7)))
        for _ in range(10):
            x = step(x)
        np.testing.assert_allclose(x[3:5], [1 + 0.1 * np.cos(psi), 2 + 0.1 * np.sin(psi)], atol=1e-6)


def test_beacon_distances_eq2():
    p = Mecanum()
    xy = np.array([0.3, -0.4])
    d = np.asarray(distances(p, jnp.asarray(xy)))
    ref = [np.sqrt(np.sum((b - xy) ** 2) + (2.0 - 0.3) ** 2) for b in np.asarray(p.beacons)]
    np.testing.assert_allclose(d, ref, rtol=1e-6)


def test_wheel_speed_saturation():
    p = Mecanum()
    x = p.dynamics(jnp.zeros(6), jnp.full(4, 100.0), jnp.zeros(7))
    np.testing.assert_allclose(x[0], p.R * p.omega_max, rtol=1e-6)


@pytest.mark.parametrize("kw, field", [({"R": 0.0}, "Mecanum.R"), ({"Lx": -1.0}, "Mecanum.Lx"),
                                       ({"T": 0.0}, "Mecanum.T")])
def test_bad_plant_parameters_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        Mecanum(**kw)


def test_bad_noise_names_the_field():
    with pytest.raises(ValueError, match="MecanumNoise.dist"):
        MecanumNoise(dist=-0.1)
