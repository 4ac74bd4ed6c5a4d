"""The ``jaxnc`` command line.

    jaxnc list
    jaxnc run EXPERIMENT [--seeds N] [--out DIR] [--set KEY=VALUE ...] [--no-progress] [--shard I/N]
              [--distributed [--coordinator HOST:PORT --num-processes N --process-id I]]
    jaxnc --version

EXPERIMENT is a registered name (see ``jaxnc list``) or ``MODULE:ATTR`` for an experiment in
the user's own module, e.g. ``jaxnc run mystudy:experiment``: MODULE is imported (the current
directory is importable, as with ``python -m``) and ATTR (dotted attributes allowed) must
be a :class:`jaxnc.experiment.Experiment` or a zero-argument callable returning one.  It then
runs exactly like a built-in one (same ``--set`` validation, ``--seeds``, ``--out`` default
``results/<name>``); see :func:`jaxnc.experiment.resolve_experiment`.

Before anything is simulated, ``run`` checks that ``--out`` is a folder it can create
and write in, that the seeds' keys fit in the memory available, and that the folder does
not hold the results of another experiment, or finished results of other settings that
this run would overwrite (:func:`jaxnc.results.claim`, which then records the run in
``OUT/run.json``; a sweep's cells, named by their whole configuration, are kept apart
instead). A run of an experiment that is not a sweep holds a lock on ``OUT`` while it runs,
so a second run into the same folder meanwhile is refused; it removes the temporary files a
killed run left there (:func:`jaxnc.montecarlo.stale_temporaries`).

:func:`main` is the console-script entry point (``jaxnc = "jaxnc.cli:main"``).  It always
ends by raising ``SystemExit(code)``: 0 on success, 2 for a bad command line or setting
(one line ``jaxnc: error: <message>`` on stderr, no traceback), 3 when a sweep run without
``--shard`` ends with cells missing (its tables are not written), 130 on Ctrl-C.  Use
:func:`run_cli` to get the exit code as a return value instead.  An unexpected exception
inside an experiment is a bug and propagates with its traceback (exit code 1).
"""
from __future__ import annotations

import argparse
import contextlib
import gc
import inspect
import os
import pathlib
import re
import sys
import tempfile
import warnings

import jax

from jaxnc import __version__
from jaxnc import experiment as _exp
from jaxnc.experiment import ConfigError

__all__ = ["main", "run_cli", "build_parser"]

PROG = "jaxnc"
DEFAULT_SEEDS = 1000
#: exit code of a sweep run without --shard that ends with cells missing
INCOMPLETE = 3
# seed indices are uint32 (jaxnc.montecarlo.seed_keys)
_SEEDS = _exp.Option("--seeds", "int", DEFAULT_SEEDS, "number of Monte-Carlo seeds", low=1, high=2**32 - 1)
_CPU_DEVICES = _exp.Option("--cpu-devices", "int", 1, "CPU devices", low=1, high=256)


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line ``jaxnc: error: ...`` and exit code 2."""

    def error(self, message):                       # noqa: D401 - argparse API
        sys.stderr.write(f"{PROG}: error: {message} (see '{self.prog} --help')\n")
        raise SystemExit(2)


class _RunHelp(argparse.Action):
    """``jaxnc run [EXPERIMENT] --help``: the run command's help, then, when an experiment is
    named before ``--help``, its settings, defaults and ranges (as ``jaxnc list`` shows them);
    exits 0, or 2 with one line for an experiment that cannot be resolved."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.print_help()
        spec = getattr(namespace, "experiment", None)
        if spec is not None:
            try:
                _load_builtin()
                exp = _exp.resolve_experiment(spec)
            except ConfigError as e:
                sys.stdout.flush()
                sys.stderr.write(f"{PROG}: error: {' '.join(str(e).split())}\n")
                raise SystemExit(2) from None
            print(f"\nsettings of {format_experiment(exp)}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Monte-Carlo simulation of networked control systems (JAX).")
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sub.add_parser("list", help="list the experiments and their settings",
                   description="List the registered experiments, their settings, defaults and ranges.")

    r = sub.add_parser("run", help="run an experiment", add_help=False,
                       description="Run an experiment over many seeds: a registered one, or one "
                                   "defined in your own module, given as MODULE:ATTR. "
                                   "'jaxnc run EXPERIMENT --help' adds its settings.")
    r.add_argument("-h", "--help", action=_RunHelp,
                   help="show this help message (and EXPERIMENT's settings when one is given before it) and exit")
    r.add_argument("experiment", metavar="EXPERIMENT",
                   help="a registered experiment name (see 'jaxnc list'), or MODULE:ATTR: an "
                        "Experiment, or a zero-argument callable returning one, in an importable "
                        "module (the current directory is importable, as with python -m), "
                        "e.g. mystudy:experiment")
    r.add_argument("--seeds", default=str(DEFAULT_SEEDS), metavar="N",
                   help=f"number of Monte-Carlo seeds, an integer in [1, {2**32 - 1}] whose keys and results "
                        f"fit in memory (default {DEFAULT_SEEDS})")
    r.add_argument("--out", default=None, metavar="DIR",
                   help="output directory (default results/NAME, the experiment's name); it holds one "
                        "experiment's results (OUT/run.json): another experiment's folder, or finished results "
                        "of other settings that this run would overwrite, are refused")
    r.add_argument("--set", "-s", dest="settings", action="extend", nargs="+", default=[],
                   metavar="KEY=VALUE", help="override a setting; repeatable (see 'jaxnc list')")
    r.add_argument("--no-progress", dest="progress", action="store_false",
                   help="do not show progress bars")
    r.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="JAX's persistent compilation cache folder (default: $JAXNC_CACHE_DIR, else "
                        "~/.cache/jaxnc/xla): a second run of the same programs skips compilation")
    r.add_argument("--no-cache", dest="cache", action="store_false",
                   help="do not use the persistent compilation cache")
    r.add_argument("--shard", default=None, metavar="I/N",
                   help="sweeps (mecanum-grid, hdd-gpi, diffdrive-sensitivity; your own experiment whose run "
                        "takes shard=): compute only shard I of N "
                        "(0 <= I < N) of the cells into the shared --out folder; the run that finds every "
                        "cell present writes the tables (README: 'Sweeps across machines')")
    r.add_argument("--distributed", action="store_true",
                   help="one of several processes (jax.distributed.initialize): each runs its share of "
                        "every batch of seeds on its local devices and gets the full result; without "
                        "--coordinator/--num-processes/--process-id JAX detects them (SLURM, Open MPI, "
                        "$JAX_COORDINATOR_ADDRESS, ...); start every process with the same command")
    r.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="with --distributed: address of process 0's coordinator service")
    r.add_argument("--num-processes", default=None, metavar="N",
                   help="with --distributed: number of processes (an integer >= 1)")
    r.add_argument("--process-id", default=None, metavar="I",
                   help="with --distributed: this process, an integer in [0, N)")
    r.add_argument("--cpu-devices", default=None, metavar="N",
                   help="split the CPU into N JAX devices and shard the seeds over them "
                        "(an integer >= 1; default: JAX's, one)")
    return p


def _load_builtin() -> None:
    """load_builtin, with any warning printed as one line on stderr."""
    with warnings.catch_warnings(record=True) as caught:
        _exp.load_builtin()
    for w in caught:
        if issubclass(w.category, RuntimeWarning) and str(w.message).startswith("built-in experiments"):
            sys.stderr.write(f"{PROG}: warning: {' '.join(str(w.message).split())}\n")
        else:                                   # anything else raised while importing: as usual
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)


def format_experiment(exp: _exp.Experiment) -> str:
    lines = [f"{exp.name}: {exp.description}"]
    if not exp.options:
        lines.append("    (no settings)")
    width = max((len(o.name) for o in exp.options), default=0)
    for o in exp.options:
        lines.append(f"    {o.name:<{width}}  default {o.format_value(o.default)}; "
                     f"{o.range_text()}. {o.help}")
    return "\n".join(lines)


def _list() -> int:
    if not _exp.REGISTRY:
        print("no experiments registered")
        return 0
    print("\n\n".join(format_experiment(_exp.REGISTRY[n]) for n in sorted(_exp.REGISTRY)))
    print("\nrun one with: jaxnc run EXPERIMENT [--seeds N] [--out DIR] [--set KEY=VALUE ...]")
    return 0


def _run(args) -> int:
    exp = _exp.resolve_experiment(args.experiment)
    settings = exp.parse_settings(args.settings)
    seeds = _SEEDS.parse(args.seeds)
    run_kw = {}
    if args.shard is not None:
        from jaxnc.sweep import parse_shard
        if "shard" not in inspect.signature(exp.run).parameters:
            raise ConfigError(f"--shard: experiment {exp.name!r} is not a sweep (its run takes no shard); "
                              f"sweeps: mecanum-grid, hdd-gpi, diffdrive-sensitivity, and an experiment of your own "
                              f"whose run takes shard= (docs/build_your_own_loop.md, 'A sweep of your own')")
        try:
            run_kw["shard"] = parse_shard(args.shard)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    cpu_devices = _CPU_DEVICES.parse(args.cpu_devices) if args.cpu_devices is not None else None
    if not args.distributed and any(v is not None for v in (args.coordinator, args.num_processes, args.process_id)):
        raise ConfigError("--coordinator, --num-processes and --process-id need --distributed")
    from jaxnc import montecarlo
    try:
        montecarlo.check_seed_memory(seeds)
    except montecarlo.MemoryBudgetError as e:
        raise ConfigError(f"--seeds {seeds}: {e}") from None
    out = _writable_out(args.out, exp.name)
    with _sole_writer(out, exp, args.distributed):
        done = _claim_and_run(args, exp, settings, seeds, out, cpu_devices, run_kw)
    if done is None:
        return 0
    if args.shard is None and isinstance(done, dict) and done.get("complete") is False:
        sys.stdout.flush()
        sys.stderr.write(f"{PROG}: error: {exp.name} ended with cells missing, so its tables were not written "
                         f"(above); run the same command again to compute them\n")
        return INCOMPLETE
    return 0


@contextlib.contextmanager
def _sole_writer(out: pathlib.Path, exp, distributed: bool):
    """Hold ``out``'s run lock while one run of an experiment that writes whole-folder results
    (not a sweep's cells, which shards write together; not ``--distributed``, whose processes
    may share the folder) claims it and runs: a second run into the same folder meanwhile is
    refused, instead of both passing the claim and the later one overwriting (or mixing its
    files with) the other's."""
    if exp.keeps_cells or distributed:
        yield
        return
    from jaxnc.sweep import folder_lock
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(folder_lock(out, wait=False))
        except BlockingIOError:
            raise ConfigError(f"--out: {out} is being written by another jaxnc run right now (it holds a lock "
                              f"on the folder); choose another folder, or wait for that run to end") from None
        from jaxnc.montecarlo import stale_temporaries
        for f in stale_temporaries(out):        # a killed run's unfinished files; no one else writes here now
            with contextlib.suppress(FileNotFoundError):
                f.unlink()
        yield


def _claim_and_run(args, exp, settings, seeds, out, cpu_devices, run_kw):
    """Claim ``out`` (:func:`jaxnc.results.claim`) and run ``exp``; its results, or None on a
    process other than 0 of a distributed run."""
    from jaxnc import montecarlo
    from jaxnc import results
    try:
        other = results.claim(out, exp.name, settings, seeds, keeps_cells=exp.keeps_cells)
    except results.FolderError as e:
        raise ConfigError(f"--out: {e}") from None
    if other:
        sys.stderr.write(f"{PROG}: note: {out} holds {exp.name} cells of other settings ({'; '.join(other)}); "
                         f"they are kept beside this run's, and the summary files will describe this run\n")
    if cpu_devices is not None:
        try:
            jax.config.update("jax_num_cpu_devices", cpu_devices)
        except RuntimeError as e:              # the backend was already initialised
            raise ConfigError(f"--cpu-devices: {e}") from None
    if args.distributed:
        _initialize_distributed(args)
    from jaxnc.cache import allow_cache_beside, enable_cache
    allow_cache_beside(args.cache)
    if args.cache:
        try:
            enable_cache(args.cache_dir)
        except OSError as e:
            raise ConfigError(f"--cache-dir: cannot create directory '{args.cache_dir}': {e.strerror or e}") from None
    try:
        if args.distributed and jax.process_index() != 0:
            # every process runs the experiment and gets the full results (and writes the same
            # files); the tables and progress bars are process 0's
            with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
                exp.run(settings, seeds=seeds, out=out, progress=False, **run_kw)
            return None
        done = exp.run(settings, seeds=seeds, out=out, progress=args.progress, **run_kw)
    except montecarlo.MemoryBudgetError as e:
        raise ConfigError(f"--seeds {seeds}: {e}") from None
    return done


def _writable_out(text: str | None, name: str) -> pathlib.Path:
    """The --out folder (default ``results/NAME``), created, after a test write in it;
    ConfigError naming --out when it is empty, cannot be created or cannot be written."""
    if text is not None and not text.strip():
        raise ConfigError(f"--out must be a folder path, got {text!r}")
    out = pathlib.Path(text) if text is not None else pathlib.Path("results") / name
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out: cannot create directory '{out}': {e.strerror or e}") from None
    try:
        fd, probe = tempfile.mkstemp(dir=out, prefix=".jaxnc-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ConfigError(f"--out: cannot write in directory '{out}': {e.strerror or e}") from None
    return out


_COORDINATOR_RE = re.compile(r"\S+:[0-9]{1,5}\Z")


def _initialize_distributed(args) -> None:
    """``jax.distributed.initialize`` from --coordinator/--num-processes/--process-id (or
    JAX's own detection when they are not given); CPU collectives over gloo."""
    kw = {}
    if args.coordinator is not None:
        if not _COORDINATOR_RE.match(args.coordinator):
            raise ConfigError(f"--coordinator must be HOST:PORT, got {args.coordinator!r}")
        kw["coordinator_address"] = args.coordinator
    if args.num_processes is not None:
        kw["num_processes"] = _exp.Option("--num-processes", "int", 1, "", low=1, high=65536).parse(args.num_processes)
    if args.process_id is not None:
        high = kw.get("num_processes", 65536) - 1
        kw["process_id"] = _exp.Option("--process-id", "int", 0, "", low=0, high=high).parse(args.process_id)
    if jax.config.jax_cpu_collectives_implementation in (None, "none"):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")   # CPU processes exchange results
    try:
        jax.distributed.initialize(**kw)
    except (ValueError, RuntimeError) as e:
        raise ConfigError(f"--distributed: jax.distributed.initialize failed: {' '.join(str(e).split())}") from None


def run_cli(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return the exit code.

    argparse's own ``--help``/``--version``/usage errors raise SystemExit (0 or 2).
    """
    args = build_parser().parse_args(argv)
    try:
        _load_builtin()
        if args.command == "list":
            return _list()
        return _run(args)
    except ConfigError as e:
        msg = " ".join(str(e).split())         # guarantee a single line
        sys.stderr.write(f"{PROG}: error: {msg}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"{PROG}: interrupted\n")
        return 130


def main(argv: list[str] | None = None) -> int:
    """Console-script entry point: runs :func:`run_cli` and raises ``SystemExit(code)``.

    It never returns normally (the ``-> int`` is for ``sys.exit(main())`` wrappers, which
    therefore also get the right code).
    """
    # a process that traces large programs: Python's collector at its defaults (700, 10, 10)
    # spent a fifth to two fifths of each loop's tracing in full collections
    # (benchmarks/RESULTS.md, "Helper tr"); the library itself leaves the collector alone
    gc.set_threshold(100_000, 50, 100)
    try:
        code = run_cli(argv)
    except KeyboardInterrupt:                   # Ctrl-C during argument parsing / imports
        sys.stderr.write(f"{PROG}: interrupted\n")
        code = 130
    sys.stdout.flush()
    raise SystemExit(code)


if __name__ == "__main__":
    main()
