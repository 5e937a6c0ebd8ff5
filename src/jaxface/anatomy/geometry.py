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


def smooth_field(
    mesh: TriMesh,
    field: np.ndarray,
    iterations: int,
    lam: float = 0.5,
    fixed: np.ndarray | None = None,
) -> np.ndarray:
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


def segment_cast(
    mesh: TriMesh, origins, directions, max_dist, *, min_dist: float = 0.0
) -> SegmentHits:
    """Cast bounded rays (segments) against a mesh and keep the first hit of each.

    :meth:`jaxface.mesh.TriMesh.ray_cast` limited to each segment (r-tree candidates along
    the segment, exact Moller-Trumbore); much faster than unbounded rays when the segments
    are short. The thesis uses a spatial hash for the same purpose (sec. 3.3).

    Args:
        mesh: the target mesh.
        origins: ``(R, 3)`` mm.
        directions: ``(R, 3)`` (normalised here; zero or non-finite rows never hit).
        max_dist: ``(R,)`` or scalar segment length, mm.
        min_dist: hits at ``t <= min_dist`` are ignored (mm).

    Returns:
        :class:`SegmentHits`.
    """
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    d = np.broadcast_to(np.asarray(directions, dtype=np.float64), o.shape)
    nrm = np.linalg.norm(d, axis=1)
    r = o.shape[0]
    L = np.broadcast_to(np.asarray(max_dist, dtype=np.float64), (r,))
    hit = np.zeros(r, dtype=bool)
    tbest = np.full(r, np.inf)
    tri = np.zeros(r, dtype=np.int64)
    bary = np.zeros((r, 3))
    rays = np.flatnonzero(
        np.isfinite(nrm) & (nrm > 1e-300) & np.isfinite(o).all(axis=1) & (L > min_dist)
    )
    if rays.size and mesh.n_triangles:
        h = mesh.ray_cast(
            o[rays],
            d[rays] / nrm[rays, None],
            min_distance=max(min_dist, 0.0),
            max_distance=float(L[rays].max()),
        )
        rr = rays[np.asarray(h.ray_index)]
        t = np.asarray(h.distances)
        keep = (t <= L[rr]) & (t > min_dist)
        rr, t = rr[keep], t[keep]
        hit[rr] = True
        tbest[rr] = t
        tri[rr] = np.asarray(h.points.tri, dtype=np.int64)[keep]
        bary[rr] = h.barycentric[keep]
    dn = np.divide(d, nrm[:, None], out=np.zeros_like(d), where=nrm[:, None] > 1e-300)
    loc = o + dn * np.where(np.isfinite(tbest), tbest, 0.0)[:, None]
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


def radial_project(
    meshes,
    points,
    centre,
    *,
    directions=None,
    far: float = 80.0,
    reach: float | None = None,
    first: str = "outermost",
    fallback_closest: bool = True,
) -> RadialHits:
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
