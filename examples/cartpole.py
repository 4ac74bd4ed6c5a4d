"""A cart-pole balanced by LQR from an EKF over a lossy, delayed sensor link with PETC.

None of the four papers has this system: it is a user's own loop built from jaxnc's parts
(docs/build_your_own_loop.md). The loop itself is :func:`f`, :func:`h` and
:func:`cartpole` (the "user code"); :data:`experiment` makes it a command-line study,
``jaxnc run examples.cartpole:experiment --seeds 1000``.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc.controllers.hold_lq import dlqr

T, STEPS = 0.02, 250                                   # 50 Hz, 5 s


def f(x, u, w):                                        # cart-pole, x = (p, theta, p', theta')
    M, m, l, g = 1.0, 0.1, 0.5, 9.81
    s, c = jnp.sin(x[1]), jnp.cos(x[1])
    a = (u[0] + m * l * x[3] ** 2 * s) / (M + m)
    th = (g * s - c * a) / (l * (4 / 3 - m * c * c / (M + m)))
    return jnp.stack([x[2], x[3], a - m * l * th * c / (M + m) + w[0], th + w[1]])


def h(x, v):                                           # cart position and pole angle
    return x[:2] + v


def cartpole(delta=1e-3, p_loss=0.3, temperature=0.0):
    plant = nc.Continuous(x0=[0.0, 0.1, 0.0, 0.0], w_std=[0.05, 0.05], v_std=[0.01, 0.005], f=f, h=h,
                          input_dim=1, noise_dim=2, output_dim=2, T=T, substeps=2)
    zero = (jnp.zeros(4), jnp.zeros(1), jnp.zeros(2))
    A, B = (np.asarray(jax.jacfwd(plant.dynamics, i)(*zero)) for i in (0, 1))
    K = dlqr(A, B, np.diag([1.0, 10.0, 0.1, 0.1]), np.eye(1) * 0.1)[0]
    ekf = nc.EKF(plant, Q=np.asarray(plant.w_std) ** 2 * T, R=np.diag(np.asarray(plant.v_std) ** 2),
                 mean0=np.zeros(4), cov0=np.eye(4) * 0.01, buffer=5,  # measurements up to 5 periods late
                 form="sqrt")   # stays positive definite in float32 through seconds of silence
    sensor_link = nc.Link(nc.Bernoulli(p_loss), nc.ShiftedExponential(eta=0.01, phi=0.02), tau_max=0.1,
                          order="all", capacity=6)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta, temperature=temperature), uplink=sensor_link,
                   estimator=ekf, controller=nc.StateFeedback(K, u_min=-20.0, u_max=20.0),
                   downlink=nc.Link(), actuator=nc.HoldLast(), monitor=nc.Monitor(bounds=[5.0, 1.0, 50.0, 50.0]),
                   cost=nc.Quadratic(Q=[1.0, 10.0, 0.1, 0.1], R=[0.1]), T=T, steps=STEPS)


# ----------------------------------------------------------------------------- beyond the loop


def cost_of_log_delta(loop):
    """Per-seed objective for :func:`jaxnc.tune.check.gradient_check`: the run's cost as a
    function of theta = [log delta] (``temperature`` > 0: straight-through trigger)."""
    def objective(theta, key, temperature):
        trig = nc.Petc(delta=jnp.exp(theta[0]), temperature=temperature)
        return nc.run(dataclasses.replace(loop, trigger=trig), key).cost_raw
    return objective


def _run_experiment(settings, *, seeds, out, progress):
    import time
    from jaxnc import montecarlo, results as results_mod
    t0 = time.time()
    loop = cartpole(delta=settings["delta"], p_loss=settings["p_loss"])
    m = montecarlo.run_batched(nc.run_seed, montecarlo.seed_keys(settings["seed"], seeds), args=(loop,),
                               chunk_size=min(seeds, 1024), progress=progress, desc="cart-pole")
    cost = montecarlo.summarize(m.cost, m.unstable)
    rate = montecarlo.summarize(m.rate_sc, np.zeros_like(m.unstable))
    print(f"cart-pole over a lossy delayed link, {seeds} seeds: delta={settings['delta']:g}, "
          f"p_loss={settings['p_loss']:g}")
    print(f"  cost        {cost.mean:.4f} +- {cost.ci95:.4f} (95 %), unstable {cost.unstable_fraction:.1%}")
    print(f"  sensor rate {rate.mean:.3f} packets per period (of 1)")
    results = {"cost": cost, "sensor_rate": rate}
    results_mod.save_per_seed(out, {"cartpole": m}, experiment="cartpole")   # per seed, for jaxnc.load(out)
    montecarlo.save_results(out / "results.json", experiment="cartpole",        # the loop that made them, whole
                            config=dict(settings, seeds=seeds, loop=results_mod.config_of(loop)),
                            results=results, wall_time_s=time.time() - t0)
    return results


def _experiment():
    from jaxnc.experiment import Experiment, Option
    return Experiment(
        name="cartpole", description="user example: cart-pole, LQR from an EKF, lossy delayed link with PETC",
        options=(Option("delta", "float", 1e-3, "PETC absolute threshold (rad^2, m^2)", low=0.0, high=1.0),
                 Option("p_loss", "float", 0.3, "sensor packet loss probability", low=0.0, high=0.99),
                 Option("seed", "int", 0, "base seed", low=0, high=2**31 - 1)),
        run=_run_experiment)


experiment = _experiment()
