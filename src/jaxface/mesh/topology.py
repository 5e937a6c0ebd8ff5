"""Cached topology of a :class:`~jaxface.mesh.TriMesh`: edges, interior edge pairs, boundary
loops, one-ring adjacency, the edge graph and geodesic (edge-graph Dijkstra) distances, mm."""

from __future__ import annotations

from functools import cached_property
from typing import cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..errors import MeshError
from .arrays import _list, _readonly
from .base import MeshBase

__all__ = ["MeshTopology"]


class MeshTopology(MeshBase):
    """The topology layer of :class:`~jaxface.mesh.TriMesh` (all arrays read-only, cached)."""

    # ---------------------------------------------------------------- topology (cached)
    @cached_property
    def _half_edges(self) -> np.ndarray:
        """(3F, 2) directed edges; row 3f+k = (t[f,k], t[f,(k+1)%3])."""
        t = self._triangles
        return _readonly(t[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2))

    @cached_property
    def _edge_index(self):
        he = self._half_edges
        nv = max(self.n_vertices, 1)
        lo = np.minimum(he[:, 0], he[:, 1])
        hi = np.maximum(he[:, 0], he[:, 1])
        key = lo * nv + hi
        uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        edges = np.stack([uniq // nv, uniq % nv], axis=1).astype(np.int64)
        return _readonly(edges), _readonly(inv.astype(np.int64)), _readonly(cnt.astype(np.int64))

    @property
    def edges(self) -> np.ndarray:
        """``(E, 2)`` int64 unique undirected edges, each row sorted (i < j), rows sorted."""
        return self._edge_index[0]

    @property
    def triangle_edges(self) -> np.ndarray:
        """``(F, 3)`` int64 edge ids of each triangle: edge k joins corners k and (k+1) % 3."""
        return _readonly(self._edge_index[1].reshape(-1, 3))

    @property
    def _edge_counts(self) -> np.ndarray:
        return self._edge_index[2]

    @cached_property
    def edge_lengths(self) -> np.ndarray:
        """``(E,)`` edge lengths, mm."""
        e = self.edges
        return _readonly(np.linalg.norm(self._vertices[e[:, 1]] - self._vertices[e[:, 0]], axis=1))

    @cached_property
    def _edge_halfedges(self):
        """(E, 2) half-edge ids per edge (-1 where absent), from the first two uses."""
        inv = self._edge_index[1]
        order = np.argsort(inv, kind="stable")
        cnt = self._edge_counts
        start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        first = order[start]
        second = np.where(cnt >= 2, order[np.minimum(start + 1, order.size - 1)], -1)
        return np.stack([first, second], axis=1)

    @cached_property
    def edge_faces(self) -> np.ndarray:
        """``(E, 2)`` int64 ids of the triangles on each edge; ``-1`` in column 1 for boundary
        edges. For non-manifold edges (only with ``validate=False``) the first two are given."""
        h = self._edge_halfedges
        return _readonly(np.where(h >= 0, h // 3, -1))

    @cached_property
    def _pairs(self):
        cnt = self._edge_counts
        interior = np.flatnonzero(cnt == 2)
        h = self._edge_halfedges[interior]
        t = self._triangles
        f1, k1 = h[:, 0] // 3, h[:, 0] % 3
        f2, k2 = h[:, 1] // 3, h[:, 1] % 3
        a = t[f1, k1]
        b = t[f1, (k1 + 1) % 3]
        c = t[f1, (k1 + 2) % 3]
        d = t[f2, (k2 + 2) % 3]
        pairs = np.stack([a, b, c, d], axis=1).astype(np.int64)
        faces = np.stack([f1, f2], axis=1).astype(np.int64)
        return _readonly(pairs), _readonly(faces), _readonly(interior.astype(np.int64))

    @property
    def edge_pairs(self) -> np.ndarray:
        """``(P, 4)`` int64 rows ``[a, b, c, d]``, one per interior edge (exactly two
        triangles), in edge-id order: ``(a, b)`` is the shared edge, ``c`` and ``d`` the
        vertices opposite it. ``(a, b, c)`` is the first triangle in its stored orientation and,
        for a consistently oriented mesh, ``(b, a, d)`` the second. Used for bending and
        cross-edge stretch constraints (distance ``c``-``d``)."""
        return self._pairs[0]

    @property
    def edge_pair_faces(self) -> np.ndarray:
        """``(P, 2)`` int64 triangle ids ``(f1, f2)`` of each :attr:`edge_pairs` row."""
        return self._pairs[1]

    @property
    def interior_edges(self) -> np.ndarray:
        """``(P,)`` int64 edge ids of the interior edges (rows of :attr:`edge_pairs`)."""
        return self._pairs[2]

    @property
    def boundary_edges(self) -> np.ndarray:
        """``(B, 2)`` int64 boundary edges (one triangle), directed as in their triangle."""
        h = self._edge_halfedges[self._edge_counts == 1, 0]
        return _readonly(self._half_edges[h].copy())

    @cached_property
    def boundary_loops(self) -> list[np.ndarray]:
        """Closed boundary loops, each an ordered ``(n,)`` int64 array of vertex ids.

        A loop follows the boundary edges in the direction of their triangles (for a surface
        seen from outside, counter-clockwise around the surface). Each loop starts at its
        smallest vertex id; loops are sorted longest first. A vertex where two loops touch is
        listed in both. Empty list for a closed mesh.
        """
        be = self.boundary_edges
        if be.shape[0] == 0:
            return []
        # outgoing boundary half-edges per vertex
        order = np.argsort(be[:, 0], kind="stable")
        src_sorted = be[order, 0]
        used = np.zeros(be.shape[0], dtype=bool)
        loops: list[np.ndarray] = []

        def outgoing(vtx):
            lo = np.searchsorted(src_sorted, vtx, side="left")
            hi = np.searchsorted(src_sorted, vtx, side="right")
            return order[lo:hi]

        for start in range(be.shape[0]):
            if used[start]:
                continue
            loop = [int(be[start, 0])]
            used[start] = True
            cur = start
            while True:
                nxt_v = int(be[cur, 1])
                if nxt_v == loop[0]:
                    break
                cand = [i for i in outgoing(nxt_v) if not used[i]]
                if not cand:  # open chain (only on a broken mesh): stop here
                    loop.append(nxt_v)
                    break
                loop.append(nxt_v)
                cur = int(cand[0])
                used[cur] = True
            arr = np.asarray(loop, dtype=np.int64)
            arr = np.roll(arr, -int(np.argmin(arr)))
            loops.append(_readonly(arr))
        loops.sort(key=lambda a: (-a.size, int(a[0])))
        return loops

    @cached_property
    def one_ring(self) -> tuple[np.ndarray, np.ndarray]:
        """One-ring adjacency in CSR form ``(indptr (V+1,), indices)``, both int64: the
        neighbours of vertex ``i`` are ``indices[indptr[i]:indptr[i+1]]`` (sorted)."""
        g = self._graph(weighted=False)
        return _readonly(g.indptr.astype(np.int64)), _readonly(g.indices.astype(np.int64))

    def _graph(self, weighted: bool = True) -> sp.csr_matrix:
        e = self.edges
        nv = self.n_vertices
        w = self.edge_lengths if weighted else np.ones(e.shape[0])
        g = sp.coo_matrix(
            (
                np.concatenate([w, w]),
                (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])),
            ),
            shape=(nv, nv),
        ).tocsr()
        g.sort_indices()
        return cast(sp.csr_matrix, g)

    @cached_property
    def _edge_graph(self) -> sp.csr_matrix:
        return self._graph(weighted=True)

    @property
    def is_closed(self) -> bool:
        """True when every edge has exactly two triangles (watertight)."""
        return bool(np.all(self._edge_counts == 2))

    # ---------------------------------------------------------------- geodesics
    def geodesic_distance(self, sources, normalise: bool = True) -> np.ndarray:
        """Shortest-path distance over the edge graph (Dijkstra) from the nearest source vertex.

        The edge-graph distance over-estimates the true surface geodesic (paths are restricted
        to edges; on a regular grid by up to ~8%), which is fine for influence maps.

        Args:
            sources: int vertex id or ``(S,)`` vertex ids (or a ``(V,)`` bool mask).
            normalise: if True divide by the largest finite distance, so values lie in [0, 1];
                if False return millimetres.

        Returns:
            ``(V,)`` float64: 0 at the sources; ``inf`` for vertices not connected to any source.
        """
        src = np.asarray(sources)
        if src.dtype == bool:
            if src.shape != (self.n_vertices,):
                raise MeshError(
                    f"a source mask must have shape ({self.n_vertices},), got {src.shape}.",
                    problem="bad_sources",
                )
            src = np.flatnonzero(src)
        src = np.atleast_1d(src).astype(np.int64).ravel()
        if src.size == 0:
            raise MeshError(
                "geodesic_distance needs at least one source vertex.", problem="bad_sources"
            )
        bad = src[(src < 0) | (src >= self.n_vertices)]
        if bad.size:
            raise MeshError(
                f"geodesic source vertex id(s) {_list(bad)} are outside [0, {self.n_vertices}).",
                problem="bad_sources",
                elements=bad,
            )
        d = dijkstra(self._edge_graph, directed=False, indices=np.unique(src), min_only=True)
        d = np.asarray(d, dtype=np.float64)
        if normalise:
            finite = d[np.isfinite(d)]
            m = float(finite.max()) if finite.size else 0.0
            if m > 0:
                d = d / m
        return d
