"""Mesh hygiene for user meshes before a rig is built on them (NumPy, build time).

:func:`clean_mesh` makes a face mesh from a file usable by :func:`jaxface.anatomy.build_rig`:

1. non-finite coordinates are refused (:class:`MeshError`, the count and the first vertex id);
2. duplicate vertices are welded: vertices closer than ``weld_mm`` (coordinates quantised
   to that grid, default 1e-6 mm, far below the 1e-5 mm rounding of float32 PLY files of a
   head, and far above nothing: exact duplicates of an unwelded "triangle soup" always
   merge) become one; without this every triangle of a soup is its own component and the
   rig's geodesics and boundary searches run on 3F disconnected pieces (a hang);
3. degenerate triangles (a repeated vertex id after welding, or an area at most
   :data:`jaxface.mesh.DEGENERATE_TOL` times the squared bounding-box diagonal) and
   repeated triangles (the same three vertex ids) are dropped;
4. vertices no triangle uses are dropped;
5. a mesh with more than ``max_vertices`` vertices after all that is refused with the
   limit in the message (:data:`MAX_RIG_VERTICES`).

Units: millimetres. The result keeps the input's triangle orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MeshError
from .mesh import DEGENERATE_TOL, TriMesh, check_finite_vertices

__all__ = ["MAX_RIG_VERTICES", "WELD_MM", "HygieneReport", "clean_mesh", "weld_vertices"]

#: Largest skin (vertices) a rig is built on. Building the rig of the default head (12,140
#: vertices) raised the peak resident memory by 350 MB, about 30 kB per skin vertex
#: (``resource.getrusage`` around ``build_rig``), so 150,000 vertices need about 4.5 GB
#: before the synthesis is compiled, what a laptop can spare; the 2.3-million-vertex face
#: of issue 49 would need about 70 GB. A face scan has far more vertices than the rig needs:
#: decimate it (e.g. ``trimesh``'s ``simplify_quadric_decimation``) below the limit.
MAX_RIG_VERTICES = 150_000

#: Weld distance of :func:`weld_vertices`, mm.
WELD_MM = 1e-6


@dataclass(frozen=True)
class HygieneReport:
    """What :func:`clean_mesh` changed (counts)."""

    welded_vertices: int = 0
    degenerate_triangles: int = 0
    duplicate_triangles: int = 0
    unused_vertices: int = 0

    @property
    def changed(self) -> bool:
        return any(
            (
                self.welded_vertices,
                self.degenerate_triangles,
                self.duplicate_triangles,
                self.unused_vertices,
            )
        )

    def describe(self) -> str:
        """A one-line summary for a warning ("welded 3 duplicate vertices, ...")."""
        parts = []
        if self.welded_vertices:
            parts.append(f"welded {self.welded_vertices} duplicate vertices")
        if self.degenerate_triangles:
            parts.append(f"dropped {self.degenerate_triangles} degenerate (zero-area) triangles")
        if self.duplicate_triangles:
            parts.append(f"dropped {self.duplicate_triangles} repeated triangles")
        if self.unused_vertices:
            parts.append(f"dropped {self.unused_vertices} vertices no triangle uses")
        return "; ".join(parts) if parts else "no change"


def weld_vertices(vertices, triangles, weld_mm: float = WELD_MM):
    """Merge vertices whose coordinates agree on a ``weld_mm`` grid.

    Args:
        vertices: ``(V, 3)`` finite, mm. triangles: ``(F, 3)`` int ids.
        weld_mm: grid step, mm (> 0).

    Returns:
        ``(vertices (U, 3), triangles (F, 3), n_merged)``: the first vertex of each group is
        kept (vertex order otherwise preserved).
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if len(v) == 0:
        return v, t, 0
    key = np.round(v / float(weld_mm)).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.argsort(first)  # keep the groups in the order of their first vertex
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    new_ids = rank[inv]
    return v[np.sort(first)], new_ids[t], int(len(v) - len(first))


def clean_mesh(
    mesh,
    *,
    source: str = "mesh",
    max_vertices: int | None = MAX_RIG_VERTICES,
    weld_mm: float = WELD_MM,
) -> tuple[TriMesh, HygieneReport]:
    """Weld, drop degenerate/repeated triangles and unused vertices, refuse NaN and huge
    meshes (see the module doc).

    Args:
        mesh: a :class:`TriMesh` (mm), unvalidated is fine.
        source: name of the mesh in messages (e.g. the file path).
        max_vertices: refuse a cleaned mesh with more vertices (None: no limit).
        weld_mm: weld distance, mm.

    Returns:
        ``(cleaned TriMesh (unvalidated), HygieneReport)``.

    Raises:
        MeshError: ``nonfinite_vertices`` (count and first id), ``too_large`` (with the
            limit), ``empty`` (no triangle left).
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    check_finite_vertices(v, source=f"{source}:")
    if max_vertices is not None and len(v) > 4 * max_vertices:
        # far beyond the limit even if it were a triangle soup: refuse before any work
        _too_large(source, len(v), max_vertices)
    v, t, n_weld = weld_vertices(v, t, weld_mm)
    rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 2] == t[:, 0])
    if len(t):
        used = np.unique(t)
        diag = float(np.linalg.norm(v[used].max(axis=0) - v[used].min(axis=0)))
        area = 0.5 * np.linalg.norm(
            np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1
        )
        rep |= area <= DEGENERATE_TOL * diag * diag
    n_deg = int(rep.sum())
    t = t[~rep]
    _, first = np.unique(np.sort(t, axis=1), axis=0, return_index=True)
    n_dup = int(len(t) - len(first))
    t = t[np.sort(first)]
    if len(t) == 0:
        raise MeshError(
            f"{source}: no usable triangle left after dropping {n_deg} degenerate ones.",
            problem="empty",
        )
    used = np.zeros(len(v), bool)
    used[t.ravel()] = True
    n_unused = int((~used).sum())
    if n_unused:
        remap = np.cumsum(used) - 1
        v, t = v[used], remap[t]
    if max_vertices is not None and len(v) > max_vertices:
        _too_large(source, len(v), max_vertices)
    report = HygieneReport(n_weld, n_deg, n_dup, n_unused)
    return TriMesh(v, t, validate=False), report


def _too_large(source: str, n: int, limit: int):
    raise MeshError(
        f"{source}: {n} vertices, more than the limit of {limit} a rig can be built on "
        f"(about 30 kB of memory per vertex). Decimate the mesh below {limit} vertices "
        "(e.g. trimesh's simplify_quadric_decimation, or MeshLab); the default head has 12,140.",
        problem="too_large",
    )
