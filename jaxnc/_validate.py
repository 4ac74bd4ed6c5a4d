"""Validation helpers run in ``__post_init__`` (plain Python, before any tracing).

Values that are JAX arrays (tracers inside jit/vmap, or batched leaves) are not
checked: validation is for configurations a person writes.
"""
from __future__ import annotations

import numpy as np


def _concrete(v):
    if isinstance(v, (bool, int, float, np.number)):
        return np.asarray(v, dtype=float)
    if isinstance(v, np.ndarray):
        return v.astype(float)
    return None


def check_range(name, v, low=None, high=None, *, low_open=False, high_open=False):
    a = _concrete(v)
    if a is None:
        return
    lo_ok = True if low is None else (np.all(a > low) if low_open else np.all(a >= low))
    hi_ok = True if high is None else (np.all(a < high) if high_open else np.all(a <= high))
    if not (lo_ok and hi_ok and np.all(np.isfinite(a))):
        lb = "(" if low_open else "["
        rb = ")" if high_open else "]"
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        got = a.tolist() if a.ndim else float(a)
        raise ValueError(f"{name} must be in {lb}{lo}, {hi}{rb}, got {got}")


def check_positive(name, v):
    check_range(name, v, 0.0, None, low_open=True)


def check_nonneg(name, v):
    check_range(name, v, 0.0, None)


def check_int(name, v, low, high=None):
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low or (high is not None and v > high):
        hi = "inf" if high is None else str(high)
        raise ValueError(f"{name} must be an integer in [{low}, {hi}], got {v!r}")
