"""Bit identity of the tuners across a change: every number of check_loop / gradient_check / tune_loop on small
configurations (the tests' loops), pickled; then compared byte for byte.

Run:  (cd <tree A> && PYTHONPATH=$PWD python /path/to/benchmarks/tune_share_bits.py dump /tmp/a.pkl)
      (cd <tree B> && PYTHONPATH=$PWD python /path/to/benchmarks/tune_share_bits.py dump /tmp/b.pkl)
      python benchmarks/tune_share_bits.py compare /tmp/a.pkl /tmp/b.pkl
"""
import sys

if sys.argv[1] == "compare":
    del sys.argv[1]
    import pickle, sys, numpy as np
    a, b = (pickle.load(open(p, "rb")) for p in sys.argv[1:3])
    bad = []
    def cmp(x, y, path):
        if isinstance(x, dict):
            if set(x) != set(y): bad.append((path, "keys", set(x) ^ set(y))); return
            for k in x: cmp(x[k], y[k], f"{path}.{k}")
        elif isinstance(x, list):
            if len(x) != len(y): bad.append((path, "len")); return
            for i, (u, v) in enumerate(zip(x, y)): cmp(u, v, f"{path}[{i}]")
        elif isinstance(x, np.ndarray):
            if x.shape != y.shape or x.dtype != y.dtype or x.tobytes() != y.tobytes(): bad.append((path, x, y))
        elif isinstance(x, float) and isinstance(y, float):
            if not (x == y or (x != x and y != y)): bad.append((path, x, y))
        elif x != y: bad.append((path, x, y))
    cmp(a, b, "")
    print(len(bad), "differences"); [print(*d) for d in bad[:30]]
else:
    del sys.argv[1]
    # every number, pickled (bit comparison)
    import os, sys, pickle
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    sys.path.insert(0, os.path.join(os.getcwd(), "tests"))
    import dataclasses
    import numpy as np, jax
    from jaxnc import loop as nc, montecarlo
    from jaxnc.tune import Positive, Interval, Unconstrained, gradient_check
    from jaxnc.tune.loop_tune import check_loop, tune_loop
    import test_loop_tune as T
    import test_tune_jump as TJ
    from jaxnc.cache import compile_clock
    
    def flat(obj):
        if hasattr(obj, "_asdict"):
            return {k: flat(v) for k, v in obj._asdict().items() if k not in ("wall_time_s", "compile_s", "n_compilations", "stages")}
        if isinstance(obj, dict):
            return {k: flat(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return [flat(v) for v in obj]
        if isinstance(obj, (np.ndarray, np.generic, jax.Array)):
            return np.asarray(obj)
        return obj
    
    out = {}
    c0 = compile_clock()
    lp = dataclasses.replace(T._loop(K=(1.0, 0.6)), trigger=nc.Periodic())
    for i, at in enumerate((None, {"controller.K": [[2.0, 1.0]]})):
        out[f"gain{i}"] = flat(check_loop(lp, {"controller.K": Positive()}, at=at, seeds=16, fd_step=0.01))
    out["pair_obj"] = flat(check_loop(T._loop(delta=1e-2), {"trigger.delta": Positive()},
                                      lambda m: (m.cost_raw, 0.5 * m.rate_sc), seeds=8, chunk_size=8))
    out["pair_run"] = flat(check_loop(T._Pair(), {"b": Positive(), "a": Positive()}, lambda j: j, run=T._pair_run, seeds=8))
    out["linear"] = flat(gradient_check(T._linear, np.zeros(2, np.float32), montecarlo.seed_keys(0, 128), max_seeds=1024,
                                        more_keys=lambda s, c: montecarlo.seed_keys(0, c, start=s), z=3.0))
    out["jump"] = flat(gradient_check(T._jump_objective(), np.full(1, 0.5, np.float32), montecarlo.seed_keys(3, 512)))
    out["corrected"] = flat(check_loop(TJ._scalar_loop(), {"controller.K": Unconstrained()}, seeds=64, fd_step=0.05,
                                       corrected=True))
    for est in ("score", "auto", "straight_through"):
        out[f"tune_{est}"] = flat(T._compilations(steps=3, estimator=est, check_seeds=16, check_max_seeds=16))
    out["tune_search"] = flat(tune_loop(dataclasses.replace(T._loop(delta=1e-2), trigger=nc.Petc(sigma=1e-2, delta=1e-2)), {("trigger.delta", "trigger.sigma"): Positive()},
                                        lambda m: m.cost_raw + 0.5 * m.rate_sc,
                                        search={"trigger.delta=trigger.sigma": [1e-4, 1e-2, 1.0]}, search_budget=24,
                                        steps=2, batch=4, estimator="straight_through", eval_seeds=8, progress=False))
    out["tune_none"] = flat(tune_loop(T._loop(delta=1e-2), {"trigger.delta": Positive()}, lambda m: m.cost_raw + 0.5 * m.rate_sc,
                      search={"trigger.delta": [1e-4, 1e-3, 1e-2, 1e-1, 1.0]}, search_budget=30, estimator="none",
                      steps=2, batch=8, eval_seeds=8, progress=False))
    out["tune_static"] = flat(tune_loop(T._loop(), {"controller.K": Unconstrained()}, search={"estimator.buffer": [0, 2]},
                                        search_budget=16, steps=2, batch=4, eval_seeds=8, progress=False))
    c1 = compile_clock() - c0
    print("compile clock", c1)
    pickle.dump(out, open(sys.argv[1], "wb"))
