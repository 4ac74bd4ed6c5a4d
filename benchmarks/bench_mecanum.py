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
from jaxnc.experiments.mecanum import run_seed
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update, ekf_update_diag
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


def jax_ekf(plant, noise, steps, p_drop=0.3, sequential=False):
    Q, R = noise.Q(), noise.R()
    r = noise.measurement_std() ** 2

    def one(key):
        kd, kz = jax.random.split(key)
        drop = jax.random.uniform(kd, (steps,)) < p_drop
        vz = jax.random.normal(kz, (steps, 9)) * 0.01

        def step(b, inp):
            d, v = inp
            b = ekf_predict(plant.dynamics, b, jnp.full(4, 4.0), Q, 7)
            z = plant.measure(b.mean, v)
            c = ekf_update_diag(plant.measure, b, z, r, 9) if sequential else ekf_update(plant.measure, b, z, R, 9)
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
    for seq in (False, True):
        f = jax_ekf(plant, noise, steps, sequential=seq)
        name = "sequential scalar update" if seq else "Cholesky update"
        for B in batches:
            keys = montecarlo.seed_keys(0, B)
            t0 = time.perf_counter()
            jax.block_until_ready(f(keys))
            compile_s = time.perf_counter() - t0
            t = _time(lambda: f(keys))
            rate = B * steps / t
            rows.append([f"jaxnc EKF, {name}, B={B}", f"{compile_s:.1f}", f"{rate:,.0f}", f"{rate / np_rate:.1f}"])
    return markdown_table(["EKF steps (6 states, 9 outputs, 30 % drops)", "compile s", "steps/s", "x NumPy"], rows)


def bench_loops(batches):
    """Closed loops through run_batched with the configuration as a runtime argument:
    one compilation per N serves every case (the grid experiment's path)."""
    rows = []
    cells = [("SR", 1, 0.0), ("SR", 10, 0.5), ("DR", 10, 0.5), ("DRH", 10, 0.5), ("DRHE", 10, 0.5), ("DRHE", 1, 0.5)]
    for case, N, dp in cells:
        loop = mec.mecanum_loop(case, N, dp)
        for B in batches:
            keys = montecarlo.seed_keys(0, B)
            run = lambda: montecarlo.run_batched(run_seed, keys, args=(loop,), chunk_size=B, progress=False)
            t0 = time.perf_counter()
            run()
            first = time.perf_counter() - t0
            t = _time(run, repeat=2)
            rows.append([f"{case} N={N} DP={dp} h={int(loop.h)}", B, f"{max(first - t, 0.0):.1f}", f"{t:.2f}",
                         f"{B * loop.steps / t:,.0f}"])
    return markdown_table(["closed loop (Lissajous)", "seeds", "compile s", "run s", "seed-steps/s"], rows)


def bench_grad(B=64):
    """Cost of value_and_grad of a Monte-Carlo objective against the forward pass alone."""
    import dataclasses
    loop = mec.mecanum_loop("DRHE", 10, 0.3, trigger_temperature=0.05)
    keys = montecarlo.seed_keys(0, B)

    def objective(delta, kp):
        lp = dataclasses.replace(loop, trigger=dataclasses.replace(loop.trigger, delta=delta),
                                 follower=dataclasses.replace(loop.follower, Kp=kp))
        return jnp.mean(jax.vmap(lambda k: mec.tracking_cost(lp, k))(keys))

    args = (jnp.asarray(loop.trigger.delta), jnp.asarray(loop.follower.Kp))
    fwd = jax.jit(objective)
    both = jax.jit(jax.value_and_grad(objective, argnums=(0, 1)))
    rows = []
    for name, f in (("forward", fwd), ("value_and_grad", both)):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        c = time.perf_counter() - t0
        t = _time(lambda: f(*args))
        rows.append([name, f"{c:.1f}", f"{t:.2f}"])
    ratio = float(rows[1][2]) / float(rows[0][2])
    rows.append(["ratio grad / forward", "", f"{ratio:.2f}"])
    return markdown_table([f"DRHE N=10 DP=0.3, mean tracking cost over {B} seeds", "compile s", "run s"], rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller batches")
    ap.add_argument("--full", action="store_true", help="also B = 10 000")
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--cpu-devices", type=int, default=1, help="split the CPU into this many JAX devices")
    ap.add_argument("--batches", type=int, nargs="+", help="seed counts (overrides --quick/--full), e.g. on a GPU")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md", help="file the tables are appended to")
    a = ap.parse_args()
    if a.cpu_devices > 1:
        jax.config.update("jax_num_cpu_devices", a.cpu_devices)
    batches = a.batches or ([1, 100] if a.quick else ([1, 100, 1000, 10000] if a.full else [1, 100, 1000]))
    ekf = bench_ekf(batches, steps=2000)
    print(ekf, flush=True)
    loops = bench_loops(batches)
    print(loops, flush=True)
    grad = bench_grad()
    print(grad, flush=True)
    if not a.no_record:
        cmd = "python benchmarks/bench_mecanum.py" + "".join(" " + a for a in sys.argv[1:])
        head = (f"\n## {datetime.date.today()} — `{cmd}`\n\n"
                f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.platform()}; "
                f"jax {jax.__version__}, backend {jax.default_backend()}, Python {sys.version.split()[0]}\n\n")
        with open(a.results, "a") as f:
            f.write(head + f"Devices: {len(jax.devices())} x {jax.devices()[0].device_kind}\n\n" + ekf + "\n\n" + loops + "\n\n" + grad + "\n")


if __name__ == "__main__":
    main()
