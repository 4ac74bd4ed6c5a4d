"""Experiment ``balancing``: seed 001 (Branz et al. 2020), model-based vs emulation design.

For each network severity (nominal Table 1 fit, more loss, more delay) and each seed, both
designs replay the same pair of network traces and the same noise (common random
numbers).  Reports the fraction of runs that stay upright (|theta| < limit for the whole
run) with a 95 % Wilson interval, the tilt RMS and the final tracking error over the
upright runs, writes ``results.json``, the per-seed metrics (``seeds.npz``,
:func:`jaxnc.load`; dimensions severity, design, seed) and ``balancing.png`` (like Fig. 7: tilt and wheel
angle of both designs for seed 0 at the nominal and the harshest severity).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import numpy as np

from jaxnc import montecarlo, results as per_seed
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import fmt, markdown_table
from jaxnc.schemes import balancing as bal

SEV_CHOICES = (*bal.SEVERITIES, "all")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion k/n."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, c - h), min(1.0, c + h)


def build_loops(settings: dict) -> dict:
    try:
        return {(sev, d): bal.balancing_loop(d, gain=settings["gain"], hold=settings["strategy"] == "hold",
                                             ca=bal.SEVERITIES[sev], N_buf=settings["N_buf"],
                                             horizon_s=settings["horizon"], tau_d=settings["tau_d"])
                for sev in _sevs(settings) for d in bal.DESIGNS}
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _sevs(settings):
    return tuple(bal.SEVERITIES) if settings["severity"] == "all" else (settings["severity"],)


def summarise(m) -> dict:
    up = np.asarray(m.upright, bool)
    n, k = up.size, int(up.sum())
    lo, hi = wilson(k, n)
    return {"upright_fraction": k / n, "upright_ci95": [lo, hi], "n": n,
            "tilt_rms_deg": montecarlo.summarize(m.tilt_rms_deg, ~up).to_dict(),
            "track_rms_mm": montecarlo.summarize(m.track_rms_mm, ~up).to_dict()}


def table(summary: dict) -> str:
    rows = []
    for name, s in summary.items():
        lo, hi = s["upright_ci95"]
        t, e = s["tilt_rms_deg"], s["track_rms_mm"]
        rows.append([name, f"{100 * s['upright_fraction']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]",
                     fmt(t["mean"], 3) + ("" if math.isinf(t["mean"]) else " \u00b1 " + fmt(t["ci95"], 3)),
                     fmt(e["mean"], 2) + ("" if math.isinf(e["mean"]) else " \u00b1 " + fmt(e["ci95"], 2))])
    return markdown_table(["severity / design", "upright % [95 % CI]", "tilt RMS (deg)", "track RMS (mm)"], rows)


def plot(loops: dict, key, out: Path, sevs) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [sevs[0], sevs[-1]] if len(sevs) > 1 else [sevs[0]]
    fig, axes = plt.subplots(2, len(cols), figsize=(6 * len(cols), 5.5), squeeze=False, sharex=True)
    for j, sev in enumerate(cols):
        ch = bal.SEVERITIES[sev]
        for d in bal.DESIGNS:
            loop = loops[(sev, d)]
            sc, ca = bal.traces(key, ch, ch, loop.steps)
            tr = jax.device_get(jax.jit(bal.simulate)(loop, sc, ca, jax.random.fold_in(key, 2)))
            t = np.arange(loop.steps) * loop.T
            lab = f"{d}" + (" (fell)" if bool(tr.failed) else "")
            axes[0, j].plot(t, np.rad2deg(tr.x[:, 1]), lw=0.8, label=lab)
            axes[1, j].plot(t, tr.x[:, 0], lw=0.8, label=lab)
        axes[1, j].plot(t, np.asarray(bal.reference(loop)), "k--", lw=0.8, label="reference")
        axes[0, j].set_title(f"network: {sev} (seed 0)")
        axes[0, j].set_ylabel("tilt (deg)")
        axes[1, j].set_ylabel("wheel angle (rad)")
        axes[1, j].set_xlabel("t (s)")
        axes[0, j].legend(fontsize=8)
        axes[1, j].legend(fontsize=8)
    fig.tight_layout()
    f = out / "balancing.png"
    fig.savefig(f, dpi=120)
    plt.close(fig)
    return f


def run(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    t0 = time.perf_counter()
    loops = build_loops(settings)
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    summary, runs = {}, {}
    for (sev, d), loop in loops.items():
        # the loop's links carry the severity's channel in both directions
        m = montecarlo.run_batched(lambda k, loop=loop: bal.run(loop, k), keys,
                                   chunk_size=min(settings["chunk"], seeds), progress=progress,
                                   desc=f"{sev:>8} {d:>9}")
        summary[f"{sev} / {d}"] = summarise(m)
        runs[(sev, d)] = {**m._asdict(), "unstable": ~np.asarray(m.upright, bool)}   # what summarise leaves out
    print(f"\nseed 001 balancing robot, {seeds} seeds, {settings['horizon']} s, gain={settings['gain']}, "
          f"strategy={settings['strategy']}, N_buf={settings['N_buf']}\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, runs, dims=("severity", "design"))
    fig = plot(loops, keys[0], out, _sevs(settings))
    wall = time.perf_counter() - t0
    config = {"settings": settings, "seeds": seeds,
              "severities": {s: {f: np.asarray(getattr(bal.SEVERITIES[s], f)).tolist()
                                 for f in ("p_gb", "p_bg", "loss_good", "loss_bad", "delay_pmf", "gap_min", "gap_max")}
                             for s in _sevs(settings)}}
    montecarlo.save_results(out / "results.json", experiment="balancing", config=config,
                            results=summary, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'} and {fig}  ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="balancing",
    description="Seed 001: balancing robot at 1 kHz over Wi-Fi, buffered KF (model-based) vs emulation",
    options=(
        Option("severity", "choice", "all", "network severity", choices=SEV_CHOICES),
        Option("gain", "choice", "hold", "model-based gain: hold-aware (eq. 17-19) or plain LQR", choices=("hold", "lqr")),
        Option("strategy", "choice", "hold", "actuator strategy on a missing command", choices=("hold", "zero")),
        Option("N_buf", "int", 10, "buffer length of the Kalman filter", low=1, high=100),
        Option("tau_d", "float", 0.005, "time constant of the differentiating observer, s", low=0.0, high=0.1),
        Option("horizon", "float", 25.0, "simulated time per run, s (step at 15 s)", low=16.0, high=120.0),
        Option("chunk", "int", 128, "seeds per compiled batch", low=1, high=4096),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
))
