"""Array checks shared by the mesh modules: ``(V, 3)`` vertices and ``(F, 3)`` triangles as
read-only NumPy arrays (mm), non-finite vertices, and short id lists for error messages."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError

__all__ = ["check_finite_vertices"]

_MAX_LISTED = 10


def _list(ids, limit: int = _MAX_LISTED) -> str:
    ids = list(ids)
    head = ", ".join(str(i) for i in ids[:limit])
    return head + (f", ... ({len(ids)} in all)" if len(ids) > limit else "")


def _edge_list(edges: np.ndarray, limit: int = _MAX_LISTED) -> str:
    rows = [f"({int(a)}, {int(b)})" for a, b in edges[:limit]]
    return ", ".join(rows) + (f", ... ({len(edges)} in all)" if len(edges) > limit else "")


def _as_vertices(vertices) -> np.ndarray:
    v = np.asarray(vertices)
    if (
        v.ndim != 2
        or v.shape[1] != 3
        or not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer))
    ):
        raise MeshError(
            f"vertices must be a (V, 3) array of numbers in mm; got shape {v.shape} dtype "
            f"{v.dtype}.",
            problem="shape",
        )
    v = np.array(v, dtype=np.float64, copy=True)
    v.setflags(write=False)
    return v


def check_finite_vertices(vertices, *, source: str = "mesh") -> None:
    """Raise :class:`MeshError` (``problem="nonfinite_vertices"``) if any vertex of the
    ``(V, 3)`` array holds NaN or inf, naming how many and the first vertex id.

    Args:
        vertices: ``(V, 3)`` coordinates (any unit).
        source: what to call the data in the message (e.g. the file name).
    """
    v = np.asarray(vertices, dtype=np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(v.reshape(len(v), -1)), axis=1)) if v.size else []
    if len(bad):
        raise MeshError(
            f"{source} {len(bad)} of {len(v)} vertices have NaN or inf coordinates (first: "
            f"vertex {int(bad[0])} = {v[bad[0]].tolist()}; ids {_list(bad)}). Remove or repair "
            "them (e.g. fill the holes of the scan) and try again.",
            problem="nonfinite_vertices",
            elements=bad,
        )


def _as_triangles(triangles) -> np.ndarray:
    t = np.asarray(triangles)
    if t.size == 0 and t.ndim == 1:  # [] -> no triangles
        t = t.reshape(0, 3).astype(np.int64)
    if t.ndim != 2 or t.shape[1] != 3:
        raise MeshError(
            f"triangles must be a (F, 3) integer array; got shape {t.shape}. Polygons with more "
            f"than 3 corners must be triangulated first (load_mesh does this for OBJ/PLY).",
            problem="shape",
        )
    if not np.issubdtype(t.dtype, np.integer):
        if (
            np.issubdtype(t.dtype, np.floating)
            and np.all(np.isfinite(t))
            and np.all(t == np.round(t))
        ):
            t = t.astype(np.int64)
        else:
            raise MeshError(
                f"triangles must hold integer vertex ids; got dtype {t.dtype} with non-integer "
                f"values.",
                problem="shape",
            )
    t = np.array(t, dtype=np.int64, copy=True)
    t.setflags(write=False)
    return t


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
