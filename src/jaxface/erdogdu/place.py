"""Placing the Erdoğdu control points on a face (:func:`place_control_points`), with the
helpers shared by the animation: projection onto the frontmost vertex, snapping to a face,
and the landmark thin-plate spline (mm)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..errors import LandmarkError, RBFError, RigError
from ..landmarks import FACE_LABELS, Landmarks
from ..rbf import fit_numpy
from .face import Face, FaceFrame, as_face, face_frame
from .layouts import AU_LAYOUTS, ControlPoint, parse_au

__all__ = ["place_control_points"]


def _project_frontmost(
    face: Face, frame: FaceFrame, points: np.ndarray, radius: float
) -> np.ndarray:
    """Index of the frontmost (largest frame z) vertex within ``radius`` mm of the line
    through each point along frame z; grows the radius up to 8x if nothing is found."""
    loc = frame.local(face.vertices)
    tree2 = cKDTree(loc[:, :2])
    out = np.empty(len(points), dtype=np.int64)
    for k, p in enumerate(frame.local(points)):
        r = radius
        for _ in range(4):
            idx = tree2.query_ball_point(p[:2], r)
            if idx:
                idx = np.asarray(idx)
                out[k] = idx[np.argmax(loc[idx, 2])]
                break
            r *= 2
        else:
            out[k] = int(face.tree().query(points[k])[1])
    return out


def _snap(face: Face, points: np.ndarray, mode: str) -> np.ndarray:
    """Snap (K, 3) mm points onto ``face``: nearest vertex (thesis) or closest surface point."""
    if mode == "vertex" or face.triangles is None:
        return face.vertices[face.tree().query(points)[1]]
    if mode != "surface":
        raise RigError(f"unknown snap mode {mode!r}; use 'vertex' or 'surface'")
    mesh = face.mesh()
    assert mesh is not None  # the face has triangles here
    sp, _ = mesh.closest_points(points)
    tri = np.asarray(sp.tri, dtype=np.int64)
    bary = np.asarray(sp.bary, dtype=np.float64)
    return np.einsum("kj,kjd->kd", bary, face.vertices[face.triangles[tri]])


def _landmark_tps(
    src: Landmarks, dst: Landmarks, reg: float, what: str, still: np.ndarray | None = None
):
    """TPS on the landmarks common to both (matched by label), plus optional ``still`` (n, 3)
    mm points mapped to themselves."""
    common = [n for n in src.names if n in dst]
    if len(common) < 5:
        raise LandmarkError(
            f"{what}: only {len(common)} landmarks in common ({common}); the TPS "
            f"needs at least 5 non-coplanar ones (ideally the 22 Bosphorus landmarks).",
            missing=[n for n in FACE_LABELS if n not in common],
        )
    try:
        a, b = src.array(common), dst.array(common)
        if still is not None and len(still):
            a, b = np.concatenate([a, still]), np.concatenate([b, still])
        return fit_numpy(a, b, kernel="tps", reg=reg), tuple(common)
    except RBFError as e:
        raise LandmarkError(f"{what}: landmark TPS failed: {e}", missing=()) from e


def place_control_points(
    face, au, *, landmarks: Landmarks | None = None, radius: float = 0.02
) -> tuple[tuple[ControlPoint, ...], np.ndarray]:
    """Place an AU's control points on a neutral face (the thesis places them once, on the
    source neutral).

    Args:
        face: anything :func:`as_face` accepts.
        au: AU number or code (``12``, ``"12L"``); the side is ignored here.
        radius: projection tolerance in units of ``D`` (see :func:`_project_frontmost`).

    Returns:
        ``(control points (K,), vertex indices (K,) into the face's vertices)``.

    Raises:
        LandmarkError: a landmark used by the layout or the frame is missing (all listed).
    """
    face = as_face(face, landmarks)
    num, _ = parse_au(au)
    layout = AU_LAYOUTS[num]
    miss = face.landmarks.missing(layout.landmarks_used)
    if miss:
        raise LandmarkError(
            f"{face.name}: AU{num} control points need landmark(s) {list(miss)}, "
            f"which are missing.",
            missing=miss,
        )
    frame = face_frame(face.landmarks)
    pts = layout.expanded()
    raw = np.empty((len(pts), 3))
    for k, cp in enumerate(pts):
        base = sum(w * np.asarray(face.landmarks[l]) for l, w in cp.base)
        sgn = -1.0 if cp.side == "R" else 1.0
        raw[k] = base + frame.size * (
            sgn * cp.offset[0] * frame.axes[0] + cp.offset[1] * frame.axes[1]
        )
    idx = _project_frontmost(face, frame, raw, radius * frame.size)
    # distinct vertices: duplicates would make the TPS singular
    _, first = np.unique(idx, return_index=True)
    keep = np.sort(first)
    return tuple(pts[i] for i in keep), idx[keep]
