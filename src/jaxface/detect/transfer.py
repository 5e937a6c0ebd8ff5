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
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..fit.metrics import SurfaceIndex
from ..fit.register import RegisterOptions, Registration, register_template
from ..head import generic_head
from ..io.preprocess import RigidTransform
from ..landmarks import FACE_LABELS, Landmarks
from ..mesh import TriMesh

__all__ = ["FaceTemplate", "face_template", "transfer_landmarks", "TRANSFER_OPTIONS"]

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
        landmarks: the 22 Bosphorus face landmarks on it.
        ear_lobes: the two ear-lobe landmarks of the whole head (outside ``mesh``).
        normals: ``(V, 3)`` unit vertex normals.
        nose_tip: ``(3,)`` mm.
        regions: ``(V,)`` bool masks named as :attr:`jaxface.head.Head.regions` (restricted
            to the face).
    """

    mesh: TriMesh
    landmarks: Landmarks
    ear_lobes: Landmarks
    normals: np.ndarray
    nose_tip: np.ndarray
    regions: dict


@functools.lru_cache(maxsize=1)
def face_template() -> FaceTemplate:
    """The cached :class:`FaceTemplate` of the default head."""
    head = generic_head()
    tri = np.asarray(head.mesh.triangles)
    sub, ids = head.mesh.submesh(head.face_mask[tri].all(axis=1))
    lm = head.landmarks.subset(FACE_LABELS)
    ears = head.landmarks.subset(("Left ear lobe", "Right ear lobe"))
    regions = {k: np.asarray(m, bool)[ids] for k, m in head.regions.items()}
    return FaceTemplate(
        mesh=sub,
        landmarks=lm,
        ear_lobes=ears,
        normals=np.asarray(sub.vertex_normals),
        nose_tip=np.array(lm["Nose tip"]),
        regions=regions,
    )


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
