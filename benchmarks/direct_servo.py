"""The issue-32 small loop, as a runner :class:`~jaxnc.loop.Loop` of library parts and
written directly as one ``lax.scan``: the baseline the runner is measured against.

The loop (:func:`servo`): a 2-state position servo (a DC motor Km / (s (tau s + 1)),
exact ZOH at T = 5 ms), its angle sent over a Gilbert-Elliott (bursty) link with a
discrete delay law of 0-3 fast periods when PETC decides, a Kalman filter (the
:class:`~jaxnc.loop.EKF` on the linear model) with a 3-period window for late
measurements, a saturated PI on the estimated angle (clamping anti-windup, computing
every period), an ideal downlink and a hold-last actuator; quadratic cost.

:func:`direct_cost` computes the same run on the runner's own draws
(:func:`jaxnc.loop.draw`) with the same kernels (:mod:`jaxnc.estimators.ekf`,
:func:`jaxnc.loop.petc_gap`), so a speed ratio means something
(``tests/test_bench_direct.py`` checks the two are equal). What it leaves out is the
runner's generality: rings of packets and inboxes, blends for gradients, the
believed-actuator copy, records.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update

T, STEPS = 0.005, 1000                                 # 200 Hz, 5 s
NEVER = 2**30


def servo(delta=1e-4, buffer=3, steps=STEPS):
    """The servo loop of the module docstring (angle regulated from 1 rad to 0)."""
    Km, tau = 10.0, 0.05
    plant = nc.LTI.from_continuous([[0.0, 1.0], [0.0, -1.0 / tau]], [0.0, Km / tau], [[1.0, 0.0]], T,
                                   x0=[1.0, 0.0], w_std=[1e-4, 1e-2], v_std=[2e-3])
    kf = nc.EKF(plant, Q=np.asarray(plant.w_std) ** 2, R=np.diag(np.asarray(plant.v_std) ** 2),
                mean0=[1.0, 0.0], cov0=np.diag([1e-2, 1e-1]), buffer=buffer)
    link = nc.Link(nc.GilbertElliott(p_gb=0.05, p_bg=0.3, loss_good=0.02, loss_bad=0.7),
                   nc.PmfDelay([0.4, 0.3, 0.2, 0.1]), order="all", capacity=buffer + 1)
    pi = nc.PID(Kp=2.0, Ki=1.0, u_min=-12.0, u_max=12.0, index=0, anti_windup="clamping", hold=False)
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=link, estimator=kf, controller=pi,
                   downlink=nc.Link(), actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 0.01], R=[1e-3]),
                   T=T, steps=steps, record=("x", "u"))


def direct_cost(loop: nc.Loop, key):
    """Cost of one run of the servo ``loop`` (inf when it fails), written directly."""
    plant, kf, pi, trig = loop.plant, loop.estimator, loop.controller, loop.trigger
    D, S = kf.buffer, loop.steps                         # N = 1: slow instants = fast instants
    d = nc.draw(loop, key)
    A, B, C = (jnp.asarray(a) for a in (plant.A, plant.B, plant.C))
    Q, R = jnp.asarray(kf.Q), jnp.asarray(kf.R)
    Kp, Ki = jnp.asarray(pi.Kp), jnp.asarray(pi.Ki)
    lo, hi = jnp.asarray(pi.u_min), jnp.asarray(pi.u_max)
    q, r = jnp.asarray(loop.cost.Q), jnp.asarray(loop.cost.R)
    g0 = Gaussian(jnp.asarray(kf.mean0, jnp.float32), jnp.asarray(kf.cov0, jnp.float32))
    x0 = plant.init(d.init_key)
    p, h = plant.output_dim, loop.T

    def predict(g, u):
        return ekf_predict(plant.dynamics, g, u, Q, plant.noise_dim)

    def correct(g, z, ok):
        post = ekf_update(plant.measure, g, z, R, p)
        return jax.tree.map(lambda a, b: jnp.where(ok, a, b), post, g)

    def step(c, inp):
        x, last, base, us, zs, arr, integral, failed, J = c
        k, w, v, delay = inp
        z = C @ x + v
        gap = jnp.sum((last - z) ** 2) - jnp.sum(trig.sigma * z * z + trig.delta * jnp.ones_like(z))
        fire = (gap > 0) | (k == 0)
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
        # PI on the estimated angle, clamping anti-windup (reference 0)
        e = -post.mean[:1]
        vv = Kp * e + integral
        u = jnp.clip(vv, lo, hi)
        gain = Ki * e
        gain = jnp.where(((vv > hi) & (gain > 0)) | ((vv < lo) & (gain < 0)), 0.0, gain)
        integral = integral + h * gain
        x_new = A @ x + B @ u + w
        failed = failed | ~jnp.all(jnp.isfinite(x_new))
        x_new = jnp.where(failed, x, x_new)
        J = J + (x * x) @ q + (u * u) @ r
        us = jnp.concatenate([us[1:], u[None]])
        return (x_new, last, next_base, us, zs, arr, integral, failed, J), None

    m = plant.input_dim
    c0 = (x0, jnp.zeros((p,), jnp.float32), g0, jnp.zeros((D, m), jnp.float32), jnp.zeros((D + 1, p), jnp.float32),
          jnp.full((D + 1,), NEVER, jnp.int32), jnp.zeros((m,), jnp.float32), jnp.zeros((), bool),
          jnp.zeros((), jnp.float32))
    (*_, failed, J), _ = jax.lax.scan(step, c0, (jnp.arange(S, dtype=jnp.int32), d.w[:, 0], d.v,
                                                 d.uplink.delay))
    return jnp.where(failed, jnp.inf, J / S)


def hand_cost(loop: nc.Loop, key):
    """:func:`direct_cost` as a user writes a 2-state loop by hand: the Kalman filter of
    the one measured angle in closed form (scalar innovation, gain P h' / s, Joseph form
    written out, no Jacobians, no matrix factorisation), the model's matrices used
    directly. Same maths and draws as the runner; float rounding differs."""
    plant, kf, pi, trig = loop.plant, loop.estimator, loop.controller, loop.trigger
    D, S = kf.buffer, loop.steps
    d = nc.draw(loop, key)
    A, b = jnp.asarray(plant.A), jnp.asarray(plant.B)[:, 0]
    c = jnp.asarray(plant.C)[0]
    Qd, rv = jnp.diag(jnp.asarray(kf.Q)), jnp.asarray(kf.R)[0, 0]
    Kp, Ki = jnp.asarray(pi.Kp)[0], jnp.asarray(pi.Ki)[0]
    lo, hi = jnp.asarray(pi.u_min)[0], jnp.asarray(pi.u_max)[0]
    q, r = jnp.asarray(loop.cost.Q), jnp.asarray(loop.cost.R)[0]
    h = loop.T

    def predict(m, P, u):
        return A @ m + b * u, A @ P @ A.T + Qd

    def correct(m, P, z, ok):
        Ph = P @ c
        s = c @ Ph + rv
        K = Ph / s
        IKH = jnp.eye(2, dtype=P.dtype) - jnp.outer(K, c)
        P2 = IKH @ P @ IKH.T + rv * jnp.outer(K, K)
        return jnp.where(ok, m + K * (z - c @ m), m), jnp.where(ok, 0.5 * (P2 + P2.T), P)

    def step(carry, inp):
        x, last, bm, bP, us, zs, arr, integral, failed, J = carry
        k, w, v, delay = inp
        z = c @ x + v[0]
        fire = ((last - z) ** 2 - (trig.sigma * z * z + trig.delta) > 0) | (k == 0)
        last = jnp.where(fire, z, last)
        zs = jnp.concatenate([zs[1:], z[None]])
        arr = jnp.concatenate([arr[1:], jnp.where(fire & (delay >= 0), k + delay, NEVER)[None]])
        m, P = bm, bP
        nbm, nbP = bm, bP
        for i in range(D):
            s = k - D + i
            m1, P1 = predict(*correct(m, P, zs[i], arr[i] <= k), us[i])
            m, P = jnp.where(s >= 0, m1, m), jnp.where(s >= 0, P1, P)
            if i == 0:
                nbm, nbP = m, P
        m, P = correct(m, P, zs[D], arr[D] <= k)
        e = -m[0]
        vv = Kp * e + integral
        u = jnp.clip(vv, lo, hi)
        gain = Ki * e
        gain = jnp.where(((vv > hi) & (gain > 0)) | ((vv < lo) & (gain < 0)), 0.0, gain)
        integral = integral + h * gain
        x_new = A @ x + b * u + w
        failed = failed | ~jnp.all(jnp.isfinite(x_new))
        x_new = jnp.where(failed, x, x_new)
        J = J + (x * x) @ q + r * u * u
        us = jnp.concatenate([us[1:], u[None]])
        return (x_new, last, nbm, nbP, us, zs, arr, integral, failed, J), None

    f32 = jnp.float32
    c0 = (plant.init(d.init_key), jnp.zeros((), f32), jnp.asarray(kf.mean0, f32), jnp.asarray(kf.cov0, f32),
          jnp.zeros((D,), f32), jnp.zeros((D + 1,), f32), jnp.full((D + 1,), NEVER, jnp.int32), jnp.zeros((), f32),
          jnp.zeros((), bool), jnp.zeros((), f32))
    (*_, failed, J), _ = jax.lax.scan(step, c0, (jnp.arange(S, dtype=jnp.int32), d.w[:, 0], d.v, d.uplink.delay))
    return jnp.where(failed, jnp.inf, J / S)
