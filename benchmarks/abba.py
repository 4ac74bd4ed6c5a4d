"""ABBA comparison of two checkouts with this branch's bench_runner.py (issue 30 "no slower than today").

Run:  .venv/bin/python benchmarks/abba.py --trees /tmp/base_e9b . [--rounds 2] -- --batches 1000 --cells DRHE:10

Each tree runs *this* checkout's ``benchmarks/bench_runner.py`` in a fresh process, with that
tree's ``jaxnc`` first on the path (so both sides time the same library call), in the order
A B B A (``--rounds`` times), persistent compilation cache off. Prints each run's rows and,
per cell, the after/before ratio of seed-steps per CPU-second and per wall second (the mean
over the runs of each tree), with the 1-minute load average at each run's start.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

_CHILD = """
import sys
tree, script, here = sys.argv[1], sys.argv[2], sys.argv[3]
sys.argv = [script] + sys.argv[4:]
sys.path.insert(0, here)
sys.path.insert(0, tree)
g = {"__file__": tree + "/benchmarks/bench_runner.py", "__name__": "__main__"}
exec(compile(open(script).read(), script, "exec"), g)
"""


def run_tree(tree: Path, bench_args: list[str]) -> list[list[str]]:
    """Rows of bench_runner's table run against ``tree``'s package."""
    env = dict(os.environ, JAXNC_NO_CACHE="1", PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, "-c", _CHILD, str(tree), str(HERE / "bench_runner.py"), str(HERE),
                          *bench_args, "--no-record"], env=env, cwd=tree, check=True, capture_output=True,
                         text=True).stdout
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in out.splitlines()
            if line.startswith("|") and not line.startswith("|--")]
    return rows[1:]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs=2, type=Path, required=True, help="before after")
    ap.add_argument("--rounds", type=int, default=1, help="ABBA rounds")
    a, bench_args = ap.parse_known_args()
    bench_args = [b for b in bench_args if b != "--"]
    trees = [t.resolve() for t in a.trees]
    order = [0, 1, 1, 0] * a.rounds
    rates = {}
    for i in order:
        load = os.getloadavg()[0]
        for row in run_tree(trees[i], bench_args):
            cell = (row[0], row[1])
            wall, cpu = float(row[5].replace(",", "")), float(row[7].replace(",", ""))
            rates.setdefault(cell, ([], []))[i].append((wall, cpu))
            print(f"{'AB'[i]} {trees[i]} load {load:.1f}: {' | '.join(row)}", flush=True)
    for cell, (before, after) in rates.items():
        mw = [sum(r[k] for r in side) / len(side) for side in (before, after) for k in (0, 1)]
        print(f"{cell[0]}, {cell[1]} seeds: after/before per wall s x{mw[2] / mw[0]:.3f}, "
              f"per CPU-s x{mw[3] / mw[1]:.3f}")


if __name__ == "__main__":
    main()
