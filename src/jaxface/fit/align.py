"""Rigid (or similarity) alignment of an expression scan to the same subject's neutral scan.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.
Everything here is NumPy/SciPy (preprocessing, not on the jit path).

Procedure (:func:`align_scans`):

1. **Landmarks.** Kabsch/Umeyama (:func:`umeyama`) on the expression-stable landmarks only:
   the four eye corners, the two nose saddles and the nose tip
   (:data:`jaxface.landmarks.STABLE_LABELS`). Mouth and chin landmarks are never used.
2. **Robust ICP on the stable region.** Points of the moving scan near the stable landmarks
   and not below the nose tip (:func:`stable_mask`) are matched to their exact closest
   points on the fixed scan's surface (:class:`jaxface.fit.metrics.SurfaceIndex`), and a
   linearised point-to-plane rigid (or similarity) update is solved by iteratively
   reweighted least squares. Matches are rejected when the closest point lies on the fixed
   scan's border (a hole rim or the silhouette: no data there), when they are farther than
   ``max_distance`` or when the normals disagree by more than ``max_normal_angle_deg``; the
   worst ``trim`` fraction is dropped, and the rest are weighted with Tukey's biweight (or
   Huber's) at ``c * 1.4826 * MAD`` of the residuals.
3. **Robust ICP on the upper face and cheeks** (``region="auto"``, the default): the same
   estimator on every point of the moving scan except the mouth/chin region
   (:func:`mouth_chin_mask`: within ``mouth_margin`` of the lip/chin landmarks, or below
   the mouth corners), with the Tukey cut-off annealed from ``anneal[0]`` to ``anneal[1]``
   mm. Reason: the "stable" landmarks are not perfectly still under expression. In the
   ICT-made Bosphorus-style data an inner-brow raise (AU1) moves the nose saddles by
   1.8 mm and a nose wrinkle (AU9) the nose tip by 3.6 mm, so a fit restricted to the
   nose/eye region inherits that motion; over the whole upper face and cheeks the surface
   the expression did not move dominates and the moving parts become Tukey outliers.
   ``region="stable"`` stops after step 2.

The result maps the **moving** scan into the **fixed** frame: ``fixed ~ T(moving)``.

Limits (measured on the shared data, see ``benchmarks/bench_register.py``): the rigid motion
is observable only from surface that the expression leaves still. In the ICT-made scans
``E_HAPPY`` and ``E_SURPRISE`` move every visible face vertex by more than 0.3 mm (the
forehead by 0.6-9 mm), so no rigid fit can recover ``truth.json``'s motion there (errors of
0.25 and 2 degrees); ``AlignmentResult.notes`` then reports the low consensus, and the
expression fit's own rigid correction has to finish the job. Where a still region exists
(AU1, 2, 4, 9, 12, 12L, 20, 26) the error is 0.01-0.2 degrees.

The landmark fit, the ICP and the result type are the one alignment stack of
:mod:`jaxface.alignment` (shared with :func:`jaxface.io.preprocess.align_scan`); this module
adds the fit's regions (:func:`stable_mask`, :func:`mouth_chin_mask`), the noise floor
(:func:`estimate_noise`) and the stage schedule above.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..alignment import AlignmentResult, ICPStage, landmark_transform, robust_icp
from ..errors import FitError, LandmarkError
from ..landmarks import STABLE_LABELS
from ..rigid import RigidTransform, procrustes, rotation_from_euler
from ..stats import DistanceStats
from .metrics import SurfaceIndex, landmark_dict, mesh_arrays

__all__ = [
    "RigidTransform",
    "umeyama",
    "rotation_from_euler",
    "stable_mask",
    "mouth_chin_mask",
    "ICPStage",
    "AlignmentResult",
    "robust_icp",
    "align_scans",
    "MOUTH_CHIN_LABELS",
    "estimate_noise",
]

#: landmarks of the mouth and chin: never used for alignment, and their neighbourhood is
#: excluded from the ICP region
MOUTH_CHIN_LABELS: tuple[str, ...] = (
    "Left mouth corner",
    "Right mouth corner",
    "Upper lip outer middle",
    "Upper lip inner middle",
    "Lower lip inner middle",
    "Lower lip outer middle",
    "Chin middle",
)


def umeyama(src, dst, weights=None, *, scale: bool = False) -> RigidTransform:
    """Weighted least-squares rigid (``scale=False``) or similarity transform with
    ``dst ~ s R src + t`` (Kabsch/Umeyama, reflection-safe).

    Arguments:
        src, dst: ``(n, 3)`` corresponding points, mm; ``n >= 3``, not collinear.
        weights: optional ``(n,)`` non-negative weights.
        scale: estimate a uniform scale too.

    Returns:
        :class:`RigidTransform` (mm).

    Raises:
        FitError: fewer than 3 weighted pairs, or collinear points.
    """
    return procrustes(src, dst, weights, scale=scale)


# --------------------------------------------------------------------------------------
# regions
# --------------------------------------------------------------------------------------
def _stable_positions(landmarks, labels=STABLE_LABELS, min_count: int = 3):
    lm = landmark_dict(landmarks)
    used = [n for n in labels if n in lm]
    if len(used) < min_count:
        raise LandmarkError(
            f"at least {min_count} expression-stable landmarks are needed ({', '.join(labels)}); "
            f"found {len(used)}: {', '.join(used) or 'none'}. Add them to the .lm3 file.",
            missing=tuple(n for n in labels if n not in lm),
        )
    return lm, used


def _face_frame(lm: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    """Up direction (unit) and face size (outer-eye-corner distance, mm) from landmarks."""
    up = np.array([0.0, 1.0, 0.0])
    eyes = [n for n in ("Outer left eye corner", "Outer right eye corner") if n in lm]
    mouth = [n for n in ("Left mouth corner", "Right mouth corner") if n in lm]
    if len(eyes) == 2:
        size = float(np.linalg.norm(lm[eyes[0]] - lm[eyes[1]]))
        if len(mouth) == 2:
            u = 0.5 * (lm[eyes[0]] + lm[eyes[1]]) - 0.5 * (lm[mouth[0]] + lm[mouth[1]])
            if np.linalg.norm(u) > 0:
                up = u / np.linalg.norm(u)
    else:
        pts = np.stack(list(lm.values()))
        size = float(2.0 * np.max(np.linalg.norm(pts - pts.mean(0), axis=1)))
    return up, max(size, 1e-6)


def stable_mask(
    points, landmarks, *, radius_factor: float = 0.6, below_nose_mm: float = 5.0
) -> np.ndarray:
    """The expression-stable region of a face: ``(K,)`` bool over ``points`` ``(K, 3)`` mm.

    A point belongs to it when it lies within ``radius_factor`` x (outer-eye-corner
    distance) of one of the stable landmarks (eye corners, nose saddles, nose tip) and no
    lower than ``below_nose_mm`` under the nose tip (along the face's up direction). Mouth
    and chin are therefore always excluded.

    Raises:
        LandmarkError: fewer than 3 stable landmarks, or no nose tip.
    """
    p = np.asarray(points, dtype=np.float64)
    lm, used = _stable_positions(landmarks)
    if "Nose tip" not in lm:
        raise LandmarkError(
            "the stable region needs the 'Nose tip' landmark.", missing=("Nose tip",)
        )
    up, size = _face_frame(lm)
    st = np.stack([lm[n] for n in used])
    near = np.zeros(len(p), bool)
    r = radius_factor * size
    for c in st:
        near |= np.sum((p - c) ** 2, axis=1) < r * r
    return near & ((p - lm["Nose tip"]) @ up > -below_nose_mm)


def mouth_chin_mask(points, landmarks, *, margin_factor: float = 0.2) -> np.ndarray:
    """``(K,)`` bool: the mouth/chin region of a face (never used for alignment).

    A point is in it when it lies within ``margin_factor`` x (outer-eye-corner distance) of
    one of the lip/mouth-corner/chin landmarks present, or lower (along the face's up
    direction) than the mouth corners. Without any mouth/chin landmark: everything lower
    than 0.6 face sizes under the nose tip.
    """
    p = np.asarray(points, dtype=np.float64)
    lm = landmark_dict(landmarks)
    up, size = _face_frame(lm)
    have = [n for n in MOUTH_CHIN_LABELS if n in lm]
    out = np.zeros(len(p), bool)
    if not have:
        if "Nose tip" in lm:
            return (p - lm["Nose tip"]) @ up < -0.6 * size
        return out
    r = margin_factor * size
    for n in have:
        out |= np.sum((p - lm[n]) ** 2, axis=1) < r * r
    corners = [lm[n] for n in ("Left mouth corner", "Right mouth corner") if n in lm]
    ref = min(float(c @ up) for c in corners) if corners else min(float(lm[n] @ up) for n in have)
    return out | (p @ up < ref)


def estimate_noise(index: SurfaceIndex, *, n_samples: int = 2000, k: int = 9) -> float:
    """Depth-noise estimate (mm) of a scan surface: the median over sampled vertices of the
    RMS residual of a least-squares plane through each vertex's ``k`` nearest vertices
    (corrected for the 3 fitted parameters). On a smooth face sampled at 1 mm the curvature
    adds about 0.02 mm; the Bosphorus-style bs901 scans (0.1 mm noise) give about 0.09."""
    key = (int(n_samples), int(k))
    cache = index.__dict__.setdefault("_noise_estimates", {})
    if key in cache:
        return cache[key]
    used = np.unique(index.triangles[index.active_ids])
    pts = index.vertices[used]
    if len(pts) < k + 1:
        return 0.0
    sel = pts[np.linspace(0, len(pts) - 1, min(n_samples, len(pts))).astype(np.int64)]
    _, nn = cKDTree(pts).query(sel, k=k)
    nb = pts[nn]  # (S, k, 3)
    c = nb - nb.mean(axis=1, keepdims=True)
    ev = np.linalg.eigvalsh(np.einsum("ski,skj->sij", c, c))[:, 0]  # smallest: out-of-plane
    rms = np.sqrt(np.maximum(ev, 0.0) / max(k - 3, 1))
    cache[key] = float(np.median(rms))
    return cache[key]


def _mesh_or_points(x):
    """(vertices, triangles or None) of a TriMesh / Scan / trimesh / (V, F) / points."""
    if hasattr(x, "mesh_arrays") and hasattr(x, "points"):  # jaxface.io.Scan
        v, t, _ = x.mesh_arrays()
        return np.asarray(v, float), np.asarray(t, np.int64)
    if isinstance(x, np.ndarray):
        return np.asarray(x, float), None
    return mesh_arrays(x)


def align_scans(
    moving,
    fixed,
    moving_landmarks=None,
    fixed_landmarks=None,
    *,
    similarity: bool = False,
    icp: bool = True,
    region: Literal["auto", "stable"] | np.ndarray = "auto",
    loss: Literal["tukey", "huber"] = "tukey",
    iterations: int = 30,
    max_distance: float = 5.0,
    max_normal_angle_deg: float = 60.0,
    trim: float = 0.1,
    anneal: tuple[float, float] = (2.0, 0.15),
    noise_mm: float | Literal["auto"] | None = "auto",
    max_points: int = 2500,
    labels: Sequence[str] = STABLE_LABELS,
    fixed_index: SurfaceIndex | None = None,
    low_consensus: float = 0.35,
) -> AlignmentResult:
    """Align ``moving`` (an expression scan) to ``fixed`` (the neutral scan of the subject).

    Arguments:
        moving: the scan to move: a :class:`jaxface.io.Scan`, a TriMesh / ``trimesh`` /
            ``(V, F)`` pair, mm. Its vertices are the ICP points (boundary vertices excluded);
            its triangles give their normals.
        fixed: the reference scan (same kinds), mm; meshed so closest points are exact.
        moving_landmarks, fixed_landmarks: Landmarks (or dicts), mm; default the scans'
            own ``landmarks``.
        similarity: estimate a uniform scale as well (landmarks and ICP).
        icp: refine with robust ICP (steps 2-3 of the module doc); False = landmarks only.
        region: ``"auto"`` (stable region, then upper face and cheeks with an annealed
            cut-off), ``"stable"`` (stable region only), or a ``(K,)`` bool mask over the
            moving vertices for a single MAD-scaled stage.
        loss, max_distance, max_normal_angle_deg, trim: see :func:`robust_icp`.
        anneal: Tukey cut-off schedule of the face stage, mm.
        noise_mm: depth noise of the scans, mm; the final cut-off is at least 2.5 times it.
            ``"auto"`` estimates it from the fixed scan (:func:`estimate_noise`), ``None``
            uses ``anneal`` as given.
        max_points: at most this many moving points per stage (evenly subsampled).
        labels: the landmarks for step 1 (default the stable ones; mouth/chin labels are
            refused).
        fixed_index: a prebuilt :class:`SurfaceIndex` of ``fixed`` (to align many scans to
            one neutral).
        low_consensus: a note is added when fewer than this fraction of the face-stage
            matches are inliers (no still region to align on).

    Returns:
        :class:`AlignmentResult`.

    Raises:
        LandmarkError: fewer than 3 common stable landmarks, or a mouth/chin label in
            ``labels``.
        FitError: ICP impossible (no overlap after the landmark fit).
    """
    bad = [n for n in labels if n in MOUTH_CHIN_LABELS]
    if bad:
        raise LandmarkError(
            f"alignment must not use mouth or chin landmarks (they move with expression): {bad}."
        )
    mlm = landmark_dict(
        moving_landmarks if moving_landmarks is not None else getattr(moving, "landmarks", None)
    )
    flm = landmark_dict(
        fixed_landmarks if fixed_landmarks is not None else getattr(fixed, "landmarks", None)
    )
    T0, used = landmark_transform(mlm, flm, labels, scale=similarity)
    src = np.stack([mlm[n] for n in used])
    dst = np.stack([flm[n] for n in used])
    notes: list[str] = []
    missing = [n for n in labels if n not in used]
    if missing:
        notes.append(f"stable landmarks absent, not used: {', '.join(missing)}")
    T = T0
    stages: list[ICPStage] = []
    if icp:
        mv, mt = _mesh_or_points(moving)
        if fixed_index is None:
            fv, ft = _mesh_or_points(fixed)
            if ft is None:
                raise FitError(
                    "the fixed scan must be a mesh (or a grid scan) for ICP; got bare points."
                )
            fixed_index = SurfaceIndex(fv, ft)
        normals = None
        usable = np.ones(len(mv), bool)
        if mt is not None:
            mi = SurfaceIndex(mv, mt)
            normals = mi.vertex_normals
            usable = ~mi.boundary_vertices & (np.linalg.norm(normals, axis=1) > 0)
            used_v = np.zeros(len(mv), bool)
            used_v[mt.ravel()] = True
            usable &= used_v
        moved_lm = {k: T.apply(v[None])[0] for k, v in mlm.items()}
        mv_f = T.apply(mv)  # moving points in the fixed frame (landmark fit)

        def pick(mask):
            ids = np.flatnonzero(mask & usable)
            if ids.size > max_points:
                ids = ids[np.linspace(0, ids.size - 1, max_points).astype(np.int64)]
            return ids

        def run(ids, name, T, anneal_=None):
            T2, st = robust_icp(
                mv[ids],
                fixed_index,
                init=T,
                moving_normals=None if normals is None else normals[ids],
                similarity=similarity,
                loss=loss,
                iterations=iterations,
                max_distance=max_distance,
                max_normal_angle_deg=max_normal_angle_deg,
                trim=trim,
                anneal=anneal_,
                name=name,
            )
            return T2, st

        if isinstance(region, str):
            if region not in ("auto", "stable"):
                raise FitError(
                    f"unknown ICP region {region!r}; use 'auto', 'stable' or a bool mask."
                )
            ids = pick(stable_mask(mv_f, moved_lm))
            if ids.size < 50:
                notes.append(f"ICP skipped: only {ids.size} points in the stable region")
            else:
                T, st = run(ids, "stable", T)
                stages.append(st)
                if region == "auto":
                    ids2 = pick(~mouth_chin_mask(mv_f, moved_lm))
                    sigma = estimate_noise(fixed_index) if noise_mm == "auto" else (noise_mm or 0.0)
                    end = max(float(anneal[1]), 2.5 * float(sigma))
                    T, st = run(ids2, "face", T, (max(float(anneal[0]), end), end))
                    stages.append(st)
        else:
            m = np.asarray(region, bool)
            if m.shape != (len(mv),):
                raise FitError(
                    f"region mask must be ({len(mv)},) bool over the moving vertices, got {m.shape}."
                )
            ids = pick(m)
            T, st = run(ids, "mask", T)
            stages.append(st)
    a = T.apply(src)
    lrms = float(np.sqrt(np.mean(np.sum((a - dst) ** 2, axis=1))))
    residual = (
        stages[-1].residual
        if stages
        else DistanceStats.from_distances(np.linalg.norm(a - dst, axis=1))
    )
    converged = all(s.converged for s in stages)
    for s in stages:
        if not s.converged:
            notes.append(f"ICP stage {s.name!r} did not converge in {s.iterations} iterations")
        if s.name == "face" and s.n_inliers < low_consensus * max(s.n_matches, 1):
            notes.append(
                f"only {s.n_inliers} of {s.n_matches} face points agree with one rigid motion: the "
                "expression moves most of the face, so the rigid alignment is uncertain (a fit "
                "with a rigid correction should refine it)"
            )
    return AlignmentResult(
        transform=T,
        landmark_transform=T0,
        labels=used,
        landmark_rms=lrms,
        stages=tuple(stages),
        residual=residual,
        converged=converged,
        notes=tuple(notes),
    )
