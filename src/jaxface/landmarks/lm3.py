"""Bosphorus ``.lm3`` landmark files (labels and ``x y z`` in mm): :func:`read_lm3`,
:func:`write_lm3`, and :func:`lm3_is_detected` for files that ``jaxface landmarks`` wrote."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..atomic import write_text_atomic
from ..errors import ScanFormatError
from ..mesh import check_input_file as _check_input_file
from .container import Landmarks
from .labels import (
    BOSPHORUS_LABELS,
    LandmarkLabelWarning,
    _normalise_name,
    canonical_label,
    fuzzy_label,
)

__all__ = ["DETECTED_LM3_HEADER", "lm3_is_detected", "read_lm3", "write_lm3"]

#: the first comment line of a ``.lm3`` written by ``jaxface landmarks`` (detected landmarks)
DETECTED_LM3_HEADER = "landmarks detected automatically by jaxface"


def lm3_is_detected(path) -> bool:
    """True when the ``.lm3`` at ``path`` was written by ``jaxface landmarks``: its comment
    header begins with :data:`DETECTED_LM3_HEADER`. Such landmarks were detected from the
    scan's surface, and the fit treats them so (``Scan.landmarks_detected``)."""
    with open(os.fspath(path), "rb") as fh:
        head = fh.read(len(DETECTED_LM3_HEADER) + 16).decode("utf-8-sig", errors="replace")
    return head.lstrip("#").strip().startswith(DETECTED_LM3_HEADER)


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
