"""The :class:`Scan` container: a range-grid or mesh face scan in mm with its landmarks."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...errors import LandmarkError, ScanFormatError
from ...landmarks import FACE_LABELS, Landmarks
from ...mesh import TriMesh
from .grid import DEFAULT_MAX_EDGE_FACTOR, _check_points, _grid_spacing, grid_triangles
from .lm2 import _canon
from .names import ScanInfo, parse_scan_name

__all__ = ["Scan"]


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
        landmarks_detected: True when ``landmarks`` were detected from this scan's own
            surface (:mod:`jaxface.detect`) rather than read from a landmark file; the fit
            then leaves them out of its landmark term
            (:attr:`jaxface.fit.options.FitOptions.detected_landmark_weight`).
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
    landmarks_detected: bool = False

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
    def with_landmarks(self, landmarks, *, detected: bool = False) -> Scan:
        """A copy with other landmarks (mm); ``missing_landmarks`` recomputed. ``detected``:
        they were detected from this scan's surface (:attr:`landmarks_detected`)."""
        return replace(
            self,
            landmarks=landmarks,
            missing_landmarks=_missing(landmarks),
            landmarks_detected=bool(detected),
        )

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
