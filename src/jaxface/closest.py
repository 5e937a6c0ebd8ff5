"""Exact closest points on triangle meshes (mm), NumPy/SciPy, off the jit path.

* :func:`mesh_arrays`: ``(vertices, triangles)`` of a :class:`jaxface.mesh.TriMesh`, a
  ``trimesh.Trimesh`` or a ``(V, F)`` pair, checked.
* :func:`closest_on_triangles`: closest point of each of ``K`` triangles to ``K`` points.
* :class:`SurfaceIndex`: exact closest points on a triangle mesh, built once and queried many
  times (ICP, registration, metrics, virtual scans). Besides the closest point it reports the
  triangle, barycentrics, the interpolated normal and whether the closest point lies on the
  mesh boundary (a hole rim or the outer border of a scan), which is how callers tell "the
  scan has no data here" from "the scan is far away".
* :func:`point_to_surface`: distances of points to a surface.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ._parallel import thread_map
from .errors import MeshError
from .normals import vertex_normals
from .surface import SurfacePoints

__all__ = [
    "mesh_arrays",
    "closest_on_triangles",
    "ClosestPoints",
    "SurfaceIndex",
    "point_to_surface",
]


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64 mm, triangles (F, 3) int64)`` of a :class:`jaxface.mesh.TriMesh`,
    a ``trimesh.Trimesh`` or a ``(vertices, triangles)`` pair. Raises :class:`MeshError` for
    anything else or for malformed arrays."""
    if isinstance(mesh, tuple) and len(mesh) == 2:
        v, f = mesh
    elif hasattr(mesh, "vertices") and hasattr(mesh, "triangles"):
        v, f = cast(Any, mesh).vertices, cast(Any, mesh).triangles
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        v, f = cast(Any, mesh).vertices, cast(Any, mesh).faces
    else:
        raise MeshError(
            f"expected a TriMesh, a trimesh.Trimesh or a (vertices, triangles) pair, got "
            f"{type(mesh).__name__}.",
            problem="not_a_mesh",
        )
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(
            f"mesh arrays must be vertices (V, 3) and triangles (F, 3); got {v.shape} and "
            f"{f.shape}.",
            problem="mesh_shape",
        )
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        bad = np.flatnonzero((f < 0).any(1) | (f >= len(v)).any(1))
        raise MeshError(
            f"{bad.size} triangle(s) index vertices outside [0, {len(v)}) (rows "
            f"{bad[:10].tolist()}); fix the triangle array.",
            problem="index_out_of_range",
            elements=bad[:100],
        )
    return v, f


# --------------------------------------------------------------------------------------
# exact closest points on triangles
# --------------------------------------------------------------------------------------
def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _sdiv(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    ok = d != 0
    return np.where(ok, n / np.where(ok, d, 1.0), 0.0)


def closest_on_triangles(p, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each triangle ``(a[k], b[k], c[k])`` to ``p[k]`` (Voronoi-region
    classification, exact; degenerate triangles fall back to their edges or vertices).

    Arguments:
        p, a, b, c: ``(K, 3)`` points and triangle corners, mm.

    Returns:
        ``(closest (K, 3) mm, bary (K, 3))`` with ``closest = bary @ [a, b, c]``, barycentrics
        non-negative and summing to 1.
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = _dot(ab, ap)
    d2 = _dot(ac, ap)
    bp = p - b
    d3 = _dot(ab, bp)
    d4 = _dot(ac, bp)
    cp = p - c
    d5 = _dot(ab, cp)
    d6 = _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    den = va + vb + vc
    v = _sdiv(vb, den)
    w = _sdiv(vc, den)
    bary = np.stack([1.0 - v - w, v, w], axis=1)
    # Voronoi regions, assigned from the lowest to the highest priority
    t = np.clip(_sdiv(d4 - d3, (d4 - d3) + (d5 - d6)), 0.0, 1.0)
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    bary[m] = np.stack([np.zeros(m.sum()), 1.0 - t[m], t[m]], axis=1)
    t = np.clip(_sdiv(d2, d2 - d6), 0.0, 1.0)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    bary[m] = np.stack([1.0 - t[m], np.zeros(m.sum()), t[m]], axis=1)
    m = (d6 >= 0) & (d5 <= d6)
    bary[m] = (0.0, 0.0, 1.0)
    t = np.clip(_sdiv(d1, d1 - d3), 0.0, 1.0)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    bary[m] = np.stack([1.0 - t[m], t[m], np.zeros(m.sum())], axis=1)
    m = (d3 >= 0) & (d4 <= d3)
    bary[m] = (0.0, 1.0, 0.0)
    m = (d1 <= 0) & (d2 <= 0)
    bary[m] = (1.0, 0.0, 0.0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


@dataclass(frozen=True)
class ClosestPoints:
    """Result of :meth:`SurfaceIndex.query` for ``K`` query points.

    Attributes:
        points: ``(K, 3)`` closest surface points, mm.
        distances: ``(K,)`` distances query -> surface, mm.
        triangles: ``(K,)`` int64 ids of the triangles (into the mesh's triangle array).
        bary: ``(K, 3)`` barycentric coordinates of the points in those triangles.
        normals: ``(K, 3)`` unit normals at the points (barycentric interpolation of the
            area-weighted vertex normals).
        on_boundary: ``(K,)`` bool: the closest point lies on a boundary edge or boundary
            vertex of the (active part of the) mesh, i.e. the query is beyond a hole rim or the
            mesh border rather than above the surface.
    """

    points: np.ndarray
    distances: np.ndarray
    triangles: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    on_boundary: np.ndarray

    def surface_points(self):
        """The closest points as :class:`jaxface.surface.SurfacePoints` (JAX)."""
        return SurfacePoints(self.triangles, self.bary)


class SurfaceIndex:
    """Exact closest-point queries on a fixed triangle mesh (mm), built once, queried often.

    Candidate triangles come from a k-d tree of the vertices (the triangles around the
    nearest vertices give an upper bound ``u`` of the distance) and then from k-d trees of
    triangle centroids, bucketed by triangle radius ``r``: every triangle whose centroid lies
    within ``u + r`` of the query is tested, which makes the result exact (a triangle lies
    inside the ball of radius ``r`` about its centroid).

    Arguments:
        vertices: ``(V, 3)`` mm.
        triangles: ``(F, 3)`` int vertex ids.
        triangle_mask: optional ``(F,)`` bool; only these triangles are searched, and the
            boundary used for ``on_boundary`` is the boundary of this active part.

    Raises:
        MeshError: malformed arrays, non-finite vertices, or no active triangle.
    """

    def __init__(self, vertices, triangles, triangle_mask=None):
        v, f = mesh_arrays((vertices, triangles))
        if not np.all(np.isfinite(v)):
            bad = np.flatnonzero(~np.isfinite(v).all(1))
            raise MeshError(
                f"{bad.size} vertices are NaN/inf (first {bad[:10].tolist()}); remove them "
                "before building a SurfaceIndex.",
                problem="non_finite_vertices",
                elements=bad[:100],
            )
        self.vertices = v
        self.triangles = f
        active = np.ones(len(f), bool) if triangle_mask is None else np.asarray(triangle_mask, bool)
        if active.shape != (len(f),):
            raise MeshError(
                f"triangle_mask must have shape ({len(f)},), got {active.shape}.",
                problem="mask_shape",
            )
        self.active_ids = np.flatnonzero(active)
        if self.active_ids.size == 0:
            raise MeshError(
                "the surface has no (active) triangles to search.", problem="empty_mesh"
            )
        fa = f[self.active_ids]
        self._a, self._b, self._c = v[fa[:, 0]], v[fa[:, 1]], v[fa[:, 2]]
        # normals
        cr = np.cross(self._b - self._a, self._c - self._a)
        self.vertex_normals = vertex_normals(v, fa)
        # boundary of the active part: edges used by exactly one active triangle
        e = np.concatenate(
            [fa[:, [1, 2]], fa[:, [2, 0]], fa[:, [0, 1]]]
        )  # edge k opposite corner k
        es = np.sort(e, axis=1)
        key = es[:, 0] * np.int64(len(v)) + es[:, 1]
        _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        bnd_edge = (cnt[inv] == 1).reshape(3, -1).T  # (Fa, 3): edge opposite corner k is boundary
        self._edge_boundary = bnd_edge
        bv = np.zeros(len(v), bool)
        bv[e[cnt[inv] == 1].ravel()] = True
        self.boundary_vertices = bv
        # vertex -> incident active triangles (CSR over local ids)
        used = np.unique(fa)
        self._used_vertices = used
        self._vtree = cKDTree(v[used])
        order = np.argsort(fa.ravel(), kind="stable")
        counts = np.bincount(fa.ravel(), minlength=len(v))
        self._vt_ptr = np.concatenate([[0], np.cumsum(counts)])
        self._vt_idx = (order // 3).astype(np.int64)
        # centroid trees bucketed by radius
        cen = (self._a + self._b + self._c) / 3.0
        rad = np.sqrt(
            np.max(
                np.stack([np.sum((x - cen) ** 2, 1) for x in (self._a, self._b, self._c)]), axis=0
            )
        )
        med = max(float(np.median(rad)), 1e-12)
        levels = np.ceil(np.log2(np.maximum(rad / med, 1.0))).astype(int)
        self._lo = np.minimum(np.minimum(self._a, self._b), self._c)
        self._hi = np.maximum(np.maximum(self._a, self._b), self._c)
        crn = np.linalg.norm(cr, axis=1, keepdims=True)
        self._fn = np.where(crn > 0, cr / np.where(crn > 0, crn, 1.0), 0.0)  # 0: no plane bound
        self._buckets = []
        for lev in np.unique(levels):
            ids = np.flatnonzero(levels == lev)
            self._buckets.append((cKDTree(cen[ids]), ids, float(rad[ids].max())))

    @classmethod
    def from_mesh(cls, mesh, triangle_mask=None) -> SurfaceIndex:
        """Index of a :class:`TriMesh` / ``trimesh.Trimesh`` / ``(V, F)`` pair."""
        v, f = mesh_arrays(mesh)
        return cls(v, f, triangle_mask)

    def _candidate_pairs(self, q: np.ndarray, k_vertices: int) -> tuple[np.ndarray, np.ndarray]:
        k = min(k_vertices, len(self._used_vertices))
        _, nn = self._vtree.query(q, k=k)
        nn = self._used_vertices[np.asarray(nn).reshape(len(q), k)]
        starts = self._vt_ptr[nn].ravel()
        lens = (self._vt_ptr[nn + 1] - self._vt_ptr[nn]).ravel()
        qi = np.repeat(np.repeat(np.arange(len(q)), k), lens)
        offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
        ti = self._vt_idx[np.repeat(starts, lens) + offs]
        return qi, ti

    def _eval_pairs(self, q, qi, ti):
        pts, bary = closest_on_triangles(q[qi], self._a[ti], self._b[ti], self._c[ti])
        d2 = np.sum((pts - q[qi]) ** 2, axis=1)
        return pts, bary, d2

    @staticmethod
    def _best(qi, d2):
        """Index of the smallest ``d2`` for each distinct ``qi`` (first one on ties)."""
        order = np.argsort(qi, kind="stable")
        qs = qi[order]
        d2s = d2[order]
        starts = np.flatnonzero(np.concatenate([[True], qs[1:] != qs[:-1]]))
        mins = np.minimum.reduceat(d2s, starts)
        lens = np.diff(np.concatenate([starts, [len(qs)]]))
        hit = np.flatnonzero(d2s <= np.repeat(mins, lens))
        grp = np.searchsorted(starts, hit, side="right") - 1
        _, first = np.unique(grp, return_index=True)
        return order[hit[first]]

    def _lower_bound(self, q, qi, ti):
        """A cheap lower bound of the pair distances: max(box distance, plane distance)."""
        p = q[qi]
        gap = np.maximum(self._lo[ti] - p, 0.0) + np.maximum(p - self._hi[ti], 0.0)
        box = np.sqrt(np.sum(gap * gap, axis=1))
        plane = np.abs(_dot(p - self._a[ti], self._fn[ti]))
        return np.maximum(box, plane)

    def query(
        self,
        points,
        *,
        max_distance: float | None = None,
        exact: bool = True,
        k_vertices: int = 3,
        chunk: int = 8192,
    ) -> ClosestPoints:
        """Closest surface points of ``points`` ``(K, 3)`` mm; see :class:`ClosestPoints`.

        Arguments:
            points: ``(K, 3)`` query points, mm.
            max_distance: optional search radius, mm. Results closer than it are exact;
                a query whose closest point is farther gets *some* surface point farther
                than ``max_distance`` (not necessarily the closest), which is all ICP-style
                callers that reject far pairs need, and much faster for far queries.
                ``None`` (default): exact everywhere.
            exact: if False, only the triangles around the ``k_vertices`` nearest vertices
                are searched: several times faster, and exact on well-shaped meshes for
                queries near the surface (ICP inner loops); metrics use the exact search.
            k_vertices: nearest vertices whose triangles seed the search.

        Raises:
            MeshError: ``points`` is not ``(K, 3)`` or holds NaN/inf.
        """
        q = np.asarray(points, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3:
            raise MeshError(
                f"query points must be (K, 3) mm, got {q.shape}.", problem="points_shape"
            )
        if not np.all(np.isfinite(q)):
            bad = np.flatnonzero(~np.isfinite(q).all(1))
            raise MeshError(
                f"{bad.size} query points are NaN/inf (first {bad[:10].tolist()}).",
                problem="non_finite_points",
                elements=bad[:100],
            )
        if len(q) > chunk:
            # independent blocks: on all cores (NumPy and the k-d trees release the GIL)
            parts = thread_map(
                lambda s: self.query(
                    q[s : s + chunk],
                    max_distance=max_distance,
                    exact=exact,
                    k_vertices=k_vertices,
                    chunk=chunk,
                ),
                range(0, len(q), chunk),
            )
            return ClosestPoints(
                *(
                    np.concatenate([getattr(p, f.name) for p in parts])
                    for f in dataclasses.fields(ClosestPoints)
                )
            )
        n = len(q)
        if n == 0:
            z3 = np.zeros((0, 3))
            return ClosestPoints(z3, np.zeros(0), np.zeros(0, np.int64), z3, z3, np.zeros(0, bool))
        # 1) upper bound from the triangles around the nearest vertices
        qi, ti = self._candidate_pairs(q, k_vertices)
        _, _, d2 = self._eval_pairs(q, qi, ti)
        sel = self._best(qi, d2)
        sel = sel[np.argsort(qi[sel])]
        ub = np.sqrt(d2[sel]) * (1.0 + 1e-9) + 1e-9
        radius = ub if max_distance is None else np.minimum(ub, float(max_distance))
        if not exact:
            radius = np.zeros(0)
        # 2) every triangle that could be closer: centroid within radius + triangle radius,
        #    then a box/plane lower bound
        qis, tis = [qi[sel]], [ti[sel]]
        for tree, ids, rmax in self._buckets if exact else ():
            lists = tree.query_ball_point(q, radius + rmax, return_sorted=False)
            lens = np.fromiter(map(len, lists), dtype=np.int64, count=n)
            total = int(lens.sum())
            if total == 0:
                continue
            cq = np.repeat(np.arange(n), lens)
            ct = ids[np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=total)]
            keep = self._lower_bound(q, cq, ct) <= radius[cq]
            qis.append(cq[keep])
            tis.append(ct[keep])
        qi = np.concatenate(qis)
        ti = np.concatenate(tis)
        pts, bary, d2 = self._eval_pairs(q, qi, ti)
        sel = self._best(qi, d2)
        sel = sel[np.argsort(qi[sel])]  # one per query, in query order
        ti, pts, bary, d2 = ti[sel], pts[sel], bary[sel], d2[sel]
        tri_global = self.active_ids[ti]
        corners = self.triangles[tri_global]
        nrm = np.einsum("kj,kjd->kd", bary, self.vertex_normals[corners])
        ln = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.where(ln > 0, nrm / np.where(ln > 0, ln, 1.0), 0.0)
        # on the boundary: on a boundary edge (its opposite barycentric is 0), or at a
        # boundary vertex (its barycentric is 1)
        eps = 1e-9
        on_edge = np.any((bary <= eps) & self._edge_boundary[ti], axis=1)
        at_vertex = np.any((bary >= 1.0 - eps) & self.boundary_vertices[corners], axis=1)
        return ClosestPoints(
            points=pts,
            distances=np.sqrt(d2),
            triangles=tri_global,
            bary=bary,
            normals=nrm,
            on_boundary=np.asarray(on_edge | at_vertex),
        )


def point_to_surface(points, surface) -> np.ndarray:
    """Distances ``(K,)`` mm from ``points`` ``(K, 3)`` mm to a surface (a :class:`SurfaceIndex`,
    TriMesh, ``trimesh.Trimesh`` or ``(V, F)`` pair)."""
    index = surface if isinstance(surface, SurfaceIndex) else SurfaceIndex.from_mesh(surface)
    return index.query(points).distances
