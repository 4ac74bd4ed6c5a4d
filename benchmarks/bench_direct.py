"""The runner against the same loop written by hand (issue 32): examples/cartpole.py.

Run:  .venv/bin/python benchmarks/bench_direct.py [--batches 1000 4000] [--repeat 3] [--no-record]

Both compute the same runs on the same draws (``benchmarks/direct_cartpole.py``,
checked by ``tests/test_bench_direct.py``): the runner through ``jaxnc.loop.run`` and
the direct ``jit(vmap(scan))``. Each is compiled once per batch size (the first call's
time minus the best repeat is the compile time), then timed ``--repeat`` times,
interleaved so machine load hits both; the ratio is measured in the same run. Prints a
table and appends it to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from _record import record  # noqa: E402
from benchmarks.direct_cartpole import direct_cost  # noqa: E402
from examples.cartpole import cartpole  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.report import markdown_table  # noqa: E402


def bench(batches, repeat):
    loop = cartpole()
    fns = {"runner (jaxnc.loop.run)": lambda k, lp: nc.run(lp, k).cost,
           "direct jit(vmap(scan))": lambda k, lp: direct_cost(lp, k)}
    rows = []
    for B in batches:
        keys = montecarlo.seed_keys(0, B)
        progs = {name: jax.jit(jax.vmap(fn, in_axes=(0, None))) for name, fn in fns.items()}
        first, best = {}, {name: np.inf for name in fns}
        for name, prog in progs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(prog(keys, loop))
            first[name] = time.perf_counter() - t0
        for _ in range(repeat):
            for name, prog in progs.items():
                t0 = time.perf_counter()
                jax.block_until_ready(prog(keys, loop))
                best[name] = min(best[name], time.perf_counter() - t0)
        rate = {name: B * loop.steps / best[name] for name in fns}
        for name in fns:
            rows.append([name, B, f"{max(first[name] - best[name], 0):.2f}", f"{best[name]:.3f}",
                         f"{rate[name]:,.0f}"])
        r = rate["runner (jaxnc.loop.run)"] / rate["direct jit(vmap(scan))"]
        c = (first["runner (jaxnc.loop.run)"] - best["runner (jaxnc.loop.run)"]) / max(
            first["direct jit(vmap(scan))"] - best["direct jit(vmap(scan))"], 1e-9)
        rows.append([f"**runner / direct**", B, f"compile x{c:.2f}", "", f"throughput x{r:.3f}"])
    return markdown_table(["loop (cart-pole, examples/cartpole.py)", "seeds", "compile (s)", "run (s)",
                           "seed-steps/s"], rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1000, 4000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md")
    a = ap.parse_args()
    table = bench(a.batches, a.repeat)
    print(table)
    if not a.no_record:
        record(a.results, ["### The runner against the same loop written directly (cart-pole)\n\n" + table])


if __name__ == "__main__":
    main()
