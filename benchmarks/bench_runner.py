"""The one runner's throughput and compile time on seed-000 loops (default DRHE, N = 10, DP = 0.5).

Run:  .venv/bin/python benchmarks/bench_runner.py [--batches 1000 10000] [--cpu-devices 2] [--cells DRHE:10 DRHE:1]
      [--chunks 1024 2048]

Throughput is in seed-steps/s (seeds x fast periods per second; issue 32's goal: DRHE N = 10 at
10 000 seeds >= 3 M on two cores, N = 1 >= 1 M); ``--batches 1000`` is the quick form.

The loop runs through montecarlo.run_batched with the configuration as a runtime
argument (best of the repeats), in one chunk of all the seeds, or in chunks of each size
of ``--chunks`` (a size at or above the seed count: one chunk; each size compiles its own
program). To compare against another version of the code in the same conditions, run this
script in a checkout of that version right after (the hand-written loop it was first
compared with is retired). Prints a table and appends it to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from _record import record  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.report import markdown_table  # noqa: E402
from jaxnc.schemes import mecanum as runner_impl  # noqa: E402


def _runner_seed(key, loop):
    return runner_impl.run(loop, key)


def bench(batches, repeat, case="DRHE", N=10, dp=0.5, rows=None, chunks=None):
    """Rows (cell, seeds, chunk size, compile s, compile CPU s, best wall s, seed-steps/s, its process CPU s,
    seed-steps per CPU-second): on a shared machine the CPU times are the steadier figures
    (compile: the first call's time less the best call's, wall and CPU). ``chunks``: the
    chunk sizes to run each seed count with (None: one chunk of all the seeds)."""
    impls = {"runner (jaxnc.loop)": (runner_impl.mecanum_loop(case, N, dp), _runner_seed)}
    rows, rates = ([] if rows is None else rows), {}
    for B, C in ((B, min(C, B)) for B in batches for C in (chunks or [B])):
        keys = montecarlo.seed_keys(0, B)
        first, first_cpu, best, cpu = {}, {}, {}, {}
        for name, (loop, fn) in impls.items():
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(montecarlo.run_batched(fn, keys, args=(loop,), chunk_size=C, progress=False).J1)
            first[name], first_cpu[name] = time.perf_counter() - t0, time.process_time() - c0
            best[name] = cpu[name] = np.inf
        for _ in range(repeat):
            for name, (loop, fn) in impls.items():
                t0, c0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(montecarlo.run_batched(fn, keys, args=(loop,), chunk_size=C, progress=False).J1)
                best[name] = min(best[name], time.perf_counter() - t0)
                cpu[name] = min(cpu[name], time.process_time() - c0)
        steps = next(iter(impls.values()))[0].steps
        for name in impls:
            rates[(name, B)] = B * steps / best[name]
            rows.append([f"{case} N={N} DP={dp}, {name}", B, C, f"{max(first[name] - best[name], 0):.1f}",
                         f"{max(first_cpu[name] - cpu[name], 0):.1f}", f"{best[name]:.2f}", f"{rates[(name, B)]:,.0f}",
                         f"{cpu[name]:.2f}", f"{B * steps / cpu[name]:,.0f}"])
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--cpu-devices", type=int, default=1)
    ap.add_argument("--cells", nargs="+", default=["DRHE:10"], help="CASE:N pairs, e.g. DRHE:10 DRHE:1 SR:10")
    ap.add_argument("--dp", type=float, default=0.5)
    ap.add_argument("--chunks", type=int, nargs="+", help="chunk sizes (default: one chunk of all the seeds)")
    ap.add_argument("--no-record", action="store_true")
    a = ap.parse_args()
    if a.cpu_devices > 1:
        jax.config.update("jax_num_cpu_devices", a.cpu_devices)
    rows = []
    for cell in a.cells:
        case, N = cell.split(":")
        bench(a.batches, a.repeat, case, int(N), a.dp, rows, a.chunks)
    table = markdown_table(["closed loop (Lissajous)", "seeds", "chunk", "compile s", "compile CPU s", "run s",
                            "seed-steps/s", "CPU s", "seed-steps per CPU-s"], rows)
    print(table)
    if not a.no_record:
        record(HERE / "RESULTS.md", [table], note="The runner's seed-000 loops (runner's own draws).")


if __name__ == "__main__":
    main()
