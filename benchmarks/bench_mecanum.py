"""Throughput of the seed-000 Mecanum loops and of the EKF against a NumPy baseline.

Run:  make bench        (or: .venv/bin/python benchmarks/bench_mecanum.py [--quick])

Prints a table and appends it to benchmarks/RESULTS.md with the command, machine,
JAX version and date. All ratios are measured in the same run (machines are noisy).
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import montecarlo
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.plants.mecanum import Mecanum, MecanumNoise
from jaxnc.report import markdown_table
from jaxnc.schemes import mecanum as mec

HERE = Path(__file__).resolve().parent


def _time(f, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(f())
        best = min(best, time.perf_counter() - t)
    return best


# -- EKF: NumPy per-seed loop (what one writes by hand) vs jit(vmap(scan)) -------------
def numpy_ekf(plant, noise, steps, rng, p_drop=0.3):
    """Per-seed float64 EKF with analytic Jacobians and np.linalg.solve."""
    R, T, L = plant.R, plant.T, plant.Lx + plant.Ly
    b = np.asarray(plant.beacons, float)
    dz2 = (plant.z_fb - plant.z_mb) ** 2
    G = np.array([[1, 1, 1, 1], [-1, 1, 1, -1], [-1 / L, 1 / L, -1 / L, 1 / L]]) * R / 4
    Q = np.asarray(noise.Q(), float)[:4, :4]
    Rm = np.asarray(noise.R(), float)
    x, P = np.zeros(6), np.eye(6) * 1e-3
    Hw = np.array([[1, -1, -L], [1, 1, L], [1, 1, -L], [1, -1, L]]) / R
    for _ in range(steps):
        u = np.full(4, 4.0)
        v = G @ u
        a = x[5] + v[2] * T
        c, s = np.cos(a), np.sin(a)
        x = np.concatenate([v, [x[3] + T * (v[0] * c - v[1] * s), x[4] + T * (v[0] * s + v[1] * c), a]])
        A = np.eye(6)
        A[:3, :3] = 0
        A[3, 5], A[4, 5] = T * (-v[0] * s - v[1] * c), T * (v[0] * c - v[1] * s)
        Lw = np.zeros((6, 4))
        Lw[:3] = G
        P = A @ P @ A.T + Lw @ Q @ Lw.T
        if rng.random() < p_drop:
            continue
        d = np.sqrt(np.sum((b - x[3:5]) ** 2, axis=1) + dz2)
        H = np.zeros((9, 6))
        H[:4, :3] = Hw
        H[4, 5] = 1
        H[5:, 3:5] = (x[3:5] - b) / d[:, None]
        zhat = np.concatenate([Hw @ x[:3], [x[5]], d])
        z = zhat + rng.normal(size=9) * 0.01
        S = H @ P @ H.T + Rm
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (z - zhat)
        IKH = np.eye(6) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T
    return x


def jax_ekf(plant, noise, steps, p_drop=0.3):
    Q, R = noise.Q(), noise.R()

    def one(key):
        kd, kz = jax.random.split(key)
        drop = jax.random.uniform(kd, (steps,)) < p_drop
        vz = jax.random.normal(kz, (steps, 9)) * 0.01

        def step(b, inp):
            d, v = inp
            b = ekf_predict(plant.dynamics, b, jnp.full(4, 4.0), Q, 7)
            z = plant.measure(b.mean, v)
            c = ekf_update(plant.measure, b, z, R, 9)
            return jax.tree.map(lambda a, o: jnp.where(d, o, a), c, b), None

        b, _ = jax.lax.scan(step, Gaussian(jnp.zeros(6), jnp.eye(6) * 1e-3), (drop, vz))
        return b.mean

    return jax.jit(jax.vmap(one))


def bench_ekf(batches, steps):
    plant, noise = Mecanum(), MecanumNoise()
    rng = np.random.default_rng(0)
    n_np = 20
    t_np = _time(lambda: [numpy_ekf(plant, noise, steps, rng) for _ in range(n_np)], repeat=1)
    np_rate = n_np * steps / t_np
    rows = [["NumPy per-seed loop (float64)", "-", f"{np_rate:,.0f}", "1.0"]]
    f = jax_ekf(plant, noise, steps)
    for B in batches:
        keys = montecarlo.seed_keys(0, B)
        t0 = time.perf_counter()
        jax.block_until_ready(f(keys))
        compile_s = time.perf_counter() - t0
        t = _time(lambda: f(keys))
        rate = B * steps / t
        rows.append([f"jaxnc EKF jit(vmap(scan)) B={B}", f"{compile_s:.1f}", f"{rate:,.0f}", f"{rate / np_rate:.1f}"])
    return markdown_table(["EKF steps (6 states, 9 outputs, 30 % drops)", "compile s", "steps/s", "x NumPy"], rows)


def bench_loops(batches):
    rows = []
    cells = [("SR", 1, 0.0), ("SR", 10, 0.5), ("DR", 10, 0.5), ("DRH", 10, 0.5), ("DRHE", 10, 0.5)]
    for case, N, dp in cells:
        loop = mec.mecanum_loop(case, N, dp)
        fn = lambda k, loop=loop: mec.run(loop, k)
        for B in batches:
            keys = montecarlo.seed_keys(0, B)
            t0 = time.perf_counter()
            montecarlo.run_batched(fn, keys, chunk_size=max(B, 16), progress=False)
            first = time.perf_counter() - t0
            t = _time(lambda: montecarlo.run_batched(fn, keys, chunk_size=max(B, 16), progress=False), repeat=2)
            rows.append([f"{case} N={N} DP={dp} h={loop.h}", B, f"{first - t:.1f}", f"{t:.2f}",
                         f"{B * loop.steps / t:,.0f}"])
    return markdown_table(["closed loop (Lissajous)", "seeds", "compile s", "run s", "seed-steps/s"], rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller batches")
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    a = ap.parse_args()
    batches = [1, 100] if a.quick else [1, 100, 1000]
    ekf = bench_ekf(batches, steps=2000)
    print(ekf, flush=True)
    loops = bench_loops(batches)
    print(loops, flush=True)
    if not a.no_record:
        cmd = "python benchmarks/bench_mecanum.py" + (" --quick" if a.quick else "")
        head = (f"\n## {datetime.date.today()} — `{cmd}`\n\n"
                f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.platform()}; "
                f"jax {jax.__version__}, backend {jax.default_backend()}, Python {sys.version.split()[0]}\n\n")
        with open(HERE / "RESULTS.md", "a") as f:
            f.write(head + ekf + "\n\n" + loops + "\n")


if __name__ == "__main__":
    main()
