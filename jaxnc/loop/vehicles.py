"""Differential-drive vehicle (the Lego robot of seed 004) as a plant of the loop.

Seed 004 (Cuenca et al., Sensors 2019), eq. (1)-(3) (kinematics), eq. (4)-(7) (motor
model per wheel and its lifted, dual-rate form) and eq. (26) (motor transfer function)

    G_p(s) = 0.1276 / (0.1235 s + 1)      (wheel speed in rad/s per unit of command).

State   xi = (w_r, w_l, x, y, psi)    (wheel speeds rad/s, position m, heading rad)
Input   u  = (u_r, u_l)               (motor commands, saturated at +-u_max)
Output  z  = xi + n2                  (encoders, zenithal camera, IMU)

:class:`DiffDrive` runs at the fine period dt = T / sub (the runner's fast period): the
motors discretised exactly (ZOH) at dt and the kinematics integrated at dt (midpoint
heading, trapezoidal wheel speed), so a command may change in the middle of a period T,
as in the paper's TrueTime simulation. The wheel noise n1 (eq. 4) enters once per period
T, at its first fine step. Its slow-period (lifted) models, for estimators and predictors
that run once per sensing period (:class:`jaxnc.loop.AbstractLiftedPlant`):
``lifted="integrated"``, the same fine integrator over the period with the commands
applied (the paper's "accurate system model", section 2.2), or ``"eq1"``, eq. (1)-(3) and
(7) as printed. docs/diffdrive.md gives the numbers the paper leaves out (r, b, u_max,
the noise at F = 1).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxnc._validate import array_fields, check_choice, check_int, check_nonneg, check_positive, scalar_fields
from jaxnc.loop.base import pytree_dataclass as _dataclass
from jaxnc.loop.base import static_field as _static
from jaxnc.loop.base import AbstractLiftedPlant

__all__ = ["DiffDrive", "lifted_wheel_var", "motor", "body_velocity", "wheel_command", "substep",
           "eq1", "integrated", "K_MOTOR", "TAU_MOTOR", "LIFTED_MODELS"]

K_MOTOR = 0.1276    # eq. (26), static gain
TAU_MOTOR = 0.1235  # eq. (26), time constant, s
#: the slow-period models :meth:`DiffDrive.period` implements
LIFTED_MODELS = ("integrated", "eq1")


@_dataclass
class DiffDrive(AbstractLiftedPlant):
    """Differential-drive robot with first-order motors (eq. 1-7, 26) at the fine period T / sub.

    Attributes:
      x0: float[5], the initial state (at rest: wheel speeds 0).
      r: wheel radius, m; b: half the wheel track, m; K, tau: the motor, eq. (26);
        u_max: command saturation, applied inside :meth:`dynamics` and the lifted models
        (``Trajectory.u`` records the command before it; a
        :class:`~jaxnc.loop.LimitedActuator`'s ``Saturation`` is recorded, but a controller's
        prediction with this model does not see it).
      F: the noise factor of section 5.1, scaling the standard deviations at F = 1:
        ``wheel`` (n1, rad/s per T), ``enc`` (rad/s), ``cam`` (m), ``imu`` (rad).
      T: static, the actuation period, s; sub: static, fine steps per T.
      lifted: static, the slow-period model of :meth:`period` (:data:`LIFTED_MODELS`).

    Raises:
      ValueError: a non-positive physical parameter, a negative noise, a number that is not a
        single number (both wheels share r, K, tau and u_max), ``sub`` outside [1, 1000], an
        unknown ``lifted``.
    """

    x0: Any = (0.0, 0.0, 0.0, 0.0, 0.0)
    r: Any = 0.028
    b: Any = 0.06
    K: Any = K_MOTOR
    tau: Any = TAU_MOTOR
    u_max: Any = 100.0
    F: Any = 0.0
    wheel: Any = 1.0
    enc: Any = 1.0
    cam: Any = 0.02
    imu: Any = 0.05
    T: float = _static(0.1)
    sub: int = _static(10)
    lifted: str = _static("integrated")

    state_dim = 5
    input_dim = 2
    noise_dim = 2
    output_dim = 5
    position_index = 2      # xi[2:4] = (x, y), m

    def __post_init__(self):
        for name in ("r", "b", "K", "tau", "u_max", "T"):
            check_positive(f"DiffDrive.{name}", getattr(self, name))
        for name in ("F", "wheel", "enc", "cam", "imu"):
            check_nonneg(f"DiffDrive.{name}", getattr(self, name))
        scalar_fields(self, "r", "b", "K", "tau", "u_max", "F", "wheel", "enc", "cam", "imu")
        check_int("DiffDrive.sub", self.sub, 1, 1000)
        object.__setattr__(self, "lifted", check_choice("DiffDrive.lifted", self.lifted, LIFTED_MODELS))
        array_fields(self, "x0")

    @property
    def dt(self) -> float:
        return self.T / self.sub

    @property
    def step_period(self) -> float:
        """One ``dynamics`` step is the fine period dt = T / sub."""
        return self.dt

    @property
    def noise_period(self) -> int:
        """The wheel noise n1 enters once per period T = sub fine periods (eq. 4)."""
        return self.sub

    @property
    def w_std(self):
        """float[2]: std of n1 on each wheel speed, added once per T."""
        s = jnp.asarray(self.F * self.wheel, jnp.float32)
        return jnp.stack([s, s])

    @property
    def v_std(self):
        """float[5]: std of n2 for (w_r, w_l, x, y, psi)."""
        e, c, i = (jnp.asarray(self.F * v, jnp.float32) for v in (self.enc, self.cam, self.imu))
        return jnp.stack([e, e, c, c, i])

    # -- the plant protocol
    def dynamics(self, x, u, w):
        """One fine period: the wheel noise w float[2] added to the wheel speeds (the runner
        draws it at the first fine step of each period T, ``noise_period``), then :func:`substep`."""
        return substep(self, x.at[:2].add(w), u)

    def measure(self, x, v):
        """z = xi + n2 (eq. 8)."""
        return x + v

    def period(self, x, us, w):
        """The slow-period model selected by ``lifted``: ``us`` float[M, 2] the fine commands
        of the period (M a multiple of sub), w float[5] additive. "eq1" uses, per slot T,
        the mean of its fine commands."""
        if self.lifted == "eq1":
            return eq1(self, x, jnp.mean(us.reshape(-1, self.sub, 2), axis=1), w)
        return integrated(self, x, us, w)


# ----------------------------------------------------------------------------- the physics (kernels)


def motor(robot: DiffDrive, Ts):
    """(a, g): the exact ZOH of eq. (26) at period Ts: w' = a w + g u, a = exp(-Ts/tau), g = K (1 - a)."""
    a = jnp.exp(-Ts / jnp.asarray(robot.tau, jnp.float32))
    return a, robot.K * (1.0 - a)


def body_velocity(robot: DiffDrive, w):
    """(w_r, w_l) -> (v, omega), eq. (2)-(3)."""
    vr, vl = robot.r * w[..., 0], robot.r * w[..., 1]
    return 0.5 * (vr + vl), (vr - vl) / (2.0 * robot.b)


def wheel_command(robot: DiffDrive, v, omega):
    """(v_ref, omega_ref) -> (w_r^com, w_l^com) float[2], eq. (20)."""
    return jnp.stack([(v + robot.b * omega) / robot.r, (v - robot.b * omega) / robot.r], axis=-1)


def substep(robot: DiffDrive, x, u):
    """x float[5] after one fine period dt with the command u float[2] held (no noise)."""
    u = jnp.clip(u, -robot.u_max, robot.u_max)
    a, g = motor(robot, robot.dt)
    w1 = a * x[:2] + g * u
    v, om = body_velocity(robot, 0.5 * (x[:2] + w1))
    h = x[4] + 0.5 * om * robot.dt
    return jnp.concatenate([w1, jnp.stack([x[2] + v * robot.dt * jnp.cos(h), x[3] + v * robot.dt * jnp.sin(h),
                                           x[4] + om * robot.dt])])


def eq1(robot: DiffDrive, x, U, n1):
    """Eq. (8) with eq. (1)-(3), (7) as printed: xi_k = f(xi_{k-1}, U) + n1 over NT.

    Args:
      x: float[5]; U: float[N, 2], the N actions of the period (one per T); n1: float[5], additive.
    Returns:
      float[5]: the wheel speeds by the lifted motor (eq. 7), the pose by eq. (1) with the
      end-of-period speeds and the heading psi_{k-1} + omega_k NT.
    """
    N = U.shape[0]
    a, g = motor(robot, robot.T)
    powers = a ** jnp.arange(N - 1, -1, -1, dtype=jnp.float32)          # a^{N-1-c}
    U = jnp.clip(U, -robot.u_max, robot.u_max)
    w = (a ** N) * x[:2] + g * jnp.sum(powers[:, None] * U, axis=0)
    v, om = body_velocity(robot, w)
    NT = N * robot.T
    h = x[4] + om * NT
    return jnp.concatenate([w, jnp.stack([x[2] + v * NT * jnp.cos(h), x[3] + v * NT * jnp.sin(h),
                                          x[4] + om * NT])]) + n1


def integrated(robot: DiffDrive, x, u_fine, n1):
    """The true plant's integrator over M fine periods, noise-free, plus n1 float[5] at the end.

    ``u_fine`` float[M, 2]: the commands of the M fine periods, applied in order by
    :func:`substep`; it follows a command that changes in the middle of a slot T."""
    x1, _ = jax.lax.scan(lambda xc, u: (substep(robot, xc, u), None), x, u_fine)
    return x1 + n1


def lifted_wheel_var(plant: DiffDrive, std_T, N: int):
    """Variance over NT of wheel-speed noise of std ``std_T`` entering as :class:`DiffDrive`'s
    does (at the first fine step of each T, before that step, so the motor filters it over
    the whole T): std_T^2 sum_{c=1..N} a^{2c}, a = exp(-T/tau) (the n1 of eq. 7 for this
    plant; noise added at the end of each T, after the motor, as eq. (4) is printed, would
    give sum_{c=0..N-1}, a^-2 ~ 5 times more)."""
    a, _ = motor(plant, plant.T)
    return jnp.asarray(std_T, jnp.float32) ** 2 * jnp.sum(a ** (2 * jnp.arange(1, N + 1, dtype=jnp.float32)))
