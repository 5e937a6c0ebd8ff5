"""Exact closest point on triangles as barycentric coordinates (NumPy, vectorised, mm)."""

from __future__ import annotations

import numpy as np

__all__ = ["closest_point_barycentric"]


def closest_point_barycentric(points, a, b, c) -> np.ndarray:
    """Exact closest point on triangles, as barycentric coordinates (NumPy, vectorised).

    Region-based point-triangle projection (vertex, edge and face regions; Ericson,
    "Real-Time Collision Detection", 5.1.5). Degenerate triangles fall back to the closest of
    their edges' end points; no NaN is produced.

    Args:
        points: ``(K, 3)`` query points, mm.
        a, b, c: ``(K, 3)`` triangle corners, mm.

    Returns:
        ``(K, 3)`` float64 barycentric coordinates ``(u, v, w)`` (non-negative, sum 1) of the
        closest point ``u a + v b + w c``.
    """
    p = np.asarray(points, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    k = p.shape[0]
    out = np.full((k, 3), np.nan)
    done = np.zeros(k, dtype=bool)

    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)

    def put(mask, u, v, w):
        m = mask & ~done
        out[m, 0] = np.broadcast_to(u, (k,))[m]
        out[m, 1] = np.broadcast_to(v, (k,))[m]
        out[m, 2] = np.broadcast_to(w, (k,))[m]
        done[m] = True

    zero = np.zeros(k)
    one = np.ones(k)
    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), one, zero, zero)  # vertex a
        put((d3 >= 0) & (d4 <= d3), zero, one, zero)  # vertex b
        vc = d1 * d4 - d3 * d2
        t = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0) & np.isfinite(t), 1 - t, t, zero)  # edge ab
        put((d6 >= 0) & (d5 <= d6), zero, zero, one)  # vertex c
        vb = d5 * d2 - d1 * d6
        t = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0) & np.isfinite(t), 1 - t, zero, t)  # edge ac
        va = d3 * d6 - d5 * d4
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0) & np.isfinite(t), zero, 1 - t, t)  # bc
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        put(np.isfinite(v) & np.isfinite(w) & (denom != 0), 1 - v - w, v, w)  # inside
    if not done.all():  # degenerate leftovers: nearest corner
        rest = ~done
        dist = np.stack([np.linalg.norm(p[rest] - q[rest], axis=1) for q in (a, b, c)], axis=1)
        out[rest] = np.eye(3)[np.argmin(dist, axis=1)]
    out = np.clip(out, 0.0, 1.0)
    return out / out.sum(axis=1, keepdims=True)
