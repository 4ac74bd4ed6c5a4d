"""Where the time goes: each loop's arithmetic against the machine's measured peak.

Run:  .venv/bin/python benchmarks/bench_roofline.py [--seeds 1000] [--repeat 3] [--no-record]

For the servo (benchmarks/direct_servo.py, runner and by hand), the cart-pole
(examples/cartpole.py) and the seed-000 DRHE loop at N = 10 and N = 1, DP = 0.5: flops,
transcendental functions and bytes per seed-step counted on the jaxpr with every scan
multiplied by its length (benchmarks/jaxpr_cost.py; bytes: every primitive's operands and
results once, i.e. the *unfused* traffic, an upper bound), beside XLA's
``cost_analysis()`` of the compiled ``jit(vmap(run))`` program, which counts each while
loop's body once whatever its trip count (so its totals divided by seeds x steps are far
too small: shown to say so), and the measured throughput per CPU-second (process CPU
time, best of ``--repeat``). The peaks are measured in the same run, per CPU-second too:
a float32 matrix product (4096 x 4096) and a large array scaling (256 MB, bytes read plus
written). Each loop's attained flop/s and byte/s per CPU-second are then a fraction of
those peaks. Appends the table to benchmarks/RESULTS.md.
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
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _record import record  # noqa: E402
from jaxpr_cost import jaxpr_cost  # noqa: E402
from benchmarks.direct_servo import hand_cost, servo  # noqa: E402
from examples.cartpole import cartpole  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.report import markdown_table  # noqa: E402


def _best(f, repeat):
    """Best process CPU time of ``repeat`` calls after a first one."""
    jax.block_until_ready(f())
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        jax.block_until_ready(f())
        best = min(best, time.process_time() - t0)
    return best


def peaks(repeat):
    """(flop per CPU-s of a 4096^2 float32 matmul, bytes per CPU-s of a 256 MB scaling: read + write)."""
    n = 4096
    a = jnp.ones((n, n), jnp.float32)
    mm = jax.jit(lambda a: a @ a)
    t = _best(lambda: mm(a), repeat)
    flops = 2 * n ** 3 / t
    x = jnp.ones((64 * 2 ** 20,), jnp.float32)                 # 256 MB
    cp = jax.jit(lambda x: x * 1.0001)                        # one read, one write per element
    t = _best(lambda: cp(x), repeat)
    return flops, 2 * x.nbytes / t


def _loops():
    from jaxnc.schemes import mecanum as mec
    from experiments.mecanum import run_seed, uniform_dtypes
    sv, cp = servo(), cartpole()
    d10, d1 = (uniform_dtypes(mec.mecanum_loop("DRHE", N, 0.5)) for N in (10, 1))
    return [("servo, runner", lambda k, lp: nc.run(lp, k).cost, sv, sv.steps),
            ("servo, by hand", lambda k, lp: hand_cost(lp, k), sv, sv.steps),
            ("cart-pole, runner", lambda k, lp: nc.run(lp, k).cost, cp, cp.steps),
            ("DRHE N=10 DP=0.5, runner", run_seed, d10, d10.steps),
            ("DRHE N=1 DP=0.5, runner", run_seed, d1, d1.steps)]


def bench(seeds, repeat):
    pf, pb = peaks(repeat)
    keys = montecarlo.seed_keys(0, seeds)
    rows = []
    for name, fn, loop, steps in _loops():
        prog = jax.jit(jax.vmap(fn, in_axes=(0, None)))
        ca = prog.lower(keys, loop).compile().cost_analysis()
        ca = ca[0] if isinstance(ca, (list, tuple)) else ca
        jc = jaxpr_cost(fn, keys[0], loop)            # one seed's run
        t = _best(lambda: prog(keys, loop), repeat)
        n = seeds * steps
        fl, tr, by = jc["flops"] / steps, jc["transcendentals"] / steps, jc["bytes"] / steps
        rate = n / t
        rows.append([name, f"{fl:,.0f}", f"{tr:,.0f}", f"{by:,.0f}", f"{ca.get('flops', 0.0) / n:,.0f}",
                     f"{rate:,.0f}", f"{fl * rate / 1e9:.2f}", f"{100 * fl * rate / pf:.1f} %",
                     f"{by * rate / 1e9:.1f}", f"{100 * by * rate / pb:.0f} %"])
    head = (f"Peaks measured in this run, per CPU-second: {pf / 1e9:.1f} GFLOP (float32 4096^2 matmul), "
            f"{pb / 1e9:.1f} GB (256 MB scaling, read + write).\n\n")
    return head + markdown_table([f"loop ({seeds} seeds)", "flops / seed-step (jaxpr)", "transcendentals",
                                  "bytes / seed-step (jaxpr, unfused)", "XLA cost_analysis flops / seed-step",
                                  "seed-steps per CPU-s", "GFLOP per CPU-s", "of flop peak",
                                  "GB per CPU-s (unfused)", "of byte peak"], rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md")
    a = ap.parse_args()
    table = bench(a.seeds, a.repeat)
    load = f"Load average {os.getloadavg()[0]:.1f} at the end (machine shared with other sessions)."
    print(table)
    print(load)
    if not a.no_record:
        record(a.results, ["### Where the time goes: cost analysis against the measured peak\n\n" + table], note=load)


if __name__ == "__main__":
    main()
