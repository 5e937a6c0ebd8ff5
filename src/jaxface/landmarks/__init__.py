"""Facial landmarks: the 24 Bosphorus labels, a container, label variants, MPEG-4 FDPs, the
mirror check and the Bosphorus ``.lm3`` file format.

Units and frame: millimetres, +y up, the face looks along +z, the subject's left is +x (so the
"left" eye corners have larger x than the "right" ones).

Canonical labels are the Bosphorus database's 24 labels (22 on the face plus the two ear lobes,
for which jaxface uses "Left ear lobe" / "Right ear lobe"). Lookup is tolerant of case,
spacing, punctuation, word order and ear-lobe wording ("left earlobe", "Ear lobe (L)", ...).

``.lm3`` format (Bosphorus): comment lines starting with ``#``, a blank line, ``N landmarks:``,
then N pairs of lines: the label, and ``x y z`` in mm. Landmarks missing from a scan are
omitted, so always match by label.

Layout: :mod:`.labels` (label tables, normalisation), :mod:`.container` (:class:`Landmarks`,
attaching to a mesh), :mod:`.sides` (the side check), :mod:`.lm3` (``.lm3`` files).
"""

from __future__ import annotations

from .container import Landmarks, attach_to_mesh
from .labels import (
    BOSPHORUS_LABELS,
    FACE_LABELS,
    FUZZY_MARGIN,
    FUZZY_MIN_RATIO,
    MIRROR_PAIRS,
    MPEG4_FDP,
    STABLE_LABELS,
    LandmarkLabelWarning,
    canonical_label,
    fuzzy_label,
)
from .lm3 import DETECTED_LM3_HEADER, lm3_is_detected, read_lm3, write_lm3
from .sides import check_side

__all__ = [
    "BOSPHORUS_LABELS",
    "FACE_LABELS",
    "STABLE_LABELS",
    "MIRROR_PAIRS",
    "MPEG4_FDP",
    "Landmarks",
    "canonical_label",
    "fuzzy_label",
    "LandmarkLabelWarning",
    "FUZZY_MIN_RATIO",
    "FUZZY_MARGIN",
    "check_side",
    "read_lm3",
    "lm3_is_detected",
    "DETECTED_LM3_HEADER",
    "write_lm3",
    "attach_to_mesh",
]
