"""Local refinement of the eye and mouth landmarks from the scan's own relief (mm).

The palpebral fissures and the mouth slit are the face's valleys (closed) or holes (open, or
not seen by a range scanner): a band of concave scan points, or of hole-rim points, running
left-right. Their ends are the eye and mouth corners.

Method (:func:`refine_slits`), per slit, in the face frame of the coarse pose (``left``,
``up`` unit vectors):

1. **Search box** around the transferred slit: centred on the transferred corners' midpoint,
   half-width the transferred half-width plus a margin, half-height a few mm.
2. **Valley points.** Concavity of a scan vertex ``p`` with unit normal ``n``:
   ``c = (mean of the scan vertices within 3 mm - p) . n`` (mm; positive in a valley).
   Points with ``c > VALLEY_MM`` and the vertices on a hole rim are slit candidates.
3. **The slit** is the connected group of candidates (links shorter than 2.5 mm) that passes
   nearest to the slit's centre and spans at least a third of the transferred width.
4. **Corners** are its extreme points along ``left``; the inner lip midpoints (mouth) are its
   top and bottom points within 3 mm of the midline. A refined point further than the slit's
   ``max_shift`` from the transferred one is not trusted (the transfer is kept), nor a slit
   whose width differs from the transferred one by more than 25 % (eyes) or 35 % (mouth):
   the valley merged with a hole or a crease, or was cut short.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import KDTree

from ..fit.metrics import SurfaceIndex

__all__ = ["refine_slits", "scan_rim_vertices"]

VALLEY_MM = 0.3
LINK_MM = 2.5


@dataclass(frozen=True)
class _Slit:
    corners: tuple[str, str]  # (label at +left, label at -left)
    margin_mm: float
    half_height_mm: float
    max_shift_mm: float
    width_tol: float  # accepted relative change of the slit's width
    midline: tuple[str, str] | None = None  # (upper, lower) midpoint labels


_SLITS = (
    _Slit(("Outer left eye corner", "Inner left eye corner"), 6.0, 6.0, 8.0, 0.25),
    _Slit(("Inner right eye corner", "Outer right eye corner"), 6.0, 6.0, 8.0, 0.25),
    _Slit(
        ("Left mouth corner", "Right mouth corner"),
        15.0,
        18.0,
        22.0,
        0.35,
        ("Upper lip inner middle", "Lower lip inner middle"),
    ),
)


def scan_rim_vertices(index: SurfaceIndex) -> np.ndarray:
    """``(V,)`` bool: vertices on a boundary edge of the scan (hole rims, border)."""
    f = index.triangles[index.active_ids]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = e[:, 0] * np.int64(len(index.vertices)) + e[:, 1]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    rim = np.zeros(len(index.vertices), bool)
    rim[e[cnt[inv] == 1].ravel()] = True
    return rim


def refine_slits(
    index: SurfaceIndex,
    guesses: dict[str, np.ndarray],
    left: np.ndarray,
    up: np.ndarray,
    rim: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Refined positions (mm, scan frame) of the eye corners, mouth corners and inner lip
    midpoints; labels it cannot refine are left out of the result.

    Arguments:
        index: the scan surface.
        guesses: label -> ``(3,)`` transferred position, mm.
        left, up: ``(3,)`` unit vectors of the face frame (coarse pose).
        rim: optional precomputed :func:`scan_rim_vertices`.
    """
    v = index.vertices
    nrm = index.vertex_normals
    used = np.zeros(len(v), bool)
    used[np.unique(index.triangles[index.active_ids])] = True
    rim = scan_rim_vertices(index) if rim is None else rim
    tree = KDTree(v[used])
    used_ids = np.flatnonzero(used)
    out: dict[str, np.ndarray] = {}
    for s in _SLITS:
        if any(c not in guesses for c in s.corners):
            continue
        a, b = np.asarray(guesses[s.corners[0]]), np.asarray(guesses[s.corners[1]])
        centre = 0.5 * (a + b)
        half_w = 0.5 * abs(float((a - b) @ left)) + s.margin_mm
        ids = used_ids[tree.query_ball_point(centre, np.hypot(half_w, s.half_height_mm) + 3.0)]
        if ids.size < 10:
            continue
        d = v[ids] - centre
        u, w = d @ left, d @ up
        box = ids[(np.abs(u) <= half_w) & (np.abs(w) <= s.half_height_mm)]
        if box.size < 10:
            continue
        # concavity of the box points against their 3 mm neighbourhood
        nb = tree.query_ball_point(v[box], 3.0)
        mean_nb = np.stack([v[used_ids[np.asarray(n)]].mean(axis=0) for n in nb])
        conc = np.einsum("ij,ij->i", mean_nb - v[box], nrm[box])
        cand = box[(conc > VALLEY_MM) | rim[box]]
        if cand.size < 3:
            continue
        pairs = KDTree(v[cand]).query_pairs(LINK_MM, output_type="ndarray")
        g = sp.coo_matrix(
            (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(cand.size, cand.size)
        )
        _, lab = connected_components(g, directed=False)
        dc = v[cand] - centre
        cu, cw = dc @ left, dc @ up
        width = abs(float((a - b) @ left))
        best, best_d = None, np.inf
        for k in np.unique(lab):
            m = lab == k
            if cu[m].max() - cu[m].min() < width / 3.0:
                continue
            dist = float(np.min(np.hypot(cu[m], cw[m])))
            if dist < best_d:
                best, best_d = m, dist
        if best is None or best_d > 6.0:
            continue
        pts, pu, pw = v[cand[best]], cu[best], cw[best]
        ratio = (pu.max() - pu.min()) / max(width, 1e-9)
        if not (1.0 - s.width_tol <= ratio <= 1.0 + s.width_tol):
            continue  # merged with a hole or a crease, or cut short: keep the transfer
        for label, p in ((s.corners[0], pts[np.argmax(pu)]), (s.corners[1], pts[np.argmin(pu)])):
            if np.linalg.norm(p - guesses[label]) <= s.max_shift_mm:
                out[label] = p.copy()
        if s.midline is not None:
            mid = np.abs(pu) <= 3.0
            if mid.any():
                mp, mw = pts[mid], pw[mid]
                for label, p in (
                    (s.midline[0], mp[np.argmax(mw)]),
                    (s.midline[1], mp[np.argmin(mw)]),
                ):
                    if label in guesses and np.linalg.norm(p - guesses[label]) <= s.max_shift_mm:
                        out[label] = p.copy()
    return out
