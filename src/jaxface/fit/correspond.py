"""Correspondences of scan points on the simulated skin, with rejection and robust weights
(NumPy, one outer iteration).

Each scan point ``q_k`` is matched to its exact closest point ``S_k`` on the face triangles of
the current simulated skin (triangle id and barycentrics, fixed during an inner solve). Matches
are rejected on the face border, beyond a distance and across opposed normals; the others get
Tukey's biweight at ``c = max(4.685 * 1.4826 * MAD, floor)`` of the point-to-plane residuals
``n_k . (S_k - q_k)`` (mm), normalised to sum to 1.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import FitError
from .metrics import SurfaceIndex

__all__ = ["ScanTargets", "Correspondences", "find_correspondences"]


@dataclass(frozen=True)
class ScanTargets:
    """One scan's data for the fit (neutral-scan frame, mm).

    Attributes:
        points: ``(K, 3)`` scan points (``FitOptions.n_points`` rows, padded).
        normals: ``(K, 3)`` unit scan normals, or None.
        valid: ``(K,)`` bools (False: padding).
        landmarks: ``(L, 3)`` landmark targets; landmark_valid: ``(L,)`` bools.
        landmark_scale: factor on ``FitOptions.landmark_weight`` for this scan (1 for
            landmarks read from files, ``FitOptions.detected_landmark_weight`` for detected
            ones).
    """

    points: np.ndarray
    normals: np.ndarray | None
    valid: np.ndarray
    landmarks: np.ndarray
    landmark_valid: np.ndarray
    landmark_scale: float = 1.0

    @classmethod
    def of(cls, scan: ScanTargets | Mapping[str, Any]) -> ScanTargets:
        """``scan`` as :class:`ScanTargets`; a mapping (as
        :func:`jaxface.fit.pipeline.scan_fit_inputs` returns) has the same keys
        (``normals`` optional).

        Raises:
            FitError: a required key is missing."""
        if isinstance(scan, ScanTargets):
            return scan
        missing = [k for k in ("points", "valid", "landmarks", "landmark_valid") if k not in scan]
        if missing:
            raise FitError(
                f"a scan given to fit_points lacks {missing}; it needs points, valid, landmarks "
                "and landmark_valid (and optionally normals), as scan_fit_inputs returns."
            )
        return cls(
            points=scan["points"],
            normals=scan.get("normals"),
            valid=scan["valid"],
            landmarks=scan["landmarks"],
            landmark_valid=scan["landmark_valid"],
            landmark_scale=float(scan.get("landmark_scale", 1.0)),
        )


@dataclass(frozen=True)
class Correspondences:
    """Scan points matched to the simulated skin (one outer iteration), padded to ``K``.

    Attributes:
        tri: ``(K,)`` skin triangle ids; bary: ``(K, 3)``; local: ``(K, 3)`` local point ids
            of the triangle corners (into the fit-vertex set).
        target: ``(K, 3)`` scan points (mm); normal: ``(K, 3)`` skin normals.
        weight: ``(K,)`` robust weights summing to 1 (0 = rejected or padding).
        distance: ``(K,)`` point-to-plane residual at the current skin (mm, signed).
        n_accepted: accepted matches; scale_mm: the Tukey cut-off used.
    """

    tri: np.ndarray
    bary: np.ndarray
    local: np.ndarray
    target: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    distance: np.ndarray
    n_accepted: int
    scale_mm: float


def find_correspondences(
    skin,
    triangles: np.ndarray,
    face_triangles: ArrayLike,
    local_ids: np.ndarray,
    points: np.ndarray,
    point_normals: np.ndarray | None,
    valid: np.ndarray,
    *,
    max_distance: float,
    robust_floor: float,
    max_normal_angle_deg: float = 60.0,
) -> Correspondences:
    """Closest points of scan ``points`` ``(K, 3)`` on the simulated ``skin`` ``(V, 3)``
    (face triangles only), with rejection and Tukey weights.

    A match is rejected when the point is padding (``valid`` False), its closest point lies
    on the border of the face region (the scan point is outside the face), it is farther
    than ``max_distance`` mm, or the scan normal differs from the skin normal by more than
    ``max_normal_angle_deg``. Weights: Tukey's biweight at
    ``max(4.685 * 1.4826 * MAD, robust_floor)`` of the point-to-plane residuals, normalised
    to sum to 1.

    Raises:
        FitError: no match accepted.
    """
    index = SurfaceIndex(skin, triangles, face_triangles)
    cp = index.query(points, max_distance=max_distance * 2.0)
    tri = cp.triangles
    bary = cp.bary
    nrm = cp.normals
    d_signed = np.einsum("kd,kd->k", cp.points - points, nrm)  # n . (S - q)
    ok = np.asarray(valid, bool) & ~cp.on_boundary & (cp.distances <= max_distance)
    if point_normals is not None:
        cos_max = np.cos(np.radians(max_normal_angle_deg))
        ok &= np.einsum("kd,kd->k", point_normals, nrm) >= cos_max
    if not ok.any():
        raise FitError(
            "no scan point found a compatible point on the simulated skin (all farther than "
            f"{max_distance:.1f} mm, outside the face region or with opposed normals); the scan "
            "and the subject's neutral do not overlap (check the landmarks and the alignment)."
        )
    r = np.abs(d_signed[ok])
    mad = float(np.median(np.abs(r - np.median(r))))
    c = max(4.685 * 1.4826 * mad, float(robust_floor))
    u = np.abs(d_signed) / c
    w = np.where(ok & (u < 1.0), (1.0 - u * u) ** 2, 0.0)
    if w.sum() <= 0:
        w = ok.astype(np.float64)
    w = w / w.sum()
    loc = local_ids[triangles[tri]]
    if np.any(loc[ok] < 0):  # pragma: no cover - face triangles are always in the fit set
        raise FitError("internal: a face triangle corner is missing from the fit-vertex set.")
    loc = np.where(loc < 0, 0, loc)
    return Correspondences(
        tri=tri,
        bary=bary,
        local=loc,
        target=np.asarray(points, np.float64),
        normal=nrm,
        weight=w,
        distance=d_signed,
        n_accepted=int(ok.sum()),
        scale_mm=c,
    )
