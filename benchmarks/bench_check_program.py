"""The gradient check's compile + run cost: one vmap over its hard points against one copy per point.

Run (one version per fresh process, no persistent cache):
    git show <commit>:jaxnc/tune/check.py > /tmp/check_old.py
    JAXNC_NO_CACHE=1 python benchmarks/bench_check_program.py old /tmp/check_old.py
    JAXNC_NO_CACHE=1 python benchmarks/bench_check_program.py new

``check_loop`` of the LTI loop of tests/test_loop_tune.py (both gains K and the PETC threshold
delta, 16 seeds, every default estimator); prints the process CPU seconds of the call (compile
included) and the estimates as JSON, so that two versions' numbers can be compared.
"""
from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import jaxnc.tune.loop_tune as _lt  # noqa: E402

which = sys.argv[1] if len(sys.argv) > 1 else "new"
if which == "old":      # the other version's gradient_check, called by check_loop
    spec = importlib.util.spec_from_file_location("_check_old", sys.argv[2])
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    _lt.gradient_check = mod.gradient_check
print("gradient_check from", _lt.gradient_check.__code__.co_filename, file=sys.stderr)

import numpy as np  # noqa: E402
from test_loop_tune import _loop  # noqa: E402

from jaxnc.tune.loop_tune import Positive, check_loop  # noqa: E402

t0 = time.process_time()
c = check_loop(_loop(), {"controller.K": Positive(), "trigger.delta": Positive()}, seeds=16, max_seeds=16)
cpu = time.process_time() - t0
print(json.dumps({"which": which, "cpu_s": cpu, "value": c.value,
                  "estimates": {k: np.asarray(v).tolist() for k, v in c.estimates.items()}}))   # (mean, se) per estimator
