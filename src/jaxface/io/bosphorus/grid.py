"""Range-grid meshing (:func:`grid_triangles`, mm) and the checks of grid points."""

from __future__ import annotations

import numpy as np

from ...errors import ScanFormatError

__all__ = ["grid_triangles", "DEFAULT_MAX_EDGE_FACTOR"]

#: Default long-edge threshold for range-grid meshing, in units of the grid spacing: a
#: triangle is dropped when one of its edges is longer than this many grid steps. 6 steps
#: keeps surfaces inclined up to about 80 degrees from the view direction and removes the
#: bridges across depth discontinuities (chin over neck, nose side over cheek holes), which
#: are tens of steps long.
DEFAULT_MAX_EDGE_FACTOR = 6.0


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
