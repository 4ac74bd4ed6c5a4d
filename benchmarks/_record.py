"""Appending a benchmark's tables to RESULTS.md: one heading and machine line for all scripts."""
from __future__ import annotations

import datetime
import os
import platform
import sys
from pathlib import Path

import jax


def record(results: Path, tables: list[str], note: str = "") -> None:
    """Append ``tables`` under a heading with the command, date, machine, JAX version and devices.

    ``note`` (e.g. package versions or the workload) is added to the machine line.
    """
    cmd = "python " + os.path.relpath(sys.argv[0]) + "".join(" " + a for a in sys.argv[1:])
    dev = jax.devices()
    machine = (f"Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.platform()}; "
               f"jax {jax.__version__}, backend {jax.default_backend()}, {len(dev)} x {dev[0].device_kind}, "
               f"Python {platform.python_version()}.")
    body = "\n\n".join(t for t in tables if t)
    with open(results, "a") as f:
        f.write(f"\n## {datetime.date.today()} — `{cmd}`\n\n{machine}{' ' + note if note else ''}\n\n{body}\n")
