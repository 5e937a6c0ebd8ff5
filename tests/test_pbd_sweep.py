"""The engine's sweep (:mod:`jaxface.sweep`): the fused Jacobi scheme the rig runs against a
sequential oracle, the hull projection against a per-point loop, multi-body volumes, and
run-time fields set on traced values.

Independent references: :func:`jaxface.reference.jacobi` (scalar Python formulas, one
constraint at a time), a per-point nearest-face loop, the enclosed volume of each body
computed in NumPy.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxface import pbd
from jaxface import reference as ref
from jaxface.constraints import AnchorConstraints, VolumeConstraint
from jaxface.mesh import TriMesh
from test_pbd import dodecahedron, grid, volume


def _volume(system, name) -> VolumeConstraint:
    c = system[name]
    assert isinstance(c, VolumeConstraint)
    return c


def _cloth():
    """A 6 x 6 grid cloth (mm) with every kind the rig uses, rest measured on the flat grid;
    a corner row is kinematic."""
    v, t = grid(6, 6, 2.0)
    m = TriMesh(v, t)
    n = len(v)
    rng = np.random.default_rng(11)
    ids = np.arange(0, n, 3)
    N, d = pbd.hull_planes(rng.normal(size=(30, 3)) * 2.0 + np.array([5.0, 5.0, 0.0]))
    groups = {
        "anchors": pbd.anchor_constraints(
            ids, v[ids] + rng.normal(size=(len(ids), 3)), stiffness=0.4
        ),
        "stretch": pbd.distance_constraints(
            np.concatenate([m.edges, m.edge_pairs[:, 2:]]), v, stiffness=0.8
        ),
        "area": pbd.area_constraints(t, v, stiffness=0.9),
        "bend": pbd.bending_constraints(m.edge_pairs, v, stiffness=0.5),
        "volume": pbd.volume_constraint(t, v, origin=[5.0, 5.0, -4.0], stiffness=1.0),
        "hull": pbd.hull_constraints(np.arange(n), N, d, clearance=0.1),
    }
    w = np.ones(n)
    w[:6] = 0.0
    S = pbd.build_system(groups, w, omega={"stretch": 1.5})
    x0 = v + rng.normal(size=v.shape) * 0.4
    return S, x0


def test_fused_jacobi_equals_the_sequential_jacobi_oracle():
    """Every kind, omega 1.5 on one group, kinematic particles: 6 sweeps of the engine equal the
    scalar oracle (float64 rounding)."""
    S, x0 = _cloth()
    got = np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=6, scheme="jacobi"))
    want = ref.jacobi(S, x0, iterations=6)
    assert np.abs(want - x0).max() > 0.1  # the sweeps do move the cloth
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got[:6], x0[:6])  # kinematic particles stay


def test_set_works_on_traced_values_inside_filter_jit():
    """``system.set`` with the system and the new targets as arguments of a jitted function
    (a TracerArrayConversionError before the one engine); the result equals the eager one."""
    S, x0 = _cloth()
    anchors = S["anchors"]
    assert isinstance(anchors, AnchorConstraints)
    t = np.asarray(anchors.target) + 0.5

    @eqx.filter_jit
    def solve(system, target, x):
        s = system.set("anchors", target=target).set(
            "volume", rest=_volume(system, "volume").rest * 1.01
        )
        return pbd.relax(s, x, iterations=3, scheme="jacobi")

    got = np.asarray(solve(S, jnp.asarray(t), jnp.asarray(x0)))
    eager = S.set("anchors", target=t).set(
        "volume", rest=np.asarray(_volume(S, "volume").rest) * 1.01
    )
    want = ref.jacobi(eager, x0, iterations=3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # and differentiable through the traced set (a small system: one group)
    A = pbd.build_system({"anchors": S["anchors"]}, S.inv_mass)

    @jax.grad
    def grad(tt):
        s = A.set("anchors", target=tt)
        return jnp.sum(pbd.relax(s, jnp.asarray(x0), iterations=2, scheme="jacobi") ** 2)

    g = np.asarray(grad(jnp.asarray(t)))
    assert np.isfinite(g).all() and np.abs(g).max() > 0


def test_multi_body_volumes_each_reach_their_target():
    """Two separate dodecahedra in one volume group (one body each) inflated by different
    factors: each body's enclosed volume (NumPy) reaches its own target."""
    v, t = dodecahedron(5.0)
    v2 = np.concatenate([v, v + np.array([20.0, 0.0, 0.0])])
    t2 = np.concatenate([t, t + len(v)])
    owner = np.repeat([0, 1], len(t))
    V0 = volume(v, t)
    c = pbd.volume_constraint(t2, v2, rest=[1.2 * V0, 0.9 * V0], origin=[10.0, 0, 0], owner=owner)
    S = pbd.build_system({"vol": c}, len(v2))
    x = np.asarray(pbd.relax(S, jnp.asarray(v2), iterations=20, scheme="jacobi"))
    np.testing.assert_allclose(volume(x[: len(v)], t), 1.2 * V0, rtol=1e-6)
    np.testing.assert_allclose(volume(x[len(v) :] - [20.0, 0, 0], t), 0.9 * V0, rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(_volume(S, "vol").volume(x)), [1.2 * V0, 0.9 * V0], rtol=1e-6
    )


def test_teeth_hull_projection_matches_a_per_point_reference():
    """The rig's teeth collision (one-hot nearest plane) against a plain per-point loop:
    every particle inside the hull (plus clearance) goes out along the normal of its nearest
    face, by exactly its depth; particles outside stay put."""
    rng = np.random.default_rng(3)
    hull_pts = rng.normal(size=(60, 3)) * np.array([20.0, 8.0, 6.0])
    N, d = pbd.hull_planes(hull_pts)
    x = rng.uniform(-25, 25, size=(400, 3)) * np.array([1.0, 0.5, 0.4])
    ids = np.arange(0, 400, 2)  # half of the particles collide-able
    clearance = 0.5
    g = pbd.make_group(pbd.hull_constraints(ids, N, d, clearance=clearance), len(x))
    got = np.asarray(pbd.sweep((g,), jnp.asarray(x, jnp.float32), jnp.ones(len(x))))
    want = x.copy()
    for i in ids:
        sd = N @ x[i] - d
        h = int(np.argmax(sd))
        depth = clearance - sd[h]
        if depth > 0:
            want[i] = x[i] + depth * N[h]
    assert np.sum(np.any(want != x, axis=1)) > 10  # the test does push particles out
    np.testing.assert_allclose(got, want, atol=2e-4)
