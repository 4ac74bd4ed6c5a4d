"""Experiment ``mecanum``: seed 000 (Carbonell et al. 2024), one (N, DP) cell.

Runs the requested cases (SR, DR, DRH, DRHE or all) and the nominal single-rate run
(SR, N = 1, DP = 0) on the same seeds, normalises J1-J3 to the nominal run as the
paper does (J4 is normalised by definition), prints the table, writes
``results.json`` (full configuration, per-metric mean and 95 % interval, unstable
fraction, version, wall time), the per-seed metrics (``seeds.npz``, read by
:func:`jaxnc.load`) and a path-tracking figure like Fig. 4.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import jax
import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo, results as per_seed
from jaxnc.controllers.path_following import LOOKAHEAD
from jaxnc.estimators.sparsity import EKFStructure
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.paths import PATHS, Path as RefPath
from jaxnc.report import fmt, markdown_table, save_figure
from jaxnc.schemes import mecanum as mec
from jaxnc.sweep import code_fingerprint

CASE_CHOICES = (*mec.CASES, "all")
UNSTABLE_CELL = 0.5   # a cell is shown as inf when more than half of its runs are unstable


def loop_config(loop: nc.Loop) -> dict:
    """JSON-friendly description of a loop (the path by name, functions by name)."""
    def conv(obj):
        if isinstance(obj, EKFStructure):        # the Jacobians' sparsity patterns, drawn
            return obj.describe()
        if type(obj).__name__ == "MjxMecanum":   # the MJX plant: its parameters, not its arrays
            from jaxnc.plants.mecanum_mjx import describe
            return describe(obj)
        if dataclasses.is_dataclass(obj):
            if isinstance(obj, RefPath):
                return {"name": obj.name, "length_m": float(obj.length)}
            return {f.name: conv(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        if isinstance(obj, tuple):
            return [conv(a) for a in obj]
        if callable(obj):
            return obj.__qualname__
        a = np.asarray(obj)
        return a.tolist() if a.ndim else a.item()
    return conv(loop)


def run_seed(key, loop):
    """Per-seed metrics with the configuration as an argument: the function the seed-000
    experiments hand to ``run_batched(..., args=(loop,))`` (module level, so one compiled
    program per loop structure is cached and shared)."""
    return mec.run(loop, key)


def true_plant(name: str):
    """The robot the loops run on: None (the kinematic model itself) or the MJX multibody
    platform (``plant=mjx``, needs ``pip install 'jaxnc[mjx]'``)."""
    if name == "kinematic":
        return None
    if name == "mjx":
        from jaxnc.plants import mecanum_mjx
        try:
            return mecanum_mjx.mjx_mecanum()
        except ImportError as e:
            raise ConfigError(f"plant=mjx: {e}") from None
    raise ConfigError(f"plant must be 'kinematic' or 'mjx', got {name!r}")


def build_loops(settings: dict) -> dict[str, nc.Loop]:
    """Validated configurations (a bad combination is a ConfigError, before any tracing)."""
    cases = mec.CASES if settings["case"] == "all" else (settings["case"],)
    kw = dict(path=settings["path"], sigma=settings["sigma"], delta=settings["delta"],
              follower_kw=dict(L_ref=settings["L_ref"]), truth=true_plant(settings.get("plant", "kinematic")))
    try:
        loops = {"SR nominal": mec.mecanum_loop("SR", 1, 0.0, **kw)}
        for c in cases:
            loops[c] = mec.mecanum_loop(c, settings["N"], settings["dp"], h=settings["h"] or None,
                                        max_silence=settings["max_silence"], **kw)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return loops


def _stats(metrics, name):
    unstable = np.asarray(metrics.unstable)
    return montecarlo.summarize(np.asarray(getattr(metrics, name), float), unstable)


def summarise(results: dict) -> dict:
    """Per case: absolute summaries and indexes normalised to the nominal SR run."""
    nom = results["SR nominal"]
    nom_rate = np.asarray(nom.tx_sc) / np.asarray(nom.l)
    base = {j: _stats(nom, j).mean for j in ("J1", "J2", "J3")}
    rate_nom = float(np.mean(nom_rate[~np.asarray(nom.unstable)]))
    out = {}
    for name, m in results.items():
        unstable = np.asarray(m.unstable)
        rate = np.asarray(m.tx_sc) / np.asarray(m.l)
        s = {j: _stats(m, j) for j in ("J1", "J2", "J3")}
        j4 = montecarlo.summarize(rate / rate_nom, unstable)
        frac = float(np.mean(unstable))
        cell_unstable = frac > UNSTABLE_CELL
        norm = {j: (math.inf if cell_unstable else s[j].mean / base[j]) for j in s}
        out[name] = {
            "absolute": {j: s[j].to_dict() for j in s},
            "normalised": {**norm, "J4": math.inf if cell_unstable else j4.mean},
            "J4": j4.to_dict(),
            "tx_sc_mean": float(np.mean(m.tx_sc)), "tx_ca_mean": float(np.mean(m.tx_ca)),
            "unstable_fraction": frac,
        }
    return out


def table(summary: dict) -> str:
    rows = []
    for name, s in summary.items():
        n = s["normalised"]
        a = s["absolute"]["J1"]
        rows.append([name, fmt(n["J1"]), fmt(n["J2"]), fmt(n["J3"]), fmt(n["J4"], 3),
                     fmt(100 * a["mean"], 2) + ("" if math.isinf(a["mean"]) else " \u00b1 " + fmt(100 * a["ci95"], 2)),
                     f"{100 * s['unstable_fraction']:.1f}"])
    return markdown_table(["case", "J1", "J2", "J3", "J4", "J1 abs (cm)", "unstable %"], rows)


_simulate = jax.jit(nc.simulate)   # one compilation per loop structure (N, true plant)

#: bytes of recorded positions (every seed's, float32 (X, Y) per fast period) up to which
#: :func:`run`'s main Monte-Carlo run also records them, so that the seed-0 figure needs no
#: second compiled program; beyond it (about 48 000 seeds of the default path) the figure
#: runs seed 0 again (:func:`plot_paths`), a compilation small against such a run
POSITION_BUDGET = 1 << 28


def horizon(loop: nc.Loop) -> int:
    """h, the prediction horizon in slow periods, of a :func:`~jaxnc.schemes.mecanum.mecanum_loop` loop."""
    return int(loop.actuator.horizon) // loop.N


def position(plant, x):
    """float[2]: the robot's position (X, Y) in a state of ``plant`` (a :class:`jaxnc.loop.Record`
    function of the plant: recorded after each fast period)."""
    return plant.state_vector(x)[3:5]


def with_positions(loop: nc.Loop) -> nc.Loop:
    """``loop`` recording also the robot's position after each fast period
    (``Trajectory.parts["plant"]`` [K, 2]); the simulation itself is unchanged."""
    return dataclasses.replace(loop, record=dataclasses.replace(nc.Record.of(loop.record), plant=position))


def run_seed_positions(key, loop):
    """(per-seed metrics, float[K, 2] positions after each fast period) of a loop from
    :func:`with_positions`: the main run's function when the figure's path comes from it."""
    traj = nc.simulate(loop, key)
    return mec.metrics(loop, traj), traj.parts["plant"]


def path_drawn(loop: nc.Loop, after, l) -> np.ndarray:
    """float[l, 2]: the robot's positions at the start of fast periods 0 .. l-1 (the figure's
    path up to completion), from ``after`` [K, 2], its positions after each fast period; the
    first is the loop's start, the path's first point (:func:`~jaxnc.schemes.mecanum.mecanum_loop`)."""
    start = np.asarray(loop.monitor.path.points, np.float32)[:1]
    return np.concatenate([start, np.asarray(after)[: max(int(l) - 1, 0)]])


def plot_paths(loops: dict, key, out: Path, title: str, paths: dict | None = None) -> Path:
    """Fig. 4-like figure of one seed: the reference and each loop's path up to completion
    (dotted when unstable), written to ``out/paths.png``.

    ``paths``: per loop name, ``(positions float[l, 2], unstable)`` of that seed (from the
    Monte-Carlo run, :func:`path_drawn`); None: seed ``key`` of each loop is simulated here
    (one more compiled program per loop structure)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if paths is None:
        paths = {}
        for name, loop in loops.items():
            full = dataclasses.replace(loop, record=mec.FULL_RECORD)
            traj = _simulate(montecarlo.uniform_dtypes(full), key)
            paths[name] = (np.asarray(traj.x[:, 3:5])[: int(traj.done_step)], bool(mec.metrics(full, traj).unstable))
    fig, ax = plt.subplots(figsize=(7, 5))
    path = next(iter(loops.values())).monitor.path
    ref = np.asarray(path.points)
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.5, label="reference")
    for name in loops:
        xy, unstable = paths[name]
        ax.plot(xy[:, 0], xy[:, 1], ls=":" if unstable else "-", lw=1.2,
                label=name + (" (unstable)" if unstable else ""))
    lo, hi = ref.min(axis=0) - 0.6, ref.max(axis=0) + 0.6   # unstable runs leave the frame
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="best")
    f = save_figure(fig, out / "paths.png", dpi=130)
    return f


def _while_compiling() -> None:
    """The run's own work that needs no compiled program, done while XLA compiles the loop
    programs (:func:`jaxnc.montecarlo.precompile` with ``wait=False``): the code's fingerprint
    that :func:`jaxnc.montecarlo.save_results` writes (about a second of hashing) and the
    figure's plotting library."""
    code_fingerprint()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t_start = time.perf_counter()
    loops = build_loops(settings)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    # the figure's seed-0 paths come from the main run while every seed's fit the budget
    record_paths = seeds * max(l.steps for l in loops.values()) * 2 * 4 <= POSITION_BUDGET
    fn = run_seed_positions if record_paths else run_seed
    # the configuration is a runtime argument: the loops of one structure share a compilation;
    # the structures' programs (nominal SR's N = 1, the cases' N) compile side by side first
    args = {name: montecarlo.uniform_dtypes(with_positions(loop) if record_paths else loop)
            for name, loop in loops.items()}
    montecarlo.precompile([(fn, (a,)) for a in args.values()], keys, chunk_size=min(256, seeds), wait=False)
    _while_compiling()
    results, paths = {}, {}
    for name, loop in loops.items():
        out_ = montecarlo.run_batched(
            fn, keys, args=(args[name],), progress=progress, chunk_size=min(256, seeds),
            desc=f"{name:>10} N={loop.N} DP={float(loop.uplink.loss.p):.2f} h={horizon(loop)}")
        if record_paths:
            out_, after = out_
            paths[name] = (path_drawn(loop, after[0], out_.l[0]), bool(out_.unstable[0]))
        results[name] = out_
    summary = summarise(results)
    print(f"\nseed 000 Mecanum, path={settings['path']}, N={settings['N']}, DP={settings['dp']}, seeds={seeds}, "
          f"plant={settings.get('plant', 'kinematic')}")
    print("J1-J3 normalised to nominal SR (N=1, DP=0) on the same seeds; J4 = sensor transmission rate / nominal\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, results, dims=("case",), experiment="mecanum")
    title = f"{settings['path']}: N={settings['N']}, DP={settings['dp']} (seed 0)"
    fig = plot_paths(loops, None if paths else keys[0], out, title, paths=paths or None)
    wall = time.perf_counter() - t_start
    config = {"settings": settings, "seeds": seeds,
              "loops": {n: {"case": n.split()[0], "N": l.N, "h": horizon(l), "steps": l.steps,
                            "config": loop_config(l)}
                        for n, l in loops.items()}}
    montecarlo.save_results(out / "results.json", experiment="mecanum", config=config,
                            results=summary, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'} and {fig}  ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="mecanum",
    description="Seed 000: Mecanum robot, SR/DR/DRH/DRHE at one (N, DP) cell, normalised to nominal SR",
    options=(
        Option("case", "choice", "all", "scheme to run", choices=CASE_CHOICES),
        Option("N", "int", 10, "multiplicity: slow period NT", low=1, high=20),
        Option("dp", "float", 0.5, "dropout probability DP = p_sc = p_ca", low=0.0, high=0.95),
        Option("path", "choice", "lissajous", "reference path", choices=tuple(PATHS)),
        Option("h", "int", 0, "prediction horizon in slow periods (0: the documented default rule)", low=0, high=200),
        Option("sigma", "floats", mec.DEFAULT_SIGMA, "PETC sigma(i): 1 or 9 values (paper 4.1: 0.1 x4, 0.05 x5; see README)", low=0.0, high=10.0),
        Option("delta", "floats", mec.PAPER_DELTA, "PETC delta(i): 1 or 9 values", low=0.0, high=100.0),
        Option("L_ref", "float", LOOKAHEAD, "pure-pursuit look-ahead distance, m", low=0.01, high=2.0),
        Option("max_silence", "int", 0, "DRHE: also send after this many silent slow periods (0 = off, as the paper)", low=0, high=100_000),
        Option("plant", "choice", "kinematic", "true plant: the kinematic model, or the MJX multibody robot "
               "(pip install 'jaxnc[mjx]'; the estimator keeps the kinematic model)", choices=("kinematic", "mjx")),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
))
