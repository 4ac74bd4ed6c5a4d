"""Batch-first (``ekf``) vs batch-last (``ekf_batched``) EKF kernels under ``vmap``.

Run:  .venv/bin/python benchmarks/bench_ekf_kernels.py [--quick] [--steps 100] [--batches 1000 10000]

Each seed runs a ``lax.scan`` of the Mecanum EKF (6 states, 7 process noises, 9
outputs, float32): ``predict`` alone, ``update`` (``ekf_update_diag``) alone, and the
filter step (predict, then update with 30 % of the measurements dropped), vmapped
over B seeds and jitted; ``value_and_grad`` differentiates the seed mean of a scalar
of the final belief w.r.t. Q (shared) and the initial means (per seed). Reports the
best of ``--repeat`` runs, CPU time (``time.process_time``, all threads) and wall
time per seed-step. Prints a Markdown table; records nothing.
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc.estimators import ekf as old
from jaxnc.estimators import ekf_batched as new
from jaxnc.plants.mecanum import OUTPUT_DIM, PROCESS_NOISE_DIM, Mecanum, MecanumNoise
from jaxnc.report import markdown_table


def make_filter(mod, what: str, steps: int):
    """``run(keys, Q, m0) -> Gaussian`` for B seeds; ``what`` in predict / update / step."""
    plant, noise = Mecanum(), MecanumNoise()
    r = noise.measurement_std() ** 2

    def one(key, Q, m0):
        ku, kv, kd, kp = jax.random.split(key, 4)
        us = 4.0 + jax.random.normal(ku, (steps, 4))
        vs = 0.01 * jax.random.normal(kv, (steps, OUTPUT_DIM))
        drop = jax.random.uniform(kd, (steps,)) < 0.3
        P0 = jnp.eye(6) * 1e-3 * (1.0 + jax.random.uniform(kp))

        def body(b, inp):
            u, v, d = inp
            if what in ("predict", "step"):
                b = mod.ekf_predict(plant.dynamics, b, u, Q, PROCESS_NOISE_DIM)
            if what in ("update", "step"):
                z = plant.measure(b.mean, v)
                c = mod.ekf_update_diag(plant.measure, b, z, r, OUTPUT_DIM)
                b = jax.tree.map(lambda a, o: jnp.where(d, o, a), c, b) if what == "step" else c
            return b, None

        b, _ = jax.lax.scan(body, old.Gaussian(m0, P0), (us, vs, drop))
        return b

    return jax.vmap(one, in_axes=(0, None, 0))


def objective(run):
    def f(Q, m0, keys):
        b = run(keys, Q, m0)
        return jnp.mean(jnp.sum(b.mean ** 2, axis=-1) + jnp.trace(b.cov, axis1=-2, axis2=-1))
    return f


def timed(f, args, repeat):
    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    compile_s = time.perf_counter() - t0
    cpu, wall = np.inf, np.inf
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        jax.block_until_ready(f(*args))
        cpu, wall = min(cpu, time.process_time() - c), min(wall, time.perf_counter() - w)
    return compile_s, cpu, wall


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="B = 1000 only, 50 steps, forward of the filter step")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--what", nargs="+", default=["predict", "update", "step"])
    ap.add_argument("--no-grad", action="store_true")
    a = ap.parse_args()
    if a.quick:
        a.batches, a.steps, a.what, a.no_grad = [1000], 50, ["step"], True
    Q = MecanumNoise().Q()
    rows = []
    for B in a.batches:
        keys = jax.random.split(jax.random.key(0), B)
        m0 = 0.1 * jax.random.normal(jax.random.key(1), (B, 6))
        modes = [("forward", w) for w in a.what] + ([] if a.no_grad else [("value_and_grad", "step")])
        for mode, what in modes:
            res = {}
            for name, mod in (("ekf", old), ("ekf_batched", new)):
                run = make_filter(mod, what, a.steps)
                if mode == "forward":
                    f = jax.jit(lambda k, Q, m0, run=run: run(k, Q, m0))
                    args = (keys, Q, m0)
                else:
                    f = jax.jit(jax.value_and_grad(objective(run), argnums=(0, 1)))
                    args = (Q, m0, keys)
                res[name] = timed(f, args, a.repeat)
            n = B * a.steps
            (c0, cpu0, w0), (c1, cpu1, w1) = res["ekf"], res["ekf_batched"]
            rows.append([f"{what} {mode}", B,
                         f"{cpu0 / n * 1e6:.3f}", f"{cpu1 / n * 1e6:.3f}",
                         f"{w0 / n * 1e6:.3f}", f"{w1 / n * 1e6:.3f}",
                         f"{n / w1:,.0f}", f"{w0 / w1:.2f}", f"{c0:.1f} / {c1:.1f}"])
            print(rows[-1], flush=True)
    head = ["kernel", "seeds B", "CPU us/step old", "CPU us/step new", "wall us/step old", "wall us/step new",
            "new steps/s", "speed-up (wall)", "compile s old / new"]
    print()
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, {a.steps} steps per seed, float32, "
          f"best of {a.repeat}")
    print()
    print(markdown_table(head, rows))


if __name__ == "__main__":
    main()
