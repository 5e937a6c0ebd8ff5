"""The :class:`TriMesh` class: construction, validation (:class:`~jaxface.errors.MeshError`
with a ``problem`` tag, see :mod:`jaxface.mesh`), new vertices, sub-meshes. Topology, geometry
and queries come from its base classes (:mod:`.base`, :mod:`.topology`, :mod:`.raycast`)."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from .arrays import _as_triangles, _as_vertices, _edge_list, _list, _readonly
from .raycast import MeshQueries

__all__ = ["TriMesh", "DEGENERATE_TOL"]

#: default relative tolerance for degenerate (zero-area) triangles: area <= tol * bbox_diag^2
DEGENERATE_TOL = 1e-10


class TriMesh(MeshQueries):
    """An immutable triangle mesh (NumPy): vertices in mm and triangles, with cached topology.

    Build-time only (never on the jit path). Topology and geometry properties are computed on
    first access and cached; all returned arrays are read-only.

    Attributes:
        vertices: ``(V, 3)`` float64, mm.
        triangles: ``(F, 3)`` int64 vertex ids, counter-clockwise seen from outside.

    Args:
        vertices: ``(V, 3)`` array-like, mm.
        triangles: ``(F, 3)`` integer array-like.
        validate: run :meth:`validate` (with ``orientation=True``) and raise
            :class:`MeshError` on a bad mesh.
        degenerate_tol: relative zero-area tolerance used by the validation (see module doc).
    """

    def __init__(
        self, vertices, triangles, *, validate: bool = True, degenerate_tol: float = DEGENERATE_TOL
    ):
        self._vertices = _as_vertices(vertices)
        self._triangles = _as_triangles(triangles)
        self._degenerate_tol = float(degenerate_tol)
        if validate:
            self.validate()

    def __getstate__(self):  # pickle only the data; caches (trimesh, r-trees) are rebuilt
        return {"v": self._vertices, "t": self._triangles, "tol": self._degenerate_tol}

    def __setstate__(self, state):
        self._vertices = _readonly(np.array(state["v"], dtype=np.float64))
        self._triangles = _readonly(np.array(state["t"], dtype=np.int64))
        self._degenerate_tol = float(state["tol"])

    def with_vertices(self, vertices, *, validate: bool = False) -> TriMesh:
        """The same topology with new ``(V, 3)`` vertex positions (mm)."""
        v = np.asarray(vertices)
        if v.shape != self._vertices.shape:
            raise MeshError(
                f"with_vertices needs {self._vertices.shape} vertices, got {v.shape}.",
                problem="shape",
            )
        return TriMesh(v, self._triangles, validate=validate, degenerate_tol=self._degenerate_tol)

    # ---------------------------------------------------------------- validation
    def validate(self, *, orientation: bool = True, degenerate_tol: float | None = None) -> None:
        """Check the mesh; raise :class:`MeshError` on the first problem found.

        Checks, in order: at least one triangle; finite coordinates; vertex ids in range;
        no degenerate triangles (repeated id, or area <= ``degenerate_tol * D**2`` with ``D``
        the bounding-box diagonal); no edge shared by more than two triangles; and, if
        ``orientation``, a consistent orientation (each interior edge traversed in opposite
        directions by its two triangles). The error's ``problem`` names the check and
        ``elements`` the offending vertex or triangle ids (see the module docstring).

        Unreferenced vertices, several connected components, open boundaries and
        non-manifold *vertices* are allowed.
        """
        tol = self._degenerate_tol if degenerate_tol is None else float(degenerate_tol)
        v, t = self._vertices, self._triangles
        nv = v.shape[0]
        if t.shape[0] == 0:
            raise MeshError("mesh has no triangles; a TriMesh needs at least one.", problem="empty")

        bad_v = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
        if bad_v.size:
            raise MeshError(
                f"{bad_v.size} vertex(es) have NaN or inf coordinates: vertex ids "
                f"{_list(bad_v)}. Remove or repair them (e.g. fill holes in the scan) before "
                f"building the mesh.",
                problem="nonfinite_vertices",
                elements=bad_v,
            )

        bad_t = np.flatnonzero(np.any((t < 0) | (t >= nv), axis=1))
        if bad_t.size:
            raise MeshError(
                f"{bad_t.size} triangle(s) refer to vertex ids outside [0, {nv}): triangle ids "
                f"{_list(bad_t)} (e.g. triangle {int(bad_t[0])} = {t[bad_t[0]].tolist()}). "
                f"Check for one-based indices or a truncated vertex list.",
                problem="index_out_of_range",
                elements=bad_t,
            )

        rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 2] == t[:, 0])
        used = np.unique(t)
        diag = float(np.linalg.norm(v[used].max(axis=0) - v[used].min(axis=0)))
        area = self._areas_raw()
        thresh = tol * diag * diag
        degenerate = rep | (area <= thresh)
        bad_t = np.flatnonzero(degenerate)
        if bad_t.size:
            raise MeshError(
                f"{bad_t.size} degenerate (zero-area) triangle(s): triangle ids {_list(bad_t)} "
                f"(area <= {thresh:.3g} mm^2 = {tol:g} * bbox_diagonal^2, or a repeated vertex "
                f"id; smallest area {float(area[bad_t].min()):.3g} mm^2). Remove them, merge "
                f"the coincident vertices, or pass a smaller degenerate_tol.",
                problem="degenerate_triangles",
                elements=bad_t,
            )

        counts = self._edge_counts
        nm = np.flatnonzero(counts > 2)
        if nm.size:
            edges = self.edges[nm]
            tris = np.unique(np.flatnonzero(np.isin(self.triangle_edges, nm).any(axis=1)))
            err = MeshError(
                f"{nm.size} non-manifold edge(s) shared by more than two triangles: edges "
                f"{_edge_list(edges)}; triangles {_list(tris)}. Split the mesh at these edges "
                f"or remove the extra triangles (duplicated or fin triangles).",
                problem="non_manifold_edges",
                elements=tris,
            )
            err.edges = edges
            raise err

        if orientation:
            he = self._half_edges  # (3F, 2) directed, in triangle order
            key = he[:, 0] * nv + he[:, 1]
            uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
            dup = np.flatnonzero(cnt[inv] > 1)
            if dup.size:
                tris = np.unique(dup // 3)
                edges = np.unique(np.sort(he[dup], axis=1), axis=0)
                err = MeshError(
                    f"inconsistent orientation: {edges.shape[0]} edge(s) are traversed in the "
                    f"same direction by both of their triangles (normals flip across them): "
                    f"edges {_edge_list(edges)}; triangles {_list(tris)}. Reorient the mesh "
                    f"consistently (e.g. trimesh.repair.fix_winding) so that triangles are "
                    f"counter-clockwise seen from outside.",
                    problem="inconsistent_orientation",
                    elements=tris,
                )
                err.edges = edges
                raise err

    @classmethod
    def concatenate(cls, meshes) -> TriMesh:
        """The meshes as one (not validated), in order: mesh ``k``'s vertices and triangles
        follow those of meshes ``0..k-1`` (its triangle ids offset by their vertex count), so
        a triangle index into the first mesh is one into the result."""
        meshes = list(meshes)
        offs = np.cumsum([0] + [m.n_vertices for m in meshes])[:-1]
        return cls(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.triangles + o for m, o in zip(meshes, offs)]),
            validate=False,
        )

    @classmethod
    def from_trimesh(cls, tm, *, validate: bool = True) -> TriMesh:
        """Build from a ``trimesh.Trimesh`` (its vertices are taken as mm; ids unchanged)."""
        return cls(np.asarray(tm.vertices), np.asarray(tm.faces), validate=validate)

    def submesh(self, face_mask) -> tuple[TriMesh, np.ndarray]:
        """The mesh made of a subset of the triangles, with only the vertices they use.

        Args:
            face_mask: ``(F,)`` bool mask or integer triangle ids.

        Returns:
            ``(mesh, old_vertex_ids)``: the new mesh (triangle order kept) and ``(V',)`` int64
            ids of its vertices in this mesh (new vertex ``i`` is old vertex
            ``old_vertex_ids[i]``, in increasing order).
        """
        m = np.asarray(face_mask)
        if m.dtype == bool:
            if m.shape != (self.n_triangles,):
                raise MeshError(
                    f"face_mask must have shape ({self.n_triangles},), got {m.shape}.",
                    problem="shape",
                )
            ids = np.flatnonzero(m)
        else:
            ids = np.atleast_1d(m).astype(np.int64)
            bad = ids[(ids < 0) | (ids >= self.n_triangles)]
            if bad.size:
                raise MeshError(
                    f"submesh triangle id(s) {_list(bad)} are outside [0, {self.n_triangles}).",
                    problem="index_out_of_range",
                    elements=bad,
                )
        if ids.size == 0:
            raise MeshError("submesh selects no triangles.", problem="empty")
        t = self._triangles[ids]
        old = np.unique(t)
        new_t = np.searchsorted(old, t)
        return (
            TriMesh(
                self._vertices[old], new_t, validate=False, degenerate_tol=self._degenerate_tol
            ),
            _readonly(old.astype(np.int64)),
        )
