"""The DRHE tracking cost's straight-through gradient in (sigma, delta), one checkout per process.

Run:  JAXNC_NO_CACHE=1 .venv/bin/python benchmarks/bench_grad_drhe_trees.py TREE [N] [SEEDS]   (A B B A over two trees)

Builds seed 000's DRHE loop (N = 10 unless given, p = 0.3, PETC temperature 1e-2) from the
checkout TREE, compiles ``jit(f)`` and ``jit(value_and_grad(f))`` of the mean tracking cost over
64 seeds (or SEEDS; process CPU seconds of each compilation) and runs each four times in the
order f g g f (best process CPU seconds of each), printing one line with the forward value and
the gradient (full precision, to compare trees).
"""
import sys, time, numpy as np
tree = sys.argv[1]
sys.path.insert(0, tree)
import jax, jax.numpy as jnp, dataclasses
from jaxnc.schemes import mecanum as mec
N = int(sys.argv[2]) if len(sys.argv) > 2 else 10
seeds = int(sys.argv[3]) if len(sys.argv) > 3 else 64
lp = mec.mecanum_loop("DRHE", N, 0.3, trigger_temperature=1e-2)
keys = jax.random.split(jax.random.PRNGKey(3), seeds)
def f(sd):
    trig = dataclasses.replace(lp.trigger, sigma=sd[0] * jnp.ones(9), delta=sd[1] * jnp.ones(9))
    l = dataclasses.replace(lp, trigger=trig)
    return jnp.mean(jax.vmap(lambda k: mec.tracking_cost(l, k))(keys))
x = jnp.array([1e-3, 1e-2], jnp.float32)
c0 = time.process_time(); fg = jax.jit(jax.value_and_grad(f)).lower(x).compile(); cg = time.process_time() - c0
c0 = time.process_time(); ff = jax.jit(f).lower(x).compile(); cf = time.process_time() - c0
best = {}
for name, p in (("fwd", ff), ("grad", fg), ("grad", fg), ("fwd", ff)) * 2:
    jax.block_until_ready(p(x))
    c0 = time.process_time()
    jax.block_until_ready(p(x))
    best[name] = min(best.get(name, 9e9), time.process_time() - c0)
print(tree, f"N={N} seeds={seeds} compile fwd {cf:.1f} grad {cg:.1f}  run fwd {best['fwd']:.3f} grad {best['grad']:.3f} "
      f"ratio {best['grad'] / best['fwd']:.2f}  forward {float(ff(x))!r} gradient {np.asarray(fg(x)[1]).tolist()}")
