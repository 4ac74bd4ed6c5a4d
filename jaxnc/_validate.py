"""Validation helpers run in ``__post_init__`` (plain Python, before any tracing).

Values that are JAX arrays (tracers inside jit/vmap, or batched leaves) are not
checked: validation is for configurations a person writes. :func:`concrete` also decides
:func:`jit_when_eager`'s path (a function compiled once when called on concrete values).
"""
from __future__ import annotations

import dataclasses

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


def check_range(name, v, low=None, high=None, *, low_open=False, high_open=False, finite=True):
    """Every element of ``v`` (a number or array, checked when concrete) in the interval,
    and finite (``finite=False``: +-inf allowed where the interval has no bound, NaN never);
    ValueError naming ``name`` and the interval, or for a string."""
    a = _concrete(v, name)
    if a is None:
        return
    lo_ok = True if low is None else (np.all(a > low) if low_open else np.all(a >= low))
    hi_ok = True if high is None else (np.all(a < high) if high_open else np.all(a <= high))
    fin_ok = np.all(np.isfinite(a)) if finite else not np.any(np.isnan(a))
    if not (lo_ok and hi_ok and fin_ok):
        if not finite:
            low_open, high_open = low_open and low is not None, high_open and high is not None
            lb, rb = "(" if low_open else "[", ")" if high_open else "]"
            lo, hi = ("-inf" if low is None else f"{low:g}"), ("inf" if high is None else f"{high:g}")
            got = a.tolist() if a.ndim else float(a)
            raise ValueError(f"{name} must be in {lb}{lo}, {hi}{rb} (not NaN), got {got}")
        lb = "(" if low_open or low is None else "["      # an infinite bound is excluded
        rb = ")" if high_open or high is None else "]"
        got = a.tolist() if a.ndim else float(a)
        if low is None and high is None:
            raise ValueError(f"{name} must be finite, got {got}")
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise ValueError(f"{name} must be in {lb}{lo}, {hi}{rb}, got {got}")


def check_finite(name, v):
    """Every element of ``v`` a finite number (strings refused; tracers not checked)."""
    check_range(name, v)


def check_given(name, v, what: str = "a number or an array of numbers"):
    """``v`` is not None (a field that a person must give a value)."""
    if v is None:
        raise ValueError(f"{name} must be {what}, got None")


def choice(v, choices):
    """The element of ``choices`` that ``v`` names: an exact match, else the one match
    ignoring case (the command line's rule, :meth:`jaxnc.experiment.Option.parse`); None
    when there is none or more than one."""
    for c in choices:
        if (v == str(c)) if isinstance(v, str) else (type(v) is type(c) and v == c):
            return c
    if isinstance(v, str):
        folded = [c for c in choices if str(c).lower() == v.lower()]
        if len(folded) == 1:
            return folded[0]
    return None


def check_choice(name, v, choices):
    """:func:`choice`, or ValueError naming ``name`` and the choices."""
    c = choice(v, choices)
    if c is None:
        raise ValueError(f"{name} must be one of {', '.join(str(c) for c in choices)} (any case), got {v!r}")
    return c


def psd_rounding(M) -> float:
    """How far below 0 the smallest eigenvalue of a covariance M (float[n, n]) may round and M
    still count as positive semi-definite: n float32 epsilons of its largest entry. A singular
    covariance (G Q G' of a noise narrower than the state, the textbook discrete white-noise
    acceleration Q) has eigenvalues 0 that come out of either sign at that scale."""
    a = np.asarray(M, float)
    return a.shape[0] * float(np.finfo(np.float32).eps) * float(np.abs(a).max(initial=0.0))


def check_bool(name, v):
    if not isinstance(v, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {v!r}")


def check_callable(name, v, what: str = "a function"):
    if not callable(v):
        raise ValueError(f"{name} must be {what}, got {type(v).__name__} {v!r}")


def check_instance(name, v, cls, what: str):
    """``v`` is an instance of ``cls`` (a class or tuple); ``what`` says it in words."""
    if not isinstance(v, cls):
        raise ValueError(f"{name} must be {what}, got {type(v).__name__}")


def check_positive(name, v):
    check_range(name, v, 0.0, None, low_open=True)


def check_nonneg(name, v):
    check_range(name, v, 0.0, None)


def check_int(name, v, low, high=None):
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low or (high is not None and v > high):
        hi = "inf)" if high is None else f"{high}]"
        raise ValueError(f"{name} must be an integer in [{low}, {hi}, got {v!r}")


def index_tuple(name, index, what: str = "") -> tuple:
    """A static component index, an int >= 0 or a non-empty tuple/list of distinct ones, as a
    tuple of ints. Raises ValueError naming ``name`` (``what``: the components, in words, for
    the message)."""
    idx = (index,) if isinstance(index, (int, np.integer)) and not isinstance(index, bool) else index
    if not isinstance(idx, (tuple, list)) or not idx or \
            not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) and i >= 0 for i in idx) \
            or len(set(idx)) != len(idx):
        raise ValueError(f"{name} must be an int >= 0 or a tuple of distinct ints >= 0{what and f' ({what})'}, "
                         f"got {index!r}")
    return tuple(int(i) for i in idx)


def check_components(name, index, size: int, what: str):
    """The static component indices ``index`` (a tuple of ints) pick entries of a vector of
    ``size`` (static: a traced array's shape), named ``what`` in words. Indexing with an
    array of indices out of range would not fail under jit: XLA clamps them to the last
    entry, silently reading another component.

    Raises: ValueError naming ``name``, the allowed range and ``what``."""
    bad = [i for i in index if not 0 <= i < size]
    if bad:
        raise ValueError(f"{name} must pick components in [0, {size - 1}] of {what} ({size} entries), "
                         f"got {tuple(index)}")


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


def jit_when_eager(fn=None, *, static_argnums: tuple = ()):
    """``fn`` compiled as one program (``jax.jit``, the positional arguments ``static_argnums``
    static) when every leaf of its other arguments, keywords included, is a concrete number or
    array (:func:`concrete`) and no static argument is a tracer, so that a call outside any
    transformation neither dispatches its small operations one by one nor compiles its loops
    again (an eager ``lax.scan`` or ``fori_loop`` whose body is a new closure is a new program
    at every call); called as it is otherwise: under a trace (jit, vmap, grad), so that the
    enclosing program is the same as without this wrapper, and with a leaf that ``jax.jit``
    cannot take (a plain Python object a part holds). Usable as ``@jit_when_eager`` or
    ``@jit_when_eager(static_argnums=(...))``."""
    import functools

    import jax
    if fn is None:
        return functools.partial(jit_when_eager, static_argnums=static_argnums)
    static = tuple(static_argnums)
    jitted = jax.jit(fn, static_argnums=static)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        dynamic = [a for i, a in enumerate(args) if i not in static]
        eager = concrete(*dynamic, *kwargs.values()) and not any(
            isinstance(args[i], jax.core.Tracer) for i in static if i < len(args))
        return jitted(*args, **kwargs) if eager else fn(*args, **kwargs)

    return call


def unbounded(limit) -> bool:
    """True when an output limit is None or, looked at on the host, +-inf in every entry;
    a JAX array (a traced or batched leaf) is not looked at and counts as a bound."""
    import jax
    return limit is None or (not isinstance(limit, jax.Array) and bool(np.all(np.isinf(np.asarray(limit)))))


def fields_concrete(obj) -> bool:
    """:func:`concrete` over a dataclass's fields."""
    import dataclasses
    return concrete(*(getattr(obj, f.name) for f in dataclasses.fields(obj)
                      if not f.metadata.get("static", False)))


def scalar_fields(obj, *names) -> None:
    """The named fields of a dataclass are single numbers where they are concrete (None and
    tracers are not checked): ValueError naming ``Class.field`` and the shape given."""
    for n in names:
        v = getattr(obj, n)
        if v is not None and concrete(v) and np.ndim(v) != 0:
            raise ValueError(f"{type(obj).__name__}.{n} must be a single number, got shape {np.shape(v)}")


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


def checked_pytree(cls):
    """``cls`` as a frozen dataclass registered as a pytree (fields whose metadata has
    ``static`` are auxiliary data, the others leaves) that jax rebuilds *without* calling
    ``__init__``: its ``__post_init__`` validation runs when a person builds one, never when
    jax rebuilds one from tracers, the None of a ``vmap`` ``in_axes`` prefix or its own
    placeholders. So ``__post_init__`` may refuse None and anything that is not a number;
    build an ``in_axes`` prefix (fields that are axes or None) with :func:`unchecked`."""
    import jax
    if "__dataclass_fields__" not in cls.__dict__:           # not yet a dataclass itself
        cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    data = tuple(f.name for f in fields if not f.metadata.get("static", False))
    meta = tuple(f.name for f in fields if f.metadata.get("static", False))
    keys = tuple(jax.tree_util.GetAttrKey(n) for n in data)

    def flatten_with_keys(obj):
        return tuple(zip(keys, (getattr(obj, n) for n in data))), tuple(getattr(obj, n) for n in meta)

    def flatten(obj):
        return tuple(getattr(obj, n) for n in data), tuple(getattr(obj, n) for n in meta)

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for n, v in zip(data, children):
            object.__setattr__(obj, n, v)
        for n, v in zip(meta, aux):
            object.__setattr__(obj, n, v)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
    return cls


def unchecked(cls, **fields):
    """An instance of the dataclass ``cls`` built without ``__init__`` (no validation):
    the fields given, the others their defaults. For ``vmap`` ``in_axes`` prefixes, e.g.
    ``unchecked(Bernoulli, p=0)``."""
    obj = object.__new__(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(fields) - names
    if unknown:
        raise ValueError(f"{cls.__name__} has no field(s) {', '.join(sorted(unknown))}")
    for f in dataclasses.fields(cls):
        if f.name in fields:
            v = fields[f.name]
        elif f.default is not dataclasses.MISSING:
            v = f.default
        elif f.default_factory is not dataclasses.MISSING:
            v = f.default_factory()
        else:
            v = None
        object.__setattr__(obj, f.name, v)
    return obj
