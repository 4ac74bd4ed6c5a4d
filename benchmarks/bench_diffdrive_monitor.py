"""CPU and wall time of diffdrive scenario e (compile, then the best of 3 runs of 128 seeds) with the
jaxnc on PYTHONPATH; prints one JSON line. Used for benchmarks/RESULTS.md (PathMonitor in the loop).

    PYTHONPATH=<tree> python benchmarks/bench_diffdrive_monitor.py LABEL
"""
import sys, time, resource, json
import jax, numpy as np
from jaxnc import montecarlo
from jaxnc.schemes import diffdrive as dd
cpu = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_stime
loop = dd.diffdrive_loop("e")
keys = montecarlo.seed_keys(1, 128)
f = jax.jit(jax.vmap(lambda k, lp: dd.run(lp, k), in_axes=(0, None)))
c0, w0 = cpu(), time.perf_counter()
jax.block_until_ready(f.lower(keys, loop).compile())
comp = (cpu() - c0, time.perf_counter() - w0)
runs = []
for _ in range(3):
    c0, w0 = cpu(), time.perf_counter()
    jax.block_until_ready(f(keys, loop))
    runs.append((cpu() - c0, time.perf_counter() - w0))
print(json.dumps({"tree": sys.argv[1], "compile_cpu_s": comp[0], "compile_wall_s": comp[1],
                  "run_cpu_s": min(r[0] for r in runs), "run_wall_s": min(r[1] for r in runs)}))
