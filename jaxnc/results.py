"""Results as labelled arrays: a run's per-seed metrics as an ``xarray.Dataset``.

Every experiment writes ``results.json`` (summaries and the full configuration,
:func:`jaxnc.montecarlo.save_results`); the per-seed metrics behind the summaries are
kept too, so that a seed-level histogram or a plot over N and DP is one line:

* a single run (``mecanum``, ``hdd``, ``balancing``, ``diffdrive``) writes
  ``seeds.npz`` beside ``results.json`` (:func:`save_per_seed`): every metric of every
  seed of every case;
* a grid (``mecanum-grid``) keeps one ``.npz`` per cell under ``cells/`` (written as
  each cell is done) and lists the cells of its configuration, with their coordinates,
  in ``results.json`` (``results["per_seed"]``).

:func:`load` reads either into one Dataset with named dimensions -- ``case`` (or
``severity`` and ``design`` for ``balancing``; ``path``, ``N``, ``case``, ``dp`` for a
grid) and ``seed`` last -- and the run's metadata as attributes (``experiment``,
``settings``, ``seeds``, ``config``, versions, ``created``, ``wall_time_s``). Every
Dataset has a boolean ``unstable`` variable: the runs the experiment's summaries leave
out. :func:`summary` / :func:`to_pandas` reduce it over seeds exactly as the printed
tables do (:func:`jaxnc.montecarlo.summarize`: mean, 95 % interval over the stable runs,
unstable fraction); the same are methods of the ``.jaxnc`` accessor
(``jaxnc.load(folder).jaxnc.to_pandas()``).

A results folder belongs to one experiment: ``run.json`` (:func:`claim`, written by
``jaxnc run`` before anything is simulated) names the experiment, settings and seeds of
the run that last wrote there. :func:`load` refuses a folder whose files come from two
experiments or two runs (``run.json``, ``results.json`` and ``seeds.npz`` naming
different experiments, a grid's cells beside a single run's ``seeds.npz``, a seed count
that does not match the per-seed files, ``results.json`` and ``seeds.npz`` of two runs that
:func:`claim` gave different ids: a run stopped between writing the two).

Writing needs only numpy; reading needs xarray (and pandas), imported when first used.
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
import zipfile
from typing import Mapping, Sequence

import numpy as np

__all__ = ["PER_SEED_FILE", "RUN_FILE", "FORMAT", "FolderError", "config_of", "save_per_seed", "per_seed_index", "claim",
           "folder_owner", "run_id", "load", "summary", "to_pandas"]

PER_SEED_FILE = "seeds.npz"
#: the record of the experiment, settings and seeds that a folder's results come from
RUN_FILE = "run.json"
#: format tag stored in every per-seed file (and checked when reading one)
FORMAT = "jaxnc-per-seed-1"
RUN_FORMAT = "jaxnc-run-1"
_META = "__meta__"
_CELL_DIRS = ("cells", "points")


class FolderError(ValueError):
    """A results folder that holds the results of another experiment, or of other
    settings where they would be overwritten (:func:`claim`)."""


def config_of(obj, special=None, _where: str = "config"):
    """A JSON value that describes ``obj`` whole: what a results file's ``config`` or a sweep
    cell's configuration (:func:`jaxnc.sweep.cell_path`, :func:`jaxnc.sweep.load_cell`) holds so
    that a change anywhere in a loop makes another configuration (a stored cell of the old
    loop is then not reused).

    A dataclass (a :class:`jaxnc.loop.Loop` and every part in it) becomes ``{"type": its class
    name, field: ...}`` over all its fields, static ones included, and, for a class of the
    user's own (defined outside jaxnc, whose code :func:`jaxnc.sweep.code_fingerprint` covers),
    ``"class"``: its module and the code of its methods (:func:`_class_config`), so an edited
    ``dynamics`` or another module's class of the same name is another configuration; a
    mapping a dict with string keys; a tuple or list a list; a number, numpy or jax array (concrete) a number or nested
    lists of numbers; a string, bool or None itself; a callable (a plant's ``f``, a cost
    function) its module and qualified name, and for a Python function also a hash of its
    code (:func:`_code_hash`: an edited body, another lambda of the same module) and the
    values it closes over, its defaults and the module-level numbers, strings and arrays it
    reads (a changed constant); a ``functools.partial`` its function, arguments and keywords;
    a bound method its object and function. ``special(obj)``, when given, is tried
    first on every object and returns a description, or None to fall through (e.g. a path by
    its name instead of its points).

    Raises TypeError naming where in ``obj`` a value is that none of these describe."""
    if special is not None:
        made = special(obj)
        if made is not None:
            return made
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {"type": type(obj).__qualname__}
        for f in dataclasses.fields(obj):
            out[f.name] = config_of(getattr(obj, f.name), special, f"{_where}.{f.name}")
        own = _class_config(type(obj), special, _where)
        if own is not None:
            out["class"] = own
        return out
    if isinstance(obj, Mapping):
        return {str(k): config_of(v, special, f"{_where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (tuple, list)):
        return [config_of(v, special, f"{_where}[{i}]") for i, v in enumerate(obj)]
    if callable(obj) and not hasattr(obj, "__array__"):
        return _function_config(obj, special, _where)
    try:
        a = np.asarray(obj)
    except Exception:                       # noqa: BLE001 - a tracer or another object: named below
        a = None
    if a is None or a.dtype.kind not in "biuf":
        raise TypeError(f"config_of: {_where} of type {type(obj).__name__} is not a number, array, string, "
                        f"dataclass, mapping, sequence or function")
    return a.tolist()


def _code_hash(code) -> str:
    """A hex digest of a code object's bytecode, constants (nested code objects by their own
    digest) and names: equal for the same source compiled twice, different after an edit."""
    import hashlib
    import types
    h = hashlib.sha256()
    h.update(code.co_code)
    for c in code.co_consts:
        h.update((_code_hash(c) if isinstance(c, types.CodeType) else repr(c)).encode())
    h.update(repr((code.co_names, code.co_varnames, code.co_freevars)).encode())
    return h.hexdigest()[:16]


def _global_names(code) -> set:
    """Every global name a code object (and the code nested in it) reads."""
    import types
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= _global_names(c)
    return names


def _class_config(cls, special, where, seen=frozenset()):
    """The code of a user's class: ``{"module", "members": {"Class.name": ...}}`` over the
    classes of its MRO defined outside jaxnc and the standard library, with the functions
    each defines (methods, ``__call__``, static and class methods, properties' accessors: as
    :func:`_function_config`) and its plain class-level data (``state_dim = 2``); dataclass
    fields (described as fields), generated methods and other dunder data are left out. None
    for a class of jaxnc or the standard library."""
    import inspect
    import sys
    import types
    lib = lambda c: (c.__module__ or "").split(".")[0] in ("jaxnc", "builtins", *sys.stdlib_module_names)
    if lib(cls):
        return None
    members = {}
    for c in cls.__mro__:
        if lib(c):
            continue
        fields = set(getattr(c, "__dataclass_fields__", {}))
        for name, v in sorted(vars(c).items()):
            if name in fields or name.startswith("_abc"):
                continue
            if isinstance(v, (staticmethod, classmethod)):
                v = v.__func__
            fns = [v.fget, v.fset, v.fdel] if isinstance(v, property) else [v]
            if any(isinstance(f, types.FunctionType) for f in fns):
                fns = [f for f in fns if isinstance(f, types.FunctionType)   # not a method dataclasses made
                       and inspect.unwrap(f).__code__.co_filename != "<string>"]
                if fns:
                    members[f"{c.__qualname__}.{name}"] = [_function_config(f, special, f"{where}.{name}", set(seen))
                                                           for f in fns]
            elif not name.startswith("__") and isinstance(v, (bool, int, float, str, tuple, np.ndarray, np.generic)):
                members[f"{c.__qualname__}.{name}"] = _value_config(v, special, f"{where}.{name}", set(seen))
    return {"module": cls.__module__, "members": members}


def _function_config(fn, special, where, _seen=None):
    """:func:`config_of` of a callable (see there)."""
    import functools
    import types
    seen = set() if _seen is None else _seen
    if isinstance(fn, functools.partial):
        return {"partial": _function_config(fn.func, special, f"{where}.func", seen),
                "args": [_value_config(a, special, f"{where}.args[{i}]", seen) for i, a in enumerate(fn.args)],
                "keywords": {k: _value_config(v, special, f"{where}.keywords[{k!r}]", seen)
                             for k, v in sorted(fn.keywords.items())}}
    if isinstance(fn, types.MethodType):
        return {"method": _function_config(fn.__func__, special, f"{where}.__func__", seen),
                "self": _value_config(fn.__self__, special, f"{where}.__self__", seen)}
    inner = getattr(fn, "__wrapped__", None)            # jax.jit, functools.wraps
    name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', type(fn).__qualname__)}"
    if inner is not None and callable(inner) and not isinstance(fn, types.FunctionType):
        return _function_config(inner, special, where, seen)
    if not isinstance(fn, types.FunctionType):
        python_call = isinstance(getattr(type(fn), "__call__", None), types.FunctionType)
        own = _class_config(type(fn), special, where, seen) if python_call and not isinstance(fn, type) else None
        if own is not None and hasattr(fn, "__dict__"):  # an instance of a user's callable class
            return {"object": name, "class": own, "attributes": _value_config(vars(fn), special, where, seen)}
        return name                                      # a builtin, ufunc or other compiled callable
    if id(fn) in seen:
        return name                                      # a function that refers to itself
    seen = seen | {id(fn)}
    code = fn.__code__
    out = {"function": name, "code": _code_hash(code)}
    if fn.__closure__:
        out["closure"] = {v: _value_config(c.cell_contents, special, f"{where}.<closure {v}>", seen)
                          for v, c in zip(code.co_freevars, fn.__closure__) if _has_contents(c)}
    if fn.__defaults__:
        out["defaults"] = [_value_config(d, special, f"{where}.<default {i}>", seen)
                           for i, d in enumerate(fn.__defaults__)]
    if fn.__kwdefaults__:
        out["kwdefaults"] = {k: _value_config(v, special, f"{where}.<default {k}>", seen)
                             for k, v in sorted(fn.__kwdefaults__.items())}
    reads = {}
    for g in sorted(_global_names(code)):
        v = fn.__globals__.get(g, None)
        if isinstance(v, (bool, int, float, str, complex, np.ndarray, np.generic)) or type(v).__module__.startswith("jax"):
            if callable(v):
                continue
            try:
                reads[g] = _value_config(v, special, f"{where}.<global {g}>", seen)
            except TypeError:
                continue
        elif isinstance(v, types.FunctionType) and v.__module__ == fn.__module__:
            reads[g] = _function_config(v, special, f"{where}.<global {g}>", seen)
    if reads:
        out["globals"] = reads
    return out


def _has_contents(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:                                   # an empty cell (a name not yet bound)
        return False
    return True


def _value_config(v, special, where, seen):
    """:func:`config_of` of a value met inside a function (a closure, default or global):
    a function there keeps the set of functions already being described (no endless
    recursion), and a value none of :func:`config_of`'s kinds describe is named by its type
    (its contents cannot be compared)."""
    if callable(v) and not hasattr(v, "__array__") and not (dataclasses.is_dataclass(v) and not isinstance(v, type)):
        return _function_config(v, special, where, seen)
    try:
        return config_of(v, special, where)
    except TypeError:
        return f"<{type(v).__module__}.{type(v).__qualname__}>"


def _coord_value(v):
    """A coordinate label as a JSON value (numpy scalars to Python)."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise TypeError(f"save_per_seed: coordinate values must be str, int or float, got {v!r}")
    return v


def _fields(metrics) -> dict[str, np.ndarray]:
    """A NamedTuple, dataclass or mapping of per-seed arrays -> {name: 1-D numpy array}."""
    if hasattr(metrics, "_asdict"):
        metrics = metrics._asdict()
    elif not isinstance(metrics, Mapping):
        raise TypeError(f"save_per_seed: metrics must be a NamedTuple or a mapping, got {type(metrics).__name__}")
    return {str(k): np.asarray(v) for k, v in metrics.items()}


def _dims(dims, where: str) -> tuple[str, ...]:
    """``dims`` as a tuple of distinct names; ValueError naming ``where`` for a single
    string (``"case"`` would be four dimensions c, a, s, e) or names that are not strings."""
    if isinstance(dims, str) or not isinstance(dims, Sequence) or not dims \
            or not all(isinstance(d, str) and d for d in dims) or len(set(dims)) != len(dims):
        raise ValueError(f"{where}: dims must be a non-empty sequence of distinct dimension names, e.g. "
                         f"('case',) or ('p', 'delta'), got {dims!r}")
    return tuple(dims)


def _key(key, dims: tuple, where: str, what: str = "run") -> tuple:
    """A run's coordinates as a tuple with one label per dimension (a single label for one
    dimension); ValueError naming ``where`` otherwise."""
    key = key if isinstance(key, tuple) else (key,)
    if len(key) != len(dims):
        raise ValueError(f"{where}: {what} {key!r} has {len(key)} coordinates, dims are {dims}")
    return tuple(_coord_value(v) for v in key)


def _stack(runs: Mapping[tuple, Mapping], dims: Sequence[str]):
    """{coords: metrics} -> (coords per dim, {name: array (*dims, seed)}, present mask).

    Coordinates are listed per dimension in order of first appearance; a combination with
    no run has NaN metrics, ``unstable`` True and ``present`` False."""
    dims = _dims(dims, "save_per_seed")
    if not runs:
        raise ValueError("save_per_seed: no runs")
    coords = {d: [] for d in dims}
    rows = {}
    for key, metrics in runs.items():
        key = _key(key, dims, "save_per_seed")
        for d, v in zip(dims, key):
            if v not in coords[d]:
                coords[d].append(v)
        rows[key] = _fields(metrics)
    first = next(iter(rows.values()))
    if "unstable" not in first:
        raise ValueError("save_per_seed: the metrics need an 'unstable' field (the runs the summaries leave out)")
    n = None
    for key, fields in rows.items():
        if set(fields) != set(first):
            raise ValueError(f"save_per_seed: run {key!r} has fields {sorted(fields)}, expected {sorted(first)}")
        for name, a in fields.items():
            if a.ndim != 1 or (n is not None and a.shape[0] != n):
                raise ValueError(f"save_per_seed: {name} of run {key!r} has shape {a.shape}; every metric must "
                                 f"be one value per seed ({n if n is not None else 'n'},)")
            n = a.shape[0]
    shape = tuple(len(coords[d]) for d in dims)
    present = np.zeros(shape, bool)
    complete = len(rows) == present.size
    data = {}
    for name, a in first.items():
        if name == "unstable":
            fill, dtype = True, bool
        elif a.dtype == bool:
            fill, dtype = False, bool
        elif complete:
            fill, dtype = 0, a.dtype
        else:
            fill, dtype = np.nan, np.result_type(a.dtype, np.float32)
        data[name] = np.full((*shape, n), fill, dtype)
    for key, fields in rows.items():
        idx = tuple(coords[d].index(v) for d, v in zip(dims, key))
        present[idx] = True
        for name, a in fields.items():
            data[name][idx] = a
    return coords, data, present


def _units(metrics: Sequence, given: Mapping | None, names: Sequence[str], where: str) -> dict[str, str]:
    """``{metric: unit}``: the ``UNITS`` of the metrics' NamedTuple classes, then ``given``;
    ValueError naming ``where`` for a name that is not one of ``names`` or a unit that is not
    a non-empty string."""
    out = {}
    for m in metrics:
        own = getattr(type(m), "UNITS", None)
        if hasattr(m, "_asdict") and isinstance(own, Mapping):
            out.update({k: v for k, v in own.items() if k in names})
    if given is not None:
        if not isinstance(given, Mapping):
            raise ValueError(f"{where}: units must be a mapping of metric name to unit, e.g. {{'J1': 'm'}}, "
                             f"got {type(given).__name__}")
        for k, v in given.items():
            if k not in names:
                raise ValueError(f"{where}: units names {k!r}, which is not one of the metrics {list(names)}")
            if not isinstance(v, str) or not v.strip():
                raise ValueError(f"{where}: the unit of {k!r} must be a non-empty string, got {v!r}")
        out.update({str(k): v for k, v in given.items()})
    return out


def save_per_seed(folder, runs: Mapping, dims: Sequence[str] = ("case",), *, experiment: str | None = None,
                  units: Mapping[str, str] | None = None) -> pathlib.Path:
    """Write the per-seed metrics of a run to ``folder/seeds.npz`` (atomically); returns the file.

    ``runs`` maps a run's coordinates (a tuple with one label per entry of ``dims``, or a
    single label for one dimension) to its metrics: a NamedTuple or mapping of 1-D arrays,
    one value per seed (all runs the same fields and seed count), with a boolean
    ``unstable`` field. Raises ValueError / TypeError for runs that do not fit that shape.
    ``experiment`` (the name in ``results.json``) is stored too, and :func:`load` checks it;
    so is the id of the run that claimed ``folder`` (:func:`run_id`), which
    :func:`jaxnc.montecarlo.save_results` stores in ``results.json`` too: :func:`load` refuses
    a ``seeds.npz`` of one run beside a ``results.json`` of another (a run stopped between
    writing the two).

    ``units`` maps a metric's name to its unit (``{"J1": "m"}``); a run's metrics given as a
    NamedTuple whose class has a ``UNITS`` mapping (:class:`jaxnc.loop.Metrics`, the papers'
    ``Metrics``) add theirs. :func:`load` gives each such variable ``attrs["units"]``. Raises
    ValueError for a unit of a name that is not one of the metrics, or one that is not a
    non-empty string.
    """
    from jaxnc.montecarlo import atomic_write
    coords, data, present = _stack(runs, dims)
    units = _units([*runs.values()], units, sorted(data), "save_per_seed")
    meta = {"format": FORMAT, "dims": list(dims), "coords": coords, "variables": sorted(data)}
    if experiment is not None:
        meta["experiment"] = str(experiment)
    if units:
        meta["units"] = units
    run = run_id(folder)
    if run is not None:
        meta["run"] = run
    if not present.all():
        data["present"] = present
    arrays = {_META: np.asarray(json.dumps(meta)), **data}
    f = pathlib.Path(folder) / PER_SEED_FILE
    atomic_write(f, lambda fh: np.savez_compressed(fh, **arrays))
    return f


def per_seed_index(folder, cells: Mapping[tuple, object], dims: Sequence[str], *,
                   units: Mapping[str, str] | None = None) -> dict:
    """The ``results["per_seed"]`` entry of a grid: ``{"dims", "cells": [[*coords, file]]}``,
    each cell's ``.npz`` (of its metrics' fields, one value per seed) relative to ``folder``.

    ``cells`` maps a cell's coordinates (a tuple with one label per entry of ``dims``, or a
    single label for one dimension) to its file inside ``folder``. Raises ValueError (naming
    ``per_seed_index`` and the cell) for dims that are not a sequence of names, a cell with
    another number of coordinates, or a file outside ``folder``: checked here, when the
    index is written, rather than by :func:`load` after the sweep. ``units``: ``{metric: unit}``
    (as :func:`save_per_seed`'s; the names are not checked against the cells' files here,
    :func:`load` ignores a unit of a name they do not hold)."""
    folder = pathlib.Path(folder)
    dims = _dims(dims, "per_seed_index")
    rows = []
    for key, f in cells.items():
        key = _key(key, dims, "per_seed_index", "cell")
        try:
            rel = pathlib.Path(f).relative_to(folder).as_posix()
        except ValueError:
            raise ValueError(f"per_seed_index: the file of cell {key!r}, {f}, must be inside the folder "
                             f"{folder}") from None
        rows.append([*key, rel])
    index = {"format": FORMAT, "dims": list(dims), "cells": rows}
    if units is not None:
        names = list(units) if isinstance(units, Mapping) else []
        index["units"] = _units([], units, names, "per_seed_index")
    return index


# ----------------------------------------------------------------------------- folders


def _plain(x):
    """``x`` as the JSON values it is stored as (tuples as lists, numpy as Python)."""
    return json.loads(json.dumps(x, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))


def _read_json(f: pathlib.Path):
    try:
        with open(f, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def folder_owner(folder) -> dict | None:
    """``{"experiment", "settings", "seeds"}`` of the run whose results ``folder`` holds:
    its ``run.json``, else (a folder written without one) what ``results.json`` says
    (``settings`` and ``seeds`` None where it does not hold them in the built-in
    experiments' layout); None for a folder with neither."""
    folder = pathlib.Path(folder)
    run = _read_json(folder / RUN_FILE)
    if isinstance(run, dict) and run.get("format") == RUN_FORMAT and isinstance(run.get("experiment"), str):
        return {"experiment": run["experiment"], "settings": run.get("settings"), "seeds": run.get("seeds")}
    doc = _read_json(folder / "results.json")
    if isinstance(doc, dict) and isinstance(doc.get("experiment"), str):
        config = doc.get("config") if isinstance(doc.get("config"), dict) else {}
        settings = config.get("settings") if isinstance(config.get("settings"), dict) else None
        return {"experiment": doc["experiment"], "settings": settings,
                "seeds": config.get("seeds") if settings is not None else None}
    return None


def _show(v) -> str:
    if v is None:
        return "(none)"
    if isinstance(v, list):
        return ",".join(_show(x) for x in v)
    return str(v).lower() if isinstance(v, bool) else str(v)


def _differences(there: dict, here: dict) -> list[str]:
    keys = list(here) + [k for k in there if k not in here]
    return [f"{k}: {_show(there.get(k))} there, {_show(here.get(k))} here"
            for k in keys if there.get(k) != here.get(k)]


def run_id(folder) -> str | None:
    """The id that :func:`claim` gave the run that last claimed ``folder`` (``run.json``'s
    ``"run"``, new at every claim); None for a folder without one (never claimed, or claimed
    by a jaxnc before run ids). :func:`save_per_seed` and
    :func:`jaxnc.montecarlo.save_results` store it in the files they write there, so that
    :func:`load` tells a folder whose files come from two runs of the same settings apart."""
    run = _read_json(pathlib.Path(folder) / RUN_FILE)
    rid = run.get("run") if isinstance(run, dict) and run.get("format") == RUN_FORMAT else None
    return rid if isinstance(rid, str) else None


def claim(folder, experiment: str, settings: Mapping, seeds: int, *, keeps_cells: bool = False) -> list[str]:
    """Record in ``folder/run.json`` that ``folder`` receives the results of ``experiment``
    run with ``settings`` and ``seeds`` (atomically; the folder must exist), under a new
    run id (:func:`run_id`).

    Raises :class:`FolderError`, writing nothing, when the folder holds the results of
    another experiment (:func:`folder_owner`), or when it holds finished results
    (``results.json``) of the same experiment with other settings or seeds that this run
    would overwrite; the message names every differing setting. ``keeps_cells``: the
    experiment stores its results as cell files named by their whole configuration
    (:func:`jaxnc.sweep.cell_path`), so a run with other settings keeps its cells beside
    the others' and only the summary files describe the latest run: allowed, and the
    differences are returned (``"key: A there, B here"``, empty when there are none) for
    the caller to show.
    """
    from jaxnc.montecarlo import atomic_write
    folder = pathlib.Path(folder)
    owner = folder_owner(folder)
    here = _plain({"settings": dict(settings), "seeds": int(seeds)})
    if owner is not None and owner["experiment"] != experiment:
        raise FolderError(f"{folder} holds the results of experiment {owner['experiment']!r}, not {experiment!r}; "
                          f"choose another folder (or remove this one)")
    diff = []
    if owner is not None and owner["settings"] is not None:
        there = _plain({"settings": owner["settings"], "seeds": owner["seeds"]})
        diff = _differences(there["settings"], here["settings"])
        if there["seeds"] != here["seeds"]:
            diff.append(f"seeds: {_show(there['seeds'])} there, {here['seeds']} here")
        if diff and not keeps_cells and (folder / "results.json").exists():
            raise FolderError(f"{folder} holds the results of {experiment} with other settings ({'; '.join(diff)}), "
                              f"which this run would overwrite; choose another folder (or remove this one)")
    import uuid
    doc = {"format": RUN_FORMAT, "experiment": experiment, **here, "run": uuid.uuid4().hex}
    text = json.dumps(doc, indent=1, allow_nan=False) + "\n"
    atomic_write(folder / RUN_FILE, lambda fh: fh.write(text.encode("utf-8")))
    return diff if keeps_cells else []


# ----------------------------------------------------------------------------- reading


def _read_npz(f: pathlib.Path) -> dict[str, np.ndarray]:
    try:
        with np.load(f, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as e:
        raise ValueError(f"{f}: damaged per-seed file ({type(e).__name__}: {' '.join(str(e).split())}); "
                         f"rerun the experiment to write it again") from None


def _load_single(f: pathlib.Path):
    if not f.exists():
        raise FileNotFoundError(f"{f}: no per-seed file (this folder was written by a jaxnc older than per-seed "
                                f"results, or by an experiment that saves only summaries); rerun the experiment")
    z = _read_npz(f)
    try:
        meta = json.loads(str(z.pop(_META)))
        assert meta.get("format") == FORMAT, f"format {meta.get('format')!r}, expected {FORMAT!r}"
        dims, coords = list(meta["dims"]), meta["coords"]
        shape = tuple(len(coords[d]) for d in dims)
        for name in meta["variables"]:
            a = z[name]
            assert a.ndim == len(dims) + 1 and a.shape[:-1] == shape, f"{name} has shape {a.shape}"
    except (KeyError, TypeError, ValueError, AssertionError) as e:
        raise ValueError(f"{f}: damaged per-seed file ({type(e).__name__}: {e})") from None
    run = meta.get("run")
    return dims, coords, z, meta.get("experiment"), run if isinstance(run, str) else None, meta.get("units")


def _load_cells(folder: pathlib.Path, index: dict, results_file: pathlib.Path):
    try:
        dims, rows = list(index["dims"]), index["cells"]
        assert isinstance(rows, list) and all(isinstance(d, str) for d in dims)
    except (KeyError, TypeError, AssertionError):
        raise ValueError(f"{results_file}: damaged per-seed index (results['per_seed'] needs 'dims', a list of "
                         f"names, and 'cells', a list of rows)") from None
    runs = {}
    for i, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != len(dims) + 1 or not isinstance(row[-1], str) or not row[-1]:
            raise ValueError(f"{results_file}: per-seed index row {i} ({row!r}) must be [{', '.join(dims)}, "
                             f"file name]: one coordinate per dimension, then the cell's file name")
        key, rel = tuple(row[:-1]), row[-1]
        if pathlib.PurePosixPath(rel).is_absolute() or ".." in pathlib.PurePosixPath(rel).parts:
            raise ValueError(f"{results_file}: per-seed index row {i}: file name {rel!r} must be inside the folder")
        f = folder / rel
        if not f.exists():
            raise FileNotFoundError(f"{f}: cell file listed in {results_file} is missing")
        runs[key] = _read_npz(f)
    try:
        coords, data, present = _stack(runs, dims)
    except ValueError as e:
        raise ValueError(f"{folder / 'cells'}: cell files do not fit together ({e})") from None
    if not present.all():
        data["present"] = present
    return dims, coords, data


def _xarray():
    import xarray as xr
    if not hasattr(xr.Dataset, "jaxnc"):
        xr.register_dataset_accessor("jaxnc")(_Accessor)
    return xr


def load(folder):
    """The per-seed metrics of the run in ``folder`` as an ``xarray.Dataset`` (module docstring).

    Dimensions: the run's own (``case``; ``severity``, ``design``; ``path``, ``N``,
    ``case``, ``dp``) and ``seed``, labelled 0 .. n - 1 in the order the per-seed arrays hold
    them: the seed index i of ``fold_in(PRNGKey(seed), i)`` for a run of
    ``seed_keys(seed, n)``, as every built-in experiment's; the files do not record a
    ``start``, so a study run from ``seed_keys(seed, n, start=k)`` reads k + i as i.
    Variables: the experiment's per-seed metrics (float32 / int32 / bool as computed;
    a grid with combinations it did not compute has NaN there, ``unstable`` True and a
    boolean ``present`` variable), each with ``attrs["units"]`` where the run stored its unit
    (:func:`save_per_seed`'s ``units``: the built-in experiments' and
    :class:`jaxnc.loop.Metrics`' rates; a cost's unit is the user's). Attributes: ``experiment``, ``settings``, ``seeds``,
    ``config`` (the whole configuration), ``jaxnc_version``, ``jax_version``,
    ``platform``, ``created``, ``wall_time_s``.

    Raises FileNotFoundError naming the file when ``folder`` has no ``results.json`` or
    no per-seed data (a folder written before per-seed results existed), ValueError
    naming the file when one is damaged or malformed (a ``config`` that is not a mapping,
    a ``config.seeds`` that is not a positive integer or not the per-seed files' seed
    count, an index row without a file name) and naming the files when the folder mixes
    two experiments' or two runs' files (module docstring).
    """
    xr = _xarray()
    from jaxnc.montecarlo import load_results
    folder = pathlib.Path(folder)
    rj = folder / "results.json"
    if not rj.exists():
        raise FileNotFoundError(f"{rj}: no results file; is {folder} a jaxnc results folder?")
    doc = load_results(rj)
    if not isinstance(doc, dict) or "experiment" not in doc or not isinstance(doc.get("results"), dict):
        raise ValueError(f"{rj}: not a jaxnc results file (no 'experiment' or 'results')")
    experiment = doc["experiment"]
    config = doc.get("config")
    config = {} if config is None else config
    if not isinstance(config, dict):
        raise ValueError(f"{rj}: 'config' must be a mapping (a JSON object) of the run's configuration, "
                         f"got {type(config).__name__}")
    if not isinstance(config.get("settings", {}), dict):
        raise ValueError(f"{rj}: config.settings must be a mapping (a JSON object), "
                         f"got {type(config['settings']).__name__}")
    seeds = config.get("seeds")
    if seeds is not None and (isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1):
        raise ValueError(f"{rj}: config.seeds must be the number of seeds, an integer >= 1, got {seeds!r}")
    run = folder_owner(folder) if (folder / RUN_FILE).exists() else None
    if run is not None and run["experiment"] != experiment:
        raise ValueError(f"{folder} mixes the files of two experiments: {rj.name} is {experiment!r}'s, "
                         f"{RUN_FILE} {run['experiment']!r}'s; rerun the experiment into a folder of its own")
    index = doc["results"].get("per_seed")
    single = folder / PER_SEED_FILE
    cell_dirs = [d for d in _CELL_DIRS if (folder / d).is_dir()]
    if index is not None and single.exists():
        raise ValueError(f"{folder} mixes the files of two runs: {rj.name} lists per-seed cells and {PER_SEED_FILE} "
                         f"holds a single run's; rerun the experiment into a folder of its own")
    units = None
    if index is not None:
        dims, coords, data = _load_cells(folder, index, rj)
        units = index.get("units") if isinstance(index, dict) else None
    elif cell_dirs and not single.exists():
        raise FileNotFoundError(f"{rj}: lists no per-seed cells (written by a jaxnc older than per-seed results); "
                                f"rerun the same command: the stored cells are reused and indexed")
    elif cell_dirs:
        raise ValueError(f"{folder} mixes the files of two runs: {cell_dirs[0]}/ holds a sweep's cells, which "
                         f"{rj.name} does not list, beside a single run's {PER_SEED_FILE}; rerun the experiment "
                         f"into a folder of its own")
    else:
        dims, coords, data, stored, run, units = _load_single(single)
        if stored is not None and stored != experiment:
            raise ValueError(f"{folder} mixes the files of two experiments: {rj.name} is {experiment!r}'s, "
                             f"{PER_SEED_FILE} {stored!r}'s; rerun the experiment into a folder of its own")
        if run != doc.get("run"):
            raise ValueError(f"{folder} mixes the files of two runs: {PER_SEED_FILE} was written by run "
                             f"{run or '(no id)'}, {rj.name} by run {doc.get('run') or '(no id)'} (a run stopped "
                             f"after writing one and before the other?); rerun the experiment")
    n = next(iter(data.values())).shape[-1]
    if seeds is not None and seeds != n:
        raise ValueError(f"{rj}: config.seeds is {seeds} but the per-seed files hold {n} seeds (the files of two "
                         f"runs mixed?); rerun the experiment into a folder of its own")
    all_dims = (*dims, "seed")
    variables = {k: ((tuple(dims) if k == "present" else all_dims), v) for k, v in data.items()}
    attrs = {"experiment": experiment, "settings": config.get("settings", {}),
             "seeds": config.get("seeds", n), "config": config}
    attrs |= {k: doc[k] for k in ("jaxnc_version", "jax_version", "platform", "created", "wall_time_s") if k in doc}
    ds = xr.Dataset(variables, coords={**{d: list(coords[d]) for d in dims}, "seed": np.arange(n)}, attrs=attrs)
    for name, unit in (units.items() if isinstance(units, dict) else ()):
        if name in ds.data_vars and isinstance(unit, str):
            ds[name].attrs["units"] = unit
    return ds


# ----------------------------------------------------------------------------- summaries

_STATS = ("mean", "ci95", "std", "n_stable")


def summary(ds):
    """Each numeric per-seed metric reduced over ``seed`` as the printed tables do
    (:func:`jaxnc.montecarlo.summarize` over the runs that are not ``unstable``):
    variables ``<metric>`` (the mean; with no stable run, ``<metric>_n_stable`` 0 and the
    mean inf where the metric is +inf in every run, a divergent cost, else nan), ``<metric>_ci95``,
    ``<metric>_std``, ``<metric>_n_stable``, and ``n``, ``unstable_fraction``; the
    other dimensions are kept. Boolean metrics other than ``unstable`` are averaged over
    all seeds (the fraction of runs where they hold). A combination no run computed
    (``present`` False) has ``n`` and the ``_n_stable`` counts 0 and every other statistic
    nan. A metric's ``attrs["units"]`` (:func:`load`) is kept on its mean, ``_ci95`` and
    ``_std``."""
    xr = _xarray()
    from jaxnc.montecarlo import summarize

    def stats(v, u):
        s = summarize(v, u)
        return np.array([s.mean, s.ci95, s.std, s.n_stable], float)

    unstable = ds["unstable"]
    out = {}
    for name, v in ds.data_vars.items():
        if "seed" not in v.dims or name == "unstable":
            continue
        if v.dtype == bool:
            out[name] = v.astype(float).mean("seed")
            continue
        r = xr.apply_ufunc(stats, v, unstable, input_core_dims=[["seed"], ["seed"]], output_core_dims=[["stat"]],
                           vectorize=True, keep_attrs=False, dask_gufunc_kwargs={"output_sizes": {"stat": len(_STATS)}})
        for i, s in enumerate(_STATS):
            stat = r.isel(stat=i, drop=True)
            unit = v.attrs.get("units") if s != "n_stable" else None        # a count has none
            out[name if s == "mean" else f"{name}_{s}"] = stat.assign_attrs(units=unit) if unit else stat
    out["n"] = xr.full_like(unstable.isel(seed=0, drop=True), ds.sizes["seed"], dtype=int)
    out["unstable_fraction"] = unstable.astype(float).mean("seed")
    if "present" in ds:
        # a combination no run computed has no runs (summarize's rule for none: nan), not
        # every run unstable: its stored fill (NaN metrics, unstable True) is not data
        present = ds["present"]
        out = {k: (v.where(present, 0) if k == "n" or k.endswith("_n_stable") else v.where(present))
               for k, v in out.items()}
        out["present"] = present
    out = {k: (v.astype(int) if k.endswith("_n_stable") else v) for k, v in out.items()}   # counts (float from stats)
    return xr.Dataset(out, attrs=ds.attrs)


def to_pandas(ds):
    """:func:`summary` as a ``pandas.DataFrame``: one row per case (a MultiIndex over the
    run's dimensions), one column per statistic."""
    return summary(ds).to_dataframe()


class _Accessor:
    """``ds.jaxnc.summary()`` / ``ds.jaxnc.to_pandas()`` on a Dataset from :func:`load`."""

    def __init__(self, ds):
        self._ds = ds

    def summary(self):
        return summary(self._ds)

    def to_pandas(self):
        return to_pandas(self._ds)
