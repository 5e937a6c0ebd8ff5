"""Scan input/output: Bosphorus ``.bnt`` / ``.lm2`` files, OBJ/PLY scans with ``.lm3``
landmarks, range-grid meshing, scan-name parsing, and rigid alignment of expression scans
to the neutral (:mod:`jaxface.io.preprocess`) (all coordinates in mm, +y up, the
face looking along +z, the subject's left at +x). See :mod:`jaxface.io.bosphorus`."""

from .bosphorus import (
    DEFAULT_MAX_EDGE_FACTOR,
    FACE_LABELS,
    AUCode,
    ImageLandmarks,
    MissingLandmarkWarning,
    Scan,
    ScanInfo,
    complete_landmarks,
    grid_triangles,
    load_scan,
    parse_scan_name,
    read_bnt,
    read_lm2,
    write_bnt,
    write_lm2,
)
from .preprocess import AlignmentResult, RigidTransform, align_points, align_scan, procrustes

__all__ = [
    "AlignmentResult",
    "RigidTransform",
    "align_points",
    "align_scan",
    "procrustes",
    "DEFAULT_MAX_EDGE_FACTOR",
    "FACE_LABELS",
    "AUCode",
    "ImageLandmarks",
    "MissingLandmarkWarning",
    "Scan",
    "ScanInfo",
    "complete_landmarks",
    "grid_triangles",
    "load_scan",
    "parse_scan_name",
    "read_bnt",
    "read_lm2",
    "write_bnt",
    "write_lm2",
]
