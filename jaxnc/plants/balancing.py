"""Planar wheeled inverted pendulum (balancing robot) of seed 001, section 3, eq. (20).

Coordinates: body tilt ``theta`` from the vertical (positive leaning forward) and wheel
angle ``delta`` *relative to the body*; the input is the wheel acceleration
``u = delta_ddot`` that the robot's own speed servo tracks (section 3), so ``delta`` is a
double integrator and only the tilt is free.  With ``phi = theta + delta`` the wheel's
absolute angle and ``x = r phi`` the axle position, Lagrange's equation for ``theta``
(the motor torque does no work on ``theta`` in these coordinates; ``b`` is a viscous
rolling/air drag on the wheel's absolute speed) gives

    (a + 2 M r l cos th + I) th'' = M g l sin th + M r l sin th th'^2
                                    - (a + M r l cos th) u - b (th' + delta')

with ``a = (M + m_w) r^2 + J_w`` and ``I = M l^2 + J_b``.  Linearised at rest it is eq. (20),

    alpha2 th'' + alpha1 th' + alpha0 th = beta1 delta'' + beta0 delta',
    alpha2 = a + 2 M r l + I, alpha1 = b, alpha0 = -M g l, beta1 = -(a + M r l), beta0 = -b.

State ``x = (delta, theta, delta', theta')``.  The paper does not publish the robot's
numbers; ours are those of a small educational two-wheeled robot (one place, here):
body 1.0 kg with its centre of mass 0.10 m above the axle, a 0.2 m tall body
(``J_b = M h^2 / 12``), two 35 mm wheels of 50 g each, drag 1e-3 N m s.  The open loop
has an unstable pole near +6.7 rad/s (time constant 0.15 s).  The speed servo saturates
the acceleration at ``u_max = 300 rad/s^2`` (10 m/s^2 at the rim).

Measurements (section 3): wheel angle from a 2048-count/rev encoder (quantised, step
3.1e-3 rad) and tilt "obtained by fusing the information (complementary filtering)
provided by the onboard IMU sensor (accelerometer and gyroscope)". ``tilt_sensor``
chooses its error model:

* ``"complementary"`` (default): the filter ``th^_k = a (th^_{k-1} + Ts g_k) + (1 - a) t_k``,
  ``a = tau_cf / (tau_cf + Ts)``, of a gyro ``g_k = th'_k + sigma_gyro n_k`` and an
  accelerometer tilt ``t_k = th_k + sigma_accel m_k`` (n, m standard normal per sample),
  with the gyro integrated exactly and the accelerometer's error from the robot's own
  acceleration neglected (ours), has the error ``e_k = a e_{k-1} + a Ts sigma_gyro n_k +
  (1 - a) sigma_accel m_k``: a first-order Gauss-Markov sequence independent of the
  state, of stationary std ~0.016 deg with the numbers below (:func:`tilt_error_std`),
  changing only ~1e-3 deg from one sample to the next. The error is the sensor's own state:
  it is the fifth entry of the plant's state, driven by the third process noise;
* ``"white"``: ``th_k + sigma_theta v_k`` with white ``v`` (0.1 deg).

The paper publishes no sensor numbers; ours are of the order of a consumer MEMS IMU at
1 kHz: gyro 0.11 deg/s and accelerometer tilt 0.5 deg per sample (std), ``tau_cf = 0.5 s``.
``sigma_theta`` is also the tilt noise the Kalman filter designs for (:func:`kalman_QR`),
with either sensor.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxnc._validate import check_nonneg, check_positive, check_range, scalar_fields
from jaxnc.loop.base import AbstractPlant, pytree_dataclass

STATE_DIM = 4
INPUT_DIM = 1
OUTPUT_DIM = 2
G = 9.81
TILT_SENSORS = ("complementary", "white")   # error models of the tilt measurement (module docstring)


@pytree_dataclass
class Balancing(AbstractPlant):
    """The robot as a loop plant (:class:`jaxnc.loop.AbstractPlant`) at the period ``Ts``.

    State float[5]: ``(delta, theta, delta', theta', e)``, the rigid body and the tilt
    sensor's error ``e`` (0 for the white sensor); :meth:`state_vector` is the rigid body,
    float[4]. Input ``u`` float[1], the wheel acceleration (rad/s^2). Process noise ``w``
    float[3]: servo error and tilt acceleration (rad/s^2, held over the period) and the
    complementary filter's drive (rad); measurement noise ``v`` float[2] (``v[0]`` unused:
    the encoder's error is its quantisation; ``v[1]`` the white sensor's tilt noise). The
    robot starts at rest with tilt ``theta0`` (rad) and ``e`` in its stationary law.
    Parameters in SI units; ``tilt_sensor`` and ``Ts`` static.

    Raises:
      ValueError: a parameter out of its range or not a single number (naming it), an
        unknown ``tilt_sensor``.
    """

    state_dim = 4
    input_dim = 1
    noise_dim = 3
    output_dim = 2

    M: float = 1.0          # body mass, kg
    l: float = 0.10         # axle -> body centre of mass, m
    J_b: float = 1.0 * 0.2**2 / 12.0   # body inertia about its centre of mass, kg m^2
    m_w: float = 0.10       # both wheels, kg
    r: float = 0.035        # wheel radius, m
    J_w: float = 0.5 * 0.10 * 0.035**2  # both wheels (solid discs), kg m^2
    b: float = 1.0e-3       # viscous drag on the wheel's absolute speed, N m s
    u_max: float = 300.0    # wheel acceleration saturation of the speed servo, rad/s^2
    w_theta: float = 0.5    # std of the tilt acceleration disturbance (held 1 ms), rad/s^2
    w_servo: float = 1.0    # std of the servo's acceleration tracking error, rad/s^2
    sigma_theta: float = np.deg2rad(0.1)      # white tilt noise ("white" sensor; the filter's R), rad
    encoder_step: float = 2 * np.pi / 2048    # encoder quantum, rad
    sigma_gyro: float = np.deg2rad(0.11)      # gyro noise per sample, rad/s ("complementary")
    sigma_accel: float = np.deg2rad(0.5)      # accelerometer tilt noise per sample, rad
    tau_cf: float = 0.5                       # complementary filter's time constant, s
    theta0: Any = 0.0                         # initial tilt, rad
    tilt_sensor: str = dataclasses.field(default="complementary", metadata=dict(static=True))
    Ts: float = dataclasses.field(default=1e-3, metadata=dict(static=True))

    def __post_init__(self):
        if self.tilt_sensor not in TILT_SENSORS:
            raise ValueError(f"Balancing.tilt_sensor must be one of {', '.join(TILT_SENSORS)}, "
                             f"got {self.tilt_sensor!r}")
        for name in ("M", "l", "J_b", "m_w", "r", "J_w", "u_max", "Ts", "encoder_step", "tau_cf"):
            check_positive(f"Balancing.{name}", getattr(self, name))
        for name in ("b", "w_theta", "w_servo", "sigma_theta", "sigma_gyro", "sigma_accel"):
            check_nonneg(f"Balancing.{name}", getattr(self, name))
        check_range("Balancing.theta0", self.theta0, -np.pi / 2, np.pi / 2, low_open=True, high_open=True)
        # one robot: a vector made x0 float[5, k] (theta0) or failed later in float() (the masses)
        scalar_fields(self, "M", "l", "J_b", "m_w", "r", "J_w", "b", "u_max", "w_theta", "w_servo", "sigma_theta",
                      "encoder_step", "sigma_gyro", "sigma_accel", "tau_cf", "theta0")

    @property
    def w_std(self):
        """float[3]: servo error, tilt acceleration, sensor drive (0 for the white sensor)."""
        drive = _cf(self)[1] if self.tilt_sensor == "complementary" else 0.0
        return jnp.stack([jnp.asarray(self.w_servo, jnp.float32), jnp.asarray(self.w_theta, jnp.float32),
                          jnp.asarray(drive, jnp.float32)])

    @property
    def v_std(self):
        """float[2]: 0 and, for the white sensor, ``sigma_theta``."""
        s = self.sigma_theta if self.tilt_sensor == "white" else 0.0
        return jnp.stack([jnp.float32(0.0), jnp.asarray(s, jnp.float32)])

    def dynamics(self, x, u, w):
        """One period ``Ts``: the rigid body by RK4 (2 substeps), input held (ZOH), and the
        tilt sensor's error ``e+ = a e + w[2]``.

        Args:
          x: float[5] (or float[4]: the rigid body only, without the sensor).
          u: float[1], saturated at ``u_max``.
          w: float[3] (servo error, tilt acceleration, sensor drive), or float[2].

        Returns:
          float[5] (float[4] for a float[4] state).

        Raises:
          ValueError: a state that is not float[4] or float[5], or w with fewer entries than
            the state needs (3 with the sensor's error, 2 without): JAX would clamp the index
            of the missing sensor drive to w[1], the tilt acceleration.
        """
        nx, nw = jnp.shape(x)[0], jnp.shape(w)[0]
        if nx not in (4, 5) or nw < nx - 2:
            raise ValueError(f"Balancing.dynamics: x must have 4 or 5 entries and w at least {max(nx - 2, 2)} "
                             f"(servo error, tilt acceleration{', sensor drive' if nx == 5 else ''}), got x of "
                             f"{nx} and w of {nw} entries")
        ua = jnp.clip(u[0], -self.u_max, self.u_max) + w[0]
        h = self.Ts / 2

        def f(x):
            return derivative(self, x, ua) + jnp.stack([0.0 * w[1], 0.0 * w[1], 0.0 * w[1], w[1]])

        body = x[:4]
        for _ in range(2):
            k1 = f(body)
            k2 = f(body + 0.5 * h * k1)
            k3 = f(body + 0.5 * h * k2)
            k4 = f(body + h * k3)
            body = body + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        if x.shape[0] == 4:
            return body
        a, _ = _cf(self)
        return jnp.concatenate([body, (a * x[4] + w[2])[None]])

    def measure(self, x, v):
        """``(q round(delta / q), theta + e + v[1])``, float[2] (section 3; ``q`` the
        encoder step, ``e = x[4]`` the complementary filter's error)."""
        q = self.encoder_step
        return jnp.stack([q * jnp.round(x[0] / q), x[1] + x[4] + v[1]])

    @property
    def x0(self):
        """float[5]: at rest, tilt ``theta0``, no sensor error (its random part: :attr:`x0_std`)."""
        th = jnp.asarray(self.theta0, jnp.float32)
        return jnp.stack([0.0 * th, th, 0.0 * th, 0.0 * th, 0.0 * th])

    @property
    def x0_std(self):
        """float[5]: the sensor's error starts in its stationary law (std :func:`tilt_error_std`)."""
        e = tilt_error_std(self) if self.tilt_sensor == "complementary" else jnp.float32(0.0)
        z = jnp.float32(0.0)
        return jnp.stack([z, z, z, z, jnp.asarray(e, jnp.float32)])

    def state_vector(self, x):
        """float[4]: the rigid body ``(delta, theta, delta', theta')``."""
        return x[:4]


# ----------------------------------------------------------------------------- the model (functions of a Balancing)


def coefficients(p: Balancing) -> dict:
    """alpha2, alpha1, alpha0, beta1, beta0 of eq. (20) (floats, numpy)."""
    M, l, r = float(p.M), float(p.l), float(p.r)
    a = (M + float(p.m_w)) * r**2 + float(p.J_w)
    inertia = M * l**2 + float(p.J_b)
    return dict(alpha2=a + 2 * M * r * l + inertia, alpha1=float(p.b), alpha0=-M * G * l,
                beta1=-(a + M * r * l), beta0=-float(p.b))


def continuous(p: Balancing) -> tuple[np.ndarray, np.ndarray]:
    """(Ac, Bc) of eq. (20) in the state (delta, theta, delta', theta')."""
    c = coefficients(p)
    a2 = c["alpha2"]
    Ac = np.array([[0, 0, 1, 0],
                   [0, 0, 0, 1],
                   [0, 0, 0, 0],
                   [0, -c["alpha0"] / a2, c["beta0"] / a2, -c["alpha1"] / a2]], float)
    Bc = np.array([[0], [0], [1], [c["beta1"] / a2]], float)
    return Ac, Bc


def discrete(p: Balancing) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact ZOH discretisation at ``Ts``: (A, B, C), float64 (matrix exponential)."""
    Ac, Bc = continuous(p)
    n, m = Bc.shape
    Mx = np.zeros((n + m, n + m))
    Mx[:n, :n], Mx[:n, n:] = Ac, Bc
    E = scipy.linalg.expm(Mx * float(p.Ts))
    C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    return E[:n, :n], E[:n, n:], C


def derivative(p: Balancing, x, u):
    """Continuous-time nonlinear dynamics x' = f(x, u) (module docstring)."""
    delta_d, th, th_d = x[2], x[1], x[3]
    M, l, r = p.M, p.l, p.r
    a = (M + p.m_w) * r**2 + p.J_w
    inertia = M * l**2 + p.J_b
    s, c = jnp.sin(th), jnp.cos(th)
    num = M * G * l * s + M * r * l * s * th_d**2 - (a + M * r * l * c) * u - p.b * (th_d + delta_d)
    th_dd = num / (a + 2 * M * r * l * c + inertia)
    return jnp.stack([delta_d, th_d, u + 0.0 * th, th_dd])


def _cf(p: Balancing):
    a = jnp.asarray(p.tau_cf, jnp.float32) / (p.tau_cf + p.Ts)
    drive = jnp.hypot(a * p.Ts * p.sigma_gyro, (1.0 - a) * p.sigma_accel)
    return a, drive


def tilt_error_std(p: Balancing) -> jax.Array:
    """Stationary std (rad) of the ``"complementary"`` sensor's error, float32 (traceable)."""
    a, drive = _cf(p)
    return drive / jnp.sqrt(1.0 - a * a)


def filter_noise_std(p: Balancing) -> np.ndarray:
    """float64[2]: std of the servo error and tilt acceleration (rad/s^2), the filter's Q."""
    return np.array([float(p.w_servo), float(p.w_theta)])


def noise_input(p: Balancing) -> np.ndarray:
    """float64[4, 2]: how ``w[:2]``, held over ``Ts``, enters the discrete rigid body
    (exact ZOH of the servo error through ``Bc`` and the tilt acceleration through ``e_4``)."""
    Ac, Bc = continuous(p)
    n = 4
    Mx = np.zeros((n + 2, n + 2))
    Mx[:n, :n] = Ac
    Mx[:n, n:] = np.column_stack([Bc[:, 0], np.eye(n)[:, 3]])
    return scipy.linalg.expm(Mx * float(p.Ts))[:n, n:]


def kalman_QR(p: Balancing) -> tuple[np.ndarray, np.ndarray]:
    """Discrete Q float[4, 4] (``G diag(filter_noise_std^2) G'``, G = :func:`noise_input`) and R
    float[2, 2]: the encoder quantisation as uniform noise of variance q^2/12, the tilt
    as white noise of std ``sigma_theta``."""
    Gw = noise_input(p)
    Q = Gw @ np.diag(filter_noise_std(p) ** 2) @ Gw.T
    R = np.diag([float(p.encoder_step) ** 2 / 12.0, float(p.sigma_theta) ** 2])
    return Q, R
