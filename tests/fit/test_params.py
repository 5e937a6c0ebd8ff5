"""The fit's parameters (jaxface.fit.params): the bounded activation map, the rotation vector
of the rigid correction, and the Params pytree's leaf order."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from jaxface.fit.params import (
    Params,
    activations_from_z,
    rotation_from_rotvec_deg,
    z_from_activations,
)


def test_activation_map_is_bounded_smooth_and_invertible():
    z = jnp.linspace(-3.0, 4.0, 701)
    a = np.asarray(activations_from_z(z))
    assert a.min() >= 0.0 and a.max() <= 1.0
    # bounds are reached at finite parameters, with zero slope (no run-away at a bound)
    g = jax.vmap(jax.grad(activations_from_z))
    np.testing.assert_allclose(np.asarray(g(jnp.asarray([0.0, 1.0]))), 0.0, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(activations_from_z(jnp.asarray([0.0, 1.0]))), [0.0, 1.0], atol=1e-15
    )
    aa = jnp.asarray([0.0, 0.02, 0.5, 0.97, 1.0])
    np.testing.assert_allclose(
        np.asarray(activations_from_z(z_from_activations(aa))), aa, atol=1e-12
    )


def test_rotation_vector_matches_scipy_and_has_finite_gradient_at_zero():
    w = np.array([3.0, -2.0, 5.0])
    np.testing.assert_allclose(
        np.asarray(rotation_from_rotvec_deg(jnp.asarray(w))),
        Rotation.from_rotvec(np.radians(w)).as_matrix(),
        atol=1e-12,
    )

    def f(v):
        return jnp.sum(rotation_from_rotvec_deg(v) @ jnp.asarray([1.0, 2.0, 3.0]))

    g0 = np.asarray(jax.grad(f)(jnp.zeros(3)))
    assert np.all(np.isfinite(g0))
    h = 1e-5
    fd = np.array([(f(jnp.eye(3)[i] * h) - f(-jnp.eye(3)[i] * h)) / (2 * h) for i in range(3)])
    np.testing.assert_allclose(g0, fd, atol=1e-8)


def test_params_flatten_in_the_order_of_the_former_parameter_dict():
    """The inner solves' sums run over the leaves in flatten order; Params keeps the order of
    the dict it replaced (sorted keys: jaw, rigid, z), with and without the rigid part."""
    p = Params.initial(4, 7.0, 0.05, rigid=True)
    as_dict = {"z": p.z, "jaw": p.jaw, "rigid": p.rigid}
    for a, b in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(as_dict), strict=True):
        assert a is b
    q = Params.initial(4, 7.0, 0.05, rigid=False)
    assert q.rigid is None and len(jax.tree_util.tree_leaves(q)) == 2
    np.testing.assert_allclose(np.asarray(q.jaw), [7.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(activations_from_z(q.z)), 0.05, rtol=1e-12)
    assert q.z.dtype == jnp.result_type(float)
    r = q.with_z(jnp.zeros(4))
    assert r.jaw is q.jaw and np.all(np.asarray(r.z) == 0.0)
