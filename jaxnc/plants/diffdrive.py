"""Differential-drive vehicle (Lego robot) of seed 004: kinematics, motors, noise.

Seed 004 (Cuenca et al., Sensors 2019), eq. (1)-(3) (kinematics), eq. (4)-(7) (motor
model per wheel and its lifted, dual-rate form) and eq. (26) (motor transfer function)

    G_p(s) = 0.1276 / (0.1235 s + 1)      (wheel speed in rad/s per unit of command).

State   xi = (w_r, w_l, x, y, psi)    (wheel speeds rad/s, position m, heading rad)
Input   u  = (u_r, u_l)               (motor commands)
Output  z  = xi + n2                  (encoders, zenithal camera, IMU)

Numbers the paper leaves out, chosen here and kept in one place:

* wheel radius r = 0.028 m (the 56 mm tyre of the Lego NXT/EV3 kits) and half-track
  b = 0.06 m (a 12 cm wheel track, the usual Lego "tribot");
* commands saturate at +-100: the paper calls the input volts, but with the static
  gain 0.1276 a cruise wheel speed of 5 rad/s needs 39 units, so the unit is the
  Lego firmware's power percentage, whose range is +-100;
* noise at F = 1 (the paper only gives the factor F: 0.1 low, 0.45 high): process noise
  n1 on each wheel speed, added every T (eq. 4), 1.0 rad/s; measurement noise n2:
  encoders 1.0 rad/s, camera position 0.02 m, IMU heading 0.05 rad.  At F = 0.1 that
  is 0.1 rad/s, 2 mm, 0.005 rad; at F = 0.45, 0.45 rad/s, 9 mm, 0.0225 rad.

Two models of the same robot live here.  :meth:`DiffDrive.substep` is the "true"
plant: the motors discretised exactly (ZOH) at the fine period ``T / sub`` and the
kinematics integrated at that period (midpoint heading, trapezoidal wheel speed);
the fine grid lets a network delay change the command in the middle of a period
T, as in the paper's TrueTime simulation.  :meth:`DiffDrive.dynamics` is the EKF's
model at NT, eq. (1)-(3) with the lifted motor of eq. (7), exactly as printed;
:meth:`DiffDrive.integrated` is the "accurate system model" the paper assumes (section
2.2): the true plant's integrator over the period with the fine commands it receives.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnc._validate import check_int, check_nonneg, check_positive

STATE_DIM = 5
INPUT_DIM = 2
PROCESS_NOISE_DIM = 5   # additive on every state in the EKF model (eq. 8)
OUTPUT_DIM = 5

K_MOTOR = 0.1276    # eq. (26), static gain
TAU_MOTOR = 0.1235  # eq. (26), time constant, s


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiffDrive:
    """Differential-drive robot with first-order motors (eq. 1-7, 26); ``T`` the actuation period."""

    r: jax.Array = 0.028          # wheel radius r_r = r_l, m
    b: jax.Array = 0.06           # half the distance between the wheels, m
    K: jax.Array = K_MOTOR
    tau: jax.Array = TAU_MOTOR
    u_max: jax.Array = 100.0
    T: float = dataclasses.field(default=0.1, metadata=dict(static=True))
    sub: int = dataclasses.field(default=10, metadata=dict(static=True))   # fine steps per T

    def __post_init__(self):
        for name in ("r", "b", "K", "tau", "u_max"):
            check_positive(f"DiffDrive.{name}", getattr(self, name))
        check_positive("DiffDrive.T", self.T)
        check_int("DiffDrive.sub", self.sub, 1, 1000)

    @property
    def dt(self) -> float:
        return self.T / self.sub

    def motor(self, Ts):
        """Exact ZOH of eq. (26) at period Ts: w' = a w + g u, a = exp(-Ts/tau), g = K (1 - a)."""
        a = jnp.exp(-Ts / jnp.asarray(self.tau, jnp.float32))
        return a, self.K * (1.0 - a)

    def body_velocity(self, w):
        """(w_r, w_l) -> (v, omega), eq. (2)-(3)."""
        vr, vl = self.r * w[..., 0], self.r * w[..., 1]
        return 0.5 * (vr + vl), (vr - vl) / (2.0 * self.b)

    def wheel_command(self, v, omega):
        """(v_ref, omega_ref) -> (w_r^com, w_l^com), eq. (20)."""
        return jnp.stack([(v + self.b * omega) / self.r, (v - self.b * omega) / self.r], axis=-1)

    def substep(self, x, u):
        """True plant over one fine period dt = T/sub with the command u held."""
        u = jnp.clip(u, -self.u_max, self.u_max)
        a, g = self.motor(self.dt)
        w0 = x[:2]
        w1 = a * w0 + g * u
        v, om = self.body_velocity(0.5 * (w0 + w1))
        dt = self.dt
        h = x[4] + 0.5 * om * dt
        return jnp.concatenate([w1, jnp.stack([x[2] + v * dt * jnp.cos(h), x[3] + v * dt * jnp.sin(h),
                                               x[4] + om * dt])])

    def dynamics(self, x, U, n1):
        """EKF model at NT: xi_k = f(xi_{k-1}, n1_{k-1}, U_{k-1}), eq. (8) from eq. (1)-(3), (7).

        ``U`` holds the N actions of the period ([N, 2]); the wheel speeds follow the
        lifted motor model (eq. 7) and the pose eq. (1), which uses the wheel speeds at
        the end of the period and the heading psi_{k-1} + omega_k NT.  ``n1`` is additive.
        """
        N = U.shape[0]
        a, g = self.motor(self.T)
        powers = a ** jnp.arange(N - 1, -1, -1, dtype=jnp.float32)          # a^{N-1-c}
        U = jnp.clip(U, -self.u_max, self.u_max)
        w = (a ** N) * x[:2] + g * jnp.sum(powers[:, None] * U, axis=0)
        v, om = self.body_velocity(w)
        NT = N * self.T
        h = x[4] + om * NT
        return jnp.concatenate([w, jnp.stack([x[2] + v * NT * jnp.cos(h), x[3] + v * NT * jnp.sin(h),
                                              x[4] + om * NT])]) + n1

    def integrated(self, x, u_fine, n1):
        """The slow-period model that integrates the true plant: xi_k = F(xi_{k-1}, u) + n1.

        ``u_fine`` float[M, 2] holds the commands of the M fine periods dt = T/sub of the
        period (M = N sub for one period NT), applied in order by :meth:`substep`, the same
        integrator as the true robot (noise-free inside the period); ``n1`` float[5] is
        additive at the end, as in eq. (8). Unlike :meth:`dynamics` (eq. 1 as printed) it
        follows the heading and speed through the period and a command that changes in the
        middle of a slot T (a packet arriving mid-period)."""
        x1, _ = jax.lax.scan(lambda xc, u: (self.substep(xc, u), None), x, u_fine)
        return x1 + n1

    def measure(self, x, n2):
        """z = h(xi, n2) = xi + n2: encoders, camera (x, y), IMU heading."""
        return x + n2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DiffDriveNoise:
    """Noise standard deviations at F = 1 and the factor F of section 5.1 (see module docstring)."""

    F: jax.Array = 0.1
    wheel: jax.Array = 1.0     # rad/s per T, process noise n1 on each wheel speed (eq. 4)
    enc: jax.Array = 1.0       # rad/s, encoder noise
    cam: jax.Array = 0.02      # m, camera position noise
    imu: jax.Array = 0.05      # rad, heading noise

    def __post_init__(self):
        for f in dataclasses.fields(self):
            check_nonneg(f"DiffDriveNoise.{f.name}", getattr(self, f.name))

    def process_std(self):
        """Std of the wheel-speed process noise added every T, [2]."""
        s = jnp.asarray(self.F * self.wheel, jnp.float32)
        return jnp.stack([s, s])

    def measurement_std(self):
        """Std of n2 for (w_r, w_l, x, y, psi), [5]."""
        e, c, i = (jnp.asarray(self.F * v, jnp.float32) for v in (self.enc, self.cam, self.imu))
        return jnp.stack([e, e, c, c, i])


def lifted_wheel_var(plant: DiffDrive, std_T, N: int):
    """Variance over NT of wheel-speed noise added every T and filtered by the motor:
    std^2 sum_{c<N} a^{2c} (the n1 of eq. 7 that the EKF should assume)."""
    a, _ = plant.motor(plant.T)
    return jnp.asarray(std_T, jnp.float32) ** 2 * jnp.sum(a ** (2 * jnp.arange(N, dtype=jnp.float32)))


__all__ = ["DiffDrive", "DiffDriveNoise", "lifted_wheel_var", "STATE_DIM", "INPUT_DIM", "OUTPUT_DIM",
           "PROCESS_NOISE_DIM", "K_MOTOR", "TAU_MOTOR"]
