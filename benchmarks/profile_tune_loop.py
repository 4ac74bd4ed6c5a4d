"""Where ``tune_loop``'s wall time goes, stage by stage: compilation against running.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/profile_tune_loop.py [--problem hdd|cartpole|hdd-grid]
        [--steps 30] [--batch 16] [--check-seeds 32] [--eval-seeds 8]

Builds one ``tune-study`` problem (experiments/tune_study.py, its default settings) and calls
:func:`jaxnc.tune.tune_loop` with the study's settings, counting every XLA compilation
(``jax.monitoring``'s backend-compile events, with the programs' names) and
attributing each to the stage on the call stack (start evaluation, search, check, gradient
steps, final evaluation), then prints the seconds compiling per stage and the call's
compile clock (``LoopTuneResult.compile_s`` / ``n_compilations``). No persistent
compilation cache (cold, as the study).
"""
from __future__ import annotations

import argparse
import collections
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import jax  # noqa: E402
import jax.monitoring  # noqa: E402

STAGES = collections.defaultdict(lambda: [0, 0.0])
NAMES = []


def _stage() -> str:
    names = [f.name for f in traceback.extract_stack()]
    for fn, stage in (("gradient_check", "check"), ("successive_halving", "search"), ("_refine", "search"),
                      ("tune", "gradient steps")):
        if fn in names:
            return stage
    if "tune_loop" in names:
        return "evaluation (start/final) and other"
    return "outside tune_loop"


def _listener(event, secs, fun_name="?", **kw):
    """XLA compilations (backend-compile events), attributed to the stage on the stack."""
    if event == "/jax/core/compile/backend_compile_duration":
        st = _stage()
        STAGES[st][0] += 1
        STAGES[st][1] += secs
        NAMES.append((secs, st, fun_name))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="hdd")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--check-seeds", type=int, default=32)
    ap.add_argument("--eval-seeds", type=int, default=8)
    ap.add_argument("--top", type=int, default=12)
    a = ap.parse_args()
    jax.monitoring.register_event_duration_secs_listener(_listener)
    from jaxnc.experiments import tune_study as ts
    from jaxnc.tune import tune_loop
    from jaxnc.experiment import get_experiment
    exp = get_experiment("tune-study")
    settings = {o.name: o.default for o in exp.options}
    problem = ts.BUILDERS[a.problem](settings)
    t0 = time.perf_counter()
    r = tune_loop(problem.config, problem.params, problem.objective, run=problem.run, steps=a.steps, batch=a.batch,
                  check_seeds=a.check_seeds, seed=0, eval_seeds=a.eval_seeds, eval_seed=ts.EVAL_SEED + 1,
                  progress=False)
    wall = time.perf_counter() - t0
    print(f"problem {a.problem}: tune_loop wall {wall:.1f} s, estimator {r.estimator}")
    for k in ("compile_s", "n_compilations", "stages"):
        if hasattr(r, k):
            print(f"  LoopTuneResult.{k} = {getattr(r, k)}")
    print("  XLA compilations by stage (count, seconds):")
    for st, (c, t) in sorted(STAGES.items(), key=lambda kv: -kv[1][1]):
        print(f"    {st:40s} {c:4d} {t:8.1f}")
    print(f"  the {a.top} longest compilations:")
    for t, st, n in sorted(NAMES, reverse=True)[:a.top]:
        print(f"    {t:7.2f} s  [{st}] {n}")


if __name__ == "__main__":
    main()
