"""Test configuration. Global JAX flags belong here, never in the package."""
import os

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

# JAX's persistent compilation cache (jaxnc.cache): a second run of the suite on the same
# machine loads the closed loops' programs instead of compiling them. JAXNC_NO_CACHE=1: off.
if not os.environ.get("JAXNC_NO_CACHE"):
    from jaxnc.cache import enable_cache  # noqa: E402
    enable_cache()

# Shapes must match exactly; silent broadcasting hides bugs.
jax.config.update("jax_numpy_rank_promotion", "raise")
