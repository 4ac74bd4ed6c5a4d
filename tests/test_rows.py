"""jaxnc.rows: rows of a random draw, bit for bit equal to the full draw sliced."""
import jax
import numpy as np
import pytest

from jaxnc import montecarlo
from jaxnc import rows as rows_mod
from jaxnc.rows import exponential_rows, normal_rows, uniform_rows


@pytest.mark.parametrize("shape, every", [((690,), 10), ((690, 9), 10), ((37, 3), 4), ((12, 2, 3), 1), ((5,), 7)])
def test_rows_equal_the_sliced_full_draw(shape, every):
    keys = montecarlo.seed_keys(3, 16)
    assert rows_mod._fast_path(keys[0])          # the default configuration takes the cheap path
    for name, rows, full in (("normal", normal_rows, jax.random.normal), ("uniform", uniform_rows, jax.random.uniform),
                             ("exponential", exponential_rows, jax.random.exponential)):
        got = jax.jit(jax.vmap(lambda k: rows(k, shape, every)))(keys)
        want = jax.jit(jax.vmap(lambda k: full(k, shape)[::every]))(keys)
        assert got.shape == want.shape, name
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=name)


def test_typed_keys_fall_back_to_the_full_draw():
    key = jax.random.key(0)
    np.testing.assert_array_equal(normal_rows(key, (20, 3), 5), jax.random.normal(key, (20, 3))[::5])
