"""Holonomic Mecanum-wheeled robot: kinematic model and beacon measurements.

Seed 000 (Carbonell et al., ISA Trans. 2024), eq. (1) (kinematics at period T),
eq. (2) (distances to four fixed beacons) and eq. (9) (inverse kinematics).

State   xi = (Vx, Vy, W, X, Y, psi)          (body velocities, yaw rate, pose)
Input   u  = (w1, w2, w3, w4)                 (wheel speed references, rad/s)
Output  z  = (w1, w2, w3, w4, psi, d1..d4)    (encoders, yaw, beacon distances)

The paper gives no numbers for the platform; the defaults below are those of a
small laboratory Mecanum robot and live here, in one place:

* R = 0.05 m wheel radius, Lx = Ly = 0.15 m (half wheel base / half track),
* four beacons at the corners of a 5 m x 5 m room, fixed beacons 2.0 m high,
  mobile beacon 0.3 m high (Marvelmind-like indoor positioning),
* process noise on each wheel speed 0.2 rad/s (about 1 cm/s of slip and motor
  loop error) plus 2 mm / 0.003 rad of pose slip per 0.1 s step, at cruise speed;
  both scale with the commanded wheel speed (none at rest),
* measurement noise: encoders 0.05 rad/s, yaw (IMU) 0.01 rad, beacon distance
  0.02 m (the +-2 cm accuracy of commercial ultrasonic beacons).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc._validate import check_positive, check_nonneg
from jaxnc.loop.base import AbstractPlant

STATE_DIM = 6
INPUT_DIM = 4
PROCESS_NOISE_DIM = 7   # 4 wheel speeds + X, Y, psi slip
OUTPUT_DIM = 9
POSITION_INDEX = 3      # xi[3:5] = (X, Y), the planar position (AbstractPlant.position_index)

DEFAULT_BEACONS = ((-2.5, -2.5), (2.5, -2.5), (2.5, 2.5), (-2.5, 2.5))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MecanumNoise:
    """Standard deviations of process (n1) and measurement (n2) noise; see module docstring."""

    omega: jax.Array = 0.2       # rad/s, wheel speed (actuation) noise
    xy: jax.Array = 0.002        # m per step, pose slip
    psi: jax.Array = 0.003       # rad per step
    enc: jax.Array = 0.05        # rad/s, encoder noise
    yaw: jax.Array = 0.01        # rad, yaw sensor noise
    dist: jax.Array = 0.02       # m, beacon distance noise

    def __post_init__(self):
        for f in dataclasses.fields(self):
            check_nonneg(f"MecanumNoise.{f.name}", getattr(self, f.name))

    def process_std(self):
        o, p, q = (jnp.asarray(a, jnp.float32) for a in (self.omega, self.xy, self.psi))
        return jnp.stack([o, o, o, o, p, p, q])

    def measurement_std(self):
        e, y, d = (jnp.asarray(a, jnp.float32) for a in (self.enc, self.yaw, self.dist))
        return jnp.stack([e, e, e, e, y, d, d, d, d])

    def Q(self):
        """Process noise covariance (of n1)."""
        return jnp.diag(self.process_std() ** 2)

    def R(self):
        """Measurement noise covariance (of n2)."""
        return jnp.diag(self.measurement_std() ** 2)

    def scaled(self, factor):
        return MecanumNoise(*(getattr(self, f.name) * factor for f in dataclasses.fields(self)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mecanum(AbstractPlant):
    """Kinematic Mecanum platform sampled at the fast period ``T`` (eq. 1-2, 9), a loop
    plant (:class:`jaxnc.loop.AbstractPlant`) and the model of seed 000's estimator and
    controller.

    As a true plant it starts at rest at ``x0`` (float[6]) and the runner scales its
    standard normal draws by ``noise`` (:class:`MecanumNoise`: process n1, 7 entries, and
    measurement n2, 9 entries); a model ignores both.

    The model methods take one seed's vectors, e.g. ``x`` of shape (6,), or the same
    with trailing batch axes, (6, B), as :func:`jaxnc.estimators.ekf_batched.ekf_filter`
    passes them (every input then carries the batch axes).
    """

    R: jax.Array = 0.05
    Lx: jax.Array = 0.15
    Ly: jax.Array = 0.15
    beacons: jax.Array = dataclasses.field(default_factory=lambda: np.asarray(DEFAULT_BEACONS, np.float32))
    z_fb: jax.Array = 2.0
    z_mb: jax.Array = 0.3
    omega_max: jax.Array = 20.0   # wheel speed saturation, rad/s (1 m/s at R = 0.05)
    x0: jax.Array = dataclasses.field(default_factory=lambda: np.zeros(STATE_DIM, np.float32))
    noise: MecanumNoise = dataclasses.field(default_factory=MecanumNoise)
    T: float = dataclasses.field(default=0.1, metadata=dict(static=True))

    def __post_init__(self):
        check_positive("Mecanum.R", self.R)
        check_positive("Mecanum.Lx", self.Lx)
        check_positive("Mecanum.Ly", self.Ly)
        check_positive("Mecanum.T", self.T)
        check_positive("Mecanum.omega_max", self.omega_max)

    state_dim = STATE_DIM
    input_dim = INPUT_DIM
    noise_dim = PROCESS_NOISE_DIM
    output_dim = OUTPUT_DIM
    position_index = POSITION_INDEX

    @property
    def step_period(self) -> float:
        return self.T

    @property
    def w_std(self):
        """float[7]: std of the true process noise n1 (``noise``)."""
        return self.noise.process_std()

    @property
    def v_std(self):
        """float[9]: std of the true measurement noise n2 (``noise``)."""
        return self.noise.measurement_std()

    def dynamics(self, x, u, w):
        """xi_k = f(xi_{k-1}, n1_{k-1}, u_{k-1}), eq. (1) and (10).

        ``w`` is the process noise n1 = (4 wheel-speed errors, X, Y, psi slip).
        """
        u, m = commanded(self, u)
        omega = u + m[None] * w[:4]
        v = body_velocity(self, omega)
        T = self.T
        a = x[5] + v[2] * T
        c, s = jnp.cos(a), jnp.sin(a)
        X = x[3] + v[0] * T * c - v[1] * T * s + m * w[4]
        Y = x[4] + v[0] * T * s + v[1] * T * c + m * w[5]
        psi = x[5] + v[2] * T + m * w[6]
        return jnp.concatenate([v, jnp.stack([X, Y, psi])])

    def measure(self, x, v):
        """z = h(xi, n2): encoders (eq. 9 of the state velocities), yaw, eq. (2)."""
        omega = inverse_kinematics(self, x[:3])
        return jnp.concatenate([omega, x[5:6], distances(self, x[3:5])]) + v


# ----------------------------------------------------------------------------- the model (functions of a Mecanum)


def body_velocity(p: Mecanum, omega):
    """Wheel speeds -> (Vx, Vy, W), eq. (1)."""
    w1, w2, w3, w4 = omega[0], omega[1], omega[2], omega[3]
    q = p.R / 4.0
    return jnp.stack([
        (w1 + w2 + w3 + w4) * q,
        (-w1 + w2 + w3 - w4) * q,
        (-w1 + w2 - w3 + w4) * q / (p.Lx + p.Ly),
    ])


def inverse_kinematics(p: Mecanum, v):
    """(Vx, Vy, W) -> wheel speeds, eq. (9)."""
    vx, vy, w = v[0], v[1], v[2]
    L = p.Lx + p.Ly
    return jnp.stack([vx - vy - L * w, vx + vy + L * w, vx + vy - L * w, vx - vy + L * w]) / p.R


def commanded(p: Mecanum, u):
    """The saturated wheel-speed command and the process-noise scale it implies.

    Noise scales with motion (full at the cruise wheel speed 4 rad/s): a robot at
    rest neither slips nor jitters.
    """
    u = jnp.clip(u, -p.omega_max, p.omega_max)
    return u, jnp.minimum(1.0, jnp.mean(jnp.abs(u), axis=0) / 4.0)


def distances(p: Mecanum, xy):
    """Beacon distances d_i, eq. (2). ``xy`` is (2,) or (2, *batch)."""
    dz2 = (p.z_fb - p.z_mb) ** 2
    b = jnp.reshape(p.beacons, p.beacons.shape + (1,) * (jnp.ndim(xy) - 1))
    diff = b - xy[None]                      # (4, 2, *batch); per seed exactly the old (4, 2)
    # the two squares added as written (a sum over the axis is a library call per use on XLA:CPU)
    return jnp.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + dz2)

