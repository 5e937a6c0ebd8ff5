"""The side convention check (:func:`check_side`): the subject's left is +x."""

from __future__ import annotations

from ..errors import LandmarkError
from .container import Landmarks
from .labels import MIRROR_PAIRS

__all__ = ["check_side"]


def check_side(landmarks: Landmarks) -> None:
    """Check the side convention: the subject's left is +x.

    Compares the x of each left/right pair; the four eye corners decide when present (both
    pairs must agree), otherwise all other available pairs (eyebrows, nose saddles, nose peaks,
    mouth corners, ear lobes) vote.

    Raises:
        LandmarkError: the input looks mirrored (left landmarks at smaller x than the right
            ones: a left-right flip, swapped labels, or a face looking along -z); the pairs
            disagree; or no left/right pair is present to decide.
    """
    eye_pairs = [p for p in MIRROR_PAIRS if "eye corner" in p[0]]
    other_pairs = [p for p in MIRROR_PAIRS if p not in eye_pairs]

    def diffs(pairs):
        out = []
        for left, right in pairs:
            if left in landmarks and right in landmarks:
                out.append((left, right, float(landmarks[left][0] - landmarks[right][0])))
        return out

    d = diffs(eye_pairs) or diffs(other_pairs)
    if not d:
        raise LandmarkError(
            "cannot check the left/right convention: no left/right landmark pair is present "
            "(need e.g. 'Outer left eye corner' and 'Outer right eye corner').",
            missing=tuple(n for pair in eye_pairs for n in pair if n not in landmarks),
        )
    detail = "; ".join(f"x({l}) - x({r}) = {v:+.2f} mm" for l, r, v in d)
    if all(v > 0 for _, _, v in d):
        return
    if all(v < 0 for _, _, v in d):
        raise LandmarkError(
            f"the landmarks look mirrored: the subject's left must be at +x, but the left "
            f"landmarks lie at smaller x than the right ones ({detail}). The input is probably "
            f"flipped left-right, has left/right labels swapped, or looks along -z. Fix it by "
            f"negating x of the whole scan and landmarks (Landmarks.mirrored()), by swapping "
            f"the labels, or by rotating the face 180 degrees about y so it looks along +z."
        )
    raise LandmarkError(
        f"inconsistent left/right landmarks ({detail}): some pairs have the left point at +x "
        f"and others at -x. Check the labels of these landmarks."
    )
