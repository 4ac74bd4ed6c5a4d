"""The trigger's gradient at the instants where the sensor stays silent (docs/tuning.md, "The
filters read a silent instant's weight").

Run:  .venv/bin/python benchmarks/silent_instants.py [--seeds 8192]

Three measurements, each against central differences on common random numbers:

1. straight-through d/dδ of a two-output LTI servo with an ``EKF`` (PETC δ = 0.05, 20 % loss,
   N = 2, 60 steps) with the filter's ``weight="stamp"`` and ``"slot"``, τ = 0.01 and 0.05,
   against differences of the hard objective (h = 0.02 and 0.01, 95 % intervals from the
   per-seed differences);
2. a relaxed PETC (τ = 0.02) on a pendulum with two sensors (``EKF(form="sequential")``, N = 4,
   200 steps, 256 seeds): the cost's largest second difference over δ in [0.02, 0.03] (41
   points) and the exact d/dδ at 0.025 against differences of step 2e-3, both weights;
3. straight-through d/dδ of a servo with ``Passthrough`` and ``PID(Kp=3, Ki=0.5)`` (no filter:
   not fixed by the weight), against differences of the hard objective.
Prints the numbers; nothing is asserted (tests/test_nudrekf.py holds the tests).
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc

T = 0.1


def _fd(per_seed, d0, h):
    up, down = (np.asarray(per_seed(jnp.float32(d0 + s * h)), float) for s in (1, -1))
    diff = (up - down) / (2 * h)
    return diff.mean(), 1.96 * diff.std(ddof=1) / np.sqrt(diff.size)


def servo_ekf(seeds):
    plant = nc.LTI([[1.0, 0.1], [0.0, 0.95]], [[0.005], [0.1]], [[1.0, 0.0], [0.3, 1.0]], x0=[1.0, -0.5],
                   x0_std=[0.3, 0.3], w_std=[0.05, 0.05], v_std=[0.1, 0.2], T=T)
    keys = jax.random.split(jax.random.PRNGKey(7), seeds)

    def per_seed(d, weight, tau):
        ekf = nc.EKF(plant, Q=np.diag([0.05 ** 2] * 2), R=np.diag([0.1 ** 2, 0.2 ** 2]), mean0=[1.0, -0.5],
                     cov0=0.09 * np.eye(2), weight=weight)
        lp = nc.Loop(plant=plant, trigger=nc.Petc(delta=d, temperature=tau), uplink=nc.Link(nc.Bernoulli(0.2)),
                     estimator=ekf, controller=nc.StateFeedback([[2.0, 1.0]]), downlink=nc.Link(),
                     actuator=nc.HoldLast(), N=2, steps=60, T=T, record=nc.Record(signals=("x",)))
        return jax.vmap(lambda k: jnp.mean(jnp.square(nc.simulate(lp, k).x)))(keys)

    hard = jax.jit(lambda d: per_seed(d, "slot", 0.0))
    for h in (0.02, 0.01):
        print("servo + EKF, central differences h=%g: %.4f +- %.4f (95 %%)" % ((h,) + _fd(hard, 0.05, h)))
    for tau in (0.01, 0.05):
        for w in ("stamp", "slot"):
            g = jax.jit(jax.grad(lambda d: per_seed(d, w, tau).mean()))(jnp.float32(0.05))
            print(f"servo + EKF, straight-through tau={tau:g} weight={w}: {float(g):.4f}")


def relaxed_pendulum_cost(weight: str, keys, steps: int):
    """cost(δ): the mean squared state over ``keys`` of a pendulum with two sensors under a relaxed
    PETC (τ = 0.02), an ``EKF(form="sequential", weight=weight)``, 20 % loss and N = 4, ``steps``
    fast periods (item 2 above; tests/test_nudrekf.py checks its smoothness and gradient)."""
    Tp = 0.02

    def f(x, u, w):
        return jnp.stack([x[0] + Tp * x[1], x[1] + Tp * (-9.81 * jnp.sin(x[0]) - 0.2 * x[1] + u[0]) + w[0]])

    pend = nc.Discrete(x0=[0.3, 0.0], x0_std=[0.05, 0.05], w_std=[0.02], v_std=[0.01, 0.05], f=f,
                       h=lambda x, v: x + v, input_dim=1, noise_dim=1, output_dim=2)
    ekf = nc.EKF(pend, Q=[0.02 ** 2], R=[0.01 ** 2, 0.05 ** 2], mean0=[0.3, 0.0], cov0=0.01 * np.eye(2),
                 form="sequential", weight=weight)

    def cost(d):
        lp = nc.Loop(plant=pend, trigger=nc.Petc(delta=d, temperature=0.02, relaxed=True),
                     uplink=nc.Link(nc.Bernoulli(0.2)), estimator=ekf, controller=nc.StateFeedback([[8.0, 2.0]]),
                     downlink=nc.Link(), actuator=nc.HoldLast(), N=4, steps=steps, T=Tp,
                     record=nc.Record(signals=("x",)))
        return jnp.mean(jnp.square(jax.vmap(lambda k: nc.simulate(lp, k).x)(keys)))
    return cost


def pendulum_relaxed():
    keys = jax.random.split(jax.random.PRNGKey(1), 256)
    for weight in ("stamp", "slot"):
        cost = relaxed_pendulum_cost(weight, keys, 200)
        c, g = jax.jit(cost), jax.jit(jax.grad(cost))
        vals = np.array([float(c(jnp.float32(d))) for d in np.linspace(0.02, 0.03, 41)])
        fd = (float(c(jnp.float32(0.027))) - float(c(jnp.float32(0.023)))) / 4e-3
        print(f"pendulum, relaxed PETC, weight={weight}: max |2nd difference| {np.abs(np.diff(vals, 2)).max():.2e}, "
              f"exact d/ddelta {float(g(jnp.float32(0.025))):.5f}, central difference (step 2e-3) {fd:.5f}")


def servo_passthrough(seeds):
    plant = nc.LTI([[1.0, T], [0.0, 0.95]], [[0.005], [0.1]], [[1.0, 0.0]], x0=[1.0, 0.0], x0_std=[0.3, 0.3],
                   w_std=[0.05, 0.05], v_std=[0.05], T=T)
    keys = jax.random.split(jax.random.PRNGKey(7), seeds)

    def per_seed(d, tau):
        lp = nc.Loop(plant=plant, trigger=nc.Petc(delta=d, temperature=tau), uplink=nc.Link(nc.Bernoulli(0.2)),
                     estimator=nc.Passthrough(), controller=nc.PID(Kp=3.0, Ki=0.5, Kd=0.0), downlink=nc.Link(),
                     actuator=nc.HoldLast(), N=2, steps=60, T=T, record=nc.Record(signals=("x",)))
        return jax.vmap(lambda k: jnp.mean(jnp.square(nc.simulate(lp, k).x)))(keys)

    hard = jax.jit(lambda d: per_seed(d, 0.0))
    for h in (0.01, 0.005):
        print("servo + Passthrough + PID, central differences h=%g: %.4f +- %.4f (95 %%)"
              % ((h,) + _fd(hard, 0.02, h)))
    for tau in (0.005, 0.02):
        g = jax.jit(jax.grad(lambda d: per_seed(d, tau).mean()))(jnp.float32(0.02))
        print(f"servo + Passthrough + PID, straight-through tau={tau:g}: {float(g):.4f}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=8192)
    a = ap.parse_args()
    servo_ekf(a.seeds)
    pendulum_relaxed()
    servo_passthrough(a.seeds)
