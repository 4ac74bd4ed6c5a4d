"""tune-loops' DRHE points on many common seeds: which is better, and why 512 evaluation seeds
could not tell (rare tube exits); docs/tuning_loops.md, "512 evaluation seeds are too few on DRHE".

Run:  python benchmarks/tune_loops_tail.py [seeds] [loop] [delta,sigma ...]
      (defaults: 8192 seeds, drhe, the points of versions 8-10: the tuner's, the search's, version 8's)

Each point runs on the same seeds (base 7 000 003); the first point is compared with each other one,
paired, on the first 512, 2048 and all seeds, with the seeds whose difference is largest, and the
seeds Cochran's rule asks for (montecarlo.seeds_for_normal_interval) on each sample.
"""
import sys
import time

import numpy as np

from jaxnc import montecarlo
from jaxnc.experiments import tune_loops as tl
from jaxnc.tune.check import objective_total
from jaxnc.tune.loop_tune import set_paths

n = int(sys.argv[1]) if len(sys.argv) > 1 else 8192
loop = sys.argv[2] if len(sys.argv) > 2 else "drhe"
pts = [tuple(float(v) for v in a.split(",")) for a in sys.argv[3:]] or [
    (0.009587315, 1e-4), (0.03063887, 1e-4), (0.009587315, 1e-3)]
p = tl.BUILDERS[loop]({"w_drhe": 30.0})
keys = montecarlo.seed_keys(7_000_003, n)
vals = {}
for d, s in pts:
    lp = set_paths(p.loop, {"trigger.delta": np.float32(d), "trigger.sigma": np.float32(s)})
    t0 = time.time()
    v = np.asarray(montecarlo.run_batched(lambda k, lp: objective_total(p.objective(p.run(lp, k))), keys,
                                          args=(lp,), chunk_size=1024, progress=False), np.float64)
    vals[(d, s)] = v
    print(f"{loop} delta={d:.4g} sigma={s:.4g}: mean {v.mean():.4f} +- {1.96 * v.std(ddof=1) / np.sqrt(n):.3f}; "
          f"median {np.median(v):.4f}; std {v.std(ddof=1):.3f}; share of runs above 10: {np.mean(v > 10):.4f}; "
          f"Cochran's rule asks {montecarlo.seeds_for_normal_interval(v)} seeds; "
          f"{time.time() - t0:.0f} s", flush=True)
first = pts[0]
for other in pts[1:]:
    diff = vals[first] - vals[other]
    for m in (512, 2048, n):
        dd = diff[:m]
        print(f"  {first} - {other} on the first {m}: {dd.mean():+.4f} +- {1.96 * dd.std(ddof=1) / np.sqrt(m):.3f}"
              f" (Cochran's rule asks {montecarlo.seeds_for_normal_interval(dd)} seeds for the differences, "
              f"{montecarlo.seeds_for_normal_interval(vals[first][:m])} and "
              f"{montecarlo.seeds_for_normal_interval(vals[other][:m])} for the two points)")
    big = np.argsort(-np.abs(diff))[:5]
    print("   largest |diff| seeds:", big.tolist(), np.round(diff[big], 2).tolist(), "share of the sum",
          round(float(np.sum(diff[big]) / np.sum(diff)), 2))
