"""Area-weighted vertex normals of a triangle mesh, NumPy (build time, off the jit path).

The JAX twin for the jit path (same definition, differentiable) is
:func:`jaxface.surface.vertex_normals`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["vertex_normals"]


def vertex_normals(vertices, triangles) -> np.ndarray:
    """Area-weighted unit vertex normals: the normalised sum of the (twice-area-weighted)
    normals ``(b - a) x (c - a)`` of the triangles around each vertex.

    The sums run over the triangles' first corners, then their second, then their third, each
    in triangle order (bit for bit the order of ``np.add.at`` over the three corners).

    Args:
        vertices: ``(V, 3)`` positions, mm (converted to float64).
        triangles: ``(F, 3)`` int vertex ids, counter-clockwise seen from outside.

    Returns:
        ``(V, 3)`` float64 unit normals; zero rows where the sum is zero (unreferenced
        vertices, or degenerate/cancelling triangles).
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    c = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    corners = t.T.reshape(-1)  # corner 0 of every triangle, then corner 1, then corner 2
    acc = np.stack(
        [np.bincount(corners, weights=np.tile(c[:, d], 3), minlength=len(v)) for d in range(3)],
        axis=1,
    )
    n = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, n, out=np.zeros_like(acc), where=n > 0)
