"""Where a command line run's time goes: import, tracing, XLA compilation, the rest.

Run:  .venv/bin/python benchmarks/profile_cli.py [--top 15] -- run mecanum --seeds 256 --set case=all --out DIR --cache-dir EMPTY_DIR

Runs ``jaxnc`` with the given arguments in this process, counting every program JAX
traces, lowers and compiles (``jax.monitoring`` duration events, and the names from
``jax_log_compiles``), and prints the wall time split and the programs that took longest
to compile. Use an empty ``--cache-dir`` for a cold run (the shared default cache is
left alone). Also printed: the persistent cache's hits and misses (a miss is a real XLA
compilation; a warm run should have none), the process's CPU seconds, and when each
compilation over 0.5 s ran (seconds from the start: side by side or one after another).
"""
from __future__ import annotations

import argparse
import collections
import logging
import os
import re
import sys
import time
import traceback

from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))    # this checkout's jaxnc
t_start = time.perf_counter()
t_epoch = time.time()
import jax  # noqa: E402
import jax.monitoring  # noqa: E402

t_jax = time.perf_counter()

EVENTS = collections.defaultdict(list)
NAMES = []
SOURCES = collections.Counter()


COUNTS = collections.Counter()
SPANS = []


def _listener(event, duration, **kw):
    EVENTS[event].append(duration)


def _count(event, **kw):
    COUNTS[event] += 1


def _span(event, start, end, **kw):
    if event == "/jax/core/compile/backend_compile_duration" and end - start >= 0.5:
        SPANS.append((start - t_epoch, end - t_epoch, kw.get("fun_name", "?")))


class _Names(logging.Handler):
    def emit(self, record):
        m = re.search(r"Finished XLA compilation of (.+?) in ([0-9.e\-]+) s", record.getMessage())
        if m:
            NAMES.append((float(m.group(2)), m.group(1)))
            here = [f for f in traceback.extract_stack()[:-1]
                    if ("/jaxnc/" in f.filename or "/experiments/" in f.filename) and "profile_cli" not in f.filename]
            SOURCES[f"{here[-1].filename.split('/')[-2]}/{here[-1].filename.split('/')[-1]}:{here[-1].lineno} "
                    f"({here[-1].name})" if here else "?"] += 1


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("args", nargs=argparse.REMAINDER)
    a = ap.parse_args()
    args = a.args[1:] if a.args[:1] == ["--"] else a.args
    jax.monitoring.register_event_duration_secs_listener(_listener)
    jax.monitoring.register_event_listener(_count)
    jax.monitoring.register_event_time_span_listener(_span)
    jax.config.update("jax_log_compiles", True)
    h = _Names()
    for name in ("jax._src.interpreters.pxla", "jax._src.dispatch", "jax._src.compiler"):
        lg = logging.getLogger(name)
        lg.addHandler(h)
        lg.propagate = False
    t0 = time.perf_counter()
    import jaxnc
    from jaxnc.cli import run_cli
    t1 = time.perf_counter()
    print(f"jaxnc from {Path(jaxnc.__file__).parent}", file=sys.stderr)
    rc = run_cli(args)
    t2 = time.perf_counter()
    comp = EVENTS.get("/jax/compilation_cache/compile_time_saved_sec", [])
    back = EVENTS.get("/jax/core/compile/backend_compile_duration", [])
    trace = EVENTS.get("/jax/core/compile/jaxpr_trace_duration", [])
    lower = EVENTS.get("/jax/core/compile/jaxpr_to_mlir_module_duration", [])
    print(f"\nexit code {rc}; wall {t2 - t_start:.1f} s: import jax {t_jax - t_start:.1f} s, import jaxnc.cli "
          f"{t1 - t0:.1f} s, run {t2 - t1:.1f} s")
    cpu = os.times()
    print(f"  CPU {cpu.user + cpu.system:.1f} s (user {cpu.user:.1f}, system {cpu.system:.1f})")
    print(f"  XLA compilations {len(back)} ({sum(back):.1f} s), traces {len(trace)} ({sum(trace):.1f} s), "
          f"lowerings {len(lower)} ({sum(lower):.1f} s); persistent-cache hits {len(comp)}")
    print(f"  persistent cache: {COUNTS['/jax/compilation_cache/cache_hits']} hits, "
          f"{COUNTS['/jax/compilation_cache/cache_misses']} misses (compiled by XLA)")
    print("  compilations over 0.5 s, seconds from the start: " +
          ", ".join(f"{n} {a:.1f}-{b:.1f}" for a, b, n in sorted(SPANS)))
    print(f"  the {a.top} longest compilations:")
    for t, n in sorted(NAMES, reverse=True)[:a.top]:
        print(f"    {t:7.2f} s  {n}")
    small = [n for t, n in NAMES if t < 0.5]
    counts = collections.Counter(small)
    print(f"  {len(small)} compilations under 0.5 s; most frequent: " +
          ", ".join(f"{n} x{c}" for n, c in counts.most_common(12)))
    print("  where the compilations are requested (innermost jaxnc/experiments frame):")
    for src, c in SOURCES.most_common(a.top):
        print(f"    {c:4d}  {src}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
