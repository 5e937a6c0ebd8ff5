"""Fit-quality metrics in millimetres: point-to-surface distances, landmark errors, and
the upper/lower face split.

Everything here is NumPy/SciPy (build-time and evaluation code, never on the jit path).

* :class:`SurfaceIndex`, :func:`point_to_surface`, :func:`mesh_arrays`: exact closest points
  on a triangle mesh (:mod:`jaxface.closest`, re-exported here).
* :class:`DistanceStats`: mean, median, RMS, 95th percentile and maximum of a set of
  distances (mm) (:mod:`jaxface.stats`, re-exported here).
* :class:`FacePlane`: the landmark-derived plane that splits the face into an upper and a
  lower part. It passes through the **nose tip** and its normal is the face's "up" direction,
  taken from the midpoint of the mouth corners to the midpoint of the inner eye corners and
  made orthogonal to the viewing direction. Points above the plane (signed height >= 0) are
  the upper face (brows, eyes, nose bridge); points below it the lower face (nostrils,
  cheeks below the nose tip, mouth, chin). Upper-face AUs (1, 2, 4) act above the plane and
  lower-face AUs (9 partly, 12, 20, 26) below it.
* :func:`fit_metrics`: the issue-7 metric set: scan points -> fitted skin over the face mask,
  ground-truth mesh -> fitted skin when a truth mesh is given, landmark errors, each for
  the whole face and the upper and lower parts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..closest import (
    ClosestPoints,
    SurfaceIndex,
    closest_on_triangles,
    mesh_arrays,
    point_to_surface,
)
from ..errors import FitError, LandmarkError
from ..landmarks import canonical_label
from ..stats import DistanceStats

__all__ = [
    "SurfaceIndex",
    "ClosestPoints",
    "closest_on_triangles",
    "point_to_surface",
    "DistanceStats",
    "FacePlane",
    "landmark_errors",
    "FitMetrics",
    "fit_metrics",
    "mesh_arrays",
    "landmark_dict",
]

REGIONS = ("all", "upper", "lower")


# --------------------------------------------------------------------------------------
# small adapters (TriMesh, trimesh.Trimesh, (V, F) tuples; Landmarks or dicts)
# --------------------------------------------------------------------------------------
def landmark_dict(landmarks) -> dict[str, np.ndarray]:
    """``{canonical label: (3,) mm}`` from a :class:`jaxface.landmarks.Landmarks` or a mapping
    label -> position. Labels are canonicalised when :mod:`jaxface.landmarks` can do it."""
    if landmarks is None:
        return {}
    if hasattr(landmarks, "names") and hasattr(landmarks, "positions"):
        items = zip(landmarks.names, np.asarray(landmarks.positions, dtype=np.float64))
    elif isinstance(landmarks, Mapping):
        items = landmarks.items()
    else:
        raise LandmarkError(
            f"expected Landmarks or a mapping label -> (3,) position in mm, got "
            f"{type(landmarks).__name__}."
        )
    out: dict[str, np.ndarray] = {}
    for name, pos in items:
        key = canonical_label(name)
        out[key or str(name)] = np.asarray(pos, dtype=np.float64).reshape(3)
    return out


# --------------------------------------------------------------------------------------
# upper / lower face
# --------------------------------------------------------------------------------------
_EYE_INNER = ("Inner left eye corner", "Inner right eye corner")
_EYE_OUTER = ("Outer left eye corner", "Outer right eye corner")
_MOUTH = ("Left mouth corner", "Right mouth corner")
_NOSE_TIP = "Nose tip"


@dataclass(frozen=True)
class FacePlane:
    """The plane splitting the face into upper and lower parts (see the module doc).

    Attributes:
        point: ``(3,)`` a point of the plane (the nose tip), mm.
        normal: ``(3,)`` unit normal pointing to the top of the head.
    """

    point: np.ndarray
    normal: np.ndarray

    @classmethod
    def from_landmarks(cls, landmarks) -> FacePlane:
        """Plane through the nose tip, normal = up direction of the face from the landmarks
        (mouth-corner midpoint -> inner-eye-corner midpoint, made orthogonal to the
        viewing direction; outer eye corners or +y used when those are missing).

        Raises:
            LandmarkError: the nose tip is missing, or no up direction can be formed.
        """
        lm = landmark_dict(landmarks)
        if _NOSE_TIP not in lm:
            raise LandmarkError(
                "the upper/lower face split needs the 'Nose tip' landmark; it is missing "
                f"(have {sorted(lm)}).",
                missing=(_NOSE_TIP,),
            )
        eyes = next((p for p in (_EYE_INNER, _EYE_OUTER) if all(x in lm for x in p)), None)
        if eyes is None or not all(x in lm for x in _MOUTH):
            raise LandmarkError(
                "the upper/lower face split needs both inner (or outer) eye corners and both "
                f"mouth corners; have {sorted(lm)}.",
                missing=tuple(x for x in _EYE_INNER + _MOUTH if x not in lm),
            )
        up = 0.5 * (lm[eyes[0]] + lm[eyes[1]]) - 0.5 * (lm[_MOUTH[0]] + lm[_MOUTH[1]])
        # make it orthogonal to the forward (viewing) direction: the nose tip sticks out
        across = lm[eyes[0]] - lm[eyes[1]]  # subject's right -> left, +x
        fwd = np.cross(across, up)
        fn = np.linalg.norm(fwd)
        if fn > 0:
            fwd /= fn
            up = up - np.dot(up, fwd) * fwd
        n = np.linalg.norm(up)
        if not n > 0:
            raise LandmarkError("eye and mouth landmarks coincide; cannot orient the face.")
        return cls(point=np.asarray(lm[_NOSE_TIP], float), normal=up / n)

    def height(self, points) -> np.ndarray:
        """Signed height ``(K,)`` mm of ``points`` ``(K, 3)`` above the plane."""
        return (np.asarray(points, dtype=np.float64) - self.point) @ self.normal

    def is_upper(self, points) -> np.ndarray:
        """``(K,)`` bool: the points at or above the plane (upper face)."""
        return self.height(points) >= 0.0

    def transformed(self, transform) -> FacePlane:
        """The plane moved by a rigid transform (an object with ``rotation`` and ``apply``)."""
        return FacePlane(
            point=transform.apply(self.point[None])[0], normal=transform.rotation @ self.normal
        )


def _region_masks(points: np.ndarray, plane: FacePlane | None) -> dict[str, np.ndarray]:
    allm = np.ones(len(points), bool)
    if plane is None:
        return {"all": allm}
    up = plane.is_upper(points)
    return {"all": allm, "upper": up, "lower": ~up}


# --------------------------------------------------------------------------------------
# landmarks
# --------------------------------------------------------------------------------------
def landmark_errors(predicted, target, names=None) -> dict[str, float]:
    """Euclidean error (mm) of each landmark present in both sets.

    Arguments:
        predicted, target: :class:`Landmarks` or mappings label -> ``(3,)`` mm.
        names: restrict to these labels; a listed label missing from either set raises.

    Returns:
        ``{label: error mm}`` in the order of ``names`` (or of ``target``).

    Raises:
        LandmarkError: a requested label is missing (all missing ones are listed).
    """
    p = landmark_dict(predicted)
    t = landmark_dict(target)
    if names is None:
        keys = [k for k in t if k in p]
    else:
        want = list(landmark_dict({n: np.zeros(3) for n in names}))
        missing = [k for k in want if k not in p or k not in t]
        if missing:
            raise LandmarkError(
                f"landmarks missing for the error computation: {missing}.", missing=missing
            )
        keys = want
    return {k: float(np.linalg.norm(p[k] - t[k])) for k in keys}


# --------------------------------------------------------------------------------------
# the metric set
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FitMetrics:
    """Fit-quality metrics (mm).

    Attributes:
        scan_to_fit: region -> stats of distances scan points -> fitted skin (regions
            ``"all"``, ``"upper"``, ``"lower"``; only ``"all"`` without a face plane).
        truth_to_fit: the same for ground-truth mesh vertices -> fitted skin, or ``None``.
        landmarks: label -> error of the fitted landmark, mm.
        landmark_stats: region -> stats of those landmark errors.
    """

    scan_to_fit: dict[str, DistanceStats]
    truth_to_fit: dict[str, DistanceStats] | None = None
    landmarks: dict[str, float] = field(default_factory=dict)
    landmark_stats: dict[str, DistanceStats] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready nested dict, all values in mm."""
        return {
            "unit": "mm",
            "scan_to_fit": {k: v.to_dict() for k, v in self.scan_to_fit.items()},
            "truth_to_fit": None
            if self.truth_to_fit is None
            else {k: v.to_dict() for k, v in self.truth_to_fit.items()},
            "landmarks": dict(self.landmarks),
            "landmark_stats": {k: v.to_dict() for k, v in self.landmark_stats.items()},
        }


def _mask_triangles(triangles: np.ndarray, vertex_mask: np.ndarray | None) -> np.ndarray | None:
    if vertex_mask is None:
        return None
    vm = np.asarray(vertex_mask, bool)
    return np.asarray(vm[triangles].all(axis=1))


def fit_metrics(
    fitted,
    scan=None,
    *,
    face_mask=None,
    fitted_landmarks=None,
    scan_landmarks=None,
    truth=None,
    truth_mask=None,
    plane: FacePlane | None = None,
    max_distance: float | None = None,
) -> FitMetrics:
    """Issue-7 metrics of a fitted skin, in mm.

    Arguments:
        fitted: the fitted skin (TriMesh / ``trimesh.Trimesh`` / ``(V, F)``), mm, in the frame
            of the scan.
        scan: the scan: a mesh (its vertices are the scan points) or ``(K, 3)`` points, mm;
            ``None`` skips the scan term.
        face_mask: ``(V,)`` bool over the fitted vertices. A scan point counts when its
            closest point on the whole fitted skin lies in the face region (triangles with
            all three vertices in the mask) and not on the skin's border (a point beyond the
            face region or the border is outside the face, not a fitting error). Default: the
            whole skin.
        fitted_landmarks, scan_landmarks: landmark sets (Landmarks or dicts, mm) compared by
            label.
        truth: ground-truth mesh in the same frame (e.g. a ``.truth.ply``) or its ``(K, 3)``
            vertices, mm; its vertices (``truth_mask`` of them, default all) are measured to
            the fitted skin.
        plane: the upper/lower split; default from ``scan_landmarks`` when they allow it,
            else only the ``"all"`` region is reported.
        max_distance: optional: scan points farther than this (mm) from the fitted skin are
            dropped as outliers before the statistics (``None`` keeps all).

    Returns:
        :class:`FitMetrics`.
    """
    fv, ff = mesh_arrays(fitted)
    if face_mask is not None and np.asarray(face_mask).shape != (len(fv),):
        raise FitError(
            f"face_mask must be a (V,) bool array over the fitted skin's {len(fv)} vertices, got "
            f"shape {np.asarray(face_mask).shape}."
        )
    if plane is None and scan_landmarks is not None:
        try:
            plane = FacePlane.from_landmarks(scan_landmarks)
        except LandmarkError:
            plane = None
    scan_stats: dict[str, DistanceStats] = {}
    if scan is not None:
        if isinstance(scan, np.ndarray):
            pts = np.asarray(scan, dtype=np.float64)
        elif hasattr(scan, "mesh_arrays") and hasattr(scan, "points"):  # jaxface.io.Scan
            pts = np.asarray(scan.points, dtype=np.float64)
        else:
            pts = mesh_arrays(scan)[0]
        cp = SurfaceIndex(fv, ff).query(pts)
        if face_mask is None:
            keep = np.ones(len(pts), bool)
        else:
            # the point's closest point on the whole skin must lie in the face region: the
            # closest point on the face region alone put skin beyond it (under an opened
            # jaw's chin) tens of mm from the face, inside the region rather than on its border
            face_tri = _mask_triangles(ff, face_mask)
            assert face_tri is not None  # face_mask is given
            keep = face_tri[cp.triangles] & ~cp.on_boundary
        if max_distance is not None:
            keep &= cp.distances <= max_distance
        regions = _region_masks(pts, plane)
        scan_stats = {
            k: DistanceStats.from_distances(cp.distances[keep & m]) for k, m in regions.items()
        }
    truth_stats = None
    if truth is not None:
        tv = (
            np.asarray(truth, dtype=np.float64)
            if isinstance(truth, np.ndarray)
            else mesh_arrays(truth)[0]
        )
        if tv.ndim != 2 or tv.shape[1] != 3:
            raise FitError(f"truth must be a mesh or (K, 3) points in mm, got shape {tv.shape}.")
        tm = np.ones(len(tv), bool) if truth_mask is None else np.asarray(truth_mask, bool)
        if tm.shape != (len(tv),):
            raise FitError(f"truth_mask must be ({len(tv)},) bool, got {tm.shape}.")
        d = SurfaceIndex(fv, ff).query(tv[tm]).distances
        regions = _region_masks(tv[tm], plane)
        truth_stats = {k: DistanceStats.from_distances(d[m]) for k, m in regions.items()}
    lm_err: dict[str, float] = {}
    lm_stats: dict[str, DistanceStats] = {}
    if fitted_landmarks is not None and scan_landmarks is not None:
        lm_err = landmark_errors(fitted_landmarks, scan_landmarks)
        if lm_err:
            t = landmark_dict(scan_landmarks)
            keys = list(lm_err)
            pos = np.stack([t[k] for k in keys])
            err = np.array([lm_err[k] for k in keys])
            lm_stats = {
                k: DistanceStats.from_distances(err[m])
                for k, m in _region_masks(pos, plane).items()
            }
    return FitMetrics(
        scan_to_fit=scan_stats, truth_to_fit=truth_stats, landmarks=lm_err, landmark_stats=lm_stats
    )
