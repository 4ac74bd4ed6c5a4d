"""A cart-pole balanced by LQR from an EKF over a lossy, delayed sensor link with PETC.

None of the papers has this system: it shows a user's own loop built from jaxnc's parts
(docs/build_your_own_loop.md). ``jaxnc run examples.cartpole:experiment`` runs it.
"""
import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc.controllers.hold_lq import dlqr

T, STEPS = 0.02, 250                                  # 50 Hz, 5 s


def f(x, u, w):                                       # cart-pole, x = (p, theta, p', theta')
    M, m, l, g = 1.0, 0.1, 0.5, 9.81
    s, c = jnp.sin(x[1]), jnp.cos(x[1])
    a = (u[0] + m * l * x[3] ** 2 * s) / (M + m)
    th = (g * s - c * a) / (l * (4 / 3 - m * c * c / (M + m)))
    return jnp.stack([x[2], x[3], a - m * l * th * c / (M + m) + w[0], th + w[1]])


def h(x, v):                                          # cart position and pole angle
    return x[:2] + v


def cartpole(delta=0.01, p_loss=0.3, temperature=0.0):
    plant = nc.Continuous(x0=[0.0, 0.1, 0.0, 0.0], w_std=[0.05, 0.05], v_std=[0.01, 0.005], f=f, h=h,
                          input_dim=1, noise_dim=2, output_dim=2, T=T, substeps=2)
    A = jax.jacfwd(plant.dynamics, 0)(jnp.zeros(4), jnp.zeros(1), jnp.zeros(2))
    B = jax.jacfwd(plant.dynamics, 1)(jnp.zeros(4), jnp.zeros(1), jnp.zeros(2))
    K = dlqr(np.asarray(A), np.asarray(B), np.diag([1.0, 10.0, 0.1, 0.1]), np.eye(1) * 0.1)[0]
    ekf = nc.EKF(plant, Q=np.asarray(plant.w_std) ** 2 * T, R=np.diag(np.asarray(plant.v_std) ** 2),
                 mean0=np.zeros(4), cov0=np.eye(4) * 0.01, buffer=5)
    sensor_link = nc.Link(nc.Bernoulli(p_loss), nc.ShiftedExponential(0.01, 0.02), tau_max=0.1,
                          order="all", capacity=6)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta, temperature=temperature), uplink=sensor_link,
                   estimator=ekf, controller=nc.StateFeedback(K, u_min=-20.0, u_max=20.0),
                   downlink=nc.Link(), actuator=nc.HoldLast(), monitor=nc.Monitor(bounds=[5, 1.0, 50, 50]),
                   cost=nc.Quadratic(Q=[1.0, 10.0, 0.1, 0.1], R=[0.1]), T=T, steps=STEPS)
