"""Tests of jaxface.surface: surface points on deformed meshes (JAX), normals, derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxface.errors import MeshError
from jaxface.mesh import TriMesh
from jaxface.surface import SurfacePoints, face_normals, from_points, safe_normalize, vertex_normals

# jit whole evaluations: one compilation each instead of many eager op dispatches
_pos = jax.jit(lambda sp, v, t: sp.positions(v, t))
_nrm = jax.jit(lambda sp, v, t: sp.normals(v, t))
_fnrm = jax.jit(lambda sp, v, t: sp.face_normals(v, t))


def rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))  # proper rotation


def random_bary(rng, k):
    b = rng.uniform(0.05, 1.0, size=(k, 3))
    return b / b.sum(axis=1, keepdims=True)


def test_points_follow_a_rigidly_moved_triangle():
    rng = np.random.default_rng(0)
    v = np.array([[0.0, 0, 0], [30, 0, 0], [5, 20, 0]])
    tri = np.array([[0, 1, 2]])
    bary = random_bary(rng, 25)
    sp = SurfacePoints(np.zeros(25, np.int32), bary)
    p0 = np.asarray(_pos(sp, v, tri))
    np.testing.assert_allclose(p0, bary @ v)  # independent: plain matrix product
    np.testing.assert_allclose(np.asarray(_nrm(sp, v, tri)), np.tile([0, 0, 1.0], (25, 1)))
    for _ in range(3):
        r, t = rotation(rng), rng.normal(size=3) * 50
        vm = v @ r.T + t
        np.testing.assert_allclose(np.asarray(_pos(sp, vm, tri)), p0 @ r.T + t, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(_nrm(sp, vm, tri)), np.tile(r[:, 2], (25, 1)), atol=1e-12
        )
        np.testing.assert_allclose(
            np.asarray(_fnrm(sp, vm, tri)), np.tile(r[:, 2], (25, 1)), atol=1e-12
        )


def test_corners_and_interpolated_normals_on_sphere():
    s = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    v, t = np.asarray(s.vertices), np.asarray(s.faces)
    # barycentric unit vectors reproduce the vertices
    sp = SurfacePoints(np.arange(len(t)), np.tile([0.0, 1.0, 0.0], (len(t), 1)))
    np.testing.assert_allclose(np.asarray(_pos(sp, v, t)), v[t[:, 1]])
    # and the interpolated normal at a corner is that vertex's normal
    vn = TriMesh(v, t).vertex_normals
    np.testing.assert_allclose(np.asarray(_nrm(sp, v, t)), vn[t[:, 1]], atol=1e-12)
    # interpolated normals at random interior points are unit and close to radial
    rng = np.random.default_rng(1)
    k = 300
    sp = SurfacePoints(rng.integers(0, len(t), k), random_bary(rng, k))
    n = np.asarray(_nrm(sp, v, t))
    p = np.asarray(_pos(sp, v, t))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.min(np.einsum("ij,ij->i", n, p / np.linalg.norm(p, axis=1, keepdims=True))) > 0.995


def test_jax_vertex_normals_match_numpy_trimesh():
    s = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    rng = np.random.default_rng(2)
    v = np.asarray(s.vertices) * [1.0, 1.3, 0.8] + rng.normal(size=s.vertices.shape) * 0.5
    m = TriMesh(v, s.faces)
    vn, fn = jax.jit(lambda x: (vertex_normals(x, m.triangles), face_normals(x, m.triangles)))(v)
    np.testing.assert_allclose(np.asarray(vn), m.vertex_normals, atol=1e-12)
    np.testing.assert_allclose(np.asarray(fn), m.face_normals, atol=1e-12)
    # independent reference: area weighting = sum of unnormalised cross products
    ref = np.zeros_like(v)
    c = np.cross(
        v[m.triangles[:, 1]] - v[m.triangles[:, 0]], v[m.triangles[:, 2]] - v[m.triangles[:, 0]]
    )
    for f, tri in enumerate(m.triangles):
        for i in tri:
            ref[i] += c[f]
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(m.vertex_normals, ref, atol=1e-12)


def _central_fd_jacobian(fun, x, h=1e-6):
    x = np.asarray(x, dtype=np.float64)
    out0 = np.asarray(fun(x))
    jac = np.zeros(out0.shape + x.shape)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = h
        jac[(Ellipsis,) + idx] = (np.asarray(fun(x + e)) - np.asarray(fun(x - e))) / (2 * h)
    return jac


def test_jacobians_match_central_finite_differences():
    assert jnp.zeros(1).dtype == jnp.float64  # conftest enables x64
    rng = np.random.default_rng(3)
    # a small curved patch: 2x2 grid with a raised centre
    v = np.array(
        [
            [0, 0, 0],
            [10, 0, 1],
            [20, 0, 0],
            [0, 10, 2],
            [10, 10, 5],
            [20, 10, 1],
            [0, 20, 0],
            [10, 20, 1],
            [20, 20, 0],
        ],
        dtype=float,
    )
    v = v + rng.normal(size=v.shape) * 0.5
    t = np.array(
        [[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]]
    )
    tri = rng.integers(0, len(t), 6)
    bary = random_bary(rng, 6)

    def both(x, b):  # positions (mm) and normals of the 6 points, stacked: (12, 3)
        s = SurfacePoints(tri, b)
        return jnp.concatenate([s.positions(x, t), s.normals(x, t)], axis=0)

    f = jax.jit(both)
    jac_v, jac_b = jax.jit(jax.jacfwd(both, argnums=(0, 1)))(v, bary)
    jac_v, jac_b = np.asarray(jac_v), np.asarray(jac_b)
    fd_v = _central_fd_jacobian(lambda x: f(x, bary), v)
    fd_b = _central_fd_jacobian(lambda b: f(v, b), bary)
    np.testing.assert_allclose(jac_v, fd_v, atol=1e-7, rtol=1e-6)
    np.testing.assert_allclose(jac_b, fd_b, atol=1e-7, rtol=1e-6)
    assert np.abs(jac_v[6:]).max() > 1e-3  # the normals really depend on the vertices
    # positions are linear in the barycentrics: d p_k / d b_kj = corner j
    corners = v[t[tri]]
    for k in range(6):
        np.testing.assert_allclose(jac_b[k, :, k, :], corners[k].T, atol=1e-12)
    # reverse mode agrees with forward mode (one vector-Jacobian product)
    u = rng.normal(size=(12, 3))
    gv, gb = jax.jit(jax.grad(lambda x, b: jnp.sum(u * both(x, b)), argnums=(0, 1)))(v, bary)
    np.testing.assert_allclose(np.asarray(gv), np.einsum("ij,ijkl->kl", u, jac_v), atol=1e-12)
    np.testing.assert_allclose(np.asarray(gb), np.einsum("ij,ijkl->kl", u, jac_b), atol=1e-12)


def test_nan_safe_normals_for_degenerate_geometry():
    # triangle 1 is collapsed to a point, and vertex 5 is isolated
    v = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2], [2, 2, 2], [9, 9, 9]])
    t = np.array([[0, 1, 2], [3, 4, 3]])
    sp = SurfacePoints([1, 0], [[0.3, 0.3, 0.4], [0.2, 0.3, 0.5]])

    def loss(x):
        return (
            jnp.sum(sp.normals(x, t) ** 2)
            + jnp.sum(vertex_normals(x, t))
            + jnp.sum(face_normals(x, t))
        )

    @jax.jit
    def evaluate(x):
        return vertex_normals(x, t), sp.normals(x, t), face_normals(x, t), jax.grad(loss)(x)

    vn, n, fn, grad = (np.asarray(a) for a in evaluate(v))
    assert np.all(np.isfinite(vn)) and np.all(np.isfinite(grad))
    np.testing.assert_allclose(vn[3:], 0.0)
    np.testing.assert_allclose(vn[:3], np.tile([0, 0, 1.0], (3, 1)))
    np.testing.assert_allclose(n, [[0, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(fn, [[0, 0, 1], [0, 0, 0]])
    # the vertices of the collapsed triangle get zero gradient, not NaN
    np.testing.assert_allclose(grad[3:], 0.0)
    z = jnp.zeros((2, 3))
    assert np.all(np.asarray(jax.jit(jax.jacfwd(safe_normalize))(z)) == 0)


def test_vmap_jit_and_dtype():
    rng = np.random.default_rng(4)
    s = trimesh.creation.icosphere(subdivisions=1, radius=20.0)
    v, t = np.asarray(s.vertices), np.asarray(s.faces)
    tri, bary = rng.integers(0, len(t), 10), random_bary(rng, 10)
    sp = SurfacePoints(tri, bary)
    ref = np.einsum("kj,kjd->kd", bary, v[t[tri]])  # plain NumPy reference
    scales = np.array([1.0, 1.5, 2.0])
    batch = jnp.asarray(v[None] * scales[:, None, None])
    out = np.asarray(jax.jit(jax.vmap(lambda x: sp.positions(x, t)))(batch))
    np.testing.assert_allclose(out, scales[:, None, None] * ref[None], atol=1e-12)
    # vmap over stacked SurfacePoints (a pytree)
    stacked = jax.tree_util.tree_map(lambda a: jnp.stack([a, a[::-1]]), sp)
    out2 = np.asarray(jax.jit(jax.vmap(lambda s_: s_.positions(v, t)))(stacked))
    np.testing.assert_allclose(out2[1], ref[::-1], atol=1e-12)
    # float32 in, float32 out
    v32 = jnp.asarray(v, dtype=jnp.float32)
    dtypes = jax.jit(lambda x: (sp.positions(x, t), sp.normals(x, t), vertex_normals(x, t)))(v32)
    assert all(a.dtype == jnp.float32 for a in dtypes)


def test_construction_checks_and_helpers():
    with pytest.raises(MeshError):
        SurfacePoints([0, 1], [[1.0, 0, 0]])
    with pytest.raises(MeshError):
        SurfacePoints([[0]], [[1.0, 0, 0]])
    sp = SurfacePoints([0, 3], [[0.2, 0.3, 0.5], [1.0, 0.0, 0.0]])
    assert sp.tri.dtype == jnp.int32 and len(sp) == 2
    sp.check(n_triangles=4)
    with pytest.raises(MeshError) as info:
        sp.check(n_triangles=3)
    assert info.value.elements == (1,)
    with pytest.raises(MeshError):
        SurfacePoints([0], [[0.7, 0.7, 0.7]]).check()
    both = SurfacePoints.concatenate([sp, sp.take([1])])
    assert len(both) == 3 and int(both.tri[2]) == 3


def test_from_points_projects_onto_the_mesh():
    s = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    m = TriMesh(s.vertices, s.faces)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * 45.0  # 5 mm outside the sphere
    sp, dist = from_points(m, pts)
    sp.check(m.n_triangles)
    on = np.asarray(_pos(sp, m.vertices, m.triangles))
    np.testing.assert_allclose(np.linalg.norm(pts - on, axis=1), dist, atol=1e-10)
    inner = float(np.min(np.einsum("ij,ij->i", m.face_normals, m.vertices[m.triangles[:, 0]])))
    assert np.all((dist > 5.0 - 1e-9) & (dist < 45.0 - inner + 1e-9))
    # the offset from the surface is along the (smooth) normal, up to the tessellation
    n = np.asarray(_nrm(sp, m.vertices, m.triangles))
    cos = np.einsum("ij,ij->i", n, (pts - on) / dist[:, None])
    assert cos.min() > 0.99
    # points of the mesh itself project onto themselves with distance 0
    sp0, d0 = m.closest_points(m.vertices[:20])
    assert d0.max() < 1e-12
    np.testing.assert_allclose(
        np.asarray(_pos(sp0, m.vertices, m.triangles)), m.vertices[:20], atol=1e-12
    )
