"""Writes tests/data/balancing_headline.json (the stored values of tests/test_balancing.py's
headline tests) from the per-seed results of a ``balancing`` run:

    python -c "from jaxnc.cli import main; main()" run balancing --seeds 512 --out DIR
    python tests/data/balancing_headline.py DIR
"""
import json
import sys
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import jaxnc  # noqa: E402
from tests.test_balancing import HEADLINE, headline_stats  # noqa: E402


def main(out: str) -> None:
    ds = jaxnc.load(out)
    res = json.loads((Path(out) / "results.json").read_text())
    cells = {}
    for sev in ds.severity.values:
        for d in ds.design.values:
            c = ds.sel(severity=sev, design=d)
            m = SimpleNamespace(**{n: c[n].values for n in ("upright", "tilt_rms_deg", "track_rms_mm")})
            cells[f"{sev} / {d}"] = headline_stats(m)
    HEADLINE.write_text(json.dumps({
        "command": f"jaxnc run balancing --seeds {res['config']['seeds']} (defaults: 25 s, seed 0), then "
                   "python tests/data/balancing_headline.py DIR",
        "settings": res["config"]["settings"], "cells": cells}, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1])
