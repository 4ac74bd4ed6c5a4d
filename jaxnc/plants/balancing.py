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
3.1e-3 rad) and tilt from a complementary filter (Gaussian, 0.1 deg).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxnc._validate import check_positive, check_nonneg

STATE_DIM = 4
INPUT_DIM = 1
OUTPUT_DIM = 2
G = 9.81


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Balancing:
    """Physical parameters (SI units) and the sampling period ``Ts`` (static)."""

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
    sigma_theta: float = np.deg2rad(0.1)      # tilt measurement noise, rad
    encoder_step: float = 2 * np.pi / 2048    # encoder quantum, rad
    Ts: float = dataclasses.field(default=1e-3, metadata=dict(static=True))

    def __post_init__(self):
        for name in ("M", "l", "J_b", "m_w", "r", "J_w", "u_max", "Ts", "encoder_step"):
            check_positive(f"Balancing.{name}", getattr(self, name))
        for name in ("b", "w_theta", "w_servo", "sigma_theta"):
            check_nonneg(f"Balancing.{name}", getattr(self, name))

    # -- eq. (20) coefficients ---------------------------------------------------------
    def coefficients(self) -> dict:
        """alpha2, alpha1, alpha0, beta1, beta0 of eq. (20) (floats, numpy)."""
        M, l, r = float(self.M), float(self.l), float(self.r)
        a = (M + float(self.m_w)) * r**2 + float(self.J_w)
        inertia = M * l**2 + float(self.J_b)
        return dict(alpha2=a + 2 * M * r * l + inertia, alpha1=float(self.b), alpha0=-M * G * l,
                    beta1=-(a + M * r * l), beta0=-float(self.b))

    def continuous(self) -> tuple[np.ndarray, np.ndarray]:
        """(Ac, Bc) of eq. (20) in the state (delta, theta, delta', theta')."""
        c = self.coefficients()
        a2 = c["alpha2"]
        Ac = np.array([[0, 0, 1, 0],
                       [0, 0, 0, 1],
                       [0, 0, 0, 0],
                       [0, -c["alpha0"] / a2, c["beta0"] / a2, -c["alpha1"] / a2]], float)
        Bc = np.array([[0], [0], [1], [c["beta1"] / a2]], float)
        return Ac, Bc

    def discrete(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact ZOH discretisation at ``Ts``: (A, B, C), float64 (matrix exponential)."""
        Ac, Bc = self.continuous()
        n, m = Bc.shape
        Mx = np.zeros((n + m, n + m))
        Mx[:n, :n], Mx[:n, n:] = Ac, Bc
        E = scipy.linalg.expm(Mx * float(self.Ts))
        C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
        return E[:n, :n], E[:n, n:], C

    # -- nonlinear model ---------------------------------------------------------------
    def derivative(self, x, u):
        """Continuous-time nonlinear dynamics x' = f(x, u) (module docstring)."""
        delta_d, th, th_d = x[2], x[1], x[3]
        M, l, r = self.M, self.l, self.r
        a = (M + self.m_w) * r**2 + self.J_w
        inertia = M * l**2 + self.J_b
        s, c = jnp.sin(th), jnp.cos(th)
        num = M * G * l * s + M * r * l * s * th_d**2 - (a + M * r * l * c) * u - self.b * (th_d + delta_d)
        th_dd = num / (a + 2 * M * r * l * c + inertia)
        return jnp.stack([delta_d, th_d, u + 0.0 * th, th_dd])

    def dynamics(self, x, u, w):
        """One period ``Ts`` of the nonlinear model, input held (ZOH), RK4 with 2 substeps.

        ``u`` (shape (1,)) is saturated at ``u_max``; ``w = (servo error, tilt accel.)``
        in rad/s^2 is held over the period.
        """
        ua = jnp.clip(u[0], -self.u_max, self.u_max) + w[0]
        h = self.Ts / 2

        def f(x):
            return self.derivative(x, ua) + jnp.stack([0.0 * w[1], 0.0 * w[1], 0.0 * w[1], w[1]])

        for _ in range(2):
            k1 = f(x)
            k2 = f(x + 0.5 * h * k1)
            k3 = f(x + 0.5 * h * k2)
            k4 = f(x + h * k3)
            x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    def measure(self, x, v):
        """(encoder-quantised delta, tilt + v): section 3."""
        q = self.encoder_step
        return jnp.stack([q * jnp.round(x[0] / q), x[1] + self.sigma_theta * v])

    def noise_std(self) -> np.ndarray:
        """Std of ``w`` (rad/s^2), used to draw it and for the filter's Q."""
        return np.array([float(self.w_servo), float(self.w_theta)])

    def kalman_QR(self) -> tuple[np.ndarray, np.ndarray]:
        """Discrete Q, R matching the noises: w held over Ts enters like an input.

        The encoder quantisation is modelled as uniform noise of variance q^2/12.
        """
        A, B, _ = self.discrete()
        Ac, _ = self.continuous()
        # the tilt disturbance enters through e_4 like the input through B
        n = 4
        Mx = np.zeros((n + 2, n + 2))
        Mx[:n, :n] = Ac
        Mx[:n, n:] = np.column_stack([self.continuous()[1][:, 0], np.eye(n)[:, 3]])
        E = scipy.linalg.expm(Mx * float(self.Ts))
        Gw = E[:n, n:]
        Q = Gw @ np.diag(self.noise_std() ** 2) @ Gw.T
        R = np.diag([float(self.encoder_step) ** 2 / 12.0, float(self.sigma_theta) ** 2])
        return Q, R
