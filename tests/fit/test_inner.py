"""The inner solves' helpers (jaxface.fit.inner): host-side stacking, the padded batch size,
and optimistix result names by the public API."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxface.errors import FitError
from jaxface.fit.inner import (
    RESULT_NAMES,
    index_tree,
    padded_batch_size,
    result_name,
    result_names,
    stack_trees,
)


def test_host_stack_and_index_equal_jax_stack_and_slicing():
    """The fit's batches are stacked and sliced on the host (no eager XLA op per leaf): the
    same values, dtypes and shapes as ``jnp.stack`` / ``x[i]``, as JAX arrays."""
    rng = np.random.default_rng(3)
    trees = [
        {
            "z": jnp.asarray(rng.normal(size=5)),
            "ids": jnp.asarray(rng.integers(0, 9, (4, 3))),
            "free": jnp.asarray(rng.random(5) > 0.5),
        }
        for _ in range(3)
    ]
    got = stack_trees(trees)
    want = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        assert isinstance(g, jax.Array) and g.dtype == w.dtype and g.shape == w.shape
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    for i in range(3):
        for g, w in zip(
            jax.tree_util.tree_leaves(index_tree(got, i)), jax.tree_util.tree_leaves(trees[i])
        ):
            assert isinstance(g, jax.Array) and g.dtype == w.dtype
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_padded_batch_size_is_the_next_power_of_two():
    assert [padded_batch_size(n) for n in (1, 2, 3, 4, 5, 8, 11, 16, 17)] == [
        1,
        2,
        4,
        4,
        8,
        8,
        16,
        16,
        32,
    ]
    with pytest.raises(FitError, match="at least one"):
        padded_batch_size(0)


def test_result_names_by_equality_with_the_public_results():
    """Scalar and batched optimistix results, passed through a jit, read back by name."""
    assert result_name(optx.RESULTS.successful) == "successful"
    for name in RESULT_NAMES:
        assert result_name(getattr(optx.RESULTS, name)) == name
    ok, cap = optx.RESULTS.successful, optx.RESULTS.nonlinear_max_steps_reached
    batched = jax.jit(jax.vmap(lambda b: optx.RESULTS.where(b, ok, cap)))(
        jnp.asarray([1, 0, 1]) > 0
    )
    assert result_names(batched) == ("successful", "nonlinear_max_steps_reached", "successful")
