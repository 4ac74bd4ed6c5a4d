"""A small loop's exact gradient with rematerialisation policies on the runner's scans (issue 32).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/bench_grad_remat.py [--seeds 256] [--repeat 3]
      [--variants none slow:nothing slow:dots fast:nothing]

The objective is bench_grad.py's (mean quadratic cost over ``--seeds`` seeds as a function of
the cart-pole's LQR gain K, or ``--loop servo``: the servo's PI gains). Variants wrap the body of the runner's slow-period scan (``slow``) or of
every scan (``all``) in ``jax.checkpoint`` with a policy (``nothing``: save nothing,
recompute the body in the backward pass; ``dots``: save matrix products without batch
dimensions; ``everything``: save every residual), by patching ``jax.lax.scan`` as the
runner's module sees it while the programs are traced; ``none`` is the runner as it is.
Forward and value_and_grad are compiled (CPU seconds) and timed interleaved (best process
CPU time); the gradient of every variant is compared with the first one. ``loop`` is the
library's own option, ``Loop(remat=True)`` (the slow body, ``nothing_saveable``).
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from examples.cartpole import cartpole  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.loop import runner  # noqa: E402

POLICIES = {"nothing": jax.checkpoint_policies.nothing_saveable,
            "dots": jax.checkpoint_policies.dots_with_no_batch_dims_saveable,
            "everything": jax.checkpoint_policies.everything_saveable}


class _Lax:
    """``jax.lax`` as the runner sees it, with scan bodies wrapped in ``jax.checkpoint``."""

    def __init__(self, where, policy):
        self.where, self.policy, self.depth = where, policy, 0

    def __getattr__(self, name):
        return getattr(jax.lax, name)

    def scan(self, f, *args, **kw):
        if self.where == "slow" and self.depth > 0:
            return jax.lax.scan(f, *args, **kw)

        def body(c, x):
            self.depth += 1
            try:
                return f(c, x)
            finally:
                self.depth -= 1
        return jax.lax.scan(jax.checkpoint(body, policy=self.policy), *args, **kw)


class _Jax:
    def __init__(self, lax):
        self.lax = lax

    def __getattr__(self, name):
        return getattr(jax, name)


@contextlib.contextmanager
def patched(variant):
    if variant in ("none", "loop"):
        yield
        return
    where, pol = variant.split(":")
    old = runner.jax
    runner.jax = _Jax(_Lax(where, POLICIES[pol]))
    try:
        yield
    finally:
        runner.jax = old


def objective(name, remat=False):
    """(objective(theta, keys), theta): bench_grad.py's cart-pole (d/dK) or servo (d/d(Kp, Ki));
    ``remat``: the loop's own option, ``Loop(remat=True)``."""
    if name == "servo":
        from benchmarks.direct_servo import servo
        sv = dataclasses.replace(servo(), remat=remat)

        def serv(theta, keys):
            lp = dataclasses.replace(sv, controller=dataclasses.replace(sv.controller, Kp=theta[:1], Ki=theta[1:]))
            return jnp.mean(jax.vmap(lambda k: nc.run(lp, k).cost_raw)(keys))
        return serv, jnp.asarray([2.0, 1.0], jnp.float32)
    cp = dataclasses.replace(cartpole(), remat=remat)

    def cart(theta, keys):
        lp = dataclasses.replace(cp, controller=dataclasses.replace(cp.controller, K=theta))
        return jnp.mean(jax.vmap(lambda k: nc.run(lp, k).cost_raw)(keys))
    return cart, jnp.asarray(cp.controller.K, jnp.float32)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--loop", choices=("cartpole", "servo"), default="cartpole")
    ap.add_argument("--variants", nargs="+", default=["none", "slow:nothing", "slow:dots", "all:nothing"])
    a = ap.parse_args()
    keys = montecarlo.seed_keys(0, a.seeds)
    obj, theta = objective(a.loop)
    progs = {}
    c0 = time.process_time()
    progs["forward"] = jax.jit(obj).lower(theta, keys).compile()
    comp = {"forward": time.process_time() - c0}
    for v in a.variants:
        with patched(v):
            c0 = time.process_time()
            o = objective(a.loop, remat=True)[0] if v == "loop" else obj
            progs[v] = jax.jit(jax.value_and_grad(o)).lower(theta, keys).compile()
            comp[v] = time.process_time() - c0
        print(f"compiled {v}: {comp[v]:.1f} CPU s", flush=True)
    out = {n: jax.block_until_ready(p(theta, keys)) for n, p in progs.items()}
    cpu = {n: [] for n in progs}
    names = list(progs)
    for r in range(a.repeat):
        for n in (names if r % 2 == 0 else names[::-1]):
            c0 = time.process_time()
            jax.block_until_ready(progs[n](theta, keys))
            cpu[n].append(time.process_time() - c0)
    g0 = np.asarray(out[a.variants[0]][1])
    print(f"\n{a.loop}, mean cost over {a.seeds} seeds; best of {a.repeat} (process CPU s); "
          f"load {os.getloadavg()[0]:.1f}\n")
    print("| program | compile CPU s | run CPU s | / forward (run) | / forward (compile) | max rel. gradient diff |")
    print("|---|---|---|---|---|---|")
    f = min(cpu["forward"])
    for n in names:
        b = min(cpu[n])
        d = "" if n == "forward" else f"{np.max(np.abs(np.asarray(out[n][1]) - g0) / np.maximum(np.abs(g0), 1e-30)):.1e}"
        print(f"| {'value_and_grad, ' + n if n != 'forward' else n} | {comp[n]:.1f} | {b:.3f} | x{b / f:.2f} "
              f"| x{comp[n] / comp['forward']:.2f} | {d} |")


if __name__ == "__main__":
    main()
