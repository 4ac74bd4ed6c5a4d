"""Experiment ``balancing``: seed 001 (Branz et al. 2020), model-based vs emulation design.

For each network severity (nominal Table 1 fit, more loss, more delay) and each seed, both
designs replay the same pair of network traces and the same noise (common random
numbers).  Reports the fraction of runs that stay upright (|theta| < limit for the whole
run) with a 95 % Wilson interval, the tilt RMS and the final tracking error over the
upright runs, writes ``results.json``, the per-seed metrics (``seeds.npz``,
:func:`jaxnc.load`; dimensions severity, design, seed), ``fig7_time_responses.png``
(Fig. 7: tilt and wheel angle of both designs for seed 0, on the same network traces and
noise, at each severity run) and ``fig5_loopback_cdf.png`` / ``.csv`` (Fig. 5: the
loop-back delay CDF of the network model at the three noise levels of section 4).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import numpy as np

from jaxnc import montecarlo, wifi, results as per_seed
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import fmt, markdown_table
from jaxnc.plants.balancing import TILT_SENSORS, Balancing
from jaxnc.schemes import balancing as bal

SEV_CHOICES = (*bal.SEVERITIES, "all")
_CHANNEL_FIELDS = ("p_gb", "p_bg", "loss_good", "loss_bad", "loss_extra", "delay_pmf", "gap_min", "gap_max")


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
        plant = Balancing(tilt_sensor=settings["tilt_sensor"])
        return {(sev, d): bal.balancing_loop(d, plant=plant, gain=settings["gain"], hold=settings["strategy"] == "hold",
                                             ca=bal.SEVERITIES[sev], N_buf=settings["N_buf"],
                                             horizon_s=settings["horizon"], derivative=settings["derivative"],
                                             tau_d=settings["tau_d"] if settings["derivative"] == "filtered" else None)
                for sev in _sevs(settings) for d in bal.DESIGNS}
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _derivative(settings) -> str:
    return "simple" if settings["derivative"] == "simple" else f"filtered (tau_d = {settings['tau_d']} s)"


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


def fig7(loops: dict, key, out: Path, sevs) -> Path:
    """Fig. 7: tilt and wheel angle of both designs on the same network realisation and
    noise (``key``, common random numbers), one column per severity."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(sevs), figsize=(5.5 * len(sevs), 5.5), squeeze=False, sharex=True)
    sim = jax.jit(bal.simulate)
    for j, sev in enumerate(sevs):
        ch = bal.SEVERITIES[sev]
        for d in bal.DESIGNS:
            loop = loops[(sev, d)]
            sc, ca = bal.traces(key, ch, ch, loop.steps)
            tr = jax.device_get(sim(loop, sc, ca, jax.random.fold_in(key, 2)))
            end = int(tr.fail_step) + 1 if bool(tr.failed) else loop.steps
            t = np.arange(end) * loop.T
            lab = d + (f" (fell at {t[-1]:.2f} s)" if bool(tr.failed) else "")
            axes[0, j].plot(t, np.rad2deg(tr.x[:end, 1]), lw=0.8, label=lab)
            axes[1, j].plot(t, tr.x[:end, 0] + tr.x[:end, 1], lw=0.8, label=lab)     # gamma = delta + theta
        t = np.arange(loop.steps) * loop.T
        axes[1, j].plot(t, np.asarray(bal.reference(loop)), "k--", lw=0.8, label="reference")
        axes[0, j].set_title(f"network: {sev} (seed 0, both designs on the same traces)", fontsize=9)
        axes[0, j].set_ylabel("tilt \u03b8 (deg)")
        axes[1, j].set_ylabel("wheel angle \u03b3 = \u03b4 + \u03b8 (rad)")
        axes[1, j].set_xlabel("t (s)")
        axes[0, j].legend(fontsize=8)
        axes[1, j].legend(fontsize=8)
    fig.tight_layout()
    f = out / "fig7_time_responses.png"
    fig.savefig(f, dpi=120)
    plt.close(fig)
    return f


FIG5_RUNS, FIG5_PACKETS, FIG5_MAX_DELAY = 10, 60_000, 20     # like the paper: 10 runs (of 60 s at 1 kHz)


def fig5(key, out: Path) -> tuple[Path, dict]:
    """Fig. 5: the loop-back delay CDF at the three noise levels of section 4
    (``bal.NOISE_LEVELS``), each the mean of the CDFs of ``FIG5_RUNS`` generated runs
    (the same keys at every level). Writes ``fig5_loopback_cdf.png`` and ``.csv``; returns
    the figure's path and, per level, the CDF and the Table-1 statistics (run means)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(np.arange(FIG5_RUNS))
    data = {}
    for name, ch in bal.NOISE_LEVELS.items():
        lb = np.asarray(_loopback_runs(keys, ch))
        cdf = np.mean([wifi.delay_cdf(t, FIG5_MAX_DELAY) for t in lb], axis=0)
        stats = np.mean([wifi.loopback_stats(t) for t in lb], axis=0)
        data[name] = {"cdf": cdf.tolist(), "stats": dict(zip(wifi.LoopbackStats._fields, stats.tolist()))}
    fig, ax = plt.subplots(figsize=(6, 4))
    d = np.arange(FIG5_MAX_DELAY + 1)
    for name, v in data.items():
        ax.step(d, v["cdf"], where="post", label=f"{name} (PER {v['stats']['per_mean']:.1f} %)")
    ax.set_xlabel("loop-back delay (steps of 1 ms)")
    ax.set_ylabel("CDF (delivered packets)")
    ax.set_title(f"loop-back delay CDF, network model, mean of {FIG5_RUNS} runs of {FIG5_PACKETS // 1000} s",
                 fontsize=9)
    ax.set_xlim(0, FIG5_MAX_DELAY)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    f = out / "fig5_loopback_cdf.png"
    fig.savefig(f, dpi=120)
    plt.close(fig)
    rows = ["delay_steps," + ",".join(data)]
    rows += [f"{k}," + ",".join(f"{v['cdf'][k]:.6f}" for v in data.values()) for k in d]
    (out / "fig5_loopback_cdf.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return f, data


@jax.jit
def _loopback_runs(keys, ch):
    """int32[runs, FIG5_PACKETS]: loop-back traces of one channel in both directions."""
    def one(k):
        f = wifi.sample_trace(jax.random.fold_in(k, 0), ch, FIG5_PACKETS)
        b = wifi.sample_trace(jax.random.fold_in(k, 1), ch, FIG5_PACKETS)
        return wifi.loopback(f, b)
    return jax.vmap(one)(keys)


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
          f"strategy={settings['strategy']}, N_buf={settings['N_buf']}, emulation derivative={_derivative(settings)}, "
          f"tilt sensor={settings['tilt_sensor']}\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, runs, dims=("severity", "design"))
    figs = [fig7(loops, keys[0], out, _sevs(settings))]
    f5, loopback = fig5(jax.random.fold_in(jax.random.PRNGKey(settings["seed"]), 5), out)
    figs.append(f5)
    print("\nnetwork model at the noise levels of Fig. 5 (loop-back, means of "
          f"{FIG5_RUNS} runs of {FIG5_PACKETS // 1000} s; the -21/-19 dBm interferer is ours)\n")
    print(markdown_table(["noise", "delay median / std / max", "P(delay <= 3)", "PER %"],
                         [[n, f"{v['stats']['delay_median']:.0f} / {v['stats']['delay_std']:.2f} / "
                              f"{v['stats']['delay_max']:.1f}", f"{v['cdf'][3]:.3f}", f"{v['stats']['per_mean']:.1f}"]
                          for n, v in loopback.items()]))
    wall = time.perf_counter() - t0
    config = {"settings": settings, "seeds": seeds,
              "severities": {s: {f: np.asarray(getattr(bal.SEVERITIES[s], f)).tolist()
                                 for f in _CHANNEL_FIELDS}
                             for s in _sevs(settings)},
              "noise_levels": {n: {f: np.asarray(getattr(ch, f)).tolist() for f in _CHANNEL_FIELDS}
                               for n, ch in bal.NOISE_LEVELS.items()},
              "fig5": {"runs": FIG5_RUNS, "packets": FIG5_PACKETS, "loopback": loopback}}
    montecarlo.save_results(out / "results.json", experiment="balancing", config=config,
                            results=summary, wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'}, {', '.join(str(f) for f in figs)}  ({wall:.1f} s)")
    return summary


EXPERIMENT = register(Experiment(
    name="balancing",
    description="Seed 001: balancing robot at 1 kHz over Wi-Fi, buffered KF (model-based) vs emulation",
    options=(
        Option("severity", "choice", "all", "network severity", choices=SEV_CHOICES),
        Option("gain", "choice", "hold", "model-based gain: hold-aware (eq. 17-19) or plain LQR", choices=("hold", "lqr")),
        Option("strategy", "choice", "hold", "actuator strategy on a missing command", choices=("hold", "zero")),
        Option("N_buf", "int", 10, "buffer length of the Kalman filter", low=1, high=100),
        Option("derivative", "choice", "simple", "emulation design's rates: simple differentiation (the paper's) "
               "or a filtered derivative", choices=bal.DERIVATIVES),
        Option("tau_d", "float", 0.005, "time constant of the filtered derivative (derivative=filtered), s",
               low=1e-4, high=0.1),
        Option("tilt_sensor", "choice", "complementary", "tilt measurement error: the complementary filter's "
               "(Gauss-Markov) or white 0.1 deg", choices=TILT_SENSORS),
        Option("horizon", "float", 25.0, "simulated time per run, s (step at 15 s)", low=16.0, high=120.0),
        Option("chunk", "int", 128, "seeds per compiled batch", low=1, high=4096),
        Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
    ),
    run=run,
))
