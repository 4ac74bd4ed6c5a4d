"""Experiment ``balancing``: seed 001 (Branz et al. 2020), model-based vs emulation design.

For each network severity (nominal Table 1 fit, more loss, more delay) and each seed, both
designs meet the same network and noise: the runner's draws from the seed's key (common
random numbers).  Reports the fraction of runs that stay upright (|theta| < limit for the whole
run) with a 95 % Wilson interval, the tilt RMS and the final tracking error over the
upright runs, writes ``results.json``, the per-seed metrics (``seeds.npz``,
:func:`jaxnc.load`; dimensions severity, design, seed), ``fig7_time_responses.png``
(Fig. 7: tilt and wheel angle of both designs for seed 0, on the same network and noise,
at each severity run) and ``fig5_loopback_cdf.png`` / ``.csv`` (Fig. 5: the
loop-back delay CDF of the network model at the three noise levels of section 4).

Experiment ``balancing-sweep``: the same two designs and outcomes as one network parameter
is made harsher, one axis at a time (:data:`jaxnc.schemes.balancing.SWEEP_AXES`: the
burst length and the loss in a burst through the *loss* severity, the delay law from the
Table-1 fit through the *delay* severity and beyond), both directions alike, the other
settings at their defaults. Each (axis, value, design) is stored as soon as it is done
(``OUT/points/<axis>_<value>_<design>-<hash>.json`` with its configuration, named by a
hash of it, and ``.npz`` with the per-seed metrics), so an interrupted run resumes where
it stopped; a point stored with another configuration is computed again. Writes ``sweep.md`` (a table per axis with each
point's verdict, :data:`VERDICTS`), ``fig_sweep.png`` (upright % with 95 % Wilson
intervals and tilt RMS against each parameter, both designs) and ``results.json``.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo, wifi, results as per_seed
from jaxnc.experiment import ConfigError, Experiment, Option, register
from jaxnc.report import fmt, markdown_table, save_figure
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


def run_seed(key, loop):
    """Per-seed :class:`~jaxnc.schemes.balancing.Metrics` with the loop as an argument, for
    ``run_batched(run_seed, keys, args=(loop,))`` (module level: one compiled program per loop structure)."""
    return bal.run(loop, key)


def design_loop(settings: dict, design: str, channel: wifi.WifiChannel):
    """The loop of ``design`` with the settings' design options on ``channel`` (both
    directions); ConfigError for a bad setting."""
    try:
        return bal.balancing_loop(design, plant=Balancing(tilt_sensor=settings["tilt_sensor"]), gain=settings["gain"],
                                  hold=settings["strategy"] == "hold", ca=channel, N_buf=settings["N_buf"],
                                  horizon_s=settings["horizon"], derivative=settings["derivative"],
                                  tau_d=settings["tau_d"] if settings["derivative"] == "filtered" else None,
                                  kf_tilt=settings["kf_tilt"])
    except ValueError as e:
        raise ConfigError(str(e)) from None


def build_loops(settings: dict) -> dict:
    return {(sev, d): design_loop(settings, d, bal.SEVERITIES[sev]) for sev in _sevs(settings) for d in bal.DESIGNS}


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


def _upright_text(s: dict) -> str:
    lo, hi = s["upright_ci95"]
    return f"{100 * s['upright_fraction']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def _rms_text(t: dict, digits: int = 3) -> str:
    ok = math.isfinite(t["mean"]) and math.isfinite(t["ci95"])      # no interval from < 2 upright runs
    return fmt(t["mean"], digits) + (" \u00b1 " + fmt(t["ci95"], digits) if ok else "")


def table(summary: dict) -> str:
    rows = [[name, _upright_text(s), _rms_text(s["tilt_rms_deg"], 3), _rms_text(s["track_rms_mm"], 2)]
            for name, s in summary.items()]
    return markdown_table(["severity / design", "upright % [95 % CI]", "tilt RMS (deg)", "track RMS (mm)"], rows)


def fig7(loops: dict, key, out: Path, sevs) -> Path:
    """Fig. 7: tilt and wheel angle of both designs on the same network realisation and
    noise (``key``, common random numbers), one column per severity."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(sevs), figsize=(5.5 * len(sevs), 5.5), squeeze=False, sharex=True)
    sim = jax.jit(nc.simulate)
    for j, sev in enumerate(sevs):
        for d in bal.DESIGNS:
            loop = loops[(sev, d)]
            tr = jax.device_get(sim(loop, key))
            end = int(tr.fail_step) + 1 if bool(tr.failed) else loop.steps
            t = np.arange(end) * loop.T
            lab = d + (f" (fell at {t[-1]:.2f} s)" if bool(tr.failed) else "")
            axes[0, j].plot(t, np.rad2deg(tr.x[:end, 1]), lw=0.8, label=lab)
            axes[1, j].plot(t, tr.x[:end, 0] + tr.x[:end, 1], lw=0.8, label=lab)     # gamma = delta + theta
        t = np.arange(loop.steps) * loop.T
        axes[1, j].plot(t, np.asarray(bal.reference(loop)), "k--", lw=0.8, label="reference")
        axes[0, j].set_title(f"network: {sev} (seed 0, both designs on the same draws)", fontsize=9)
        axes[0, j].set_ylabel("tilt \u03b8 (deg)")
        axes[1, j].set_ylabel("wheel angle \u03b3 = \u03b4 + \u03b8 (rad)")
        axes[1, j].set_xlabel("t (s)")
        axes[0, j].legend(fontsize=8)
        axes[1, j].legend(fontsize=8)
    f = save_figure(fig, out / "fig7_time_responses.png", dpi=120)
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
    f = save_figure(fig, out / "fig5_loopback_cdf.png", dpi=120)
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
        # the loop's links carry the severity's channel in both directions; uniform dtypes as
        # in run_sweep, so that the severities and the sweep's points of a design share a program
        m = montecarlo.run_batched(run_seed, keys, args=(montecarlo.uniform_dtypes(loop),),
                                   chunk_size=min(settings["chunk"], seeds), progress=progress,
                                   desc=f"{sev:>8} {d:>9}")
        summary[f"{sev} / {d}"] = summarise(m)
        runs[(sev, d)] = {**m._asdict(), "unstable": ~np.asarray(m.upright, bool)}   # what summarise leaves out
    print(f"\nseed 001 balancing robot, {seeds} seeds, {settings['horizon']} s, gain={settings['gain']}, "
          f"strategy={settings['strategy']}, N_buf={settings['N_buf']}, emulation derivative={_derivative(settings)}, "
          f"tilt sensor={settings['tilt_sensor']}, filter's tilt R={settings['kf_tilt']}\n")
    print(table(summary))
    out.mkdir(parents=True, exist_ok=True)
    per_seed.save_per_seed(out, runs, dims=("severity", "design"), experiment="balancing", units=bal.Metrics.UNITS)
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


# ----------------------------------------------------------------------------- severity sweep

SWEEP_CHOICES = (*bal.SWEEP_AXES, "all")
_DESIGN_KEYS = ("gain", "strategy", "N_buf", "derivative", "tau_d", "tilt_sensor", "horizon", "seed")
# a point's verdict (docs/balancing.md): "emulation falls in most runs" is the upper 95 %
# Wilson bound of its upright fraction below 1/2
VERDICTS = {
    "separates": "emulation falls in most runs, model-based upright in every run",
    "model falls": "emulation falls in most runs, model-based falls in some",
    "both fall": "both fall in most runs",
    "emulation up": "emulation not shown to fall in most runs",
}


def sweep_points(settings: dict) -> list[tuple[str, float]]:
    """The (axis, value) points of a sweep run: the chosen axes' values, in order."""
    axes = tuple(bal.SWEEP_AXES) if settings["axis"] == "all" else (settings["axis"],)
    return [(a, float(v)) for a in axes for v in settings[a]]


def point_file(out: Path, cfg: dict) -> Path:
    """The file of the sweep point whose configuration is ``cfg`` (:func:`jaxnc.sweep.cell_path`)."""
    from jaxnc.sweep import cell_path
    return cell_path(Path(out) / "points", f"{cfg['axis']}_{cfg['value']:g}_{cfg['design']}", cfg)


def _channel_config(ch: wifi.WifiChannel) -> dict:
    return {f: np.asarray(getattr(ch, f)).tolist() for f in _CHANNEL_FIELDS}


def channel_stats(ch: wifi.WifiChannel, N_buf: int) -> dict:
    """One-way statistics of a channel from its parameters (no sampling): loss, delay
    median (first d with CDF >= 1/2) and mean over the delivered packets, and the
    probabilities that a packet arrives within the model-based design's lead (2 steps)
    and within its filter's buffer (N_buf steps)."""
    pmf = np.asarray(ch.delay_pmf, np.float64)
    cdf = np.cumsum(pmf)
    return {"loss": wifi.stationary_loss(ch), "delay_median": int(np.searchsorted(cdf, 0.5)),
            "delay_mean": float(pmf @ np.arange(pmf.size)), "max_delay": ch.max_delay,
            "in_time_lead2": wifi.delivery_probability(ch, 2), "within_buffer": wifi.delivery_probability(ch, N_buf)}


def verdict(model: dict, emulation: dict) -> str:
    """The point's key in :data:`VERDICTS` from the two designs' summaries."""
    emu_falls = emulation["upright_ci95"][1] < 0.5
    if not emu_falls:
        return "emulation up"
    if model["upright_fraction"] == 1.0:
        return "separates"
    return "both fall" if model["upright_ci95"][1] < 0.5 else "model falls"


def sweep_table(points: list[dict]) -> str:
    """Markdown table of one axis: channel statistics, both designs, verdict."""
    rows = [[f"{p['value']:g}", f"{100 * p['channel']['loss']:.1f}", str(p["channel"]["delay_median"]),
             f"{p['channel']['in_time_lead2']:.3f}", _upright_text(p["model"]), _rms_text(p["model"]["tilt_rms_deg"]),
             _upright_text(p["emulation"]), _rms_text(p["emulation"]["tilt_rms_deg"]), p["verdict"]]
            for p in points]
    return markdown_table(["value", "loss %", "delay median", "P(in time, 2)", "model upright % [95 % CI]",
                           "model tilt RMS", "emulation upright % [95 % CI]", "emulation tilt RMS", "verdict"], rows)


def fig_sweep(out: Path, axes: dict) -> Path:
    """Upright fraction (95 % Wilson intervals) and tilt RMS (over the upright runs) of both
    designs against each axis's parameter; the main table's severity dashed, the former
    *loss* severity dotted."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, len(axes), figsize=(4.8 * len(axes), 6.4), squeeze=False, sharex="col")
    for j, (name, a) in enumerate(axes.items()):
        x = np.array([p["value"] for p in a["points"]])
        for d, mk in zip(bal.DESIGNS, ("o", "s")):
            s = [p[d] for p in a["points"]]
            f = 100 * np.array([q["upright_fraction"] for q in s])
            ci = 100 * np.array([q["upright_ci95"] for q in s])
            ax[0, j].errorbar(x, f, yerr=[f - ci[:, 0], ci[:, 1] - f], marker=mk, capsize=3, lw=1, label=d)
            t = np.array([q["tilt_rms_deg"]["mean"] for q in s], float)
            e = np.array([q["tilt_rms_deg"]["ci95"] for q in s], float)
            t[~np.isfinite(t)] = np.nan
            ax[1, j].errorbar(x, t, yerr=np.nan_to_num(e), marker=mk, capsize=3, lw=1, label=d)
        for r in (0, 1):
            ax[r, j].axvline(a["main_table_point"], color="k", ls="--", lw=0.8,
                             label="the main table's severity" if r == 0 else None)
            if a.get("former_loss_severity") is not None:
                ax[r, j].axvline(a["former_loss_severity"], color="gray", ls=":", lw=1,
                                 label="the former loss severity" if r == 0 else None)
            ax[r, j].grid(alpha=0.3)
            if name == "burst_length":
                ax[r, j].set_xscale("log")
        ax[0, j].axhline(50, color="gray", lw=0.6)
        ax[0, j].set_ylim(-5, 105)
        ax[0, j].set_title(name, fontsize=10)
        ax[0, j].set_ylabel("upright % [95 % Wilson CI]")
        ax[1, j].set_ylabel("tilt RMS over upright runs (deg)")
        ax[1, j].set_xlabel(a["label"], fontsize=8)
        ax[0, j].legend(fontsize=8)
    n = next(iter(axes.values()))["points"][0]["model"]["n"]
    fig.suptitle(f"seed 001 severity sweep: one network parameter at a time, {n} seeds per point", fontsize=10)
    f = save_figure(fig, Path(out) / "fig_sweep.png", dpi=120)
    return f


def run_sweep(settings: dict, *, seeds: int, out: Path, progress: bool = True) -> dict:
    """The ``balancing-sweep`` experiment (the module docstring; docs/balancing.md)."""
    from tqdm.auto import tqdm

    from jaxnc import sweep as cells

    t0 = time.perf_counter()
    out = Path(out)
    points = sweep_points(settings)
    try:
        channels = {(a, v): bal.sweep_channel(a, v) for a, v in points}
    except ValueError as e:
        raise ConfigError(str(e)) from None
    loops = {(a, v, d): design_loop(settings, d, channels[(a, v)]) for a, v in points for d in bal.DESIGNS}
    keys = montecarlo.seed_keys(settings["seed"], seeds)
    design_cfg = {k: settings[k] for k in _DESIGN_KEYS}
    results, todo, compute_s = {}, [], {}
    cfgs = {(a, v, d): {"design_options": design_cfg, "seeds": seeds, "axis": a, "value": v, "design": d,
                        "channel": _channel_config(channels[(a, v)]), "kf_tilt": settings["kf_tilt"],
                        "chunk": settings["chunk"], "devices": len(jax.local_devices())}
            for (a, v, d) in loops}
    for (a, v, d), cfg in cfgs.items():
        data = cells.load_cell(point_file(out, cfg), cfg)
        if data is None:
            todo.append(((a, v, d), cfg))
        else:
            results[(a, v, d)] = data["summary"]
            compute_s[(a, v, d)] = float(data.get("wall_time_s", 0.0))
    bar = tqdm(total=len(loops), initial=len(loops) - len(todo), desc="sweep points", unit="run",
               disable=not progress, dynamic_ncols=True)
    for (a, v, d), cfg in todo:
        bar.set_postfix_str(f"{a}={v:g} {d}")
        tc = time.perf_counter()
        m = montecarlo.run_batched(run_seed, keys, args=(montecarlo.uniform_dtypes(loops[(a, v, d)]),),
                                   chunk_size=min(settings["chunk"], seeds), progress=False)
        s = summarise(m)
        arrays = {**{k: np.asarray(x) for k, x in m._asdict().items()}, "unstable": ~np.asarray(m.upright, bool)}
        compute_s[(a, v, d)] = time.perf_counter() - tc
        cells.save_cell(point_file(out, cfg), {"config": cfg, "summary": s, "wall_time_s": compute_s[(a, v, d)]},
                        arrays=arrays)
        results[(a, v, d)] = s
        bar.update(1)
    bar.close()
    axes = {}
    for a in dict.fromkeys(a for a, _ in points):
        label, _, main, former = bal.SWEEP_AXES[a]
        pts = []
        for ax_, v in points:
            if ax_ != a:
                continue
            p = {"value": v, "channel": channel_stats(channels[(a, v)], settings["N_buf"]),
                 **{d: results[(a, v, d)] for d in bal.DESIGNS}}
            p["verdict"] = verdict(p["model"], p["emulation"])
            pts.append(p)
        axes[a] = {"label": label, "main_table_point": main, "former_loss_severity": former, "points": pts}
    print(f"\nseed 001 severity sweep, {seeds} seeds per point, {settings['horizon']} s, emulation derivative="
          f"{_derivative(settings)}, tilt sensor={settings['tilt_sensor']}; verdicts: "
          + "; ".join(f"{k} = {t}" for k, t in VERDICTS.items()))
    text = [f"# Seed 001 severity sweep ({seeds} seeds per point)", "",
            "Verdicts: " + "; ".join(f"*{k}*: {t}" for k, t in VERDICTS.items()) +
            " (falls in most runs: the upper 95 % Wilson bound of upright below 50 %).", ""]
    for a, ax_ in axes.items():
        text += [f"## {a}: {ax_['label']} (main table: {ax_['main_table_point']:g})", "", sweep_table(ax_["points"]), ""]
    print("\n" + "\n".join(text[4:]))
    (out / "sweep.md").write_text("\n".join(text), encoding="utf-8")
    fig = fig_sweep(out, axes)
    wall = time.perf_counter() - t0
    # this run's counts; the compute time of every stored point, whichever run computed it
    summary = {"axes": axes, "verdicts": VERDICTS, "computed": len(todo), "reused": len(loops) - len(todo),
               "compute_time_total_s": sum(compute_s.values()),
               "per_seed": per_seed.per_seed_index(out, {k: point_file(out, c).with_suffix(".npz")
                                                         for k, c in cfgs.items()},
                                                   dims=("axis", "value", "design"))}
    config = {"settings": settings, "seeds": seeds,
              "channels": {f"{a}={v:g}": _channel_config(ch) for (a, v), ch in channels.items()}}
    montecarlo.save_results(out / "results.json", experiment="balancing-sweep", config=config, results=summary,
                            wall_time_s=wall)
    print(f"\nwrote {out / 'results.json'}, {out / 'sweep.md'}, {fig}  ({wall:.1f} s)")
    return summary


# the design options, shared by balancing and balancing-sweep
DESIGN_OPTIONS = (
    Option("gain", "choice", "hold", "model-based gain: hold-aware (eq. 17-19) or plain LQR", choices=("hold", "lqr")),
    Option("strategy", "choice", "hold", "actuator strategy on a missing command", choices=("hold", "zero")),
    Option("N_buf", "int", 10, "buffer length of the Kalman filter", low=1, high=100),
    Option("derivative", "choice", "simple", "emulation design's rates: simple differentiation (the paper's) "
           "or a filtered derivative", choices=bal.DERIVATIVES),
    Option("tau_d", "float", 0.005, "time constant of the filtered derivative (derivative=filtered), s",
           low=1e-4, high=0.1),
    Option("tilt_sensor", "choice", "complementary", "tilt measurement error: the complementary filter's "
           "(Gauss-Markov) or white 0.1 deg", choices=TILT_SENSORS),
    Option("kf_tilt", "choice", "design", "model-based filter's tilt noise R: the design's white 0.1 deg, or the "
           "tilt sensor's stationary error variance", choices=bal.KF_TILT_NOISES),
    Option("horizon", "float", 25.0, "simulated time per run, s (step at 15 s)", low=16.0, high=120.0),
    Option("chunk", "int", 128, "seeds per compiled batch", low=1, high=4096),
    Option("seed", "int", 0, "base random seed", low=0, high=2**31 - 1),
)

EXPERIMENT = register(Experiment(
    name="balancing",
    description="Seed 001: balancing robot at 1 kHz over Wi-Fi, buffered KF (model-based) vs emulation",
    options=(Option("severity", "choice", "all", "network severity", choices=SEV_CHOICES), *DESIGN_OPTIONS),
    run=run,
))

SWEEP = register(Experiment(
    name="balancing-sweep",
    description="Seed 001: upright fraction and tilt RMS of both designs as one network parameter gets harsher "
                "(resumable per point)",
    options=(
        Option("axis", "choice", "all", "sweep axis (jaxnc.schemes.balancing.SWEEP_AXES)", choices=SWEEP_CHOICES),
        Option("burst_length", "floats", bal.SWEEP_AXES["burst_length"][1],
               "mean burst length 1/p_bg in packets (ms), at the loss severity's p_gb and loss_bad", low=1.0, high=1e5),
        Option("burst_loss", "floats", bal.SWEEP_AXES["burst_loss"][1],
               "loss in a burst (loss_bad), at the loss severity's burst length and rate", low=0.0, high=1.0),
        Option("delay", "floats", bal.SWEEP_AXES["delay"][1],
               "delay-law index lambda (0 Table 1, 1 the delay severity, up to 1.75 stretched)",
               low=0.0, high=bal.MAX_DELAY_INDEX),
        *DESIGN_OPTIONS,
    ),
    run=run_sweep,
    keeps_cells=True,
))
