"""Are the runner's draws of several checkouts the same bits? (one process, each tree imported in turn)

Run:  PYTHONPATH=. .venv/bin/python benchmarks/draws_identical.py /tmp/base_tree . [--seeds 4096]

For the five loops of tests/test_lanes.py and two seed-000 cells (SR N = 1 DP = 0, DRHE N = 10
DP = 0.5), ``jit(vmap(jaxnc.loop.runner.draw))`` over ``--seeds`` keys in each tree; every leaf
of the second and later trees' ``Draws`` (noise, link delays, the plant's initial key) is
compared bit for bit with the first tree's.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

os.environ.setdefault("JAXNC_NO_CACHE", "1")


def _purge():
    for m in list(sys.modules):
        if m == "jaxnc" or m.startswith(("jaxnc.", "experiments", "tests")):
            del sys.modules[m]


def draws_of(tree: str, seeds: int) -> dict:
    import jax
    _purge()
    sys.path.insert(0, tree)
    try:
        from jaxnc import montecarlo
        from jaxnc.loop.runner import draw
        from jaxnc.schemes import mecanum as mec
        from tests import test_lanes
        keys = montecarlo.seed_keys(0, seeds)
        loops = {n: b()[1] for n, b in test_lanes.LOOPS.items()}
        loops["mecanum SR N=1 DP=0"] = mec.mecanum_loop("SR", 1, 0.0)
        loops["mecanum DRHE N=10 DP=0.5"] = mec.mecanum_loop("DRHE", 10, 0.5)
        out = {}
        for name, lp in loops.items():
            d = jax.jit(jax.vmap(draw, in_axes=(None, 0)))(lp, keys)
            out[name] = [np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)
                                    else x) for x in jax.tree.leaves(d)]
        return out
    finally:
        sys.path.remove(tree)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trees", nargs="+")
    ap.add_argument("--seeds", type=int, default=4096)
    a = ap.parse_args()
    got = [draws_of(os.path.abspath(t), a.seeds) for t in a.trees]
    for name, ref in got[0].items():
        for t, g in zip(a.trees[1:], got[1:]):
            same = len(ref) == len(g[name]) and all(
                x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x.view(np.uint8), y.view(np.uint8))
                for x, y in zip(ref, g[name]))
            print(f"{name}: {t} {'identical' if same else 'DIFFERS'} ({sum(x.size for x in ref):,} numbers)")


if __name__ == "__main__":
    main()
