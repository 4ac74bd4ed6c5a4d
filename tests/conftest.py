"""Test configuration. Global JAX flags belong here, never in the package."""
import os

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

# Shapes must match exactly; silent broadcasting hides bugs.
jax.config.update("jax_numpy_rank_promotion", "raise")
