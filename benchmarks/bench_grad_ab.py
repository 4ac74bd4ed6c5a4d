"""bench_grad.py's programs from several checkouts, in ONE process, timed interleaved (ABBA).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/bench_grad_ab.py --trees /tmp/base . [--seeds 256] [--rounds 3]
      [--loops cart servo]

For each tree in turn ``jaxnc`` (and ``benchmarks``, ``examples``) is imported afresh from that
tree, and its bench_grad.py's objectives (the mean cost over ``--seeds`` seeds as a function of
the controller's gains) are compiled,
``jit(objective)`` and ``jit(value_and_grad(objective))`` (compile CPU seconds), and run once.
The compiled programs then run in the order A B ... B A, ``--rounds`` times
(:func:`ab_inprocess.time_abba`); the table gives each program's best process CPU time, its
ratio to the same tree's forward pass, whether its outputs equal tree A's bit for bit, and
the gradient's largest difference from tree A's relative to tree A's largest entry.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from ab_inprocess import abba_order, abba_rows, time_abba  # noqa: E402

LOOPS = {"cart": "cart-pole (examples/cartpole.py), d/dK", "servo": "servo (benchmarks/direct_servo.py), d/d(Kp, Ki)"}


def _purge():
    for m in list(sys.modules):
        if m in ("jaxnc", "examples", "benchmarks") or m.startswith(("jaxnc.", "examples.", "benchmarks.")):
            del sys.modules[m]


def build(tree: Path, loops, seeds):
    """[(name, program(theta, keys) as f(keys, theta), theta, keys, None, compile CPU s, outputs)] of ``tree``:
    forward and value_and_grad of each loop, in the entry shape :func:`ab_inprocess.time_abba` takes."""
    import jax
    _purge()
    path = list(sys.path)
    sys.path.insert(0, str(tree))
    try:
        from benchmarks.bench_grad import _objectives       # the tree's own (it puts its folders on sys.path)
        from jaxnc import montecarlo
        keys = montecarlo.seed_keys(0, seeds)
        every = _objectives()
        objs = {short: every[long] for short, long in LOOPS.items()}
        out = []
        for name in loops:
            obj, theta = objs[name]
            for kind, fn in (("forward", obj), ("value_and_grad", jax.value_and_grad(obj))):
                c0 = time.process_time()
                comp = jax.jit(fn).lower(theta, keys).compile()
                res = jax.block_until_ready(comp(theta, keys))
                out.append(((name, kind), lambda k, th, comp=comp: comp(th, k), theta, keys, None,
                            time.process_time() - c0, [np.asarray(v) for v in jax.tree.leaves(res)]))
        return out
    finally:
        sys.path[:] = path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", type=Path, required=True)
    ap.add_argument("--loops", nargs="+", default=["cart", "servo"], choices=sorted(LOOPS))
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    trees = [t.resolve() for t in a.trees]
    load0 = os.getloadavg()[0]
    built = [build(t, a.loops, a.seeds) for t in trees]
    cpu, _ = time_abba(built, a.rounds)
    print(f"{a.seeds} seeds, {a.rounds} rounds of {abba_order(len(trees))}; 1-min load average {load0:.1f} at the "
          f"start, {os.getloadavg()[0]:.1f} at the end\n")
    print("| tree | loop | program | compile CPU s | best run CPU s | / forward (run) | / forward (compile) "
          "| bit-identical to A | gradient: max rel. difference to A |")
    print("|---|---|---|---|---|---|---|---|---|")
    for i, j, best, same in abba_rows(built, cpu):
        (name, kind), comp = built[i][j][0], built[i][j][5]
        f = j - (j % 2)                                     # the same loop's forward program
        ratio = f"x{best / min(cpu[(i, f)]):.2f}" if kind != "forward" else ""
        cratio = f"x{comp / built[i][f][5]:.2f}" if kind != "forward" else ""
        diff = ""
        if kind != "forward":
            g, g0 = built[i][j][6][1], built[0][j][6][1]
            diff = f"{np.max(np.abs(g - g0)) / np.max(np.abs(g0)):.1e}"
        print(f"| {'ABCDEFGH'[i]} {trees[i]} | {LOOPS[name]} | {kind} | {comp:.1f} | {best:.3f} | {ratio} | {cratio} "
              f"| {'yes' if same else 'NO'} | {diff} |")


if __name__ == "__main__":
    main()
