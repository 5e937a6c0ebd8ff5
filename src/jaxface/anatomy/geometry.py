"""Build-time geometry helpers shared by the anatomy modules (NumPy, mm).

* radial projection of points onto a mesh (rays from outside toward a centre, first hit), the
  thesis's cylindrical/radial ray casting used to put landmarks, muscle action lines and
  tissue-depth sites on skin, skull and muscles;
* one-ring smoothing of vertex fields (normals, positions) on a :class:`TriMesh`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh import TriMesh

__all__ = [
    "segment_cast",
    "SegmentHits",
    "adjacency_matrix",
    "smooth_field",
    "smooth_normals",
    "radial_project",
    "RadialHits",
]


def adjacency_matrix(mesh: TriMesh) -> sp.csr_matrix:
    """``(V, V)`` row-normalised one-ring averaging matrix (rows of isolated vertices are the
    identity)."""
    indptr, indices = mesh.one_ring
    n = mesh.n_vertices
    counts = np.diff(indptr)
    rows = np.repeat(np.arange(n), counts)
    w = 1.0 / np.maximum(counts, 1)
    A = sp.csr_matrix((w[rows], (rows, indices)), shape=(n, n))
    iso = np.flatnonzero(counts == 0)
    if iso.size:
        A = A + sp.csr_matrix((np.ones(iso.size), (iso, iso)), shape=(n, n))
    return A.tocsr()


def smooth_field(mesh: TriMesh, field: np.ndarray, iterations: int, lam: float = 0.5,
                 fixed: np.ndarray | None = None) -> np.ndarray:
    """Umbrella (one-ring average) smoothing of a per-vertex field.

    Args:
        mesh: the mesh whose one-rings are used.
        field: ``(V,)`` or ``(V, k)`` values.
        iterations: number of smoothing passes.
        lam: step toward the one-ring average per pass, in (0, 1].
        fixed: optional ``(V,)`` bool, vertices kept unchanged.

    Returns:
        the smoothed field (same shape).
    """
    A = adjacency_matrix(mesh)
    f = np.array(field, dtype=np.float64, copy=True)
    keep = f[fixed].copy() if fixed is not None else None
    for _ in range(int(iterations)):
        f = (1.0 - lam) * f + lam * (A @ f)
        if fixed is not None:
            f[fixed] = keep
    return f


def smooth_normals(mesh: TriMesh, iterations: int = 5) -> np.ndarray:
    """``(V, 3)`` unit vertex normals smoothed over one-rings (area-weighted to start)."""
    n = smooth_field(mesh, mesh.vertex_normals, iterations, lam=0.5)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    fallback = np.asarray(mesh.vertex_normals)
    return np.where(nn > 1e-12, n / np.maximum(nn, 1e-12), fallback)


class SegmentHits:
    """First hits of :func:`segment_cast` (one row per ray).

    Attributes:
        hit: ``(R,)`` bool; t: ``(R,)`` distance along the unit direction, mm (inf if no hit);
        tri: ``(R,)`` int triangle ids (0 where no hit); bary: ``(R, 3)``;
        locations: ``(R, 3)`` mm (the origin where no hit).
    """

    def __init__(self, hit, t, tri, bary, locations):
        self.hit, self.t, self.tri, self.bary, self.locations = hit, t, tri, bary, locations


def _tree(mesh: TriMesh):
    """An r-tree over the triangle bounding boxes (cached on the mesh's trimesh object)."""
    tm = mesh.to_trimesh()
    tree = getattr(tm, "_jaxface_tri_tree", None)
    if tree is None:
        tree = tm.triangles_tree
        try:
            tm._jaxface_tri_tree = tree
        except AttributeError:  # pragma: no cover
            pass
    return tree


def segment_cast(mesh: TriMesh, origins, directions, max_dist, *, min_dist: float = 0.0,
                 piece: float | None = None) -> SegmentHits:
    """Cast bounded rays (segments) against a mesh and keep the first hit of each.

    Much faster than unbounded ray casting for short rays: each segment is cut into pieces
    whose bounding boxes query an r-tree of the triangles (vectorised ``intersection_v``),
    then the candidates are intersected exactly (Moller-Trumbore, vectorised). The thesis
    uses a spatial hash for the same purpose (sec. 3.3).

    Args:
        mesh: the target mesh.
        origins: ``(R, 3)`` mm.
        directions: ``(R, 3)`` (normalised here).
        max_dist: ``(R,)`` or scalar segment length, mm.
        min_dist: hits at ``t <= min_dist`` are ignored (mm).
        piece: piece length for the r-tree queries, mm (default: twice the mean edge length).

    Returns:
        :class:`SegmentHits`.
    """
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    d = np.broadcast_to(np.asarray(directions, dtype=np.float64), o.shape)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    r = o.shape[0]
    L = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), (r,))
    if piece is None:
        piece = 2.0 * float(np.mean(mesh.edge_lengths)) if mesh.n_triangles else 1.0
    npc = np.maximum(np.ceil(L / piece).astype(np.int64), 1)
    ray_of = np.repeat(np.arange(r), npc)
    k = np.arange(ray_of.size) - np.repeat(np.cumsum(npc) - npc, npc)
    plen = (L / npc)[ray_of]
    a = o[ray_of] + d[ray_of] * (k * plen)[:, None]
    b = a + d[ray_of] * plen[:, None]
    eps = 1e-6 * (1.0 + np.abs(o).max(initial=0.0))
    mins = np.minimum(a, b) - eps
    maxs = np.maximum(a, b) + eps
    hit = np.zeros(r, dtype=bool)
    tbest = np.full(r, np.inf)
    tri = np.zeros(r, dtype=np.int64)
    bary = np.zeros((r, 3))
    if r == 0 or mesh.n_triangles == 0:
        return SegmentHits(hit, tbest, tri, bary, o.copy())
    # pieces whose boxes miss the mesh's bounding box need no r-tree query
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    near = np.all((maxs >= lo) & (mins <= hi), axis=1)
    if not near.any():
        return SegmentHits(hit, tbest, tri, bary, o.copy())
    ray_of, mins, maxs = ray_of[near], mins[near], maxs[near]
    ids, counts = _tree(mesh).intersection_v(mins, maxs)
    pr = np.repeat(ray_of, np.asarray(counts, dtype=np.int64))
    pt = np.asarray(ids, dtype=np.int64)
    if pr.size == 0:
        return SegmentHits(hit, tbest, tri, bary, o.copy())
    key = np.unique(pr * mesh.n_triangles + pt)
    pr, pt = key // mesh.n_triangles, key % mesh.n_triangles
    V = mesh.vertices[mesh.triangles[pt]]
    e1 = V[:, 1] - V[:, 0]
    e2 = V[:, 2] - V[:, 0]
    dd = d[pr]
    pv = np.cross(dd, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    ok = np.abs(det) > 1e-14 * (np.einsum("ij,ij->i", e1, e1) + 1e-300)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o[pr] - V[:, 0]
    u = np.einsum("ij,ij->i", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = np.einsum("ij,ij->i", dd, qv) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    tol = 1e-9
    good = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > min_dist) & (t <= L[pr])
    pr, pt, u, v, t = pr[good], pt[good], u[good], v[good], t[good]
    if pr.size:
        order = np.lexsort((t, pr))
        pr, pt, u, v, t = pr[order], pt[order], u[order], v[order], t[order]
        first = np.unique(pr, return_index=True)[1]
        pr, pt, u, v, t = pr[first], pt[first], u[first], v[first], t[first]
        hit[pr] = True
        tbest[pr] = t
        tri[pr] = pt
        bw = np.stack([1 - u - v, u, v], axis=1)
        bary[pr] = np.clip(bw, 0.0, 1.0) / np.clip(bw, 0.0, 1.0).sum(axis=1, keepdims=True)
    loc = o + d * np.where(np.isfinite(tbest), tbest, 0.0)[:, None]
    return SegmentHits(hit, tbest, tri, bary, loc)


class RadialHits:
    """Result of :func:`radial_project`.

    Attributes:
        hit: ``(K,)`` bool, whether each point found a surface.
        positions: ``(K, 3)`` mm, the hit (or the input point where none).
        mesh_index: ``(K,)`` int, which of the meshes was hit (-1 if none).
        tri: ``(K,)`` int triangle ids in that mesh; bary: ``(K, 3)`` barycentrics.
        directions: ``(K, 3)`` unit inward ray directions used.
    """

    def __init__(self, hit, positions, mesh_index, tri, bary, directions):
        self.hit = hit
        self.positions = positions
        self.mesh_index = mesh_index
        self.tri = tri
        self.bary = bary
        self.directions = directions


def radial_project(meshes, points, centre, *, directions=None, far: float = 80.0,
                   reach: float | None = None, first: str = "outermost",
                   fallback_closest: bool = True) -> RadialHits:
    """Project points onto the first of several meshes along rays from outside.

    Each point ``p`` defines the inward direction ``d = normalize(centre - p)`` (or the given
    ``directions``); the ray starts at ``p - far * d`` (outside everything) and travels
    along ``d``. Among the meshes (listed from most superficial to deepest) the hit is:

    * ``first="outermost"``: the first surface the ray meets over all meshes;
    * ``first="priority"``: the first mesh in the list that the ray hits at all (its
      outermost hit).

    Points whose rays miss every mesh are attached by closest point to the first mesh when
    ``fallback_closest`` (else ``hit`` is False).

    Args:
        meshes: a :class:`TriMesh` or a list of them.
        points: ``(K, 3)`` mm.
        centre: ``(3,)`` mm, or ``(K, 3)`` per-point centres.
        directions: optional ``(K, 3)`` inward directions (overrides ``centre``).
        far: start distance of the rays outside the point, mm.
        reach: how far the rays travel, mm (default ``2 * far``).

    Returns:
        :class:`RadialHits`.
    """
    if isinstance(meshes, TriMesh):
        meshes = [meshes]
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    k = p.shape[0]
    if directions is None:
        d = np.asarray(centre, dtype=np.float64) - p
    else:
        d = np.broadcast_to(np.asarray(directions, dtype=np.float64), p.shape).copy()
    nd = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(nd > 1e-12, d / np.maximum(nd, 1e-12), np.array([0.0, 0.0, -1.0]))
    origins = p - far * d
    best_t = np.full(k, np.inf)
    mesh_index = np.full(k, -1, dtype=np.int64)
    tri = np.zeros(k, dtype=np.int64)
    bary = np.zeros((k, 3))
    pos = p.copy()
    reach = 2.0 * far if reach is None else reach
    for mi, m in enumerate(meshes):
        hits = segment_cast(m, origins, d, reach)
        r = np.flatnonzero(hits.hit)
        if r.size == 0:
            continue
        t = hits.t[r]
        if first == "outermost":
            better = t < best_t[r]
        else:
            better = mesh_index[r] < 0
        r = r[better]
        best_t[r] = hits.t[r]
        mesh_index[r] = mi
        tri[r] = hits.tri[r]
        bary[r] = hits.bary[r]
        pos[r] = hits.locations[r]
    hit = mesh_index >= 0
    if fallback_closest and not hit.all():
        miss = np.flatnonzero(~hit)
        spts, _ = meshes[0].closest_points(p[miss])
        mesh_index[miss] = 0
        tri[miss] = np.asarray(spts.tri)
        bary[miss] = np.asarray(spts.bary)
        corners = meshes[0].vertices[meshes[0].triangles[tri[miss]]]
        pos[miss] = np.einsum("kj,kjd->kd", bary[miss], corners)
        hit[miss] = True
    return RadialHits(hit, pos, mesh_index, tri, bary, d)
