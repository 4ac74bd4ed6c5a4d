"""Seed 000's headline cell (README *Results*: N = 10, DP = 0.5, Lissajous, DRH and DRHE)
against stored Monte-Carlo values: a statistical regression guard on the runner's own draws.

The stored means and standard errors (``tests/data/mecanum_headline.json``) come from
independent seeds (base seed 1, seeds 0..n-1) and were written by this module's command
line (``python -m tests.test_mecanum_headline --seeds 512``, recorded in the file). The
test runs a small sample (base seed 0) and asserts that every statistic lands within
k = 4 standard errors of the stored mean, the SE combining both samples'
(sqrt(se_stored^2 + se_test^2)); for the unstable fraction, the binomial SE under the
stored proportion p (sqrt(p (1 - p) (1/n_stored + 1/n_test)), p at least one event in
the stored sample), so that a stored 0 still fails a test sample that starts losing
the path (DRH: 0.6 % stored; 3 unstable runs of 64 fail).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest

from experiments.mecanum import run_seed
from jaxnc import montecarlo
from jaxnc.schemes import mecanum as mec

DATA = Path(__file__).parent / "data" / "mecanum_headline.json"
CELL = dict(N=10, dp=0.5, path="lissajous")
CASES = ("DRH", "DRHE")
K_SE = 4.0
TEST_SEEDS = 64


def headline(seed: int, n: int) -> dict:
    """Per case: mean and standard error (over ``n`` seeds of base ``seed``) of the stable
    runs' J1 and J2 (cm) and J3 (s), the sensor transmission rate (packets per fast period
    up to completion, all runs) and the unstable fraction (with its binomial SE)."""
    keys = montecarlo.seed_keys(seed, n)
    out = {}
    for case in CASES:
        loop = montecarlo.uniform_dtypes(mec.mecanum_loop(case, **CELL))     # the cases share one program
        m = montecarlo.run_batched(run_seed, keys, args=(loop,), chunk_size=min(n, 64), progress=False)
        unstable = np.asarray(m.unstable, bool)
        stats = {}
        for name, scale in (("J1", 100.0), ("J2", 100.0), ("J3", 1.0)):
            v = np.asarray(getattr(m, name), float)[~unstable] * scale
            stats[name] = (float(v.mean()), float(v.std(ddof=1) / math.sqrt(len(v))), int(len(v)))
        rate = np.asarray(m.tx_sc, float) / np.asarray(m.l, float)
        stats["rate"] = (float(rate.mean()), float(rate.std(ddof=1) / math.sqrt(n)), n)
        p = float(unstable.mean())
        stats["unstable"] = (p, math.sqrt(p * (1 - p) / n), n)
        out[case] = {k: dict(mean=a, se=b, n=c) for k, (a, b, c) in stats.items()}
    return out


def outside(stored: dict, now: dict, k: float = K_SE) -> list[str]:
    """The statistics of ``now`` farther than ``k`` combined SEs from ``stored``'s means."""
    bad = []
    for case, stats in stored.items():
        for name, ref in stats.items():
            got = now[case][name]
            se = math.hypot(ref["se"], got["se"])
            if name == "unstable":      # binomial SE under the stored proportion, at least one event's
                p = min(max(ref["mean"], 1 / ref["n"]), 1 - 1 / ref["n"])
                se = math.sqrt(p * (1 - p) * (1 / ref["n"] + 1 / got["n"]))
            if not abs(got["mean"] - ref["mean"]) <= k * se:
                bad.append(f"{case} {name}: {got['mean']:.4g} vs stored {ref['mean']:.4g} (SE {se:.3g})")
    return bad


def test_headline_cell_matches_the_stored_values():
    """DRH and DRHE at N = 10, DP = 0.5: every statistic within 4 combined SEs of the stored mean."""
    stored = json.loads(DATA.read_text())["cases"]
    bad = outside(stored, headline(0, TEST_SEEDS))
    assert not bad, "; ".join(bad)


def test_the_guard_fails_beyond_k_standard_errors():
    """The comparison flags a mean 4.5 combined SEs away and passes one 3.5 away; against
    a stored unstable fraction of 0 of 512, 1 unstable run of 64 passes and 2 fail."""
    ref = {"C": {"J1": dict(mean=1.0, se=0.03, n=100), "unstable": dict(mean=0.0, se=0.0, n=512)}}
    se = math.hypot(0.03, 0.04)
    zero = dict(mean=0.0, se=0.0, n=64)
    assert outside(ref, {"C": {"J1": dict(mean=1.0 + 3.5 * se, se=0.04, n=64), "unstable": zero}}) == []
    assert len(outside(ref, {"C": {"J1": dict(mean=1.0 - 4.5 * se, se=0.04, n=64), "unstable": zero}})) == 1
    j1 = dict(mean=1.0, se=0.04, n=64)
    for events, flagged in ((1, 0), (2, 1)):
        p = events / 64
        got = dict(mean=p, se=math.sqrt(p * (1 - p) / 64), n=64)
        assert len(outside(ref, {"C": {"J1": j1, "unstable": got}})) == flagged


def test_stored_values_are_well_formed():
    """The stored file names its command and holds every case and statistic with n > 0."""
    stored = json.loads(DATA.read_text())
    assert "test_mecanum_headline" in stored["command"]
    assert stored["cell"] == CELL
    for case in CASES:
        assert set(stored["cases"][case]) == {"J1", "J2", "J3", "rate", "unstable"}
        for s in stored["cases"][case].values():
            assert s["n"] > 0 and s["se"] >= 0 and math.isfinite(s["mean"])


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="write tests/data/mecanum_headline.json")
    ap.add_argument("--seeds", type=int, default=512)
    a = ap.parse_args()
    cmd = f"python -m tests.test_mecanum_headline --seeds {a.seeds}"
    res = dict(command=cmd, seed=1, seeds=a.seeds, cell=CELL, cases=headline(1, a.seeds),
               jax=jax.__version__)
    DATA.parent.mkdir(exist_ok=True)
    DATA.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res, indent=1))
