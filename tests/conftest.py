"""Test configuration. Global JAX flags belong here, never in the package."""
import gc
import os

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

# JAX's persistent compilation cache (jaxnc.cache): a second run of the suite on the same
# machine loads the closed loops' programs instead of compiling them. JAXNC_NO_CACHE=1: off.
if not os.environ.get("JAXNC_NO_CACHE"):
    from jaxnc.cache import enable_cache  # noqa: E402
    enable_cache()

# Python's garbage collector set for a process that traces many programs (defaults 700, 10, 10): at the
# defaults its full collections took a fifth to two fifths of a loop's tracing (benchmarks/RESULTS.md, "Helper tr").
gc.set_threshold(100_000, 50, 100)

# Shapes must match exactly; silent broadcasting hides bugs.
jax.config.update("jax_numpy_rank_promotion", "raise")
