"""Landmark transfer by registration: the default head's face, whose Bosphorus landmarks are
known, is registered onto the scan and carries its landmarks along.

Units mm. The template is the face region of :func:`jaxface.head.generic_head` (forehead to
under the chin, ear to ear), cut out as its own mesh so the registration solves for ~5k
vertices only. The registration is the project's own
:func:`jaxface.fit.register.register_template` (landmark TPS, then Laplacian-regularised
non-rigid ICP). No scan landmarks exist yet, so the "scan landmarks" handed to it are the
template's own landmarks moved by the coarse pose: the TPS reduces to that similarity
transform, and the landmark weights are zero, so only the surface decides the non-rigid
part. The smoothing schedule stops at 4 mm: finer detail is the job of the local refinement
(:mod:`jaxface.detect.refine`).

The points carried along are the head's landmarks, with the labels on a smooth surface at
their calibrated definitions (:mod:`jaxface.detect.definitions`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np

from ..anatomy.frame import face_frame
from ..anatomy.jaw import JawModel, JawPose
from ..anatomy.rig_build import jaw_follow_weights
from ..fit.metrics import SurfaceIndex
from ..fit.register import RegisterOptions, Registration, register_template
from ..head import generic_head
from ..io.preprocess import RigidTransform
from ..landmarks import FACE_LABELS, Landmarks
from ..mesh import TriMesh
from .definitions import LandmarkDefinitions, load_definitions
from .features import FEATURE_LABELS, feature_extrema
from .pose import PoseEstimate, estimate_pose, pose_score, refine_pose

__all__ = [
    "FaceTemplate",
    "face_template",
    "transfer_landmarks",
    "choose_jaw_opening",
    "register_face",
    "TRANSFER_OPTIONS",
    "JAW_OPENINGS_DEG",
]

#: jaw openings (degrees about the hinge) tried for the template, closed first
JAW_OPENINGS_DEG = (0.0, 5.0, 10.0, 15.0, 20.0)
#: an opening is taken only when its pose score beats the closed jaw's by more than this (mm)
JAW_MARGIN_MM = 0.15

#: registration schedule of the transfer (coarse to 4 mm; no landmark pull)
TRANSFER_OPTIONS = RegisterOptions(
    smoothing_mm=(20.0, 8.0, 4.0),
    iterations=1,
    final_iterations=1,
    landmark_weight_mm2=0.0,
    final_landmark_weight_mm2=0.0,
    reverse_stride=4,
    max_distance_mm=8.0,
)


@dataclass(frozen=True)
class FaceTemplate:
    """The default head's face cut out for detection (jaxface frame, mm).

    Attributes:
        mesh: the face region as a :class:`TriMesh` (``V`` vertices).
        landmarks: the 22 Bosphorus face landmarks on it: the head's own, with the labels of
            the definitions (:mod:`jaxface.detect.definitions`) at their definitions, moved
            onto the face's surface.
        ear_lobes: the two ear-lobe landmarks of the whole head (outside ``mesh``).
        normals: ``(V, 3)`` unit vertex normals.
        nose_tip: ``(3,)`` mm, the head's most anterior nose point (the coarse pose puts it on
            the scan's most protruding point).
        regions: ``(V,)`` bool masks named as :attr:`jaxface.head.Head.regions` (restricted
            to the face).
        jaw_weight: ``(V,)`` in [0, 1], how far each vertex follows the mandible
            (:func:`jaxface.anatomy.rig_build.jaw_follow_weights` with the lower lip on the
            mandible, halved toward the mouth corners, which move about half as far).
        offsets: label -> ``(3,)`` mm, head frame: from a feature label's relief extremum to
            the label (:attr:`LandmarkDefinitions.offsets_mm`; empty without definitions).
        landmark_jaw_weight: ``(22,)`` the same at the landmarks (their nearest vertex).
        jaw: the head's :class:`~jaxface.anatomy.jaw.JawModel` (opening up to 30 degrees).
    """

    mesh: TriMesh
    landmarks: Landmarks
    ear_lobes: Landmarks
    normals: np.ndarray
    nose_tip: np.ndarray
    regions: dict
    jaw_weight: np.ndarray
    landmark_jaw_weight: np.ndarray
    jaw: JawModel
    offsets: dict = field(default_factory=dict)

    def opened(self, degrees: float) -> FaceTemplate:
        """This template with the jaw opened by ``degrees`` about the hinge: each vertex (and
        landmark) moves by its jaw weight times the mandible's motion. Open the closed
        template (:func:`face_template`); the weights describe its geometry."""
        R, t = (np.asarray(a, np.float64) for a in self.jaw.transform(JawPose(float(degrees))))

        def move(x, w):
            return x + w[:, None] * (x @ R.T + t - x)

        mesh = TriMesh(
            move(np.asarray(self.mesh.vertices), self.jaw_weight),
            self.mesh.triangles,
            validate=False,
        )
        return replace(
            self,
            mesh=mesh,
            landmarks=self.landmarks.with_positions(
                move(self.landmarks.positions, self.landmark_jaw_weight)
            ),
            normals=np.asarray(mesh.vertex_normals),
        )


@functools.lru_cache(maxsize=1)
def face_template() -> FaceTemplate:
    """The cached :class:`FaceTemplate` of the default head, with the packaged landmark
    definitions (:func:`jaxface.detect.definitions.load_definitions`)."""
    return build_face_template(load_definitions())


def build_face_template(definitions: LandmarkDefinitions | None = None) -> FaceTemplate:
    """The :class:`FaceTemplate` of the default head.

    ``definitions`` (head frame, mm) replace the head's own landmarks at their labels, and
    give the feature labels' offsets from their relief extrema. ``None``: the head's own
    landmarks, and as offsets the head's own, from each feature's extremum on the head itself
    to its landmark (the nose tip: about zero, it is the most anterior point)."""
    head = generic_head()
    tri = np.asarray(head.mesh.triangles)
    sub, ids = head.mesh.submesh(head.face_mask[tri].all(axis=1))
    lm = head.landmarks.subset(FACE_LABELS)
    if definitions is not None and definitions.points:
        names = [n for n in FACE_LABELS if n in definitions.points]
        on = SurfaceIndex(np.asarray(sub.vertices), np.asarray(sub.triangles)).query(
            np.stack([definitions.points[n] for n in names])
        )
        pos = {n: p for n, p in zip(names, on.points)}
        lm = lm.with_positions(np.stack([pos.get(n, lm[n]) for n in lm.names]))
    ears = head.landmarks.subset(("Left ear lobe", "Right ear lobe"))
    regions = {k: np.asarray(m, bool)[ids] for k, m in head.regions.items()}
    frame = face_frame(head.landmarks)
    x = np.asarray(sub.vertices)
    lip = regions["lower_lip"]
    w = jaw_follow_weights(x, lip, frame)
    loc = frame.to_local(x)
    half = np.abs(frame.to_local(np.asarray(lm["Left mouth corner"]))[0])
    taper = 1.0 - 0.5 * np.clip(np.abs(loc[:, 0]) / max(half, 1e-9), 0.0, 1.0) ** 2
    w = np.where(lip, w * taper, w)
    near = np.argmin(
        np.linalg.norm(x[None, :, :] - np.asarray(lm.positions)[:, None, :], axis=2), axis=1
    )
    return FaceTemplate(
        mesh=sub,
        landmarks=lm,
        ear_lobes=ears,
        normals=np.asarray(sub.vertex_normals),
        nose_tip=np.array(head.landmarks["Nose tip"]),
        regions=regions,
        jaw_weight=w,
        landmark_jaw_weight=w[near],
        jaw=JawModel.from_landmarks(head.landmarks, pitch_limits=(-4.0, 30.0)),
        offsets=_own_offsets(sub, lm) if definitions is None else dict(definitions.offsets_mm),
    )


def choose_jaw_opening(
    index: SurfaceIndex,
    pose: PoseEstimate,
    template: FaceTemplate | None = None,
    openings: tuple[float, ...] = JAW_OPENINGS_DEG,
    *,
    seed: int = 0,
) -> tuple[float, PoseEstimate, dict[float, float]]:
    """The jaw opening of the template that best matches the scan, with its pose.

    The coarse pose (:func:`jaxface.detect.pose.estimate_pose`, closed jaw) starts, for each
    opening, the fine pose stage (:func:`jaxface.detect.pose.refine_pose`) of the opened
    template; the opening with the lowest pose score (:func:`jaxface.detect.pose.pose_score`:
    median residual, mm, plus a penalty for an unmatched face) wins. The closed jaw is kept
    unless an opening scores better by more than :data:`JAW_MARGIN_MM`.

    Returns:
        ``(degrees, pose for that opening, {degrees: score})``.
    """
    tpl = template or face_template()
    k = len(tpl.mesh.vertices)
    fine = np.random.default_rng(seed).choice(k, min(k, 1500), replace=False)
    closed = pose_score(pose.median_mm, pose.matched)
    scores: dict[float, float] = {0.0: closed}
    best = (closed, 0.0, pose)
    for deg in openings:
        if not deg:
            continue
        t = tpl.opened(deg)
        r = refine_pose(
            index, np.asarray(t.mesh.vertices)[fine], t.normals[fine], pose.transform, 15
        )
        if r is None:
            continue
        scores[float(deg)] = r[0]
        if r[0] < best[0] and closed - r[0] > JAW_MARGIN_MM:
            best = (r[0], float(deg), PoseEstimate(r[1], r[2], r[3], pose.starts))
    return best[1], best[2], scores


def transfer_landmarks(
    index: SurfaceIndex,
    pose: RigidTransform,
    template: FaceTemplate | None = None,
    *,
    options: RegisterOptions = TRANSFER_OPTIONS,
) -> Registration:
    """Register the template face (moved by ``pose``) onto the scan surface ``index``.

    Returns:
        the :class:`Registration` (scan frame, mm); ``.landmarks`` holds the 22 transferred
        face landmarks, ``.has_data`` tells which template vertices the scan covers.
    """
    tpl = template or face_template()
    moved = TriMesh(pose.apply(np.asarray(tpl.mesh.vertices)), tpl.mesh.triangles, validate=False)
    lm = tpl.landmarks.with_positions(pose.apply(tpl.landmarks.positions))
    return register_template(
        (index.vertices, index.triangles),
        lm,
        template=moved,
        template_landmarks=lm,
        options=options,
        scan_index=index,
    )


def _own_offsets(mesh: TriMesh, lm: Landmarks) -> dict[str, np.ndarray]:
    """label -> the head's own offset from the feature's extremum to its landmark (mm)."""
    index = SurfaceIndex(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    axes = np.eye(3)
    found = feature_extrema(index, {n: lm[n] for n in FEATURE_LABELS}, axes[0], axes[1], axes[2])
    return {n: np.asarray(lm[n]) - e for n, e in found.items()}


def register_face(
    index: SurfaceIndex, template: FaceTemplate | None = None
) -> tuple[PoseEstimate, float, FaceTemplate, Registration]:
    """The detector's registration of the default head's face onto a scan: coarse pose
    (:func:`jaxface.detect.pose.estimate_pose`), jaw opening (:func:`choose_jaw_opening`) and
    transfer (:func:`transfer_landmarks`).

    Arguments:
        index: the scan's surface (mm, any frame).
        template: default :func:`face_template`.

    Returns:
        ``(pose, jaw opening in degrees, the template as opened, registration)``; the
        registration's vertex ``i`` is template vertex ``i`` (scan frame, mm).

    Raises:
        NoFaceFoundError: the mesh does not look like a face.
    """
    tpl = template or face_template()
    pose = estimate_pose(index, np.asarray(tpl.mesh.vertices), tpl.normals, tpl.nose_tip)
    opening, pose, _ = choose_jaw_opening(index, pose, tpl)
    if opening:
        tpl = tpl.opened(opening)
    return pose, float(opening), tpl, transfer_landmarks(index, pose.transform, tpl)
