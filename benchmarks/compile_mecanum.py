"""Compile cost of `make run`'s two loop programs (seed 000: nominal SR at N = 1, the cases at N = 10).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/compile_mecanum.py [--seeds 256] [--top 25] [--trees A B ...] [--pieces]

For each loop program of ``jaxnc run mecanum --seeds 256 --set case=all`` (the per-seed
function and the configuration as a runtime argument, exactly as the experiment hands them to
``run_batched``: ``jit(vmap(fn, in_axes=(0, None)))`` over ``--seeds`` keys) it reports:
trace + lower CPU seconds, the number of StableHLO operations of the lowered module, XLA
``compile()`` CPU seconds (no persistent cache), the number of HLO instructions of the compiled
module, the outputs (compared bit for bit with the first tree's), and the top source locations by StableHLO operation count (the file:line of each
operation's innermost ``loc`` frame in this package), so that what dominates a program and
what is traced several times can be read off. With ``--trees`` each checkout is imported in
turn in this one process (as ``ab_inprocess.py``), in the order A B ... B A, and the compile
CPU seconds of each are the median of its compilations (``--rounds`` times A B ... B A). ``--pieces`` compiles each role's step
of DRHE N = 10 alone (:func:`pieces`).
"""
from __future__ import annotations

import argparse
import collections
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("JAXNC_NO_CACHE", "1")


def _purge():
    for m in list(sys.modules):
        if m == "jaxnc" or m.startswith(("jaxnc.", "experiments", "tests")):
            del sys.modules[m]


def programs(seeds: int):
    """[(name, jitted fn, args)] of `make run`'s two loop programs, from the imported checkout."""
    import jax
    from experiments import mecanum as exp
    from jaxnc import montecarlo
    settings = {o.name: o.default for o in exp.EXPERIMENT.options}
    settings["case"] = "all"
    loops = exp.build_loops(settings)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    record_paths = seeds * max(l.steps for l in loops.values()) * 2 * 4 <= exp.POSITION_BUDGET
    fn = exp.run_seed_positions if record_paths else exp.run_seed
    out = []
    for name in ("SR nominal", "DRHE"):
        loop = loops[name]
        arg = montecarlo.uniform_dtypes(exp.with_positions(loop) if record_paths else loop)
        out.append((f"{name} N={loop.N}", jax.jit(jax.vmap(fn, in_axes=(0, None))), (keys, arg)))
    return out


_LOC_DEF = re.compile(r'^(#loc\d+) = loc\((.*)\)$', re.M)


def loc_table(text: str):
    """{#locN: innermost 'file:line' inside jaxnc or experiments} from a module's debug text."""
    raw = dict(_LOC_DEF.findall(text))
    memo = {}

    def resolve(ref, depth=0):
        if ref in memo or depth > 50:
            return memo.get(ref)
        body = raw.get(ref, "")
        hit = None
        m = re.search(r'"([^"]*(?:jaxnc|experiments)/[^"]*)":(\d+)', body)
        if m:
            hit = f"{m.group(1).split('/jaxnc/')[-1].split('/experiments/')[-1]}:{m.group(2)}"
        else:
            for sub in re.findall(r'#loc\d+', body):
                hit = resolve(sub, depth + 1)
                if hit:
                    break
        memo[ref] = hit
        return hit

    return {k: resolve(k) for k in raw}


def measure(name, f, args, top):
    import jax
    c0 = time.process_time()
    lowered = f.lower(*args)
    c1 = time.process_time()
    text = lowered.as_text(debug_info=True)
    ops = [l for l in text.splitlines() if re.search(r'^\s*(%\S+ = |"?stablehlo\.|stablehlo\.)', l)
           and "stablehlo." in l]
    c2 = time.process_time()
    compiled = lowered.compile()
    c3 = time.process_time()
    n_kernels = compiled.as_text().count(" fusion(")
    outs = [np.asarray(v) for v in jax.tree.leaves(compiled(*args))]
    hlo = compiled.as_text()
    n_hlo = sum(1 for l in hlo.splitlines() if re.match(r'^\s*(ROOT )?%?[\w.\-]+ = ', l))
    locs = loc_table(text)
    per = collections.Counter()
    for l in ops:
        m = re.search(r'loc\((#loc\d+)\)\s*$', l)
        per[locs.get(m.group(1)) if m else None] += 1
    print(f"\n## {name}: trace+lower {c1 - c0:.2f} CPU s, {len(ops)} StableHLO ops; "
          f"compile {c3 - c2:.2f} CPU s, {n_hlo} HLO instructions after optimisation, {n_kernels} kernels (fusion call sites)")
    for loc, n in per.most_common(top):
        print(f"  {n:6d}  {loc}")
    return dict(lower=c1 - c0, ops=len(ops), compile=c3 - c2, hlo=n_hlo, kernels=n_kernels, outs=outs)


def pieces(seeds: int):
    """Compile CPU s and kernels (fusion call sites) of each role's step of DRHE N = 10 alone,
    ``jit(vmap)`` over ``seeds`` lanes from the roles' initial states: where a loop program's
    compile time goes (the pieces overlap the whole only roughly: XLA fuses across roles)."""
    import jax
    import jax.numpy as jnp
    from jaxnc import loop as nc
    from jaxnc.loop.runner import _first_inbox
    _, _, (keys, lp) = programs(seeds)[1]
    ctx = lp.ctx
    bc = lambda t: jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a), (seeds,) + jnp.shape(a)), t)
    est0, ctrl0, act0 = lp.estimator.init(ctx), lp.controller.init(ctx), lp.actuator.init(ctx)
    inbox = _first_inbox(lp, ctx)
    xhat = lp.estimator.correct(est0, inbox, jnp.int32(0))[1]
    x0 = jnp.asarray(lp.plant.x0)
    cases = [
        ("estimator.correct (eq. 13-16)", lambda l, s, b: l.estimator.correct(s, b, jnp.int32(3)), bc(est0), bc(inbox)),
        ("estimator.predict (N x eq. 11)", lambda l, s, u: l.estimator.predict(s, u, u, jnp.int32(3)), bc(est0),
         bc(jnp.ones((ctx.N, ctx.input_dim)))),
        ("controller.step (chain start + N advances)", lambda l, s, x: l.controller.step(s, x, jnp.float32(1),
                                                                                       jnp.int32(3), ctx),
         bc(ctrl0), bc(xhat)),
        ("actuator.output (one advance)", lambda l, s: l.actuator.output(s, jnp.int32(3)), bc(act0)),
        ("plant.dynamics", lambda l, x, w: l.plant.dynamics(x, jnp.ones(ctx.input_dim), w), bc(x0),
         bc(jnp.zeros(lp.plant.noise_dim))),
        ("monitor.step", lambda l, m, x: l.monitor.step(m, x, jnp.ones(ctx.input_dim), jnp.int32(3)),
         bc(lp.monitor.init(ctx)), bc(x0)),
        ("draw (all of a run's draws)", lambda l, k: nc.draw(l, k), keys),
    ]
    print("\n| DRHE N = 10, one role's step alone | compile CPU s | kernels (fusion call sites) |\n|---|---|---|")
    for name, g, *a in cases:
        low = jax.jit(jax.vmap(g, in_axes=(None,) + (0,) * len(a))).lower(lp, *a)
        c0 = time.process_time()
        c = low.compile()
        print(f"| {name} | {time.process_time() - c0:.2f} | {c.as_text().count(' fusion(')} |")


def same(a, b):
    return len(a) == len(b) and all(x.dtype == y.dtype and x.shape == y.shape and
                                    np.array_equal(x.view(np.uint8), y.view(np.uint8)) for x, y in zip(a, b))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--trees", nargs="*", type=Path, default=None)
    ap.add_argument("--rounds", type=int, default=1, help="A B ... B A this many times (with --trees)")
    ap.add_argument("--pieces", action="store_true", help="also compile each role's step of DRHE N = 10 alone")
    a = ap.parse_args()
    if a.pieces:
        pieces(a.seeds)
    if not a.trees:
        for name, f, args in programs(a.seeds):
            measure(name, f, args, a.top)
        return
    trees = [t.resolve() for t in a.trees]
    order = list(range(len(trees)))
    res = collections.defaultdict(list)
    for i in (order + order[::-1]) * a.rounds:
        _purge()
        sys.path.insert(0, str(trees[i]))
        try:
            import jax
            jax.clear_caches()
            for name, f, args in programs(a.seeds):
                res[(i, name)].append(measure(f"{'ABCDEFGH'[i]} {trees[i]} {name}", f, args, 0 if res[(i, name)] else a.top))
        finally:
            sys.path.remove(str(trees[i]))
    print(f"\n| tree | program | trace+lower CPU s | StableHLO ops | compile CPU s (median; each) | HLO instructions "
          f"| kernels | outputs bit-identical to A |")
    print("|---|---|---|---|---|---|---|---|")
    for (i, name), rs in res.items():
        print(f"| {'ABCDEFGH'[i]} {trees[i]} | {name} | {sum(r['lower'] for r in rs) / len(rs):.2f} | {rs[0]['ops']} "
              f"| {float(np.median([r['compile'] for r in rs])):.2f} ({', '.join('%.2f' % r['compile'] for r in rs)}) "
              f"| {rs[0]['hlo']} | {rs[0]['kernels']} | {'yes' if same(rs[0]['outs'], res[(0, name)][0]['outs']) else 'NO'} |")


if __name__ == "__main__":
    main()
