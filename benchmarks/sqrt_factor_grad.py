"""The square-root EKF's factor derivative (``jaxnc.estimators.ekf._tria``) against JAX's QR
derivative on the cart-pole example (examples/cartpole.py, EKF(form="sqrt")): the
straight-through gradient of the run's cost in log delta (delta = 1e-3, temperature 1e-2) on 64
seeds at the example's 30 % loss (both finite: their relative differences), and how many seeds
give a NaN gradient at 99.9 % loss (delta = 1e-2).

    PYTHONPATH=. python benchmarks/sqrt_factor_grad.py
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import jax                                   # noqa: E402
import jax.numpy as jnp                      # noqa: E402
import numpy as np                           # noqa: E402
from cartpole import cartpole, cost_of_log_delta   # noqa: E402

import jaxnc.estimators.ekf as ekf           # noqa: E402
from jaxnc import montecarlo                 # noqa: E402

KEYS = montecarlo.seed_keys(0, 64)


def grads(p_loss, delta):
    obj = cost_of_log_delta(cartpole(p_loss=p_loss))
    g = jax.jit(jax.vmap(jax.grad(obj), in_axes=(None, 0, None)))(jnp.array([np.log(delta)]), KEYS, 1e-2)
    return np.asarray(g)[:, 0]


ours = ekf._tria
results = {}
for name, fn in (("ours", ours), ("QR", lambda M: jnp.linalg.qr(M.T, mode="r").T)):
    ekf._tria = fn
    results[name] = (grads(0.3, 1e-3), grads(0.999, 1e-2))
ekf._tria = ours
(a, a_lost), (b, b_lost) = results["ours"], results["QR"]
fin = np.isfinite(a) & np.isfinite(b)
rel = np.abs(a[fin] - b[fin]) / np.maximum(np.abs(b[fin]), 1e-6)
print(f"30 % loss: finite {np.isfinite(a).sum()} (ours) / {np.isfinite(b).sum()} (QR) of 64; relative difference "
      f"median {np.median(rel):.2g}, largest {rel.max():.2g}; means {a[fin].mean():.7g} / {b[fin].mean():.7g}")
print(f"99.9 % loss: NaN gradients {np.sum(~np.isfinite(a_lost))} (ours) / {np.sum(~np.isfinite(b_lost))} (QR) of 64")
