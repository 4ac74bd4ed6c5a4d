"""The DRHE points of tune-loops (versions 8-10) on many common seeds: which is better, and why
512 evaluation seeds could not tell (rare tube exits). Run: python benchmarks/tune_loops_tail.py [seeds]
(docs/tuning_loops.md, "512 evaluation seeds are too few on DRHE")."""
import sys, time
import numpy as np, jax, jax.numpy as jnp
from jaxnc import montecarlo
from jaxnc.experiments import tune_loops as tl
from jaxnc.tune.loop_tune import set_paths
from jaxnc.tune.check import objective_total
n = int(sys.argv[1]) if len(sys.argv) > 1 else 8192
p = tl.BUILDERS["drhe"]({"w_drhe": 30.0})
pts = {"tuner v9/v10 (0.00959, 1e-4)": (0.009587315, 1e-4), "search (0.0306, 1e-4)": (0.03063887, 1e-4),
       "v8 pick (0.00959, 1e-3)": (0.009587315, 1e-3)}
keys = montecarlo.seed_keys(7_000_003, n)
vals = {}
for name, (d, s) in pts.items():
    lp = set_paths(p.loop, {"trigger.delta": np.float32(d), "trigger.sigma": np.float32(s)})
    t0 = time.time()
    vals[name] = np.asarray(montecarlo.run_batched(lambda k, lp: objective_total(p.objective(p.run(lp, k))), keys,
                                                   args=(lp,), chunk_size=1024, progress=False), np.float64)
    v = vals[name]
    print(f"{name}: mean {v.mean():.4f} +- {1.96 * v.std(ddof=1) / np.sqrt(n):.3f}; median {np.median(v):.4f}; "
          f"share of runs above 10: {np.mean(v > 10):.4f}; {time.time() - t0:.0f} s", flush=True)
names = list(pts)
for a in names[1:]:
    d = vals[names[0]] - vals[a]
    for m in (512, 2048, n):
        dd = d[:m]
        print(f"  {names[0]} - {a} on the first {m}: {dd.mean():+.4f} +- {1.96 * dd.std(ddof=1) / np.sqrt(m):.3f}")
    big = np.argsort(-np.abs(d))[:5]
    print("   largest |diff| seeds:", big.tolist(), np.round(d[big], 2).tolist(), "sum share",
          round(float(np.sum(d[big]) / np.sum(d)), 2))
