"""The Loop's build-time fit check: the whole check (every role traced once by
``jax.eval_shape``, ``runner._check_fit``) against the value checks a loop of an already
checked structure with new numbers runs (``runner._check_values``: the roles' ``init(ctx)``
and the links' draws), on a two-state loop with PETC, a lossy reordering uplink and an EKF
with a buffer of 2 (the loop of tests/test_lanes.py). Run from the repository root:

    python benchmarks/bench_fit_check.py
"""
import time

import numpy as np

from jaxnc import loop as nc
from jaxnc.loop import runner


def main(repeats: int = 20) -> None:
    plant = nc.LTI(A=[[1.0, 0.1], [0.0, 0.95]], B=[[0.005], [0.1]], C=[[1.0, 0.0]], x0=[1.0, 0.0],
                   w_std=[0.01, 0.02], v_std=[0.05], T=0.1)
    ekf = nc.EKF(plant, Q=np.diag([1e-4, 4e-4]), R=np.eye(1) * 0.0025, mean0=[0.0, 0.0], cov0=np.eye(2), buffer=2)
    up = nc.Link(nc.Bernoulli(0.3), nc.PmfDelay([0.5, 0.3, 0.2]), order="all", capacity=4)
    loop = nc.Loop(plant=plant, trigger=nc.Petc(delta=1e-3), uplink=up, estimator=ekf,
                   controller=nc.StateFeedback([[3.0, 1.5]]), downlink=nc.Link(), actuator=nc.HoldLast(),
                   cost=nc.Quadratic(Q=[1.0, 0.1], R=[0.01]), N=1, steps=60, T=0.1)
    for name, fn in (("whole fit check (_check_fit)", runner._check_fit),
                     ("value checks (_check_values)", runner._check_values)):
        fn(loop)
        t = time.perf_counter()
        for _ in range(repeats):
            fn(loop)
        print(f"{name}: {1e3 * (time.perf_counter() - t) / repeats:.1f} ms")


if __name__ == "__main__":
    main()
