"""Loading a scan of any supported format with its landmarks (:func:`load_scan`), and the
estimate of missing bilateral landmarks by mirroring (:func:`complete_landmarks`)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ...errors import LandmarkError, MeshError, ScanFormatError
from ...landmarks import FACE_LABELS, MIRROR_PAIRS, Landmarks, lm3_is_detected, read_lm3
from ...mesh import check_input_file, load_mesh
from .bnt import _unit_scale, read_bnt
from .grid import _check_points
from .lm2 import _canon
from .names import parse_scan_name
from .scan import Scan

__all__ = ["MissingLandmarkWarning", "load_scan", "complete_landmarks"]


class MissingLandmarkWarning(UserWarning):
    """A landmark that is optional for the current use is absent from a scan's landmark file."""


def load_scan(
    path: str | Path,
    landmarks: str | Path | bool | None = None,
    units: str = "mm",
    *,
    require: Sequence[str] = (),
    warn_missing: bool = True,
    check_size: bool = True,
) -> Scan:
    """Load a scan (``.bnt`` range grid, or ``.obj`` / ``.ply`` mesh) with its landmarks.

    Args:
        path: scan file; dispatch on the extension.
        landmarks: ``.lm3`` file (mm, same units as the scan); ``None`` = the file beside
            the scan with suffix ``.lm3`` if it exists (for ``x.truth.ply``, ``x.lm3`` is also
            tried; ``True`` means the same); ``False`` = no landmarks.
        units: unit of the scan and landmark coordinates; converted to mm.
        require: labels that must be present (:class:`LandmarkError` listing all missing).
        warn_missing: warn (:class:`MissingLandmarkWarning`) about Bosphorus face labels
            absent from the landmark file; they are listed in ``Scan.missing_landmarks``.
        check_size: check that the scan is face-sized in mm (catches wrong ``units``).

    Returns:
        :class:`Scan` in mm.
    """
    path = Path(path)
    check_input_file(path, "scan file")
    ext = path.suffix.lower()
    if ext == ".bnt":
        scan = read_bnt(path, units=units, check_size=check_size)
    elif ext in (".obj", ".ply"):
        try:
            # scans are data: degenerate or inconsistently oriented triangles are tolerated
            mesh = load_mesh(path, units=units, check_size=check_size, validate=False)
        except MeshError as e:
            raise ScanFormatError(f"{path}: cannot read the scan mesh: {e}") from e
        pts = np.asarray(mesh.vertices, dtype=np.float64)
        _check_points(pts, None, path)
        tri = np.asarray(mesh.triangles)
        if tri.size == 0 or tri.min() < 0 or tri.max() >= len(pts):
            raise ScanFormatError(
                f"{path}: the scan mesh has no triangles or triangle indices "
                f"outside 0..{len(pts) - 1}."
            )
        scan = Scan(
            points=pts,
            triangles=np.asarray(mesh.triangles, dtype=np.int64),
            path=path,
            info=parse_scan_name(path),
            missing_landmarks=FACE_LABELS,
        )
    else:
        raise ScanFormatError(f"{path}: unknown scan format {ext!r}; use .bnt, .obj or .ply")

    lm_path: Path | None = None
    if landmarks is None or landmarks is True:
        cands = [path.with_suffix(".lm3")]
        if path.name.lower().endswith(".truth.ply"):
            cands.append(path.with_name(path.name[: -len(".truth.ply")] + ".lm3"))
        lm_path = next((c for c in cands if c.is_file()), None)
    elif landmarks is not False:
        lm_path = Path(landmarks)
        check_input_file(lm_path, "landmark file")
    if lm_path is not None:
        lm = read_lm3(lm_path)
        scale = _unit_scale(units)
        if scale != 1.0:
            lm = lm.transformed(scale=scale)
        scan = scan.with_landmarks(lm, detected=lm3_is_detected(lm_path))
    if require:
        scan.require_landmarks(require)
    if warn_missing and scan.landmarks is not None and scan.missing_landmarks:
        warnings.warn(
            f"{lm_path}: {len(scan.missing_landmarks)} Bosphorus landmark(s) absent: "
            f"{', '.join(scan.missing_landmarks)}. They are listed in Scan.missing_landmarks; "
            f"complete_landmarks() estimates bilateral ones by mirroring.",
            MissingLandmarkWarning,
            stacklevel=2,
        )
    return scan


# ---------------------------------------------------------------------------------------------
# missing-landmark workaround
# ---------------------------------------------------------------------------------------------

_MIDLINE = (
    "Nose tip",
    "Upper lip outer middle",
    "Upper lip inner middle",
    "Lower lip inner middle",
    "Lower lip outer middle",
    "Chin middle",
)


def complete_landmarks(
    landmarks: Landmarks, points: np.ndarray | None = None, names: Sequence[str] = FACE_LABELS
) -> tuple[Landmarks, tuple[str, ...]]:
    """Estimate missing bilateral landmarks by mirroring their partner.

    The mid-sagittal plane is fitted (least squares) to the midpoints of the complete
    left/right pairs and the midline landmarks present, with its normal along the mean
    left-minus-right direction; a missing landmark whose partner exists is the partner's
    mirror image, snapped to the nearest of ``points`` (mm) when given. Midline landmarks
    cannot be mirrored and stay missing.

    Returns:
        ``(landmarks with the estimates appended, names that were estimated)``.

    Raises:
        LandmarkError: fewer than two complete pairs (the plane is undetermined).
    """
    have = {_canon(n): n for n in landmarks.names}
    pos = {c: np.asarray(landmarks[n], dtype=np.float64) for c, n in have.items()}
    pairs = [(l, r) for l, r in MIRROR_PAIRS if _canon(l) in pos and _canon(r) in pos]
    if len(pairs) < 2:
        raise LandmarkError(
            f"need at least two complete left/right landmark pairs to mirror missing "
            f"ones; found {len(pairs)}",
            missing=[n for n in names if _canon(n) not in pos],
        )
    normal = np.mean([pos[_canon(l)] - pos[_canon(r)] for l, r in pairs], axis=0)
    normal /= np.linalg.norm(normal)
    mids = [0.5 * (pos[_canon(l)] + pos[_canon(r)]) for l, r in pairs]
    mids += [pos[_canon(m)] for m in _MIDLINE if _canon(m) in pos]
    offset = float(np.mean([m @ normal for m in mids]))
    tree = None
    if points is not None:
        from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

        tree = cKDTree(np.asarray(points, dtype=np.float64))
    new_names, new_pos, done = list(landmarks.names), [np.asarray(landmarks.positions)], []
    wanted = {_canon(n) for n in names}
    for l, r in MIRROR_PAIRS:
        for miss, other in ((l, r), (r, l)):
            if _canon(miss) in wanted and _canon(miss) not in pos and _canon(other) in pos:
                p = pos[_canon(other)]
                q = p - 2.0 * (p @ normal - offset) * normal
                if tree is not None:
                    q = tree.data[tree.query(q)[1]]
                new_names.append(miss)
                new_pos.append(q[None])
                done.append(miss)
    return Landmarks(tuple(new_names), np.concatenate(new_pos)), tuple(done)
