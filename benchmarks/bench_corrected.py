"""The corrected pathwise gradient on a gain, against central differences and the score function.

    python benchmarks/bench_corrected.py [--loops servo,cartpole,hdd] [--seeds 4096] [--out docs/results/jump]

For each loop, one gain coordinate theta (hard triggers), on the same seeds (common random
numbers): the central difference (J(theta + h) - J(theta - h)) / 2h (the reference), the
antithetic score function at scale h / sqrt(3) (the smoothing of the central difference,
docs/tuning_loops.md), the corrected pathwise gradient (:mod:`jaxnc.tune.jump`) and, for
information, the pathwise gradient alone (decisions held). Reported per estimator: the mean
and its standard error, z of the paired difference to the central difference, the
variance per seed, runs per seed, the variance per run (variance x runs per seed: the
variance of a mean bought with one run's budget), the seeds a check needs to resolve the
gain (n (1.96 SE_diff / |gradient|)^2, the rule of jaxnc.tune.check), and the wall time per
seed (compiled; on a shared, busy 2-core machine: ratios within one run only).

Loops: ``servo`` (:func:`servo`, theta = Kp, the position gain), ``cartpole``
(examples/cartpole.py, theta = a multiplier of the LQR gain), ``hdd`` (seed 003, Case 4,
its paper thresholds; theta = a multiplier of the MRCI controller's output matrices, i.e.
of its gain).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc.tune.jump import corrected_grad

RUNS = {"finite difference": 2, "score (s = h/sqrt 3)": 2, "score (s = 0.1 theta)": 2, "corrected": 4,
        "corrected, 4 alternatives": 10,
        "pathwise (decisions held)": 1}


def servo(delta=1e-2, K=(3.0, 1.5)):
    """A 2-state servo (position, damped velocity; T = 0.1 s) with an EKF, PETC on the noisy
    position (noise 0.05, delta = 0.01), state feedback u = -K xhat from x0 = (1, 0), 4 s;
    the loop of tests/test_loop_tune.py on an ideal link."""
    A = np.array([[1.0, 0.1], [0.0, 0.95]])
    plant = nc.LTI(A=A, B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0], w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([0.01, 0.02]) ** 2, R=np.eye(1) * 0.05 ** 2, mean0=[0.0, 0.0], cov0=np.eye(2))
    return nc.Loop(plant=plant, trigger=nc.Petc(delta=delta), uplink=nc.Link(), estimator=ekf,
                   controller=nc.StateFeedback(np.asarray([K])), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=40, T=0.1)


def problem(name):
    """(loop_of(theta float[1]) -> Loop, cost(loop, key) -> scalar, theta0, h)."""
    if name == "servo":
        base = servo()

        def loop_of(t):
            K = jnp.stack([t[0], jnp.float32(base.controller.K[0, 1])])[None, :]
            return dataclasses.replace(base, controller=dataclasses.replace(base.controller, K=K))
        return loop_of, lambda lp, k: nc.run(lp, k).cost_raw, np.float32([3.0]), 0.05
    if name == "cartpole":
        import importlib.util
        spec = importlib.util.spec_from_file_location("cp", Path(__file__).resolve().parents[1] / "examples" /
                                                      "cartpole.py")
        cp = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(cp)
        base = cp.cartpole(delta=1e-3)
        K0 = jnp.asarray(base.controller.K)

        def loop_of(t):
            return dataclasses.replace(base, controller=dataclasses.replace(base.controller, K=K0 * t[0]))
        return loop_of, lambda lp, k: nc.run(lp, k).cost_raw + 2.0 * nc.run(lp, k).rate_sc, np.float32([1.0]), 0.05
    if name == "hdd":
        from jaxnc.schemes import hdd
        y_tts, ise_tts = hdd.tts_reference()
        cs = hdd.controller_design().cs
        base = hdd.hdd_loop(4)
        law = base.controller.law
        c0 = law.ctrl

        def loop_of(t):
            g = t[0]
            ctrl = dataclasses.replace(c0, Cs=c0.Cs * g, Ds=c0.Ds * g, Cf=c0.Cf * g, Df=c0.Df * g)
            return dataclasses.replace(base, controller=dataclasses.replace(
                base.controller, law=dataclasses.replace(law, ctrl=ctrl)))

        def cost(lp, k):
            m = hdd.run(lp, k, y_tts=y_tts, ise_tts=ise_tts, cs=cs)
            return jnp.where(m.unstable | ~jnp.isfinite(m.GPI), 10.0, m.GPI)
        return loop_of, cost, np.float32([1.0]), 0.05
    raise ValueError(f"unknown loop {name!r}")


def estimators(loop_of, cost, theta0, h):
    th = jnp.asarray(theta0)
    J = lambda t, k: cost(loop_of(t), k)
    s = h / np.sqrt(3.0)

    def fd(key):
        return (J(th + h, key) - J(th - h, key)) / (2 * h)

    def score(key, s=s):
        e = jax.random.normal(jax.random.fold_in(key, 7919), (1,), jnp.float32)
        return (J(th + s * e, key) - J(th - s * e, key)) / (2 * s) * e

    def corrected(key):
        return corrected_grad(loop_of, cost, th, key)[1]

    def pathwise(key):
        return jax.grad(lambda t: J(t, key))(th)

    return {"finite difference": fd, "score (s = h/sqrt 3)": score,
            "score (s = 0.1 theta)": lambda key: score(key, 0.1 * float(theta0[0])),
            "corrected": corrected,
            "corrected, 4 alternatives": lambda key: corrected_grad(loop_of, cost, th, key, alternatives=4)[1],
            "pathwise (decisions held)": pathwise}


def measure(name, seeds, chunk, seed=0, skip=()):
    loop_of, cost, theta0, h = problem(name)
    keys = montecarlo.seed_keys(seed, seeds)
    vals, secs = {}, {}
    for est, fn in estimators(loop_of, cost, theta0, h).items():
        if est in skip:
            continue
        f = lambda k, fn=fn: jnp.ravel(fn(k))[0]
        montecarlo.run_batched(f, keys[:chunk], chunk_size=chunk, progress=False)       # compile
        t0 = time.perf_counter()
        vals[est] = np.asarray(montecarlo.run_batched(f, keys, chunk_size=chunk, progress=False), float)
        secs[est] = (time.perf_counter() - t0) / seeds
        print(f"  {name} {est}: {secs[est] * 1e3:.2f} ms/seed", flush=True)
    fd = vals["finite difference"]
    n = seeds
    rows = []
    for est, v in vals.items():
        mean, se = v.mean(), v.std(ddof=1) / np.sqrt(n)
        diff = v - fd
        sd = diff.std(ddof=1) / np.sqrt(n)
        z = 0.0 if est == "finite difference" else (diff.mean() / sd if sd > 0 else float("inf"))
        size = max(abs(mean), abs(fd.mean()))
        need = n if est == "finite difference" else int(np.ceil(n * (1.96 * sd / size) ** 2))
        var = v.var(ddof=1)
        rows.append(dict(loop=name, estimator=est, theta=float(theta0[0]), h=h, seeds=n, mean=mean, se=se, z=z,
                         var_per_seed=var, runs_per_seed=RUNS[est], var_per_run=var * RUNS[est],
                         seeds_to_conclusive=need, ms_per_seed=secs[est] * 1e3,
                         var_x_seconds=var * secs[est]))
    return rows


def table(rows):
    out = ["| loop | estimator | gradient (± 95 %) | z vs central diff. | variance per seed | runs per seed | "
           "variance per run | seeds to a conclusive check | ms per seed | variance x s per seed |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['loop']} | {r['estimator']} | {r['mean']:.4g} ± {1.96 * r['se']:.2g} | "
                   f"{'-' if r['estimator'] == 'finite difference' else f'{r[chr(122)]:+.2f}'} | "
                   f"{r['var_per_seed']:.3g} | {r['runs_per_seed']} | {r['var_per_run']:.3g} | "
                   f"{'-' if r['estimator'] == 'finite difference' else r['seeds_to_conclusive']} | "
                   f"{r['ms_per_seed']:.2f} | {r['var_x_seconds']:.3g} |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--loops", default="servo,cartpole,hdd")
    ap.add_argument("--seeds", type=int, default=4096)
    ap.add_argument("--chunk", type=int, default=256)
    ap.add_argument("--out", default="docs/results/jump")
    ap.add_argument("--skip", default="", help="estimators left out, separated by ';'")
    a = ap.parse_args()
    rows = []
    for name in a.loops.split(","):
        t0 = time.perf_counter()
        rows += measure(name, a.seeds, min(a.chunk, a.seeds), skip=tuple(x for x in a.skip.split(";") if x))
        print(f"{name}: {time.perf_counter() - t0:.0f} s", flush=True)
    print(table(rows))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "_".join(a.loops.split(","))
    command = " ".join(["python benchmarks/bench_corrected.py", f"--loops {a.loops}", f"--seeds {a.seeds}",
                        f"--chunk {a.chunk}"] + ([f"--skip '{a.skip}'"] if a.skip else []))
    (out / f"gains_{tag}.json").write_text(json.dumps(dict(command=command, rows=rows), indent=1, default=float))
    (out / f"gains_{tag}.md").write_text(table(rows) + "\n")


if __name__ == "__main__":
    main()
