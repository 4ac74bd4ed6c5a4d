"""Arithmetic of a JAX function counted on its jaxpr, loops multiplied by their trip counts.

XLA's ``cost_analysis()`` counts a while loop's body once, whatever its trip count (a
scan of 11 steps of ``c * 1.5 + 1`` over 1000 lanes reports 2 000 flops, not 22 000), so
a closed loop's scans (slow periods, fast periods inside, filter windows) are not counted
per step. This walks the jaxpr instead: ``scan`` bodies count ``length`` times, ``cond``
its costliest branch, ``while`` its body ``while_trips`` times (the caller says; the
loops here have none in their steps), calls (``pjit``, ``custom_jvp/vjp``) their
bodies. Per primitive:

* flops: ``dot_general`` 2 x output size x contracted size; elementwise arithmetic,
  comparisons and selects one per output element; reductions one per input element;
  transcendental functions one each, also counted apart (``transcendentals``);
  data movement (broadcast, reshape, slice, gather, concatenate, convert, ...) none;
* bytes: every primitive's operands read and results written once, i.e. the traffic
  of the program *unfused* (XLA's fusion keeps most of it in registers: an upper bound).

The random draws' hash (``threefry2x32``) counts 20 rounds of 4 integer operations per
output word pair.
"""
from __future__ import annotations

import math
from collections import Counter

import jax
import jax.extend  # noqa: F401  (jax.extend.core.Jaxpr, ClosedJaxpr)
import numpy as np

_MOVE = {"broadcast_in_dim", "reshape", "squeeze", "expand_dims", "slice", "dynamic_slice", "dynamic_update_slice",
         "gather", "scatter", "scatter-add", "scatter_add", "concatenate", "transpose", "convert_element_type",
         "iota", "copy", "copy_p", "pad", "rev", "select_and_gather_add", "bitcast_convert_type", "squeeze",
         "stop_gradient", "device_put", "split", "stack", "random_wrap", "random_unwrap", "random_seed", "random_fold_in",
         "random_bits", "sharding_constraint", "optimization_barrier", "pvary", "empty"}
_TRANSC = {"exp", "exp2", "log", "log1p", "expm1", "sin", "cos", "tan", "tanh", "logistic", "atan2", "asin", "acos",
           "atan", "sinh", "cosh", "asinh", "acosh", "atanh", "sqrt", "rsqrt", "cbrt", "pow", "erf", "erfc",
           "erf_inv", "lgamma", "digamma"}
_REDUCE = {"reduce_sum", "reduce_max", "reduce_min", "reduce_prod", "reduce_and", "reduce_or", "argmin", "argmax",
           "reduce_precision", "cumsum", "cummax", "cummin", "cumprod", "cumlogsumexp"}


def _size(aval) -> int:
    return int(np.prod(getattr(aval, "shape", ()), dtype=np.int64))


def _nbytes(aval) -> int:
    dt = getattr(aval, "dtype", None)
    try:
        item = np.dtype(dt).itemsize
    except TypeError:          # key arrays and other extended dtypes
        item = 8
    return _size(aval) * item


def _sub(params):
    """The sub-jaxprs of an equation's parameters (closed or open), in order."""
    out = []
    for v in params.values():
        for x in (v if isinstance(v, (tuple, list)) else (v,)):
            if isinstance(x, jax.extend.core.ClosedJaxpr):
                out.append(x.jaxpr)
            elif isinstance(x, jax.extend.core.Jaxpr):
                out.append(x)
    return out


def count(jaxpr, while_trips: int = 1) -> Counter:
    """Counter(flops, transcendentals, bytes, eqns) of one evaluation of ``jaxpr`` (a Jaxpr)."""
    c = Counter()
    for e in jaxpr.eqns:
        name = e.primitive.name
        if name == "scan":
            c.update({k: v * e.params["length"] for k, v in count(e.params["jaxpr"].jaxpr, while_trips).items()})
            continue
        if name == "while":
            body = count(e.params["body_jaxpr"].jaxpr, while_trips) + count(e.params["cond_jaxpr"].jaxpr, while_trips)
            c.update({k: v * while_trips for k, v in body.items()})
            continue
        if name == "cond":
            branches = [count(b.jaxpr, while_trips) for b in e.params["branches"]]
            c.update(max(branches, key=lambda b: b["flops"]))
            continue
        subs = _sub(e.params)
        if subs:                                   # pjit, closed_call, custom_jvp_call, custom_vjp_call, remat
            for s in subs[:1]:                     # custom_jvp/vjp carry their rules as further jaxprs
                c.update(count(s, while_trips))
            continue
        outs = sum(_size(v.aval) for v in e.outvars)
        ins = sum(_size(v.aval) for v in e.invars if hasattr(v, "aval"))
        c["eqns"] += 1
        c["bytes"] += sum(_nbytes(v.aval) for v in e.invars if hasattr(v, "aval")) + \
            sum(_nbytes(v.aval) for v in e.outvars)
        if name == "dot_general":
            (lc, _), _ = e.params["dimension_numbers"]
            shape = e.invars[0].aval.shape
            c["flops"] += 2 * outs * int(np.prod([shape[d] for d in lc], dtype=np.int64))
        elif name == "threefry2x32":
            c["flops"] += 20 * 4 * outs // 2
        elif name in _REDUCE:
            c["flops"] += ins
        elif name in _TRANSC:
            c["flops"] += outs
            c["transcendentals"] += outs
        elif name not in _MOVE:
            c["flops"] += outs
    return c


def jaxpr_cost(fn, *args, while_trips: int = 1) -> Counter:
    """:func:`count` of ``fn(*args)``'s jaxpr."""
    return count(jax.make_jaxpr(fn)(*args).jaxpr, while_trips)


def _selftest():
    x = np.ones((1000,), np.float32)
    f = lambda x: jax.lax.scan(lambda c, _: (c * 1.5 + 1.0, None), x, None, length=11)[0]
    assert jaxpr_cost(f, x)["flops"] == 22_000, jaxpr_cost(f, x)
    A = np.ones((3, 4, 5), np.float32)
    g = lambda A: jax.numpy.einsum("bij,bjk->bik", A, A.transpose(0, 2, 1))
    assert jaxpr_cost(g, A)["flops"] == 2 * 3 * 4 * 4 * 5
    assert math.isclose(jaxpr_cost(lambda x: jax.numpy.sum(x), x)["flops"], 1000)


if __name__ == "__main__":
    _selftest()
    print("ok")
