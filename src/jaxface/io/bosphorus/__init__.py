"""Bosphorus-style scan I/O: ``.bnt`` range grids, ``.lm2`` image landmarks, OBJ/PLY scans,
range-grid meshing and scan-name parsing.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.
Bosphorus ``.bnt`` coordinates are millimetres in exactly that frame, so they are read
unchanged (``units="mm"``); other units are converted on input.

File formats (as implemented here)
----------------------------------
``.bnt`` (binary, little-endian)::

    uint16 nrows, uint16 ncols, float64 zmin
    uint16 L, then L bytes: the texture image name (ASCII)
    uint32 count  (= 5 * nrows * ncols)
    float64[count]: five planes of nrows*ncols values each, in the order X, Y, Z, U, V;
                    each plane is row-major over the grid, row 0 is the BOTTOM image row
                    (rows are stored bottom to top), column 0 the left image column (-x).

Background pixels hold ``zmin`` (a large negative sentinel) in X, Y and Z; U and V (the
texture coordinates in [0, 1]) are stored for every pixel. This layout was checked against
the Bosphorus-style files in ``shared/data/bosphorus_style``: the valid points lie on the
matching ``.truth.ply`` meshes to 1e-14 mm, X grows with the column, Y with the row, and
``U = col / (ncols - 1)``, ``V = row / (nrows - 1)``.

``.lm2`` (text; 2D landmarks in texture pixels). Our reading of the format (the Bosphorus
convention of listing the labels first, then the coordinates)::

    # comment lines start with '#'
    <blank line>
    22 landmarks:
    Labels:
    Outer left eyebrow
    ...                      (N label lines)
    2D Image coordinates:
    512.000 390.000          (N lines "x y": x = pixel column, y = pixel row, origin at
    ...                       the top-left corner of the texture image)

Headers are matched case-insensitively and blank lines are ignored.

``.lm3`` is handled by :mod:`jaxface.landmarks` (``read_lm3`` / ``write_lm3``).

File names ``bsXXX_<class>_<code>_<n>`` are parsed by :func:`parse_scan_name`.

Layout: :mod:`.names` (scan names), :mod:`.lm2` (``.lm2`` files), :mod:`.grid` (range-grid
meshing), :mod:`.scan` (:class:`Scan`), :mod:`.bnt` (``.bnt`` files), :mod:`.load`
(:func:`load_scan`, :func:`complete_landmarks`).
"""

from __future__ import annotations

from ...landmarks import FACE_LABELS
from .bnt import read_bnt, write_bnt
from .grid import DEFAULT_MAX_EDGE_FACTOR, grid_triangles
from .lm2 import ImageLandmarks, read_lm2, write_lm2
from .lm2 import _canon as _canon  # label normalisation, used by jaxface.io.preprocess
from .load import MissingLandmarkWarning, complete_landmarks, load_scan
from .names import AUCode, ScanInfo, parse_scan_name
from .scan import Scan

__all__ = [
    "Scan",
    "ScanInfo",
    "AUCode",
    "ImageLandmarks",
    "MissingLandmarkWarning",
    "FACE_LABELS",
    "read_bnt",
    "write_bnt",
    "read_lm2",
    "write_lm2",
    "load_scan",
    "parse_scan_name",
    "grid_triangles",
    "complete_landmarks",
    "DEFAULT_MAX_EDGE_FACTOR",
]
