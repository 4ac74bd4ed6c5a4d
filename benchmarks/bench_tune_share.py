"""What the tuners' shared programs save: check_loop at two points and again, tune_loop twice.

Run (one tree per fresh process; A B B A, CPU time):
    PYTHONPATH=<tree> python benchmarks/bench_tune_share.py            # the machine's compile cache
    JAXNC_NO_CACHE=1 PYTHONPATH=<tree> python benchmarks/bench_tune_share.py

On the LTI loop of tests/test_loop_tune.py (periodic sensor, both gains K, 16 seeds):
``check_loop`` at the loop's gains, at another point and at the gains again; then, on the
PETC loop (its threshold, a search over four values, 2 score steps), ``tune_loop`` twice
with the same objective. Prints each call's process CPU seconds and compilations
(:func:`jaxnc.cache.compile_clock`), and the total CPU.
"""
from __future__ import annotations

import dataclasses
import os
import resource
import sys
from pathlib import Path

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.append(str(Path(__file__).resolve().parent.parent / "tests"))

import jax  # noqa: E402

if not os.environ.get("JAXNC_NO_CACHE"):
    from jaxnc.cache import enable_cache  # noqa: E402
    enable_cache()

from jaxnc import loop as nc  # noqa: E402
from jaxnc.cache import compile_clock  # noqa: E402
from jaxnc.tune import Positive  # noqa: E402
from jaxnc.tune.loop_tune import check_loop, tune_loop  # noqa: E402
from test_loop_tune import _loop  # noqa: E402


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(label, fn):
    t, c = cpu(), compile_clock()
    out = fn()
    d = compile_clock() - c
    print(f"{label:<34} {cpu() - t:7.2f} CPU s {d.compilations:4d} compilations")
    return out


t0 = cpu()
gain = dataclasses.replace(_loop(K=(1.0, 0.6)), trigger=nc.Periodic())
for label, at in (("check_loop at the gains", None), ("check_loop at another point", {"controller.K": [[2.0, 1.0]]}),
                  ("check_loop at the gains again", None)):
    timed(label, lambda: check_loop(gain, {"controller.K": Positive()}, at=at, seeds=16, fd_step=0.01))
petc, obj = _loop(delta=1e-2), (lambda m: m.cost_raw + 0.5 * m.rate_sc)
for label in ("tune_loop", "tune_loop again"):
    timed(label, lambda: tune_loop(petc, {"trigger.delta": Positive()}, obj,
                                   search={"trigger.delta": [1e-3, 1e-2, 1e-1, 1.0]}, search_budget=16, steps=2,
                                   batch=4, eval_seeds=8, pick_seeds=8, progress=False))
print(f"{'total (after imports)':<34} {cpu() - t0:7.2f} CPU s")
