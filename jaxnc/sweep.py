"""Sweeps whose cells are spread over processes, machines or a job array (``--shard I/N``).

A sweep experiment (``mecanum-grid``, ``hdd-gpi``, ``diffdrive-sensitivity``) is a list
of cells, each computed independently and stored as its own file in the output folder
as soon as it is done (atomically: a cell file is complete or absent). Shard ``I`` of
``N`` computes only its share of the list (:meth:`Shard.share`: the ``I``-th of ``N``
contiguous blocks, so that cells sharing a compiled program stay together); whichever
run finds every cell present -- a shard, or a run without ``--shard`` (which computes
whatever is missing) -- assembles the tables from the cell files, under a lock
(:func:`assembly_lock`), so the tables are the same bytes however the cells were
computed. A cell file is named by everything that makes it: a readable name and a
hash of its whole configuration (:func:`cell_path`), so two cells whose settings differ
anywhere (``dp=0.1`` and ``dp=0.104``, another ``sigma``, other seeds) are two files and
never overwrite each other; a cell file whose configuration differs from the current
run's is not used. The code that computes a cell is part of what makes it: the name's hash
and the stored record include :func:`code_fingerprint` (jaxnc's own code, its experiments,
the JAX and jaxlib versions), so a cell computed by other library code -- an upgrade, a fix,
a local edit -- is another file and is computed again, never reused.

This module does not import jax.
"""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import pathlib
import re
import sys
from typing import Callable, Iterator, Sequence

__all__ = ["Shard", "parse_shard", "config_hash", "code_fingerprint", "cell_path", "load_cell", "save_cell",
           "missing_report", "assembly_lock", "folder_lock"]

_SHARD_RE = re.compile(r"\s*([0-9]+)\s*/\s*([0-9]+)\s*\Z")


@dataclasses.dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count`` (0 <= index < count)."""
    index: int
    count: int

    def __post_init__(self):
        for name in ("index", "count"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f"Shard: {name} must be an integer, got {v!r}")
        if self.count < 1 or not 0 <= self.index < self.count:
            raise ValueError(f"Shard: need 0 <= index < count, got {self.index}/{self.count}")

    def share(self, cells: Sequence) -> list:
        """This shard's cells: block ``index`` of ``count`` contiguous blocks of ``cells``
        (sizes differ by at most one; the blocks cover every cell exactly once)."""
        n = len(cells)
        return list(cells[self.index * n // self.count:(self.index + 1) * n // self.count])

    def owner(self, position: int, n: int) -> int:
        """The shard (of ``count``) whose share holds cell ``position`` of ``n``."""
        return next(i for i in range(self.count) if (i + 1) * n // self.count > position)

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text) -> Shard:
    """``"I/N"`` -> :class:`Shard`; ValueError (one line, naming ``--shard`` and the
    allowed values) unless I and N are integers with 0 <= I < N."""
    m = _SHARD_RE.match(str(text))
    if m is not None:
        i, n = int(m.group(1)), int(m.group(2))
        if n >= 1 and i < n:
            return Shard(i, n)
    raise ValueError(f"--shard must be I/N with integers 0 <= I < N (shard I of N, e.g. 0/4), got {str(text)!r}")


def config_hash(config, length: int = 12) -> str:
    """A hex digest (``length`` characters of SHA-256) of ``config`` as JSON with sorted
    keys: equal for equal configurations (tuples and lists alike), different as soon as
    any value differs (``0.1`` and ``0.104``, ``1`` and ``1.0`` included)."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=_json_default)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:length]


def _json_default(v):
    """numpy scalars and arrays in a configuration, as JSON values."""
    if hasattr(v, "tolist"):
        return v.tolist()
    raise TypeError(f"config_hash: a configuration value of type {type(v).__name__} is not JSON")


def _package_sources(root: pathlib.Path) -> tuple:
    """``((name, bytes), ...)``: every Python file of the package at ``root``, named by its path
    in it (``jaxnc/loop/runner.py``), ``jaxnc.experiments`` included (installed in the package,
    or beside it as ``experiments/`` in a source checkout, as ``experiment.load_builtin`` finds it)."""
    trees = [("jaxnc", root)]
    beside = root.parent / "experiments"
    if not (root / "experiments").exists() and (beside / "__init__.py").is_file():
        trees.append(("jaxnc/experiments", beside))
    files, seen = [], set()
    for prefix, top in trees:
        for d, dirs, names in os.walk(top, followlinks=True):
            dirs[:] = sorted(x for x in dirs if x != "__pycache__")
            for n in sorted(names):
                f = pathlib.Path(d, n)
                if n.endswith(".py") and f.resolve() not in seen:
                    seen.add(f.resolve())
                    files.append((f"{prefix}/{f.relative_to(top).as_posix()}", f.read_bytes()))
    return tuple(sorted(files))


#: the package's files as this process imported it (about 1 MB, read in milliseconds): what
#: :func:`code_fingerprint` hashes, not the files as they may have been edited since
_IMPORTED_SOURCES = _package_sources(pathlib.Path(__file__).resolve().parent)


@functools.lru_cache(maxsize=None)
def code_fingerprint() -> str:
    """A hex digest (16 characters of SHA-256) of the code that computes a cell: every Python
    file of the ``jaxnc`` package (``jaxnc.experiments`` included) as this process imported
    it, each by its path in the package and its syntax tree without docstrings (comments, blank
    lines and docstrings do not count; any change to the code does), and the installed ``jax``
    and ``jaxlib`` versions (XLA's rounding).

    A cell's configuration names the loop and the settings (:func:`jaxnc.results.config_of`
    describes a user's own functions and part classes) but not the library code they run on:
    without this a cell stored by another jaxnc -- before an upgrade or a fix, or by a shard
    on another checkout -- would be reused with its old numbers (:func:`cell_path`,
    :func:`load_cell`). Computed once per process; parsing the files takes about a second,
    so the digest is also kept in a small file (``~/.cache/jaxnc/code/``, or under
    ``$XDG_CACHE_HOME``), named by a hash of the
    files' exact bytes, the Python version (its syntax trees) and the two versions: a process
    whose files are byte for byte the same reads it instead of parsing (a file that is
    missing, unreadable or not a digest is ignored and the digest computed)."""
    versions = b"".join(f"{dist}=={_dist_version(dist)}\0".encode() for dist in ("jax", "jaxlib"))
    raw = hashlib.sha256(f"{sys.version_info[:2]}\0".encode() + versions)
    for name, source in _IMPORTED_SOURCES:
        raw.update(name.encode() + b"\0" + hashlib.sha256(source).digest())
    from jaxnc.cache import user_cache_root
    memo = user_cache_root() / "code" / raw.hexdigest()[:32]
    try:
        known = memo.read_text().strip()
        if len(known) == 16 and all(c in "0123456789abcdef" for c in known):
            return known
    except (OSError, UnicodeDecodeError):
        pass
    h = hashlib.sha256()
    for name, source in _IMPORTED_SOURCES:
        h.update(name.encode() + b"\0" + _code_text(source) + b"\0")
    h.update(versions)
    digest = h.hexdigest()[:16]
    try:                                  # atomically: a reader sees a whole digest or no file
        memo.parent.mkdir(parents=True, exist_ok=True)
        tmp = memo.with_name(f"{memo.name}.{os.getpid()}.tmp")
        tmp.write_text(digest)
        os.replace(tmp, memo)
    except OSError:
        pass
    return digest


def _dist_version(dist: str) -> str:
    """The installed version of the distribution ``dist``, ``"none"`` when it is not installed."""
    from importlib import metadata
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "none"


def _code_text(source: bytes) -> bytes:
    """A module's syntax tree without docstrings, as text (its bytes when it does not parse)."""
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return source
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree).encode()


def cell_path(folder, name: str, config: dict, suffix: str = ".json") -> pathlib.Path:
    """``folder/<name>-<hash><suffix>``: the file of the cell that ``config`` makes with this
    code, ``name`` being its readable part (e.g. ``N02_DRH_dp0.1``); the hash is
    :func:`config_hash` of ``config`` and :func:`code_fingerprint` together, so another
    configuration or other library code names another file."""
    if not name or "/" in name or "\\" in name:
        raise ValueError(f"cell_path: name must be a non-empty file name, got {name!r}")
    return pathlib.Path(folder) / f"{name}-{config_hash({'config': config, 'code': code_fingerprint()})}{suffix}"


def load_cell(f, config: dict, *, defaults: dict | None = None) -> dict | None:
    """The record stored in cell file ``f`` (JSON) if its ``"config"`` equals ``config`` and
    its ``"code"`` is this process's :func:`code_fingerprint`; None when the file is missing,
    damaged, or was computed with another configuration or by other code (a file without
    ``"code"``, written before it was stored, is not reused either). ``defaults`` fill
    configuration keys that older files lack."""
    try:
        with open(f, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    stored = data.get("config")
    if not isinstance(stored, dict) or data.get("code") != code_fingerprint():
        return None
    stored = {**(defaults or {}), **stored}
    # tuples as the lists JSON stores, numpy values as their numbers
    return data if stored == json.loads(json.dumps(config, default=_json_default)) else None


def save_cell(f, record: dict, arrays: dict | None = None) -> None:
    """Write cell file ``f`` (``record`` as JSON, numpy values as their numbers, with its
    ``"config"``, and ``"code"``: the :func:`code_fingerprint` that :func:`load_cell` checks),
    atomically; ``arrays``
    (per-seed metrics) go first to ``f`` with the suffix ``.npz``, so a cell whose JSON
    exists always has its arrays."""
    import numpy as np
    from jaxnc.montecarlo import atomic_write
    f = pathlib.Path(f)
    if arrays is not None:
        atomic_write(f.with_suffix(".npz"), lambda fh: np.savez_compressed(fh, **arrays))
    # inf/nan as JSON's Infinity/NaN (read back by json)
    text = json.dumps({**record, "code": code_fingerprint()}, indent=1, default=_json_default)
    atomic_write(f, lambda fh: fh.write(text.encode("utf-8")))


def missing_report(cells: Sequence, missing: Sequence, shard: Shard | None, describe: Callable = str,
                   command_hint: str = "the same command without --shard") -> str:
    """One paragraph for a run that ends with cells still missing: how many, which
    shards owe them, a few by name, and how the tables get written."""
    pos = {c: i for i, c in enumerate(cells)}
    head = f"{len(missing)} of {len(cells)} cells are missing"
    if shard is not None:
        owners = sorted({shard.owner(pos[c], len(cells)) for c in missing})
        k = len(shard.share(cells))
        head = (f"shard {shard} has done its share ({k} cell{'' if k == 1 else 's'}); {head} (shard"
                f"{'s' if len(owners) > 1 else ''} {', '.join(f'{i}/{shard.count}' for i in owners)})")
    some = "; ".join(describe(c) for c in missing[:4]) + ("; ..." if len(missing) > 4 else "")
    return (f"{head}: {some}. The tables are written by the run that finds every cell present: "
            f"run the missing shards, or {command_hint}, which computes what is missing.")


@contextlib.contextmanager
def assembly_lock(folder) -> Iterator[None]:
    """Hold an exclusive lock on ``folder/.assemble.lock`` (:func:`folder_lock`, waiting for
    it), so two shards finishing together write the tables one after the other, never
    interleaved."""
    with folder_lock(folder, ".assemble.lock"):
        yield


@contextlib.contextmanager
def folder_lock(folder, name: str | None = None, *, wait: bool = True) -> Iterator[None]:
    """Hold an exclusive lock on ``folder/name``, or on the folder itself when ``name`` is
    None (nothing is written in it) (``fcntl.flock``, released when the block ends or the
    process dies; no lock where fcntl does not exist). ``wait=False``: raise
    :class:`BlockingIOError` at once when another process (or another open of the file)
    holds it."""
    import os
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:                      # not POSIX
        yield
        return
    if name is None:
        fd = os.open(folder, os.O_RDONLY)
    else:
        fd = os.open(folder / name, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
