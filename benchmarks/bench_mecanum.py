"""Throughput of the seed-000 Mecanum loops and of the EKF against a NumPy baseline.

Run:  make bench        (or: .venv/bin/python benchmarks/bench_mecanum.py [--quick])

Prints a table and appends it to benchmarks/RESULTS.md with the command, machine,
JAX version and date. All ratios are measured in the same run (machines are noisy).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from _record import record
from jaxnc import montecarlo
from jaxnc.experiments.mecanum import run_seed
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update, ekf_update_diag
from jaxnc.estimators.ekf_batched import ekf_filter
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


# -- EKF: NumPy per-seed loop (what one writes by hand) vs jit(vmap(scan)) vs ekf_filter --
P_DROP = 0.3


def ekf_data(plant, noise, B, steps, seed=0):
    """The filters' input, generated once outside the timings: per seed, wheel commands
    near 4 rad/s, the true run of the plant with process noise, its noisy measurements
    and 30 % Bernoulli drops. Returns float32 us (B, K, 4), zs (B, K, 9), valid (B, K)."""
    def one(key):
        ku, kw, kv, kd = jax.random.split(key, 4)
        us = 4.0 + 0.5 * jax.random.normal(ku, (steps, 4))
        ws = noise.process_std()[None] * jax.random.normal(kw, (steps, 7))
        vs = noise.measurement_std()[None] * jax.random.normal(kv, (steps, 9))

        def step(x, inp):
            x = plant.dynamics(x, inp[0], inp[1])
            return x, plant.measure(x, inp[2])
        zs = jax.lax.scan(step, jnp.zeros(6), (us, ws, vs))[1]
        return us, zs, jax.random.uniform(kd, (steps,)) >= P_DROP
    return jax.jit(jax.vmap(one))(montecarlo.seed_keys(seed, B))


def numpy_ekf(plant, noise, us, zs, valid):
    """One seed's float64 EKF with analytic Jacobians and np.linalg.solve."""
    R, T, L = plant.R, plant.T, plant.Lx + plant.Ly
    b = np.asarray(plant.beacons, float)
    dz2 = (plant.z_fb - plant.z_mb) ** 2
    G = np.array([[1, 1, 1, 1], [-1, 1, 1, -1], [-1 / L, 1 / L, -1 / L, 1 / L]]) * R / 4
    Q = np.asarray(noise.Q(), float)[:4, :4]
    Rm = np.asarray(noise.R(), float)
    x, P = np.zeros(6), np.eye(6) * 1e-3
    Hw = np.array([[1, -1, -L], [1, 1, L], [1, 1, -L], [1, -1, L]]) / R
    for u, z, ok in zip(us, zs, valid):
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
        if not ok:
            continue
        d = np.sqrt(np.sum((b - x[3:5]) ** 2, axis=1) + dz2)
        H = np.zeros((9, 6))
        H[:4, :3] = Hw
        H[4, 5] = 1
        H[5:, 3:5] = (x[3:5] - b) / d[:, None]
        zhat = np.concatenate([Hw @ x[:3], [x[5]], d])
        S = H @ P @ H.T + Rm
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (z - zhat)
        IKH = np.eye(6) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T
    return x


def jax_ekf(plant, noise, sequential=False, structured=False):
    """jit(vmap(scan)) of the per-seed ``ekf`` functions (the closed loops' form);
    ``structured``: with the Jacobians' sparsity and Q as a vector of variances."""
    Q, R = noise.Q(), noise.R()
    r = noise.measurement_std() ** 2
    st = mec.ekf_structure(plant) if structured else None
    Q = noise.process_std() ** 2 if structured else Q

    def one(us, zs, valid):
        def step(b, inp):
            u, z, ok = inp
            b = ekf_predict(plant.dynamics, b, u, Q, 7, structure=st)
            c = (ekf_update_diag(plant.measure, b, z, r, 9, structure=st) if sequential
                 else ekf_update(plant.measure, b, z, R, 9))
            return jax.tree.map(lambda a, o: jnp.where(ok, o, a), b, c), None

        b, _ = jax.lax.scan(step, Gaussian(jnp.zeros(6), jnp.eye(6) * 1e-3), (us, zs, valid))
        return b.mean

    return jax.jit(jax.vmap(one))


def jax_ekf_filter(plant, noise, structured=False):
    """``ekf_batched.ekf_filter``: the whole filter with the seed axis last; ``structured``:
    with the Jacobians' sparsity (``jaxnc.estimators.sparsity``) and Q as a vector."""
    Q, r = noise.Q(), noise.measurement_std() ** 2
    st = mec.ekf_structure(plant) if structured else None
    Q = noise.process_std() ** 2 if structured else Q

    def run(us, zs, valid):
        B = us.shape[0]
        b0 = Gaussian(jnp.zeros((B, 6)), jnp.broadcast_to(jnp.eye(6) * 1e-3, (B, 6, 6)))
        return ekf_filter(plant.dynamics, plant.measure, b0, us, zs, valid, Q, r, noise_dim=7, structure=st).mean

    return jax.jit(run)


def bench_ekf(batches, steps):
    plant, noise = Mecanum(), MecanumNoise()
    n_np = 20
    us, zs, valid = (np.asarray(a, np.float64) for a in ekf_data(plant, noise, n_np, steps, seed=1))
    t_np = _time(lambda: [numpy_ekf(plant, noise, us[i], zs[i], valid[i] > 0) for i in range(n_np)], repeat=1)
    np_rate = n_np * steps / t_np
    rows = [["NumPy per-seed loop (float64)", "-", f"{np_rate:,.0f}", "1.0"]]
    # (name, filter, may split the seeds over devices). The Cholesky variant stays on one
    # device: split over two CPU devices at B = 10 000 its LAPACK calls deadlocked (jax 0.10.2).
    filters = (("jit(vmap(scan)) of ekf, Cholesky update", jax_ekf(plant, noise, sequential=False), False),
               ("jit(vmap(scan)) of ekf, sequential scalar update", jax_ekf(plant, noise, sequential=True), True),
               ("jit(vmap(scan)) of ekf, sequential scalar update, structured", jax_ekf(plant, noise, True, True), True),
               ("ekf_filter (seed axis last), sequential scalar update", jax_ekf_filter(plant, noise), True),
               ("ekf_filter (seed axis last), sequential scalar update, structured",
                jax_ekf_filter(plant, noise, structured=True), True))
    devices = jax.devices()
    seeds = montecarlo.seed_sharding(devices)
    for B in batches:
        one = ekf_data(plant, noise, B, steps)
        split = one
        if len(devices) > 1 and B % len(devices) == 0:          # seeds split over the devices, as run_batched does
            split = tuple(jax.device_put(a, seeds) for a in one)
        jax.block_until_ready(split)
        for name, f, may_split in filters:
            data = split if may_split else one
            ndev = len(data[0].sharding.device_set)
            name = f"{name}, B={B}" + (f", {ndev} devices" if ndev > 1 else "")
            t0 = time.perf_counter()
            jax.block_until_ready(f(*data))
            compile_s = time.perf_counter() - t0
            t = _time(lambda: f(*data), repeat=2)
            rate = B * steps / t
            rows.append([name, f"{compile_s:.1f}", f"{rate:,.0f}", f"{rate / np_rate:.1f}"])
    return markdown_table([f"EKF steps (6 states, 9 outputs, 30 % drops, {steps} steps per seed)", "compile s",
                           "steps/s", "x NumPy"], rows)


def bench_loops(batches):
    """Closed loops through run_batched with the configuration as a runtime argument:
    one compilation per N serves every case (the grid experiment's path)."""
    rows = []
    cells = [("SR", 1, 0.0), ("SR", 10, 0.5), ("DR", 10, 0.5), ("DRH", 10, 0.5), ("DRHE", 10, 0.5), ("DRHE", 1, 0.5),
             ("DRHE", 10, 0.5, False)]          # the last without the Jacobians' sparsity (dense EKF)
    for case, N, dp, *sparse in cells:
        loop = mec.mecanum_loop(case, N, dp, sparse=sparse[0] if sparse else True)
        for B in batches:
            keys = montecarlo.seed_keys(0, B)
            run = lambda: montecarlo.run_batched(run_seed, keys, args=(loop,), chunk_size=B, progress=False)
            t0 = time.perf_counter()
            run()
            first = time.perf_counter() - t0
            t = _time(run, repeat=2)
            dense = loop.estimator.structure is None
            rows.append([f"{case} N={N} DP={dp} h={int(loop.actuator.horizon) // N}" + (" (dense EKF)" if dense else ""), B, f"{max(first - t, 0.0):.1f}", f"{t:.2f}",
                         f"{B * loop.steps / t:,.0f}"])
    return markdown_table(["closed loop (Lissajous)", "seeds", "compile s", "run s", "seed-steps/s"], rows)


def bench_grad(B=64, repeat=5):
    """Cost of value_and_grad of a Monte-Carlo objective against the forward pass alone,
    exact and with the EKF Jacobians held constant in reverse mode (``jacobian_grad=False``:
    same simulation, approximate gradient; its distance to the exact one is reported).
    The four programs are timed interleaved (best of ``repeat``), so machine load hits all."""
    import dataclasses
    keys = montecarlo.seed_keys(0, B)
    progs = {}
    for exact in (True, False):
        loop = mec.mecanum_loop("DRHE", 10, 0.3, trigger_temperature=0.05, jacobian_grad=exact)

        def objective(delta, kp, loop=loop):
            lp = mec.with_follower(dataclasses.replace(loop, trigger=dataclasses.replace(loop.trigger, delta=delta)),
                                   Kp=kp)
            return jnp.mean(jax.vmap(lambda k: mec.tracking_cost(lp, k))(keys))

        args = (jnp.asarray(loop.trigger.delta), jnp.asarray(loop.controller.law.Kp))
        for name, f in (("forward", jax.jit(objective)),
                        ("value_and_grad", jax.jit(jax.value_and_grad(objective, argnums=(0, 1))))):
            t0 = time.perf_counter()
            out = jax.block_until_ready(f(*args))
            progs[(exact, name)] = [f, time.perf_counter() - t0, np.inf, out]
    for _ in range(repeat):
        for p in progs.values():
            t0 = time.perf_counter()
            jax.block_until_ready(p[0](*args))
            p[2] = min(p[2], time.perf_counter() - t0)
    flat = lambda exact: np.concatenate([np.ravel(g) for g in progs[(exact, "value_and_grad")][3][1]])
    rel = float(np.linalg.norm(flat(True) - flat(False)) / np.linalg.norm(flat(True)))
    # the two forward programs compute the same thing (stop_gradient is the identity): the
    # faster of the two is the forward pass both gradients are compared with
    t_fwd = min(progs[(e, "forward")][2] for e in (True, False))
    rows = []
    for exact in (True, False):
        label = "exact" if exact else "Jacobians held constant"
        fwd, vg = progs[(exact, "forward")], progs[(exact, "value_and_grad")]
        rows.append([f"forward ({label})", f"{fwd[1] - fwd[2]:.1f}", f"{fwd[2]:.3f}", ""])
        rows.append([f"value_and_grad ({label})", f"{vg[1] - vg[2]:.1f}", f"{vg[2]:.3f}",
                     f"{vg[2] / t_fwd:.2f}" + ("" if exact else f" (gradient {100 * rel:.2f} % from exact)")])
    return markdown_table([f"DRHE N=10 DP=0.3, mean tracking cost over {B} seeds", "compile s", "run s",
                           "grad / fastest forward"], rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller batches")
    ap.add_argument("--full", action="store_true", help="also B = 10 000")
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--cpu-devices", type=int, default=1, help="split the CPU into this many JAX devices")
    ap.add_argument("--batches", type=int, nargs="+", help="seed counts (overrides --quick/--full), e.g. on a GPU")
    ap.add_argument("--ekf-steps", type=int, default=500, help="steps per seed of the EKF benchmark")
    ap.add_argument("--only-ekf", action="store_true", help="run the EKF benchmark only")
    ap.add_argument("--only-grad", action="store_true", help="run the gradient-cost benchmark only")
    ap.add_argument("--grad-batches", type=int, nargs="+", default=[64],
                    help="seed counts of the gradient-cost benchmark (one table each)")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md", help="file the tables are appended to")
    a = ap.parse_args()
    if a.cpu_devices > 1:
        jax.config.update("jax_num_cpu_devices", a.cpu_devices)
    batches = a.batches or ([1, 100] if a.quick else ([1, 100, 1000, 10000] if a.full else [1, 100, 1000]))
    ekf = loops = grad = ""
    if not a.only_grad:
        ekf = bench_ekf(batches, steps=a.ekf_steps)
        print(ekf, flush=True)
    if not (a.only_ekf or a.only_grad):
        loops = bench_loops(batches)
        print(loops, flush=True)
    if not a.only_ekf:
        grad = "\n\n".join(bench_grad(B) for B in a.grad_batches)
        print(grad, flush=True)
    if not a.no_record:
        record(a.results, [ekf, loops, grad])


if __name__ == "__main__":
    main()
