"""Pytest plugin: what each test costs in XLA compilation (issue 30, the suite from a fresh clone).

Load it with ``-p benchmarks.suite_compile_profile`` (from the repository root) and run the suite
with an empty compilation cache to see what a CI machine without a cache pays::

    JAXNC_CACHE_DIR=$(mktemp -d) SUITE_PROFILE_CSV=/tmp/profile.csv \\
        python -m pytest -q -n 2 -m "not slow" -p benchmarks.suite_compile_profile

Every test (its setup, call and teardown together, so a module-scoped fixture's programs are
charged to the first test that uses it) writes one CSV row: ``nodeid, file, wall_s, cpu_s,
child_cpu_s, compile_s, compilations, worker``. ``compile_s`` and ``compilations`` come from
:func:`jaxnc.cache.compile_clock` (lowering plus XLA compilation in this process; a program loaded
from the persistent cache counts with its load time). ``child_cpu_s`` is the CPU time of
subprocesses the test waited for (command-line and sharding tests compile there, which the
clock of this process cannot see). Each xdist worker appends its own rows to
``$SUITE_PROFILE_CSV.<worker>``; :func:`main` merges them and prints the totals per file::

    python benchmarks/suite_compile_profile.py /tmp/profile.csv [--top 40]
"""
from __future__ import annotations

import csv
import os
import resource
import sys
import time

import pytest

_FIELDS = ["nodeid", "file", "wall_s", "cpu_s", "child_cpu_s", "compile_s", "compilations", "worker"]


def _out_path():
    base = os.environ.get("SUITE_PROFILE_CSV")
    if not base:
        return None
    return f"{base}.{os.environ.get('PYTEST_XDIST_WORKER', 'main')}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    from jaxnc.cache import compile_clock
    path = _out_path()
    c0 = compile_clock()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    k0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    yield
    t1 = time.perf_counter()
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    k1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    c1 = compile_clock()
    if path is None:
        return
    d = c1 - c0
    new = not os.path.exists(path)
    with open(path, "a", newline="") as f:
        w = csv.writer(f)
        if new:
            w.writerow(_FIELDS)
        w.writerow([item.nodeid, item.nodeid.split("::")[0], f"{t1 - t0:.3f}",
                    f"{(r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime):.3f}",
                    f"{(k1.ru_utime + k1.ru_stime) - (k0.ru_utime + k0.ru_stime):.3f}",
                    f"{d.seconds:.3f}", d.compilations, os.environ.get("PYTEST_XDIST_WORKER", "main")])


def load(base: str) -> list[dict]:
    """All workers' rows of the run whose CSV base name is ``base``."""
    import glob
    rows = []
    for p in sorted(glob.glob(base + ".*")):
        with open(p) as f:
            rows.extend(csv.DictReader(f))
    return rows


def main(argv=None):
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", help="the SUITE_PROFILE_CSV base name of a run")
    ap.add_argument("--top", type=int, default=30)
    a = ap.parse_args(argv)
    rows = load(a.csv)
    num = ["wall_s", "cpu_s", "child_cpu_s", "compile_s"]
    for r in rows:
        for k in num:
            r[k] = float(r[k])
        r["compilations"] = int(r["compilations"])
    files: dict[str, dict] = {}
    for r in rows:
        f = files.setdefault(r["file"], {"tests": 0, **{k: 0.0 for k in num}, "compilations": 0})
        f["tests"] += 1
        for k in num + ["compilations"]:
            f[k] += r[k]
    tot = {k: sum(r[k] for r in rows) for k in num + ["compilations"]}
    print(f"{len(rows)} tests; wall {tot['wall_s']:.0f} s summed over workers, CPU {tot['cpu_s']:.0f} s "
          f"(+{tot['child_cpu_s']:.0f} s in subprocesses), compile {tot['compile_s']:.0f} s in "
          f"{tot['compilations']} compilations\n")
    print("| file | tests | compile s | compilations | CPU s | subprocess CPU s | wall s |")
    print("|---|---|---|---|---|---|---|")
    for name, f in sorted(files.items(), key=lambda kv: -(kv[1]["cpu_s"] + kv[1]["child_cpu_s"]))[:a.top]:
        print(f"| {name} | {f['tests']} | {f['compile_s']:.1f} | {f['compilations']} | {f['cpu_s']:.1f} | "
              f"{f['child_cpu_s']:.1f} | {f['wall_s']:.1f} |")
    print("\n| test | compile s | compilations | CPU s | subprocess CPU s |")
    print("|---|---|---|---|---|")
    for r in sorted(rows, key=lambda r: -(r["cpu_s"] + r["child_cpu_s"]))[:a.top]:
        print(f"| {r['nodeid']} | {r['compile_s']:.1f} | {r['compilations']} | {r['cpu_s']:.1f} | "
              f"{r['child_cpu_s']:.1f} |")


if __name__ == "__main__":
    sys.exit(main())
