"""``check_loop`` with its defaults at the ``tune-loops`` points (issue 31, acceptance 1).

    python benchmarks/check_defaults.py [--loops hdd,drhe,cartpole] [--out docs/results/tune_check]
                                        [--points start,second] [--max-seeds N]

For each loop of ``experiments/tune_loops.py`` (built by its own problem builders, with the
experiment's default settings) and each of its two check points (the start, and the
problem's ``second``), :func:`jaxnc.tune.check_loop` is called with its defaults: nothing
is given but the loop, the parameters, the objective, the run and ``at``. Each point's
result is written as soon as it finishes (``<loop>_<point>.json``: the check's table,
estimates, verdicts, the measured smoothing bias, seeds used, wall time and the machine
load); ``tables.md`` collects the summary rows (per loop and point: seeds used, the
recommended estimator, conclusive or not, max |z| of the recommended estimator against its
finite-difference reference, wall time). ``--max-seeds`` (default: check_loop's own) is
the one override, for a run beyond the defaults' budget (written to another ``--out``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from jaxnc.report import markdown_table
from jaxnc.tune import check_loop, get_path, param_paths

SETTINGS = {"w_drhe": 30.0, "w_cartpole": 2.0}     # experiments/tune_loops.py's defaults


def _load() -> str:
    return ", ".join(f"{x:.1f}" for x in os.getloadavg())


def _row(chk, loop: str, point: str, at: dict, wall: float) -> dict:
    rec = chk.recommended
    return {"loop": loop, "point": point, "at": at, "seeds": chk.seeds, "recommended": rec or "none",
            "conclusive": rec is not None,
            "max abs z (recommended)": float(np.max(np.abs(chk.paired_z[rec]))) if rec else float("nan"),
            "bias resolved": chk.bias_resolved, "runs per seed": chk.runs_per_seed, "wall time (s)": wall}


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} = {x:.3g}" for k, x in v.items())
    return str(v)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", default="hdd,drhe,cartpole")
    ap.add_argument("--out", default="docs/results/tune_check")
    ap.add_argument("--points", default="start,second")
    ap.add_argument("--max-seeds", type=int, default=None)
    args = ap.parse_args(argv)
    from jaxnc.cache import enable_cache
    from jaxnc.experiments.tune_loops import BUILDERS
    enable_cache()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python " + " ".join([os.path.relpath(sys.argv[0])] + (argv or sys.argv[1:]))
    for name in args.loops.split(","):
        problem = BUILDERS[name](SETTINGS)
        names = param_paths(problem.params)
        start = {n: float(np.asarray(get_path(problem.loop, p[0]))) for n, p in names.items()}
        for point, at in (("start", None), ("second", problem.second)):
            if point not in args.points.split(","):
                continue
            load0, t0 = _load(), time.perf_counter()
            extra = {} if args.max_seeds is None else {"max_seeds": args.max_seeds}
            chk = check_loop(problem.loop, problem.params, problem.objective, run=problem.run, at=at, progress=True,
                             **extra)
            wall = time.perf_counter() - t0
            row = _row(chk, name, point, at or start, wall)
            print(f"[{name} {point}] {row}\n{chk.table()}\n", flush=True)
            (out / f"{name}_{point}.json").write_text(json.dumps({
                "command": command, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "load (1, 5, 15 min) before / after": [load0, _load()], "summary": row,
                "estimates": {k: {"mean": m.tolist(), "se": s.tolist()}
                              for k, (m, s) in {**chk.estimates, **chk.references}.items()},
                "smoothing_bias": {k: {"mean": m.tolist(), "se": s.tolist()}
                                   for k, (m, s) in chk.smoothing_bias.items()},
                "paired_z": {k: np.asarray(v).tolist() for k, v in chk.paired_z.items()},
                "reason": chk.reason, "names": list(chk.names), "values": np.asarray(chk.values).tolist(),
                "table": chk.table()}, indent=1, default=str))
            rows = [json.loads(p.read_text())["summary"] for p in sorted(out.glob("*_*.json"))]
            (out / "tables.md").write_text(
                f"`{command}` (check_loop's defaults; one row per finished point)\n\n"
                + markdown_table(list(rows[0]), [[_fmt(v) for v in r.values()] for r in rows]) + "\n")


if __name__ == "__main__":
    main()
