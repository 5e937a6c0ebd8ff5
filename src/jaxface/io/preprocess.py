"""Scan preprocessing: rigid (or similarity) alignment of a scan to a reference scan of the
same subject (an expression scan to the neutral): Procrustes on the expression-stable
landmarks, then robust point-to-plane ICP.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.

Choices (facial-anatomy notes; Erdoğdu 2010 notes sec. 7.1):

* The landmark fit uses only the four eye corners, the two nose saddles and the nose tip
  (:data:`jaxface.landmarks.STABLE_LABELS`); never mouth or chin points.
* ICP, ``region="auto"`` (default), runs in two stages: (1) on the stable region only
  (points near the stable landmarks and not below the nose tip, :func:`stable_region`),
  with Tukey-biweight weights scaled from the residual MAD; (2) on the whole scan with
  Tukey weights whose cut-off is annealed from 3 mm to 0.3 mm, so the parts of the face
  that the expression did not move take over and the moved parts fall out as outliers.
  Stage 2 matters because "stable" landmarks are not perfectly still: in the ICT-made
  Bosphorus-style data an inner-brow raise (AU1) moves the nose saddles by 1.8 mm and
  the nose tip by 1.1 mm, which leaves 1.6 mm of alignment error after the landmark fit
  and 1.4 mm after stable-region ICP, but 0.09 mm after stage 2 (measured on the vertices
  the expression leaves still, against the rigid motions in truth.json).
  ``region="stable"`` (stage 1 only), ``"all"`` (whole scan, MAD scale) or a boolean
  mask are available.
* Matches on the border of the reference scan (holes, silhouette) and farther than
  ``max_distance`` are rejected, so holes and depth noise do not bias the transform.

The landmark fit, the ICP and :class:`AlignmentResult` are the one alignment stack of
:mod:`jaxface.alignment` (shared with :func:`jaxface.fit.align.align_scans`); here the fixed
scan is a :class:`~jaxface.alignment.PointCloud` of its samples and point normals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..alignment import AlignmentResult, ICPStage, PointCloud, landmark_transform, robust_icp
from ..errors import FitError, LandmarkError
from ..landmarks import STABLE_LABELS, Landmarks
from ..rigid import RigidTransform, procrustes
from ..stats import DistanceStats
from .bosphorus import Scan, _canon

__all__ = [
    "STABLE_ALIGNMENT_LABELS",
    "RigidTransform",
    "AlignmentResult",
    "procrustes",
    "align_landmarks",
    "stable_region",
    "point_normals",
    "boundary_points",
    "icp",
    "align_points",
    "align_scan",
    "ICPInfo",
]

#: Expression-stable Bosphorus labels used for landmark alignment (eye corners, nose
#: saddles, nose tip): :data:`jaxface.landmarks.STABLE_LABELS`.
STABLE_ALIGNMENT_LABELS: tuple[str, ...] = STABLE_LABELS


def align_landmarks(
    moving,
    fixed,
    labels: Sequence[str] = STABLE_ALIGNMENT_LABELS,
    *,
    scale: bool = False,
    min_count: int = 3,
) -> tuple[RigidTransform, tuple[str, ...]]:
    """Rigid/similarity transform taking ``moving`` landmarks onto ``fixed`` ones (mm),
    using the labels in ``labels`` present in both (matched by their canonical spelling;
    :func:`jaxface.alignment.landmark_transform`).

    Returns:
        ``(transform, canonical labels used)``.

    Raises:
        LandmarkError: fewer than ``min_count`` common labels (lists the missing ones).
    """
    mv = {_canon(n): np.asarray(moving[n], dtype=np.float64) for n in moving.names}
    fx = {_canon(n): np.asarray(fixed[n], dtype=np.float64) for n in fixed.names}
    return landmark_transform(mv, fx, [_canon(n) for n in labels], scale=scale, min_count=min_count)


def stable_region(
    points: np.ndarray, landmarks, *, radius_factor: float = 0.75, below_nose_mm: float = 5.0
) -> np.ndarray:
    """(N,) bool mask of the expression-stable part of a face: points within
    ``radius_factor`` x (outer-eye-corner distance) of the centroid of the stable landmarks,
    and no lower than ``below_nose_mm`` under the nose tip (excludes mouth and jaw).

    Args:
        points: (N, 3) mm in the frame of ``landmarks``.
        landmarks: needs the nose tip and the stable labels (at least 3 of them).
    """
    pts = np.asarray(points, dtype=np.float64)
    have = {_canon(n): n for n in landmarks.names}
    st = [
        np.asarray(landmarks[have[_canon(l)]]) for l in STABLE_ALIGNMENT_LABELS if _canon(l) in have
    ]
    if len(st) < 3 or _canon("Nose tip") not in have:
        raise LandmarkError(
            "the stable region needs the nose tip and at least 3 stable landmarks",
            missing=[l for l in STABLE_ALIGNMENT_LABELS if _canon(l) not in have],
        )
    c = np.mean(st, axis=0)
    if _canon("Outer left eye corner") in have and _canon("Outer right eye corner") in have:
        size = np.linalg.norm(
            np.asarray(landmarks[have[_canon("Outer left eye corner")]])
            - np.asarray(landmarks[have[_canon("Outer right eye corner")]])
        )
    else:
        size = 2.0 * np.max(np.linalg.norm(np.asarray(st) - c, axis=1))
    tip = np.asarray(landmarks[have[_canon("Nose tip")]])
    return (np.linalg.norm(pts - c, axis=1) < radius_factor * size) & (
        pts[:, 1] > tip[1] - below_nose_mm
    )


def point_normals(scan: Scan) -> np.ndarray:
    """(N, 3) unit normals of ``scan.points`` (area-weighted over the meshed scan, pointing
    toward +z for range grids); points in no triangle get +z."""
    v, t, ids = scan.mesh_arrays(drop_unreferenced=False)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    ln = np.linalg.norm(n, axis=1)
    out = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    ok = ln > 1e-12
    out[ok] = n[ok] / ln[ok, None]
    return out


def boundary_points(scan: Scan) -> np.ndarray:
    """(N,) bool: points on the border of the scanned surface (grid pixels with a background
    4-neighbour or on the grid border; for meshes, vertices on boundary edges)."""
    if scan.is_grid:
        v = scan.valid
        assert v is not None  # a grid scan has its valid mask
        pad = np.pad(v, 1, constant_values=False)
        inner = pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
        return (v & ~inner)[v]
    t = np.asarray(scan.triangles)
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    out = np.zeros(scan.n_points, dtype=bool)
    out[uniq[cnt == 1].ravel()] = True
    return out


#: Diagnostics of :func:`icp` (the alignment stack's :class:`~jaxface.alignment.ICPStage`:
#: ``iterations``, ``converged``, ``rms`` (weighted), ``median``, ``n_inliers``, mm).
ICPInfo = ICPStage


def icp(
    moving: np.ndarray,
    fixed: np.ndarray,
    fixed_normals: np.ndarray,
    *,
    init: RigidTransform | None = None,
    fixed_reject: np.ndarray | None = None,
    iterations: int = 30,
    max_distance: float = 5.0,
    tol: float = 1e-5,
    anneal: tuple[float, float] | None = None,
    name: str = "icp",
) -> tuple[RigidTransform, ICPStage]:
    """Robust point-to-plane ICP: the rigid transform taking ``moving`` onto the surface
    sampled by ``fixed`` (:func:`jaxface.alignment.robust_icp` on a
    :class:`~jaxface.alignment.PointCloud`).

    Each iteration matches every moving point to its nearest fixed point, drops matches
    farther than ``max_distance`` mm or landing on ``fixed_reject`` points (holes,
    silhouette), weights the point-to-plane residuals with Tukey's biweight (scale 4.685 x
    1.4826 x MAD, at least 0.05 mm, or annealed over ``anneal`` mm) and solves the
    linearised 6-DOF update; no trimming, no normal test.

    Args:
        moving: (M, 3) mm.
        fixed: (K, 3) mm; fixed_normals: (K, 3) unit.
        init: starting transform (default identity).
        fixed_reject: (K,) bool, fixed points that may not be matched.
        tol: convergence tolerance on the rotation update, radians (translation: 100 x, mm).

    Raises:
        FitError: fewer than 6 usable matches (the transform is undetermined).
    """
    return robust_icp(
        moving,
        PointCloud(fixed, fixed_normals, fixed_reject),
        init=init,
        loss="tukey",
        iterations=iterations,
        max_distance=max_distance,
        trim=0.0,
        anneal=anneal,
        tol_rad=tol,
        tol_mm=tol * 100,
        ridge=1e-9 / 6,
        min_matches=6,
        name=name,
    )


#: Tukey cut-off schedule (mm) of the whole-face ICP stage of ``region="auto"``.
ANNEAL = (3.0, 0.3)


def align_points(
    moving_points: np.ndarray,
    moving_landmarks: Landmarks,
    fixed_points: np.ndarray,
    fixed_normals: np.ndarray | None,
    fixed_landmarks: Landmarks,
    *,
    fixed_reject: np.ndarray | None = None,
    use_icp: bool = True,
    scale: bool = False,
    region="auto",
    icp_iterations: int = 40,
    max_distance: float = 5.0,
    subsample: int = 3,
) -> tuple[RigidTransform, tuple[str, ...], ICPInfo | None, list[str]]:
    """Core of :func:`align_scan` on plain arrays (mm): stable-landmark Procrustes, then ICP.

    Args:
        moving_points: (M, 3) mm, surface samples of the moving face.
        moving_landmarks, fixed_landmarks: landmarks of the two faces (mm).
        fixed_points: (K, 3) mm; fixed_normals: (K, 3) unit normals there (needed for ICP;
            may be None with ``use_icp=False``).
        fixed_reject: (K,) bool, fixed points never matched (surface border).
        region: ``"auto"`` (stable region, then annealed whole face), ``"stable"``,
            ``"all"`` or an (M,) bool mask of moving points to use.

    Returns:
        ``(transform moving -> fixed, stable labels used, ICPInfo or None, notes)``.
    """
    res = _align_points(
        moving_points,
        moving_landmarks,
        fixed_points,
        fixed_normals,
        fixed_landmarks,
        fixed_reject=fixed_reject,
        use_icp=use_icp,
        scale=scale,
        region=region,
        icp_iterations=icp_iterations,
        max_distance=max_distance,
        subsample=subsample,
    )
    return res.transform, res.labels, res.icp, list(res.notes)


def _align_points(
    moving_points,
    moving_landmarks,
    fixed_points,
    fixed_normals,
    fixed_landmarks,
    *,
    fixed_reject,
    use_icp,
    scale,
    region,
    icp_iterations,
    max_distance,
    subsample,
) -> AlignmentResult:
    """:func:`align_points` as an :class:`AlignmentResult` (``landmark_rms`` left NaN: the
    callers measure it on their own landmarks)."""
    notes: list[str] = []
    T, used = align_landmarks(moving_landmarks, fixed_landmarks, scale=scale)
    missing = [l for l in STABLE_ALIGNMENT_LABELS if l not in used]
    if missing:
        notes.append(f"stable landmarks not used (absent): {', '.join(missing)}")
    T0 = T

    def result(T, info=None):
        stages = () if info is None else (info,)
        return AlignmentResult(
            transform=T,
            landmark_transform=T0,
            labels=used,
            landmark_rms=float("nan"),
            stages=stages,
            residual=info.residual if info is not None else DistanceStats.from_distances([]),
            converged=all(s.converged for s in stages),
            notes=tuple(notes),
        )

    if not use_icp:
        return result(T)
    if fixed_normals is None:
        raise FitError("align_points: ICP needs fixed_normals; give them or use_icp=False.")
    pts = np.asarray(moving_points, dtype=np.float64)
    if isinstance(region, str) and region == "stable":
        mask = stable_region(pts, moving_landmarks)
    elif isinstance(region, str) and region in ("all", "auto"):
        mask = np.ones(len(pts), dtype=bool)
    elif isinstance(region, str):
        raise FitError(f"unknown ICP region {region!r}; use 'auto', 'stable', 'all' or a mask")
    else:
        mask = np.asarray(region, dtype=bool)
    step = max(int(subsample), 1)
    mov = pts[mask][::step]
    if len(mov) < 50:
        notes.append(f"ICP skipped: only {len(mov)} points in the ICP region")
        return result(T)
    info = None
    try:
        pre = RigidTransform(np.eye(3), np.zeros(3), T.scale)  # ICP stays rigid
        rigid0 = RigidTransform(T.rotation, T.translation, 1.0)
        kw: dict[str, Any] = dict(
            fixed_reject=fixed_reject, iterations=icp_iterations, max_distance=max_distance
        )
        if isinstance(region, str) and region == "auto":
            st = stable_region(pts, moving_landmarks)[mask][::step]
            if st.sum() >= 50:
                rigid0, _ = icp(
                    pre.apply(mov[st]),
                    fixed_points,
                    fixed_normals,
                    init=rigid0,
                    name="stable",
                    **kw,
                )
            R_icp, info = icp(
                pre.apply(mov),
                fixed_points,
                fixed_normals,
                init=rigid0,
                anneal=ANNEAL,
                name="all",
                **kw,
            )
        else:
            name = region if isinstance(region, str) else "mask"
            R_icp, info = icp(
                pre.apply(mov), fixed_points, fixed_normals, init=rigid0, name=name, **kw
            )
        T = R_icp.compose(pre)
        if not info.converged:
            notes.append(
                f"ICP did not converge in {info.iterations} iterations (last rms {info.rms:.3f} mm)"
            )
    except FitError as e:
        notes.append(f"ICP failed, landmark alignment kept: {e}")
        info = None
    return result(T, info)


def align_scan(
    scan: Scan,
    reference: Scan,
    *,
    use_icp: bool = True,
    scale: bool = False,
    region="auto",
    icp_iterations: int = 40,
    max_distance: float = 5.0,
    subsample: int = 3,
) -> AlignmentResult:
    """Align ``scan`` (e.g. an expression scan) rigidly to ``reference`` (e.g. the same
    subject's neutral): stable-landmark Procrustes, then robust ICP (see the module doc).

    Args:
        scan, reference: scans with landmarks, mm.
        use_icp: refine with ICP.
        scale: allow a uniform scale in the landmark fit (similarity); ICP stays rigid.
        region: ICP region: ``"auto"``, ``"stable"``, ``"all"`` or an (N,) bool mask.
        max_distance: ICP match rejection distance, mm.
        subsample: use every ``subsample``-th point in ICP (speed).

    Returns:
        :class:`AlignmentResult`; ``result.scan`` lives in the reference frame.

    Raises:
        LandmarkError: not enough common stable landmarks.
    """
    if scan.landmarks is None or reference.landmarks is None:
        raise LandmarkError(
            f"align_scan needs landmarks on both scans ({scan.path or 'scan'}, "
            f"{reference.path or 'reference'}); load them with the .lm3 files.",
            missing=STABLE_ALIGNMENT_LABELS,
        )
    notes = []
    for s in (scan, reference):
        if s.info is not None and (s.info.is_pose or s.info.is_occlusion):
            notes.append(f"{s.info.stem}: {s.info.describe()}")
    fn = point_normals(reference) if use_icp else None
    rej = boundary_points(reference) if use_icp else None
    res = _align_points(
        scan.points,
        scan.landmarks,
        reference.points,
        fn,
        reference.landmarks,
        fixed_reject=rej,
        use_icp=use_icp,
        scale=scale,
        region=region,
        icp_iterations=icp_iterations,
        max_distance=max_distance,
        subsample=subsample,
    )
    T = res.transform
    moved_lm = scan.landmarks.transformed(T.rotation * T.scale, T.translation)
    a = np.stack([np.asarray(moved_lm[l]) for l in res.labels])
    b = np.stack([np.asarray(reference.landmarks[l]) for l in res.labels])
    sq = np.sum((a - b) ** 2, axis=1)
    moved = replace(scan, points=T.apply(scan.points), landmarks=moved_lm)
    return replace(
        res,
        landmark_rms=float(np.sqrt(np.mean(sq))),
        residual=res.residual if res.stages else DistanceStats.from_distances(np.sqrt(sq)),
        notes=tuple(notes) + res.notes,
        scan=moved,
    )
