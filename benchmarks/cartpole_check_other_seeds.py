"""The tune-loops cart-pole check at delta = 1e-2 on other seeds than the study's (8192 seeds, seed base 100).

    python benchmarks/cartpole_check_other_seeds.py
"""
import sys
import time
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1]))
from experiments import tune_loops as tl
settings = {"w_cartpole": 2.0}
p = tl._cartpole(settings)
from jaxnc.tune import check_loop

for base in (100,):
    t = time.perf_counter()
    chk = check_loop(p.loop, p.params, p.objective, run=p.run, at={"trigger.delta": 1e-2}, seeds=8192, seed=base,
                     fd_step=p.fd_step, score_scale=tl._score_scale(p))
    print(f"seed base {base}: {time.perf_counter() - t:.0f} s"); print(chk.table(), flush=True)
