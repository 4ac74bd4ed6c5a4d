"""JAX's persistent compilation cache for jaxnc's command line and test suite.

A closed loop compiles to a large program (tens of seconds for the seed-000 grid's
programs on one core); with the cache on, a second run of the same program on the same
machine loads it from disk instead. The cache lives in ``$JAXNC_CACHE_DIR`` if set, else
``$XDG_CACHE_HOME/jaxnc/xla``, else ``~/.cache/jaxnc/xla``; every program is written
(``min_compile_time_s`` = 0 by default), the small eager ones too, so a second run of a
study compiles nothing. Entries are keyed by the program,
the JAX version and the backend, so a stale entry is never used for another program.
"""
from __future__ import annotations

import os
import pathlib
from typing import NamedTuple

__all__ = ["default_cache_dir", "user_cache_root", "enable_cache", "cache_beside", "allow_cache_beside", "CompileClock",
           "compile_clock"]

_BESIDE = [True]

# lowering to MLIR and XLA's compilation (tracing is left out: a jit traced inside another's
# trace reports its own duration too, so trace durations nest and would be counted twice)
_LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_COMPILE = "/jax/core/compile/backend_compile_duration"
_CLOCK = {"seconds": 0.0, "compilations": 0, "registered": False}


class CompileClock(NamedTuple):
    """This process's running totals since :func:`compile_clock` was first called:
    seconds spent lowering and compiling, and the number of programs compiled by XLA (a
    program loaded from the persistent cache counts too, with its load time). Subtract two
    readings for the part between them."""
    seconds: float
    compilations: int

    def __sub__(self, other):
        return CompileClock(self.seconds - other.seconds, self.compilations - other.compilations)


def _listen(name, secs, **kw):
    if name == _COMPILE:
        _CLOCK["seconds"] += secs
        _CLOCK["compilations"] += 1
    elif name == _LOWER:
        _CLOCK["seconds"] += secs


def compile_clock() -> CompileClock:
    """The compile clock's reading (:class:`CompileClock`), from ``jax.monitoring``'s
    lowering and backend-compile duration events; the first call registers the listener
    (compilations before it are not counted). Every thread's compilations count."""
    if not _CLOCK["registered"]:
        import jax.monitoring
        jax.monitoring.register_event_duration_secs_listener(_listen)
        _CLOCK["registered"] = True
    return CompileClock(_CLOCK["seconds"], _CLOCK["compilations"])


def default_cache_dir() -> pathlib.Path:
    """The cache folder (module docstring)."""
    if os.environ.get("JAXNC_CACHE_DIR"):
        return pathlib.Path(os.environ["JAXNC_CACHE_DIR"]).expanduser()
    return user_cache_root() / "xla"


def user_cache_root() -> pathlib.Path:
    """jaxnc's folder of the user's cache: ``$XDG_CACHE_HOME/jaxnc``, else ``~/.cache/jaxnc``
    (the compilation cache's default ``xla`` and :func:`jaxnc.sweep.code_fingerprint`'s
    ``code`` lie in it)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "jaxnc"


def enable_cache(path=None, *, min_compile_time_s: float = 0.0) -> pathlib.Path:
    """Turn JAX's persistent compilation cache on in ``path`` (default
    :func:`default_cache_dir`), creating it; returns the folder. Raises OSError when the
    folder cannot be created."""
    import jax
    path = pathlib.Path(path).expanduser() if path is not None else default_cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def cache_beside(out) -> None:
    """Keep compiled programs in ``out/.xla_cache`` when no cache folder is configured
    yet (the CLI's cache, ``--cache-dir`` or the test suite's take precedence), so a
    resumed study does not compile again. Only the folder is set (JAX's own minimum
    compile time applies). Nothing is set after ``allow_cache_beside(False)`` (``jaxnc
    run --no-cache``)."""
    import jax
    if _BESIDE[0] and jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", str((pathlib.Path(out) / ".xla_cache").resolve()))


def allow_cache_beside(allowed: bool) -> None:
    """Whether :func:`cache_beside` may keep compiled programs beside the results (the
    command line sets it from ``--no-cache`` for each run)."""
    _BESIDE[0] = bool(allowed)
