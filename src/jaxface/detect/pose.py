"""Coarse pose of a face scan in an unknown frame: where is up, forward and the subject's left.

Units mm; the template (the default head) is in the jaxface frame (+y up, face along +z,
subject's left at +x). The result maps template points into the scan's frame.

Method (:func:`estimate_pose`):

1. **Principal axes.** The scan's vertices give a centroid ``c`` and principal axes
   ``e0, e1, e2`` (variance decreasing). On a closed mesh (a whole head) every proper
   rotation that sends the template's axes ``(x, y, z)`` onto a signed permutation of
   ``(e0, e1, e2)`` is a candidate (24). On an open scan (a range image, a face mask) the
   area-weighted mean normal points to the viewer and the face looks roughly that way: it is
   the forward axis, and up is one of the other signed principal axes made orthogonal to it
   (4 candidates).
2. **Nose-tip anchor.** For a candidate forward direction ``f`` the nose tip is the most
   protruding scan point along ``f`` among the points within 45 mm of the axis through ``c``
   (the nose is the face's most anterior point for yaw up to about 45 degrees and pitch up
   to about 30 degrees). The template's nose tip is put there.
3. **Multi-start robust ICP.** Each candidate, and the candidate turned by +-25 degrees of
   yaw and +-15 degrees of pitch about the anchor, starts a short robust point-to-plane ICP
   (:func:`jaxface.fit.align.robust_icp`) of a sparse sample of the template's face onto the
   scan. The best starts (lowest trimmed residual with most of the face matched) are refined
   with a denser sample and a uniform scale.

A scan on which no start matches most of the template's face within a few millimetres is no
face: :class:`NoFaceFoundError`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import FitError
from ..fit.align import robust_icp, rotation_from_euler
from ..fit.metrics import SurfaceIndex
from ..io.preprocess import RigidTransform

__all__ = [
    "NoFaceFoundError",
    "PoseEstimate",
    "estimate_pose",
    "refine_pose",
    "pose_score",
    "principal_frame_rotations",
]

#: acceptance of the final rigid fit: median residual (mm), matched fraction, scale range
MAX_MEDIAN_MM = 2.5
MIN_MATCHED = 0.35
SCALE_RANGE = (0.75, 1.35)


class NoFaceFoundError(FitError):
    """The mesh does not look like a face: the default head's face matches nowhere on it."""


@dataclass(frozen=True)
class PoseEstimate:
    """Template -> scan similarity transform and its quality.

    Attributes:
        transform: :class:`RigidTransform` (with scale) mapping template points (mm) to scan
            points (mm).
        median_mm: median point-to-plane residual of the matched template face points, mm.
        matched: fraction of the template face sample matched within the final cut-off.
        starts: number of ICP starts tried.
    """

    transform: RigidTransform
    median_mm: float
    matched: float
    starts: int

    @property
    def up(self) -> np.ndarray:
        """(3,) unit vector: the subject's up in the scan frame."""
        return self.transform.rotation[:, 1].copy()

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit vector: the direction the face looks, in the scan frame."""
        return self.transform.rotation[:, 2].copy()

    @property
    def left(self) -> np.ndarray:
        """(3,) unit vector: the subject's left in the scan frame (``up x forward``)."""
        return self.transform.rotation[:, 0].copy()


def principal_frame_rotations(points: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Centroid ``(3,)`` mm and the 24 proper rotations ``(3, 3)`` sending the template axes
    onto signed permutations of the principal axes of ``points`` ``(N, 3)``."""
    c = points.mean(axis=0)
    _, vec = np.linalg.eigh(np.cov((points - c).T))
    axes = vec[:, ::-1]  # columns e0, e1, e2 (variance decreasing)
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = axes[:, perm] * np.asarray(signs)
            if np.linalg.det(R) > 0:
                out.append(R)
    return c, out


def _tip(points: np.ndarray, centre: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """The most protruding point along ``forward`` near the axis through ``centre``, mm."""
    d = points - centre
    along = d @ forward
    lateral = np.linalg.norm(d - along[:, None] * forward, axis=1)
    near = lateral < 45.0
    if not near.any():
        near = lateral <= lateral.min() + 1e-9
    i = np.flatnonzero(near)[np.argmax(along[near])]
    return points[i]


def refine_pose(
    index: SurfaceIndex,
    points: np.ndarray,
    normals: np.ndarray,
    init: RigidTransform,
    iterations: int = 25,
) -> tuple[float, RigidTransform, float, float] | None:
    """The fine stage of :func:`estimate_pose` from one start: robust point-to-plane ICP with a
    uniform scale of template ``points`` ``(K, 3)`` mm (unit ``normals``) onto the scan.

    Returns:
        ``(score, transform, median residual mm, matched fraction)`` (:func:`pose_score`;
        lower is better), or ``None`` when the ICP fails.
    """
    try:
        T, st = robust_icp(
            points,
            index,
            init=init,
            moving_normals=normals,
            similarity=True,
            iterations=iterations,
            max_distance=8.0,
            trim=0.1,
            name="pose",
        )
    except FitError:
        return None
    sc, matched = _score(st)
    return sc, T, float(st.residual.median), matched


def pose_score(median_mm: float, matched: float) -> float:
    """The pose's score (lower is better): the median residual (mm) plus 6 mm per unit of
    the matched fraction below 0.85."""
    return median_mm + 6.0 * max(0.0, 0.85 - matched)


def _score(stage) -> tuple[float, float]:
    matched = stage.n_inliers / max(stage.n_points, 1)
    med = float(stage.residual.median)
    if not np.isfinite(med):
        med = float("inf")
    return pose_score(med, matched), matched


def estimate_pose(
    index: SurfaceIndex,
    template_points: np.ndarray,
    template_normals: np.ndarray,
    template_tip: np.ndarray,
    *,
    seed: int = 0,
) -> PoseEstimate:
    """Similarity transform of the template face onto the scan (see the module doc).

    Arguments:
        index: the scan surface.
        template_points: ``(K, 3)`` template face points, mm (jaxface frame).
        template_normals: ``(K, 3)`` their unit normals.
        template_tip: ``(3,)`` the template's nose tip, mm.
        seed: seed of the point subsampling (deterministic).

    Raises:
        NoFaceFoundError: no start matches the template face (a non-face mesh, or a face far
            outside the supported pose range).
    """
    rng = np.random.default_rng(seed)
    used = np.unique(index.triangles[index.active_ids])
    pts = index.vertices[used]
    if len(pts) > 6000:
        pts = pts[rng.choice(len(pts), 6000, replace=False)]
    centre, rots = principal_frame_rotations(pts)
    tri = index.triangles[index.active_ids]
    v = index.vertices
    cr = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    area = 0.5 * np.linalg.norm(cr, axis=1).sum()
    mean_n = cr.sum(axis=0) / max(2.0 * area, 1e-12)  # |.| ~ 1 for a height field, ~0 closed
    if np.linalg.norm(mean_n) > 0.3:
        # open scan: it is seen from the side its mean normal points to, and the face looks
        # roughly that way; up is one of the other principal axes, made orthogonal to it
        mn = mean_n / np.linalg.norm(mean_n)
        rots = []
        for R in principal_frame_rotations(pts)[1]:
            if abs(R[:, 2] @ mn) < 0.5 and abs(R[:, 1] @ mn) < 0.9:
                up = R[:, 1] - (R[:, 1] @ mn) * mn
                up /= np.linalg.norm(up)
                Rn = np.stack([np.cross(up, mn), up, mn], axis=1)
                if not any(np.allclose(Rn, Q) for Q in rots):
                    rots.append(Rn)
    k = len(template_points)
    coarse = rng.choice(k, min(k, 250), replace=False)
    fine = rng.choice(k, min(k, 1500), replace=False)

    def start(R: np.ndarray, tip: np.ndarray):
        try:
            T, st = robust_icp(
                template_points[coarse],
                index,
                init=RigidTransform(R, tip - R @ template_tip),
                moving_normals=template_normals[coarse],
                iterations=8,
                max_distance=15.0,
                anneal=(12.0, 4.0),
                trim=0.2,
                name="pose",
            )
        except FitError:
            return None
        return (_score(st)[0], T)

    # every principal-axes candidate, then turned starts about the two best
    firsts = []
    for R0 in rots:
        tip = _tip(pts, centre, R0[:, 2])
        r = start(R0, tip)
        firsts.append((np.inf if r is None else r[0], R0, tip, r))
    firsts.sort(key=lambda t: t[0])
    trials = [t[3] for t in firsts if t[3] is not None]
    for _, R0, tip, _ in firsts[:2]:
        for pitch, yaw in ((0.0, 25.0), (0.0, -25.0), (15.0, 0.0), (-15.0, 0.0)):
            r = start(R0 @ rotation_from_euler(pitch, yaw), tip)
            if r is not None:
                trials.append(r)
    if not trials:
        raise NoFaceFoundError(
            "no face found: the default head's face matches nowhere on this mesh. Is it a face "
            "scan in mm (a range scan, a face mesh or a whole head)?"
        )
    trials.sort(key=lambda t: t[0])
    best: tuple[float, RigidTransform, float, float] | None = None
    for _, T0 in trials[:3]:
        r = refine_pose(index, template_points[fine], template_normals[fine], T0)
        if r is not None and (best is None or r[0] < best[0]):
            best = r
    if best is None:
        raise NoFaceFoundError(
            "no face found: the rigid fit of the default head's face did not converge on this "
            "mesh. Is it a face scan in mm?"
        )
    _, T, med, matched = best
    if (
        med > MAX_MEDIAN_MM
        or matched < MIN_MATCHED
        or not (SCALE_RANGE[0] <= T.scale <= SCALE_RANGE[1])
    ):
        raise NoFaceFoundError(
            f"no face found: the best rigid fit of the default head's face leaves a median "
            f"residual of {med:.2f} mm (at most {MAX_MEDIAN_MM} accepted), matches "
            f"{100 * matched:.0f}% of the face (at least {100 * MIN_MATCHED:.0f}%) at scale "
            f"{T.scale:.2f} (accepted {SCALE_RANGE[0]}-{SCALE_RANGE[1]}). Is this a face scan "
            f"in mm, showing the face from the brows to the chin?"
        )
    return PoseEstimate(T, med, matched, len(trials))
