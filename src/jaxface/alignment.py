"""Rigid (or similarity) alignment of one face onto another: the one alignment stack.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.
NumPy/SciPy (preprocessing, off the jit path).

Both entry points run on these parts:

* :func:`landmark_transform`: Kabsch/Umeyama (:func:`jaxface.rigid.procrustes`) on the
  labelled landmarks present in both faces (the expression-stable ones by default);
* :func:`robust_icp`: robust point-to-plane ICP (iteratively reweighted least squares,
  Tukey or Huber weights at ``mad_factor * 1.4826 * MAD`` of the residuals or an annealed
  cut-off) onto a fixed surface given as a :class:`~jaxface.closest.SurfaceIndex` (exact
  closest points on a mesh) or a :class:`PointCloud` (nearest sample with its normal);
* :class:`AlignmentResult` and :class:`ICPStage`: the result and the per-stage diagnostics.

:func:`jaxface.fit.align.align_scans` (the fit's alignment: mesh surfaces, trimmed matches,
normal test, stable region then upper face) and :func:`jaxface.io.preprocess.align_scan`
(scan preprocessing: nearest scan samples, stable region then whole scan) are two settings
of this stack; ``docs/design/pipeline.md`` lists the differences.

Every transform maps the **moving** face into the **fixed** frame: ``fixed ~ T(moving)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from .closest import SurfaceIndex
from .errors import FitError, LandmarkError
from .rigid import RigidTransform, procrustes, rotvec_matrix
from .stats import DistanceStats

__all__ = [
    "AlignmentResult",
    "ICPStage",
    "NearestPoints",
    "PointCloud",
    "landmark_transform",
    "robust_icp",
]


# --------------------------------------------------------------------------------------
# landmarks
# --------------------------------------------------------------------------------------
def landmark_transform(
    moving: Mapping[str, Any],
    fixed: Mapping[str, Any],
    labels: Sequence[str],
    *,
    scale: bool = False,
    min_count: int = 3,
) -> tuple[RigidTransform, tuple[str, ...]]:
    """Rigid (or similarity, ``scale=True``) transform taking the ``moving`` landmarks onto
    the ``fixed`` ones, ``fixed ~ s R moving + t`` (Kabsch/Umeyama, least squares).

    Args:
        moving, fixed: ``{label: (3,) mm}`` with the labels spelled as in ``labels``.
        labels: the labels to use, in order; those present in both mappings are used.
        scale: estimate a uniform scale too.
        min_count: fewest common labels accepted.

    Returns:
        ``(transform, labels used)``.

    Raises:
        LandmarkError: fewer than ``min_count`` common labels (lists the missing ones).
        FitError: the common landmarks are (nearly) collinear.
    """
    used = [n for n in labels if n in moving and n in fixed]
    if len(used) < min_count:
        missing = tuple(n for n in labels if n not in used)
        raise LandmarkError(
            f"rigid alignment needs at least {min_count} stable landmarks present in both "
            f"scans; found {len(used)} ({', '.join(used) or 'none'}); missing: "
            f"{', '.join(missing)}. Add them to the .lm3 files.",
            missing=missing,
        )
    src = np.stack([np.asarray(moving[n], dtype=np.float64).reshape(3) for n in used])
    dst = np.stack([np.asarray(fixed[n], dtype=np.float64).reshape(3) for n in used])
    return procrustes(src, dst, scale=scale), tuple(used)


# --------------------------------------------------------------------------------------
# fixed surfaces
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NearestPoints:
    """Result of :meth:`PointCloud.query` for ``K`` query points (the fields ICP reads have
    the names of :class:`~jaxface.closest.ClosestPoints`).

    Attributes:
        points: ``(K, 3)`` nearest samples, mm; distances: ``(K,)`` mm; ids: ``(K,)`` int64
        sample ids; normals: ``(K, 3)`` their unit normals; on_boundary: ``(K,)`` bool, the
        sample is one of the rejected ones (scan border, hole rim).
    """

    points: np.ndarray
    distances: np.ndarray
    ids: np.ndarray
    normals: np.ndarray
    on_boundary: np.ndarray


class PointCloud:
    """A fixed surface given by samples with normals: ICP matches each moving point to the
    nearest sample (k-d tree) and measures along that sample's normal.

    Arguments:
        points: ``(K, 3)`` mm; normals: ``(K, 3)`` unit.
        reject: optional ``(K,)`` bool, samples that may not be matched (reported as
            ``on_boundary``).
    """

    def __init__(self, points, normals, reject=None):
        self.points = np.asarray(points, dtype=np.float64)
        self.normals = np.asarray(normals, dtype=np.float64)
        n = len(self.points)
        self.reject = np.zeros(n, bool) if reject is None else np.asarray(reject, bool)
        if self.normals.shape != self.points.shape or self.reject.shape != (n,):
            raise FitError(
                f"a PointCloud needs (K, 3) points and normals and a (K,) reject mask; got "
                f"{self.points.shape}, {self.normals.shape} and {self.reject.shape}."
            )
        self._tree = cKDTree(self.points)

    def query(self, points, *, max_distance: float | None = None, exact: bool = True):
        """Nearest samples of ``points`` ``(Q, 3)`` mm (:class:`NearestPoints`);
        ``max_distance`` and ``exact`` are accepted for the interface of
        :meth:`~jaxface.closest.SurfaceIndex.query` and change nothing."""
        d, j = self._tree.query(np.asarray(points, dtype=np.float64))
        j = np.asarray(j, np.int64)
        return NearestPoints(self.points[j], np.asarray(d), j, self.normals[j], self.reject[j])


# --------------------------------------------------------------------------------------
# robust point-to-plane ICP
# --------------------------------------------------------------------------------------
def _robust_weights(r: np.ndarray, c: float, loss: str) -> np.ndarray:
    u = np.abs(r) / c
    if loss == "tukey":
        return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    if loss == "huber":
        return np.where(u <= 1.0, 1.0, 1.0 / np.maximum(u, 1e-300))
    raise FitError(f"unknown robust loss {loss!r}; use 'tukey' or 'huber'.")


@dataclass(frozen=True)
class ICPStage:
    """Diagnostics of one robust ICP run (distances in mm).

    Attributes:
        name: the stage (``"stable"``, ``"face"``, ``"all"``, ``"mask"``, ...).
        iterations: iterations run; converged: the update fell below the tolerance.
        n_points: moving points used; n_matches: accepted matches in the last iteration;
        n_inliers: matches with a non-zero robust weight in the last iteration.
        residual: stats of the absolute point-to-plane residuals of the inliers (mm).
        scale_mm: the robust cut-off in the last iteration (mm).
        weighted_rms: ``sqrt(sum w r^2 / sum w)`` of the last iteration's residuals, mm.
    """

    name: str
    iterations: int
    converged: bool
    n_points: int
    n_matches: int
    n_inliers: int
    residual: DistanceStats
    scale_mm: float
    weighted_rms: float = float("nan")

    @property
    def rms(self) -> float:
        """The weighted RMS residual, mm (``ICPInfo.rms`` of :mod:`jaxface.io.preprocess`)."""
        return self.weighted_rms

    @property
    def median(self) -> float:
        """Median absolute point-to-plane residual of the inliers, mm."""
        return self.residual.median

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "iterations": self.iterations,
            "converged": self.converged,
            "n_points": self.n_points,
            "n_matches": self.n_matches,
            "n_inliers": self.n_inliers,
            "residual_mm": self.residual.to_dict(),
            "scale_mm": self.scale_mm,
        }


def robust_icp(
    moving,
    fixed: SurfaceIndex | PointCloud,
    *,
    init: RigidTransform | None = None,
    moving_normals=None,
    similarity: bool = False,
    loss: Literal["tukey", "huber"] = "tukey",
    iterations: int = 30,
    max_distance: float = 5.0,
    max_normal_angle_deg: float = 60.0,
    trim: float = 0.1,
    mad_factor: float = 4.685,
    min_scale: float = 0.05,
    anneal: tuple[float, float] | None = None,
    tol_rad: float = 1e-5,
    tol_mm: float = 1e-3,
    exact: bool = False,
    ridge: float = 1e-12,
    min_matches: int = 7,
    name: str = "icp",
) -> tuple[RigidTransform, ICPStage]:
    """Robust point-to-plane ICP of moving points onto a fixed surface.

    Each iteration matches the moving points (moved by the current transform) to the fixed
    surface, rejects matches farther than ``max_distance``, on the surface's border or with
    disagreeing normals, drops the worst ``trim`` fraction, weights the residuals
    ``r = (p - q) . n`` robustly and solves the linearised update ``r + J x ~ 0`` with
    ``x = (omega (rad), t (mm)[, log scale])`` about the current transform's output.

    Arguments:
        moving: ``(K, 3)`` moving points, mm.
        fixed: the fixed surface: a :class:`SurfaceIndex` (exact closest points on a mesh)
            or a :class:`PointCloud` (nearest sample).
        init: starting transform (default identity); its scale is estimated further only
            when ``similarity``.
        moving_normals: optional ``(K, 3)`` unit normals of the moving points (rotated with
            the transform) for the normal-compatibility test.
        similarity: also estimate a uniform scale.
        loss: ``"tukey"`` (biweight, redescending) or ``"huber"``.
        iterations: maximum number of iterations (static).
        max_distance: matches farther than this (mm) are rejected.
        max_normal_angle_deg: matches whose normals differ more are rejected.
        trim: fraction of the largest residuals dropped before weighting (0 = none).
        mad_factor: robust cut-off ``= mad_factor * 1.4826 * MAD`` (at least ``min_scale``).
        anneal: optional ``(start, end)`` mm: cut-off annealed geometrically over the first
            half of the iterations instead of the MAD rule.
        tol_rad, tol_mm: convergence tolerances on the update (radians, mm).
        exact: exact closest points in every iteration (default: the fast local search of
            :meth:`SurfaceIndex.query`, exact near the surface on well-shaped meshes).
        ridge: Tikhonov damping of the normal equations, times their trace.
        min_matches: fewest matches (and inliers) accepted.
        name: the stage's name in the diagnostics and messages.

    Returns:
        ``(transform, ICPStage)``; ``transform`` maps moving points onto ``fixed``.

    Raises:
        FitError: fewer than ``min_matches`` usable matches or inliers (the scans are not
            roughly aligned).
    """
    p0 = np.asarray(moving, dtype=np.float64)
    n0 = None if moving_normals is None else np.asarray(moving_normals, dtype=np.float64)
    T = init or RigidTransform()
    cos_max = np.cos(np.radians(max_normal_angle_deg))
    converged = False
    it = 0
    last = (0, 0, DistanceStats.from_distances([]), float("nan"), float("nan"))
    half = max(iterations // 2, 1)
    for it in range(1, iterations + 1):
        p = T.apply(p0)
        cp = fixed.query(p, max_distance=max_distance, exact=exact)
        ok = (cp.distances <= max_distance) & ~cp.on_boundary
        if n0 is not None:
            ok &= np.einsum("ij,ij->i", n0 @ T.rotation.T, cp.normals) >= cos_max
        idx = np.flatnonzero(ok)
        if idx.size < min_matches:
            raise FitError(
                f"ICP ({name}) found only {idx.size} matches within {max_distance} mm on the fixed "
                "scan; the scans are not roughly aligned. Check the landmarks of both scans."
            )
        q, nq, pp = cp.points[idx], cp.normals[idx], p[idx]
        r = np.einsum("ij,ij->i", pp - q, nq)
        if trim > 0:
            keep = np.abs(r) <= np.quantile(np.abs(r), 1.0 - trim)
            q, nq, pp, r = q[keep], nq[keep], pp[keep], r[keep]
        if anneal is None:
            mad = float(np.median(np.abs(r - np.median(r))))
            c = max(mad_factor * 1.4826 * mad, min_scale)
        else:
            f = min((it - 1) / half, 1.0)
            c = anneal[0] * (anneal[1] / anneal[0]) ** f
        w = _robust_weights(r, c, loss)
        n_in = int((w > 0).sum())
        if n_in < min_matches:
            raise FitError(
                f"ICP ({name}): fewer than {min_matches} inlier matches after robust weighting."
            )
        cols = [np.cross(pp, nq), nq]
        centre = pp.mean(axis=0)
        if similarity:
            cols.append(np.einsum("ij,ij->i", pp - centre, nq)[:, None])
        J = np.concatenate(cols, axis=1)
        A = (J * w[:, None]).T @ J
        b = -(J * w[:, None]).T @ r
        A = A + ridge * np.trace(A) * np.eye(len(b))
        x = np.linalg.solve(A, b)
        if similarity:
            s = float(np.exp(x[6]))
            # scale about the centroid of the matched points, then rotate/translate
            S = RigidTransform(np.eye(3), (1.0 - s) * centre, s)
            T = S.compose(T)
        step = RigidTransform(rotvec_matrix(x[:3]), x[3:6])
        T = step.compose(T)
        wrms = float(np.sqrt(np.sum(w * r * r) / np.sum(w)))
        last = (int(idx.size), n_in, DistanceStats.from_distances(r[w > 0]), c, wrms)
        annealing = anneal is not None and it <= half
        if not annealing and np.linalg.norm(x[:3]) < tol_rad and np.linalg.norm(x[3:6]) < tol_mm:
            converged = True
            break
    return T, ICPStage(
        name, it, converged, len(p0), last[0], last[1], last[2], float(last[3]), last[4]
    )


# --------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AlignmentResult:
    """Result of an alignment (:func:`jaxface.fit.align.align_scans`,
    :func:`jaxface.io.preprocess.align_scan`).

    Attributes:
        transform: maps the moving scan into the fixed frame (``fixed ~ T(moving)``), mm.
        landmark_transform: the landmark-only estimate.
        labels: the landmark labels used for it.
        landmark_rms: RMS distance (mm) of those landmarks after ``transform``.
        stages: diagnostics of the ICP stages kept (empty when ICP was off, skipped or
            failed).
        residual: stats (mm) of the inlier point-to-plane residuals of the last stage (of
            the landmark distances without ICP).
        converged: every ICP stage converged.
        notes: remarks (skipped stages, missing landmarks, pose/occlusion classes).
        scan: the moving :class:`~jaxface.io.Scan` moved into the fixed frame
            (:func:`~jaxface.io.preprocess.align_scan`); None otherwise.
    """

    transform: RigidTransform
    landmark_transform: RigidTransform
    labels: tuple[str, ...]
    landmark_rms: float
    stages: tuple[ICPStage, ...] = ()
    residual: DistanceStats = field(default_factory=lambda: DistanceStats.from_distances([]))
    converged: bool = True
    notes: tuple[str, ...] = ()
    scan: Any = None

    @property
    def landmark_labels(self) -> tuple[str, ...]:
        """The landmark labels used (``labels``)."""
        return self.labels

    @property
    def icp(self) -> ICPStage | None:
        """The last ICP stage, or None when ICP was off, skipped or failed."""
        return self.stages[-1] if self.stages else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (mm, degrees): the ``alignment`` record of ``jaxface fit``."""
        return {
            "transform": self.transform.as_dict(),
            "landmark_transform": self.landmark_transform.as_dict(),
            "labels": list(self.labels),
            "landmark_rms_mm": self.landmark_rms,
            "stages": [s.to_dict() for s in self.stages],
            "residual_mm": self.residual.to_dict(),
            "converged": self.converged,
            "notes": list(self.notes),
        }

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict in the layout of :func:`jaxface.io.preprocess.align_scan`
        (transform, landmark labels and RMS, the last ICP stage, notes)."""
        icp = self.icp
        return {
            "transform": self.transform.as_dict(),
            "landmark_labels": list(self.labels),
            "landmark_rms_mm": self.landmark_rms,
            "icp": None
            if icp is None
            else {
                "iterations": icp.iterations,
                "converged": icp.converged,
                "rms": icp.rms,
                "median": icp.median,
                "n_inliers": icp.n_inliers,
            },
            "notes": list(self.notes),
        }
