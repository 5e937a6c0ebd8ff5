"""Units at the mesh file boundary: millimetres per unit, the plausible-size check of a
loaded mesh, and the readable-input-file check."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DataNotFoundError, InputPathError, UnitsError

__all__ = [
    "check_input_file",
    "unit_scale",
    "check_plausible_size",
    "UNIT_SCALE",
    "PLAUSIBLE_SIZE_MM",
]

#: millimetres per unit
UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_UNIT_ALIASES = {
    "mm": "mm",
    "millimetre": "mm",
    "millimetres": "mm",
    "millimeter": "mm",
    "millimeters": "mm",
    "cm": "cm",
    "centimetre": "cm",
    "centimetres": "cm",
    "centimeter": "cm",
    "centimeters": "cm",
    "m": "m",
    "metre": "m",
    "metres": "m",
    "meter": "m",
    "meters": "m",
}

#: default plausible range (mm) of the largest bounding-box extent of a loaded mesh. A human
#: head is ~150-300 mm, a face scan ~120-250 mm; the range is wide enough for skull parts and
#: teeth (the ArtiSynth hyoid is ~45 mm) and still catches a factor-10/1000 unit mistake on a
#: face or head.
PLAUSIBLE_SIZE_MM = (30.0, 600.0)


def check_input_file(path, what: str = "input file") -> Path:
    """``path`` as a :class:`Path` if it is a readable file.

    Raises:
        DataNotFoundError: nothing exists at ``path``.
        InputPathError: ``path`` is a folder (or another non-file), or it cannot be read.
    """
    p = Path(os.fspath(path))
    if p.is_dir():
        raise InputPathError(f"{what} {p} is a folder, not a file; give the path of the file.")
    if not p.exists():
        hint = ""
        if p.parent.exists() and not p.parent.is_dir():
            hint = f" ({p.parent} is a file, not a folder)"
        raise DataNotFoundError(f"{what} not found: {p}{hint}.")
    if not p.is_file():
        raise InputPathError(f"{what} {p} is not a regular file; give the path of a file.")
    if not os.access(p, os.R_OK):
        raise InputPathError(f"{what} {p} cannot be read (permission denied).")
    return p


def unit_scale(units: str) -> float:
    """Millimetres per unit for ``units`` in {"mm", "cm", "m"} (long names accepted);
    raises :class:`UnitsError` for anything else."""
    key = _UNIT_ALIASES.get(str(units).strip().lower()) if isinstance(units, str) else None
    if key is None:
        raise UnitsError(
            f"unknown unit {units!r}: use one of 'mm', 'cm', 'm' (the unit the file's "
            f"coordinates are in; jaxface converts to millimetres)."
        )
    return UNIT_SCALE[key]


def check_plausible_size(
    vertices_mm, units: str, *, source: str = "mesh", size_range=PLAUSIBLE_SIZE_MM
) -> None:
    """Raise :class:`UnitsError` if the largest bounding-box extent (mm, after conversion from
    ``units``) is outside ``size_range`` (mm), with advice on which unit would fit.

    Args:
        vertices_mm: ``(V, 3)`` positions already converted to mm.
        units: the unit the caller declared (used in the message).
        source: what to call the data in the message (e.g. the file name).
        size_range: ``(lo, hi)`` in mm; ``None`` disables the check.
    """
    if size_range is None:
        return
    v = np.asarray(vertices_mm, dtype=np.float64)
    v = v[np.all(np.isfinite(v), axis=1)]
    if v.shape[0] == 0:
        return
    ext = float(np.max(v.max(axis=0) - v.min(axis=0)))
    lo, hi = size_range
    if lo <= ext <= hi:
        return
    declared = unit_scale(units)
    raw = ext / declared
    fits = [u for u, s in UNIT_SCALE.items() if lo <= raw * s <= hi]
    advice = (
        f"It would be {raw * UNIT_SCALE[fits[0]]:.4g} mm with units={fits[0]!r}; pass that if the "
        f"file is in {fits[0]}."
        if fits
        else "No unit among mm/cm/m gives a plausible size."
    )
    raise UnitsError(
        f"{source}: largest extent is {ext:.4g} mm after reading it as units={units!r}, but a "
        f"face or head is about 100-300 mm (accepted range {lo:g}-{hi:g} mm). {advice} If the "
        f"size is right (e.g. a small part), pass check_size=False."
    )


# --------------------------------------------------------------------------------------------
# file I/O
