"""Bosphorus ``.bnt`` range grids: :func:`read_bnt` and :func:`write_bnt` (mm; layout in
:mod:`jaxface.io.bosphorus`)."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np

from ...atomic import write_bytes_atomic
from ...errors import ScanFormatError
from ...landmarks import FACE_LABELS
from ...mesh import check_input_file, check_plausible_size, unit_scale
from .grid import _check_points
from .names import parse_scan_name
from .scan import Scan

__all__ = ["read_bnt", "write_bnt"]

_BNT_HEADER = struct.Struct("<HHd")  # nrows, ncols, zmin
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


def read_bnt(path: str | Path, *, units: str = "mm", check_size: bool = True) -> Scan:
    """Read a Bosphorus ``.bnt`` range grid (layout in the module doc).

    Args:
        path: the ``.bnt`` file.
        units: unit of the file's coordinates (Bosphorus: ``"mm"``); converted to mm.
        check_size: raise :class:`UnitsError` when the scan's extent in mm is implausible
            for a face (:func:`jaxface.mesh.check_plausible_size`).

    Returns:
        :class:`Scan` in mm without landmarks (see :func:`load_scan` for landmarks).

    Raises:
        DataNotFoundError: no such file.
        ScanFormatError: truncated file, zero dimensions, a count field that is not
            ``5 * nrows * ncols``, a NaN sentinel, all-background grid, NaN/inf in valid
            points; the message names the file and the problem.
    """
    path = Path(path)
    check_input_file(path, "scan file")
    scale = _unit_scale(units)
    data = path.read_bytes()

    def need(offset: int, size: int, what: str):
        if len(data) < offset + size:
            raise ScanFormatError(
                f"{path}: truncated .bnt file: {len(data)} bytes, but reading {what} needs "
                f"{offset + size}. Re-export or re-download the scan."
            )

    need(0, _BNT_HEADER.size, "the header (nrows, ncols, zmin)")
    nrows, ncols, zmin = _BNT_HEADER.unpack_from(data, 0)
    if nrows == 0 or ncols == 0:
        raise ScanFormatError(
            f"{path}: range grid has zero size ({nrows} rows x {ncols} columns); "
            f"the header is corrupt."
        )
    if not np.isfinite(zmin):
        raise ScanFormatError(f"{path}: background value zmin is {zmin}; the header is corrupt.")
    off = _BNT_HEADER.size
    need(off, 2, "the image-name length")
    (name_len,) = _U16.unpack_from(data, off)
    off += 2
    need(off, name_len, f"the {name_len}-byte image name")
    image_name = data[off : off + name_len].decode("latin-1")
    off += name_len
    need(off, 4, "the value count")
    (count,) = _U32.unpack_from(data, off)
    off += 4
    n = nrows * ncols
    if count != 5 * n:
        raise ScanFormatError(
            f"{path}: wrong count field {count}: a {nrows} x {ncols} grid needs 5*{n} = {5 * n} "
            f"values (X, Y, Z, U, V planes); the file is corrupt or not a .bnt file."
        )
    need(off, 8 * count, f"{count} float64 values")
    if len(data) > off + 8 * count:
        warnings.warn(
            f"{path}: {len(data) - off - 8 * count} unexpected trailing bytes after the "
            f"data were ignored.",
            stacklevel=2,
        )
    planes = np.frombuffer(data, dtype="<f8", count=count, offset=off).reshape(5, nrows, ncols)
    xyz = np.stack(list(planes[:3]), axis=-1).astype(np.float64)
    uv = np.stack(list(planes[3:]), axis=-1).astype(np.float64)
    valid = np.all(xyz != zmin, axis=2)
    pts = xyz[valid]
    _check_points(pts, valid, path)
    if not np.all(np.isfinite(uv[valid])):
        k = int((~np.all(np.isfinite(uv[valid]), axis=1)).sum())
        raise ScanFormatError(
            f"{path}: {k} valid pixel(s) have NaN/inf texture coordinates (U, V); "
            f"the file is corrupt."
        )
    background = np.where(valid[..., None], zmin, xyz)
    if scale != 1.0:
        pts = pts * scale
    _check_extent(pts, units, path, check_size)
    return Scan(
        points=pts,
        shape=(nrows, ncols),
        valid=valid,
        uv_grid=uv,
        zmin=float(zmin),
        image_name=image_name,
        background=background,
        path=path,
        info=parse_scan_name(path),
        missing_landmarks=FACE_LABELS,
    )


def write_bnt(path: str | Path, scan: Scan, *, image_name: str | None = None) -> None:
    """Write a grid :class:`Scan` as ``.bnt`` (mm; layout in the module doc).

    Valid pixels get ``scan.points``; background pixels get their original X/Y/Z values if
    the scan was read from a file (so read -> write is byte-exact), else ``zmin``.
    """
    if scan.shape is None:
        raise ScanFormatError(
            f"{scan.path or 'scan'}: only range-grid scans can be written as .bnt"
        )
    nrows, ncols = scan.shape
    if not (0 < nrows < 65536 and 0 < ncols < 65536):
        raise ScanFormatError(f"grid {nrows} x {ncols} does not fit the uint16 .bnt header")
    name = (scan.image_name if image_name is None else image_name).encode("latin-1")
    if len(name) > 65535:
        raise ScanFormatError("image name longer than 65535 bytes")
    xyz = (
        np.full((nrows, ncols, 3), scan.zmin, dtype=np.float64)
        if scan.background is None
        else np.array(scan.background, dtype=np.float64)
    )
    xyz[scan.valid] = scan.points
    uv = scan.uv_grid if scan.uv_grid is not None else np.zeros((nrows, ncols, 2))
    planes = np.concatenate([np.moveaxis(xyz, -1, 0), np.moveaxis(uv, -1, 0)], axis=0)
    pts = np.asarray(scan.points, dtype=np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(pts), axis=1)) if pts.size else []
    if len(bad) or not np.isfinite(scan.zmin):
        raise ScanFormatError(
            f"{path}: refusing to write a .bnt with {len(bad)} non-finite point(s)"
            + (f" (first: point {int(bad[0])})" if len(bad) else " (zmin is not finite)")
            + "; nothing was written."
        )
    write_bytes_atomic(
        path,
        b"".join(
            (
                _BNT_HEADER.pack(nrows, ncols, float(scan.zmin)),
                _U16.pack(len(name)),
                name,
                _U32.pack(planes.size),
                np.ascontiguousarray(planes, dtype="<f8").tobytes(),
            )
        ),
    )


def _unit_scale(units: str) -> float:
    return unit_scale(units)


def _check_extent(pts: np.ndarray, units: str, path, check_size: bool) -> None:
    if check_size:
        check_plausible_size(pts, units, source=str(path))
