"""Re-evaluate tune-study's stored final points on more fresh seeds (issue 31 item 3).

Run:  PYTHONPATH=. python benchmarks/tune_study_eval.py [--problem cartpole] [--seeds 16384] [--methods tuner random]
      [--results docs/results/tune_study]

The study (``jaxnc run tune-study``) gives each method a wall-time budget, so re-running it moves
the points; its verdicts rest on one evaluation of the final points on ``eval.seeds`` fresh
seeds. This script rebuilds the problem from the stored configuration, runs every stored final
point (and the start) with hard triggers on the first ``--seeds`` seeds of the same fresh stream
(``experiments.tune_study.EVAL_SEED``: its first ``eval.seeds`` seeds are the study's own, and
the script checks that it reproduces the stored means on them), and prints each point's mean
with its 95 % interval and every paired difference with the seeds Cochran's rule asks for
(:func:`jaxnc.montecarlo.seeds_for_paired_interval`). Nothing is written; paste into
docs/tuning_loops.md.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from jaxnc import montecarlo  # noqa: E402
from jaxnc.experiments import tune_study as ts  # noqa: E402
from jaxnc.tune import evaluate, param_paths  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="cartpole", choices=sorted(ts.BUILDERS))
    ap.add_argument("--seeds", type=int, default=16384)
    ap.add_argument("--methods", nargs="*", default=None, help="the points to run (default: the start and every method)")
    ap.add_argument("--results", default=str(HERE.parent / "docs" / "results" / "tune_study"))
    a = ap.parse_args(argv)
    stored = json.loads((Path(a.results) / f"{a.problem}.json").read_text())
    res, settings = stored["results"], stored["config"]
    problem = ts.BUILDERS[a.problem](settings)
    names = param_paths(problem.params)
    ev = ts._per_seed(problem, names)
    n0 = int(res["eval"]["seeds"])
    assert res["eval"]["seed"] == ts.EVAL_SEED, "the study's fresh stream changed"
    keys = montecarlo.seed_keys(ts.EVAL_SEED, max(a.seeds, n0))
    points = {"start": res["start"]} | {m: d["best"] for m, d in res["methods"].items()}
    if a.methods:
        points = {m: points[m] for m in a.methods}
    values = {}
    for m, pt in points.items():
        v = np.asarray(evaluate(ev, pt, keys, chunk_size=256), np.float64)
        stored_mean = res["eval"]["mean"][m][0]
        again = float(np.mean(v[:n0]))
        mean, ci = montecarlo.mean_ci(v)
        print(f"{m:>10}: first {n0} seeds {again:.6g} (stored {stored_mean:.6g}); "
              f"{v.size} seeds {mean:.5g} +- {ci:.2g}", flush=True)
        if not np.isclose(again, stored_mean, rtol=1e-5, atol=0):
            print(f"    warning: does not reproduce the stored mean (relative {again / stored_mean - 1:.2e})")
        values[m] = v
    print(f"\n| difference | {n0} seeds (the study) | {a.seeds} seeds | Cochran's rule asks |")
    print("|---|---|---|---|")
    ms = list(values)
    for i, x in enumerate(ms):
        for y in ms[i + 1:]:
            d0 = montecarlo.mean_ci(values[x][:n0] - values[y][:n0])
            d = montecarlo.mean_ci(values[x] - values[y])
            need = montecarlo.seeds_for_paired_interval(values[x], values[y])
            print(f"| {x} − {y} | {d0[0]:+.4g} ± {d0[1]:.2g} | {d[0]:+.4g} ± {d[1]:.2g} | {need} |")


if __name__ == "__main__":
    main()
