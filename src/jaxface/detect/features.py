"""Relief features that fix a landmark where the registration slides: the nose's and the
brows' protrusion extrema and the alae's outer edges (mm, scan frame).

The registration that carries the landmarks matches surfaces, not positions along them: on
the rounded nose tip and on the brow ridge it slides by several mm, and more where the skin
itself slid (a brow raise moves the brows 5-15 mm up the forehead). The relief does not
slide: the nose tip is the face's most protruding point, and the brow's soft tissue is a
ridge that moves with the brow. Each feature label is found as such an extremum near its
transferred position, then moved by its calibrated offset from the extremum to the label
(:attr:`jaxface.detect.definitions.LandmarkDefinitions.offsets_mm`).

* **Nose tip** (:func:`nose_tip_extremum`): the scan vertex of largest ``p . forward`` within
  :data:`TIP_RADIUS_MM` of the transferred tip.
* **Brows** (:func:`brow_extremum`): on the vertical profile of the surface through the
  transferred brow point (within :data:`BROW_SLAB_MM` of it along ``left``, and
  :data:`BROW_HALF_RANGE_MM` along ``up``), the depth along ``forward`` is averaged in 1 mm
  bins, smoothed (Gaussian, :data:`BROW_SMOOTH_MM`), and its maximum is the ridge. No ridge is
  returned when the profile has gaps over more than 30 % of its bins or peaks at its ends
  (the transferred point is kept).
* **Nose peaks** (:func:`alar_edge`): on horizontal profiles through the transferred point
  (rows :data:`ALA_ROW_MM` apart within :data:`ALA_HALF_HEIGHT_MM` of it along ``up``; from
  :data:`ALA_MEDIAL_MM` medial to :data:`ALA_LATERAL_MM` lateral of it), the steepest drop of
  the depth going outward is the ala's outer edge, where the nose's wing stands 5-10 mm in
  front of the cheek; the most lateral edge over the rows is the alare. The Bosphorus-style
  label lies on the smooth cheek beside it, which no relief marks, so its calibrated offset
  from the alare places it. No edge is returned when no row has a drop of at least
  :data:`ALA_MIN_STEP_MM` over 4 mm (the transferred point is kept).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import KDTree

from ..closest import SurfaceIndex
from ..landmarks import FACE_LABELS

__all__ = [
    "BROW_LABELS",
    "FEATURE_LABELS",
    "NOSE_PEAK_LABELS",
    "alar_edge",
    "brow_extremum",
    "feature_extrema",
    "nose_tip_extremum",
]

TIP_RADIUS_MM = 8.0
BROW_HALF_RANGE_MM = 12.0
BROW_SLAB_MM = 2.0
BROW_SMOOTH_MM = 1.5
BROW_DEPTH_MM = 15.0
ALA_MEDIAL_MM = 20.0
ALA_LATERAL_MM = 8.0
ALA_MIN_STEP_MM = 2.0
ALA_ROW_MM = 1.0
ALA_HALF_HEIGHT_MM = 6.0

BROW_LABELS: tuple[str, ...] = tuple(n for n in FACE_LABELS if n.endswith("eyebrow"))
NOSE_PEAK_LABELS: tuple[str, ...] = ("Left nose peak", "Right nose peak")
#: labels placed at a relief extremum plus a calibrated offset
FEATURE_LABELS: tuple[str, ...] = (*BROW_LABELS, "Nose tip", *NOSE_PEAK_LABELS)


def nose_tip_extremum(
    vertices: np.ndarray, tree: KDTree, tip: np.ndarray, forward: np.ndarray
) -> np.ndarray | None:
    """The vertex of largest ``p . forward`` within :data:`TIP_RADIUS_MM` of ``tip`` (``(3,)``
    mm); ``None`` when no vertex is that close."""
    ids = np.asarray(tree.query_ball_point(tip, TIP_RADIUS_MM), dtype=np.int64)
    if ids.size == 0:
        return None
    return vertices[ids[np.argmax(vertices[ids] @ forward)]].copy()


def _profile(index, guess, along, across, forward, s, t):
    """Surface samples of the plane through ``guess`` spanned by ``along`` and ``forward``:
    the grid ``guess + s along + t forward`` (mm) moved to its closest surface points, those
    on the scan's border more than 1 mm away dropped. Returns their coordinates from
    ``guess`` along ``across``, ``along`` and ``forward`` (mm)."""
    q = guess + s[:, None, None] * along + t[None, :, None] * forward
    cp = index.query(q.reshape(-1, 3))
    keep = ~(cp.on_boundary & (cp.distances > 1.0))
    d = cp.points[keep] - guess
    return d @ across, d @ along, d @ forward


def brow_extremum(
    index: SurfaceIndex,
    guess: np.ndarray,
    left: np.ndarray,
    up: np.ndarray,
    forward: np.ndarray,
) -> np.ndarray | None:
    """The brow ridge on the vertical profile through ``guess`` (see the module doc), ``(3,)``
    mm (on the smoothed profile; snap it to the surface); ``None`` when the profile is too
    incomplete or has no interior maximum.

    The profile is sampled on the surface, whatever the mesh's resolution: points of the
    plane through ``guess`` spanned by ``up`` and ``forward`` (every 0.5 mm along ``up``, at
    five depths from -6 to +6 mm) are moved to their closest surface points, and those within
    :data:`BROW_SLAB_MM` of the plane, off the scan's border, are binned along ``up``.
    """
    half = BROW_HALF_RANGE_MM
    s = np.arange(-half - 2.0, half + 2.0 + 1e-9, 0.5)
    a, su, z = _profile(index, guess, up, left, forward, s, np.linspace(-6.0, 6.0, 5))
    m = (np.abs(a) < BROW_SLAB_MM) & (np.abs(su) <= half) & (np.abs(z) < BROW_DEPTH_MM)
    if m.sum() < 10:
        return None
    bins = np.arange(-half, half + 1e-9, 1.0)
    k = np.clip(np.round(su[m] + half).astype(np.int64), 0, len(bins) - 1)
    cnt = np.bincount(k, minlength=len(bins))
    depth = np.bincount(k, z[m], minlength=len(bins))
    ok = cnt > 0
    if ok.sum() < 0.7 * len(bins):
        return None
    prof = np.interp(bins, bins[ok], depth[ok] / np.maximum(cnt[ok], 1))
    r = int(np.ceil(3.0 * BROW_SMOOTH_MM))
    ker = np.exp(-0.5 * (np.arange(-r, r + 1) / BROW_SMOOTH_MM) ** 2)
    smooth = np.convolve(np.pad(prof, r, mode="edge"), ker / ker.sum(), mode="valid")
    i = int(np.argmax(smooth))
    if i in (0, len(bins) - 1):
        return None
    return guess + bins[i] * up + smooth[i] * forward


def _alar_step(index, guess, outward, up, forward):
    """The steepest outward drop of the depth on the horizontal profile through ``guess``:
    ``(s, depth, step)`` mm along ``outward`` and ``forward`` from ``guess``, and the drop
    over 4 mm; ``None`` when the profile is too incomplete."""
    lo, hi = -ALA_MEDIAL_MM, ALA_LATERAL_MM
    s = np.arange(lo - 2.0, hi + 2.0 + 1e-9, 0.5)
    a, so, z = _profile(index, guess, outward, up, forward, s, np.linspace(-8.0, 16.0, 7))
    m = (np.abs(a) < 0.5 * ALA_ROW_MM) & (so >= lo) & (so <= hi) & (np.abs(z) < 2 * BROW_DEPTH_MM)
    if m.sum() < 10:
        return None
    bins = np.arange(lo, hi + 1e-9, 1.0)
    k = np.clip(np.round(so[m] - lo).astype(np.int64), 0, len(bins) - 1)
    ok = np.bincount(k, minlength=len(bins)) > 0
    if ok.sum() < 0.7 * len(bins):
        return None
    # the most protruding surface in each bin: the wing, where it overhangs the cheek
    depth = np.full(len(bins), -np.inf)
    np.maximum.at(depth, k, z[m])
    prof = np.interp(bins, bins[ok], depth[ok])
    r = int(np.ceil(3.0 * BROW_SMOOTH_MM))
    ker = np.exp(-0.5 * (np.arange(-r, r + 1) / BROW_SMOOTH_MM) ** 2)
    smooth = np.convolve(np.pad(prof, r, mode="edge"), ker / ker.sum(), mode="valid")
    g = np.gradient(smooth)
    i = int(np.argmin(g[1:-1])) + 1
    step = smooth[max(i - 2, 0)] - smooth[min(i + 2, len(bins) - 1)]
    # the steepest point between the bins: the vertex of the parabola through three slopes
    curv = g[i - 1] - 2.0 * g[i] + g[i + 1]
    frac = float(np.clip(0.5 * (g[i - 1] - g[i + 1]) / curv, -0.5, 0.5)) if curv > 0 else 0.0
    return float(bins[i] + frac), float(np.interp(bins[i] + frac, bins, smooth)), float(step)


def alar_edge(
    index: SurfaceIndex,
    guess: np.ndarray,
    outward: np.ndarray,
    up: np.ndarray,
    forward: np.ndarray,
) -> np.ndarray | None:
    """The ala's most lateral edge point (alare) near ``guess`` (see the module doc), ``(3,)``
    mm on the smoothed profile; ``None`` when no row has a step.

    Arguments:
        outward: ``(3,)`` unit vector away from the mid-line on this side (``left`` for the
            left nose peak, ``-left`` for the right one).

    Each horizontal profile (rows every :data:`ALA_ROW_MM` within :data:`ALA_HALF_HEIGHT_MM`
    of ``guess`` along ``up``) is sampled as :func:`brow_extremum`'s, in the plane spanned by
    ``outward`` and ``forward``: points every 0.5 mm along ``outward``, at depths from -8 to
    +16 mm (the wing stands in front of the cheek), moved to their closest surface points. A
    row's edge is its steepest outward drop of depth, kept when the drop is at least
    :data:`ALA_MIN_STEP_MM` over 4 mm; the most lateral edge over the rows is returned.
    """
    best = None
    for dy in np.arange(-ALA_HALF_HEIGHT_MM, ALA_HALF_HEIGHT_MM + 1e-9, ALA_ROW_MM):
        row = guess + dy * up
        e = _alar_step(index, row, outward, up, forward)
        if e is None or e[2] < ALA_MIN_STEP_MM:
            continue
        if best is None or e[0] > best[0]:
            best = (e[0], e[1], row)
    if best is None:
        return None
    return best[2] + best[0] * outward + best[1] * forward


def feature_extrema(
    index: SurfaceIndex,
    guesses: dict[str, np.ndarray],
    left: np.ndarray,
    up: np.ndarray,
    forward: np.ndarray,
) -> dict[str, np.ndarray]:
    """Extrema of the :data:`FEATURE_LABELS` in ``guesses`` (label -> transferred ``(3,)`` mm);
    labels whose extremum is not found are left out.

    Arguments:
        index: the scan's surface (mm).
        left, up, forward: ``(3,)`` unit vectors of the face frame (scan frame).
    """
    used = np.unique(index.triangles[index.active_ids])
    v = index.vertices[used]
    tree = KDTree(v)
    out = {}
    for n, g in guesses.items():
        if n == "Nose tip":
            p = nose_tip_extremum(v, tree, np.asarray(g, float), forward)
        elif n in BROW_LABELS:
            p = brow_extremum(index, np.asarray(g, float), left, up, forward)
        elif n in NOSE_PEAK_LABELS:
            side = 1.0 if n.startswith("Left") else -1.0
            p = alar_edge(index, np.asarray(g, float), side * left, up, forward)
        else:
            continue
        if p is not None:
            out[n] = p
    return out
