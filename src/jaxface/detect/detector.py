"""Automatic Bosphorus landmarks on a scan without a landmark file.

Units mm; the landmarks are returned in the scan's own frame, whatever it is. Pipeline
(:func:`detect_landmarks`): coarse pose (:mod:`jaxface.detect.pose`), the template's jaw
opened as far as the scan's (:func:`jaxface.detect.transfer.choose_jaw_opening`),
registration of the default head's face and transfer of its landmarks at their calibrated
definitions (:mod:`jaxface.detect.transfer`, :mod:`jaxface.detect.definitions`), eye and
mouth refinement on the scan's relief (:mod:`jaxface.detect.slits`), the nose tip and brows
at their relief extrema (:mod:`jaxface.detect.features`), surface snap, visibility and
confidence (:mod:`jaxface.detect.refine`), then the side check:
the labels follow the detected anatomy (the subject's left is ``up x forward``), so when they
fail :func:`jaxface.landmarks.check_side` in the scan's frame the frame is not jaxface's
(+y up, face along +z, left at +x): it is mirrored or the face looks along -z, and a
:class:`MirroredScanWarning` says so.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import LandmarkError
from ..fit.metrics import SurfaceIndex, mesh_arrays
from ..fit.register import Registration
from ..landmarks import BOSPHORUS_LABELS, FACE_LABELS, Landmarks, check_side
from .features import feature_extrema
from .pose import PoseEstimate
from .refine import Placement, place_landmarks
from .slits import refine_slits, scan_rim_vertices
from .transfer import FaceTemplate, register_face

__all__ = ["JAW_FOLLOWERS", "Detection", "MirroredScanWarning", "detect_landmarks", "scan_arrays"]

#: labels carried by the jaw, left out when the mouth is open wider than the template followed
JAW_FOLLOWERS = ("Lower lip inner middle", "Lower lip outer middle", "Chin middle")


class MirroredScanWarning(UserWarning):
    """The detected landmarks fail the jaxface side convention in the scan's frame."""


@dataclass(frozen=True)
class Detection:
    """Detected landmarks of one scan (scan frame, mm).

    Attributes:
        landmarks: the visible labels (:class:`Landmarks`, Bosphorus order), on the scan.
        confidence: label -> confidence in [0, 1] (visible labels).
        omitted: label -> reason it was left out.
        pose: the coarse pose (template -> scan similarity; up / forward / left vectors).
        registration: the registration of the default head's face that carried them.
        jaw_opening_deg: how far the template's jaw was opened before the registration
            (:func:`jaxface.detect.transfer.choose_jaw_opening`), degrees.
        seconds: wall time, s.
        side_problem: the side-check message when the frame looks mirrored, else ``None``.
    """

    landmarks: Landmarks
    confidence: dict[str, float]
    omitted: dict[str, str]
    pose: PoseEstimate
    registration: Registration | None = field(repr=False, default=None)
    jaw_opening_deg: float = 0.0
    seconds: float = 0.0
    side_problem: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (mm, degrees)."""
        T = self.pose.transform
        return {
            "landmarks": {n: [float(x) for x in p] for n, p in self.landmarks.to_dict().items()},
            "confidence": {n: round(float(c), 4) for n, c in self.confidence.items()},
            "omitted": dict(self.omitted),
            "pose": {
                "up": self.pose.up.tolist(),
                "forward": self.pose.forward.tolist(),
                "left": self.pose.left.tolist(),
                "scale": float(T.scale),
                "median_residual_mm": self.pose.median_mm,
                "matched_fraction": self.pose.matched,
            },
            "jaw_opening_deg": self.jaw_opening_deg,
            "side_problem": self.side_problem,
            "seconds": self.seconds,
        }


def scan_arrays(scan) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3)`` mm vertices and ``(F, 3)`` triangles of a :class:`jaxface.io.Scan`, a mesh or
    a ``(V, F)`` pair."""
    if hasattr(scan, "mesh_arrays") and hasattr(scan, "points"):
        v, t, _ = scan.mesh_arrays()
        return np.asarray(v, float), np.asarray(t, np.int64)
    return mesh_arrays(scan)


def detect_landmarks(
    scan, *, warn: bool = True, refine: bool = True, template: FaceTemplate | None = None
) -> Detection:
    """Find the Bosphorus landmarks on a scan that has none (see the module doc).

    Arguments:
        scan: :class:`jaxface.io.Scan`, :class:`jaxface.mesh.TriMesh`, ``trimesh.Trimesh``
            or ``(V, F)``; mm; any frame.
        warn: issue :class:`MirroredScanWarning` when the frame looks mirrored.
        refine: refine the eye and mouth landmarks on the scan's relief
            (:mod:`jaxface.detect.slits`), and the nose tip and brows at their relief extrema
            (:mod:`jaxface.detect.features`); ``False`` keeps the transferred ones.
        template: the registered face and the points it carries (default
            :func:`jaxface.detect.transfer.face_template`: the default head with the packaged
            landmark definitions).

    Returns:
        :class:`Detection`.

    Raises:
        NoFaceFoundError: the mesh does not look like a face.
        LandmarkError: fewer than 5 landmarks are visible.
    """
    t0 = time.perf_counter()
    v, f = scan_arrays(scan)
    index = SurfaceIndex(v, f)
    pose, opening, tpl, reg = register_face(index, template)
    names = list(FACE_LABELS)
    guesses = reg.landmarks.array(names)
    findings: dict[str, str] = {}
    if refine:
        better = refine_slits(
            index,
            dict(zip(names, guesses)),
            pose.left,
            pose.up,
            scan_rim_vertices(index),
            findings,
        )
        T = pose.transform
        for n, p in feature_extrema(
            index, dict(zip(names, guesses)), pose.left, pose.up, pose.forward
        ).items():
            if n in tpl.offsets:  # a feature without an offset keeps its transferred point
                better[n] = p + T.scale * (T.rotation @ tpl.offsets[n])
        guesses = np.stack([better[n] if n in better else g for n, g in zip(names, guesses)])
    placed = place_landmarks(index, names, guesses, reg.vertices, reg.residuals, reg.has_data)
    if "open_mouth" in findings:
        # the template's lower lip and chin stayed up with the closed mouth it was registered
        # from (on the interior of the mouth): left out rather than placed 20 mm off
        for n in JAW_FOLLOWERS:
            if n in placed and placed[n].position is not None:
                placed[n] = Placement(None, 0.0, findings["open_mouth"])
    ears = list(tpl.ear_lobes.names)
    placed.update(
        place_landmarks(
            index,
            ears,
            pose.transform.apply(tpl.ear_lobes.positions),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0, bool),
        )
    )
    order = [n for n in BOSPHORUS_LABELS if n in placed]
    vis = [n for n in order if placed[n].position is not None]
    if len(vis) < 5:
        raise LandmarkError(
            f"only {len(vis)} landmark(s) are visible on the scan ({vis}); the scan covers too "
            f"little of the face to place the Bosphorus landmarks.",
            missing=tuple(n for n in order if n not in vis),
        )
    pos: list[np.ndarray] = [p for n in vis if (p := placed[n].position) is not None]
    lm = Landmarks(vis, np.stack(pos))
    side = None
    try:
        check_side(lm)
    except LandmarkError as e:
        side = (
            f"the scan's frame looks mirrored: in its coordinates the subject's left is "
            f"{_axis_name(pose.left)} and the face looks along {_axis_name(pose.forward)} "
            f"(jaxface expects left at +x and the face along +z). The landmarks are labelled "
            f"by the anatomy; mirror or rotate the scan before fitting. ({e})"
        )
        if warn:
            warnings.warn(side, MirroredScanWarning, stacklevel=2)
    return Detection(
        landmarks=lm,
        confidence={n: placed[n].confidence for n in vis},
        omitted={n: str(placed[n].reason) for n in order if n not in vis},
        pose=pose,
        registration=reg,
        jaw_opening_deg=float(opening),
        seconds=time.perf_counter() - t0,
        side_problem=side,
    )


def _axis_name(d: np.ndarray) -> str:
    k = int(np.argmax(np.abs(d)))
    return ("-" if d[k] < 0 else "+") + "xyz"[k]
