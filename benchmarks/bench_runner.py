"""The one runner's throughput and compile time on seed-000 DRHE (N = 10, DP = 0.5).

Run:  .venv/bin/python benchmarks/bench_runner.py [--batches 1000 10000] [--cpu-devices 2]

The loop runs through montecarlo.run_batched with the configuration as a runtime
argument (best of the repeats). To compare against another version of the code in the
same conditions, run this script in a checkout of that version right after (the
hand-written loop it was first compared with is retired). Prints a table and appends it
to benchmarks/RESULTS.md.
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


def bench(batches, repeat, case="DRHE", N=10, dp=0.5):
    impls = {"runner (jaxnc.loop)": (runner_impl.mecanum_loop(case, N, dp), _runner_seed)}
    rows, rates = [], {}
    for B in batches:
        keys = montecarlo.seed_keys(0, B)
        first, best = {}, {}
        for name, (loop, fn) in impls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(montecarlo.run_batched(fn, keys, args=(loop,), chunk_size=B, progress=False).J1)
            first[name] = time.perf_counter() - t0
            best[name] = np.inf
        for _ in range(repeat):
            for name, (loop, fn) in impls.items():
                t0 = time.perf_counter()
                montecarlo.run_batched(fn, keys, args=(loop,), chunk_size=B, progress=False)
                best[name] = min(best[name], time.perf_counter() - t0)
        steps = next(iter(impls.values()))[0].steps
        for name in impls:
            rates[(name, B)] = B * steps / best[name]
            rows.append([f"{case} N={N} DP={dp}, {name}", B, f"{max(first[name] - best[name], 0):.1f}",
                         f"{best[name]:.2f}", f"{rates[(name, B)]:,.0f}"])
    return markdown_table(["closed loop (Lissajous)", "seeds", "compile s", "run s", "seed-steps/s"], rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--cpu-devices", type=int, default=1)
    ap.add_argument("--no-record", action="store_true")
    a = ap.parse_args()
    if a.cpu_devices > 1:
        jax.config.update("jax_num_cpu_devices", a.cpu_devices)
    table = bench(a.batches, a.repeat)
    print(table)
    if not a.no_record:
        record(HERE / "RESULTS.md", [table], note="The runner's seed-000 DRHE loop (runner's own draws).")


if __name__ == "__main__":
    main()
