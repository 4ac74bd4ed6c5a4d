"""Several checkouts' seed-000 loops timed in ONE process, interleaved (ABBA), by CPU time.

Run:  .venv/bin/python benchmarks/ab_inprocess.py --trees /tmp/base_e9b HEAD_TREE . [--cells DRHE:10 DRHE:1]
      [--seeds 1000] [--rounds 3]

For each tree in turn the ``jaxnc`` package (and ``experiments``) is imported afresh from that
tree (the modules of the previous one dropped from ``sys.modules``), the loop
``schemes.mecanum.mecanum_loop(case, N, dp)`` built and ``jit(vmap(run))`` over ``--seeds``
keys compiled (compile CPU seconds recorded) and run once; its metrics are compared with the
first tree's (bit for bit). The compiled programs then run in the order A B C ... C B A,
``--rounds`` times, each run's process CPU time and wall time taken; the table gives the
best of each, seed-steps per CPU-second and the ratio to the first tree. On a machine shared
with other sessions, the CPU-time ratio within one process is the steadiest comparison.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np


def _purge():
    for m in list(sys.modules):
        if m == "jaxnc" or m.startswith(("jaxnc.", "experiments", "tests")):
            del sys.modules[m]


def build(tree: Path, cells, seeds):
    """[(cell, compiled program, loop, keys, steps, compile CPU s, outputs)] for ``tree``."""
    import jax
    _purge()
    sys.path.insert(0, str(tree))
    try:
        from jaxnc import montecarlo
        from jaxnc.schemes import mecanum as mec
        out = []
        for case, N in cells:
            lp = mec.mecanum_loop(case, N, 0.5)
            keys = montecarlo.seed_keys(0, seeds)
            c0 = time.process_time()
            prog = jax.jit(jax.vmap(lambda k, l: mec.run(l, k), in_axes=(0, None))).lower(keys, lp).compile()
            res = jax.block_until_ready(prog(keys, lp))
            out.append(((case, N), prog, lp, keys, lp.steps, time.process_time() - c0,
                        [np.asarray(v) for v in res]))
        return out
    finally:
        sys.path.remove(str(tree))


def time_abba(built, rounds: int):
    """Run every tree's programs in the order A B ... B A, ``rounds`` times: ``built[i][j]`` =
    (cell, compiled program, loop, keys, ...) of tree i, called ``prog(keys, loop)``.
    Returns ({(i, j): [process CPU s of each run]}, {(i, j): [wall s of each run]})."""
    import jax
    cpu = {(i, j): [] for i in range(len(built)) for j in range(len(built[i]))}
    wall = {k: [] for k in cpu}
    order = list(range(len(built)))
    for _ in range(rounds):
        for i in order + order[::-1]:
            for j, (_, prog, lp, keys, *_rest) in enumerate(built[i]):
                t0, c0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(prog(keys, lp))
                cpu[(i, j)].append(time.process_time() - c0)
                wall[(i, j)].append(time.perf_counter() - t0)
    return cpu, wall


def abba_rows(built, cpu):
    """Per cell j, then tree i: (i, j, best process CPU s of its runs, whether its results
    (``built[i][j][6]``, a tuple of arrays) equal tree A's bit for bit)."""
    for j in range(len(built[0])):
        for i in range(len(built)):
            same = all(np.array_equal(x, y, equal_nan=True) for x, y in zip(built[i][j][6], built[0][j][6]))
            yield i, j, min(cpu[(i, j)]), same


def abba_order(n_trees: int) -> str:
    """One round's order of trees, e.g. A/B/B/A."""
    order = list(range(n_trees))
    return "/".join("ABCDEFGH"[i] for i in order + order[::-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", type=Path, required=True)
    ap.add_argument("--cells", nargs="+", default=["DRHE:10", "DRHE:1"])
    ap.add_argument("--seeds", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    import jax
    cells = [(c.split(":")[0], int(c.split(":")[1])) for c in a.cells]
    trees = [t.resolve() for t in a.trees]
    built = [build(t, cells, a.seeds) for t in trees]
    load0 = os.getloadavg()[0]
    cpu, wall = time_abba(built, a.rounds)
    print(f"{a.seeds} seeds, {a.rounds} rounds of {abba_order(len(trees))}; "
          f"1-min load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end\n")
    print("| tree | loop | compile CPU s | best run CPU s | seed-steps per CPU-s | best wall s | CPU ratio to A "
          "| bit-identical to A |")
    print("|---|---|---|---|---|---|---|---|")
    for i, j, b, same in abba_rows(built, cpu):
        (case, N), steps, comp = cells[j], built[i][j][4], built[i][j][5]
        print(f"| {'ABCDEFGH'[i]} {trees[i]} | {case} N={N} DP=0.5 | {comp:.1f} | {b:.3f} | {a.seeds * steps / b:,.0f} "
              f"| {min(wall[(i, j)]):.3f} | x{min(cpu[(0, j)]) / b:.3f} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
