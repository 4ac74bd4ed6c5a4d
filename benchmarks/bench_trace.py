"""Tracing and lowering cost of representative loop programs (issues 30 and 32).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/bench_trace.py [--rounds 2] [--out DIR] [--only NAME ...]
      [--profile FILE] [--trees A B]

For each loop below, the program :func:`jaxnc.montecarlo.run_batched` compiles for it,
``jit(vmap(run_seed, in_axes=(0, None)))`` over 16 keys with the loop as the shared argument,
is traced (``.trace``) and lowered (``.lower``) after ``jax.clear_caches()`` (``--keep-caches``:
JAX's caches stay warm, as in a test-suite process; a fresh ``jit`` is traced each time); the CPU seconds
of each, the number of jaxpr equations (nested jaxprs included) and of StableHLO operations
are printed, and the lowered text is hashed (and written to ``--out`` as ``NAME.mlir``) so two
checkouts can be shown to lower the same program. Rounds repeat the loops in the order
A B B A ... (``--rounds`` times the list, every other round reversed).

``--trees A B`` runs the same in one process for two checkouts (imported in turn, the
modules purged between them, as ``ab_inprocess.py``), order A B B A per round, and prints
the median trace and lower seconds of each and whether their texts hash the same.
``--profile FILE`` writes a cProfile of every trace (not the lowering) to FILE;
``--gc-threshold a,b,c`` sets Python's garbage collector's thresholds first, and a tree
given as ``gc:a,b,c`` is this checkout with those thresholds (``--trees gc:700,10,10
gc:100000,50,100``: the collector's settings compared A B B A in one process).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

KEEP_CACHES = False
LOOPS = ("servo", "cartpole", "drhe10", "hdd", "balancing", "lti_buffer")


def _purge():
    for m in list(sys.modules):
        if m == "jaxnc" or m.startswith(("jaxnc.", "experiments", "examples")):
            del sys.modules[m]


def build(name: str):
    """(per-seed function, loop) of loop ``name`` from the imported checkout."""
    import numpy as np
    from jaxnc import loop as nc
    from jaxnc import montecarlo
    if name == "servo":                 # docs/build_your_own_loop.md's two-state servo over a lossy link
        T = 0.1
        plant = nc.LTI(A=[[1.0, T], [0.0, 1.0]], B=[[0.0], [T]], C=[[1.0, 0.0]], x0=[1.0, 0.0], w_std=[0.01, 0.01],
                       v_std=[0.05], T=T)
        ekf = nc.EKF(plant, Q=np.eye(2) * 1e-4, R=np.eye(1) * 0.05 ** 2, mean0=[0.0, 0.0], cov0=np.eye(2))
        loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=nc.Link(nc.Bernoulli(0.3)), estimator=ekf,
                       controller=nc.StateFeedback(np.array([[3.0, 2.5]])), downlink=nc.Link(),
                       actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 1.0], R=[0.1]), T=T, steps=100)
        return nc.run_seed, loop
    if name == "lti_buffer":            # tests/test_loop.py's LTI loop, N = 2, a time-stamped EKF
        T = 0.1
        plant = nc.LTI(A=[[1.0, 0.1], [0.0, 0.95]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                       w_std=[0.01, 0.02], v_std=[0.05], T=T)
        ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05 ** 2, mean0=[0.0, 0.0],
                     cov0=np.eye(2), buffer=3)
        link = nc.Link(nc.Bernoulli(0.2), nc.ShiftedExponential(eta=0.05, phi=0.1), tau_max=0.3, order="all",
                       capacity=8)
        loop = nc.Loop(plant=plant, trigger=nc.Periodic(), uplink=link, estimator=ekf,
                       controller=nc.StateFeedback(np.array([[3.0, 1.5]])), downlink=nc.Link(),
                       actuator=nc.HoldLast(), cost=nc.Quadratic(Q=[1.0, 1.0], R=[0.1]), N=2, steps=40, T=T)
        return nc.run_seed, loop
    if name == "cartpole":
        from examples.cartpole import cartpole
        return nc.run_seed, cartpole()
    if name == "drhe10":
        from jaxnc.schemes.mecanum import mecanum_loop
        return nc.run_seed, montecarlo.uniform_dtypes(mecanum_loop("DRHE", N=10, dp=0.1))
    if name == "hdd":
        from jaxnc.schemes.hdd import hdd_loop
        return nc.run_seed, hdd_loop(5, steps=400)
    if name == "balancing":
        from jaxnc.schemes.balancing import balancing_loop
        return nc.run_seed, balancing_loop("model", horizon_s=5.0)
    raise ValueError(name)


def _count_eqns(jaxpr) -> int:
    import jax.extend
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for sub in jax.extend.core.jaxprs_in_params(e.params):
            n += _count_eqns(sub)
    return n


def measure(name: str, profiler=None):
    """(trace CPU s, lower CPU s, jaxpr equations, StableHLO ops, text) of loop ``name``."""
    import jax
    from jaxnc import montecarlo
    fn, loop = build(name)
    keys = montecarlo.seed_keys(0, 16)
    if not KEEP_CACHES:
        jax.clear_caches()
    f = jax.jit(jax.vmap(lambda key, args: fn(key, *args), in_axes=(0, None)))
    t0 = time.process_time()
    if profiler is not None:
        profiler.enable()
    traced = f.trace(keys, (loop,))
    if profiler is not None:
        profiler.disable()
    t1 = time.process_time()
    lowered = traced.lower()
    t2 = time.process_time()
    text = lowered.as_text()
    ops = sum(1 for line in text.splitlines() if " = " in line and ("stablehlo." in line or "func.call" in line
                                                                     or "chlo." in line))
    return t1 - t0, t2 - t1, _count_eqns(traced.jaxpr.jaxpr), ops, text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", nargs="*", default=list(LOOPS))
    ap.add_argument("--profile", type=Path, default=None)
    ap.add_argument("--trees", nargs="*", default=None)
    ap.add_argument("--gc-threshold", default=None,
                    help="a,b,c: gc.set_threshold(a, b, c) first (default: Python's, 700,10,10)")
    ap.add_argument("--keep-caches", action="store_true",
                    help="no jax.clear_caches() between traces (a fresh jit each time): "
                         "a loop traced again in a process, as in the test suite")
    a = ap.parse_args(argv)
    global KEEP_CACHES
    KEEP_CACHES = a.keep_caches
    if a.gc_threshold:
        import gc
        gc.set_threshold(*(int(v) for v in a.gc_threshold.split(",")))
    prof = None
    if a.profile:
        import cProfile
        prof = cProfile.Profile()
    trees = a.trees or [None]
    res = {(t, n): ([], []) for t in trees for n in a.only}
    hashes = {}
    for r in range(a.rounds):
        order = trees if r % 2 == 0 else trees[::-1]
        order = order + order[::-1] if len(trees) > 1 else order
        for t in order:
            gc_setting = t is not None and t.startswith("gc:")
            if gc_setting:
                import gc
                gc.set_threshold(*(int(v) for v in t[3:].split(",")))
            elif t is not None:
                _purge()
                sys.path.insert(0, str(Path(t).resolve()))
            try:
                names = a.only if r % 2 == 0 else a.only[::-1]
                for n in names:
                    tr, lo, eqns, ops, text = measure(n, prof)
                    res[(t, n)][0].append(tr)
                    res[(t, n)][1].append(lo)
                    h = hashlib.sha256(text.encode()).hexdigest()[:16]
                    hashes.setdefault((t, n), set()).add(h)
                    print(f"round {r} {t or '.'} {n:12s} trace {tr:6.3f} s  lower {lo:6.3f} s  eqns {eqns:6d}  "
                          f"ops {ops:6d}  {h}", flush=True)
                    if a.out is not None:
                        d = a.out / (Path(t).name if t and not gc_setting else "")
                        d.mkdir(parents=True, exist_ok=True)
                        (d / f"{n}.mlir").write_text(text)
            finally:
                if t is not None and not gc_setting:
                    sys.path.remove(str(Path(t).resolve()))
    print("\nmedian CPU s         " + "  ".join(f"{(t or '.')[-14:]:>22s}" for t in trees))
    for n in a.only:
        cells = [f"{statistics.median(res[(t, n)][0]):8.3f} / {statistics.median(res[(t, n)][1]):8.3f}"
                 for t in trees]
        same = len({h for t in trees for h in hashes[(t, n)]}) == 1
        print(f"{n:12s} trace/lower " + "  ".join(f"{c:>22s}" for c in cells) + f"   one program: {same}")
    tot = [(sum(statistics.median(res[(t, n)][0]) for n in a.only),
            sum(statistics.median(res[(t, n)][1]) for n in a.only)) for t in trees]
    print(f"{'total':12s} trace/lower " + "  ".join(f"{x:8.3f} / {y:8.3f}".rjust(22) for x, y in tot))
    if prof is not None:
        prof.dump_stats(str(a.profile))


if __name__ == "__main__":
    main()
