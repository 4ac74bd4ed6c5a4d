"""Exact reverse-mode gradient against the forward pass on the small user loops (issue 32).

Run:  .venv/bin/python benchmarks/bench_grad.py [--seeds 256] [--repeat 3] [--no-record]

Objective: the mean over ``--seeds`` seeds of a loop's quadratic cost (``Metrics.cost_raw``,
no failure mask), as a function of the controller's gains: the cart-pole's LQR gain K
(examples/cartpole.py, the PETC trigger hard) and the servo's PI gains Kp, Ki
(benchmarks/direct_servo.py). For each loop ``jit(objective)`` and
``jit(value_and_grad(objective))`` are compiled (first call minus the best repeat) and
timed interleaved, wall and process CPU time; the ratios are from the same run. DRHE's
is ``benchmarks/bench_mecanum.py --only-grad``. Appends the table to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _record import record  # noqa: E402
from benchmarks.direct_servo import servo  # noqa: E402
from examples.cartpole import cartpole  # noqa: E402
from jaxnc import loop as nc  # noqa: E402
from jaxnc import montecarlo  # noqa: E402
from jaxnc.report import markdown_table  # noqa: E402


def _objectives():
    cp, sv = cartpole(), servo()

    def cart(theta, keys):
        lp = dataclasses.replace(cp, controller=dataclasses.replace(cp.controller, K=theta))
        return jnp.mean(jax.vmap(lambda k: nc.run(lp, k).cost_raw)(keys))

    def serv(theta, keys):
        lp = dataclasses.replace(sv, controller=dataclasses.replace(sv.controller, Kp=theta[:1], Ki=theta[1:]))
        return jnp.mean(jax.vmap(lambda k: nc.run(lp, k).cost_raw)(keys))

    return {"cart-pole (examples/cartpole.py), d/dK": (cart, jnp.asarray(cp.controller.K, jnp.float32)),
            "servo (benchmarks/direct_servo.py), d/d(Kp, Ki)": (serv, jnp.asarray([2.0, 1.0], jnp.float32))}


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, time.process_time() - c0, out


def bench(seeds, repeat):
    keys = montecarlo.seed_keys(0, seeds)
    rows = []
    for name, (obj, theta) in _objectives().items():
        progs = {"forward": jax.jit(obj), "value_and_grad": jax.jit(jax.value_and_grad(obj))}
        first = {n: _timed(lambda: p(theta, keys)) for n, p in progs.items()}
        g = first["value_and_grad"][2][1]
        assert np.all(np.isfinite(np.asarray(g))), f"{name}: non-finite gradient"
        wall, cpu = {n: np.inf for n in progs}, {n: np.inf for n in progs}
        for _ in range(repeat):
            for n, p in progs.items():
                w, c, _ = _timed(lambda: p(theta, keys))
                wall[n], cpu[n] = min(wall[n], w), min(cpu[n], c)
        comp = {n: max(first[n][0] - wall[n], 0.0) for n in progs}
        for n in progs:
            rows.append([name, n, f"{comp[n]:.2f}", f"{wall[n]:.3f}", f"{cpu[n]:.3f}"])
        rows.append([name, "**grad / forward**", f"x{comp['value_and_grad'] / comp['forward']:.2f}",
                     f"x{wall['value_and_grad'] / wall['forward']:.2f}", f"x{cpu['value_and_grad'] / cpu['forward']:.2f}"])
    return markdown_table([f"loop, mean cost over {seeds} seeds", "program", "compile (s)", "run (s, wall)",
                           "run (s, CPU time)"], rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-record", action="store_true", help="do not append to RESULTS.md")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md")
    a = ap.parse_args()
    table = bench(a.seeds, a.repeat)
    load = f"Load average {os.getloadavg()[0]:.1f} at the end (machine shared with other sessions)."
    print(table)
    print(load)
    if not a.no_record:
        record(a.results, ["### Exact gradient against the forward pass (small loops)\n\n" + table], note=load)


if __name__ == "__main__":
    main()
