"""The reduced response model's cubic Hermite splines (jaxface.fit.reduced): exactness on
quadratics between non-uniform knots, and the custom forward-mode rule against finite
differences."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxface.fit.reduced import hermite_parts, hermite_slopes, hermite_sum


def _quadratic_tables(knots, M=3, K=5, seed=0):
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(M, 3, K, 3))  # per spline: c0 + c1 x + c2 x^2
    f = lambda x: c[:, 0] + c[:, 1] * x + c[:, 2] * x * x  # noqa: E731
    vals = np.stack([f(t) for t in knots], axis=1)  # (M, N, K, 3)
    slopes = np.stack([hermite_slopes(knots, vals[m]) for m in range(M)])
    return c, vals, slopes


def test_hermite_sum_reproduces_quadratics_between_nonuniform_knots():
    knots = np.array([0.0, 0.15, 0.5, 0.6, 1.0])
    c, vals, slopes = _quadratic_tables(knots)
    x = np.array([0.07, 0.55, 0.93])
    got = np.asarray(
        hermite_sum(jnp.asarray(x), jnp.asarray(knots), jnp.asarray(vals), jnp.asarray(slopes))
    )
    want = sum(c[m, 0] + c[m, 1] * x[m] + c[m, 2] * x[m] ** 2 for m in range(3))
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_hermite_sum_custom_derivative_matches_finite_differences():
    knots = np.linspace(0.0, 1.0, 5)
    rng = np.random.default_rng(1)
    vals = jnp.asarray(rng.normal(size=(4, 5, 6, 3)))
    slopes = jnp.asarray(rng.normal(size=(4, 5, 6, 3)))
    kn = jnp.asarray(knots)
    f = lambda x: hermite_sum(x, kn, vals, slopes)  # noqa: E731
    # interior points off the knots, and points beyond the ends (linear continuation)
    for x in (np.array([0.1, 0.33, 0.6, 0.9]), np.array([-0.3, 1.2, 0.45, 0.05])):
        x = jnp.asarray(x)
        J = jax.jacfwd(f)(x)  # (6, 3, 4) through the custom rule
        h = 1e-6
        fd = np.stack(
            [(f(x.at[i].add(h)) - f(x.at[i].add(-h))) / (2 * h) for i in range(4)], axis=-1
        )
        np.testing.assert_allclose(np.asarray(J), fd, atol=1e-7)
    # tangents of the tables fall back to plain autodiff (linear in the tables)
    x = jnp.asarray([0.2, 0.4, 0.7, 0.95])
    dv = jnp.asarray(rng.normal(size=vals.shape))
    _, t = jax.jvp(lambda v: hermite_sum(x, kn, v, slopes), (vals,), (dv,))
    np.testing.assert_allclose(
        np.asarray(t), np.asarray(hermite_parts(x, kn, dv, slopes * 0)[0]), atol=1e-12
    )
