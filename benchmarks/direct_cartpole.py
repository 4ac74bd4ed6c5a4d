"""The cart-pole loop of examples/cartpole.py written directly as one ``lax.scan``: the
baseline the runner is measured against (issue 32).

Same arithmetic as ``jaxnc.loop.simulate`` on ``examples.cartpole.cartpole()`` (N = 1):
RK4 plant, PETC on the measurement, a lossy delayed uplink read at each slow instant, the
EKF with a 5-period re-run window of late measurements (the same kernels,
``jaxnc.estimators.ekf``), saturated LQR, hold-last actuator without network, the
monitor's freeze and the quadratic cost; the randomness is the runner's own draws
(``jaxnc.loop.draw``), so both compute the same run (``tests/test_bench_direct.py``
checks that). What it leaves out is the runner's generality: rings of packets and
inboxes, blends for gradients, the believed-actuator copy, records.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnc import loop as nc
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update

NEVER = 2**30


def direct_cost(loop: nc.Loop, key):
    """Cost of one run of the cart-pole ``loop`` (inf when it fails), written directly."""
    plant, ekf, ctrl, trig = loop.plant, loop.estimator, loop.controller, loop.trigger
    D, S = ekf.buffer, loop.steps                       # N = 1: slow instants = fast instants
    d = nc.draw(loop, key)
    K = jnp.asarray(ctrl.K)
    Q, R = jnp.asarray(ekf.Q), jnp.asarray(ekf.R)
    bounds = jnp.asarray(loop.monitor.bounds)
    q, r = jnp.asarray(loop.cost.Q), jnp.asarray(loop.cost.R)
    g0 = Gaussian(jnp.asarray(ekf.mean0, jnp.float32), jnp.asarray(ekf.cov0, jnp.float32))
    x0 = plant.init(d.init_key)
    p = plant.output_dim

    def predict(g, u):
        return ekf_predict(plant.dynamics, g, u, Q, plant.noise_dim)

    def correct(g, z, ok):
        post = ekf_update(plant.measure, g, z, R, p)
        return jax.tree.map(lambda a, b: jnp.where(ok, a, b), post, g)

    def step(c, inp):
        x, last, base, us, zs, arr, failed, J = c
        k, w, v, delay = inp
        z = plant.measure(x, v)
        fire = (jnp.sum((last - z) ** 2) > jnp.sum(trig.sigma * z * z + trig.delta * jnp.ones_like(z))) | (k == 0)
        last = jnp.where(fire, z, last)
        # the window's measurements: zs[i], arr[i] of instant k - D + i (i = D: now)
        zs = jnp.concatenate([zs[1:], z[None]])
        arr = jnp.concatenate([arr[1:], jnp.where(fire & (delay >= 0), k + delay, NEVER)[None]])
        def instant(cw, xs):                              # re-run k - D .. k - 1 (a scan: one compiled step)
            g, nb = cw
            i, ui, zi, ai = xs
            s = k - D + i
            g1 = predict(correct(g, zi, ai <= k), ui)
            g = jax.tree.map(lambda a, b: jnp.where(s >= 0, a, b), g1, g)
            nb = jax.tree.map(lambda a, b: jnp.where(i == 0, a, b), g, nb)
            return (g, nb), None

        (g, next_base), _ = jax.lax.scan(instant, (base, base), (jnp.arange(D), us, zs[:D], arr[:D]))
        post = correct(g, zs[D], arr[D] <= k)
        u = jnp.clip(-(K @ post.mean), ctrl.u_min, ctrl.u_max)
        x_new = plant.dynamics(x, u, w)
        bad = ~jnp.all(jnp.isfinite(x_new)) | jnp.any(jnp.abs(x_new) > bounds)
        failed = failed | bad
        x_new = jnp.where(failed, x, x_new)
        J = J + x @ (q * x) + u @ (r * u)
        us = jnp.concatenate([us[1:], u[None]])
        return (x_new, last, next_base, us, zs, arr, failed, J), None

    m = plant.input_dim
    c0 = (x0, jnp.zeros((p,), jnp.float32), g0, jnp.zeros((D, m), jnp.float32), jnp.zeros((D + 1, p), jnp.float32),
          jnp.full((D + 1,), NEVER, jnp.int32), jnp.zeros((), bool), jnp.zeros((), jnp.float32))
    (x, *_, failed, J), _ = jax.lax.scan(step, c0, (jnp.arange(S, dtype=jnp.int32), d.w[:, 0], d.v,
                                                    d.uplink.delay))
    return jnp.where(failed, jnp.inf, J / S)
