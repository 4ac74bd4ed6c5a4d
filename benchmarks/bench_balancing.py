"""The balancing robot's two designs (seed 001): compile and run CPU seconds per checkout, in ONE process.

Run:  JAXNC_NO_CACHE=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_balancing.py --trees /tmp/base . [--seeds 32]
      [--horizon 25] [--designs model emulation] [--rounds 2]

For each tree in turn the ``jaxnc`` package is imported afresh from that tree (the previous
tree's modules dropped from ``sys.modules``, ``benchmarks/ab_inprocess.py``'s helpers), each
design's loop ``schemes.balancing.balancing_loop(design, horizon_s=H)`` built and
``jit(vmap(run))`` over ``--seeds`` keys (base seed 1, the headline test's) lowered and
compiled (process CPU seconds of lowering + compiling), and run once; its metrics (and the
run's final state) are compared with the first tree's bit for bit. The compiled programs then
run in the order A B ... B A, ``--rounds`` times; the table gives the best run's CPU seconds,
microseconds per seed-step and the ratio to the first tree. Per-process CPU time in one
process is the steadiest comparison on a machine shared with other sessions.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.ab_inprocess import _purge, abba_order, abba_rows, time_abba


def build(tree: Path, designs, seeds: int, horizon: float):
    """[(design, compiled program, loop, keys, steps, compile CPU s, outputs)] for ``tree``."""
    import jax
    _purge()
    sys.path.insert(0, str(tree))
    try:
        from jaxnc import loop as nc
        from jaxnc import montecarlo
        from jaxnc.schemes import balancing as bal

        def seed(k, lp):                        # the paper's metrics and the final state
            tr = nc.simulate(lp, k)
            return bal.metrics(lp, tr), tr.x[-1]

        out = []
        for design in designs:
            lp = bal.balancing_loop(design, horizon_s=horizon)
            keys = montecarlo.seed_keys(1, seeds)
            c0 = time.process_time()
            prog = jax.jit(jax.vmap(seed, in_axes=(0, None))).lower(keys, lp).compile()
            comp = time.process_time() - c0
            res = jax.block_until_ready(prog(keys, lp))
            out.append((design, prog, lp, keys, lp.steps, comp, [np.asarray(v) for v in jax.tree.leaves(res)]))
        return out
    finally:
        sys.path.remove(str(tree))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", type=Path, required=True)
    ap.add_argument("--designs", nargs="+", default=["model", "emulation"])
    ap.add_argument("--seeds", type=int, default=32)
    ap.add_argument("--horizon", type=float, default=25.0, help="simulated seconds (steps = horizon / 1 ms)")
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    import jax
    trees = [t.resolve() for t in a.trees]
    load0 = os.getloadavg()[0]
    built = [build(t, a.designs, a.seeds, a.horizon) for t in trees]
    cpu, _ = time_abba(built, a.rounds)
    print(f"{a.seeds} seeds x {built[0][0][4]} steps ({a.horizon:g} s), {a.rounds} rounds of "
          f"{abba_order(len(trees))}; 1-min load average {load0:.1f} at the start, "
          f"{os.getloadavg()[0]:.1f} at the end\n")
    print("| tree | design | compile CPU s | best run CPU s | us per seed-step | run CPU ratio A / this "
          "| bit-identical to A |")
    print("|---|---|---|---|---|---|---|")
    for i, j, b, same in abba_rows(built, cpu):
        steps, comp = built[i][j][4], built[i][j][5]
        print(f"| {'ABCDEFGH'[i]} {trees[i]} | {a.designs[j]} | {comp:.1f} | {b:.3f} | {b / (a.seeds * steps) * 1e6:.2f} "
              f"| x{min(cpu[(0, j)]) / b:.2f} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
