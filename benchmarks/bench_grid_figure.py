"""Time the seed-000 grid's heatmap figure (``experiments.mecanum_grid.heatmaps``) on a
4-case x 2-DP grid of made-up normalised indexes, three calls in one process.

    python benchmarks/bench_grid_figure.py
"""
import pathlib
import tempfile
import time

import matplotlib

matplotlib.use("Agg")

from experiments import mecanum_grid as mg  # noqa: E402
from jaxnc.schemes import mecanum as mec  # noqa: E402


def main():
    mg.normalised = lambda results, cell: {j: 1.0 + 0.1 * (hash((cell, j)) % 3) for j in mg.INDEXES}
    results = {("turn180", 1, case, dp): None for case in mec.CASES for dp in (0.0, 0.3)}
    out = pathlib.Path(tempfile.mkdtemp())
    for _ in range(3):
        t = time.perf_counter()
        mg.heatmaps(out, results, "turn180")
        print(f"heatmaps {time.perf_counter() - t:.2f} s")


if __name__ == "__main__":
    main()
