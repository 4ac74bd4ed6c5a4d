"""The runner against the same small loop written directly (issue 32's 12-15x case).

Run:  .venv/bin/python benchmarks/bench_servo.py [--batches 1000 10000] [--repeat 3] [--no-record]

The loop is ``benchmarks/direct_servo.py``'s servo (2 states, Gilbert-Elliott loss,
discrete delays, PETC, Kalman filter with a 3-period window of late measurements, PI),
run three ways on the same draws: through ``jaxnc.loop.run``, written directly with the
library's filter kernels (``direct_cost``), and written by hand with the scalar filter in
closed form (``hand_cost``); ``tests/test_bench_direct.py`` checks the three give equal
runs. Each program is compiled once per batch size (first call minus the best repeat),
then timed ``--repeat`` times, interleaved so machine load hits all three. Both wall time
and the process's CPU time are reported (the CPU time is less sensitive to other jobs on
a shared machine); the ratios are measured in the same run. Appends the table to
benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from _record import record  # noqa: E402
from benchmarks.direct_servo import direct_cost, hand_cost, servo  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.report import markdown_table  # noqa: E402

NAMES = ("runner (jaxnc.loop.run)", "direct, library kernels", "direct, by hand")


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0, time.process_time() - c0


def bench(batches, repeat):
    loop = servo()
    fns = dict(zip(NAMES, (lambda k, lp: nc.run(lp, k).cost, lambda k, lp: direct_cost(lp, k),
                           lambda k, lp: hand_cost(lp, k))))
    rows = []
    for B in batches:
        keys = montecarlo.seed_keys(0, B)
        progs = {name: jax.jit(jax.vmap(fn, in_axes=(0, None))) for name, fn in fns.items()}
        first = {name: _timed(lambda: prog(keys, loop))[0] for name, prog in progs.items()}
        wall, cpu = {n: np.inf for n in fns}, {n: np.inf for n in fns}
        for _ in range(repeat):
            for name, prog in progs.items():
                w, c = _timed(lambda: prog(keys, loop))
                wall[name], cpu[name] = min(wall[name], w), min(cpu[name], c)
        comp = {n: max(first[n] - wall[n], 0.0) for n in fns}
        for name in fns:
            rows.append([name, B, f"{comp[name]:.2f}", f"{wall[name]:.3f}", f"{B * loop.steps / wall[name]:,.0f}",
                         f"{B * loop.steps / cpu[name]:,.0f}"])
        r = NAMES[0]
        for base in NAMES[1:]:
            rows.append([f"**runner / {base}**", B, f"compile x{comp[r] / max(comp[base], 1e-9):.2f}", "",
                         f"throughput x{wall[base] / wall[r]:.3f}", f"x{cpu[base] / cpu[r]:.3f}"])
    return markdown_table(["loop (servo, benchmarks/direct_servo.py)", "seeds", "compile (s)", "run (s)",
                           "seed-steps/s (wall)", "seed-steps/s (CPU time)"], rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md")
    a = ap.parse_args()
    table = bench(a.batches, a.repeat)
    load = f"Load average {os.getloadavg()[0]:.1f} at the end (machine shared with other sessions)."
    print(table)
    print(load)
    if not a.no_record:
        record(a.results, ["### The runner against the servo loop written directly\n\n" + table], note=load)


if __name__ == "__main__":
    main()
