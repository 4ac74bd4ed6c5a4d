"""jaxnc: JAX-differentiable, vectorised simulation of networked control systems.

The top level re-exports one generation: the runner and its parts (:mod:`jaxnc.loop`,
``jaxnc.Loop``, ``jaxnc.simulate``, ``jaxnc.LTI``, ...), :func:`load` for saved results,
and the study modules. Kernels (filter updates, path geometry, delay quantisation) live in
their packages: :mod:`jaxnc.estimators`, :mod:`jaxnc.paths`, :mod:`jaxnc.network`; the
papers' loops in :mod:`jaxnc.schemes`.
"""
__version__ = "0.1.0"

from jaxnc import montecarlo, metrics, paths, references, results, tracking  # noqa: E402
from jaxnc.results import load  # noqa: E402  (per-seed results as an xarray.Dataset)
from jaxnc import loop  # noqa: E402
from jaxnc.loop import *  # noqa: E402,F401,F403  (the runner's building blocks, listed in jaxnc.loop.__all__)

__all__ = ["__version__", "montecarlo", "metrics", "paths", "references", "results", "tracking", "load",
           "loop", *loop.__all__]
