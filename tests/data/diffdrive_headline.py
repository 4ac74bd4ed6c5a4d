"""Writes tests/data/diffdrive_headline.json: seed 004's headline numbers (Table 2's J1, J2, J3
and the packets for scenarios a-e, and e without noise) with the builder, on the runner's
own draws, for tests/test_diffdrive.py's equivalence tests.

    PYTHONPATH=. python tests/data/diffdrive_headline.py [--seeds 512] [--base 1]
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxnc import montecarlo
from jaxnc.schemes import diffdrive as dd

ROWS = {"a": dict(scenario="a"), "b": dict(scenario="b"), "c": dict(scenario="c"), "d": dict(scenario="d"),
        "e": dict(scenario="e"), "e (F=0)": dict(scenario="e", F=0.0)}
METRICS = ("J1", "J2", "J3", "J1_ref", "packets")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=512)
    ap.add_argument("--base", type=int, default=1)
    a = ap.parse_args()
    keys = montecarlo.seed_keys(a.base, a.seeds)
    out = {"command": f"PYTHONPATH=. python tests/data/diffdrive_headline.py --seeds {a.seeds} --base {a.base}",
           "seeds": a.seeds, "seed_base": a.base, "rows": {}}
    t0 = time.time()
    for name, kw in ROWS.items():
        m = montecarlo.run_batched(lambda k, lp: dd.run(lp, k), keys, args=(dd.diffdrive_loop(**kw),),
                                   chunk_size=128, progress=False)
        row = {"config": kw, "unstable": int(np.sum(m.unstable))}
        for j in METRICS:
            v = np.asarray(getattr(m, j), np.float64)
            row[j] = {"mean": float(v.mean()), "se": float(v.std(ddof=1) / np.sqrt(len(v)))}
        out["rows"][name] = row
        print(name, {j: round(row[j]["mean"], 3) for j in METRICS}, f"{time.time() - t0:.0f} s", flush=True)
    out["wall_time_s"] = round(time.time() - t0, 1)
    Path(__file__).with_suffix(".json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
