"""Tests of jaxface.mesh: validation, topology, normals, geodesics, ray casting, OBJ/PLY I/O.

References are hand-made meshes with known answers (tetrahedron, grid, open cube, sphere),
analytic geometry, trimesh as an independent implementation, and the ICT-FaceKit head.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from jaxface.errors import DataNotFoundError, JaxfaceError, MeshError, UnitsError
from jaxface.mesh import (
    TriMesh,
    check_plausible_size,
    closest_point_barycentric,
    load_mesh,
    save_mesh,
    unit_scale,
)

# ----------------------------------------------------------------------------- fixtures


def tetrahedron():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    # counter-clockwise seen from outside
    t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, t


def grid(nx=4, ny=3, h=1.0):
    """Flat grid in z = 0, (nx+1) x (ny+1) vertices, each quad split along its (+1, +1)
    diagonal, triangles facing +z."""
    xs, ys = np.meshgrid(np.arange(nx + 1) * h, np.arange(ny + 1) * h, indexing="xy")
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    idx = lambda i, j: j * (nx + 1) + i  # noqa: E731
    t = []
    for j in range(ny):
        for i in range(nx):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            t += [[a, b, c], [a, c, d]]
    return v, np.array(t)


def cube():
    """Unit cube, 8 vertices, 12 outward triangles; the last two triangles are the top (z=1)."""
    v = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    # vertex id = 4z + 2y + x
    quads = [
        (0, 2, 3, 1),  # bottom z=0, normal -z
        (0, 1, 5, 4),  # y=0, normal -y
        (1, 3, 7, 5),  # x=1, normal +x
        (3, 2, 6, 7),  # y=1, normal +y
        (2, 0, 4, 6),  # x=0, normal -x
        (4, 5, 7, 6),  # top z=1, normal +z
    ]
    t = []
    for a, b, c, d in quads:
        t += [[a, b, c], [a, c, d]]
    return v, np.array(t)


def triangle_set(t):
    """Triangles as a set of cyclic-canonical tuples (orientation kept)."""
    out = set()
    for a, b, c in np.asarray(t).tolist():
        r = [(a, b, c), (b, c, a), (c, a, b)]
        out.add(min(r))
    return out


def cyc(a, b, c):
    return min([(a, b, c), (b, c, a), (c, a, b)])


# ----------------------------------------------------------------------------- topology


def test_tetrahedron_topology():
    v, t = tetrahedron()
    m = TriMesh(v, t)
    assert m.edges.shape == (6, 2)
    assert np.all(m.edges[:, 0] < m.edges[:, 1])
    assert {tuple(e) for e in m.edges.tolist()} == {(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)}
    assert m.edge_pairs.shape == (6, 4)
    assert m.boundary_loops == []
    assert m.is_closed
    assert m.signed_volume() == pytest.approx(1.0 / 6.0)
    tris = triangle_set(t)
    for a, b, c, d in m.edge_pairs.tolist():
        assert cyc(a, b, c) in tris and cyc(b, a, d) in tris
        assert len({a, b, c, d}) == 4
    # one ring: in a tetrahedron every vertex neighbours the other three
    indptr, indices = m.one_ring
    for i in range(4):
        assert sorted(indices[indptr[i] : indptr[i + 1]].tolist()) == [
            j for j in range(4) if j != i
        ]
    # face normals point outwards: away from the centroid
    cen = v.mean(axis=0)
    fc = v[t].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", m.face_normals, fc - cen) > 0)
    np.testing.assert_allclose(m.face_areas, [0.5, 0.5, 0.5, np.sqrt(3) / 2])


@pytest.mark.parametrize("nx,ny", [(4, 3), (1, 1), (7, 2)])
def test_grid_topology(nx, ny):
    v, t = grid(nx, ny)
    m = TriMesh(v, t)
    n_edges = nx * (ny + 1) + ny * (nx + 1) + nx * ny  # horizontal + vertical + diagonal
    n_boundary = 2 * (nx + ny)
    assert m.edges.shape == (n_edges, 2)
    assert m.edge_pairs.shape == (n_edges - n_boundary, 4)
    assert m.boundary_edges.shape == (n_boundary, 2)
    loops = m.boundary_loops
    assert len(loops) == 1
    loop = loops[0]
    assert loop.size == n_boundary and np.unique(loop).size == n_boundary
    # ordered: consecutive vertices are joined by an edge, and the loop is counter-clockwise
    # seen from +z (the side the triangles face), i.e. positive signed area
    edge_set = {tuple(e) for e in m.edges.tolist()}
    for a, b in zip(loop, np.roll(loop, -1)):
        assert (min(a, b), max(a, b)) in edge_set
    xy = v[loop, :2]
    signed_area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    assert signed_area == pytest.approx(nx * ny)
    # the boundary vertices are exactly those on the rectangle's border
    on_border = (v[:, 0] == 0) | (v[:, 0] == nx) | (v[:, 1] == 0) | (v[:, 1] == ny)
    assert set(loop.tolist()) == set(np.flatnonzero(on_border).tolist())
    # edge pairs: consistent with the triangles
    tris = triangle_set(t)
    for a, b, c, d in m.edge_pairs.tolist():
        assert cyc(a, b, c) in tris and cyc(b, a, d) in tris
    # flat: all normals +z
    np.testing.assert_allclose(m.face_normals, np.tile([0, 0, 1.0], (len(t), 1)), atol=1e-15)
    np.testing.assert_allclose(m.vertex_normals, np.tile([0, 0, 1.0], (len(v), 1)), atol=1e-15)
    assert m.area == pytest.approx(nx * ny)


def test_one_ring_matches_brute_force():
    v, t = grid(5, 4)
    m = TriMesh(v, t)
    nbrs = [set() for _ in range(len(v))]
    for tri in t:
        for i in range(3):
            for j in range(3):
                if i != j:
                    nbrs[tri[i]].add(int(tri[j]))
    indptr, indices = m.one_ring
    assert indptr.shape == (len(v) + 1,)
    for i in range(len(v)):
        got = indices[indptr[i] : indptr[i + 1]].tolist()
        assert got == sorted(nbrs[i])
    # interior vertex of a regularly split grid has valence 6
    interior = 2 * 6 + 2
    assert indptr[interior + 1] - indptr[interior] == 6


def test_cube_with_hole():
    v, t = cube()
    closed = TriMesh(v, t)
    assert closed.is_closed and closed.boundary_loops == []
    assert closed.signed_volume() == pytest.approx(1.0)
    assert closed.edges.shape == (18, 2) and closed.edge_pairs.shape == (18, 4)
    # face normals: the six axis directions
    expected = np.repeat(
        np.array(
            [[0, 0, -1], [0, -1, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, 0, 1]], dtype=float
        ),
        2,
        axis=0,
    )
    np.testing.assert_allclose(closed.face_normals, expected, atol=1e-15)
    # vertex normals point into the corner's octant
    corner_dir = v - 0.5
    assert np.all(np.sign(closed.vertex_normals) == np.sign(corner_dir))
    np.testing.assert_allclose(np.linalg.norm(closed.vertex_normals, axis=1), 1.0)

    open_box = TriMesh(v, t[:-2])  # remove the top face
    loops = open_box.boundary_loops
    assert len(loops) == 1 and loops[0].size == 4
    assert set(loops[0].tolist()) == {4, 5, 6, 7}
    assert open_box.edges.shape == (17, 2)  # the top diagonal is gone
    assert open_box.edge_pairs.shape == (13, 4)  # 17 - 4 boundary edges
    # the loop runs along the top square's sides (no diagonal jumps)
    loop = loops[0]
    for a, b in zip(loop, np.roll(loop, -1)):
        assert np.sum(np.abs(v[a] - v[b])) == pytest.approx(1.0)


def test_sphere_normals():
    s = trimesh.creation.icosphere(subdivisions=3, radius=80.0)
    m = TriMesh(s.vertices, s.faces)
    radial = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    cosang = np.einsum("ij,ij->i", m.vertex_normals, radial)
    assert cosang.min() > 0.999
    fc = m.vertices[m.triangles].mean(axis=1)
    fc /= np.linalg.norm(fc, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", m.face_normals, fc).min() > 0.99
    assert m.signed_volume() == pytest.approx(4 / 3 * np.pi * 80.0**3, rel=0.02)
    assert m.area == pytest.approx(float(s.area))


def test_two_boundary_loops_annulus():
    # a flat ring: outer square 4x4 with a 2x2 hole -> two loops (8-ish each)
    v, t = grid(4, 4)
    centre = [
        i
        for i, tri in enumerate(t)
        if np.all((v[tri, 0] >= 1) & (v[tri, 0] <= 3) & (v[tri, 1] >= 1) & (v[tri, 1] <= 3))
    ]
    keep = np.setdiff1d(np.arange(len(t)), centre)
    m = TriMesh(v, t[keep])
    loops = m.boundary_loops
    assert [lp.size for lp in loops] == [16, 8]

    # outer loop counter-clockwise, inner loop clockwise seen from +z
    def area(lp):
        xy = v[lp, :2]
        return 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])

    assert area(loops[0]) == pytest.approx(16.0)
    assert area(loops[1]) == pytest.approx(-4.0)


def test_submesh_keeps_ids():
    v, t = grid(3, 2)
    m = TriMesh(v, t)
    mask = np.zeros(len(t), dtype=bool)
    mask[[0, 1, 5]] = True
    sub, old = m.submesh(mask)
    np.testing.assert_array_equal(sub.vertices, v[old])
    np.testing.assert_array_equal(old[sub.triangles], t[mask])
    sub2, old2 = m.submesh(np.flatnonzero(mask))
    np.testing.assert_array_equal(sub2.triangles, sub.triangles)
    with pytest.raises(MeshError):
        m.submesh(np.zeros(len(t), bool))


def test_concatenate_keeps_order_and_offsets_ids():
    """Against trimesh's concatenation (an independent reference): the same vertices and
    triangles in order, so the first mesh's triangle ids stay valid in the result."""
    a = TriMesh(*grid(3, 2))
    b = TriMesh(*tetrahedron())
    c = TriMesh.concatenate([a, b, a])
    ref = trimesh.util.concatenate(
        [trimesh.Trimesh(m.vertices, m.triangles, process=False) for m in (a, b, a)]
    )
    np.testing.assert_array_equal(c.vertices, ref.vertices)
    np.testing.assert_array_equal(c.triangles, ref.faces)
    np.testing.assert_array_equal(c.triangles[: a.n_triangles], a.triangles)
    assert c.n_vertices == 2 * a.n_vertices + b.n_vertices


def test_arrays_are_read_only():
    v, t = tetrahedron()
    m = TriMesh(v, t)
    v[0, 0] = 99.0  # the caller's array is copied
    assert m.vertices[0, 0] == 0.0
    with pytest.raises(ValueError):
        m.vertices[0, 0] = 1.0
    with pytest.raises(ValueError):
        m.edges[0, 0] = 1
    import pickle

    m.to_trimesh()  # populate caches; they are not pickled
    back = pickle.loads(pickle.dumps(m))
    np.testing.assert_array_equal(back.triangles, m.triangles)
    assert not back.vertices.flags.writeable
    np.testing.assert_array_equal(back.edge_pairs, m.edge_pairs)


# ----------------------------------------------------------------------------- validation


def _err(v, t, **kw) -> MeshError:
    with pytest.raises(MeshError) as info:
        TriMesh(v, t, **kw)
    assert isinstance(info.value, JaxfaceError) and isinstance(info.value, ValueError)
    return info.value


def test_nonfinite_vertices_named():
    v, t = tetrahedron()
    v[2, 1] = np.nan
    v[3, 0] = np.inf
    e = _err(v, t)
    assert e.problem == "nonfinite_vertices"
    assert e.elements == (2, 3)
    assert "2, 3" in str(e)


def test_out_of_range_indices_named():
    v, t = tetrahedron()
    t = t.copy()
    t[1, 2] = 4
    t[3, 0] = -1
    e = _err(v, t)
    assert e.problem == "index_out_of_range"
    assert e.elements == (1, 3)
    assert "[0, 4)" in str(e)


def test_degenerate_triangles_named():
    v, t = grid(2, 2)
    v = v.copy()
    # collapse vertex 4 (the centre) onto the line between 0 and 8: triangle (0, 4, 8)
    # does not exist, so instead put a collinear triangle explicitly
    t2 = np.vstack([t, [[0, 1, 2]]])  # 0, 1, 2 lie on the x axis: zero area
    e = _err(v, t2, validate=True)
    assert e.problem == "degenerate_triangles"
    assert e.elements == (len(t),)
    # repeated vertex id
    t3 = np.vstack([t, [[3, 3, 4]]])
    assert _err(v, t3).elements == (len(t),)
    # coincident vertices (distinct ids, same position)
    v4 = np.vstack([v, v[4]])
    t4 = np.vstack([t, [[0, 4, 9]]])
    assert _err(v4, t4).elements == (len(t),)
    # a tiny but real triangle well above the relative tolerance passes
    v5 = v.copy()
    v5[4] = [1.0, 1.0, 0.0]
    TriMesh(v5, t)
    # relative tolerance: the same shape scaled by 1e-4 still passes (scale-free test)
    TriMesh(v * 1e-4, t)


def test_non_manifold_edge_named():
    v, t = grid(1, 1)
    v = np.vstack([v, [[0.5, 0.5, 1.0]]])
    extra = [[0, 3, 4]]  # third triangle on the diagonal edge (0, 3)
    e = _err(v, np.vstack([t, extra]))
    assert e.problem == "non_manifold_edges"
    assert set(e.elements) == {0, 1, 2}
    np.testing.assert_array_equal(e.edges, [[0, 3]])
    assert "(0, 3)" in str(e)


def test_inconsistent_orientation_named():
    v, t = grid(2, 2)
    t = t.copy()
    t[3] = t[3, ::-1]
    e = _err(v, t)
    assert e.problem == "inconsistent_orientation"
    assert 3 in e.elements
    # orientation check can be switched off; everything else still holds
    m = TriMesh(v, t, validate=False)
    m.validate(orientation=False)


def test_shape_errors():
    with pytest.raises(MeshError) as info:
        TriMesh(np.zeros((4, 2)), [[0, 1, 2]])
    assert info.value.problem == "shape"
    with pytest.raises(MeshError):
        TriMesh(np.zeros((4, 3)), [[0, 1, 2, 3]])
    with pytest.raises(MeshError):
        TriMesh(np.zeros((4, 3)), [[0.5, 1, 2]])
    with pytest.raises(MeshError) as info:
        TriMesh(np.zeros((4, 3)), np.zeros((0, 3), int))
    assert info.value.problem == "empty"


# ----------------------------------------------------------------------------- geodesics


def test_geodesic_on_flat_grid_matches_euclidean_within_graph_error():
    n, h = 20, 2.5
    v, t = grid(n, n, h)
    m = TriMesh(v, t)
    d = m.geodesic_distance([0], normalise=False)  # mm, from the corner (0, 0)
    e = np.linalg.norm(v - v[0], axis=1)
    # paths use axis steps and (+1, +1) diagonals: from this corner that is an 8-connected
    # grid, whose path length lies in [euclid, euclid / cos(22.5 deg)]
    assert np.all(d >= e - 1e-9)
    bound = 1.0 / np.cos(np.pi / 8)
    assert np.all(d <= bound * e + 1e-9)
    # exact along the axes and the diagonal, and the bound is nearly reached in between
    on_lines = (v[:, 0] == 0) | (v[:, 1] == 0) | (v[:, 0] == v[:, 1])
    np.testing.assert_allclose(d[on_lines], e[on_lines], atol=1e-9)
    ratio = d[e > 0] / e[e > 0]
    assert ratio.max() > 1.07
    # normalised version
    dn = m.geodesic_distance(0)
    assert dn.min() == 0.0 and dn.max() == pytest.approx(1.0)
    np.testing.assert_allclose(dn, d / d.max())


def test_geodesic_multiple_sources_and_components():
    v, t = grid(6, 1)
    v2 = np.vstack([v, v + [0, 0, 5.0]])
    t2 = np.vstack([t, t + len(v)])
    m = TriMesh(v2, t2)
    src = [0, 6]  # both ends of the bottom row of the first strip
    d = m.geodesic_distance(src, normalise=False)
    assert d[0] == 0 and d[6] == 0
    assert d[3] == pytest.approx(3.0)  # middle of the row: 3 from either end
    assert np.all(np.isinf(d[len(v) :]))  # the second strip is not connected
    dn = m.geodesic_distance(np.isin(np.arange(len(v2)), src))
    assert np.nanmax(dn[np.isfinite(dn)]) == pytest.approx(1.0)
    with pytest.raises(MeshError):
        m.geodesic_distance([len(v2)])
    with pytest.raises(MeshError):
        m.geodesic_distance([])


# ----------------------------------------------------------------------------- closest points


def test_closest_point_barycentric_matches_trimesh():
    rng = np.random.default_rng(1)
    k = 500
    a, b, c = (rng.normal(size=(k, 3)) for _ in range(3))
    p = rng.normal(size=(k, 3)) * 2
    bary = closest_point_barycentric(p, a, b, c)
    assert np.all(bary >= 0) and np.allclose(bary.sum(axis=1), 1)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    ref = trimesh.triangles.closest_point(np.stack([a, b, c], axis=1), p)
    np.testing.assert_allclose(
        np.linalg.norm(p - q, axis=1), np.linalg.norm(p - ref, axis=1), atol=1e-10
    )
    # degenerate triangle: no NaN
    z = np.zeros((1, 3))
    out = closest_point_barycentric(np.ones((1, 3)), z, z, z)
    assert np.all(np.isfinite(out)) and out.sum() == pytest.approx(1)


def test_closest_points_on_plane_and_sphere():
    v, t = grid(10, 10, 1.0)
    m = TriMesh(v, t)
    rng = np.random.default_rng(2)
    p = np.column_stack(
        [rng.uniform(0.5, 9.5, 50), rng.uniform(0.5, 9.5, 50), rng.uniform(-3, 3, 50)]
    )
    sp, dist = m.closest_points(p)
    np.testing.assert_allclose(dist, np.abs(p[:, 2]), atol=1e-12)
    pos = np.asarray(sp.positions(m.vertices, m.triangles))
    np.testing.assert_allclose(pos, np.column_stack([p[:, :2], np.zeros(50)]), atol=1e-12)

    s = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    ms = TriMesh(s.vertices, s.faces)
    q = rng.normal(size=(200, 3)) * 40
    sp, dist = ms.closest_points(q)
    _, ref_dist, _ = trimesh.proximity.closest_point(s, q)
    np.testing.assert_allclose(dist, ref_dist, atol=1e-9)
    pos = np.asarray(sp.positions(ms.vertices, ms.triangles))
    np.testing.assert_allclose(np.linalg.norm(pos - q, axis=1), dist, atol=1e-9)


# ----------------------------------------------------------------------------- rays


def test_ray_cast_plane():
    v, t = grid(10, 10, 1.0)
    m = TriMesh(v, t)
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.1, 9.9, size=(40, 2))
    z0 = rng.uniform(1, 5, size=40)
    o = np.column_stack([xy, z0])
    o[-5:, :2] += 20.0  # these miss
    d = np.tile([0, 0, -2.0], (40, 1))  # non-unit on purpose
    hits = m.ray_cast(o, d)
    assert hits.hit.tolist() == [True] * 35 + [False] * 5
    np.testing.assert_array_equal(hits.ray_index, np.arange(35))
    np.testing.assert_allclose(hits.distances, z0[:35], atol=1e-9)
    np.testing.assert_allclose(hits.locations, np.column_stack([xy[:35], np.zeros(35)]), atol=1e-9)
    pos = np.asarray(hits.points.positions(m.vertices, m.triangles))
    np.testing.assert_allclose(pos, hits.locations, atol=1e-9)
    fd = hits.first_distance
    assert np.all(np.isinf(fd[35:])) and np.allclose(fd[:35], z0[:35])
    tri, bary, dist = hits.first_per_ray()
    assert np.all(tri[35:] == -1) and np.all(np.isinf(dist[35:])) and np.all(bary[35:] == 0)
    np.testing.assert_array_equal(tri[:35], np.asarray(hits.points.tri))
    np.testing.assert_allclose(dist[:35], z0[:35])
    # rays pointing away miss (a ray, not a line)
    away = m.ray_cast(o[:5], -d[:5])
    assert not away.hit.any() and len(away.points) == 0


def test_ray_cast_sphere_first_and_all_hits():
    r = 60.0
    s = trimesh.creation.icosphere(subdivisions=3, radius=r)
    m = TriMesh(s.vertices, s.faces)
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = -200.0 * dirs + rng.normal(size=(30, 3)) * 5  # from outside, roughly through the centre
    first = m.ray_cast(o, dirs)
    assert first.hit.all()
    # the tessellated sphere lies between its smallest face-plane distance and r
    inner = float(np.min(np.einsum("ij,ij->i", m.face_normals, m.vertices[m.triangles[:, 0]])))
    assert 0.99 * r < inner < r
    rad = np.linalg.norm(first.locations, axis=1)
    assert np.all(rad <= r + 1e-9) and np.all(rad >= inner)
    # hit = origin + distance * direction, and lies on the reported triangle
    np.testing.assert_allclose(first.locations, o + first.distances[:, None] * dirs, atol=1e-8)
    pos = np.asarray(first.points.positions(m.vertices, m.triangles))
    np.testing.assert_allclose(pos, first.locations, atol=1e-8)
    # analytic sphere distance, up to the tessellation
    b = np.einsum("ij,ij->i", o, dirs)
    t_ana = -b - np.sqrt(b * b - (np.einsum("ij,ij->i", o, o) - r * r))
    np.testing.assert_allclose(first.distances, t_ana, atol=1.1 * (r - inner))
    assert np.abs(first.distances - t_ana).max() > 0.05 * (r - inner)  # tolerance not vacuous

    every = m.ray_cast(o, dirs, all_hits=True)
    np.testing.assert_array_equal(every.counts, 2)
    d2 = every.distances.reshape(30, 2)
    assert np.all(d2[:, 0] < d2[:, 1])
    np.testing.assert_allclose(d2[:, 0], first.distances)
    # casting from the hit points outward along the normal with min_distance finds nothing
    out = m.ray_cast(first.locations, first.locations, min_distance=1e-6)
    assert not out.hit.any()
    # from inside the sphere every ray hits exactly once
    inside = m.ray_cast(np.zeros((30, 3)), dirs, all_hits=True)
    np.testing.assert_array_equal(inside.counts, 1)
    with pytest.raises(MeshError):
        m.ray_cast(o[:2], np.zeros((2, 3)))


def test_ray_cast_matches_trimesh_intersector():
    """Independent reference: trimesh's own ray/triangle intersector, on a bumpy closed
    surface with random rays from inside and outside (first and all hits)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    # two overlapping bumpy spheres: rays cross the surface up to four times
    s = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    rng = np.random.default_rng(6)
    v0 = np.asarray(s.vertices)
    v0 = v0 * (1.0 + 0.15 * np.sin(3 * v0[:, :1] / 50.0) * np.cos(2 * v0[:, 1:2] / 50.0))
    v = np.vstack([v0 - [35.0, 0, 0], v0 + [35.0, 0, 0]])
    faces = np.vstack([s.faces, s.faces + len(v0)])
    m = TriMesh(v, faces)
    o = rng.uniform(-120, 120, size=(400, 3))
    o[:100] *= 0.3  # these start inside
    d = rng.normal(size=(400, 3)) * 40 - o  # aimed near the centre
    d[:20, :2] = 0.0  # axis-parallel rays exercise the bounding-box clipping
    every = m.ray_cast(o, d, all_hits=True)
    tri, ray, loc = RayMeshIntersector(trimesh.Trimesh(v, faces, process=False)).intersects_id(
        o, d, multiple_hits=True, return_locations=True
    )
    du = d / np.linalg.norm(d, axis=1, keepdims=True)
    dist = np.einsum("ij,ij->i", loc - o[ray], du[ray])
    order = np.lexsort((dist, ray))
    assert every.hit.sum() > 300 and every.counts.max() == 4
    np.testing.assert_array_equal(every.ray_index, ray[order])
    np.testing.assert_allclose(every.distances, dist[order], atol=1e-9)
    np.testing.assert_allclose(every.locations, loc[order], atol=1e-9)
    first = m.ray_cast(o, d)
    np.testing.assert_array_equal(first.hit, every.hit)
    np.testing.assert_allclose(first.distances, every.first_distance[first.hit])
    # max_distance bounds the ray
    short = m.ray_cast(o, d, all_hits=True, max_distance=50.0)
    assert np.all(short.distances <= 50.0)
    np.testing.assert_array_equal(short.distances, every.distances[every.distances <= 50.0])


# ----------------------------------------------------------------------------- I/O and units


def _head_sized_mesh():
    s = trimesh.creation.icosphere(subdivisions=2, radius=90.0)
    return TriMesh(s.vertices * [1.0, 1.2, 1.0], s.faces)


@pytest.mark.parametrize("ext", [".obj", ".ply"])
@pytest.mark.parametrize("units", ["mm", "cm", "m"])
def test_round_trip_with_units(tmp_path, ext, units):
    m = _head_sized_mesh()
    path = tmp_path / f"head{ext}"
    save_mesh(path, m, units=units)
    back = load_mesh(path, units=units)
    np.testing.assert_array_equal(back.triangles, m.triangles)
    # PLY is float32 (relative 6e-8); OBJ 10 decimals
    np.testing.assert_allclose(
        back.vertices, m.vertices, rtol=2e-7, atol=1e-9 * unit_scale(units) * 10
    )
    # the file really is in the declared unit
    raw = trimesh.load(str(path), process=False, force="mesh")
    np.testing.assert_allclose(
        np.ptp(raw.vertices[:, 1]) * unit_scale(units), np.ptp(m.vertices[:, 1]), rtol=1e-6
    )


def test_save_vertices_and_triangles(tmp_path):
    v, t = cube()
    save_mesh(tmp_path / "c.obj", v * 100, t)
    back = load_mesh(tmp_path / "c.obj")
    np.testing.assert_allclose(back.vertices, v * 100)
    np.testing.assert_array_equal(back.triangles, t)


def test_obj_quads_and_polygons_keep_vertex_ids(tmp_path):
    # two quads with texture coordinates indexed differently from the vertices (trimesh would
    # split/reorder vertices without maintain_order), a convex quad and an unused vertex
    text = """# quads
v 0 0 0
v 100 0 0
v 100 100 0
v 0 100 0
v 200 0 0
v 200 100 0
v 150 -50 0
v 250 -40 0
v 50 50 10
v 300 0 0
v 400 0 0
v 430 80 0
v 350 130 0
v 270 80 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
f 1/5 2/1 3/2 4/3
f 2/4 5/1 6/2 3/3
f 2 7 8 5
f 10 11 12 13 14
"""
    (tmp_path / "q.obj").write_text(text)
    m = load_mesh(tmp_path / "q.obj", validate=False)
    assert m.n_vertices == 14
    np.testing.assert_allclose(m.vertices[6], [150, -50, 0])
    np.testing.assert_allclose(m.vertices[12], [350, 130, 0])
    assert m.n_triangles == 2 + 2 + 2 + 3
    # every triangle faces +z and the triangulation covers each polygon's area
    assert np.allclose(m.face_normals[:, 2], 1.0)
    quad = _polygon_area([[100, 0], [150, -50], [250, -40], [200, 0]])
    penta = _polygon_area([[300, 0], [400, 0], [430, 80], [350, 130], [270, 80]])
    assert m.area == pytest.approx(100 * 100 * 2 + quad + penta)
    used = set(np.unique(m.triangles).tolist())
    assert used == set(range(14)) - {8}  # vertex 9 of the file is unused but kept


def _polygon_area(xy):
    xy = np.asarray(xy, float)
    return abs(0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))


def test_ply_quads(tmp_path):
    text = """ply
format ascii 1.0
element vertex 5
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
0 0 0
100 0 0
100 100 0
0 100 0
200 0 0
4 0 1 2 3
3 1 4 2
"""
    (tmp_path / "q.ply").write_text(text)
    m = load_mesh(tmp_path / "q.ply")
    assert m.n_vertices == 5 and m.n_triangles == 3
    assert m.area == pytest.approx(100 * 100 + 0.5 * 100 * 100)


def test_truncated_and_corrupt_files(tmp_path):
    m = _head_sized_mesh()
    save_mesh(tmp_path / "h.ply", m)
    data = (tmp_path / "h.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshError) as info:
        load_mesh(tmp_path / "cut.ply")
    assert "cut.ply" in str(info.value)

    save_mesh(tmp_path / "h_ascii.ply", m, encoding="ascii")
    text = (tmp_path / "h_ascii.ply").read_text()
    (tmp_path / "cut_ascii.ply").write_text(text[: len(text) - 200])
    with pytest.raises(MeshError) as info:
        load_mesh(tmp_path / "cut_ascii.ply")
    assert "cut_ascii.ply" in str(info.value)

    (tmp_path / "hdr.ply").write_bytes(data[:40])
    with pytest.raises(MeshError, match="hdr.ply"):
        load_mesh(tmp_path / "hdr.ply")

    save_mesh(tmp_path / "h.obj", m)
    lines = (tmp_path / "h.obj").read_text().splitlines()
    cut = "\n".join(lines[:-3]) + "\n" + lines[-3][: len(lines[-3]) // 2]  # mid-line cut
    (tmp_path / "cut.obj").write_text(cut)
    with pytest.raises(MeshError) as info:
        load_mesh(tmp_path / "cut.obj")
    msg = str(info.value)
    assert "cut.obj" in msg and f"line {len(lines) - 2}" in msg

    vcut = "\n".join(lines[:5]) + "\n" + "v 1.0 2.0\n"
    (tmp_path / "vcut.obj").write_text(vcut)
    with pytest.raises(MeshError, match=r"vcut\.obj, line 6"):
        load_mesh(tmp_path / "vcut.obj")

    (tmp_path / "bin.obj").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(MeshError, match="bin.obj"):
        load_mesh(tmp_path / "bin.obj")
    (tmp_path / "x.stl").write_text("solid")
    with pytest.raises(MeshError, match="unsupported"):
        load_mesh(tmp_path / "x.stl")
    with pytest.raises(DataNotFoundError):
        load_mesh(tmp_path / "missing.obj")
    # a structurally bad mesh inside a well-formed file: named file + typed problem
    (tmp_path / "nm.obj").write_text(
        "v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\nf 1 2 3\nf 1 2 4\nf 2 1 3\n"
    )
    with pytest.raises(MeshError) as info:
        load_mesh(tmp_path / "nm.obj")
    assert "nm.obj" in str(info.value) and info.value.problem in (
        "inconsistent_orientation",
        "non_manifold_edges",
    )


def test_units_errors(tmp_path):
    m = _head_sized_mesh()
    save_mesh(tmp_path / "head_m.obj", m, units="m")  # a ~0.2-wide head
    with pytest.raises(UnitsError) as info:
        load_mesh(tmp_path / "head_m.obj", units="mm")
    msg = str(info.value)
    assert "units='m'" in msg and "check_size=False" in msg
    tiny = load_mesh(tmp_path / "head_m.obj", units="mm", check_size=False)
    assert np.ptp(tiny.vertices[:, 1]) == pytest.approx(0.216, rel=1e-3)
    save_mesh(tmp_path / "head_mm.obj", m)
    with pytest.raises(UnitsError, match="units='mm'"):
        load_mesh(tmp_path / "head_mm.obj", units="cm")  # would be 2 m tall
    with pytest.raises(UnitsError, match="unknown unit"):
        load_mesh(tmp_path / "head_mm.obj", units="inch")
    assert unit_scale("Metres") == 1000.0
    check_plausible_size(m.vertices, "mm")
    with pytest.raises(UnitsError):
        check_plausible_size(m.vertices / 10, "mm")


# ----------------------------------------------------------------------------- real data


@pytest.mark.data
def test_ict_face_loads_and_validates(shared):
    d = np.load(shared("data", "ict", "ict_face.npz"))
    v, t, g = d["neutral"], d["triangles"], d["triangle_group"]
    m = TriMesh(v, t)  # the whole head validates (orientation included)
    assert m.n_vertices == 21451 and m.n_triangles == len(t)
    assert not np.any(m._edge_counts > 2)
    # topology sanity: Euler characteristic from the counts
    assert m.edges.shape[0] == m.edge_pairs.shape[0] + m.boundary_edges.shape[0]
    face, old = m.submesh(g == 0)
    face.validate()
    assert list(d["group_names"]).index("face") == 0
    assert face.n_triangles == int((g == 0).sum())
    loops = face.boundary_loops
    assert len(loops) >= 3  # outer border, mouth slit, two eye openings (plus any seams)
    np.testing.assert_array_equal(face.vertices, v[old])
    # outward orientation and frame: the area-weighted mean normal of the face looks along +z
    # (triangles counter-clockwise from outside, face towards +z, left-right symmetric)
    mean_n = (face.face_normals * face.face_areas[:, None]).sum(axis=0) / face.area
    assert mean_n[2] > 0.3 and abs(mean_n[0]) < 0.02
    # geodesic from the nose tip over the face is finite on the connected face region
    tip = int(np.argmax(face.vertices[:, 2]))
    gd = face.geodesic_distance([tip])
    assert gd[tip] == 0 and np.nanmax(gd[np.isfinite(gd)]) == 1.0


@pytest.mark.data
def test_truth_ply_loads_with_stable_ids(shared):
    p = shared("data", "bosphorus_style", "bs900_N_N_0.truth.ply")
    m = load_mesh(p)
    d = np.load(shared("data", "ict", "ict_face.npz"))
    assert m.n_vertices == d["neutral"].shape[0]
    # same vertex order as the ICT model: the neutral truth scan equals the neutral head
    # up to float32 storage and the recorded rigid motion (none for bs900)
    err = np.linalg.norm(m.vertices - d["neutral"], axis=1)
    assert np.median(err) < 1e-3


@pytest.mark.data
def test_artisynth_skull_parts_load_in_metres(shared):
    """Real user-supplied skull parts, stored in metres: they load, convert and validate; the
    same file declared as millimetres is caught by the size check."""
    folder = shared("data", "artisynth")
    cranium = load_mesh(folder / "ubccranium.obj", units="m")
    assert 120 < np.ptp(cranium.vertices, axis=0).max() < 250  # a skull, in mm
    hyoid = load_mesh(folder / "ubchyoid.obj", units="m")
    assert 30 < np.ptp(hyoid.vertices, axis=0).max() < 60
    with pytest.raises(UnitsError, match="units='m'"):
        load_mesh(folder / "ubccranium.obj", units="mm")
