"""Tune any :class:`jaxnc.loop.Loop` by naming its leaves.

``tune_loop(loop, {"trigger.delta": Positive()}, objective)`` tunes the named leaves of
a loop built with the runner (attribute paths from the loop: ``"trigger.delta"``,
``"controller.K"``, ``"uplink.loss.p"``) to minimise the Monte-Carlo mean of
``objective(metrics)`` (default: the run's finite cost, ``Metrics.cost_raw``), e.g.
``lambda m: m.cost_raw + 0.5 * m.rate_sc``; ``run=`` takes any per-seed function of a
configuration (a paper's scheme: ``run=mecanum.run``), and a tuple of paths ties them to
one parameter. It

1. checks everything before tracing: the paths exist and are dynamic numeric leaves (not
   a part, not None; an integer that shapes arrays is static, and an integer-valued leaf
   such as ``Petc.max_silence`` has no gradient: give either in ``search``), the
   starts lie inside their constraints, the budgets, the objective is a scalar (and, on
   the start's evaluation seeds, not NaN);
2. with ``search={"path": [values, ...]}`` first runs successive halving with common
   random numbers over those values (static integers such as a buffer length or
   horizon included, each value compiling once: :func:`jaxnc.tune.search.successive_halving`);
3. runs :func:`jaxnc.tune.tune` (Adam with a decaying step size, constraints by
   reparametrisation: log for :class:`Positive`, logit for :class:`Interval`; Polyak
   averaging) with the antithetic score function by default: unbiased for the
   Gaussian-smoothed hard objective, so it needs no per-call check (a pathwise estimator
   can be biased on hard triggers, docs/tuning_loops.md). ``estimator="auto"`` instead
   picks the estimator by :func:`jaxnc.tune.check.gradient_check` at the start (an
   estimator that agrees with central finite differences with every coordinate resolved,
   the seeds doubled up to ``check_max_seeds``; it says which and why); ``max_seconds``
   bounds the time of the whole tuning (search, check, gradient steps, compilations
   included); then the gradient's start and end run on ``pick_seeds`` common seeds and
   the better is kept (a flat, noisy objective can make the steps drift); after a search,
   the score function's steps are tested at a quarter of their number, and if they
   resolve no coordinate the rest of their budget (and the pick's) runs the search's
   finalists and the steps' end on common seeds instead (``resolve_at``);
4. evaluates the start and the tuned point with hard triggers on fresh seeds: means
   with 95 % intervals and the paired 95 % interval of the difference.

:func:`mc_mean` is the differentiable Monte-Carlo mean over seeds in chunks (bounded
memory in the forward and the backward pass: each chunk is recomputed in the backward
pass, ``jax.checkpoint``), for objectives a user writes by hand. :func:`check_loop` is the
gradient check alone, at any point, for a user to run before trusting an estimator.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import math
import time
import weakref
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxnc import montecarlo
from jaxnc.cache import compile_clock
from jaxnc._validate import check_int, check_positive, check_range
from jaxnc.tune.check import GradientCheck, gradient_check, objective_total
from jaxnc.tune.gradient import (Interval, Positive, TuneResult, Unconstrained, _rate_pair, constrain, tune,
                                 unconstrain)
from jaxnc.tune.search import halving_schedule, mean_ci, paired_ci, successive_halving
from jaxnc.tune.estimators import score_terms

__all__ = ["get_path", "set_paths", "is_static", "mc_mean", "LoopTuneResult", "tune_loop", "check_loop", "steps_resolution",
           "with_temperature", "has_temperature"]

_CONSTRAINTS = (Positive, Interval, Unconstrained)
CHECK_SEEDS, CHECK_MAX_SEEDS = 256, 32768   # check_loop's default seeds and budget (docs/tuning_loops.md, issue 31)
STEPS, BATCH, LEARNING_RATE = 200, 16, (0.3, 0.03)   # tune_loop's gradient stage (docs/tuning_loops.md, "tune-study")
RESOLVE_AT, RESOLVE_MIN_STEPS = 0.25, 8   # tune_loop's budget rule: when its steps are tested (docs/tuning_loops.md, version 9)


def _split(path: str) -> list[str]:
    if not isinstance(path, str) or not path or \
            any(not (p.isidentifier() or (p.isdigit() and p.isascii())) for p in path.split(".")):
        raise ValueError(f"a tuned parameter is named by an attribute path like 'trigger.delta' (a tuple's "
                         f"entry by its index: 'actuator.limits.0.high'), got {path!r}")
    return path.split(".")


def _fields(obj):
    if isinstance(obj, dict):
        return [k for k in obj if isinstance(k, str)]
    if isinstance(obj, (tuple, list)) and not hasattr(obj, "_fields"):
        return [str(i) for i in range(len(obj))]
    return [f.name for f in dataclasses.fields(obj)] if dataclasses.is_dataclass(obj) else []


def _child(obj, name: str):
    """The field ``name`` of a configuration object, the entry ``name`` of a dict, or the
    entry at index ``name`` of a tuple or list."""
    if isinstance(obj, dict):
        return obj[name]
    return obj[int(name)] if isinstance(obj, (tuple, list)) else getattr(obj, name)


def _replaced(obj, name: str, new):
    """``obj`` with its field, dict entry or tuple entry ``name`` replaced by ``new``."""
    if isinstance(obj, dict):
        return {**obj, name: new}
    if isinstance(obj, (tuple, list)):
        return type(obj)(new if i == int(name) else v for i, v in enumerate(obj))
    return dataclasses.replace(obj, **{name: new})


def get_path(loop, path: str):
    """The value at attribute ``path`` of ``loop``: fields of configuration objects, string
    keys of dicts inside them (``"controller.params.gains.kp"`` for a
    ``Function(params={"gains": {"kp": ...}})``) and indices of tuples
    (``"actuator.limits.1.rising"``); ValueError naming the missing part."""
    obj = loop
    parts = _split(path)
    for i, name in enumerate(parts):
        if name not in _fields(obj):
            where = ".".join(parts[:i]) or type(loop).__name__
            avail = ", ".join(_fields(obj)) or "(none: not a configuration object)"
            raise ValueError(f"{path!r}: {where} ({type(obj).__name__}) has no field {name!r}; fields: {avail}")
        obj = _child(obj, name)
    return obj


def is_static(loop, path: str) -> bool:
    """True when the field at ``path`` is static (it shapes arrays or picks code); a dict's
    entry is a leaf, never static."""
    parts = _split(path)
    parent = get_path(loop, ".".join(parts[:-1])) if len(parts) > 1 else loop
    get_path(loop, path)
    if not dataclasses.is_dataclass(parent):     # a dict's or a tuple's entry
        return False
    f = next(f for f in dataclasses.fields(parent) if f.name == parts[-1])
    return bool(f.metadata.get("static", False))


def set_paths(loop, values: dict):
    """``loop`` with the values at the given attribute paths replaced (nested
    ``dataclasses.replace``, a dict or tuple copied with the entry replaced; works on
    traced values)."""
    for path, v in values.items():
        parts = _split(path)
        get_path(loop, path)                    # names what is missing (a dict would take a new key)

        def rep(obj, ps):
            return _replaced(obj, ps[0], v if len(ps) == 1 else rep(_child(obj, ps[0]), ps[1:]))
        loop = rep(loop, parts)
    return loop


def mc_mean(fn: Callable, keys, *, chunk_size: int = 256):
    """Mean of ``fn(key)`` (a scalar) over ``keys`` [n, 2], in chunks of ``chunk_size``.

    Usable inside ``jax.grad``: the chunks run one after another (``lax.map``) and each is
    recomputed in the backward pass (``jax.checkpoint``), so memory grows with the chunk,
    not with n. The last chunk is padded by repeating its last key with weight 0."""
    check_int("chunk_size", chunk_size, 1)
    keys = jnp.asarray(keys)
    n = int(keys.shape[0])
    if n < 1:
        raise ValueError("mc_mean: keys must hold at least one key")
    c = min(chunk_size, n)
    m = -(-n // c)
    idx = np.minimum(np.arange(m * c), n - 1).reshape(m, c)
    w = (np.arange(m * c) < n).astype(np.float32).reshape(m, c)

    @jax.checkpoint
    def chunk(args):
        ks, ws = args
        return jnp.sum(jax.vmap(fn)(ks) * ws)

    return jnp.sum(jax.lax.map(chunk, (keys[idx], jnp.asarray(w)))) / n


class LoopTuneResult(NamedTuple):
    """What :func:`tune_loop` found (parameters keyed by their names: a path, or
    ``"a=b"`` for tied paths)."""

    params: dict              # name -> tuned value (numpy), natural units
    start: dict               # name -> starting value
    estimator: str            # the gradient estimator used ("none": the check passed none after a search)
    estimator_reason: str     # why (the check's verdict, or "given")
    check: GradientCheck | None
    search: Any               # the SearchResult of the search stage, or None
    tune: TuneResult | None   # optimiser history, or None (no continuous parameters)
    start_eval: tuple         # (mean, 95 % half-width) of the objective at the start, fresh seeds
    tuned_eval: tuple         # the same at the tuned point
    paired_diff: tuple        # tuned - start on the same fresh seeds: (mean, 95 % half-width)
    n_simulations: int        # every simulation, the final evaluation's included
    wall_time_s: float
    eval_values: tuple = ()   # (start, tuned): per-seed objective on the fresh seeds, float[eval_seeds] each
    compile_s: float = math.nan   # of wall_time_s, the seconds spent lowering and compiling (jaxnc.cache.compile_clock)
    n_compilations: int = 0       # XLA compilations during the call (the small eager ones included)
    stages: Any = None            # {stage: (wall s, compile s, compilations)}: evaluation, search, check, gradient, pick
    pick: tuple = ()              # (gradient's start, its end): mean objective on the pick's common seeds; () without a pick
    resolution: tuple = ()        # (steps looked at, per-coordinate |t| float[d], threshold z): the budget rule's test; () untested

    @property
    def tuning_simulations(self) -> int:
        """Simulations spent on finding the point (check, search, gradient steps), without
        the final evaluation: the budget an equal-budget search should get."""
        n_eval = len(self.eval_values[0]) if self.eval_values else 0
        return self.n_simulations - 2 * n_eval

    def __str__(self) -> str:
        return self.summary()

    __repr__ = __str__

    def summary(self) -> str:
        """A few lines: the estimator and why, each parameter's start and tuned value, the
        objective at both on the fresh seeds, the budget rule's test and the pick, times.
        ``print(result)`` prints this (the per-seed arrays stay in the fields)."""
        s, t, d = self.start_eval, self.tuned_eval, self.paired_diff
        lines = [f"estimator: {self.estimator} ({self.estimator_reason})"]
        for k in self.params:
            lines.append(f"  {k}: {np.array2string(np.asarray(self.start[k]), precision=4)} -> "
                         f"{np.array2string(np.asarray(self.params[k]), precision=4)}")
        if self.eval_values:
            lines.append(f"objective (hard triggers, fresh seeds): start {s[0]:.4g} +- {s[1]:.2g}, "
                         f"tuned {t[0]:.4g} +- {t[1]:.2g}; paired difference {d[0]:.4g} +- {d[1]:.2g}")
            v0, v1 = (np.asarray(v, np.float64) for v in self.eval_values)
            need = montecarlo.seeds_for_paired_interval(v1, v0)
            if need > v0.size:
                lines.append(f"  doubtful: the objective is skewed (rare costly runs); its normal interval needs about "
                             f"{need} seeds by Cochran's rule, the evaluation has {v0.size} (eval_seeds)")
        else:
            lines.append("objective: not evaluated (evaluate=False)")
        if self.tune is not None:
            lines.append(f"gradient steps made: {len(self.tune.history.objective)}")
        if self.resolution:
            looked, tv, z = self.resolution
            lines.append(f"budget rule: after {looked} steps, per-coordinate |t| "
                         f"{np.array2string(np.abs(np.asarray(tv, float)), precision=2)} against z = {z:.2f}")
        if self.pick:
            lines.append(f"pick: the gradient's start {self.pick[0]:.4g}, its end {self.pick[1]:.4g} "
                         f"(mean objective on the pick's common seeds)")
        lines.append(f"wall time {self.wall_time_s:.1f} s, of which {self.compile_s:.1f} s lowering and compiling "
                     f"({self.n_compilations} compilations); {self.n_simulations} simulations")
        for k, (w, c, n) in (self.stages or {}).items():
            lines.append(f"  {k}: {w:.1f} s, compiling {c:.1f} s ({n} compilations)")
        return "\n".join(lines)


def has_temperature(cfg) -> bool:
    """True when some configuration object inside ``cfg`` has a ``temperature`` field (a
    trigger whose straight-through gradient can be switched on)."""
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return False
    for f in dataclasses.fields(cfg):
        if f.metadata.get("static", False):
            continue
        if f.name == "temperature" or has_temperature(getattr(cfg, f.name)):
            return True
    return False


def with_temperature(cfg, temp):
    """``cfg`` with every (non-static) ``temperature`` field at any depth set to ``temp``:
    0 gives the hard simulation, > 0 the straight-through gradient of every trigger that
    has one (:func:`jaxnc.loop.triggers.fires_straight_through`)."""
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return cfg
    changes = {}
    for f in dataclasses.fields(cfg):
        if f.metadata.get("static", False):
            continue
        v = getattr(cfg, f.name)
        if f.name == "temperature":
            changes[f.name] = temp
        elif dataclasses.is_dataclass(v) and not isinstance(v, type):
            nv = with_temperature(v, temp)
            if nv is not v:
                changes[f.name] = nv
    return dataclasses.replace(cfg, **changes) if changes else cfg


class _Spec(NamedTuple):
    """The checked request: parameter name -> its paths and constraint."""
    paths: dict          # name -> tuple of paths set to the same value
    constraints: dict    # name -> constraint
    run: Callable
    objective: Callable  # metrics -> scalar (smooth + jump for a pair objective)
    parts: Callable | None = None   # metrics -> (smooth, jump) when the user's objective returns a pair


def _name(key) -> str:
    return key if isinstance(key, str) else "=".join(key)


def param_paths(params) -> dict:
    """``{name: paths}`` of a ``params`` argument of :func:`tune_loop` (a dict or list whose
    keys are a path or a tuple of tied paths): the name is the path, or ``"a=b"`` for tied
    paths, as in :class:`LoopTuneResult` and the check's labels."""
    return {_name(k): ((k,) if isinstance(k, str) else tuple(k)) for k in params}


# point_objective's functions, the most recent last: (id(loop), objective, run, names) -> (loop, f)
POINT_FUNCTIONS = 16
_POINT: "collections.OrderedDict" = collections.OrderedDict()


def point_objective(loop, objective: Callable, run: Callable, names: dict | None = None) -> Callable:
    """``f(point, key, temp=0.0)``: the objective of one run of ``loop`` with ``point``'s
    values set, ``objective_total(objective(run(loop', key)))`` (float32 scalar).

    ``point`` is ``{path: value}``, or ``{name: value}`` when ``names`` (``{name: paths}``,
    as :func:`param_paths` returns) is given: a tied name sets each of its paths. ``temp``
    is every trigger's temperature (:func:`with_temperature`): 0, the default, simulates
    hard triggers. The one per-seed objective of :func:`tune_loop`'s search stages and of
    the tuning studies' searches and evaluations.

    The same ``loop`` object, ``objective``, ``run`` and ``names`` give the same function
    object while it is among the last :data:`POINT_FUNCTIONS` asked for (the function
    holds ``loop``), so that the searches of repeated calls share their traces and
    compiled programs."""
    names_key = None if names is None else tuple((n, tuple(ps)) for n, ps in names.items())
    key = (id(loop), objective, run, names_key)
    hit = _POINT.get(key)
    if hit is not None and hit[0] is loop:
        _POINT.move_to_end(key)
        return hit[1]

    def f(point, key, temp=jnp.float32(0.0)):
        values = point if names is None else {p: point[n] for n in point for p in names[n]}
        return objective_total(objective(run(with_temperature(set_paths(loop, values), temp), key)))
    _POINT[key] = (loop, f)
    while len(_POINT) > POINT_FUNCTIONS:
        _POINT.popitem(last=False)
    return f


def _leaf_value(fn_name: str, loop, path: str) -> np.ndarray:
    """The numeric value at ``path``; ValueError when it names a part (a configuration
    object: name one of its fields), a field that holds None or no number, or one that
    holds an integer array or a bool (a count or a switch, e.g. ``Petc.max_silence``:
    searched, not tuned by gradient; a Python int is taken as a number)."""
    v = get_path(loop, path)
    if dataclasses.is_dataclass(v):
        raise ValueError(f"{fn_name}: {path!r} is a part ({type(v).__name__}), not a leaf: name one of its fields "
                         f"({', '.join(path + '.' + f for f in _fields(v))})")
    if v is None:
        raise ValueError(f"{fn_name}: {path!r} is None in this loop (a part or value that is not set): a tuned "
                         f"leaf must hold a number or an array")
    a = np.asarray(v)
    if a.dtype.kind not in "biuf" or a.size == 0:
        raise ValueError(f"{fn_name}: {path!r} must hold a number or a non-empty array of numbers to be tuned, "
                         f"got {type(v).__name__}")
    if isinstance(v, bool) or (a.dtype.kind != "f" and not isinstance(v, int)):
        # an integer array or a bool: the part stores a count or a switch (Petc.max_silence is
        # int32); a Python int is a number a person wrote for a continuous field (Petc(delta=1))
        raise ValueError(f"{fn_name}: {path!r} holds {a.dtype} values, a count or a switch (e.g. Petc.max_silence) "
                         f"with no gradient: the tuner would simulate fractional values the part refuses; give its "
                         f"candidate values in search={{{path!r}: [...]}}, or a float start if the leaf is continuous")
    return a


def _leaf_shaped(a: np.ndarray, shape: tuple, what: str, leaf: str) -> np.ndarray:
    """``a`` as float32 of ``shape`` (a number broadcast to it); ValueError naming ``what``
    and ``leaf`` when it does not broadcast."""
    a = a.astype(np.float32)
    try:
        return np.broadcast_to(a, shape).copy()
    except ValueError:
        raise ValueError(f"{what} has shape {a.shape}, {leaf} has shape {shape}: give a value of that shape, "
                         f"or a number") from None


def _search_value(loop, key: str, paths: tuple, v):
    """``v``, a candidate of ``search[key]``, as the search's points hold it: a static value
    as given, a dynamic one as float32 of the leaf's shape (a number is broadcast to it), so
    that one program serves every candidate. ValueError naming ``search[key]`` when ``v``
    is not numbers, has another shape, or is refused by the part that holds it (its own
    check, run on the host when the loop is built with ``v``: a range, a channel count)."""
    out = v
    if not all(is_static(loop, p) for p in paths):
        a = np.asarray(v)
        if a.dtype.kind not in "biuf":
            raise ValueError(f"tune_loop: search[{key!r}] value {v!r} must be a number or an array of numbers")
        out = _leaf_shaped(a, np.shape(get_path(loop, paths[0])),
                           f"tune_loop: search[{key!r}] value {v!r}", f"the leaf {paths[0]!r}")
    try:
        set_paths(loop, {p: out for p in paths})
    except ValueError as e:
        raise ValueError(f"tune_loop: search[{key!r}] value {v!r}: {e}") from None
    return out


def _check_in_constraint(fn_name: str, what: str, constraint, value) -> None:
    """ValueError naming ``what`` when ``value`` is outside ``constraint``'s domain (nothing
    is moved to the edge: the tuner would start somewhere the user did not ask for)."""
    try:
        constraint.inverse(value)
    except ValueError as e:
        raise ValueError(f"{fn_name}: {what} {e}") from None


def _cost_raw(m):
    """The default objective, ``m.cost_raw`` (one function: calls share its programs)."""
    return m.cost_raw


def _prepare(fn_name: str, loop, params, objective, run) -> _Spec:
    """Check ``params`` / ``objective`` / ``run`` against ``loop`` before anything is traced."""
    from jaxnc import loop as nc            # late: jaxnc.loop imports nothing from tune
    if isinstance(params, (list, tuple)):
        params = {p: Unconstrained() for p in params}
    if not isinstance(params, dict):
        raise ValueError(f"{fn_name}: params must be a dict {{path: constraint}} or a list of paths, "
                         f"got {type(params).__name__}")
    paths, constraints = {}, {}
    for key, c in params.items():
        group = (key,) if isinstance(key, str) else tuple(key)
        if not group:
            raise ValueError(f"{fn_name}: an empty tuple of tied paths")
        name = _name(group)
        values = []
        for path in group:
            values.append(_leaf_value(fn_name, loop, path))
            if is_static(loop, path):
                raise ValueError(f"{fn_name}: {path!r} is static (it shapes arrays or selects code) and has no "
                                 f"gradient; give its candidate values in search={{{path!r}: [...]}}")
        if any(v.shape != values[0].shape or not np.array_equal(v, values[0]) for v in values[1:]):
            raise ValueError(f"{fn_name}: the tied paths {name!r} must start with equal values, got "
                             + ", ".join(f"{p}={np.array2string(v, precision=4)}" for p, v in zip(group, values)))
        if not isinstance(c, _CONSTRAINTS):
            raise ValueError(f"{fn_name}: the constraint of {name!r} must be Positive, Interval or Unconstrained, "
                             f"got {type(c).__name__}")
        paths[name], constraints[name] = group, c
    if objective is None and run is None and isinstance(loop, nc.Loop) and loop.cost is None:
        raise ValueError(f"{fn_name}: the loop has no cost (Loop.cost is None), so the default objective "
                         f"m.cost_raw is NaN on every run: give the Loop a cost= or an objective(metrics)")
    run = nc.run if run is None else run
    if not callable(run):
        raise ValueError(f"{fn_name}: run must be a function run(loop, key) -> metrics, got {type(run).__name__}")
    objective = objective or _cost_raw
    if not callable(objective):
        raise ValueError(f"{fn_name}: objective must be a function objective(metrics) -> scalar, "
                         f"got {type(objective).__name__}")
    try:
        # one function per loop object, objective and run: a second call does not trace the loop again
        of_key = _per_loop(loop, ("shape", objective, run), lambda ref: lambda k: objective(run(ref(), k)))
        shape = jax.eval_shape(of_key, jax.random.PRNGKey(0))
    except AttributeError as e:
        raise ValueError(f"{fn_name}: the objective does not fit what run(loop, key) returns: {e}") from None
    if isinstance(shape, (tuple, list)):
        if len(shape) != 2 or any(getattr(o, "shape", None) != () for o in shape):
            raise ValueError(f"{fn_name}: the objective must return a scalar, or a pair (smooth, jump) of "
                             f"scalars, per seed, got {shape}")
        return _Spec(paths, constraints, run, lambda m: objective_total(objective(m)), objective)
    if not hasattr(shape, "shape") or shape.shape != ():
        raise ValueError(f"{fn_name}: the objective must return a scalar per seed, got "
                         f"{getattr(shape, 'shape', type(shape).__name__)}")
    return _Spec(paths, constraints, run, objective)


def _set(loop, spec: _Spec, values: dict):
    """``loop`` with each named value written at all of its paths."""
    return _write(loop, spec.paths, values)


def _write(loop, paths: dict, values: dict):
    """``loop`` with each named value written at all of its paths (``paths``: name -> paths)."""
    return set_paths(loop, {p: values[n] for n in values for p in paths[n]})


def _theta_writer(paths: dict, cons: dict, shapes: dict) -> Callable:
    """``write(loop, theta)``: ``loop`` with the parameters of the flat raw ``theta``
    (``shapes``: each parameter's shape, in sorted-name order) constrained and written at
    their paths."""
    unravel = ravel_pytree({n: np.zeros(shapes[n], np.float32) for n in shapes})[1]
    return lambda loop, theta: _write(loop, paths, constrain(unravel(theta), cons))


def _flat(loop, spec: _Spec, at: dict | None = None):
    """(flat raw start, unravel, flat_objective(theta, key, temperature)) in the
    unconstrained coordinates (log for Positive, logit for Interval); the flat objective
    returns what the user's does (a scalar, or a (smooth, jump) pair). It is one function
    for every point and call on this ``loop`` object with the same objective, run,
    parameters and shapes (:func:`_flat_program`), so checks at several points share
    their compiled program."""
    init = {n: np.asarray(get_path(loop, spec.paths[n][0]), np.float32) for n in spec.paths}
    if at:
        unknown = [k for k in at if k not in spec.paths]
        if unknown:
            raise ValueError(f"the point names {unknown}, which are not among the parameters {list(spec.paths)}")
        for k, v in at.items():
            init[k] = _leaf_shaped(np.asarray(v), init[k].shape, f"check_loop: at[{k!r}]", f"the parameter {k!r}")
        try:                                            # the parts' own checks, on the host
            _set(loop, spec, init)
        except ValueError as e:
            raise ValueError(f"check_loop: at: {e}") from None
    raw0 = unconstrain(init, spec.constraints)
    flat0, unravel = ravel_pytree(raw0)
    return np.asarray(flat0), unravel, _flat_program(loop, spec, {n: v.shape for n, v in init.items()})


# functions shared by the calls of check_loop / tune_loop on one loop object: id(loop) ->
# (weak reference to the loop, {key: function}); an entry leaves with its loop. The loop is
# closed over, not an argument: its values stay constants of the program, so the numbers are
# those of a closure built per call (an argument would compute the configuration's own
# arithmetic in float32 and move the last bits)
_BY_LOOP: dict = {}


def _per_loop(loop, key: tuple, build: Callable) -> Callable:
    """``build(loop_ref)``'s function for ``loop`` (reached through ``loop_ref()``) and
    ``key``, built once and kept while ``loop`` lives (:data:`_BY_LOOP`), so that
    :func:`jaxnc.montecarlo.run_batched` and ``jax.jit`` / ``jax.eval_shape`` reuse its
    traces and compilations."""
    try:
        ref = weakref.ref(loop)
    except TypeError:                 # not weak-referenceable: a function for this call alone
        return build(lambda: loop)
    store = _BY_LOOP.get(id(loop))
    if store is None or store[0]() is not loop:
        store = _BY_LOOP[id(loop)] = (ref, {})
        weakref.finalize(loop, _BY_LOOP.pop, id(loop), None)
    if key not in store[1]:
        store[1][key] = build(ref)
    return store[1][key]


def _shared(loop, spec: _Spec, what: str, extra: tuple, build: Callable) -> Callable:
    """:func:`_per_loop` keyed by ``what``, ``spec``'s user objective and run, its
    parameters and constraints, and ``extra``."""
    return _per_loop(loop, (what, spec.parts or spec.objective, spec.run, tuple(spec.paths.items()),
                            _constraints_key(spec.constraints), extra), build)


def _constraints_key(cons: dict) -> tuple:
    """The constraints as a key of the program caches: each constraint itself where it can be
    hashed, else its type and its fields' values by their bytes (bounds given as JAX arrays)."""
    def key(c):
        try:
            hash(c)
            return c
        except TypeError:
            fields = (getattr(c, f.name) for f in dataclasses.fields(c))
            return (type(c), tuple((np.asarray(v).dtype.str, np.shape(v), np.asarray(v).tobytes()) for v in fields))
    return tuple((n, key(c)) for n, c in cons.items())


def _flat_program(loop, spec: _Spec, shapes: dict) -> Callable:
    """``f(theta, key, temperature)``: the user's objective (a scalar or a (smooth, jump)
    pair) of one run of ``loop`` with the tuned parameters set from the flat raw ``theta``
    (``shapes``: each parameter's shape); one function per loop object, objective, run,
    parameters and shapes (:func:`_shared`)."""
    paths, cons, run = spec.paths, spec.constraints, spec.run
    objective = spec.parts or spec.objective

    def build(loop_ref):
        write = _theta_writer(paths, cons, shapes)

        def f(theta, key, temp):
            return objective(run(with_temperature(write(loop_ref(), theta), temp), key))
        return f
    return _shared(loop, spec, "flat", tuple(sorted((n, tuple(v)) for n, v in shapes.items())), build)


# _hard_program's jitted function per user objective and run (weakly: it must not keep its
# own keys alive), then per parameters and constraints
_HARD: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _hard_batched(spec: _Spec) -> Callable:
    """``jit(vmap(one))(keys, scales, lp)`` of :func:`_hard_program`, one per user objective,
    run, parameters and constraints, kept while the objective and run live."""
    paths, cons = spec.paths, spec.constraints
    obj = spec.parts or spec.objective
    key = (tuple(paths.items()), _constraints_key(cons))
    try:
        cache = _HARD.setdefault(obj, weakref.WeakKeyDictionary()).setdefault(spec.run, {})
        obj_ref, run_ref = weakref.ref(obj), weakref.ref(spec.run)
    except TypeError:                 # not weak-referenceable: a program for this call alone
        cache, obj_ref, run_ref = {}, (lambda: obj), (lambda: spec.run)
    if key in cache:
        return cache[key]

    def one(key, scale, lp):
        vals = {n: jnp.asarray(get_path(lp, g[0]), jnp.float32) for n, g in paths.items()}
        flat, unravel = ravel_pytree({n: cons[n].raw(v) for n, v in vals.items()})
        e = jax.random.normal(jax.random.fold_in(key, 7919), flat.shape, jnp.float32)
        moved = constrain(unravel(flat + scale * e), cons)
        point = {n: jnp.where(scale == 0, vals[n], moved[n]) for n in vals}
        lp = with_temperature(_write(lp, paths, point), jnp.float32(0.0))
        return objective_total(obj_ref()(run_ref()(lp, key))), e

    cache[key] = jax.jit(jax.vmap(one, in_axes=(0, 0, None)))
    return cache[key]


def _hard_program(spec: _Spec, chunk: int) -> Callable:
    """``hard(lp, keys [n, 2], scales float[n]) -> (values float[n], e float[n, d])``: the
    objective of one run per key with hard triggers, the tuned parameters of ``lp`` moved
    to raw + scale e (raw: their unconstrained coordinates, flattened in sorted-name order;
    e ~ N(0, I) drawn from the key; scale 0: ``lp``'s own values, untouched).

    One compiled program (``lp`` is an argument) runs, in chunks of ``chunk`` keys (the
    last padded), both the evaluation (scales 0) and the score function's antithetic pairs
    (the same key at +s and -s, as :func:`jaxnc.tune.estimators.score_grad`): a loop of the
    same structure and dtypes reuses it, and so does every call with the same objective
    and run (the same function objects), parameters and constraints (:data:`_HARD`)."""
    batched = _hard_batched(spec)

    def hard(lp, keys, scales):
        keys, scales = np.asarray(keys), np.asarray(scales, np.float32)
        n = keys.shape[0]
        idx = np.minimum(np.arange(-(-n // chunk) * chunk), n - 1)
        outs = [batched(keys[idx[i:i + chunk]], scales[idx[i:i + chunk]], lp) for i in range(0, idx.size, chunk)]
        return tuple(np.concatenate([np.asarray(o[j]) for o in outs])[:n] for j in range(2))
    return hard


def _as_f32(loop, spec: _Spec, values: dict | None = None):
    """``loop`` with every tuned leaf (``values``, default its own) as a float32 array, so
    that loops before and after tuning share one compiled program."""
    values = values or {n: get_path(loop, g[0]) for n, g in spec.paths.items()}
    return _set(loop, spec, {n: np.asarray(v, np.float32) for n, v in values.items()})


def _score_step(hard: Callable, loop, spec: _Spec, n_pairs: int, scale: float, record: list | None = None) -> Callable:
    """``host_grad(raw, keys, temp) -> (value, grads)`` for :func:`jaxnc.tune.tune`: the
    antithetic score function (``score_grad``'s estimate, g = mean_i (J(+) - J(-)) e_i / 2s)
    on the step's first ``n_pairs`` keys, run by ``hard``; each step's flat g (float[d],
    sorted-name order) is appended to ``record`` when given."""
    def host_grad(raw, keys, temp):
        lp = _as_f32(loop, spec, constrain(raw, spec.constraints))
        pk = np.asarray(keys)[:n_pairs]
        v, e = hard(lp, np.concatenate([pk, pk]), np.r_[np.full(n_pairs, scale), np.full(n_pairs, -scale)])
        g = np.mean(score_terms(v[:n_pairs], v[n_pairs:], e[:n_pairs], scale), axis=0)
        if record is not None:
            record.append(g)
        return float(np.mean(v)), ravel_pytree(raw)[1](jnp.asarray(g, jnp.float32))
    return host_grad


@contextlib.contextmanager
def _stage(stages: dict, name: str):
    """Adds the block's wall time and compile clock to ``stages[name]``."""
    t, c = time.perf_counter(), compile_clock()
    try:
        yield
    finally:
        dc = compile_clock() - c
        w0, c0, n0 = stages.get(name, (0.0, 0.0, 0))
        stages[name] = (w0 + time.perf_counter() - t, c0 + dc.seconds, n0 + dc.compilations)


def _corrected(loop, spec: _Spec):
    """``corrected(theta, key) -> (value, grad)`` in the flat raw coordinates
    (:func:`jaxnc.tune.jump.corrected_grad` on the hard loop), or None when ``loop`` does not
    support it (:func:`jaxnc.tune.jump.corrected_supported`); one function per loop object,
    objective, run, parameters and shapes (:func:`_shared`)."""
    from jaxnc.tune.jump import corrected_grad, corrected_supported
    if corrected_supported(loop):
        return None
    paths, cons, run, objective = spec.paths, spec.constraints, spec.run, spec.objective
    shapes = {n: tuple(np.shape(get_path(loop, g[0]))) for n, g in paths.items()}

    def build(loop_ref):
        write = _theta_writer(paths, cons, shapes)

        def corrected(t, key):
            def loop_of(u):
                return with_temperature(write(loop_ref(), u), jnp.float32(0.0))
            cost = lambda lp, k: objective(run(lp, k))
            return corrected_grad(loop_of, cost, t, key)
        return corrected
    return _shared(loop, spec, "corrected", tuple(sorted(shapes.items())), build)


def _check(spec: _Spec, flat0, unravel, fobj, *, seeds: int, max_seeds: int, seed: int, loop,
           corrected: bool = False, **kw) -> GradientCheck:
    """:func:`gradient_check` of the flat objective (:func:`_flat` on ``loop``) on seeds
    ``seed_keys(seed, seeds)``
    (doubling up to ``max_seeds``), labelled, with each coordinate's value and slope
    d value / d theta so that its table is in the user's units; with the corrected
    estimator where asked (``corrected``) and ``loop`` supports it."""
    def values(theta):
        return ravel_pytree(constrain(unravel(theta), spec.constraints))[0]
    th = jnp.asarray(flat0)
    vals, slope = jax.jvp(values, (th,), (jnp.ones_like(th),))   # constraints act elementwise: the diagonal
    return gradient_check(fobj, flat0, montecarlo.seed_keys(seed, seeds), names=_labels(unravel, flat0.size),
                          max_seeds=max_seeds, more_keys=lambda start, count: montecarlo.seed_keys(seed, count, start),
                          values=np.asarray(vals), dvalue_dtheta=np.asarray(slope),
                          corrected=_corrected(loop, spec) if corrected else None, **kw)


def _labels(unravel, size: int) -> tuple:
    """The label of each coordinate of a flat vector, in the vector's order: ``name`` for a
    scalar parameter, ``name[i]`` (flat index) for an array. Read from ``unravel`` itself,
    so the labels follow the flattening order (sorted names), not the order of ``params``."""
    index = unravel(np.arange(size, dtype=np.float32))
    labels = [""] * size
    for name, pos in index.items():
        pos = np.asarray(pos).ravel().astype(int)
        for i, j in enumerate(pos):
            labels[j] = name if pos.size == 1 else f"{name}[{i}]"
    return tuple(labels)


def steps_resolution(grads) -> tuple[np.ndarray, float]:
    """The budget rule's test on the gradient steps made so far: ``grads`` float[n, d], one
    independent gradient estimate per step (fresh seeds each). Returns the per-coordinate
    |t| = |mean| / (sd / sqrt(n)) and the threshold z = Phi^-1(1 - 0.025 / d), the
    family-wise 95 % level over the d coordinates (the gradient check's, Bonferroni). On a
    flat objective every step's estimate has mean zero, so all |t| < z with probability at
    least 0.95; a coordinate the steps agree on (a slope they descend) has |t| growing like
    sqrt(n). A coordinate whose estimates are all equal has |t| = inf when they are not 0,
    0 when they are."""
    g = np.asarray(grads, np.float64)
    if g.ndim != 2 or g.shape[0] < 2:
        raise ValueError(f"steps_resolution: needs float[n >= 2, d] gradients, got shape {g.shape}")
    d = g.shape[1]
    g = g[np.all(np.isfinite(g), axis=1)]      # a step with a non-finite estimate moved nothing (tune zeroes it)
    n = g.shape[0]
    if n < 2:
        return np.zeros(d), _z_family(d)
    mean, se = g.mean(axis=0), g.std(axis=0, ddof=1) / math.sqrt(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(se > 0, np.abs(mean) / se, np.where(mean != 0, np.inf, 0.0))
    return t, _z_family(d)


def _z_family(d: int) -> float:
    from scipy.stats import norm
    return float(norm.ppf(1.0 - 0.025 / d))


def _refine(res, per_seed: Callable, budget: int, seed: int, static: tuple, finalists: int = 4,
            chunk_size: int | None = None, extra: dict | None = None, new_only: bool = False):
    """``res`` (a SearchResult) with ``budget`` more simulations spent on its best
    ``finalists`` candidates, and on ``extra`` (a point that is not among them, appended to
    the candidates) when given: the same new seeds for all (common random numbers). The
    best is then the lowest mean over all the seeds a candidate ran, or with ``new_only``
    over the new seeds alone (the finalists were chosen on the old ones, whose means are
    biased low by that choice; an ``extra`` point has only new ones): the refined rows'
    ``mean`` and ``ci95`` are then those of the new seeds."""
    from jaxnc.tune.search import SearchResult, search as run_search
    order = [int(i) for i in np.argsort(np.where(np.isfinite(res.mean), res.mean, np.inf), kind="stable")]
    top = order[:min(finalists, len(order))]
    points = list(res.points) + ([extra] if extra is not None else [])
    rows = top + ([len(res.points)] if extra is not None else [])
    n_new = budget // len(rows)
    if n_new < 1:
        return res
    new = run_search(per_seed, [points[i] for i in rows], montecarlo.seed_keys(seed, n_new), static=static,
                     chunk_size=chunk_size, progress=False)
    values = np.full((len(points), res.values.shape[1] + n_new), np.nan)
    values[:len(res.points), :res.values.shape[1]] = res.values
    values[rows, -n_new:] = new.values
    stats = np.asarray([mean_ci(row[~np.isnan(row)]) for row in values])
    if new_only:
        stats[rows] = [mean_ci(values[i, -n_new:]) for i in rows]
    mean = np.where(np.isfinite(stats[:, 0]), stats[:, 0], np.inf)
    best = min(rows, key=lambda i: mean[i])
    return SearchResult(points, values, mean, stats[:, 1], best, points[best], float(mean[best]),
                        float(stats[best, 1]), res.n_simulations + len(rows) * n_new,
                        res.wall_time_s + new.wall_time_s)


def check_loop(loop, params: dict | list | tuple, objective: Callable | None = None, *, at: dict | None = None,
               run: Callable | None = None, seeds: int | None = None, seed: int = 0, fd_step: float = 0.2,
               temperature: float = 1e-3, score_scale: float | None = None, chunk_size: int = 256,
               max_seeds: int | None = None, progress: bool = False, corrected: bool = False) -> GradientCheck:
    """The gradient check of :func:`jaxnc.tune.check.gradient_check` on ``loop``: at the
    loop's values of ``params`` (or at ``at``, ``{name: value}`` in natural units), the
    straight-through and score-function estimates of d E[objective] / d theta (and, with
    ``corrected=True`` on a :class:`jaxnc.loop.Loop` whose sensor trigger is a hard PETC
    with additive measurement noise, the corrected pathwise gradient of
    :mod:`jaxnc.tune.jump`; off by default: a larger program to compile, and on the loops
    of docs/tuning_loops.md noisier per run than the score function except on a servo)
    beside central finite differences on the same ``seeds`` seeds (base ``seed``).

    theta is the *unconstrained* coordinate the tuner moves (log of a ``Positive``
    parameter, logit of an ``Interval``), so ``fd_step`` and ``score_scale`` are relative
    steps. ``params``, ``objective`` and ``run`` as in :func:`tune_loop`. The seeds run in
    compiled batches of ``chunk_size`` (bounded memory, so thousands of seeds are fine),
    with a progress bar if ``progress``. Every coordinate must be resolved for an
    estimator to be recommended; the check doubles its seeds from ``seeds`` until it is
    conclusive or reaches ``max_seeds``. By default (``seeds=None``) it starts at 256 and
    doubles up to ``max_seeds`` = 32768; an explicit ``seeds`` runs that many, doubled
    only up to a ``max_seeds`` given with it.

    The defaults are those the loops of docs/tuning_loops.md need to be conclusive: 256
    seeds doubled up to 32768 (HDD was conclusive at 256, the cart-pole at 512-1024, DRHE
    at 16384 and 32768; on a slow loop ``progress=True`` shows the seeds, and a smaller
    ``max_seeds`` bounds the wait); ``fd_step`` 0.2 (on objectives with rare failures a
    central difference's variance grows like 1/h, and 0.05 left DRHE inconclusive at 512
    seeds); ``score_scale`` default ``fd_step / sqrt(3)``, the
    Gaussian with the variance of the central difference's uniform kernel on [-h, h], so
    that the score function and the finite differences estimate the gradient of the same
    smoothed objective to second order. Their common smoothing bias is measured and, where
    resolved, removed by the extrapolated estimators (``"richardson"``,
    :mod:`jaxnc.tune.check`).

    Compiled programs: one per loop object, objective and run (the same function objects),
    parameters and settings: another point (``at``) or a second call on the same loop
    traces and compiles nothing; the numbers are those of a check compiled for that point.

    Returns:
      :class:`jaxnc.tune.check.GradientCheck`: ``names`` the coordinates' labels (in the
      gradient vector's order: parameters sorted by name), ``values`` and
      ``dvalue_dtheta`` each coordinate's value and slope, so that ``table()`` and
      ``in_units()`` give d E[objective] / d parameter in the parameter's own units.

    Raises:
      ValueError: as :func:`tune_loop`, fewer than 2 seeds, max_seeds below seeds,
        non-positive steps, an ``at`` value of another shape than its parameter (a number
        is broadcast to it), outside its constraint or refused by the part that holds it.
    """
    spec = _prepare("check_loop", loop, params, objective, run)
    if not spec.paths:
        raise ValueError("check_loop: name at least one parameter")
    if seeds is None:
        seeds, max_seeds = CHECK_SEEDS, CHECK_MAX_SEEDS if max_seeds is None else max_seeds
    check_int("seeds", seeds, 2)
    check_int("seed", seed, 0, 2**32 - 1)
    max_seeds = seeds if max_seeds is None else max_seeds
    check_int("max_seeds", max_seeds, seeds)
    check_positive("fd_step", fd_step)
    score_scale = fd_step / np.sqrt(3.0) if score_scale is None else score_scale
    flat0, unravel, fobj = _flat(loop, spec, at)
    return _check(spec, flat0, unravel, fobj, seeds=seeds, max_seeds=max_seeds,
                  seed=seed, loop=loop, corrected=corrected, fd_step=fd_step, temperature=temperature,
                  score_scale=score_scale, chunk_size=chunk_size, progress=progress)


def tune_loop(loop, params: dict | list | tuple = (), objective: Callable | None = None, *,
              run: Callable | None = None, search: dict | None = None, search_budget: int | None = None,
              steps: int = STEPS, batch: int = BATCH, estimator: str = "score", temperature: tuple = (1e-2, 1e-3),
              learning_rate: float | tuple = LEARNING_RATE, score_scale: float | None = None, fd_step: float = 0.2,
              seed: int = 0, check_seeds: int = CHECK_SEEDS, check_max_seeds: int | None = None,
              max_seconds: float | None = None, pick_seeds: int = 256, eval_seeds: int = 256,
              eval_seed: int = 100_000, evaluate: bool = True, progress: bool = True,
              check_corrected: bool = False, resolve_at: float = RESOLVE_AT) -> LoopTuneResult:
    """Tune the leaves of ``loop`` named in ``params`` (module docstring).

    Args:
      loop: a :class:`jaxnc.loop.Loop` (e.g. :func:`jaxnc.schemes.mecanum.mecanum_loop`'s with
        ``run=mecanum.run``), or any configuration dataclass ``run`` accepts.
      params: ``{path: constraint}`` (``Positive()``, ``Interval(lo, hi)``,
        ``Unconstrained()``) or a list of paths (unconstrained). A key may be a tuple of
        paths, *tied*: one parameter written at all of them (they must start equal), e.g.
        ``{("delta_s", "sigma_s"): Positive()}``; it is reported as ``"delta_s=sigma_s"``.
      objective: ``objective(metrics) -> scalar`` per seed; default ``m.cost_raw``. It may
        return a pair ``(smooth, jump)`` whose sum is the objective (``jump``: what
        failures are charged, a constant with no pathwise gradient): this adds the
        ``"hybrid"`` estimator (straight-through for the sum plus the score function of
        ``jump``) to the check and the tuner.
      run: ``run(loop, key) -> metrics`` for one seed; default :func:`jaxnc.loop.run`.
      search: ``{path: [values]}`` searched first by successive halving (static integer
        fields allowed); ``search_budget`` simulations (default None: 16 per candidate;
        at least one per candidate and round of successive halving). A key
        that names a parameter of ``params`` (its path, or ``"a=b"`` for a tied group)
        makes the search pick the gradient's *start* among the values (the two-stage
        tuner for objectives dominated by rare failures, docs/tuning_loops.md).
      steps, batch: gradient steps (the most, with ``max_seconds``) and seeds per step,
        >= 1 each (>= 2 for the score function: batch // 2 antithetic pairs). Default 200
        steps of 16 seeds: small batches, many steps (on CPU a batch below 16 costs as much
        as 16: the runs are vectorised 16 at a time; docs/tuning_loops.md, "tune-study").
      estimator: ``"score"`` (default: the antithetic score function, unbiased for the
        objective smoothed by N(0, score_scale^2) in the raw coordinates, whatever the
        triggers; no check is run), ``"auto"`` (the gradient check decides: opt-in, it
        compiles and runs a check program of the whole loop), ``"straight_through"``,
        ``"richardson"`` (the score extrapolated over its scale, :mod:`jaxnc.tune.check`),
        ``"hybrid"`` (a pair objective), ``"corrected"`` (a Loop whose sensor trigger is a
        hard PETC with additive measurement noise: :mod:`jaxnc.tune.jump`)
        or ``"none"`` (no gradient stage: needs ``search``). Without a gradient stage
        (``"none"``, or no estimator passing the check after a search) its budget,
        ``steps * batch`` simulations, goes to the search's four best candidates.
      temperature: (start, end) of the annealed temperature of every trigger with a
        ``temperature`` field (:func:`with_temperature`; pathwise estimator only).
      learning_rate: Adam's step size on the raw (unconstrained) parameters: a number
        (constant) or ``(start, end)``, decayed geometrically over the budget (the
        fraction of ``steps`` or of ``max_seconds`` spent, whichever is larger). The
        default (0.3, 0.03) lets a parameter cross decades: a raw step of 0.3 is a
        factor e^0.3 of a ``Positive`` value.
      score_scale, fd_step: the score function's perturbation scale (check and steps) and
        the check's finite-difference step, in the raw coordinates; default
        ``fd_step`` = 0.2 and ``score_scale`` = fd_step / sqrt(3), as :func:`check_loop`.
      check_seeds, eval_seeds: seeds of the gradient check (default 256, as
        :func:`check_loop`) and of the final evaluation; ``eval_seed``: base seed of the
        evaluation (fresh: different from ``seed``).
      max_seconds: a wall-time budget (s) for the tuning: the search, the check and the
        gradient steps, their compilations included, from the call's start (the
        evaluation is not counted); the search starts no round and the gradient stage no
        step once it would be spent (each makes at least one), so ``steps`` is then the
        most steps. A check (``"auto"``) cannot be cut short: give it a smaller
        ``check_max_seeds`` under a tight budget. None: no time limit.
      pick_seeds: after the gradient stage, its start (the search's winner, or the given
        start) and its end run on ``pick_seeds`` common seeds (hard triggers, seeds of their
        own), and the one with the lower mean is the tuned point: on a flat, noisy objective
        the steps can drift to a worse point, and the pick keeps the start then
        (``LoopTuneResult.pick`` has both means, ``estimator_reason`` says which was kept).
        0 turns it off (the end is kept). Its ``2 * pick_seeds`` simulations count in the
        budget and in ``n_simulations``, not in ``max_seconds``. Default 256.
      resolve_at: the budget rule of the score function's steps after a search (the
        default path; no check is run): once ``max(8, ceil(resolve_at * steps))`` steps
        are made (fewer than ``steps``), their per-step gradient estimates are tested
        (:func:`steps_resolution`: each coordinate's |mean| / standard error against the
        family-wise 95 % threshold). If no coordinate is resolved, the objective is flat to
        within what the steps resolve (or the steps reached a minimum before the test):
        the steps stop, and the simulations of the steps not made plus the pick's
        ``2 * pick_seeds`` run the search's four best candidates and the steps' end on new
        common seeds; the lowest mean on those seeds alone (the finalists' search means are
        biased low by their selection) is the tuned point (``LoopTuneResult.search`` holds
        the end as its last candidate; the budget is the same). ``LoopTuneResult.resolution`` holds the
        test, ``estimator_reason`` says what happened. In [0, 1]; 0 turns the rule off.
        Default 0.25 (docs/tuning_loops.md, study versions 9 and 11).
      evaluate: run the start's and the tuned point's evaluation (default); False skips
        both (a caller that evaluates the point itself saves their time): ``start_eval``,
        ``tuned_eval`` and ``paired_diff`` are then NaN, ``eval_values`` empty, and an
        objective that is NaN at the start is not refused before the budget is spent.
      check_max_seeds: the check's budget: while it recommends nothing because some
        coordinate is unresolved, its seeds double up to this many (>= check_seeds;
        default 32768 or check_seeds if larger, as :func:`check_loop`; ``check_seeds``
        turns the increase off).
        A check still inconclusive there says which coordinate and how many seeds it
        would need (``LoopTuneResult.estimator_reason``).
      check_corrected: the check also tests the corrected estimator (``check_loop``'s
        ``corrected``), so that ``"auto"`` may pick it where it is consistent, resolved
        and the least noisy.

    Returns:
      :class:`LoopTuneResult`, with its own overheads: ``compile_s`` and
      ``n_compilations`` (:func:`jaxnc.cache.compile_clock` over the call) and ``stages``,
      the wall time, compile time and compilations of each stage (``evaluation``,
      ``search``, ``check``, ``gradient``).

    Compiled programs: the evaluation and the score function's steps share one (the hard
    objective with the point as an argument, :func:`_hard_program`: the start and the
    tuned point, and every step, reuse it); the check compiles one (its chunks and seed
    doublings reuse it); a pathwise estimator's step compiles one (reused by every step:
    the temperature and the point are arguments); the search one per distinct static
    value (its rounds share a chunk size). None of these grows with ``steps``. A second
    call with the same objective and run (the same function objects) reuses the hard
    program, and on the same loop object the search's programs and the check's too
    (:func:`check_loop`).

    Raises:
      ValueError: a path that does not exist, names a part (a configuration object) or a
        field that is None, a static leaf in ``params``, tied paths that start unequal, a
        start (or a searched start) outside its constraint (0 under ``Positive()``, a
        value outside its ``Interval``: nothing is moved to the edge), a search value that
        is not numbers, has another shape than its leaf (a number is broadcast to it) or is
        refused by the part that holds it (checked on the host, naming ``search[key]``), a
        budget below one step, ``search_budget`` below one seed per candidate and round or
        without a search, a non-scalar objective, the default objective on a Loop without a cost,
        an objective that is NaN at the start on some evaluation seed (checked on the
        evaluation's fresh seeds before the budget is spent), an unknown estimator or
        constraint, a learning rate that is not > 0 or a pair of them, a ``max_seconds``,
        ``fd_step`` or ``score_scale`` that is not > 0.
    """
    t0, clock0 = time.perf_counter(), compile_clock()
    stages = {}
    spec = _prepare("tune_loop", loop, params, objective, run)
    search = dict(search or {})
    if not spec.paths and not search:
        raise ValueError("tune_loop: name at least one parameter to tune (params or search)")
    for name, group in spec.paths.items():
        if name not in search:            # (a searched parameter starts at the search's winner)
            _check_in_constraint("tune_loop", f"the start of {name!r}", spec.constraints[name],
                                np.asarray(get_path(loop, group[0])))
    tuned_paths = {p: n for n, g in spec.paths.items() for p in g}
    search_paths = {}                   # search key -> the paths it sets
    for key, vals in search.items():
        if key in spec.paths:           # a tuned parameter (or tied group) by name: the search picks its start
            search_paths[key] = spec.paths[key]
        else:
            get_path(loop, key)
            if key in tuned_paths:
                raise ValueError(f"tune_loop: {key!r} is tuned as part of {tuned_paths[key]!r}: search that name")
            search_paths[key] = (key,)
        if not isinstance(vals, (list, tuple, np.ndarray)) or len(vals) == 0:
            raise ValueError(f"tune_loop: search[{key!r}] must be a non-empty list of values")
        if key in spec.paths:            # a start candidate: inside the parameter's constraint
            for v in vals:
                _check_in_constraint("tune_loop", f"search[{key!r}] value {v!r}: the start of {key!r}",
                                    spec.constraints[key], v)
        search[key] = [_search_value(loop, key, search_paths[key], v) for v in vals]
    if search_budget is not None:
        if not search:
            raise ValueError("tune_loop: search_budget is given without a search")
        check_int("search_budget", search_budget, 1)
    if search:      # refused here, before the start's evaluation is compiled and run
        n_points = math.prod(len(v) for v in search.values())
        rounds = max(1, math.ceil(math.log2(n_points)))
        budget = 16 * n_points if search_budget is None else search_budget
        if budget < rounds * n_points:
            raise ValueError(f"tune_loop: search_budget must be at least {rounds * n_points} (one seed per "
                             f"candidate and round: {n_points} candidates, {rounds} rounds), got {budget}")
    check_int("steps", steps, 1)
    check_int("batch", batch, 2 if estimator == "score" else 1)
    check_int("check_seeds", check_seeds, 2)
    check_max_seeds = max(CHECK_MAX_SEEDS, check_seeds) if check_max_seeds is None else check_max_seeds
    check_int("check_max_seeds", check_max_seeds, check_seeds)
    check_int("eval_seeds", eval_seeds, 2)
    check_int("pick_seeds", pick_seeds, 0)
    check_range("resolve_at", resolve_at, 0.0, 1.0)
    check_int("seed", seed, 0, 2**32 - 3)
    check_int("eval_seed", eval_seed, 0, 2**32 - 1)
    _rate_pair(learning_rate)
    check_positive("fd_step", fd_step)
    score_scale = fd_step / math.sqrt(3.0) if score_scale is None else score_scale
    check_positive("score_scale", score_scale)
    if max_seconds is not None:
        check_positive("max_seconds", max_seconds)
    if estimator not in ("auto", "straight_through", "score", "richardson", "hybrid", "corrected", "none"):
        raise ValueError(f"tune_loop: estimator must be auto, straight_through, score, richardson, hybrid, corrected "
                         f"or none, got {estimator!r}")
    if estimator == "corrected":
        from jaxnc.tune.jump import corrected_supported
        why = corrected_supported(loop)
        if why:
            raise ValueError(f"tune_loop: estimator='corrected' cannot run on this loop: {why}")
    if estimator == "hybrid" and spec.parts is None:
        raise ValueError("tune_loop: estimator='hybrid' needs an objective that returns (smooth, jump)")
    if estimator == "none" and not search:
        raise ValueError("tune_loop: estimator='none' (no gradient stage) needs a search")
    if (not isinstance(temperature, (tuple, list)) or len(temperature) != 2):
        raise ValueError(f"tune_loop: temperature must be a (start, end) pair, got {temperature!r}")
    for t in temperature:
        check_positive("temperature", t)
    run, objective = spec.run, spec.objective

    def left():
        """Seconds of ``max_seconds`` left (None: no budget): the call's time so far without
        its evaluation; at least a millisecond, so that a stage still makes its first step."""
        if max_seconds is None:
            return None
        spent = time.perf_counter() - t0 - stages.get("evaluation", (0.0,))[0]
        return max(max_seconds - spent, 1e-3)

    per_seed = point_objective(loop, spec.parts or objective, run)

    # the start's evaluation first (fresh seeds, so its values are those it would have at the
    # end): an objective that is NaN at the start is refused before the budget is spent
    ekeys = montecarlo.seed_keys(eval_seed, eval_seeds)
    hard = _hard_program(spec, max(batch, montecarlo.LANES))
    if evaluate:
        with _stage(stages, "evaluation"):
            v0 = hard(_as_f32(loop, spec), ekeys, np.zeros(eval_seeds))[0]
        if np.any(np.isnan(v0)):
            raise ValueError(f"tune_loop: the objective is NaN at the start on {int(np.sum(np.isnan(v0)))} of "
                             f"{eval_seeds} evaluation seeds (a loop without a cost gives m.cost_raw = NaN): there "
                             f"is nothing to tune; give the loop a cost or an objective that is a number on every run")
    sims = 0
    result_search = None
    loop1 = loop
    if search:
        static = tuple(p for ps in search_paths.values() for p in ps if is_static(loop, p))
        names = list(search)
        combos = np.array(np.meshgrid(*[np.arange(len(search[n])) for n in names], indexing="ij")).reshape(
            len(names), -1).T.tolist()
        # a point sets every path of each searched key (dynamic values as float32 of the leaf's shape,
        # _search_value: one program serves all)
        points = [{p: search[n][i] for n, i in zip(names, combo) for p in search_paths[n]} for combo in combos]
        schedule = halving_schedule(len(points), budget)     # budget: set and checked with the arguments
        keys = montecarlo.seed_keys(seed + 1, sum(s for _, s in schedule))
        search_seed = per_seed      # one function: the search and its refinement (and every call) share programs
        search_chunk = schedule[0][1]
        with _stage(stages, "search"):
            result_search = successive_halving(search_seed, points, keys, budget=budget, static=static,
                                               chunk_size=search_chunk, progress=progress, desc="search",
                                               max_seconds=left())
        sims += result_search.n_simulations
        sims_search = result_search.n_simulations
        loop1 = set_paths(loop, result_search.best_point)
    start = {n: np.asarray(get_path(loop, g[0])) for n, g in spec.paths.items()}
    start.update({k: np.asarray(get_path(loop, ps[0])) for k, ps in search_paths.items() if k not in spec.paths})

    reason = {"none": "asked for no gradient stage",
              "score": "the score function: unbiased for the hard objective smoothed by N(0, score_scale^2) in the "
                       "raw coordinates, so no check is needed"}.get(estimator, "given")
    chk, used, tres, pick, resolution = None, estimator, None, (), ()
    tuned = {n: np.asarray(get_path(loop1, g[0])) for n, g in spec.paths.items()}
    if spec.paths:
        init = {n: np.asarray(get_path(loop1, g[0]), np.float32) for n, g in spec.paths.items()}
        flat0, unravel, flat_objective = _flat(loop1, spec)
        if estimator == "auto":
            with _stage(stages, "check"):
                chk = _check(spec, flat0, unravel, flat_objective, seeds=check_seeds, max_seeds=check_max_seeds,
                             seed=seed + 2, loop=loop1, corrected=check_corrected,
                             temperature=float(temperature[0]), score_scale=score_scale, fd_step=fd_step,
                             progress=progress)
            sims += chk.seeds * chk.runs_per_seed
            if chk.recommended is None and result_search is not None:
                used, reason = "none", (f"no estimator passed the gradient check at the search's winner on "
                                        f"{chk.seeds} seeds ("
                                        + "; ".join(f"{k}: {v}" for k, v in chk.reason.items() if v)
                                        + "): the gradient stage is skipped")
            elif chk.recommended is None:
                used, reason = "score", (f"no estimator passed the gradient check at the start point on {chk.seeds} "
                                         "seeds (" + "; ".join(f"{k}: {v}" for k, v in chk.reason.items() if v)
                                         + "); the score function is unbiased for the smoothed objective")
            else:
                used = chk.recommended
                others = ", ".join(f"{k}: {v}" for k, v in chk.reason.items() if v)
                reason = "recommended by the gradient check" + (f" ({others})" if others else "")
            if progress and used != "none":
                print(f"tune_loop: estimator {used} ({reason})")
        if progress and used == "none":
            print(f"tune_loop: {reason}")
    if used == "none" and result_search is not None:
        # the gradient stage's budget goes to the search's finalists: new common seeds for
        # the best few, ranked by their mean over every seed each has run
        with _stage(stages, "search"):
            result_search = _refine(result_search, search_seed, steps * batch, seed + 3, static, chunk_size=search_chunk)
        sims += result_search.n_simulations - sims_search
        loop1 = set_paths(loop, result_search.best_point)
        tuned = {n: np.asarray(get_path(loop1, g[0])) for n, g in spec.paths.items()}
        reason += "; its budget refined the search's finalists"
    elif spec.paths and used != "none":
        loss_of = spec.parts if used == "hybrid" else objective
        corr = _corrected(loop1, spec) if used == "corrected" else None
        # the score function's steps run in the evaluation's program (the hard objective)
        grads = []
        host = _score_step(hard, loop1, spec, batch // 2, score_scale, grads) if used == "score" else None
        # the budget rule (score steps after a search): at the test's step, no coordinate resolved -> stop
        n_test = max(RESOLVE_MIN_STEPS, math.ceil(resolve_at * steps))
        rule = used == "score" and result_search is not None and resolve_at > 0 and n_test < steps
        resolution = ()

        def stop():
            nonlocal resolution
            if not rule or len(grads) != n_test or resolution:
                return False
            t, z = steps_resolution(grads)
            resolution = (n_test, t, z)
            return not bool(np.any(t >= z))
        with _stage(stages, "gradient"):
            tres = tune(lambda p, k, temp: loss_of(run(with_temperature(_set(loop1, spec, p), temp), k)), init,
                        spec.constraints, steps=steps, batch=batch, learning_rate=learning_rate,
                        estimator=used, temperature=temperature, seed=seed, score_scale=score_scale,
                        progress=progress, desc="tune_loop", corrected=corr, host_grad=host, max_seconds=left(),
                        stop=stop if rule else None)
        sims += tres.n_simulations
        tuned, kept = tres.params, tuned          # kept: the gradient's start, loop1's values
        made = len(tres.history.objective)
        if resolution and not np.any(resolution[1] >= resolution[2]):
            # nothing resolved: the steps' end is noise; the steps not made and the pick's seeds refine the
            # search's finalists instead (the same total), and the tuned point is the refined search's winner
            # (the steps' end is one of the finalists: a bowl descended before the test has no slope left)
            extra = (steps - made) * batch + 2 * pick_seeds
            n_before, n_points = result_search.n_simulations, len(result_search.points)
            end = {**result_search.best_point,
                   **{p: np.asarray(v, np.float32) for n, v in tres.params.items() for p in spec.paths[n]}}
            with _stage(stages, "search"):
                result_search = _refine(result_search, search_seed, extra, seed + 3, static, chunk_size=search_chunk,
                                        extra=end, new_only=True)
            sims += result_search.n_simulations - n_before
            won = "the steps' end" if result_search.best == n_points else "a searched candidate"
            loop1 = set_paths(loop, result_search.best_point)
            tuned = {n: np.asarray(get_path(loop1, g[0])) for n, g in spec.paths.items()}
            t_txt = ", ".join(f"{lab} {v:.2g}" for lab, v in zip(_labels(unravel, flat0.size), resolution[1]))
            reason += (f"; after {made} of {steps} steps no coordinate was resolved (|t| {t_txt} < {resolution[2]:.2f}):"
                       f" the steps stopped, and their remaining budget and the pick's "
                       f"({result_search.n_simulations - n_before} simulations) ran the search's finalists and the "
                       f"steps' end on common new seeds: {won} won")
        elif pick_seeds:    # the end against the start, on common seeds of their own (not the evaluation's)
            with _stage(stages, "pick"):
                pkeys = montecarlo.seed_keys(seed + 4, pick_seeds)
                va, vb = (hard(_as_f32(loop1, spec, pt), pkeys, np.zeros(pick_seeds))[0] for pt in (init, tuned))
            sims += 2 * pick_seeds
            pick = (float(np.mean(va)), float(np.mean(vb)))
            d = paired_ci(vb, va)
            if not pick[1] <= pick[0]:          # a NaN end keeps the start
                tuned = kept
                reason += (f"; the gradient's end was worse than its start on {pick_seeds} common seeds "
                           f"({pick[1]:.4g} against {pick[0]:.4g}, paired {d[0]:.3g} +- {d[1]:.2g}): the start is kept")
            else:
                reason += (f"; the gradient's end beat its start on {pick_seeds} common seeds "
                           f"({pick[1]:.4g} against {pick[0]:.4g}, paired {d[0]:.3g} +- {d[1]:.2g})")
    final_loop = _set(loop1, spec, tuned)
    best = result_search.best_point if result_search else {}
    final = {**{k: best[ps[0]] for k, ps in search_paths.items() if k not in spec.paths}, **tuned}

    nan2 = (math.nan, math.nan)
    evals = (nan2, nan2, nan2, ())
    if evaluate:
        with _stage(stages, "evaluation"):
            v1 = hard(_as_f32(final_loop, spec), ekeys, np.zeros(eval_seeds))[0]
        sims += 2 * eval_seeds
        evals = (mean_ci(v0), mean_ci(v1), paired_ci(v1, v0), (v0, v1))
    clock = compile_clock() - clock0
    return LoopTuneResult(final, start, used, reason, chk, result_search, tres, *evals[:3], sims,
                          time.perf_counter() - t0, evals[3], clock.seconds, clock.compilations, stages, pick,
                          resolution)
