"""Validation helpers run in ``__post_init__`` (plain Python, before any tracing).

Values that are JAX arrays (tracers inside jit/vmap, or batched leaves) are not
checked: validation is for configurations a person writes.
"""
from __future__ import annotations

import numpy as np


def _concrete(v, name="value"):
    """``v`` as a float array when it is a concrete number, array or (nested) sequence of
    numbers; None when it is a JAX array or tracer, or None itself (not checked: a
    configuration used as a ``vmap`` ``in_axes`` prefix holds None and 0); ValueError for a
    string, naming ``name``."""
    if isinstance(v, (bool, int, float, np.number)):
        return np.asarray(v, dtype=float)
    if isinstance(v, np.ndarray):
        if v.dtype.kind not in "biuf":
            raise ValueError(f"{name} must be a number or an array of numbers, got an array of {v.dtype}")
        return v.astype(float)
    if isinstance(v, (list, tuple)):
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number or an array of numbers, got {v!r}") from None
        return a
    if isinstance(v, (str, bytes)):
        raise ValueError(f"{name} must be a number, got {v!r}")
    return None


def check_range(name, v, low=None, high=None, *, low_open=False, high_open=False):
    a = _concrete(v, name)
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


def concrete(*values) -> bool:
    """True when every leaf of ``values`` is a concrete number or array (not a tracer, nor a
    placeholder that jax puts in a pytree while unflattening): validation may look at them."""
    import jax
    for leaf in jax.tree_util.tree_leaves(values):
        if isinstance(leaf, jax.core.Tracer):
            return False
        if not isinstance(leaf, (bool, int, float, complex, np.ndarray, np.generic, jax.Array)):
            return False
    return True


def fields_concrete(obj) -> bool:
    """:func:`concrete` over a dataclass's fields."""
    import dataclasses
    return concrete(*(getattr(obj, f.name) for f in dataclasses.fields(obj)
                      if not f.metadata.get("static", False)))


def array_fields(obj, *names) -> None:
    """Turn the named fields of a frozen dataclass that are Python sequences (lists,
    tuples of numbers) into float32 arrays, so that they are one pytree leaf each."""
    for n in names:
        v = getattr(obj, n)
        if isinstance(v, (list, tuple)):
            try:
                a = np.asarray(v, np.float32)
            except (TypeError, ValueError):
                raise ValueError(f"{type(obj).__name__}.{n} must be a number or an array of numbers, got {v!r}") from None
            object.__setattr__(obj, n, a)
