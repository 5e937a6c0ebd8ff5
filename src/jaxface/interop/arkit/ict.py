"""The ICT-FaceKit data at run time: where ``ict_face.npz`` is (:func:`default_ict_path`) and its
Bosphorus-labelled landmarks (:func:`ict_bosphorus_landmarks`, Multi-PIE 68 -> Bosphorus, mm)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ...errors import DataNotFoundError, LandmarkError

__all__ = ["MULTIPIE68_TO_BOSPHORUS", "default_ict_path", "ict_bosphorus_landmarks"]

# ------------------------------------------------------------------------------------------
# the ICT data at run time
# ------------------------------------------------------------------------------------------
#: Multi-PIE 68-point index (0-based, ICT ``vertex_indices.json`` ``idx_to_landmark_verts``)
#: -> Bosphorus label. Multi-PIE numbers the subject's right side first (17-21 the right brow,
#: 36-39 the right eye), so 26 is the outer *left* eyebrow (+x). Bosphorus's "Chin middle" has
#: no Multi-PIE counterpart: point 8 is the menton, the lowest point of the jaw line, which on
#: the ICT head lies about 15 mm below and behind the chin's front middle. Pairing the two
#: bent the cloning morph over the whole lower face (the cloned ``jawOpen`` 39 % off instead
#: of 12 %), so the chin is left out.
MULTIPIE68_TO_BOSPHORUS: dict[int, str] = {
    17: "Outer right eyebrow",
    19: "Middle right eyebrow",
    21: "Inner right eyebrow",
    22: "Inner left eyebrow",
    24: "Middle left eyebrow",
    26: "Outer left eyebrow",
    36: "Outer right eye corner",
    39: "Inner right eye corner",
    42: "Inner left eye corner",
    45: "Outer left eye corner",
    30: "Nose tip",
    48: "Right mouth corner",
    54: "Left mouth corner",
    51: "Upper lip outer middle",
    62: "Upper lip inner middle",
    66: "Lower lip inner middle",
    57: "Lower lip outer middle",
}


def default_ict_path(*, shared_fallback: bool = True) -> Path | None:
    """Where the ICT-FaceKit file is found at run time: ``$JAXFACE_ICT`` (the ``.npz``), else
    (with ``shared_fallback``) ``$JAXFACE_SHARED/data/ict/ict_face.npz`` (default
    ``../shared``); None when neither exists (jaxface ships no ICT data).

    The fit's readout (:func:`readout_for_subject` with ``"auto"``) looks at ``$JAXFACE_ICT``
    only: cloning the 51 shapes costs tens of seconds per subject, which a fit pays only when
    the user asked for it by naming the file."""
    env = os.environ.get("JAXFACE_ICT", "").strip()
    if env:
        p = Path(env).expanduser()
        return p if p.is_file() else None
    if not shared_fallback:
        return None
    root = Path(os.environ.get("JAXFACE_SHARED", "../shared")).expanduser()
    p = root / "data" / "ict" / "ict_face.npz"
    return p.resolve() if p.is_file() else None


def ict_bosphorus_landmarks(npz_path, landmark_ids=None):
    """Bosphorus-labelled landmarks on the ICT neutral (mm) for the motion cloning.

    Args:
        npz_path: ``ict_face.npz``.
        landmark_ids: ``{label: ICT vertex id}``; default: the Multi-PIE 68 ids of
            ``vertex_indices.json`` beside the ``.npz`` (ICT-FaceKit's own file), mapped by
            :data:`MULTIPIE68_TO_BOSPHORUS` (17 labels).

    Raises:
        DataNotFoundError / LandmarkError: neither ids nor ``vertex_indices.json``.
    """
    from ...landmarks import Landmarks

    p = Path(npz_path)
    X = np.asarray(np.load(p)["neutral"], np.float64)
    if landmark_ids is None:
        vi = p.with_name("vertex_indices.json")
        if not vi.is_file():
            raise DataNotFoundError(
                f"no landmark ids for the ICT face: {vi} is missing. Put ICT-FaceKit's "
                "vertex_indices.json beside the .npz or pass landmark_ids={label: vertex id}."
            )
        mp = json.loads(vi.read_text()).get("idx_to_landmark_verts")
        if not isinstance(mp, list) or len(mp) != 68:
            raise LandmarkError(f"{vi}: 'idx_to_landmark_verts' is not the 68 Multi-PIE ids.")
        landmark_ids = {lab: int(mp[i]) for i, lab in MULTIPIE68_TO_BOSPHORUS.items()}
    names = list(landmark_ids)
    return Landmarks(names, X[[int(landmark_ids[n]) for n in names]])
