"""Landmark labels: the 24 Bosphorus labels, the face, stable and mirror sets, the MPEG-4 FDP
table, and label normalisation (exact variants, :func:`canonical_label`; close spellings,
:func:`fuzzy_label`)."""

from __future__ import annotations

import difflib
import re

__all__ = [
    "BOSPHORUS_LABELS",
    "FACE_LABELS",
    "STABLE_LABELS",
    "MIRROR_PAIRS",
    "MPEG4_FDP",
    "canonical_label",
    "fuzzy_label",
    "LandmarkLabelWarning",
    "FUZZY_MIN_RATIO",
    "FUZZY_MARGIN",
]

#: the 24 canonical Bosphorus landmark labels (22 face landmarks + 2 ear lobes), in the
#: Bosphorus file order
BOSPHORUS_LABELS: tuple[str, ...] = (
    "Outer left eyebrow",
    "Middle left eyebrow",
    "Inner left eyebrow",
    "Inner right eyebrow",
    "Middle right eyebrow",
    "Outer right eyebrow",
    "Outer left eye corner",
    "Inner left eye corner",
    "Inner right eye corner",
    "Outer right eye corner",
    "Nose saddle left",
    "Nose saddle right",
    "Left nose peak",
    "Nose tip",
    "Right nose peak",
    "Left mouth corner",
    "Upper lip outer middle",
    "Right mouth corner",
    "Upper lip inner middle",
    "Lower lip inner middle",
    "Lower lip outer middle",
    "Chin middle",
    "Left ear lobe",
    "Right ear lobe",
)

#: the 22 face landmarks (all but the ear lobes), as found in Bosphorus ``.lm3`` files
FACE_LABELS: tuple[str, ...] = BOSPHORUS_LABELS[:22]

#: landmarks stable under expression, for rigid alignment: the four eye corners, the two nose
#: saddle points and the nose tip (never align on mouth or chin points)
STABLE_LABELS: tuple[str, ...] = (
    "Outer left eye corner",
    "Inner left eye corner",
    "Inner right eye corner",
    "Outer right eye corner",
    "Nose saddle left",
    "Nose saddle right",
    "Nose tip",
)

#: (left, right) label pairs that swap under a left-right mirror
MIRROR_PAIRS: tuple[tuple[str, str], ...] = (
    ("Outer left eyebrow", "Outer right eyebrow"),
    ("Middle left eyebrow", "Middle right eyebrow"),
    ("Inner left eyebrow", "Inner right eyebrow"),
    ("Outer left eye corner", "Outer right eye corner"),
    ("Inner left eye corner", "Inner right eye corner"),
    ("Nose saddle left", "Nose saddle right"),
    ("Left nose peak", "Right nose peak"),
    ("Left mouth corner", "Right mouth corner"),
    ("Left ear lobe", "Right ear lobe"),
)

#: canonical label -> MPEG-4 Facial Definition Point (ISO/IEC 14496-2 Annex C; the FDP set the
#: thesis uses for skull landmarks and motion cloning). "Left/right" are the subject's.
#: Choices where the correspondence is approximate: the Bosphorus nose saddles (either side of
#: the nasal root) -> 9.7/9.6 "left/right upper edge of nose bone"; the nose peaks (outermost
#: points of the alae) -> 9.1/9.2 "left/right nostril border"; the chin middle -> 2.10 "chin
#: boss"; the ear lobes -> 10.5/10.6 "bottom of left/right ear lobe".
MPEG4_FDP: dict[str, str] = {
    "Outer left eyebrow": "4.5",  # left corner of left eyebrow
    "Middle left eyebrow": "4.3",  # uppermost point of the left eyebrow
    "Inner left eyebrow": "4.1",  # right corner of left eyebrow
    "Inner right eyebrow": "4.2",  # left corner of right eyebrow
    "Middle right eyebrow": "4.4",  # uppermost point of the right eyebrow
    "Outer right eyebrow": "4.6",  # right corner of right eyebrow
    "Outer left eye corner": "3.7",  # left corner of left eye
    "Inner left eye corner": "3.11",  # right corner of left eye
    "Inner right eye corner": "3.8",  # left corner of right eye
    "Outer right eye corner": "3.12",  # right corner of right eye
    "Nose saddle left": "9.7",  # left upper edge of nose bone
    "Nose saddle right": "9.6",  # right upper edge of nose bone
    "Left nose peak": "9.1",  # left nostril border
    "Nose tip": "9.3",
    "Right nose peak": "9.2",  # right nostril border
    "Left mouth corner": "8.3",  # left corner of outer lip contour
    "Upper lip outer middle": "8.1",  # middle point of outer upper lip contour
    "Right mouth corner": "8.4",  # right corner of outer lip contour
    "Upper lip inner middle": "2.2",  # middle point of inner upper lip contour
    "Lower lip inner middle": "2.3",  # middle point of inner lower lip contour
    "Lower lip outer middle": "8.2",  # middle point of outer lower lip contour
    "Chin middle": "2.10",  # chin boss
    "Left ear lobe": "10.5",  # bottom of left ear lobe
    "Right ear lobe": "10.6",  # bottom of right ear lobe
}

_FDP_TO_LABEL = {v: k for k, v in MPEG4_FDP.items()}

# ---------------------------------------------------------------------------------------------
# label normalisation
# ---------------------------------------------------------------------------------------------

_WORD_MAP = {
    "l": "left",
    "lt": "left",
    "r": "right",
    "rt": "right",
    "earlobe": "ear lobe",
    "earlobes": "ear lobe",
    "lobe": "lobe",
    "lobule": "lobe",
    "eyebrow": "eyebrow",
    "brow": "eyebrow",
    "eyecorner": "eye corner",
    "mid": "middle",
    "centre": "middle",
    "center": "middle",
    "lips": "lip",
    "corners": "corner",
    "nosetip": "nose tip",
}
_STOP = {"of", "the", "point", "pt", "landmark"}


def _tokens(text: str) -> tuple[str, ...]:
    s = re.sub(r"(?<=[a-z])(?=[A-Z])", " ", str(text).strip()).lower()
    s = re.sub(r"[^a-z0-9.]+", " ", s)
    s = s.replace("eye brow", "eyebrow").replace("ear lobe", "earlobe")
    words: list[str] = []
    for w in s.split():
        w = w.strip(".")
        if not w or w in _STOP:
            continue
        words.extend(_WORD_MAP.get(w, w).split())
    return tuple(words)


def _key(text: str) -> tuple[str, ...]:
    return tuple(sorted(_tokens(text)))


_CANON_BY_KEY: dict[tuple[str, ...], str] = {_key(lbl): lbl for lbl in BOSPHORUS_LABELS}
assert len(_CANON_BY_KEY) == len(BOSPHORUS_LABELS)  # bag-of-words keys are unambiguous


def canonical_label(text: str) -> str | None:
    """The canonical Bosphorus label for a spelling variant, or None if not recognised.

    Tolerates case, spacing, punctuation, word order, "L"/"R" abbreviations, "eye brow" /
    "eyebrow", every ear-lobe wording that contains the words ear + lobe (or "earlobe") and a
    side, and the MPEG-4 FDP name (e.g. "9.3" -> "Nose tip").

    >>> canonical_label("NOSE_TIP"), canonical_label("left earlobe"), canonical_label("2.10")
    ('Nose tip', 'Left ear lobe', 'Chin middle')
    """
    if not isinstance(text, str):
        return None
    raw = text.strip()
    if raw in _FDP_TO_LABEL:
        return _FDP_TO_LABEL[raw]
    toks = _tokens(raw)
    hit = _CANON_BY_KEY.get(tuple(sorted(toks)))
    if hit is not None:
        return hit
    ts = set(toks)
    if "ear" in ts and "lobe" in ts:
        if "left" in ts and "right" not in ts:
            return "Left ear lobe"
        if "right" in ts and "left" not in ts:
            return "Right ear lobe"
    return None


#: Least similarity (:class:`difflib.SequenceMatcher` ratio of the lower-case, word-sorted
#: spellings) for a misspelled label to be read as a known one. One wrong, added or missing
#: letter in a label of 8 or more letters scores at least 0.88 ("Nose tipp" -> "Nose tip":
#: 0.94); two different labels of the same side score at most 0.86 ("Inner right eye
#: corner" / "Outer right eye corner"), which is why a match must also beat the runner-up by
#: :data:`FUZZY_MARGIN`.
FUZZY_MIN_RATIO = 0.85

#: The best match must beat the second best by this much (ratio), else the label is unknown.
FUZZY_MARGIN = 0.04


class LandmarkLabelWarning(UserWarning):
    """A landmark label was misspelled and read as the closest known label, or is unknown
    (kept as a custom label that jaxface does not use)."""


def _sides(words) -> set[str]:
    return {w for w in words if w in ("left", "right")}


def fuzzy_label(text: str) -> tuple[str, float] | None:
    """The Bosphorus label a misspelled ``text`` most likely means, with its similarity in
    [0, 1], or None when no label is close enough or two are equally close.

    Exact spelling variants go through :func:`canonical_label` first. The candidate must
    name the same side (left/right words) as ``text``, reach :data:`FUZZY_MIN_RATIO`, and
    beat the next candidate by :data:`FUZZY_MARGIN`.

    >>> fuzzy_label("Nose tipp")[0]
    'Nose tip'
    """
    exact = canonical_label(text)
    if exact is not None:
        return exact, 1.0
    toks = _tokens(text)
    if not toks:
        return None
    words = " ".join(sorted(toks))
    side = _sides(toks)
    scores = []
    for lbl in BOSPHORUS_LABELS:
        ref = _key(lbl)
        if _sides(ref) != side and side:
            continue
        scores.append((difflib.SequenceMatcher(None, words, " ".join(ref)).ratio(), lbl))
    scores.sort(reverse=True)
    if not scores or scores[0][0] < FUZZY_MIN_RATIO:
        return None
    if len(scores) > 1 and scores[0][0] - scores[1][0] < FUZZY_MARGIN:
        return None
    if _sides(_key(scores[0][1])) != side:  # "Nose tipp" has no side; a sided label needs one
        return None
    return scores[0][1], float(scores[0][0])


def _normalise_name(name: str) -> str:
    """Canonical label if recognised, otherwise the stripped text (custom labels allowed)."""
    c = canonical_label(name)
    return c if c is not None else " ".join(str(name).split())
