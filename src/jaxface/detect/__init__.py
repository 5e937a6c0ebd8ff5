"""Automatic 3-D landmarks: the Bosphorus labels found on a scan without a landmark file.

Units mm; see :func:`detect_landmarks` and docs/landmarks.md for the method and accuracy.
"""

from .detector import (
    JAW_FOLLOWERS,
    Detection,
    MirroredScanWarning,
    detect_landmarks,
    scan_arrays,
)
from .pose import NoFaceFoundError, PoseEstimate, estimate_pose
from .transfer import FaceTemplate, face_template, transfer_landmarks

__all__ = [
    "JAW_FOLLOWERS",
    "Detection",
    "FaceTemplate",
    "MirroredScanWarning",
    "NoFaceFoundError",
    "PoseEstimate",
    "detect_landmarks",
    "estimate_pose",
    "face_template",
    "scan_arrays",
    "transfer_landmarks",
]
