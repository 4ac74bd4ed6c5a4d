"""Which compiled operations a loop's time goes to: jax.profiler's per-thunk trace of XLA:CPU.

Run:  PYTHONPATH=. .venv/bin/python benchmarks/profile_ops.py [--loop drhe10|drhe1|cartpole|balmodel|balemu] [--seeds 1000] [--top 25]

Compiles ``jit(vmap(run))`` of the loop over ``--seeds`` keys (configuration as an argument,
as the experiments run it), runs it once to warm up, then once under ``jax.profiler.trace``
with XLA:CPU's per-thunk TraceMe annotations on (``--xla_cpu_enable_xprof_traceme``). The
trace's events are summed by HLO instruction name (self time: an event's duration less its
children's on the same thread), each mapped to the HLO text's ``op_name`` metadata (the JAX
source it came from) and to its instruction kind. Prints the top instructions and totals by
kind (fusion, while, custom call, copy, ...), and the number of thunk executions per seed-step.
"""
from __future__ import annotations

import argparse
import collections
import os
import re
import sys
import tempfile
import time
from pathlib import Path

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_xprof_traceme=true").strip()

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxnc import montecarlo  # noqa: E402


def loops():
    """name -> (per-seed function (key, loop), loop, steps)."""
    from experiments.mecanum import run_seed
    from jaxnc.montecarlo import uniform_dtypes
    from jaxnc.schemes import mecanum as mec
    out = {}
    for N in (10, 1):
        lp = uniform_dtypes(mec.mecanum_loop("DRHE", N, 0.5))
        out[f"drhe{N}"] = (run_seed, lp, lp.steps)
    try:
        from examples.cartpole import cartpole
        from jaxnc import loop as nc
        cp = cartpole()
        out["cartpole"] = (lambda k, lp: nc.run(lp, k).cost, cp, cp.steps)
    except ImportError:      # an older checkout without the example
        pass
    from jaxnc.schemes import balancing as bal
    for design, name in (("model", "balmodel"), ("emulation", "balemu")):     # 2.5 s of the 25 s scenario
        bl = bal.balancing_loop(design, horizon_s=2.5)
        out[name] = (lambda k, lp: bal.run(lp, k), bl, bl.steps)
    return out


def _frames(text: str) -> dict:
    """stack_frame_id -> list of "file:line function" from the innermost frame outwards."""
    sec, files, funcs, locs, frames = None, {}, {}, {}, {}
    for line in text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            sec = line
            continue
        m = re.match(r"^(\d+) (.*)$", line)
        if not m or sec is None:
            if not line.strip():
                sec = None
            continue
        i, rest = int(m.group(1)), m.group(2)
        if sec == "FileNames":
            files[i] = Path(rest.strip('"')).name
        elif sec == "FunctionNames":
            funcs[i] = rest.strip('"').split(".<locals>.")[-1]
        elif sec == "FileLocations":
            d = dict(re.findall(r"(\w+)=(\d+)", rest))
            locs[i] = f"{files.get(int(d['file_name_id']), '?')}:{d['line']} {funcs.get(int(d['function_name_id']), '?')}"
        else:
            d = dict(re.findall(r"(\w+)=(\d+)", rest))
            frames[i] = (int(d["file_location_id"]), int(d.get("parent_frame_id", 0)))
    out = {}
    for i in frames:
        chain, j, seen = [], i, set()
        while j in frames and j not in seen:
            seen.add(j)
            loc, parent = frames[j]
            chain.append(locs.get(loc, "?"))
            j = parent
        out[i] = chain
    return out


def where(chain: list) -> str:
    """The innermost frame, and the runner's line it was called from."""
    if not chain:
        return ""
    role = next((c for c in chain if c.startswith("runner.py")), "")
    return chain[0] + (f" < {role}" if role and role != chain[0] else "")


def hlo_index(text: str) -> dict:
    """instruction name -> (opcode / fusion kind, source: innermost frame < runner line) from compiled HLO text."""
    frames = _frames(text)
    idx = {}
    pat = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(?:\(.*?\)|\S+)\s+([\w\-]+)\(")
    for line in text.splitlines():
        m = pat.match(line)
        if not m:
            continue
        name, op = m.group(1), m.group(2)
        kind = re.search(r"kind=(k\w+)", line)
        cc = re.search(r'custom_call_target="([^"]+)"', line)
        sf = re.search(r"stack_frame_id=(\d+)", line)
        label = op + (f":{kind.group(1)}" if kind else "") + (f":{cc.group(1)}" if cc else "")
        if "__ynn_fusion" in line:
            label += ":ynn"
        idx[name] = (label, where(frames.get(int(sf.group(1)), [])) if sf else "")
    return idx


def self_times(profile) -> tuple[collections.Counter, collections.Counter]:
    """(self duration ns, count) per event name over every host thread's line."""
    dur, cnt = collections.Counter(), collections.Counter()
    for plane in profile.planes:
        if not plane.name.startswith("/host"):
            continue
        for line in plane.lines:
            evs = sorted(((e.start_ns, e.duration_ns, e.name) for e in line.events), key=lambda e: (e[0], -e[1]))
            stack = []        # [end, name, child time]
            for s, d, n in evs:
                while stack and stack[-1][0] <= s:
                    end, nm, ch = stack.pop()
                    dur[nm] -= ch
                stack_parent = stack[-1] if stack else None
                if stack_parent is not None:
                    stack_parent[2] += d
                dur[n] += d
                cnt[n] += 1
                stack.append([s + d, n, 0])
            while stack:
                end, nm, ch = stack.pop()
                dur[nm] -= ch
    return dur, cnt


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loop", default="drhe10")
    ap.add_argument("--seeds", type=int, default=1000)
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args()
    fn, lp, steps = loops()[a.loop]
    keys = montecarlo.seed_keys(0, a.seeds)
    prog = jax.jit(jax.vmap(fn, in_axes=(0, None)))
    comp = prog.lower(keys, lp).compile()
    idx = hlo_index(comp.as_text())
    jax.block_until_ready(comp(keys, lp))
    t0 = time.perf_counter()
    jax.block_until_ready(comp(keys, lp))
    plain = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        with jax.profiler.trace(d):
            jax.block_until_ready(comp(keys, lp))
        traced = time.perf_counter() - t0
        f = next(Path(d).rglob("*.xplane.pb"))
        prof = jax.profiler.ProfileData.from_serialized_xspace(f.read_bytes())
    dur, cnt = self_times(prof)
    n = a.seeds * steps
    known = {k: v for k, v in dur.items() if k in idx}
    total = sum(known.values())
    print(f"{a.loop}: {a.seeds} seeds x {steps} steps; run {plain:.3f} s plain, {traced:.3f} s traced; "
          f"{sum(cnt[k] for k in known) / steps:.1f} thunk executions per step (of {len(idx)} instructions); "
          f"self time in HLO thunks {total / 1e9:.3f} s")
    by_kind = collections.Counter()
    for k, v in known.items():
        by_kind[idx[k][0].split(":")[0] + (":" + idx[k][0].split(":")[1] if idx[k][0].startswith(("fusion", "custom")) else "")] += v
    print("\nby kind:")
    for k, v in by_kind.most_common():
        print(f"  {k:40s} {v / 1e9:8.3f} s  {100 * v / total:5.1f} %")
    print(f"\ntop {a.top} instructions (self time; count per step; op_name):")
    for k, v in sorted(known.items(), key=lambda kv: -kv[1])[:a.top]:
        print(f"  {v / 1e9:7.3f} s {100 * v / total:5.1f} %  x{cnt[k] / steps:6.2f}  {k:28s} {idx[k][0]:28s} {idx[k][1]}")
    by_src = collections.Counter()
    for k, v in known.items():
        by_src[idx[k][1]] += v
    print(f"\nby source line (innermost frame < the runner's line):")
    for k, v in by_src.most_common(a.top):
        print(f"  {v / 1e9:7.3f} s {100 * v / total:5.1f} %  {k}")
    by_file = collections.Counter()
    for k, v in known.items():
        by_file[idx[k][1].split(":")[0] or "(no source)"] += v
    print("\nby source file (innermost frame):")
    for k, v in by_file.most_common():
        print(f"  {v / 1e9:7.3f} s {100 * v / total:5.1f} %  {k}")
    other = {k: v for k, v in dur.items() if k not in idx}
    print("\nother events:", ", ".join(f"{k[:50]} {v / 1e9:.3f} s" for k, v in collections.Counter(other).most_common(6)))


if __name__ == "__main__":
    main()
