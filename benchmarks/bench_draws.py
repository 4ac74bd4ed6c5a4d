"""What a run's draws cost inside the loop: seed 000's DRHE loop with its draws made inside
against the same loop given precomputed draws, per checkout, in one process (ABBA, CPU time).

Run:  NN=10 ROUNDS=4 .venv/bin/python benchmarks/bench_draws.py TREE_A [TREE_B ...]

For each checkout (its ``jaxnc`` imported afresh): ``jit(vmap(simulate))`` of
``mecanum_loop("DRHE", NN, 0.5)`` over 1000 keys, the same with ``draws=`` given, and
``jit(vmap(draw))`` alone; prints the best process CPU time of each over ROUNDS interleaved
rounds, and whether the draws are bit-identical between the first and last checkout.
(loop with draws) - (loop given draws) is the draws' cost in the loop.
"""
import os
import sys
import time

import jax
import numpy as np


def _purge():
    for m in list(sys.modules):
        if m == "jaxnc" or m.startswith(("jaxnc.", "experiments")):
            del sys.modules[m]


def main():
    trees = sys.argv[1:]
    N, seeds, rounds = int(os.environ.get("NN", 10)), 1000, int(os.environ.get("ROUNDS", 4))
    progs = []
    for t in trees:
        _purge()
        sys.path.insert(0, t)
        from jaxnc import montecarlo
        from jaxnc.loop import runner
        from jaxnc.schemes import mecanum as mec
        lp = mec.mecanum_loop("DRHE", N, 0.5)
        keys = montecarlo.seed_keys(0, seeds)
        full = jax.jit(jax.vmap(lambda k, l: runner.simulate(l, k), in_axes=(0, None))).lower(keys, lp).compile()
        dr = jax.jit(jax.vmap(lambda k, l: runner.draw(l, k), in_axes=(0, None))).lower(keys, lp).compile()
        d = jax.block_until_ready(dr(keys, lp))
        given = jax.jit(jax.vmap(lambda k, dd, l: runner.simulate(l, k, draws=dd),
                                 in_axes=(0, 0, None))).lower(keys, d, lp).compile()
        progs.append((t, full, dr, given, lp, keys, d))
        sys.path.remove(t)
    T = {}
    order = list(range(len(progs)))
    for _ in range(rounds):
        for i in order + order[::-1]:
            t, full, dr, given, lp, keys, d = progs[i]
            for name, f, args in (("loop with its draws", full, (keys, lp)), ("draws alone", dr, (keys, lp)),
                                  ("loop given the draws", given, (keys, d, lp))):
                c0 = time.process_time()
                jax.block_until_ready(f(*args))
                T.setdefault((t, name), []).append(time.process_time() - c0)
    print(f"DRHE N={N} DP=0.5, {seeds} seeds, 1-min load {os.getloadavg()[0]:.1f}")
    for (t, name), v in T.items():
        print(f"{t:30s} {name:22s} best {min(v):.3f} s CPU")
    same = all(np.array_equal(np.asarray(a), np.asarray(b))
               for a, b in zip(jax.tree.leaves(progs[0][6]), jax.tree.leaves(progs[-1][6])))
    print("draws bit-identical between the first and last checkout:", same)


if __name__ == "__main__":
    main()
