"""The data of a :class:`~jaxface.mesh.TriMesh` and its cached geometry: vertices (mm),
triangles, face areas (mm^2), face and vertex normals, bounds, signed volume (mm^3)."""

from __future__ import annotations

from functools import cached_property

import numpy as np

from ..normals import vertex_normals
from .arrays import _readonly

__all__ = ["MeshBase"]


class MeshBase:
    """Vertices and triangles of a :class:`~jaxface.mesh.TriMesh`, with the geometry computed
    from them (cached); the constructor and validation are on :class:`~jaxface.mesh.TriMesh`."""

    _vertices: np.ndarray
    _triangles: np.ndarray
    _degenerate_tol: float

    # ---------------------------------------------------------------- basic accessors
    @property
    def vertices(self) -> np.ndarray:
        """``(V, 3)`` float64 vertex positions, mm (read-only)."""
        return self._vertices

    @property
    def triangles(self) -> np.ndarray:
        """``(F, 3)`` int64 vertex ids per triangle, counter-clockwise from outside (read-only)."""
        return self._triangles

    @property
    def n_vertices(self) -> int:
        return int(self._vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self._triangles.shape[0])

    def __repr__(self) -> str:
        return f"TriMesh(V={self.n_vertices}, F={self.n_triangles})"

    # ---------------------------------------------------------------- geometry (cached)
    def _cross(self) -> np.ndarray:
        v, t = self._vertices, self._triangles
        ok = np.all((t >= 0) & (t < v.shape[0]), axis=1)
        tt = np.where(ok[:, None], t, 0)
        c = np.cross(v[tt[:, 1]] - v[tt[:, 0]], v[tt[:, 2]] - v[tt[:, 0]])
        c[~ok] = 0.0
        return c

    def _areas_raw(self) -> np.ndarray:
        with np.errstate(invalid="ignore", over="ignore"):
            return 0.5 * np.linalg.norm(self._cross(), axis=1)

    @cached_property
    def face_areas(self) -> np.ndarray:
        """``(F,)`` triangle areas, mm^2."""
        return _readonly(self._areas_raw())

    @cached_property
    def face_normals(self) -> np.ndarray:
        """``(F, 3)`` unit triangle normals (right-hand rule); zero rows for zero-area ones."""
        c = self._cross()
        n = np.linalg.norm(c, axis=1, keepdims=True)
        out = np.divide(c, n, out=np.zeros_like(c), where=n > 0)
        return _readonly(out)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """``(V, 3)`` area-weighted unit vertex normals; zero rows for unreferenced vertices.
        Same definition as :func:`jaxface.surface.vertex_normals` (:func:`jaxface.normals.vertex_normals`)."""
        return _readonly(vertex_normals(self._vertices, self._triangles))

    @property
    def bounds(self) -> np.ndarray:
        """``(2, 3)`` min and max corner of the bounding box, mm."""
        return np.stack([self._vertices.min(axis=0), self._vertices.max(axis=0)])

    @property
    def area(self) -> float:
        """Total surface area, mm^2."""
        return float(self.face_areas.sum())

    def signed_volume(self) -> float:
        """Signed enclosed volume, mm^3 (divergence theorem); positive for a closed mesh whose
        triangles are counter-clockwise seen from outside. Meaningless for open meshes."""
        v, t = self._vertices, self._triangles
        return float(
            np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6.0
        )
