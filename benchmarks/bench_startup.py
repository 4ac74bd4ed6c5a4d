"""Start-up cost of a jaxnc process: ``import jaxnc`` plus the built-in experiments' registry
(what every ``jaxnc`` command, test worker and subprocess pays before any JAX work).

Run:  .venv/bin/python benchmarks/bench_startup.py [--trees A B ...] [--rounds 3]

Each measurement is a fresh ``python -c`` process (wall and CPU seconds, the best of
``--rounds``); with ``--trees`` each checkout is run from (its folder first on ``sys.path``) in turn, in the
order A B ... B A per round, so the trees are compared in one run on the same machine. It also
lists which heavy optional libraries the start-up imported.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CODE = ("import resource, sys, time; t = time.perf_counter()\n"
        "import jaxnc\n"
        "from jaxnc.experiment import load_builtin; load_builtin()\n"
        "r = resource.getrusage(resource.RUSAGE_SELF)\n"
        "print(__import__('json').dumps({'wall': time.perf_counter() - t, 'cpu': r.ru_utime + r.ru_stime,\n"
        "  'heavy': sorted(m for m in ('control', 'scipy.signal', 'matplotlib', 'mujoco', 'xarray') if m in sys.modules)}))\n")


def measure(tree: Path | None) -> dict:
    tree = Path(__file__).resolve().parents[1] if tree is None else tree.resolve()
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, env=env, cwd=tree, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="*", type=Path, default=[None])
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    res = {i: [] for i in range(len(a.trees))}
    order = list(range(len(a.trees)))
    for _ in range(a.rounds):
        for i in order + order[::-1]:
            res[i].append(measure(a.trees[i]))
    print("| tree | import + registry, wall s (best; all) | CPU s (best) | heavy libraries imported |")
    print("|---|---|---|---|")
    for i, rs in res.items():
        print(f"| {a.trees[i] or 'this checkout'} | {min(r['wall'] for r in rs):.2f} "
              f"({', '.join('%.2f' % r['wall'] for r in rs)}) | {min(r['cpu'] for r in rs):.2f} | "
              f"{', '.join(rs[0]['heavy']) or 'none'} |")


if __name__ == "__main__":
    main()
