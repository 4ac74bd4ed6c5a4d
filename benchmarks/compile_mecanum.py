"""Compile cost of `make run`'s two loop programs (seed 000: nominal SR at N = 1, the cases at N = 10).

Run:  PYTHONPATH=. .venv/bin/python benchmarks/compile_mecanum.py [--seeds 256] [--top 25] [--trees A B ...]

For each loop program of ``jaxnc run mecanum --seeds 256 --set case=all`` (the per-seed
function and the configuration as a runtime argument, exactly as the experiment hands them to
``run_batched``: ``jit(vmap(fn, in_axes=(0, None)))`` over ``--seeds`` keys) it reports:
trace + lower CPU seconds, the number of StableHLO operations of the lowered module, XLA
``compile()`` CPU seconds (no persistent cache), the number of HLO instructions of the compiled
module, the outputs (compared bit for bit with the first tree's), and the top source locations by StableHLO operation count (the file:line of each
operation's innermost ``loc`` frame in this package), so that what dominates a program and
what is traced several times can be read off. With ``--trees`` each checkout is imported in
turn in this one process (as ``ab_inprocess.py``), in the order A B ... B A, and the compile
CPU seconds of each are the mean of its two compilations.
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
        arg = exp.uniform_dtypes(exp.with_positions(loop) if record_paths else loop)
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
    outs = [np.asarray(v) for v in jax.tree.leaves(compiled(*args))]
    hlo = compiled.as_text()
    n_hlo = sum(1 for l in hlo.splitlines() if re.match(r'^\s*(ROOT )?%?[\w.\-]+ = ', l))
    locs = loc_table(text)
    per = collections.Counter()
    for l in ops:
        m = re.search(r'loc\((#loc\d+)\)\s*$', l)
        per[locs.get(m.group(1)) if m else None] += 1
    print(f"\n## {name}: trace+lower {c1 - c0:.2f} CPU s, {len(ops)} StableHLO ops; "
          f"compile {c3 - c2:.2f} CPU s, {n_hlo} HLO instructions after optimisation")
    for loc, n in per.most_common(top):
        print(f"  {n:6d}  {loc}")
    return dict(lower=c1 - c0, ops=len(ops), compile=c3 - c2, hlo=n_hlo, outs=outs)


def same(a, b):
    return len(a) == len(b) and all(x.dtype == y.dtype and x.shape == y.shape and
                                    np.array_equal(x.view(np.uint8), y.view(np.uint8)) for x, y in zip(a, b))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=256)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--trees", nargs="*", type=Path, default=None)
    a = ap.parse_args()
    if not a.trees:
        for name, f, args in programs(a.seeds):
            measure(name, f, args, a.top)
        return
    trees = [t.resolve() for t in a.trees]
    order = list(range(len(trees)))
    res = collections.defaultdict(list)
    for i in order + order[::-1]:
        _purge()
        sys.path.insert(0, str(trees[i]))
        try:
            import jax
            jax.clear_caches()
            for name, f, args in programs(a.seeds):
                res[(i, name)].append(measure(f"{'ABCDEFGH'[i]} {trees[i]} {name}", f, args, 0 if res[(i, name)] else a.top))
        finally:
            sys.path.remove(str(trees[i]))
    print(f"\n| tree | program | trace+lower CPU s | StableHLO ops | compile CPU s (mean of 2) | HLO instructions "
          f"| outputs bit-identical to A |")
    print("|---|---|---|---|---|---|---|")
    for (i, name), rs in res.items():
        print(f"| {'ABCDEFGH'[i]} {trees[i]} | {name} | {sum(r['lower'] for r in rs) / len(rs):.2f} | {rs[0]['ops']} "
              f"| {sum(r['compile'] for r in rs) / len(rs):.2f} ({', '.join('%.2f' % r['compile'] for r in rs)}) "
              f"| {rs[0]['hlo']} | {'yes' if same(rs[0]['outs'], res[(0, name)][0]['outs']) else 'NO'} |")


if __name__ == "__main__":
    main()
