"""Automatic 3-D landmarks: the Bosphorus labels found on a scan without a landmark file.

Units mm; see :func:`detect_landmarks` and docs/landmarks.md for the method and accuracy.
"""

from .calibrate import calibrate_definitions
from .definitions import LandmarkDefinitions, load_definitions
from .detector import (
    JAW_FOLLOWERS,
    Detection,
    MirroredScanWarning,
    detect_landmarks,
    scan_arrays,
)
from .pose import NoFaceFoundError, PoseEstimate, estimate_pose
from .transfer import FaceTemplate, face_template, register_face, transfer_landmarks

__all__ = [
    "JAW_FOLLOWERS",
    "Detection",
    "FaceTemplate",
    "LandmarkDefinitions",
    "MirroredScanWarning",
    "NoFaceFoundError",
    "PoseEstimate",
    "calibrate_definitions",
    "detect_landmarks",
    "estimate_pose",
    "face_template",
    "load_definitions",
    "register_face",
    "scan_arrays",
    "transfer_landmarks",
]
