"""Experiment registry and ``KEY=VALUE`` option parsing for the command line.

An :class:`Experiment` names a study, declares its settings as :class:`Option` s (type,
default, bounds) and provides ``run(settings, *, seeds, out, progress) -> dict``.  Modules in
``jaxnc.experiments`` call :func:`register` at import time; :func:`load_builtin` imports them.
Every bad user setting raises :class:`ConfigError` with a one-line message naming the key and
the allowed values, which the CLI prints as ``jaxnc: error: <message>``.

This module does not import jax, so ``jaxnc --help`` / ``--version`` stay fast.
"""
from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import math
import pathlib
import sys
import warnings
from typing import Callable

__all__ = ["ConfigError", "Option", "Experiment", "REGISTRY", "register", "get_experiment",
           "load_builtin", "KINDS"]

KINDS = ("int", "float", "choice", "floats", "ints", "bool")
_TRUE = ("true", "yes", "on", "1")
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
        try:
            x = float(item)
        except ValueError:
            raise self._error(text) from None
        if not math.isfinite(x) or not self._in_range(x):
            raise self._error(text)
        return x

    def parse(self, text: str) -> object:
        """Parse the command-line text of this option; :class:`ConfigError` if invalid."""
        s = str(text).strip()
        if self.kind == "int":
            try:
                x = int(s, 10)
            except ValueError:
                raise self._error(text) from None
            if not self._in_range(x):
                raise self._error(text)
            return x
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
            out = []
            for p in items:
                try:
                    x = int(p, 10)
                except ValueError:
                    raise self._error(text) from None
                if not self._in_range(x):
                    raise self._error(text)
                out.append(x)
            return tuple(out)
        if self.kind == "bool":
            low = s.lower()
            if low in _TRUE:
                return True
            if low in _FALSE:
                return False
            raise self._error(text)
        # choice: exact match first, then a unique case-insensitive match
        for c in self.choices:
            if s == str(c):
                return c
        folded = [c for c in self.choices if str(c).lower() == s.lower()]
        if len(folded) == 1:
            return folded[0]
        raise self._error(text)


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A registered study.

    ``run(settings, *, seeds, out, progress) -> dict`` receives the parsed settings (every
    option's default, updated by the user's ``KEY=VALUE`` pairs), the number of Monte-Carlo
    seeds, the output directory (already created) and whether to show progress bars; it
    prints its own table, writes its own files and returns the results.  ``check(settings)``,
    if given, validates combinations of options (raising :class:`ConfigError`) when the
    settings are parsed, before anything is built.
    """
    name: str
    description: str
    options: tuple[Option, ...]
    run: Callable[..., dict]
    check: Callable[[dict], None] | None = None

    def __post_init__(self):
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
        """``["KEY=VALUE", ...]`` -> the defaults updated (later pairs win)."""
        settings = self.defaults()
        for pair in pairs or ():
            key, sep, value = str(pair).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ConfigError(f"malformed setting {pair!r}: expected KEY=VALUE")
            opt = self.option(key)
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
    """The registered experiment ``name``; :class:`ConfigError` listing the available ones."""
    try:
        return REGISTRY[name]
    except KeyError:
        available = ", ".join(sorted(REGISTRY)) or "(none)"
        raise ConfigError(f"unknown experiment {name!r}; available: {available}") from None


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
