"""The Monte-Carlo study shared by the tracking examples (thermal_pid, two_axis_observer):
run the seeds with :func:`jaxnc.loop.run_tracking`, summarise, print and save."""
import time

import numpy as np

from jaxnc import loop as nc
from jaxnc import montecarlo


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


def run_study(name, title, loop, tracking, channels, settings, *, seeds, out, progress):
    """Run ``seeds`` seeds of ``loop`` from ``settings["seed"]``, print the :func:`summary`
    (mean +- 95 % interval) under ``title`` and save it to ``out/results.json``."""
    t0 = time.time()
    m, tm = montecarlo.run_batched(nc.run_tracking, montecarlo.seed_keys(settings["seed"], seeds),
                                   args=(loop, tracking), chunk_size=min(seeds, 1024), progress=progress, desc=name)
    results = summary(m, tm, channels)
    print(f"{title}, {seeds} seeds:")
    for key, s in results.items():
        print(f"  {key:18s} {s.mean:.4g} +- {s.ci95:.2g} (95 %), not finite or unstable {s.unstable_fraction:.1%}")
    montecarlo.save_results(out / "results.json", experiment=name, config=dict(settings, seeds=seeds),
                            results=results, wall_time_s=time.time() - t0)
    return results
