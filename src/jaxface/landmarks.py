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
"""

from __future__ import annotations

import difflib
import os
import re
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import cast

import numpy as np

from .atomic import write_text_atomic
from .errors import LandmarkError, ScanFormatError
from .mesh import check_input_file as _check_input_file

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
    "write_lm3",
    "attach_to_mesh",
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


# ---------------------------------------------------------------------------------------------
# container
# ---------------------------------------------------------------------------------------------


class Landmarks:
    """Named 3-D landmarks in mm (immutable).

    Names are stored in canonical form when recognised (:func:`canonical_label`); other labels
    are kept as given (whitespace collapsed). Lookup accepts any spelling variant.

    Attributes:
        names: ``(N,)`` tuple of labels.
        positions: ``(N, 3)`` float64 read-only array, mm.

    Args:
        names: N labels (unique after canonicalisation).
        positions: ``(N, 3)`` finite coordinates, mm.

    Raises:
        LandmarkError: wrong shapes, duplicated labels or non-finite positions.
    """

    __slots__ = ("names", "positions", "_index")

    def __init__(self, names: Iterable[str], positions):
        names = tuple(_normalise_name(n) for n in names)
        pos = np.array(positions, dtype=np.float64, copy=True)
        if pos.size == 0 and len(names) == 0:
            pos = pos.reshape(0, 3)
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] != len(names):
            raise LandmarkError(
                f"Landmarks needs N names and (N, 3) positions in mm; got {len(names)} names and "
                f"positions of shape {pos.shape}."
            )
        seen: dict[str, int] = {}
        dups = []
        for n in names:
            seen[n] = seen.get(n, 0) + 1
            if seen[n] == 2:
                dups.append(n)
        if dups:
            raise LandmarkError(
                f"duplicated landmark label(s) {dups} (after normalising spelling variants); "
                f"each landmark must appear once."
            )
        bad = [n for n, p in zip(names, pos) if not np.all(np.isfinite(p))]
        if bad:
            raise LandmarkError(
                f"landmark(s) {bad} have NaN/inf coordinates; leave missing landmarks out "
                f"instead of marking them with NaN."
            )
        pos.setflags(write=False)
        self.names = names
        self.positions = pos
        self._index = {n: i for i, n in enumerate(names)}

    # -------------------------------------------------------------- lookup
    def _find(self, name: str) -> int | None:
        key = _normalise_name(name)
        if key in self._index:
            return self._index[key]
        low = key.lower()
        for n, i in self._index.items():  # custom labels: case-insensitive
            if n.lower() == low:
                return i
        return None

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and self._find(name) is not None

    def __getitem__(self, name: str) -> np.ndarray:
        """``(3,)`` position (mm) of a landmark; any spelling variant of its label.

        Raises:
            LandmarkError: the landmark is absent (the message lists the close matches).
        """
        i = self._find(name)
        if i is None:
            close = difflib.get_close_matches(_normalise_name(name), self.names, n=3, cutoff=0.5)
            hint = f" Did you mean {close}?" if close else ""
            raise LandmarkError(
                f"landmark {name!r} not found among {len(self.names)} landmarks "
                f"{list(self.names)}.{hint}",
                missing=(_normalise_name(name),),
            )
        return self.positions[i]

    def get(self, name: str, default=None):
        """Position of ``name`` (mm) or ``default`` if absent."""
        i = self._find(name)
        return default if i is None else self.positions[i]

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self):
        return iter(self.names)

    def __repr__(self) -> str:
        return f"Landmarks({len(self.names)}: {', '.join(self.names[:4])}{', ...' if len(self) > 4 else ''})"

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Landmarks)
            and self.names == other.names
            and np.array_equal(self.positions, other.positions)
        )

    __hash__ = None  # type: ignore[assignment]

    # -------------------------------------------------------------- selections
    def missing(self, names: Iterable[str]) -> tuple[str, ...]:
        """The labels (normalised) among ``names`` that are absent."""
        if isinstance(names, str):
            names = (names,)
        return tuple(_normalise_name(n) for n in names if self._find(n) is None)

    def require(self, names: Iterable[str]) -> Landmarks:
        """The landmarks ``names`` in that order; raise if any is absent.

        Raises:
            LandmarkError: listing *every* missing name (``error.missing``), not just the first.
        """
        if isinstance(names, str):
            names = (names,)
        names = tuple(names)
        miss = self.missing(names)
        if miss:
            raise LandmarkError(
                f"{len(miss)} required landmark(s) missing: {list(miss)}. Present: "
                f"{list(self.names)}. Add them (e.g. pick them on the mesh) or choose a method "
                f"that needs fewer landmarks.",
                missing=miss,
            )
        idx = [cast(int, self._find(n)) for n in names]  # all present: checked above
        return Landmarks([self.names[i] for i in idx], self.positions[idx])

    def subset(self, names: Iterable[str]) -> Landmarks:
        """The landmarks among ``names`` that are present, in the order of ``names``
        (absent ones are skipped; use :meth:`require` to insist)."""
        if isinstance(names, str):
            names = (names,)
        idx = [i for i in (self._find(n) for n in names) if i is not None]
        return Landmarks([self.names[i] for i in idx], self.positions[idx])

    def array(self, names: Iterable[str]) -> np.ndarray:
        """``(len(names), 3)`` positions, mm, in the given order (all must be present)."""
        return np.array(self.require(names).positions)

    def to_dict(self) -> dict[str, np.ndarray]:
        """``{label: (3,) position in mm}`` (copies)."""
        return {n: np.array(p) for n, p in zip(self.names, self.positions)}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> Landmarks:
        """From ``{label: (3,) position in mm}``."""
        names = list(d.keys())
        pos = np.array([np.asarray(d[n], dtype=np.float64).reshape(3) for n in names]).reshape(
            -1, 3
        )
        return cls(names, pos)

    def with_positions(self, positions) -> Landmarks:
        """Same labels, new ``(N, 3)`` positions (mm)."""
        return Landmarks(self.names, positions)

    def transformed(self, rotation=None, translation=None, scale: float = 1.0) -> Landmarks:
        """``p' = scale * R p + t`` for every landmark (``R`` (3, 3), ``t`` (3,) mm)."""
        p = self.positions * float(scale)
        if rotation is not None:
            p = p @ np.asarray(rotation, dtype=np.float64).T
        if translation is not None:
            p = p + np.asarray(translation, dtype=np.float64)
        return Landmarks(self.names, p)

    def mirrored(self, swap_labels: bool = True) -> Landmarks:
        """Reflect through the x = 0 plane (x -> -x). With ``swap_labels`` the left/right labels
        are exchanged too (the physically mirrored face, correctly labelled again); without,
        the result is what a mirrored input looks like (and fails :func:`check_side`)."""
        p = np.array(self.positions)
        p[:, 0] = -p[:, 0]
        names = list(self.names)
        if swap_labels:
            swap = {}
            for left, right in MIRROR_PAIRS:
                swap[left], swap[right] = right, left
            names = [swap.get(n, n) for n in names]
        return Landmarks(names, p)

    def on_mesh(self, mesh, *, max_distance: float | None = None):
        """Attach to a mesh as surface points: see :func:`attach_to_mesh`."""
        return attach_to_mesh(self, mesh, max_distance=max_distance)


# ---------------------------------------------------------------------------------------------
# side convention
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# .lm3 I/O
# ---------------------------------------------------------------------------------------------

_COUNT_RE = re.compile(r"^\s*(\d+)\s+landmarks?\s*:?\s*$", re.IGNORECASE)


def read_lm3(path) -> Landmarks:
    """Read a Bosphorus ``.lm3`` landmark file (coordinates in mm).

    Labels are canonicalised (spelling variants accepted). A misspelled label close to one
    known label (:func:`fuzzy_label`) is read as that label with a
    :class:`LandmarkLabelWarning`; other unknown labels are kept as written (custom labels)
    and listed in one :class:`LandmarkLabelWarning`.

    Raises:
        DataNotFoundError: the file does not exist.
        ScanFormatError: no ``N landmarks:`` line, truncated file (fewer than N label /
            coordinate pairs), more landmarks after the N announced (the header count is
            wrong: nothing is silently dropped), a coordinate line that is not three finite
            numbers, or a duplicated label; the message names the file and line number.
    """
    path = Path(os.fspath(path))
    _check_input_file(path, "landmark file")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        text = path.read_bytes().decode("latin-1")
    lines = text.splitlines()
    i = 0
    n = None
    while i < len(lines):
        s = lines[i].strip()
        i += 1
        if not s or s.startswith("#"):
            continue
        m = _COUNT_RE.match(s)
        if m is None:
            raise ScanFormatError(
                f"{path}, line {i}: expected the 'N landmarks:' line, found {s!r}. Is this a "
                f"Bosphorus .lm3 file?"
            )
        n = int(m.group(1))
        break
    if n is None:
        raise ScanFormatError(f"{path}: no 'N landmarks:' line found (empty or truncated file).")
    names: list[str] = []
    pos: list[list[float]] = []
    seen: dict[str, int] = {}
    fixed: list[str] = []
    unknown: list[str] = []
    while len(names) < n:
        # label line (skip blank lines between entries)
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise ScanFormatError(
                f"{path}: truncated: the header announces {n} landmarks but the file ends after "
                f"{len(names)} (line {len(lines)})."
            )
        label = lines[i].strip()
        label_line = i + 1
        i += 1
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise ScanFormatError(
                f"{path}, line {label_line}: truncated: landmark {label!r} has no coordinate "
                f"line ({len(names)} of {n} landmarks read)."
            )
        parts = lines[i].split()
        try:
            xyz = [float(x) for x in parts]
        except ValueError:
            xyz = []
        if len(xyz) != 3 or not np.all(np.isfinite(xyz)):
            raise ScanFormatError(
                f"{path}, line {i + 1}: bad coordinates {lines[i].strip()!r} for landmark "
                f"{label!r}: expected three finite numbers 'x y z' in mm."
            )
        i += 1
        if canonical_label(label) is None:
            fz = fuzzy_label(label)
            if fz is not None:
                fixed.append(f"{label!r} -> {fz[0]!r} (line {label_line})")
                label = fz[0]
            else:
                unknown.append(label)
        key = _normalise_name(label)
        if key in seen:
            raise ScanFormatError(
                f"{path}, line {label_line}: landmark {label!r} appears twice (first at line "
                f"{seen[key]})."
            )
        seen[key] = label_line
        names.append(label)
        pos.append(xyz)
    extra = [ln.strip() for ln in lines[i:] if ln.strip() and not ln.strip().startswith("#")]
    if extra:
        raise ScanFormatError(
            f"{path}: the header announces {n} landmarks but {len(extra)} more non-empty "
            f"line(s) follow them (about {len(extra) // 2} more landmarks, from line "
            f"{i + 1}: {extra[0]!r}). Correct the count in the 'N landmarks:' line."
        )
    if fixed:
        warnings.warn(
            f"{path}: misspelled landmark label(s) read as the closest Bosphorus label: "
            + "; ".join(fixed)
            + ". Correct the file to silence this warning.",
            LandmarkLabelWarning,
            stacklevel=2,
        )
    if unknown:
        warnings.warn(
            f"{path}: unknown landmark label(s) {unknown}, kept as custom labels that jaxface "
            f"does not use; the Bosphorus labels are {list(BOSPHORUS_LABELS)}.",
            LandmarkLabelWarning,
            stacklevel=2,
        )
    return Landmarks(names, np.asarray(pos, dtype=np.float64).reshape(-1, 3))


def write_lm3(
    path, landmarks: Landmarks, comment: str = "landmarks written by jaxface (mm)"
) -> None:
    """Write landmarks as a Bosphorus ``.lm3`` file (coordinates in mm, 6 decimals).

    Args:
        path: destination file.
        landmarks: the :class:`Landmarks` to write (canonical labels are written).
        comment: text for the ``#`` comment header (may span several lines).
    """
    path = Path(os.fspath(path))
    out = [f"# {c}".rstrip() for c in str(comment).splitlines()] or ["#"]
    out.append("")
    out.append(f"{len(landmarks)} landmarks:")
    for name, p in zip(landmarks.names, landmarks.positions):
        out.append(name)
        out.append(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}")
    write_text_atomic(path, "\n".join(out) + "\n")


# ---------------------------------------------------------------------------------------------
# attaching to a mesh
# ---------------------------------------------------------------------------------------------


def attach_to_mesh(landmarks: Landmarks, mesh, *, max_distance: float | None = None):
    """Attach landmarks to a mesh as surface points (closest-point projection).

    Args:
        landmarks: the landmarks (mm).
        mesh: a :class:`jaxface.mesh.TriMesh` (mm).
        max_distance: if given (mm), raise when a landmark is farther than this from the
            surface (a landmark set that does not belong to this mesh, or wrong units).

    Returns:
        ``(SurfacePoints (N,), distances (N,) mm)`` in the order of ``landmarks.names``.

    Raises:
        LandmarkError: a landmark lies farther than ``max_distance`` from the surface.
    """
    sp, dist = mesh.closest_points(landmarks.positions)
    if max_distance is not None:
        far = [(n, float(d)) for n, d in zip(landmarks.names, dist) if d > max_distance]
        if far:
            listed = ", ".join(f"{n!r} ({d:.2f} mm)" for n, d in far)
            raise LandmarkError(
                f"{len(far)} landmark(s) lie more than {max_distance:g} mm from the mesh "
                f"surface: {listed}. Are the landmarks for this mesh, in the same units and "
                f"frame?",
                missing=tuple(n for n, _ in far),
            )
    return sp, dist
