"""The Monte-Carlo study shared by the tracking examples (thermal_pid, two_axis_observer):
run the seeds with :func:`jaxnc.loop.run_tracking`, summarise, print and save."""
import time

import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo
from jaxnc import results as results_mod


def summary(metrics, tracking, channels):
    """{name: montecarlo.Summary}: ISE, overshoot (%) and settling time (s) of each tracked
    channel (``channels``: {name suffix: column}), sensor and controller transmissions per period."""
    bad = np.asarray(metrics.unstable)
    out = {}
    for suffix, i in channels.items():
        out[f"ise{suffix}"] = montecarlo.summarize(tracking.ise[:, i], bad)
        out[f"overshoot_pct{suffix}"] = montecarlo.summarize(tracking.overshoot[:, i], bad)
        out[f"settling_time_s{suffix}"] = montecarlo.summarize(tracking.settling_time[:, i], bad)
    out["sensor_rate"] = montecarlo.summarize(metrics.rate_sc, bad)
    out["controller_rate"] = montecarlo.summarize(metrics.rate_ca, bad)
    return out


def per_seed(metrics, tracking, channels):
    """{field: float[S]}: the loop's Metrics and each tracked channel's TrackingMetrics per
    seed (``channels``: {name suffix: column}; the cost only if the loop has one), what :func:`jaxnc.results.save_per_seed` stores."""
    out = {k: np.asarray(v) for k, v in metrics._asdict().items()
           if not (k.startswith("cost") and np.all(np.isnan(v)))}        # a loop without a cost: no cost field
    for suffix, i in channels.items():
        out.update({f"{k}{suffix}": np.asarray(v)[:, i] for k, v in tracking._asdict().items()})
    return out


def run_study(name, title, loop, tracking, channels, settings, *, seeds, out, progress):
    """Run ``seeds`` seeds of ``loop`` from ``settings["seed"]``, print the :func:`summary`
    (mean +- 95 % interval) under ``title`` and save it to ``out/results.json`` (with the settings and
    the whole loop, :func:`jaxnc.results.config_of`), the per-seed
    metrics to ``out/seeds.npz`` (:func:`per_seed`; ``jaxnc.load(out)`` reads them)."""
    t0 = time.time()
    m, tm = montecarlo.run_batched(nc.run_tracking, montecarlo.seed_keys(settings["seed"], seeds),
                                   args=(loop, tracking), chunk_size=min(seeds, 1024), progress=progress, desc=name)
    results = summary(m, tm, channels)
    print(f"{title}, {seeds} seeds:")
    for key, s in results.items():
        print(f"  {key:18s} {s.mean:.4g} +- {s.ci95:.2g} (95 %), not finite or unstable {s.unstable_fraction:.1%}")
    results_mod.save_per_seed(out, {name: per_seed(m, tm, channels)}, experiment=name)    # jaxnc.load(out)
    montecarlo.save_results(out / "results.json", experiment=name,      # the loop that made them, whole
                            config=dict(settings, seeds=seeds, loop=results_mod.config_of(loop)),
                            results=results, wall_time_s=time.time() - t0)
    return results
