"""Differentiating through the PBD solver: reverse mode against central finite differences
(float64, 60 iterations), forward mode against reverse mode, checkpointing, vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface import pbd
from test_pbd import grid, grid_topology

ITERS = 60


@pytest.fixture(scope="module")
def cloth():
    v, t = grid(4, 4, h=2.0)
    v[:, 2] = 0.1 * v[:, 0] * v[:, 1] / 4.0
    e, p = grid_topology(v, t)
    sel = np.array([0, 3, 12, 15, 5])
    rng = np.random.default_rng(0)
    groups = {
        "stretch": pbd.distance_constraints(e, v, stiffness=0.5),
        "cross": pbd.distance_constraints(p[:, 2:], v, compliance=1e-6),
        "bend": pbd.bending_constraints(p, v, stiffness=0.3),
        "area": pbd.area_constraints(t, v, stiffness=0.4),
        "anchors": pbd.anchor_constraints(sel, v[sel] + rng.normal(size=(5, 3)), stiffness=0.5),
    }
    S = pbd.build_system(groups, len(v))
    x0 = v + rng.normal(size=v.shape) * 0.2
    weights = rng.normal(size=v.shape)
    return S, jnp.asarray(x0), jnp.asarray(weights)


def _fd_check(f, x, directions, h=1e-6, rtol=1e-6):
    """Compare jax.grad(f) . d with the central difference of f along d."""
    g = jax.grad(f)(x)
    for d in directions:
        fd = (f(x + h * d) - f(x - h * d)) / (2 * h)
        an = float(jnp.sum(g * d))
        assert abs(an - float(fd)) <= rtol * max(1.0, abs(float(fd))), (an, float(fd))
    return g


def _dirs(shape, n=3, seed=1):
    rng = np.random.default_rng(seed)
    return [jnp.asarray(rng.normal(size=shape)) for _ in range(n)]


@pytest.mark.parametrize("scheme", ["gs", "jacobi"])
def test_gradients_match_central_differences(cloth, scheme):
    """One reverse-mode gradient with respect to everything a fit may vary at once: initial
    positions, anchor targets (user order), stretch stiffness, bending rest angles and the
    log of the XPBD compliance; checked along random joint directions and along each block."""
    S, x0, wts = cloth
    params = {
        "x": x0,
        "target": S["anchors"].target,
        "k": jnp.full(S["stretch"].size, 0.5),
        "rest": S["bend"].rest,
        "log_c": jnp.full(S["cross"].size, np.log(1e-6)),
    }

    @jax.jit
    def f(q):
        s = (
            S.set("anchors", target=q["target"])
            .set("stretch", stiffness=q["k"])
            .set("bend", rest=q["rest"])
            .set("cross", compliance=jnp.exp(q["log_c"]))
        )
        return jnp.sum(wts * pbd.relax(s, q["x"], iterations=ITERS, scheme=scheme))

    g = jax.jit(jax.grad(f))(params)
    rng = np.random.default_rng(1)
    dirs = [jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape)), params) for _ in range(2)]
    for name in params:  # each block alone, so a wrong block cannot hide behind the others
        dirs.append(
            {
                k: (jnp.asarray(rng.normal(size=a.shape)) if k == name else jnp.zeros_like(a))
                for k, a in params.items()
            }
        )
    h = 1e-6
    for d in dirs:
        fp = f(jax.tree.map(lambda a, b: a + h * b, params, d))
        fm = f(jax.tree.map(lambda a, b: a - h * b, params, d))
        fd = float((fp - fm) / (2 * h))
        an = float(sum(jnp.sum(a * b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d))))
        assert abs(an) > 1e-8 or abs(fd) < 1e-8
        assert abs(an - fd) <= 1e-6 * max(1.0, abs(fd)), (an, fd)


def test_forward_mode_equals_reverse_mode_and_checkpointing_is_exact(cloth):
    S, x0, wts = cloth
    t0 = S["anchors"].target

    def out(t, ck=1):
        return pbd.relax(S.set("anchors", target=t), x0, iterations=ITERS, checkpoint_every=ck)[
            jnp.array([1, 6, 10])
        ]

    jf = jax.jacfwd(out)(t0)
    jr = jax.jacrev(out)(t0)
    np.testing.assert_allclose(np.asarray(jf), np.asarray(jr), atol=1e-10)

    def loss(x, ck):
        return jnp.sum(wts * pbd.relax(S, x, iterations=ITERS, checkpoint_every=ck))

    g_ref = jax.grad(loss)(x0, None)
    for ck in (7,):  # 60 = 8 blocks of 7 + a remainder block of 4
        np.testing.assert_allclose(
            np.asarray(jax.grad(loss)(x0, ck)), np.asarray(g_ref), atol=1e-12
        )


def test_gradient_through_time_steps(cloth):
    S, x0, wts = cloth

    def loss(x):
        p = pbd.Particles.at_rest(x)
        return jnp.sum(
            wts
            * pbd.simulate(S, p, steps=6, iterations=10, gravity=jnp.array([0.0, -9810.0, 0.0])).x
        )

    _fd_check(jax.jit(loss), x0, _dirs(x0.shape, n=2, seed=6))


def test_vmap_over_targets_equals_loop(cloth):
    S, x0, _ = cloth
    t0 = np.asarray(S["anchors"].target)
    rng = np.random.default_rng(9)
    batch = jnp.asarray(t0[None] + rng.normal(size=(4,) + t0.shape))

    def solve(t):
        return pbd.relax(S.set("anchors", target=t), x0, iterations=30)

    vm = jax.vmap(solve)(batch)
    loop = jnp.stack([solve(t) for t in batch])
    np.testing.assert_allclose(np.asarray(vm), np.asarray(loop), atol=1e-12)
