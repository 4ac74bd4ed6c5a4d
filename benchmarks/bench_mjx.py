"""MJX Mecanum platform: physics steps per second against MuJoCo's C ``mj_step``.

Run:  .venv/bin/python benchmarks/bench_mjx.py [--quick] [--no-record]
      (needs the extra: pip install 'jaxnc[mjx]')

Same model (jaxnc.plants.mecanum_mjx.mecanum_mjcf) and the same open-loop wheel
torques in every row, measured in one run:

* C ``mj_step`` in a Python loop, one seed after another (what a user writes first);
* C ``mujoco.rollout`` (the loop in C, multi-threaded over seeds, one thread per core);
* MJX ``jit(vmap(scan(mjx.step)))`` at B = 1, 64, 512 seeds, with its compile time;

and the study a user runs: DRHE at N = 10, DP = 0.5 on the MJX plant, 256 seeds x
60 s of simulated time, through ``montecarlo.run_batched`` (compile included).
Appends the tables to benchmarks/RESULTS.md with the command, machine and date.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from _record import record
from jaxnc import montecarlo
from jaxnc.report import markdown_table

HERE = Path(__file__).resolve().parent
TORQUE = np.array([0.02, 0.02, 0.02, 0.02])   # N m per wheel: the robot accelerates forward


def _best(f, repeat=2):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def bench_c(steps, seeds):
    import mujoco
    import mujoco.rollout
    from jaxnc.plants.mecanum_mjx import mecanum_mjcf

    m = mujoco.MjModel.from_xml_string(mecanum_mjcf())
    rows = []

    def loop():
        for _ in range(seeds):
            d = mujoco.MjData(m)
            d.ctrl[:] = TORQUE
            for _ in range(steps):
                mujoco.mj_step(m, d)

    t = _best(loop)
    rows.append(("C mj_step, Python loop over seeds", seeds, "-", t, seeds * steps / t))
    nthread = os.cpu_count() or 1
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    d0 = mujoco.MjData(m)
    mujoco.mj_forward(m, d0)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d0, s, spec)
    state0 = np.tile(s, (seeds, 1))
    ctrl = np.broadcast_to(TORQUE, (seeds, steps, m.nu)).copy()
    t = _best(lambda: mujoco.rollout.rollout(m, datas, state0, ctrl))
    rows.append((f"C mujoco.rollout, {nthread} threads", seeds, "-", t, seeds * steps / t))
    return rows


def bench_mjx(steps, batches):
    import mujoco
    from mujoco import mjx
    from jaxnc.plants.mecanum_mjx import mecanum_mjcf

    m = mujoco.MjModel.from_xml_string(mecanum_mjcf())
    mx = mjx.put_model(m)
    d0 = mjx.make_data(mx).replace(ctrl=jnp.asarray(TORQUE, jnp.float32))

    def rollout(d):
        return jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), d, None, length=steps)[0].qpos

    rows = []
    for B in batches:
        d = jax.tree.map(lambda a: jnp.broadcast_to(a, (B, *a.shape)) if isinstance(a, jax.Array) else a, d0)
        f = jax.jit(jax.vmap(rollout))
        t = time.perf_counter()
        compiled = f.lower(d).compile()
        comp = time.perf_counter() - t
        t = _best(lambda: jax.block_until_ready(compiled(d)))
        rows.append((f"MJX jit(vmap(scan(mjx.step))) B={B}", B, f"{comp:.1f}", t, B * steps / t))
    return rows


def bench_study(seeds, seconds, chunk=256):
    from jaxnc.experiments.mecanum import run_seed, uniform_dtypes
    from jaxnc.plants.mecanum_mjx import mjx_mecanum
    from jaxnc.schemes import mecanum as mec

    loop = mec.mecanum_loop("DRHE", 10, 0.5, truth=mjx_mecanum(), horizon_s=seconds)
    keys = montecarlo.seed_keys(0, seeds)
    t = time.perf_counter()
    metrics = montecarlo.run_batched(run_seed, keys, args=(uniform_dtypes(loop),), chunk_size=chunk,
                                     progress=True, desc="DRHE on MJX")
    jax.block_until_ready(metrics)
    wall = time.perf_counter() - t
    physics = seeds * loop.steps * loop.plant.substeps
    return [(f"DRHE N=10 DP=0.5 on MJX, {seconds:g} s simulated", seeds, f"{wall:.0f}", physics, physics / wall)]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--skip-study", action="store_true", help="physics tables only")
    ap.add_argument("--batches", type=int, nargs="+", help="MJX seed counts (default 1 64 512), e.g. more on a GPU")
    ap.add_argument("--study-seeds", type=int, help="seeds of the closed-loop study (default 256)")
    ap.add_argument("--chunk", type=int, default=256, help="seeds per compiled batch in the study (more on a GPU)")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md", help="file the tables are appended to")
    args = ap.parse_args()
    steps = 50 if args.quick else 200
    batches = args.batches or ((1, 8) if args.quick else (1, 64, 512))
    c_seeds = 4 if args.quick else 64
    rows = bench_c(steps, c_seeds) + bench_mjx(steps, batches)
    c_rate = rows[0][4]
    table1 = markdown_table(
        ["physics, open-loop torques", "seeds", "compile s", "run s", "steps/s", "x C loop"],
        [[r[0], r[1], r[2], f"{r[3]:.3f}", f"{r[4]:,.0f}", f"{r[4] / c_rate:.2f}"] for r in rows])
    print(table1)
    table2 = ""
    if not args.skip_study:
        study = bench_study(args.study_seeds or (8 if args.quick else 256), 10.0 if args.quick else 60.0, args.chunk)
        table2 = markdown_table(["closed-loop study", "seeds", "wall s (incl. compile)", "physics steps", "steps/s"],
                                [[r[0], r[1], r[2], f"{r[3]:,}", f"{r[4]:,.0f}"] for r in study])
        print(table2)
    if not args.no_record:
        import mujoco
        record(args.results, [table1, table2],
               f"mujoco {mujoco.__version__}; {steps} physics steps of 5 ms per seed; C is float64, MJX float32.")


if __name__ == "__main__":
    main()
