"""Bosphorus ``.lm2`` files: 2D landmarks in texture pixels (:class:`ImageLandmarks`,
:func:`read_lm2`, :func:`write_lm2`; layout in :mod:`jaxface.io.bosphorus`), and the label
normalisation shared by the scan modules."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...atomic import write_text_atomic
from ...errors import LandmarkError, ScanFormatError
from ...landmarks import canonical_label
from ...mesh import check_input_file

__all__ = ["ImageLandmarks", "read_lm2", "write_lm2"]


@dataclass(frozen=True)
class ImageLandmarks:
    """Landmarks in texture-image pixels, as stored in ``.lm2`` files.

    Attributes:
        names: labels as written in the file (``N`` strings).
        pixels: (N, 2) float64, ``[column, row]`` in pixels, origin at the image's top-left.
    """

    names: tuple[str, ...]
    pixels: np.ndarray

    def __post_init__(self):
        px = np.asarray(self.pixels, dtype=np.float64).reshape(-1, 2)
        if px.shape[0] != len(self.names):
            raise LandmarkError(
                f"{len(self.names)} landmark names but {px.shape[0]} pixel positions; give one "
                f"(column, row) pair per name."
            )
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "pixels", px)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, name: str) -> np.ndarray:
        """Pixel position (2,) of a landmark, matched by label (spelling variants tolerated)."""
        key = _canon(name)
        for n, p in zip(self.names, self.pixels):
            if _canon(n) == key:
                return p.copy()
        raise LandmarkError(f"landmark {name!r} not in {list(self.names)}", missing=(name,))


def _canon(name: str) -> str:
    """Canonical Bosphorus label (:func:`jaxface.landmarks.canonical_label`), else normalised text."""
    c = canonical_label(name)
    return c if c is not None else " ".join(str(name).lower().replace("_", " ").split())


def read_lm2(path: str | Path) -> ImageLandmarks:
    """Read a Bosphorus ``.lm2`` file (2D landmarks in texture pixels; layout in the module doc).

    Raises:
        DataNotFoundError: the file does not exist.
        ScanFormatError: missing headers, a count that does not match the labels or
            coordinates, unparsable or non-finite coordinates (message names the file and line).
    """
    path = Path(path)
    check_input_file(path, "landmark file")
    raw = path.read_text(encoding="utf-8", errors="replace").splitlines()
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(raw)]
    lines = [(i, ln) for i, ln in lines if ln and not ln.startswith("#")]

    def bad(why: str, lineno: int | None = None):
        where = f" (line {lineno})" if lineno else ""
        return ScanFormatError(
            f"{path}{where}: malformed .lm2 file: {why}. Expected '<N> landmarks:', "
            f"'Labels:', N label lines, '2D Image coordinates:', N 'x y' lines."
        )

    if not lines:
        raise bad("no content")
    lineno, head = lines.pop(0)
    m = re.match(r"^(\d+)\s+landmarks?\s*:?\s*$", head, re.IGNORECASE)
    if m is None:
        raise bad(f"first line {head!r} is not '<N> landmarks:'", lineno)
    n = int(m.group(1))
    if not lines or not re.match(r"^labels\s*:?$", lines[0][1], re.IGNORECASE):
        raise bad("missing 'Labels:' header", lines[0][0] if lines else None)
    lines.pop(0)
    if len(lines) < n:
        raise bad(f"file ends after {len(lines)} of {n} labels")
    names = [ln for _, ln in lines[:n]]
    lines = lines[n:]
    if not lines or not re.match(r"^2d\s+image\s+coordinates\s*:?$", lines[0][1], re.IGNORECASE):
        found = lines[0][1] if lines else "end of file"
        raise bad(
            f"expected '2D Image coordinates:' after {n} labels, found {found!r}",
            lines[0][0] if lines else None,
        )
    lines.pop(0)
    if len(lines) < n:
        raise bad(f"file ends after {len(lines)} of {n} coordinate lines")
    pix = np.empty((n, 2))
    for k, (lineno, ln) in enumerate(lines[:n]):
        toks = ln.split()
        try:
            pix[k] = [float(toks[0]), float(toks[1])]
        except (ValueError, IndexError):
            raise bad(f"cannot read 'x y' from {ln!r}", lineno) from None
        if not np.all(np.isfinite(pix[k])):
            raise bad(f"non-finite coordinate {ln!r} for {names[k]!r}", lineno)
    if len(lines) > n:
        raise bad(f"{len(lines) - n} extra line(s) after the {n} coordinates", lines[n][0])
    return ImageLandmarks(tuple(names), pix)


def write_lm2(
    path: str | Path,
    landmarks: ImageLandmarks,
    comment: str = "2D landmarks in texture pixels (column, row), written by jaxface",
) -> None:
    """Write ``.lm2`` (layout in the module doc); coordinates with 3 decimals (pixels)."""
    if not isinstance(landmarks, ImageLandmarks):
        raise TypeError("write_lm2 expects an ImageLandmarks")
    if not np.all(np.isfinite(landmarks.pixels)):
        bad = [n for n, p in zip(landmarks.names, landmarks.pixels) if not np.all(np.isfinite(p))]
        raise LandmarkError(f"cannot write non-finite pixel positions for {bad}", missing=bad)
    out = [f"# {c}" for c in comment.splitlines() or [""]]
    out += ["", f"{len(landmarks)} landmarks:", "Labels:"]
    out += list(landmarks.names)
    out.append("2D Image coordinates:")
    out += [f"{x:.3f} {y:.3f}" for x, y in landmarks.pixels]
    write_text_atomic(path, "\n".join(out) + "\n")
