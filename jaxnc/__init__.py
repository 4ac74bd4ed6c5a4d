"""jaxnc: JAX-differentiable, vectorised simulation of networked control systems."""
__version__ = "0.1.0"

from jaxnc import montecarlo, metrics, paths, references, results, tracking  # noqa: E402
from jaxnc.results import load  # noqa: E402  (per-seed results as an xarray.Dataset)
from jaxnc.controllers import PathFollower, pure_pursuit_curvature, pure_pursuit_velocity  # noqa: E402
from jaxnc.estimators import Gaussian, ekf_predict, ekf_update, nudrekf_correct, predict_horizon  # noqa: E402
from jaxnc.network import Channel, sample_channel  # noqa: E402
from jaxnc.plants import Mecanum, MecanumNoise  # noqa: E402
from jaxnc import loop  # noqa: E402
from jaxnc.loop import *  # noqa: E402,F401,F403  (the runner's building blocks, listed in jaxnc.loop.__all__)

__all__ = [
    "__version__", "montecarlo", "metrics", "paths", "references", "results", "tracking", "load",
    "Channel", "sample_channel",
    "Gaussian", "ekf_predict", "ekf_update", "nudrekf_correct", "predict_horizon",
    "Mecanum", "MecanumNoise", "PathFollower", "pure_pursuit_velocity", "pure_pursuit_curvature",
    "loop", *loop.__all__,
]
