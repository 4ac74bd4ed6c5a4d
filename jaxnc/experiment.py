"""Experiment registry and ``KEY=VALUE`` option parsing for the command line.

An :class:`Experiment` names a study, declares its settings as :class:`Option` s (type,
default, bounds) and provides ``run(settings, *, seeds, out, progress) -> dict``.  Modules in
``jaxnc.experiments`` call :func:`register` at import time; :func:`load_builtin` imports them.
Every bad user setting raises :class:`ConfigError` with a one-line message naming the key and
the allowed values, which the CLI prints as ``jaxnc: error: <message>``.
:func:`resolve_experiment` also finds an experiment defined in the user's own module from a
``MODULE:ATTR`` spec (``jaxnc run mymod:experiment``).

This module does not import jax, so ``jaxnc --help`` / ``--version`` stay fast.
"""
from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import inspect
import math
import os
import pathlib
import re
import sys
import types
import warnings
from typing import Callable

__all__ = ["ConfigError", "Option", "Experiment", "REGISTRY", "register", "get_experiment",
           "resolve_experiment", "load_builtin", "KINDS"]

KINDS = ("int", "float", "choice", "floats", "ints", "bool")
_TRUE = ("true", "yes", "on", "1")
# plain ASCII numbers only: Python's int()/float() also take full-width digits and "1_0"
_INT_RE = re.compile(r"[+-]?[0-9]+\Z")
_FLOAT_RE = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?\Z")
_FALSE = ("false", "no", "off", "0")


class ConfigError(ValueError):
    """A bad user setting; its message is one line naming the key and the allowed range."""


def _num(x) -> str:
    """Compact number for messages: 0.0 -> '0', 2**31 - 1 -> '2147483647', 0.95 -> '0.95'."""
    x = float(x)
    if math.isfinite(x) and x.is_integer() and abs(x) < 1e16:
        return str(int(x))
    return repr(x)


@dataclasses.dataclass(frozen=True)
class Option:
    """One setting of an experiment.

    ``kind`` is ``"int"``, ``"float"``, ``"choice"`` (one of ``choices``), ``"floats"`` (a
    comma-separated list of floats, parsed to a tuple), ``"ints"`` (the same for integers) or ``"bool"`` (true/false, yes/no,
    on/off, 1/0).  ``low``/``high`` are inclusive bounds for int, float and each element of
    floats; ``None`` means unbounded.  Floats must be finite.
    """
    name: str
    kind: str
    default: object
    help: str
    choices: tuple = ()
    low: float | None = None
    high: float | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Option {self.name!r}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind == "choice" and not self.choices:
            raise ValueError(f"Option {self.name!r}: a choice option needs choices")
        if self.low is not None and self.high is not None and self.low > self.high:
            raise ValueError(f"Option {self.name!r}: low > high")
        if not self._valid(self.default):
            raise ValueError(f"Option {self.name!r}: default {self.default!r} must be {self.range_text()} "
                             f"(the value a run without --set {self.name}=... uses)")

    def _valid(self, value) -> bool:
        """Whether ``value`` is a value of this option, as :meth:`parse` returns them (the
        default must be one: a run without ``--set`` uses it unchecked)."""
        def number(x, integer):
            if isinstance(x, bool) or not isinstance(x, (int, float) if not integer else int):
                return False
            return math.isfinite(x) and self._in_range(x)
        if self.kind in ("int", "float"):
            return number(value, self.kind == "int")
        if self.kind in ("floats", "ints"):
            return (isinstance(value, (tuple, list)) and len(value) > 0
                    and all(number(v, self.kind == "ints") for v in value))
        if self.kind == "bool":
            return isinstance(value, bool)
        return value in self.choices

    # -- descriptions used in messages and by `jaxnc list`
    def range_text(self) -> str:
        """The allowed values in words, e.g. 'an integer in [1, 12]'."""
        if self.kind == "choice":
            return "one of " + ", ".join(str(c) for c in self.choices)
        if self.kind == "bool":
            return "true or false"
        what = {"int": "an integer", "float": "a number", "floats": "a comma-separated list of numbers",
                "ints": "a comma-separated list of integers"}[self.kind]
        lo, hi = self.low, self.high
        if lo is not None and hi is not None:
            return f"{what} in [{_num(lo)}, {_num(hi)}]"
        if lo is not None:
            return f"{what} >= {_num(lo)}"
        if hi is not None:
            return f"{what} <= {_num(hi)}"
        return what

    def format_value(self, value) -> str:
        """A value written the way :meth:`parse` reads it."""
        if self.kind == "bool":
            return "true" if value else "false"
        if self.kind == "floats":
            try:
                return ",".join(f"{float(v):g}" for v in value)
            except TypeError:
                return f"{float(value):g}"
        if self.kind == "ints":
            try:
                return ",".join(str(int(v)) for v in value)
            except TypeError:
                return str(int(value))
        if self.kind == "float":
            return f"{float(value):g}"
        return str(value)

    def _error(self, text: str) -> ConfigError:
        return ConfigError(f"{self.name} must be {self.range_text()}, got {text!r}")

    def _in_range(self, x: float) -> bool:
        return (self.low is None or x >= self.low) and (self.high is None or x <= self.high)

    def _float(self, item: str, text: str) -> float:
        if not _FLOAT_RE.match(item):
            raise self._error(text)
        x = float(item)
        if not math.isfinite(x) or not self._in_range(x):
            raise self._error(text)
        mantissa = re.split(r"[eE]", item)[0]
        if x == 0.0 and re.search(r"[1-9]", mantissa):
            raise ConfigError(f"{self.name} must be {self.range_text()}, got {text!r}, which underflows to 0")
        return x

    def _int(self, item: str, text: str) -> int:
        if not _INT_RE.match(item):
            raise self._error(text)
        x = int(item, 10)
        if not self._in_range(x):
            raise self._error(text)
        return x

    def parse(self, text: str) -> object:
        """Parse the command-line text of this option; :class:`ConfigError` if invalid."""
        s = str(text).strip()
        if self.kind == "int":
            return self._int(s, text)
        if self.kind == "float":
            return self._float(s, text)
        if self.kind == "floats":
            items = [p.strip() for p in s.split(",")]
            if not s or any(not p for p in items):
                raise self._error(text)
            return tuple(self._float(p, text) for p in items)
        if self.kind == "ints":
            items = [p.strip() for p in s.split(",")]
            if not s or any(not p for p in items):
                raise self._error(text)
            return tuple(self._int(p, text) for p in items)
        if self.kind == "bool":
            low = s.lower()
            if low in _TRUE:
                return True
            if low in _FALSE:
                return False
            raise self._error(text)
        # choice: exact match first, then a unique case-insensitive match
        from jaxnc._validate import choice
        c = choice(s, self.choices)
        if c is None:
            raise self._error(text)
        return c


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A registered study.

    ``run(settings, *, seeds, out, progress) -> dict`` receives the parsed settings (every
    option's default, updated by the user's ``KEY=VALUE`` pairs), the number of Monte-Carlo
    seeds, the output directory (already created) and whether to show progress bars; it
    prints its own table, writes its own files and returns the results.  ``check(settings)``,
    if given, validates combinations of options (raising :class:`ConfigError`) when the
    settings are parsed, before anything is built. A sweep's ``run`` also takes
    ``shard`` (a :class:`jaxnc.sweep.Shard`, or None for all cells), which
    ``jaxnc run --shard I/N`` passes; the CLI refuses ``--shard`` for the others.

    ``keeps_cells``: the experiment stores its results as cell files named by their whole
    configuration (:func:`jaxnc.sweep.cell_path`), so a run with other settings into the
    same ``--out`` keeps its cells beside the others' (only the summary files describe
    the latest run); without it such a run is refused rather than overwriting the
    folder's results (:func:`jaxnc.results.claim`). A sweep's ``run`` returns a dict with
    ``"complete": False`` when it ends with cells missing.
    """
    name: str
    description: str
    options: tuple[Option, ...]
    run: Callable[..., dict]
    check: Callable[[dict], None] | None = None
    keeps_cells: bool = False

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.strip() or any(c in self.name for c in "/\\"):
            raise ValueError(f"Experiment.name must be a non-empty name without / or \\ (the default --out is "
                             f"results/NAME), got {self.name!r}")
        if not isinstance(self.options, (tuple, list)):
            raise ValueError(f"Experiment {self.name!r}: options must be a tuple of jaxnc.experiment.Option, "
                             f"got {type(self.options).__name__}")
        for i, o in enumerate(self.options):
            if not isinstance(o, Option):
                raise ValueError(f"Experiment {self.name!r}: options[{i}] must be a jaxnc.experiment.Option, "
                                 f"got {o!r}")
        if not callable(self.run):
            raise ValueError(f"Experiment {self.name!r}: run must be a function run(settings, *, seeds, out, "
                             f"progress), got {self.run!r}")
        if self.check is not None and not callable(self.check):
            raise ValueError(f"Experiment {self.name!r}: check must be a function check(settings) or None, "
                             f"got {self.check!r}")
        names = [o.name for o in self.options]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"Experiment {self.name!r}: duplicate options {', '.join(dup)}")

    def defaults(self) -> dict:
        return {o.name: o.default for o in self.options}

    def option(self, key: str) -> Option:
        """The option called ``key`` (exact, else unique case-insensitive match)."""
        for o in self.options:
            if o.name == key:
                return o
        folded = [o for o in self.options if o.name.lower() == key.lower()]
        if len(folded) == 1:
            return folded[0]
        valid = ", ".join(o.name for o in self.options) or "(none)"
        raise ConfigError(f"unknown setting {key!r} for experiment {self.name!r}; valid keys: {valid}")

    def parse_settings(self, pairs: list[str]) -> dict:
        """``["KEY=VALUE", ...]`` -> the defaults updated; a key given twice is an error."""
        settings = self.defaults()
        seen: dict[str, str] = {}
        for pair in pairs or ():
            key, sep, value = str(pair).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ConfigError(f"malformed setting {pair!r}: expected KEY=VALUE")
            opt = self.option(key)
            if opt.name in seen:
                raise ConfigError(f"setting {opt.name!r} given twice ({seen[opt.name]!r} and {pair!r}); give it once")
            seen[opt.name] = str(pair)
            settings[opt.name] = opt.parse(value)
        if self.check is not None:
            self.check(settings)
        return settings


REGISTRY: dict[str, Experiment] = {}


def register(exp: Experiment) -> Experiment:
    """Add ``exp`` to the registry (replacing one of the same name) and return it."""
    if not isinstance(exp, Experiment):
        raise TypeError(f"register expects an Experiment, got {type(exp).__name__}")
    REGISTRY[exp.name] = exp
    return exp


def get_experiment(name) -> Experiment:
    """The registered experiment ``name``; :class:`ConfigError` listing the available ones.

    A ``MODULE:ATTR`` name that is not registered is resolved by :func:`resolve_experiment`.
    """
    return resolve_experiment(name)


def resolve_experiment(spec) -> Experiment:
    """The experiment that ``spec`` names: a registered name, or ``MODULE:ATTR``.

    A registered name (looked up first, exactly) returns that experiment.  Otherwise a spec
    with a colon is ``MODULE:ATTR``: MODULE (an absolute dotted module name, not a file) is
    imported with :func:`importlib.import_module`, the current working directory first
    being put at the front of ``sys.path`` if it is not on it (as ``python -m`` does), and
    ATTR (dotted attributes allowed, e.g. ``studies.main``) is looked up on it.  ATTR must be
    an :class:`Experiment`, or a callable taking no arguments that returns one (it is called
    once per resolution).  It need not be registered.

    Every bad spec raises :class:`ConfigError` with a one-line message naming the module
    and/or attribute: an unknown registered name (listing the available ones), an empty
    module or attribute part, a module that does not exist, a module that raises ImportError
    or SyntaxError while importing (its one-line message), a missing attribute (listing the
    module's Experiment objects), and an object that is not an Experiment (naming its type).
    A ConfigError raised while importing the module or calling the factory propagates as
    is; any other exception from the user's code is a bug in it and propagates unchanged.
    A built-in (C) function is never called (``sys:exit``, ``os:abort`` are not
    experiments), and a factory that exits (raises SystemExit) is a ConfigError.
    """
    spec = str(spec)
    if spec in REGISTRY:
        return REGISTRY[spec]
    if ":" not in spec:
        available = ", ".join(sorted(REGISTRY)) or "(none)"
        raise ConfigError(f"unknown experiment {spec!r}; available: {available} "
                          f"(or MODULE:ATTR for an experiment in your own module)")
    module_name, _, attr = (part.strip() for part in spec.partition(":"))
    if not module_name:
        raise ConfigError(f"experiment {spec!r} has an empty module name; expected MODULE:ATTR")
    if not attr:
        raise ConfigError(f"experiment {spec!r} has an empty attribute name; expected MODULE:ATTR")
    module = _import_user_module(module_name, spec)
    obj = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ConfigError(f"module {module_name!r} has no attribute {attr!r}; "
                              f"{_experiments_in(module)}") from None
    if isinstance(obj, Experiment):
        return obj
    if not callable(obj):
        raise ConfigError(f"{spec!r} is of type {_type_name(obj)}, not an Experiment "
                          f"(or a zero-argument callable returning one)")
    if isinstance(obj, (types.BuiltinFunctionType, types.BuiltinMethodType)):
        raise ConfigError(f"{spec!r} is a built-in function, not an Experiment (or a zero-argument "
                          f"callable of yours returning one)")
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):             # no signature (some builtins): just call it
        signature = None
    if signature is not None:
        required = [p.name for p in signature.parameters.values()
                    if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        if required:
            raise ConfigError(f"{spec!r} is a callable that needs arguments ({', '.join(required)}); "
                              f"expected an Experiment or a zero-argument callable returning one")
    try:
        made = obj()
    except SystemExit as e:
        raise ConfigError(f"{spec!r} exited (SystemExit({e.code!r})) when called, instead of returning an "
                          f"Experiment") from None
    if not isinstance(made, Experiment):
        raise ConfigError(f"{spec!r} returned {_type_name(made)}, not an Experiment")
    return made


def _import_user_module(module_name: str, spec: str):
    """Import ``module_name`` for :func:`resolve_experiment`; ConfigError if that fails."""
    if module_name.startswith("."):
        raise ConfigError(f"experiment {spec!r}: module {module_name!r} is relative; "
                          f"give an absolute module name")
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    importlib.invalidate_caches()               # a module written since the last import
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        missing = e.name or ""
        if module_name == missing or module_name.startswith(missing + "."):
            hint = ""
            if module_name.endswith(".py") or "/" in module_name or "\\" in module_name:
                hint = "; give a module name (mymod, pkg.mod), not a file name"
            raise ConfigError(f"no module named {missing!r} (experiment {spec!r}; searched the "
                              f"current directory and sys.path){hint}") from None
        raise ConfigError(f"module {module_name!r} failed to import: {_one_line(e)}") from None
    except (ImportError, SyntaxError) as e:
        raise ConfigError(f"module {module_name!r} failed to import: {_one_line(e)}") from None


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _type_name(obj) -> str:
    """'int', 'NoneType', 'mymod.Thing': the type of ``obj`` for messages."""
    t = type(obj)
    return t.__qualname__ if t.__module__ == "builtins" else f"{t.__module__}.{t.__qualname__}"


def _experiments_in(module) -> str:
    names = sorted(k for k, v in vars(module).items() if isinstance(v, Experiment))
    if not names:
        return "it has no Experiment objects"
    return "Experiment objects in it: " + ", ".join(names)


def _load_source_tree_experiments() -> bool:
    """Running from a source checkout (not installed): load ``<repo>/experiments`` as
    ``jaxnc.experiments``, the mapping pyproject.toml gives it when installed."""
    root = pathlib.Path(__file__).resolve().parent.parent / "experiments"
    init = root / "__init__.py"
    if not init.is_file():
        return False
    spec = importlib.util.spec_from_file_location(
        "jaxnc.experiments", init, submodule_search_locations=[str(root)])
    if spec is None or spec.loader is None:
        return False
    module = importlib.util.module_from_spec(spec)
    sys.modules["jaxnc.experiments"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop("jaxnc.experiments", None)
        raise
    return True


def load_builtin() -> None:
    """Import ``jaxnc.experiments``, which registers the built-in experiments.

    When jaxnc is used from a source checkout without being installed, the top-level
    ``experiments/`` directory next to the package is loaded under that name instead.  If
    neither exists, nothing is registered.  If an experiment module fails to import
    (ImportError), a RuntimeWarning names the problem and this returns without raising.
    Importing is done once per process (later calls are no-ops).
    """
    try:
        try:
            importlib.import_module("jaxnc.experiments")
        except ModuleNotFoundError as e:
            if e.name != "jaxnc.experiments":
                raise
            _load_source_tree_experiments()
    except ImportError as e:
        warnings.warn(f"built-in experiments not loaded: {e}", RuntimeWarning, stacklevel=2)
