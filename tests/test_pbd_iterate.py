"""The engine's iteration (:func:`jaxface.pbd.iterate`): plain and Chebyshev semi-iterative
sweeps, checkpoint blocks.

References: the analytic solution of a linear system (the plain iteration is Jacobi on it, so
its spectral radius is known), central finite differences for the derivative."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface.pbd import iterate


def _jacobi_problem(n=40, seed=0):
    """A 1D Laplacian-plus-mass system ``K u = f`` (3 columns) and its Jacobi step."""
    rng = np.random.default_rng(seed)
    K = 2.05 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    f = rng.normal(size=(n, 3))
    d = np.diag(K)
    rho = float(np.max(np.abs(np.linalg.eigvals(np.eye(n) - K / d[:, None]))))
    Kj, fj, dj = jnp.asarray(K), jnp.asarray(f), jnp.asarray(d)

    def step(u, f=fj):
        return u + (f - Kj @ u) / dj[:, None]

    return step, np.linalg.solve(K, f), rho, fj


def test_chebyshev_converges_to_the_analytic_solution_much_faster_than_plain_sweeps():
    step, exact, rho, _ = _jacobi_problem()
    assert 0.95 < rho < 1.0  # a slow problem for the plain iteration
    u0 = jnp.zeros_like(jnp.asarray(exact))
    err = lambda u: float(np.abs(np.asarray(u) - exact).max())  # noqa: E731
    plain = err(iterate(step, u0, 60))
    cheb = err(iterate(step, u0, 60, rho=rho))
    assert cheb < 1e-3 * plain, (cheb, plain)
    assert cheb < 1e-4
    # rho = 0 is exactly the plain loop
    ref = u0
    for _ in range(25):
        ref = step(ref)
    np.testing.assert_allclose(
        np.asarray(iterate(step, u0, 25)), np.asarray(ref), rtol=0, atol=1e-12
    )
    # the fixed point does not depend on rho
    np.testing.assert_allclose(np.asarray(iterate(step, u0, 400, rho=0.9)), exact, atol=1e-8)


def test_chebyshev_result_ends_with_a_plain_step_and_is_differentiable():
    step0, _, rho, f = _jacobi_problem(n=12)

    def step(u):  # a unilateral projection last, like the teeth collisions
        return jnp.maximum(step0(u), -0.05)

    u = iterate(step, jnp.zeros((12, 3)), 30, rho=rho)
    assert float(jnp.min(u)) >= -0.05

    def loss(s):
        return jnp.sum(iterate(lambda u: step0(u, s * f), jnp.zeros((12, 3)), 30, rho=rho) ** 2)

    g = float(jax.grad(loss)(1.0))
    h = 1e-4
    fd = (float(loss(1.0 + h)) - float(loss(1.0 - h))) / (2 * h)
    assert abs(g - fd) < 1e-5 * max(1.0, abs(fd))


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_checkpointed_sweeps_change_no_value_and_no_derivative(rho):
    step0, _, _, f = _jacobi_problem(n=12)

    def run(s, checkpoint):
        # a non-linear step with intermediates the checkpoint recomputes on the way back
        step = lambda u: jnp.tanh(step0(u, s * f)) + 0.1 * jnp.sin(u)  # noqa: E731
        every = 1 if checkpoint else None
        return iterate(step, jnp.zeros((12, 3)), 30, rho=rho, checkpoint_every=every)

    np.testing.assert_array_equal(np.asarray(run(1.0, True)), np.asarray(run(1.0, False)))
    loss = lambda s, c: jnp.sum(run(s, c) ** 2)  # noqa: E731
    g_on = float(jax.grad(loss)(1.0, True))
    g_off = float(jax.grad(loss)(1.0, False))
    h = 1e-5
    fd = (float(loss(1.0 + h, False)) - float(loss(1.0 - h, False))) / (2 * h)
    assert abs(g_on - g_off) <= 1e-12 * max(1.0, abs(g_off))
    assert abs(g_on - fd) < 1e-6 * max(1.0, abs(fd))
    # the checkpoint is in the program: the reverse pass recomputes the sweep (a remat)
    jaxpr = str(jax.make_jaxpr(jax.grad(loss), static_argnums=1)(1.0, True))
    assert "remat" in jaxpr or "checkpoint" in jaxpr
    assert "remat" not in str(jax.make_jaxpr(jax.grad(loss), static_argnums=1)(1.0, False))


def test_bad_spectral_radius_is_refused():
    from jaxface.errors import RigError

    step, _, _, _ = _jacobi_problem(n=5)
    with pytest.raises(RigError, match=r"\[0, 1\)"):
        iterate(step, jnp.zeros((5, 3)), 10, rho=1.0)
