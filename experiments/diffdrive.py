"""Experiment ``diffdrive``: seed 004 (Cuenca et al., Sensors 2019), scenarios a-e of section 5.2.

Runs the five scenarios on the same seeds (common random numbers), prints Table 2
(J1, J2, J3 absolute with 95 % intervals and normalised to scenario a, network packets),
writes ``results.json`` (full configuration), ``paths.png`` (Figs. 5-9, seed 0) and
``control.png`` (Fig. 10: control signal of scenario e, seed 0).  ``F`` sets the noise
factor of scenario e (0.1 low, 0.45 high); ``e_high=true`` adds a run of e at F = 0.45.
"""
from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

from jaxnc import montecarlo
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import fmt, markdown_table
from jaxnc.schemes import diffdrive as dd

PAPER_TABLE2 = {   # Table 2: J1 (mm, sum over NT instants), J2 (mm), J3 (s)
    "a": (1043.4, 38.76, 22.0), "b": (1671.8, 44.55, 22.4), "c": (1029.9, 38.33, 22.0),
    "d": (1684.4, 44.33, 21.6), "e": (1030.0, 38.97, 21.6)}


def build_loops(settings: dict) -> dict[str, dd.DiffDriveLoop]:
    kw = dict(N=settings["N"], lad=settings["lad"], eta=settings["eta"], phi=settings["phi"])
    try:
        loops = {s: dd.diffdrive_loop(s, h=settings["h"], F=(settings["F"] if s == "e" else None), **kw)
                 for s in dd.SCENARIOS}
        if settings["e_high"]:
            loops["e (F=0.45)"] = dd.diffdrive_loop("e", h=settings["h"], F=0.45, **kw)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return loops


def summarise(results: dict) -> dict:
    base = {j: montecarlo.summarize(results["a"][j], results["a"]["unstable"]).mean for j in ("J1", "J2", "J3")}
    out = {}
    for name, m in results.items():
        s = {j: montecarlo.summarize(m[j], m["unstable"]) for j in ("J1", "J1_mean", "J2", "J3", "packets")}
        out[name] = {"absolute": {j: v.to_dict() for j, v in s.items()},
                     "normalised": {j: s[j].mean / base[j] for j in ("J1", "J2", "J3")},
                     "packets_ratio": s["packets"].mean / float(np.mean(results["a"]["packets"])),
                     "unstable_fraction": float(np.mean(m["unstable"]))}
    return out


def table(summary: dict) -> str:
    rows = []
    for name, s in summary.items():
        a, n = s["absolute"], s["normalised"]
        p = PAPER_TABLE2.get(name)   # the paper gives no Table 2 row for F = 0.45
        pa = PAPER_TABLE2["a"]
        cell = lambda j, d=1: fmt(a[j]["mean"], d) + " \u00b1 " + fmt(a[j]["ci95"], d)
        rows.append([name, cell("J1"), fmt(n["J1"]), f"{p[0] / pa[0]:.2f}" if p else "\u2013",
                     cell("J2"), fmt(n["J2"]), f"{p[1] / pa[1]:.2f}" if p else "\u2013",
                     cell("J3", 2), fmt(n["J3"]), fmt(a["packets"]["mean"], 0), fmt(s["packets_ratio"]),
                     f"{100 * s['unstable_fraction']:.1f}"])
    return markdown_table(["scenario", "J1 (mm)", "J1/a", "paper", "J2 (mm)", "J2/a", "paper", "J3 (s)", "J3/a",
                           "packets", "pkt/a", "unstable %"], rows)


def plot_paths(loops: dict, key, out: Path) -> tuple[Path, Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = np.asarray(next(iter(loops.values())).path.points)
    n = len(loops)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.4), sharey=True)
    trajs = {}
    for ax, (name, loop) in zip(np.atleast_1d(axes), loops.items()):
        tr = jax.device_get(jax.jit(dd.simulate)(loop, key))
        trajs[name] = tr
        xy = np.asarray(tr.x[: int(tr.l), 2:4])
        ax.plot(ref[:, 0], ref[:, 1], "k-", lw=1.2)
        ax.plot(xy[:, 0], xy[:, 1], "b-", lw=1.0)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    np.atleast_1d(axes)[0].set_ylabel("y (m)")
    fig.tight_layout()
    f1 = out / "paths.png"
    fig.savefig(f1, dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2 if "e (F=0.45)" in trajs else 1, figsize=(10, 3.4), squeeze=False)
    for ax, name in zip(axes[0], [k for k in ("e", "e (F=0.45)") if k in trajs]):
        tr, T = trajs[name], loops[name].plant.T
        l = int(tr.l)
        t = np.arange(l) * T
        ax.step(t, np.asarray(tr.u)[:l, 0], where="post", label="u_r")
        ax.step(t, np.asarray(tr.u)[:l, 1], where="post", label="u_l")
        ax.set_title(f"control signal, scenario {name}")
        ax.set_xlabel("t (s)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    f2 = out / "control.png"
    fig.savefig(f2, dpi=120)
    plt.close(fig)
    return f1, f2


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    loops = build_loops(settings)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    results = {}
    for name, loop in loops.items():
        m = montecarlo.run_batched(lambda k, loop=loop: dd.run(loop, k), keys, chunk_size=min(64, max(seeds, 1)),
                                   progress=progress, desc=f"scenario {name}")
        results[name] = {k: np.asarray(v) for k, v in m._asdict().items()}
    summary = summarise(results)
    print(f"\nseed 004 differential drive, N={settings['N']}, h={settings['h']}, F(e)={settings['F']}, seeds={seeds}")
    print("J1 = sum over NT instants of the distance to the path (eq. 23), J2 max (eq. 24), J3 time (eq. 25);"
          " '/a' normalised to scenario a, 'paper' the same ratio from Table 2\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    f1, f2 = plot_paths(loops, keys[0], out)
    wall = time.perf_counter() - t0
    config = {"settings": settings, "seeds": seeds,
              "loops": {n: {"scenario": l.scenario, "N": l.N, "h": l.h, "n_slow": l.n_slow, "F": float(l.noise.F),
                            "v_ref": float(l.v_ref), "lad": float(l.lad), "eta": float(l.eta), "phi": float(l.phi),
                            "tau_max": float(l.tau_max), "r": float(l.plant.r), "b": float(l.plant.b),
                            "noise_F1": {k: float(getattr(l.noise, k)) for k in ("wheel", "enc", "cam", "imu")},
                            "path": {"name": l.path.name, "length_m": float(l.path.length),
                                     "waypoints": dd.STAIRS}}
                        for n, l in loops.items()},
              "paper_table2": PAPER_TABLE2}
    montecarlo.save_results(out / "results.json", experiment="diffdrive", config=config, results=summary,
                            wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'}, {f1}, {f2}  ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="diffdrive",
    description="Seed 004: differential-drive robot, scenarios a-e (single/dual rate, delays, EKF + prediction)",
    options=(
        Option("N", "int", 2, "multiplicity: sensing period NT (tau_max must stay below NT)", low=2, high=10),
        Option("h", "int", 1, "prediction horizon of scenario e, in sensing periods", low=1, high=50),
        Option("F", "float", 0.1, "noise factor of scenario e (paper: 0.1 low, 0.45 high)", low=0.0, high=2.0),
        Option("e_high", "bool", True, "also run scenario e at F = 0.45"),
        Option("lad", "float", dd.LAD, "pure-pursuit look-ahead distance, m", low=0.02, high=1.0),
        Option("eta", "float", dd.DELAY_ETA, "delay shift, s (< tau_max = 0.17)", low=0.0, high=0.17),
        Option("phi", "float", dd.DELAY_PHI, "delay scale, s", low=0.0, high=1.0),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
))
