"""Bosphorus scan-name parsing: ``bsXXX_<class>_<code>_<n>`` -> :class:`ScanInfo` (subject,
class, AU codes or emotion, pose/occlusion flags)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ...errors import ScanFormatError

__all__ = ["AUCode", "ScanInfo", "parse_scan_name", "EMOTION_AUS"]

_CLASS_DESCRIPTIONS = {
    "N": ("neutral", "neutral face"),
    "LFAU": ("lower_au", "lower-face action unit"),
    "UFAU": ("upper_au", "upper-face action unit"),
    "CAU": ("au_combination", "combination of action units"),
    "E": ("emotion", "emotional expression"),
    "YR": ("pose_yaw", "head yaw rotation (pose)"),
    "PR": ("pose_pitch", "head pitch rotation (pose)"),
    "CR": ("pose_cross", "cross (yaw + pitch) head rotation (pose)"),
    "O": ("occlusion", "occlusion"),
    "IGN": ("ignored", "scan marked to be ignored"),
}

#: Ekman/Friesen prototype AU sets of the six Bosphorus emotions (facial-anatomy notes).
EMOTION_AUS = {
    "HAPPY": (6, 12),
    "SADNESS": (1, 4, 15),
    "SURPRISE": (1, 2, 5, 26),
    "FEAR": (1, 2, 4, 5, 20, 26),
    "ANGER": (4, 5, 7, 23),
    "DISGUST": (9, 15, 16),
}
_EMOTION_ALIASES = {
    "HAPPINESS": "HAPPY",
    "SAD": "SADNESS",
    "SURPRISED": "SURPRISE",
    "ANGRY": "ANGER",
    "DISGUSTED": "DISGUST",
    "AFRAID": "FEAR",
}


@dataclass(frozen=True)
class AUCode:
    """One action unit named in a scan code.

    Attributes:
        au: FACS action-unit number (e.g. 12).
        side: ``"L"`` (subject's left, +x), ``"R"`` (subject's right, -x) or ``None``
            (bilateral).
        modifier: any further letters of the code kept verbatim (e.g. ``"W"`` in ``12LW``,
            whose meaning the Bosphorus documentation we have does not state).
    """

    au: int
    side: str | None = None
    modifier: str = ""

    def __str__(self) -> str:
        return f"AU{self.au}{self.side or ''}{self.modifier}"


@dataclass(frozen=True)
class ScanInfo:
    """What a Bosphorus file name ``bsXXX_<class>_<code>_<n>`` says about a scan.

    Attributes:
        stem: the parsed file stem.
        subject: ``"bsXXX"``.
        kind: the class token: ``N``, ``LFAU``, ``UFAU``, ``CAU``, ``E``, ``YR``, ``PR``,
            ``CR``, ``O`` or ``IGN``.
        category: readable category (``"neutral"``, ``"lower_au"``, ``"upper_au"``,
            ``"au_combination"``, ``"emotion"``, ``"pose_yaw"``, ``"pose_pitch"``,
            ``"pose_cross"``, ``"occlusion"``, ``"ignored"``).
        code: the code token (``"N"``, ``"12L"``, ``"A22A25"``, ``"HAPPY"``, ``"R10"``, ...).
        index: the trailing sample number.
        aus: action units named by the code (for emotions: the prototype AU set).
        emotion: the emotion name for class ``E``.
        is_pose: head pose scan (YR, PR, CR): not frontal, alignment must be checked.
        is_occlusion: occluded face (O): expect missing regions and landmarks.
    """

    stem: str
    subject: str
    kind: str
    category: str
    code: str
    index: int
    aus: tuple[AUCode, ...] = ()
    emotion: str | None = None
    is_pose: bool = False
    is_occlusion: bool = False

    @property
    def is_neutral(self) -> bool:
        return self.kind == "N"

    @property
    def au_numbers(self) -> tuple[int, ...]:
        """The distinct AU numbers, in order of appearance."""
        return tuple(dict.fromkeys(a.au for a in self.aus))

    def describe(self) -> str:
        """One readable line, e.g. ``bs000 lower-face action unit 12L: AU12L``."""
        desc = _CLASS_DESCRIPTIONS.get(self.kind, (self.category, self.category))[1]
        parts = [f"{self.subject} {desc} {self.code}"]
        if self.aus:
            parts.append(("prototype " if self.emotion else "") + "+".join(map(str, self.aus)))
        if self.is_pose:
            parts.append("POSE scan: not frontal")
        if self.is_occlusion:
            parts.append("OCCLUSION scan: parts of the face hidden")
        return ": ".join(parts)


_NAME_RE = re.compile(r"^(bs\d+)_([A-Za-z]+)_([A-Za-z0-9]+(?:_[A-Za-z0-9]+)*?)_(\d+)$")
_AU_SINGLE_RE = re.compile(r"^(\d+)([LR]?)([A-Za-z]*)$", re.IGNORECASE)
_AU_COMBO_RE = re.compile(r"A(\d+)([A-Za-z]*?)(?=A\d|$)", re.IGNORECASE)


def _parse_au(number: str, letters: str) -> AUCode:
    letters = letters.upper()
    side = None
    if letters[:1] in ("L", "R"):
        side, letters = letters[0], letters[1:]
    return AUCode(int(number), side, letters)


def parse_scan_name(name: str | Path, *, strict: bool = False) -> ScanInfo | None:
    """Parse a Bosphorus scan name ``bsXXX_<class>_<code>_<n>`` (any extension ignored).

    Examples: ``bs000_N_N_0`` (neutral), ``bs000_LFAU_12L_0`` (AU12, left side),
    ``bs000_UFAU_4_0``, ``bs000_CAU_A22A25_0`` (AU22 + AU25), ``bs000_E_SURPRISE_0``
    (emotion; ``aus`` holds the prototype set 1+2+5+26), ``bs000_YR_R10_0`` (pose, yaw),
    ``bs000_O_GLASSES_0`` (occlusion).

    Args:
        name: file name or path.
        strict: raise :class:`ScanFormatError` instead of returning ``None`` when the name
            does not follow the pattern or the class is unknown.

    Returns:
        :class:`ScanInfo`, or ``None`` for a name that is not a Bosphorus name.
    """
    stem = Path(str(name)).name
    for suffix in (".truth.ply", ".bnt", ".lm3", ".lm2", ".ply", ".obj", ".png"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break

    def fail(why: str):
        if strict:
            raise ScanFormatError(
                f"{name}: cannot parse the scan name ({why}); expected bsXXX_<class>_<code>_<n> "
                f"with class N, LFAU, UFAU, CAU, E, YR, PR, CR or O, e.g. bs000_LFAU_12L_0."
            )
        return None

    m = _NAME_RE.match(stem)
    if m is None:
        return fail("pattern not matched")
    subject, kind, code, index = m.group(1), m.group(2).upper(), m.group(3), int(m.group(4))
    if kind not in _CLASS_DESCRIPTIONS:
        return fail(f"unknown class {kind!r}")
    category = _CLASS_DESCRIPTIONS[kind][0]
    aus: list[AUCode] = []
    emotion = None
    if kind == "N":
        if code.upper() != "N":
            return fail(f"neutral scans have code N, got {code!r}")
    elif kind in ("LFAU", "UFAU"):
        am = _AU_SINGLE_RE.match(code)
        if am is None:
            return fail(f"AU code {code!r} is not <number>[L|R][modifier]")
        aus.append(_parse_au(am.group(1), am.group(2) + am.group(3)))
    elif kind == "CAU":
        parts = _AU_COMBO_RE.findall(code)
        if not parts or "".join(f"A{n}{s}" for n, s in parts).upper() != code.upper():
            return fail(f"AU combination {code!r} is not A<n>[letters]A<n>...")
        aus.extend(_parse_au(n, s) for n, s in parts)
    elif kind == "E":
        emo = _EMOTION_ALIASES.get(code.upper(), code.upper())
        emotion = emo
        aus.extend(AUCode(a) for a in EMOTION_AUS.get(emo, ()))
    return ScanInfo(
        stem=stem,
        subject=subject,
        kind=kind,
        category=category,
        code=code,
        index=index,
        aus=tuple(aus),
        emotion=emotion,
        is_pose=kind in ("YR", "PR", "CR"),
        is_occlusion=kind == "O",
    )
