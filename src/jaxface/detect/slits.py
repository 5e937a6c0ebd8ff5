"""Local refinement of the eye and mouth landmarks from the scan's own relief (mm).

The palpebral fissures and the mouth slit are the face's valleys (closed) or holes (open, or
not seen by a range scanner): a band of concave scan points, or of hole-rim points, running
left-right. Their ends are the eye and mouth corners.

Method (:func:`refine_slits`), per slit, in the face frame of the coarse pose (``left``,
``up`` unit vectors):

1. **Search box** around the transferred slit: centred on the transferred corners' midpoint,
   half-width the transferred half-width plus a margin, half-height a few mm.
2. **Valley points.** Concavity of a scan vertex: ``c = (m_3 - m_s) . n_s`` (mm; positive in
   a valley), with ``m_3`` the mean of the scan vertices within 3 mm, and ``m_s`` and
   ``n_s`` the mean position and mean unit normal within :data:`SMOOTH_MM` (1.5 mm). The
   smoothing keeps a scanner's depth noise (0.1-0.4 mm) from making single vertices look
   concave; without it, 0.3 mm of noise ran the mouth's slit out to 13-16 mm past the
   corners. Points with ``c > VALLEY_MM`` and the vertices on a hole rim are slit
   candidates.
3. **The slit** is the connected group of candidates (links shorter than 2.5 mm) that passes
   nearest to the slit's centre (within 6 mm for an eye, 10 mm for the mouth, whose centre a
   smile lifts; the inner lip midpoints are taken only from a slit within 6 mm) and spans at
   least a third of the transferred width. The mouth's slit is then
   grown outward across breaks of up to 6 mm (:func:`_grow_slit`): a smile stretches the lips
   thin, and a range scan sees their valley in pieces.
4. **Corners** are its extreme points along ``left``; the inner lip midpoints (mouth) are its
   top and bottom points within 3 mm of the midline (when the slit there is a hole's rim less
   than 3 mm high, it is one lip of an open mouth: only the lip whose transferred midpoint is
   nearer is placed). A refined point further than the slit's
   ``max_shift`` from the transferred one is not trusted (the transfer is kept), nor a slit
   whose width differs from the transferred one by more than 25 % (eyes) or 50 % (mouth; a
   full smile or stretch widens it by 35-45 %): the valley merged with a hole or a crease,
   or was cut short.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import KDTree

from ..fit.metrics import SurfaceIndex

__all__ = ["refine_slits", "scan_rim_vertices"]

VALLEY_MM = 0.3  # concavity of a slit candidate, mm
SMOOTH_MM = 1.5  # radius of the smoothing under the concavity, mm (0: the raw vertices)
LINK_MM = 2.5
GAP_MM = 6.0
MIDLINE_CENTRE_MM = 6.0
ONE_ARC_MM = 3.0


@dataclass(frozen=True)
class _Slit:
    corners: tuple[str, str]  # (label at +left, label at -left)
    margin_mm: float
    half_height_mm: float
    max_shift_mm: float
    width_tol: float  # accepted relative change of the slit's width
    midline: tuple[str, str] | None = None  # (upper, lower) midpoint labels
    gap_mm: float = 0.0  # a break the slit is grown across (:func:`_grow_slit`); 0: none
    centre_tol_mm: float = 6.0  # the slit passes this close to the transferred centre


_SLITS = (
    _Slit(("Outer left eye corner", "Inner left eye corner"), 6.0, 6.0, 8.0, 0.25),
    _Slit(("Inner right eye corner", "Outer right eye corner"), 6.0, 6.0, 8.0, 0.25),
    _Slit(
        ("Left mouth corner", "Right mouth corner"),
        15.0,
        18.0,
        22.0,
        0.5,
        ("Upper lip inner middle", "Lower lip inner middle"),
        GAP_MM,
        10.0,
    ),
)


def _grow_slit(
    pts: np.ndarray,
    lab: np.ndarray,
    seed: np.ndarray,
    cu: np.ndarray,
    cw: np.ndarray,
    gap_mm: float = 6.0,
) -> np.ndarray:
    """Extend the slit ``seed`` (bool over the candidates) with the candidate groups that
    continue it outward past a gap: a group joins when one of its points lies within
    ``gap_mm`` of the slit's current end on that side, it reaches farther out along
    ``left`` (``cu``), and it rises or falls no more than its run (``|dw| <= |du| + 2 mm``
    from that end; a slit, not a crease). A range scan breaks a thin slit (a smile's
    stretched lips) into pieces where the valley is shallower than :data:`VALLEY_MM` for a
    few samples. Only the mouth is grown: an eye's valley runs on into the lacrimal hollow and
    the lid crease."""
    sel = seed.copy()
    while True:
        grown = False
        for side in (1.0, -1.0):
            ends = np.flatnonzero(sel)
            e = ends[np.argmax(side * cu[ends])]
            for k in np.unique(lab[~sel]):
                m = lab == k
                if (side * cu[m]).max() <= side * cu[e]:
                    continue  # does not reach past the end on this side
                if np.linalg.norm(pts[m] - pts[e], axis=1).min() > gap_mm:
                    continue
                far = np.flatnonzero(m)[np.argmax(side * cu[m])]
                if abs(cw[far] - cw[e]) > abs(cu[far] - cu[e]) + 2.0:
                    continue
                sel |= m
                grown = True
                break
        if not grown:
            return sel


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
    findings: dict[str, str] | None = None,
) -> dict[str, np.ndarray]:
    """Refined positions (mm, scan frame) of the eye corners, mouth corners and inner lip
    midpoints; labels it cannot refine are left out of the result.

    Arguments:
        index: the scan surface.
        guesses: label -> ``(3,)`` transferred position, mm.
        left, up: ``(3,)`` unit vectors of the face frame (coarse pose).
        rim: optional precomputed :func:`scan_rim_vertices`.
        findings: optional dict that receives ``"open_mouth"`` (a sentence) when the mouth
            is a hole of which only the upper lip's rim was found near the transferred mouth:
            the jaw is open wider than the registered template followed.
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
        if SMOOTH_MM > 0:
            sm = tree.query_ball_point(v[box], SMOOTH_MM)
            p_s = np.stack([v[used_ids[np.asarray(n)]].mean(axis=0) for n in sm])
            n_s = np.stack([nrm[used_ids[np.asarray(n)]].sum(axis=0) for n in sm])
            n_s /= np.maximum(np.linalg.norm(n_s, axis=1, keepdims=True), 1e-12)
            conc = np.einsum("ij,ij->i", mean_nb - p_s, n_s)
        else:
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
        if best is None or best_d > s.centre_tol_mm:
            continue
        seed = best
        if s.gap_mm > 0:
            best = _grow_slit(v[cand], lab, best, cu, cw, s.gap_mm)
        pts, pu = v[cand[best]], cu[best]
        ratio = (pu.max() - pu.min()) / max(width, 1e-9)
        if not (1.0 - s.width_tol <= ratio <= 1.0 + s.width_tol):
            continue  # merged with a hole or a crease, or cut short: keep the transfer
        for label, p in ((s.corners[0], pts[np.argmax(pu)]), (s.corners[1], pts[np.argmin(pu)])):
            if np.linalg.norm(p - guesses[label]) <= s.max_shift_mm:
                out[label] = p.copy()
        if s.midline is not None and best_d <= MIDLINE_CENTRE_MM:
            # the midpoints come from the slit found, not from the pieces grown onto its ends,
            # and only when it passes close to the transferred centre (a slit found farther
            # away may be one arc of an open mouth's rim)
            mid = np.abs(cu[seed]) <= 3.0
            if mid.any():
                mp, mw = v[cand[seed]][mid], cw[seed][mid]
                picks = [(s.midline[0], mp[np.argmax(mw)]), (s.midline[1], mp[np.argmin(mw)])]
                on_rim = rim[cand[seed]][mid]
                if on_rim.any() and float(mw.max() - mw.min()) < ONE_ARC_MM:
                    # one thin arc of a hole's rim: the open mouth's other lip was not found,
                    # so the arc is the lip whose transferred midpoint is nearer
                    arc = mp[np.argmin(np.abs(mw - np.median(mw)))]
                    near = [lb for lb in s.midline if lb in guesses]
                    if near:
                        keep = min(near, key=lambda lb: float(np.linalg.norm(arc - guesses[lb])))
                        picks = [(lb, p) for lb, p in picks if lb == keep]
                        if findings is not None and keep == s.midline[0]:
                            findings["open_mouth"] = (
                                "the mouth is open wider than the registered template "
                                "followed (only the upper lip's rim was found)"
                            )
                for label, p in picks:
                    if label in guesses and np.linalg.norm(p - guesses[label]) <= s.max_shift_mm:
                        out[label] = p.copy()
    return out
