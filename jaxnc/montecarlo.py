"""Monte-Carlo engine: per-seed keys, chunked ``jit(vmap(fn))`` over seeds, statistics, results files.

One closed-loop run is a pure function ``fn(key) -> pytree of arrays``; a Monte-Carlo study
is that function mapped over many seeds.  The pieces here are deliberately small:

* :func:`seed_keys` gives seed ``i`` the key ``fold_in(PRNGKey(seed), i)``, so a seed's
  trajectory never depends on how many seeds are run or how they are batched;
* :func:`run_batched` maps ``fn`` over the keys in fixed-size chunks (one compilation,
  bounded memory), sharded over the local devices and, after
  ``jax.distributed.initialize()``, split over the processes, and returns numpy arrays;
* :func:`precompile` compiles the programs of several such runs ahead, in threads, while
  the caller traces the next program or does its own work;
* :func:`summarize` reduces one metric to mean / 95 % interval over the *stable* runs,
  reporting the unstable ones as a fraction (an unstable run is data, not an error);
* :func:`save_results` / :func:`load_results` write and read the JSON results file
  atomically, with ``inf``/``nan`` stored as strings (JSON has no infinities).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import io
import json
import math
import os
import pathlib
import platform as _platform
import re
import sys
import tempfile
import time
import weakref
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxnc import __version__
from jaxnc.sweep import code_fingerprint

__all__ = ["seed_keys", "seed_sharding", "run_batched", "precompile", "Summary", "summarize", "mean_ci", "seeds_for_normal_interval",
           "seeds_for_paired_interval", "describe", "save_results", "load_results",
           "atomic_write", "MemoryBudgetError", "available_memory", "check_seed_memory", "chunk_lanes", "CHUNK_MEMORY",
           "stored_or_run", "stored_study", "uniform_dtypes", "stale_temporaries"]


# ----------------------------------------------------------------------------- memory

#: host bytes per seed of a key array: the uint32 index and the two uint32 words of its key
KEY_BYTES = 12
#: host bytes per lane of a chunk besides its outputs: the padding index (int64) and the
#: chunk's keys on the host and on the device
LANE_BYTES = 24
#: at most this many bytes of keys and outputs per chunk (:func:`run_batched`)
CHUNK_MEMORY = 1 << 30


class MemoryBudgetError(ValueError):
    """A run whose seeds cannot fit in the memory available; raised before anything is
    allocated or simulated (the command line reports it as a bad ``--seeds``)."""


def available_memory() -> int | None:
    """Bytes of memory available to new allocations (``MemAvailable`` of /proc/meminfo,
    else the free physical pages); None where the system does not say."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check_seed_memory(n: int, per_seed_bytes: int = KEY_BYTES, *, what: str = "the keys of") -> None:
    """Raise :class:`MemoryBudgetError` when ``n`` seeds of ``per_seed_bytes`` bytes each
    need more memory than :func:`available_memory` (no check where it is unknown)."""
    need = int(n) * int(per_seed_bytes)
    free = available_memory()
    if free is not None and need > free:
        raise MemoryBudgetError(f"{what} {n} seeds need {_gib(need)} ({per_seed_bytes} bytes per seed), more than "
                                f"the {_gib(free)} of memory available; at most {max(free // per_seed_bytes, 0)} "
                                f"seeds fit: run fewer seeds")


# ----------------------------------------------------------------------------- keys


def seed_keys(seed: int, n: int, start: int = 0) -> jax.Array:
    """Keys for seeds ``start .. start + n - 1``, shape ``(n, 2)`` (raw ``uint32`` keys).

    Seed ``i`` gets ``jax.random.fold_in(jax.random.PRNGKey(seed), i)``: it depends only on
    ``(seed, i)``, never on ``n`` or ``start``, so ``seed_keys(s, 10)[7]`` and
    ``seed_keys(s, 5, start=5)[2]`` are bitwise the same key and a seed's trajectory is the
    same whatever the batch it runs in.

    Raises :class:`MemoryBudgetError` (before allocating) when the ``n`` keys
    (:data:`KEY_BYTES` each) need more memory than is available.
    """
    for name, v in (("seed", seed), ("n", n), ("start", start)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"seed_keys: {name} must be an integer, got {v!r}")
    seed, n, start = int(seed), int(n), int(start)
    if not 0 <= seed < 2**32:
        # PRNGKey keeps 32 bits of a seed in this range: 2**32 would give seed 0's keys
        raise ValueError(f"seed_keys: seed must be in [0, {2**32 - 1}], got {seed}")
    if n < 0 or start < 0:
        raise ValueError(f"seed_keys: n and start must be >= 0, got n={n}, start={start}")
    if start + n > 2**32:
        raise ValueError(f"seed_keys: seed indices must fit in uint32, got start+n={start + n}")
    check_seed_memory(n, KEY_BYTES, what="seed_keys: the keys of")
    # whole blocks from one compiled program, joined and cut on the host: a program per n
    # cost a compilation for every batch size a study used
    blocks = [np.asarray(_key_block(np.uint32(seed), np.uint32(start + b))) for b in range(0, n, KEY_BLOCK)]
    keys = np.concatenate(blocks)[:n] if blocks else np.zeros((0, 2), np.uint32)
    return jax.device_put(keys)         # (jnp.asarray compiles a program per shape)


#: seeds whose keys :func:`seed_keys` makes in one call of its compiled program
KEY_BLOCK = 4096


@jax.jit
def _key_block(seed, start):
    """The keys of seeds start .. start + KEY_BLOCK - 1 (uint32 arithmetic: past 2**32 they
    wrap, and seed_keys never returns those)."""
    base = jax.random.PRNGKey(seed)
    idx = start + jnp.arange(KEY_BLOCK, dtype=jnp.uint32)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(idx)


# ----------------------------------------------------------------------------- batched runs

#: seeds per vector group: chunks are padded to a multiple of this per device (16 float32
#: lanes of a 512-bit vector unit; a multiple of the narrower units' widths too)
LANES = 16

def _out_bytes(batched: Callable, keys, args: tuple, size: int) -> int:
    """Bytes of one key's outputs, from the shapes of a chunk of ``size`` lanes (the jitted
    function's ``eval_shape``: traced, not run; the trace is the one the call reuses)."""
    spec = jax.ShapeDtypeStruct((size, *keys.shape[1:]), keys.dtype)
    shapes = batched.eval_shape(spec, args)
    return sum(int(np.prod(x.shape[1:])) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(shapes))


def chunk_lanes(chunk_size: int, n: int, out_bytes: int, devices: int = 1) -> int:
    """Lanes per compiled chunk of :func:`run_batched`: ``chunk_size`` rounded up to a
    multiple of :data:`LANES` x ``devices``; when that many lanes would hold more than
    :data:`CHUNK_MEMORY` bytes of keys and outputs (``LANE_BYTES + out_bytes`` per
    lane), the smaller of the seeds ``n`` and the lanes that fit, rounded the same way
    (at least one group)."""
    group = LANES * devices
    size = -(-chunk_size // group) * group
    per_lane = LANE_BYTES + int(out_bytes)
    if size * per_lane > CHUNK_MEMORY:
        fit = max(group, CHUNK_MEMORY // per_lane // group * group)
        size = min(-(-max(n, 1) // group) * group, fit)
    return size


# fn -> jit(vmap(fn)).  Weak keys so that a throw-away lambda (e.g. one per configuration)
# and everything it closes over can be freed; the compiled wrapper reaches fn only through
# a weak reference, otherwise the value would keep its own key alive.
_COMPILED: "weakref.WeakKeyDictionary[Callable, Callable]" = weakref.WeakKeyDictionary()


def _compiled(fn: Callable) -> Callable:
    try:
        ref = weakref.ref(fn)
        return _COMPILED[fn]
    except KeyError:
        pass
    except TypeError:                       # not hashable / not weak-referenceable: no cache
        return jax.jit(jax.vmap(lambda key, args: fn(key, *args), in_axes=(0, None)))

    def call(key, args):
        f = ref()
        if f is None:                       # cannot happen while a caller holds fn
            raise RuntimeError("run_batched: the mapped function was garbage-collected")
        return f(key, *args)

    compiled = jax.jit(jax.vmap(call, in_axes=(0, None)))
    _COMPILED[fn] = compiled
    return compiled


def _to_numpy(tree, keep: int):
    """Device pytree -> numpy pytree, first ``keep`` rows (drops the padding)."""
    tree = jax.device_get(tree)
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:keep], tree)


def seed_sharding(devices=None) -> jax.sharding.NamedSharding:
    """The sharding :func:`run_batched` gives a chunk of seeds: split along its leading
    (seed) axis over ``devices`` (default: all of them), a one-axis mesh named "seeds".
    Its ``.mesh`` with ``PartitionSpec()`` replicates an argument over the same devices."""
    devices = jax.devices() if devices is None else list(devices)
    mesh = jax.sharding.Mesh(np.asarray(devices), ("seeds",))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seeds"))


def run_batched(fn: Callable[..., Any], keys: jax.Array, *, args: tuple = (), chunk_size: int = 256,
                progress: bool = True, desc: str = "seeds"):
    """Apply ``fn`` (key -> pytree of arrays) to every key; returns the pytree of numpy arrays.

    ``args`` (a tuple of pytrees) are passed after the key, ``fn(key, *args)``, as
    arguments of the compiled function, shared by all keys (not batched): calls with
    different values of the same structure and shapes (e.g. another scheme or dropout
    probability of one configuration type) reuse one compiled program.

    ``jax.jit(jax.vmap(fn))`` runs on chunks of exactly ``chunk_size`` keys, which
    bounds device memory; the last chunk is padded to the same size by repeating its last
    key, so every chunk reuses the one compiled function, and the padding is dropped.  The
    outputs are moved to host memory chunk by chunk (the next chunk is dispatched before the
    previous one is fetched, so the device stays busy) and concatenated along axis 0: leaf
    ``x`` of ``fn``'s output becomes an array of shape ``(len(keys), *x.shape)``.

    Row ``i`` of the result depends only on ``keys[i]`` and ``chunk_size``, not on the other
    keys, on how many there are or on its lane in the chunk: with the same ``chunk_size``
    (and devices) a seed is bit-identical alone or in any batch (tested at the first, a
    middle and the last lane, for chunk sizes that are and are not multiples of
    :data:`LANES`). ``chunk_size`` is rounded up to a multiple of :data:`LANES` per device
    (the compiler vectorises a batched loop that many lanes at a time and computes a
    remainder with other code).

    **Memory.** A chunk whose lanes would hold more than :data:`CHUNK_MEMORY` bytes of
    keys and outputs is capped at the number of seeds and at that budget
    (:func:`chunk_lanes`; the outputs' size comes from ``jax.eval_shape``, before
    anything runs): ``chunk_size=2e8`` with 4 seeds runs one chunk of 16 lanes. Within
    the budget ``chunk_size`` is used as given, so the bit-identity above holds for every
    chunk size below it. The whole result (``len(keys)`` times the outputs of one key,
    twice while the chunks are joined) must fit in the memory available:
    :class:`MemoryBudgetError` before the first chunk otherwise.

    **Several devices.** With more than one local device (GPUs, or CPU devices from
    ``jax.config.update("jax_num_cpu_devices", n)`` / ``jaxnc run --cpu-devices n``) each
    chunk is sharded over them along the seed axis (``jax.sharding``, ``args``
    replicated); ``chunk_size`` is rounded up to a multiple of the device count (times :data:`LANES`).

    **Several processes.** After ``jax.distributed.initialize()`` (``jaxnc run
    --distributed``) every process calls ``run_batched`` with the same ``fn``, keys and
    ``args`` (as any multi-controller JAX program does); process ``p`` of ``P`` runs the
    ``p``-th of ``P`` contiguous blocks of the keys on its own local devices, exactly as
    above, and the blocks are gathered (``multihost_utils.process_allgather``) so that
    *every* process returns the full result. A seed's row is the one a single process
    with as many devices as each process has local ones computes (bit for bit: tested
    with two CPU processes of one device against one process).

    The compiled function is cached per ``fn`` object (weakly), so calling again with
    the same ``fn`` and chunk size does not recompile; :func:`precompile` fills that cache
    ahead (a call whose program it is still compiling waits for it).  ``progress`` shows a tqdm bar
    over seeds (on stderr) labelled ``desc``; with several processes only process 0
    shows it, over its own block.
    """
    _check_call("run_batched", fn, args)
    keys, chunk_size = _checked("run_batched", keys, chunk_size)
    batched = _compiled(fn)
    n = int(keys.shape[0])
    out_bytes = _chunk_out_bytes(batched, keys, args, chunk_size) if n else 0
    check_seed_memory(n, 2 * out_bytes, what="run_batched: the results of")
    if jax.process_count() > 1:
        return _run_processes(batched, keys, args, chunk_size, progress, desc, out_bytes)
    return _run_local(batched, keys, args, chunk_size, progress, desc, out_bytes)


def _checked(who: str, keys, chunk_size):
    """``(keys as a jax array, chunk_size as an int)``; ValueError naming ``who`` when either is not
    what :func:`run_batched` takes."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"{who}: chunk_size must be an integer >= 1, got {chunk_size!r}")
    keys = jnp.asarray(keys) if not isinstance(keys, jax.Array) else keys
    if jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key):
        if keys.ndim != 1:
            raise ValueError(f"{who}: typed keys must be a 1-D array of keys, got shape {keys.shape}")
    elif keys.dtype != jnp.uint32 or keys.ndim != 2 or keys.shape[1] != 2:
        raise ValueError(f"{who}: keys must be raw uint32 keys of shape (n, 2) (from seed_keys) or a 1-D "
                         f"array of typed keys, got {keys.dtype} of shape {keys.shape}")
    return keys, int(chunk_size)


def _check_call(who: str, fn, args) -> None:
    """ValueError naming ``who`` when ``fn`` is not callable or ``args`` not a tuple."""
    if not callable(fn):
        raise ValueError(f"{who}: fn must be a function fn(key, *args), got {type(fn).__name__}")
    if not isinstance(args, tuple):
        raise ValueError(f"{who}: args must be a tuple (of fn's extra arguments), got {type(args).__name__}")


def _chunk_out_bytes(batched, keys, args, chunk_size: int) -> int:
    """:func:`_out_bytes` of a chunk of ``chunk_size`` lanes rounded up as :func:`chunk_lanes` rounds them."""
    group = LANES * len(jax.local_devices())
    return _out_bytes(batched, keys, args, -(-chunk_size // group) * group)


def _default_workers() -> int:
    """Half the processors this process may run on, at least 1 (XLA:CPU compiles one program
    on two threads much of the time)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return max(1, cpus // 2)


#: compilations :func:`precompile` (``wait=False``) handed to its threads and not yet waited
#: for, by the program's :func:`_signature`
_IN_FLIGHT: dict = {}


def _signature(batched, chunk, args) -> tuple:
    """What tells the programs of one compiled function apart: the structure, shapes and dtypes of
    its arguments (a chunk of keys and ``args``)."""
    leaves, tree = jax.tree_util.tree_flatten((chunk, args))
    return id(batched), tree, tuple(jax.typeof(x) for x in leaves)


def _wait_in_flight(sig=None) -> None:
    """Wait for the compilation of the program ``sig`` if :func:`precompile` left it in flight
    (None: for every one); raise its error."""
    for key in ([sig] if sig is not None else list(_IN_FLIGHT)):
        job = _IN_FLIGHT.pop(key, None)
        if job is not None:
            job.result()


def precompile(calls, keys: jax.Array, *, chunk_size: int = 256, workers: int | None = None,
               wait: bool = True) -> int:
    """Compile ahead, side by side, the programs that ``run_batched(fn, keys, args=args,
    chunk_size=chunk_size)`` will run for each ``(fn, args)`` of ``calls``; returns the number
    of distinct programs (one already compiled by an earlier call is counted, not compiled again).

    Each program is traced and lowered in this thread, in the order of ``calls``, and handed
    at once to a pool of ``workers`` threads (default: half the processors this process may
    run on, at least one, since XLA:CPU compiles one program on two threads much of the time)
    that compile it with XLA, which releases Python's lock while it compiles: the next
    program is traced while the previous ones compile, and with enough cores a cold run of
    several programs takes about the time of its longest compilation instead of the sum.
    Calls that :func:`run_batched` would run through one program (the same ``fn`` with
    ``args`` of one structure, shapes and dtypes: :func:`uniform_dtypes`) compile it once.
    Returns once every program is compiled (``wait=False``: once every program is lowered
    and handed to the threads, so that the caller's own work, and the runs of the programs
    compiled first, overlap the later compilations: a :func:`run_batched` call waits for its
    own program's compilation, and raises its error; the next :func:`precompile` call waits
    for all of them). Nothing is run.

    The programs land where :func:`run_batched` looks for them (its per-``fn`` compiled
    function; with the persistent compilation cache on, a program found there is loaded
    instead of compiled, and a compiled one is written there), so the ``run_batched`` calls
    that follow compile nothing and run the very programs they would have compiled
    themselves: their results are bit for bit the same. ``fn`` must be an object
    :func:`run_batched` caches (a function or lambda, not e.g. a ``functools.partial``,
    which it compiles afresh on every call). After ``jax.distributed.initialize()``
    (several processes) nothing is compiled ahead and 0 is returned; the runs compile as
    before. No keys (``len(keys) == 0``): nothing to compile, 0.

    Raises:
      ValueError: as :func:`run_batched` for ``keys``, ``chunk_size``, a call's ``fn`` or
        ``args``; for ``calls`` not made of ``(fn, args)`` pairs, or ``workers`` < 1.
    """
    _wait_in_flight()
    keys, chunk_size = _checked("precompile", keys, chunk_size)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer))
                                or workers < 1):
        raise ValueError(f"precompile: workers must be an integer >= 1 or None, got {workers!r}")
    pairs = []
    for call in calls:
        if not isinstance(call, (tuple, list)) or len(call) != 2:
            raise ValueError(f"precompile: each call must be a pair (fn, args), got {call!r:.80}")
        _check_call("precompile", *call)
        pairs.append(tuple(call))
    if int(keys.shape[0]) == 0 or jax.process_count() > 1 or not pairs:
        return 0
    from concurrent.futures import ThreadPoolExecutor
    seen = set()
    pool = ThreadPoolExecutor(max_workers=min(workers or _default_workers(), len(pairs)))
    try:
        for fn, args in pairs:
            batched = _compiled(fn)
            out_bytes = _chunk_out_bytes(batched, keys, args, chunk_size)
            _, _, placed, chunk_at = _chunks(keys, args, chunk_size, out_bytes)
            chunk = chunk_at(0)
            sig = _signature(batched, chunk, placed)
            if sig not in seen:
                seen.add(sig)
                _IN_FLIGHT[sig] = pool.submit(batched.lower(chunk, placed).compile)
    finally:
        pool.shutdown(wait=False)               # the threads end with their last compilation
    if wait:
        _wait_in_flight()
    return len(seen)


def uniform_dtypes(config):
    """``config`` with every floating leaf as float32 and every integer leaf as int32 (numpy
    arrays; booleans and other leaves unchanged).

    Two configurations of one structure passed to :func:`run_batched` as ``args`` share a
    compiled program only when their leaves have the same dtypes and shapes; a Python int in
    one and a float in the other, or a float64 array built with numpy, would each compile
    their own. Seed 000's grid and the balancing sweep pass every cell's loop through this.

    Args:
        config: a pytree (e.g. a ``jaxnc.loop.Loop``).

    Returns:
        the same pytree with numpy leaves of the uniform dtypes.
    """
    def conv(x):
        a = np.asarray(x)
        if a.dtype.kind == "f":
            return a.astype(np.float32)
        if a.dtype.kind in "iu":
            return a.astype(np.int32)
        return a
    return jax.tree.map(conv, config)


def _run_processes(batched, keys, args, chunk_size: int, progress: bool, desc: str, out_bytes: int):
    """run_batched after jax.distributed.initialize(): this process's block of the keys
    on its local devices, then every process's block gathered on every process."""
    from jax.experimental import multihost_utils
    n, count, me = int(keys.shape[0]), jax.process_count(), jax.process_index()
    block = -(-n // count)
    rows = [max(0, min(block, n - q * block)) for q in range(count)]     # valid rows of each block
    lo = min(me * block, n)
    mine = _run_local(batched, keys[lo:lo + rows[me]], args, chunk_size, progress and me == 0,
                      f"{desc} (process {me}/{count})", out_bytes)
    if n == 0:
        return mine

    def pad(a):       # equal shapes on every process (the last blocks may be short); bool as uint8
        a = a.view(np.uint8) if a.dtype == bool else a
        return np.concatenate([a, np.zeros((block - a.shape[0], *a.shape[1:]), a.dtype)])

    padded = jax.tree_util.tree_map(pad, mine)
    gathered = multihost_utils.process_allgather(padded, tiled=False)   # (count, block, ...)
    return jax.tree_util.tree_map(
        lambda g, a: np.concatenate([g[q, :rows[q]] for q in range(count)]).astype(a.dtype, copy=False),
        gathered, mine)


def _chunks(keys, args, chunk_size: int, out_bytes: int):
    """How :func:`_run_local` cuts ``keys`` (n >= 1) into chunks on this process's devices:
    ``(size, keys, args, chunk_at)``, the lanes per chunk, the keys and ``args`` as the
    compiled program takes them, and ``chunk_at(lo)``, the chunk of keys ``lo .. lo + size - 1``
    (padded by repeating the last key, placed on the devices)."""
    n = int(keys.shape[0])
    # Every chunk has exactly chunk_size lanes (padded): XLA:CPU's code for a vmapped
    # loop depends on the batch size (fusion, vector tiling), so a seed is bit-identical
    # alone or in any batch only if both run through one compiled batch shape. Within
    # it, a lane's result does not depend on its position or its neighbours (tested).
    devices = jax.local_devices()
    # each device's share is a whole number of vector groups (LANES): the CPU compiler
    # vectorises a batched loop LANES float32 lanes at a time and computes a remainder
    # with other code, so a lane there would differ in its last bits from the same seed
    # in a full group
    size = chunk_lanes(chunk_size, n, out_bytes, len(devices))
    if len(devices) > 1 or jax.process_count() > 1:
        # (with several processes even one local device is named: otherwise the outputs
        # spanned the other processes' devices too, and this process could not read them)
        place_keys = seed_sharding(devices)
        args = jax.device_put(args, jax.sharding.NamedSharding(place_keys.mesh, jax.sharding.PartitionSpec()))
    else:
        place_keys = None
    if not jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key):
        keys = np.asarray(keys)            # raw uint32 keys: slice and pad on the host

    def chunk_at(lo):
        idx = np.minimum(np.arange(lo, lo + size), n - 1)   # pad by repeating the last key
        return keys[idx] if place_keys is None else jax.device_put(keys[idx], place_keys)
    return size, keys, args, chunk_at


def _run_local(batched, keys, args, chunk_size: int, progress: bool, desc: str, out_bytes: int):
    """run_batched on this process's local devices (all of them with one process)."""
    n = int(keys.shape[0])
    if n == 0:
        spec = jax.ShapeDtypeStruct((1, *keys.shape[1:]), keys.dtype)
        shapes = jax.eval_shape(batched, spec, args)
        return jax.tree_util.tree_map(lambda s: np.zeros((0, *s.shape[1:]), s.dtype), shapes)

    size, keys, args, chunk_at = _chunks(keys, args, chunk_size, out_bytes)
    if _IN_FLIGHT:                         # its program, if precompile is compiling it
        _wait_in_flight(_signature(batched, chunk_at(0), args))
    pieces = []
    pending = None                         # (device output, number of valid rows)
    with tqdm(total=n, desc=desc, unit="seed", disable=not progress, dynamic_ncols=True) as bar:
        for lo in range(0, n, size):
            hi = min(lo + size, n)
            out = batched(chunk_at(lo), args)                 # asynchronous dispatch
            if pending is not None:
                pieces.append(_to_numpy(jax.block_until_ready(pending[0]), pending[1]))
                bar.update(pending[1])
            pending = (out, hi - lo)
        pieces.append(_to_numpy(jax.block_until_ready(pending[0]), pending[1]))
        bar.update(pending[1])
    if len(pieces) == 1:
        return pieces[0]
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=0), *pieces)


# ----------------------------------------------------------------------------- statistics


@dataclasses.dataclass(frozen=True)
class Summary:
    """One metric over a Monte-Carlo batch; statistics are over the stable runs only.

    ``mean`` is ``inf`` when no run is stable; ``ci95`` is the half-width of the normal 95 %
    interval of the mean, ``1.96 * std / sqrt(n_stable)``; ``std`` is the sample standard
    deviation (``ddof=1``); both are ``nan`` when fewer than two runs are stable.
    """
    mean: float
    ci95: float
    std: float
    n: int
    n_stable: int
    unstable_fraction: float

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def mean_ci(values) -> tuple[float, float]:
    """Mean of ``values`` (any shape, flattened) and the half-width of its normal 95 %
    interval, 1.96 s / sqrt(n) (s the sample standard deviation, ddof = 1). The half-width is
    nan for fewer than two values, the mean nan for none. Whether the normal interval can be
    trusted for these values: :func:`seeds_for_normal_interval`."""
    v = np.asarray(values, np.float64).reshape(-1)
    if v.size < 2:
        return (float(v.mean()) if v.size else math.nan), math.nan
    return float(v.mean()), float(1.96 * v.std(ddof=1) / math.sqrt(v.size))


def seeds_for_normal_interval(values) -> int:
    """How many values the normal 95 % interval of their mean needs to be trusted, by
    Cochran's rule as refined by Sugden, Smith and Jones (2000, "Cochran's rule for simple
    random sampling", JRSS B 62(4)): n > 28 + 25 G1^2, G1 the sample skewness
    (m3 / m2^1.5, central moments of ``values``, flattened, non-finite values dropped).

    A cost with rare, large failures (a robot leaving its tube 1 run in 200 at 20x the
    typical cost) has G1 of 10 or more, so its interval needs thousands of runs however small
    it looks on a few hundred: see docs/tuning_loops.md ("512 evaluation seeds are too few on
    DRHE"). The rule reads the skewness from the sample, so a sample that holds none of the
    rare runs cannot see them: it flags the tails a sample shows, it does not prove their
    absence. Returns an int >= 28 (28 for fewer than three finite values or values constant
    up to rounding, a spread below 1e-12 of their largest magnitude)."""
    v = np.asarray(values, np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size < 3:
        return 28
    c = v - v.mean()
    m2 = float(np.mean(c * c))
    if m2 <= (1e-12 * float(np.max(np.abs(v)))) ** 2:     # constant up to rounding: no skewness to read
        return 28
    g1 = float(np.mean(c ** 3)) / m2 ** 1.5
    return int(math.floor(28 + 25 * g1 * g1)) + 1


def seeds_for_paired_interval(a, b) -> int:
    """The seeds a paired comparison of ``a`` and ``b`` (costs of two configurations on the
    same seeds, equal shapes) needs before its normal intervals can be trusted: the largest
    of :func:`seeds_for_normal_interval` of ``a``, of ``b`` and of their differences
    ``a - b``. Each point's own costs count, not only the differences: on few seeds two
    heavy-tailed points can agree in every run drawn so far while either one's rare costly
    runs (not yet drawn together) decide the sign (docs/tuning_loops.md, "When a normal
    interval can be trusted").

    Raises ValueError when the shapes differ."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"seeds_for_paired_interval: a and b must have the same shape (paired seeds), "
                         f"got {a.shape} and {b.shape}")
    return max(seeds_for_normal_interval(v) for v in (a, b, a - b))


def summarize(values: np.ndarray, unstable: np.ndarray) -> Summary:
    """Summary of ``values`` (one per run) over the runs where ``unstable`` is false.

    A run whose value is not finite (nan/inf) counts as unstable too.  Unstable runs are
    reported through ``unstable_fraction`` and never raise.  With no run to average
    (``n_stable`` 0) the mean is ``inf`` where the value is +inf in every run (a divergent
    cost: the papers' ∞ for an unstable cell) and ``nan`` otherwise (a rate or a finite cost
    of failed runs has no mean; ``inf`` there would be a number no run had), as
    :func:`describe` shows them (``inf`` / ``–``).  With no runs at all, mean and
    ``unstable_fraction`` are ``nan``.
    """
    v = np.asarray(values, dtype=np.float64)
    u = np.asarray(unstable)
    if v.shape != u.shape:
        raise ValueError(f"summarize: values {v.shape} and unstable {u.shape} must have the same shape")
    v, u = v.reshape(-1), u.reshape(-1).astype(bool)
    bad = u | ~np.isfinite(v)
    n = int(v.size)
    good = v[~bad]
    k = int(good.size)
    nan = float("nan")
    if n == 0:
        return Summary(mean=nan, ci95=nan, std=nan, n=0, n_stable=0, unstable_fraction=nan)
    if k:
        mean, ci95 = mean_ci(good)
    else:
        mean, ci95 = (math.inf if bool(np.all(np.isposinf(v))) else nan), nan
    std = float(np.std(good, ddof=1)) if k >= 2 else nan
    return Summary(mean=mean, ci95=ci95, std=std, n=n, n_stable=k,
                   unstable_fraction=(n - k) / n)


def describe(metrics, run_ndim: int = 0) -> str:
    """A NamedTuple of per-run metrics as a few readable lines (the runner's ``Metrics`` and
    ``TrackingMetrics`` print this way).

    ``run_ndim`` is the number of axes of one run's field (0: scalars, as ``Metrics``; 1:
    float[c] per channel, as ``TrackingMetrics``). A batch (every field with one leading
    axis more, of the same length, as :func:`run_batched` returns): one line per field and
    channel (``name[j]`` when a field has more than one), the mean and 95 % half-width over
    the stable runs (:func:`summarize`, with the tuple's ``unstable`` field when it has one)
    and how many runs were left out (unstable or not finite: a settling time that is nan
    because the run never settled is left out and counted); a boolean field as the fraction
    of runs where it holds. A field with no run to average (every run unstable, or its value
    not finite in the others) shows no mean: ``inf`` where its value is +inf in every run (a
    divergent cost, ``Metrics.cost`` of failed runs: the papers' ∞), else ``–``, with how many
    runs failed and how many were not finite (:func:`summarize`'s mean there: inf or nan), and,
    where the tuple's class says what a nan in every run that did not fail means (a class
    attribute ``NAN_MEANS = {field: text}``: ``Metrics.cost`` of a loop without a cost), that. One run: the
    values. Anything else (traced values inside
    ``jit``, other shapes): the tuple's plain repr. A field whose stable runs are too skewed
    for their normal interval (:func:`seeds_for_normal_interval` above their count and above
    56, i.e. |skewness| > 1, so that a small symmetric batch is not flagged) says so on its
    line."""
    name, fields = type(metrics).__name__, metrics._asdict()
    plain = f"{name}(" + ", ".join(f"{k}={v!r}" for k, v in fields.items()) + ")"
    if any(isinstance(v, jax.core.Tracer) for v in fields.values()):
        return plain
    try:
        arrays = {k: np.asarray(v) for k, v in fields.items()}
    except Exception:                       # a field that is not an array
        return plain
    ndims = {a.ndim for a in arrays.values()}
    if ndims == {run_ndim}:
        fmt = lambda x: f"{x:.6g}" if isinstance(x, float) else f"{x}"
        val = lambda a: fmt(a.item()) if a.ndim == 0 else "[" + ", ".join(fmt(x) for x in a.reshape(-1).tolist()) + "]"
        return f"{name}(" + ", ".join(f"{k}={val(a)}" for k, a in arrays.items()) + ")"
    if ndims != {run_ndim + 1} or len({a.shape[0] for a in arrays.values()}) != 1 or run_ndim > 1:
        return plain
    n = next(iter(arrays.values())).shape[0]
    if n == 0:                              # run_batched on no keys
        return f"{name} over 0 runs"
    unstable = arrays["unstable"].astype(bool) if "unstable" in arrays and arrays["unstable"].ndim == 1 \
        else np.zeros(n, bool)
    columns = {}
    for k, a in arrays.items():
        c = a.reshape(n, -1)
        for j in range(c.shape[1]):
            columns[k if c.shape[1] == 1 else f"{k}[{j}]"] = (k, c[:, j])
    lines = [f"{name} over {n} runs (mean +- 95 % over the stable runs)"]
    w = max(len(k) for k in columns)
    for label, (k, a) in columns.items():
        if a.dtype == bool:
            lines.append(f"  {label:<{w}}  {a.mean():.4g} of the runs")
        elif a.dtype.kind in "fiu":
            bad = unstable if k != "unstable" else np.zeros(n, bool)
            sm = summarize(a, bad)
            if sm.n_stable == 0:            # nothing to average: say why
                failed = int(np.count_nonzero(bad))
                why = (f"no stable run: all {n} failed" if failed == n
                       else f"no run to average: {failed} failed, {n - failed} not finite")
                hint = getattr(type(metrics), "NAN_MEANS", {}).get(k)
                if hint and failed < n and np.all(np.isnan(a[~bad])):
                    why += f"; {hint}"
                shown = "inf" if np.all(np.isposinf(a)) else "\u2013"
                lines.append(f"  {label:<{w}}  {shown} ({why})")
                continue
            left = f" ({n - sm.n_stable} left out: unstable or not finite)" if sm.n_stable < n else ""
            need = seeds_for_normal_interval(a[~bad])
            skew = (f" [skewed: the interval needs about {need} runs (Cochran's rule), not {sm.n_stable}]"
                    if need > max(sm.n_stable, 56) else "")
            lines.append(f"  {label:<{w}}  {sm.mean:.6g} +- {sm.ci95:.2g}{left}{skew}")
        else:
            return plain
    return "\n".join(lines)


# ----------------------------------------------------------------------------- results files

_NONFINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def _float(x: float):
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


def _jsonable(obj, where: str = "results"):
    """Plain JSON types; non-finite floats as the strings "inf"/"-inf"/"nan"."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return _float(float(obj))
    if isinstance(obj, np.generic):
        return _jsonable(obj.item(), where)
    if isinstance(obj, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(obj).tolist(), where)
    if isinstance(obj, dict):
        return {str(k): _jsonable(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if hasattr(obj, "to_dict") and callable(obj.to_dict):
        return _jsonable(obj.to_dict(), where)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable({f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}, where)
    if hasattr(obj, "_asdict"):                                     # NamedTuple
        return _jsonable(obj._asdict(), where)
    raise TypeError(f"save_results: {where} of type {type(obj).__name__} is not JSON-serialisable")


def _platform_string() -> str:
    try:
        devs = jax.devices()
        kinds = sorted({d.device_kind for d in devs})
        dev = f"{jax.default_backend()}: {', '.join(kinds)} x{len(devs)}"
    except Exception as e:                # noqa: BLE001 - the platform line must never fail a save
        dev = f"unknown backend ({e})"
    return f"{dev}; {_platform.platform()}; Python {_platform.python_version()}"


def save_results(path, *, experiment: str, config: dict, results: dict, wall_time_s: float) -> None:
    """Write the results JSON file atomically.

    Fields: ``jaxnc_version, experiment, config, results, wall_time_s, created`` (ISO 8601,
    UTC), ``jax_version, platform`` and ``code``, the :func:`jaxnc.sweep.code_fingerprint`
    of the library that wrote it (:func:`stored_or_run` reuses a file only with the same), and
    ``run``, the id of the run that claimed the folder (:func:`jaxnc.results.run_id`), where it
    has one: :func:`jaxnc.results.load` checks it against the per-seed file's.  numpy scalars/arrays, jax arrays, tuples, paths,
    dataclasses (``Summary``) and NamedTuples are converted; ``inf``/``-inf``/``nan`` are
    written as those strings (:func:`load_results` turns them back into floats).  The file
    is written to a temporary file in the same directory, flushed and fsynced, then moved
    over ``path`` with ``os.replace``: a reader sees either the old file or the complete
    new one, and a failure leaves the old file untouched and no temporary file behind.
    """
    path = pathlib.Path(path)
    doc = _jsonable({
        "jaxnc_version": __version__,
        "experiment": experiment,
        "config": config,
        "results": results,
        "wall_time_s": float(wall_time_s),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "jax_version": jax.__version__,
        "platform": _platform_string(),
        "code": code_fingerprint(),
    })
    from jaxnc.results import run_id
    run = run_id(path.parent)
    if run is not None:
        doc["run"] = run

    def write(f):
        text = io.TextIOWrapper(f, encoding="utf-8")
        json.dump(doc, text, indent=2, allow_nan=False)
        text.write("\n")
        text.flush()
        text.detach()                          # leave f open for atomic_write's fsync

    atomic_write(path, write)


def atomic_write(path, write: Callable) -> None:
    """Write a file atomically: ``write(f)`` fills a temporary file (binary mode) in the
    same directory, which is flushed, fsynced and moved over ``path`` with ``os.replace``
    (the directory is fsynced too). A reader sees the old file or the complete new one;
    an exception (Ctrl-C included) leaves the old file untouched and no temporary file
    behind. Parent directories are created; the file gets the usual mode (umask).

    A process killed outright (SIGKILL, a machine's crash) leaves its temporary file,
    ``.<name>.<8 characters>.tmp`` beside ``path``: no reader opens it (every reader names
    its file), and :func:`stale_temporaries` lists such files for removal."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)          # mkstemp creates 0600; give a normal file mode
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    if sys.platform != "win32":                # make the rename itself durable
        try:
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass


_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp\Z")


def stale_temporaries(folder) -> list[pathlib.Path]:
    """The temporary files :func:`atomic_write` left in ``folder`` (not its subfolders) when
    its process was killed while writing (``.<name>.<8 characters>.tmp``, sorted). Only
    safe to remove while no other process writes in ``folder``: ``jaxnc run`` removes them
    from its ``--out`` while it holds the folder's lock (an experiment that is not a sweep)."""
    folder = pathlib.Path(folder)
    if not folder.is_dir():
        return []
    return sorted(f for f in folder.iterdir() if _TEMPORARY.match(f.name) and f.is_file())


def _restore(obj):
    if isinstance(obj, str):
        return _NONFINITE.get(obj, obj)
    if isinstance(obj, dict):
        return {k: _restore(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_restore(v) for v in obj]
    return obj


def stored_or_run(path, *, experiment: str, config: dict, compute, progress: bool = True) -> dict:
    """The results stored at ``path`` when it was written by :func:`save_results` with this
    very ``config`` and by this code (its ``code``, :func:`jaxnc.sweep.code_fingerprint`: a
    part stored by another jaxnc is computed again) -- a resumed study reuses each finished
    part; otherwise ``compute()``, a dict of results with a ``"wall_time_s"`` entry, saved
    there first. Returns the results as :func:`load_results` reads them back (the same
    either way)."""
    path = pathlib.Path(path)
    if path.exists():
        try:
            doc = load_results(path)
        except ValueError:
            doc = None
        if doc and doc.get("code") == code_fingerprint() and doc["config"] == _restore(_jsonable(config)):
            if progress:
                print(f"[{path.stem}] reusing {path}")
            return doc["results"]
    res = compute()
    save_results(path, experiment=experiment, config=config, results=res, wall_time_s=res["wall_time_s"])
    return load_results(path)["results"]


def stored_study(out, *, experiment: str, config: dict, parts, compute, tables, plot, progress: bool = True) -> dict:
    """A study of several parts (loops, problems) written to folder ``out``: each part's
    results from :func:`stored_or_run` (``out/<part>.json``, ``compute(part)``), then the
    markdown ``tables(results)`` printed and written to ``out/tables.md``, the figure
    ``plot(results, out)`` (returns its path), and every part in ``out/results.json``
    (config plus ``loops``: the parts). Each part's results must name it in ``"loop"``.
    Returns ``{part: results}``."""
    t0 = time.perf_counter()
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results = [stored_or_run(out / f"{name}.json", experiment=experiment, config=config, progress=progress,
                             compute=lambda name=name: compute(name)) for name in parts]
    text = tables(results)
    print("\n" + text)
    (out / "tables.md").write_text(text, encoding="utf-8")
    fig = plot(results, out)
    save_results(out / "results.json", experiment=experiment, config=dict(config, loops=list(parts)),
                 results={r["loop"]: r for r in results}, wall_time_s=time.perf_counter() - t0)
    print(f"wrote {out / 'results.json'}, {out / 'tables.md'} and {fig}")
    return {r["loop"]: r for r in results}


def load_results(path) -> dict:
    """Read a file written by :func:`save_results`; the strings "inf"/"-inf"/"nan" become floats.

    (Any string value exactly equal to one of those three is converted, wherever it is.)
    Raises ValueError naming the file (and the line) when it is not valid JSON or not text;
    OSError when it cannot be read.
    """
    path = pathlib.Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            return _restore(json.load(f))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not a jaxnc results file (invalid JSON at line {e.lineno}, column {e.colno}: "
                         f"{e.msg}; truncated or damaged?)") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a jaxnc results file (not UTF-8 text at byte {e.start})") from None
