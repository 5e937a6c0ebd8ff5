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
"""

from __future__ import annotations

import re
import struct
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..atomic import write_bytes_atomic, write_text_atomic
from ..errors import LandmarkError, MeshError, ScanFormatError
from ..landmarks import FACE_LABELS, MIRROR_PAIRS, Landmarks, canonical_label, read_lm3
from ..mesh import TriMesh, check_input_file, check_plausible_size, load_mesh, unit_scale

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

#: Default long-edge threshold for range-grid meshing, in units of the grid spacing: a
#: triangle is dropped when one of its edges is longer than this many grid steps. 6 steps
#: keeps surfaces inclined up to about 80 degrees from the view direction and removes the
#: bridges across depth discontinuities (chin over neck, nose side over cheek holes), which
#: are tens of steps long.
DEFAULT_MAX_EDGE_FACTOR = 6.0

_BNT_HEADER = struct.Struct("<HHd")  # nrows, ncols, zmin
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


class MissingLandmarkWarning(UserWarning):
    """A landmark that is optional for the current use is absent from a scan's landmark file."""


# ---------------------------------------------------------------------------------------------
# scan names
# ---------------------------------------------------------------------------------------------

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


# ---------------------------------------------------------------------------------------------
# 2D landmarks
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# the Scan container
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Scan:
    """A 3D face scan, in millimetres, frame +y up / +z toward the viewer / subject's left +x.

    A range-grid scan (from ``.bnt``) keeps its grid: ``shape``, ``valid``, ``uv_grid``,
    ``zmin``, ``background`` (the original X/Y/Z of background pixels, kept for exact
    rewriting). A mesh scan (OBJ/PLY) has ``triangles`` instead and ``shape is None``.

    Attributes:
        points: (N, 3) float64 mm, the valid points; for a grid, in row-major grid order
            (row 0 = bottom row) over the valid pixels.
        shape: ``(nrows, ncols)`` of the range grid, or ``None`` for a mesh scan.
        valid: (nrows, ncols) bool, True where the pixel holds a point (grid scans).
        uv_grid: (nrows, ncols, 2) float64 texture coordinates in [0, 1] for every pixel.
        zmin: the background sentinel of the ``.bnt`` file.
        image_name: texture image name stored in the ``.bnt`` header.
        triangles: (F, 3) int64 for mesh scans (indices into ``points``), else ``None``.
        landmarks: :class:`jaxface.landmarks.Landmarks` in mm, or ``None``.
        path: source file, or ``None``.
        info: parsed file name (:class:`ScanInfo`) or ``None``.
        missing_landmarks: canonical Bosphorus face labels absent from ``landmarks``.
    """

    points: np.ndarray
    shape: tuple[int, int] | None = None
    valid: np.ndarray | None = None
    uv_grid: np.ndarray | None = None
    zmin: float = -1.0e9
    image_name: str = ""
    background: np.ndarray | None = field(default=None, repr=False)
    triangles: np.ndarray | None = None
    landmarks: Landmarks | None = None
    path: Path | None = None
    info: ScanInfo | None = None
    missing_landmarks: tuple[str, ...] = ()

    # -- constructors --------------------------------------------------------------------
    @classmethod
    def from_grid(
        cls,
        xyz: np.ndarray,
        valid: np.ndarray | None = None,
        uv: np.ndarray | None = None,
        *,
        zmin: float = -1.0e9,
        image_name: str = "",
        landmarks=None,
        path: str | Path | None = None,
    ) -> Scan:
        """A grid scan from a (nrows, ncols, 3) mm array (row 0 = bottom row).

        Args:
            xyz: (nrows, ncols, 3) mm.
            valid: (nrows, ncols) bool; default: pixels whose coordinates are all finite and
                differ from ``zmin``.
            uv: (nrows, ncols, 2) texture coordinates; default ``(col/(ncols-1), row/(nrows-1))``.
            zmin: background sentinel written to ``.bnt`` files.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.shape[0] < 1 or xyz.shape[1] < 1:
            raise ScanFormatError(f"grid must have shape (nrows>0, ncols>0, 3), got {xyz.shape}")
        nr, nc = xyz.shape[:2]
        if valid is None:
            valid = np.all(np.isfinite(xyz), axis=2) & np.all(xyz != zmin, axis=2)
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (nr, nc):
            raise ScanFormatError(f"valid mask shape {valid.shape} does not match grid {(nr, nc)}")
        if uv is None:
            jj, ii = np.meshgrid(np.arange(nc) / max(nc - 1, 1), np.arange(nr) / max(nr - 1, 1))
            uv = np.stack([jj, ii], axis=-1)
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape != (nr, nc, 2):
            raise ScanFormatError(f"uv grid shape {uv.shape} does not match grid {(nr, nc)}")
        pts = xyz[valid]
        _check_points(pts, valid, path or "<grid>")
        p = Path(path) if path is not None else None
        return cls(
            points=pts,
            shape=(nr, nc),
            valid=valid,
            uv_grid=uv,
            zmin=float(zmin),
            image_name=image_name,
            background=None,
            landmarks=landmarks,
            path=p,
            info=parse_scan_name(p) if p is not None else None,
            missing_landmarks=_missing(landmarks),
        )

    # -- views ---------------------------------------------------------------------------
    @property
    def is_grid(self) -> bool:
        return self.shape is not None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def uv(self) -> np.ndarray | None:
        """(N, 2) texture coordinates of the valid points (grid scans), else ``None``."""
        return None if self.uv_grid is None else self.uv_grid[self.valid]

    @property
    def grid_index(self) -> np.ndarray:
        """(nrows, ncols) int64: index into ``points`` of each pixel, -1 for background."""
        shape, valid = self._need_grid("grid_index")
        idx = np.full(shape, -1, dtype=np.int64)
        idx[valid] = np.arange(self.n_points)
        return idx

    def xyz_grid(self, fill: float = np.nan) -> np.ndarray:
        """(nrows, ncols, 3) mm, background pixels set to ``fill``."""
        shape, valid = self._need_grid("xyz_grid")
        g = np.full(shape + (3,), fill, dtype=np.float64)
        g[valid] = self.points
        return g

    def grid_spacing(self) -> float:
        """Median distance in mm between horizontally or vertically adjacent valid pixels,
        measured in the image (x, y) plane."""
        _, valid = self._need_grid("grid_spacing")
        return _grid_spacing(self.xyz_grid(), valid, self.path or "scan")

    def _need_grid(self, what: str) -> tuple[tuple[int, int], np.ndarray]:
        """``(shape, valid)`` of a range-grid scan; ScanFormatError for a mesh scan."""
        if self.shape is None:
            raise ScanFormatError(
                f"{self.path or 'scan'}: {what} needs a range-grid scan (.bnt); "
                f"this is a mesh scan."
            )
        assert self.valid is not None  # a grid scan always has its valid mask
        return self.shape, self.valid

    # -- meshing -------------------------------------------------------------------------
    def mesh_arrays(
        self, max_edge_factor: float = DEFAULT_MAX_EDGE_FACTOR, *, drop_unreferenced: bool = True
    ):
        """Triangulate the scan.

        Grid scans: see :func:`grid_triangles` (valid cells only, long edges dropped,
        counter-clockwise seen from +z). Mesh scans: their own triangles.

        Returns:
            ``(vertices (V, 3) mm, triangles (F, 3) int64, point_ids (V,) int64)`` where
            ``point_ids`` maps each vertex to its row in ``points``.
        """
        if self.shape is None:
            if self.triangles is None:
                raise ScanFormatError(
                    f"{self.path or 'scan'}: a point cloud without triangles cannot be meshed here."
                )
            tri = np.asarray(self.triangles, dtype=np.int64)
            ids = np.arange(self.n_points)
        else:
            tri = grid_triangles(
                self.xyz_grid(),
                self._need_grid("mesh_arrays")[1],
                max_edge_factor=max_edge_factor,
                spacing=self.grid_spacing(),
            )
            tri = self.grid_index[tri[..., 0], tri[..., 1]]  # (F, 3) into points
            ids = np.arange(self.n_points)
        if drop_unreferenced:
            used = np.unique(tri)
            remap = np.full(self.n_points, -1, dtype=np.int64)
            remap[used] = np.arange(used.size)
            return self.points[used], remap[tri], used
        return self.points, tri, ids

    def to_mesh(
        self, max_edge_factor: float = DEFAULT_MAX_EDGE_FACTOR, *, validate: bool | None = None
    ) -> TriMesh:
        """The scan as a :class:`jaxface.mesh.TriMesh` (mm).

        Grid scans are meshed by :func:`grid_triangles` (normals toward +z, the viewer;
        consistent orientation), unreferenced points dropped (``mesh_arrays`` gives the map
        back to ``points``). Mesh scans keep their vertices and vertex order.

        Args:
            validate: run :meth:`TriMesh.validate`; default True for grid scans and False for
                mesh scans (scan meshes may hold degenerate triangles, which are tolerated).
        """
        if validate is None:
            validate = self.is_grid
        v, t, _ = self.mesh_arrays(max_edge_factor, drop_unreferenced=self.is_grid)
        if t.shape[0] == 0:
            raise ScanFormatError(
                f"{self.path or 'scan'}: no triangle survives meshing "
                f"(max_edge_factor={max_edge_factor}); the grid has no valid cells."
            )
        return TriMesh(v, t, validate=validate)

    # -- landmarks -----------------------------------------------------------------------
    def with_landmarks(self, landmarks) -> Scan:
        """A copy with other landmarks (mm); ``missing_landmarks`` recomputed."""
        return replace(self, landmarks=landmarks, missing_landmarks=_missing(landmarks))

    def require_landmarks(self, names: Iterable[str]) -> Landmarks:
        """The landmarks restricted to ``names``; :class:`LandmarkError` naming the file and
        every missing label if any is absent."""
        names = list(names)
        if self.landmarks is None:
            raise LandmarkError(
                f"{self.path or 'scan'}: no landmarks loaded but {len(names)} are required "
                f"({', '.join(names)}); give a .lm3 file (load_scan(path, landmarks=...)).",
                missing=names,
            )
        have = {_canon(n) for n in self.landmarks.names}
        missing = [n for n in names if _canon(n) not in have]
        if missing:
            raise LandmarkError(
                f"{self.path or 'scan'}: {len(missing)} required landmark(s) missing: "
                f"{', '.join(missing)}. Add them to the landmark file or choose other labels.",
                missing=missing,
            )
        return self.landmarks.subset(names)


def _missing(landmarks) -> tuple[str, ...]:
    if landmarks is None:
        return FACE_LABELS
    have = {_canon(n) for n in landmarks.names}
    return tuple(n for n in FACE_LABELS if _canon(n) not in have)


def _check_points(pts: np.ndarray, valid: np.ndarray | None, where) -> None:
    if pts.shape[0] == 0:
        raise ScanFormatError(
            f"{where}: every pixel of the range grid is background (no valid "
            f"points); the file holds no scan data."
        )
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        if valid is not None:
            rc = np.argwhere(valid)[bad][:5]
            loc = ", ".join(f"(row {r}, col {c})" for r, c in rc)
        else:
            loc = ", ".join(map(str, np.flatnonzero(bad)[:5]))
        raise ScanFormatError(
            f"{where}: {int(bad.sum())} valid point(s) have NaN/inf coordinates, "
            f"first at {loc}; the file is corrupt (background must be zmin, not NaN)."
        )


# ---------------------------------------------------------------------------------------------
# .bnt
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# range-grid meshing
# ---------------------------------------------------------------------------------------------


def _grid_spacing(xyz: np.ndarray, valid: np.ndarray, where) -> float:
    d = []
    for a, b, m in (
        (xyz[:, 1:], xyz[:, :-1], valid[:, 1:] & valid[:, :-1]),
        (xyz[1:], xyz[:-1], valid[1:] & valid[:-1]),
    ):
        if m.any():
            d.append(np.linalg.norm((a - b)[m][:, :2], axis=1))
    d = np.concatenate(d) if d else np.zeros(0)
    d = d[d > 0]
    if d.size == 0:
        raise ScanFormatError(
            f"{where}: no two adjacent valid pixels at distinct positions; cannot "
            f"measure the grid spacing or mesh the grid."
        )
    return float(np.median(d))


def grid_triangles(
    xyz: np.ndarray,
    valid: np.ndarray,
    *,
    max_edge_factor: float = DEFAULT_MAX_EDGE_FACTOR,
    spacing: float | None = None,
) -> np.ndarray:
    """Triangulate a range grid.

    Each cell (a = (i, j), b = (i, j+1), c = (i+1, j+1), d = (i+1, j)) with four valid
    corners becomes two triangles split along its shorter 3D diagonal; a cell with exactly
    three valid corners becomes one triangle. A triangle is dropped when any edge is longer
    than ``max_edge_factor * spacing`` (depth discontinuities). The winding is chosen so
    that the total projected normal points toward +z (the viewer): counter-clockwise seen
    from +z.

    Args:
        xyz: (nrows, ncols, 3) mm (background values ignored).
        valid: (nrows, ncols) bool.
        max_edge_factor: long-edge threshold in grid steps (``inf`` keeps everything).
        spacing: grid step in mm; default the median xy distance of adjacent valid pixels.

    Returns:
        (F, 3, 2) int64: ``[row, col]`` grid indices of each triangle's corners.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    nr, nc = valid.shape
    if nr < 2 or nc < 2:
        return np.zeros((0, 3, 2), dtype=np.int64)
    ii, jj = np.meshgrid(np.arange(nr - 1), np.arange(nc - 1), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    corners = np.stack(
        [
            np.stack([ii, jj], -1),
            np.stack([ii, jj + 1], -1),
            np.stack([ii + 1, jj + 1], -1),
            np.stack([ii + 1, jj], -1),
        ],
        axis=1,
    )  # (C,4,2)
    cv = valid[corners[..., 0], corners[..., 1]]  # (C, 4)
    nvalid = cv.sum(1)
    P = np.where(valid[..., None], xyz, 0.0)
    cp = P[corners[..., 0], corners[..., 1]]  # (C, 4, 3)

    tris = []
    full = nvalid == 4
    if full.any():
        c4, p4 = corners[full], cp[full]
        ac = np.linalg.norm(p4[:, 0] - p4[:, 2], axis=1)
        bd = np.linalg.norm(p4[:, 1] - p4[:, 3], axis=1)
        use_ac = ac <= bd
        t_ac = np.concatenate([c4[use_ac][:, [0, 1, 2]], c4[use_ac][:, [0, 2, 3]]])
        t_bd = np.concatenate([c4[~use_ac][:, [0, 1, 3]], c4[~use_ac][:, [1, 2, 3]]])
        tris += [t_ac, t_bd]
    three = nvalid == 3
    if three.any():
        c3, v3 = corners[three], cv[three]
        miss = np.argmin(v3, axis=1)  # index of the single invalid corner
        keep = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[miss]  # cyclic order kept
        tris.append(np.take_along_axis(c3, keep[..., None], axis=1))
    if not tris:
        return np.zeros((0, 3, 2), dtype=np.int64)
    T = np.concatenate(tris).astype(np.int64)
    V = P[T[..., 0], T[..., 1]]  # (F, 3, 3)
    if np.isfinite(max_edge_factor):
        if spacing is None:
            spacing = _grid_spacing(xyz, valid, "grid")
        e = np.stack(
            [
                np.linalg.norm(V[:, 1] - V[:, 0], axis=1),
                np.linalg.norm(V[:, 2] - V[:, 1], axis=1),
                np.linalg.norm(V[:, 0] - V[:, 2], axis=1),
            ],
            1,
        ).max(1)
        ok = e <= max_edge_factor * spacing
        T, V = T[ok], V[ok]
    # orientation: make the total projected normal point toward +z
    nz = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])[:, 2].sum() if len(T) else 1.0
    if nz < 0:
        T = T[:, [0, 2, 1]]
    return T


# ---------------------------------------------------------------------------------------------
# generic loading
# ---------------------------------------------------------------------------------------------


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
        scan = scan.with_landmarks(lm)
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
