"""A virtual range scanner: resample a triangle mesh into a Bosphorus-style range grid.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.

The scanner sits in front of the face (at +z) and looks along ``-z``. One ray is cast along
``-z`` through every node ``(xs[j], ys[i])`` of a regular x/y grid; the first surface it meets
(the largest ``z``) is the range sample of that pixel. Rows go bottom to top (row 0 = the
smallest ``y``) and columns from the subject's right to left (column 0 = the smallest ``x``),
exactly as :func:`jaxface.io.read_bnt` returns the Bosphorus files; a pixel whose ray misses
the mesh is background.

The rays are parallel, so casting them is an orthographic z-buffer: every triangle is
projected on the x/y plane, the grid nodes inside its projection get the triangle's depth by
barycentric interpolation, and each node keeps the nearest (largest ``z``) one
(:func:`cast_grid`, vectorised NumPy, processed in chunks to bound the memory). The hits are
the exact ray/triangle intersections: ``tests/commands/test_commands.py`` checks them against
:meth:`jaxface.mesh.TriMesh.ray_cast`, which is 10-50 times slower for a whole grid.

Grid nodes lie on integer multiples of the resolution (:func:`grid_axes`), so a mesh made
from a ``.bnt`` grid of that spacing is resampled at its own vertices: ``.bnt`` -> mesh ->
``.bnt`` gives the same points back wherever the mesh kept the grid's triangles.

:func:`scan_mesh` wraps this into a :class:`jaxface.io.Scan` (write it with
:func:`jaxface.io.write_bnt`), optionally with a grazing-angle cut-off and depth noise, to
make synthetic scans of simulated faces. The :class:`GridHits` it can return re-evaluates
the same surface points on deformed vertices of the mesh (``positions``/``sample``), which
carries morph targets or simulated expressions over to the scan's pixels.
"""

from __future__ import annotations

import dataclasses
from typing import Literal, overload

import numpy as np

from ..closest import SurfaceIndex, mesh_arrays
from ..errors import MeshError, ScanFormatError
from ..landmarks import Landmarks
from .bosphorus import Scan

__all__ = [
    "DEFAULT_RESOLUTION_MM",
    "MAX_GRID_PIXELS",
    "GridHits",
    "grid_axes",
    "cast_grid",
    "scan_mesh",
    "SkinLandmarks",
    "scan_skin",
]

#: default grid spacing of :func:`scan_mesh`, mm (real Bosphorus scans: about 0.3-1 mm)
DEFAULT_RESOLUTION_MM = 0.5

#: largest grid :func:`scan_mesh` accepts (pixels); also the ``.bnt`` header caps each side
#: at 65535
MAX_GRID_PIXELS = 25_000_000

_BARY_TOL = 1e-9  # inclusive tolerance on barycentric coordinates (rays through edges/vertices)


@dataclasses.dataclass(frozen=True)
class GridHits:
    """Where the rays of a range grid met a mesh (result of :func:`cast_grid`).

    Attributes:
        xs: ``(ncols,)`` x of the grid columns, mm, increasing (column 0 = subject's right).
        ys: ``(nrows,)`` y of the grid rows, mm, increasing (row 0 = bottom).
        valid: ``(nrows, ncols)`` bool, True where the ray hit the mesh.
        triangle: ``(nrows, ncols)`` int64, the triangle hit first (-1 where no hit).
        bary: ``(nrows, ncols, 3)`` barycentric coordinates of the hit in that triangle
            (0 where no hit).
        xyz: ``(nrows, ncols, 3)`` hit positions, mm: ``x``, ``y`` exactly the grid node,
            ``z`` the surface depth; NaN where no hit.
        triangles: ``(F, 3)`` int64, the triangles of the scanned mesh (for :meth:`positions`).
    """

    xs: np.ndarray
    ys: np.ndarray
    valid: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray
    xyz: np.ndarray
    triangles: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(nrows, ncols)``."""
        return self.valid.shape

    @property
    def n_hits(self) -> int:
        return int(self.valid.sum())

    def sample(self, field) -> np.ndarray:
        """Evaluate a per-vertex field of the scanned mesh at the hits of the valid pixels.

        Args:
            field: ``(..., V, C)`` values per mesh vertex (e.g. ``(V, 3)`` deformed vertex
                positions in mm, or ``(T, V, 3)`` morph-target displacements in mm).

        Returns:
            ``(..., N, C)`` barycentric interpolation at the ``N = valid.sum()`` hits, in
            row-major pixel order (the order of :attr:`jaxface.io.Scan.points`).
        """
        f = np.asarray(field)
        if f.ndim < 2:
            raise MeshError(f"field must have shape (..., V, C), got {f.shape}.", problem="shape")
        corners = self.triangles[self.triangle[self.valid]]  # (N, 3)
        if corners.size and corners.max() >= f.shape[-2]:
            raise MeshError(
                f"field has {f.shape[-2]} vertices but the scanned mesh's triangles use vertex "
                f"{int(corners.max())}; pass a field over the same mesh.",
                problem="shape",
            )
        return np.einsum("nk,...nkc->...nc", self.bary[self.valid], f[..., corners, :])

    def positions(self, vertices) -> np.ndarray:
        """``(nrows, ncols, 3)`` mm: the same surface points on other vertex positions
        ``(V, 3)`` mm of the scanned mesh (e.g. a simulated expression); NaN where no hit.

        The result is not a new scan of the deformed mesh (the points move with the surface,
        off the grid nodes); scan the deformed mesh for that."""
        out = np.full(self.valid.shape + (3,), np.nan)
        out[self.valid] = self.sample(np.asarray(vertices, dtype=np.float64))
        return out


def grid_axes(lo: float, hi: float, resolution: float) -> np.ndarray:
    """The multiples of ``resolution`` (mm) in ``[lo, hi]`` (mm), increasing.

    Grid nodes on multiples of the resolution make scans of the same object at the same
    resolution share their nodes (and reproduce a ``.bnt`` grid of that spacing)."""
    res = float(resolution)
    if not (np.isfinite(res) and res > 0):
        raise ScanFormatError(
            f"scan resolution must be a positive number of mm, got {resolution!r}."
        )
    k0 = int(np.ceil(lo / res - 1e-9))
    k1 = int(np.floor(hi / res + 1e-9))
    return np.arange(k0, k1 + 1, dtype=np.float64) * res


def _as_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's arrays (:func:`jaxface.closest.mesh_arrays`), refusing NaN/inf on any vertex
    a triangle uses (mm)."""
    v, t = mesh_arrays(mesh)
    used = np.unique(t)
    bad = used[~np.all(np.isfinite(v[used]), axis=1)]
    if bad.size:
        raise MeshError(
            f"{bad.size} vertices used by triangles have NaN/inf coordinates, first "
            f"{bad[:5].tolist()}.",
            problem="nonfinite",
            elements=bad[:100],
        )
    return v, t


def _reduce_nearest(pix, z, tri, bary):
    """Keep, for every pixel id, the candidate with the largest z."""
    if pix.size == 0:
        return pix, z, tri, bary
    order = np.lexsort((-z, pix))
    pix, z, tri, bary = pix[order], z[order], tri[order], bary[order]
    first = np.ones(pix.size, dtype=bool)
    first[1:] = pix[1:] != pix[:-1]
    return pix[first], z[first], tri[first], bary[first]


def cast_grid(vertices, triangles, xs, ys, *, chunk: int = 2_000_000) -> GridHits:
    """Cast one ray along ``-z`` through every grid node and keep its first hit.

    Args:
        vertices: ``(V, 3)`` mesh vertices, mm.
        triangles: ``(F, 3)`` vertex ids (either orientation: a scanner sees both sides).
        xs: ``(ncols,)`` increasing x of the grid columns, mm.
        ys: ``(nrows,)`` increasing y of the grid rows, mm.
        chunk: maximum number of (triangle, node) candidates processed at once (memory knob,
            about 200 bytes each).

    Returns:
        :class:`GridHits`. A ray through a shared edge or vertex hits at the same depth in
        every triangle there; one of them is reported. Triangles seen edge-on (zero projected
        area) are not hit.
    """
    V, T = _as_arrays((vertices, triangles))
    xs = np.asarray(xs, dtype=np.float64).reshape(-1)
    ys = np.asarray(ys, dtype=np.float64).reshape(-1)
    if xs.size == 0 or ys.size == 0 or np.any(np.diff(xs) <= 0) or np.any(np.diff(ys) <= 0):
        raise ScanFormatError("grid axes xs and ys must be non-empty and strictly increasing (mm).")
    nr, nc = ys.size, xs.size
    P = V[T]  # (F, 3, 3)
    a, b, c = P[:, 0], P[:, 1], P[:, 2]
    e0, e1 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2]
    den = e0[:, 0] * e1[:, 1] - e1[:, 0] * e0[:, 1]  # twice the signed projected area
    scale = np.maximum(np.abs(e0).max(1), np.abs(e1).max(1))
    ok = np.abs(den) > 1e-12 * np.maximum(scale * scale, 1e-300)
    pad = 1e-9 * (1.0 + float(np.abs(V).max(initial=0.0)))
    lo, hi = P[:, :, :2].min(1) - pad, P[:, :, :2].max(1) + pad
    j0 = np.searchsorted(xs, lo[:, 0], "left")
    j1 = np.searchsorted(xs, hi[:, 0], "right")
    i0 = np.searchsorted(ys, lo[:, 1], "left")
    i1 = np.searchsorted(ys, hi[:, 1], "right")
    nj, ni = np.maximum(j1 - j0, 0), np.maximum(i1 - i0, 0)
    cnt = np.where(ok, nj * ni, 0).astype(np.int64)
    tris = np.flatnonzero(cnt)
    cum = np.cumsum(cnt[tris])
    found = []
    start = 0
    while start < tris.size:
        base = int(cum[start - 1]) if start else 0
        stop = max(int(np.searchsorted(cum, base + chunk, side="right")), start + 1)
        t = tris[start:stop]
        n = cnt[t]
        tri_of = np.repeat(t, n)
        k = np.arange(tri_of.size) - np.repeat(np.cumsum(n) - n, n)
        jj = j0[tri_of] + k % nj[tri_of]
        ii = i0[tri_of] + k // nj[tri_of]
        px, py = xs[jj] - a[tri_of, 0], ys[ii] - a[tri_of, 1]
        E0, E1, D = e0[tri_of], e1[tri_of], den[tri_of]
        u = (px * E1[:, 1] - E1[:, 0] * py) / D  # weight of corner b
        v = (E0[:, 0] * py - px * E0[:, 1]) / D  # weight of corner c
        w = 1.0 - u - v
        inside = (u >= -_BARY_TOL) & (v >= -_BARY_TOL) & (w >= -_BARY_TOL)
        bary = np.stack([w, u, v], 1)[inside]
        tri_of, ii, jj = tri_of[inside], ii[inside], jj[inside]
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(1, keepdims=True)
        z = np.einsum("kj,kj->k", bary, P[tri_of, :, 2])
        found.append(_reduce_nearest(ii * nc + jj, z, tri_of, bary))
        start = stop
    if found:
        pix, z, tri, bary = _reduce_nearest(*(np.concatenate(x) for x in zip(*found)))
    else:
        pix, z, tri, bary = (
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros(0, np.int64),
            np.zeros((0, 3)),
        )
    valid = np.zeros(nr * nc, dtype=bool)
    valid[pix] = True
    triangle = np.full(nr * nc, -1, dtype=np.int64)
    triangle[pix] = tri
    B = np.zeros((nr * nc, 3))
    B[pix] = bary
    xyz = np.full((nr * nc, 3), np.nan)
    X, Y = np.meshgrid(xs, ys)
    xyz[pix, 0] = X.ravel()[pix]
    xyz[pix, 1] = Y.ravel()[pix]
    xyz[pix, 2] = z
    for arr in (valid, triangle, B, xyz, T):
        arr.setflags(write=False)
    return GridHits(
        xs=xs,
        ys=ys,
        valid=valid.reshape(nr, nc),
        triangle=triangle.reshape(nr, nc),
        bary=B.reshape(nr, nc, 3),
        xyz=xyz.reshape(nr, nc, 3),
        triangles=T,
    )


@overload
def scan_mesh(
    mesh,
    resolution: float = ...,
    *,
    bounds=...,
    landmarks: Landmarks | None = ...,
    max_angle_deg: float | None = ...,
    noise_mm: float = ...,
    seed: int | None = ...,
    image_name: str = ...,
    path=...,
    zmin: float = ...,
    return_hits: Literal[False] = ...,
) -> Scan: ...


@overload
def scan_mesh(
    mesh,
    resolution: float = ...,
    *,
    bounds=...,
    landmarks: Landmarks | None = ...,
    max_angle_deg: float | None = ...,
    noise_mm: float = ...,
    seed: int | None = ...,
    image_name: str = ...,
    path=...,
    zmin: float = ...,
    return_hits: Literal[True],
) -> tuple[Scan, GridHits]: ...


def scan_mesh(
    mesh,
    resolution: float = DEFAULT_RESOLUTION_MM,
    *,
    bounds=None,
    landmarks: Landmarks | None = None,
    max_angle_deg: float | None = None,
    noise_mm: float = 0.0,
    seed: int | None = 0,
    image_name: str = "",
    path=None,
    zmin: float = -1.0e9,
    return_hits: bool = False,
) -> Scan | tuple[Scan, GridHits]:
    """Scan a mesh into a Bosphorus-style range grid (virtual scanner looking along ``-z``).

    Args:
        mesh: a :class:`jaxface.mesh.TriMesh`, a ``trimesh.Trimesh`` or ``(vertices (V, 3),
            triangles (F, 3))``, mm, face looking along +z.
        resolution: grid spacing, mm (default :data:`DEFAULT_RESOLUTION_MM`); nodes lie on
            its integer multiples.
        bounds: ``((xmin, ymin), (xmax, ymax))`` mm, the scanned window; default the mesh's
            x/y bounding box.
        landmarks: :class:`jaxface.landmarks.Landmarks` (mm) attached to the scan unchanged
            (they stay where they are on the surface, as in the Bosphorus-style data).
        max_angle_deg: drop samples whose surface normal is more than this many degrees from
            the viewing axis (grazing surfaces a real scanner misses); ``None`` keeps all.
            The angle ignores the triangle orientation.
        noise_mm: standard deviation of Gaussian depth noise added to ``z``, mm.
        seed: seed of the noise generator.
        image_name: texture image name stored in the ``.bnt`` header.
        path: optional file name recorded in the scan (parsed as a Bosphorus name).
        zmin: background sentinel written to ``.bnt`` files.
        return_hits: also return the :class:`GridHits` (to carry per-vertex fields over).

    Returns:
        a grid :class:`jaxface.io.Scan` (mm), or ``(scan, hits)`` with ``return_hits``.

    Raises:
        MeshError: malformed mesh arrays.
        ScanFormatError: non-positive resolution or noise, a grid larger than
            :data:`MAX_GRID_PIXELS` or 65535 per side, or no ray hitting the mesh.
    """
    V, T = _as_arrays(mesh)
    res = float(resolution)
    if not (np.isfinite(res) and res > 0):
        raise ScanFormatError(
            f"scan resolution must be a positive number of mm, got {resolution!r}."
        )
    if not (np.isfinite(noise_mm) and noise_mm >= 0):
        raise ScanFormatError(f"noise_mm must be a non-negative number of mm, got {noise_mm!r}.")
    if max_angle_deg is not None and not (0 < float(max_angle_deg) <= 90):
        raise ScanFormatError(f"max_angle_deg must lie in (0, 90] degrees, got {max_angle_deg!r}.")
    if T.shape[0] == 0:
        raise MeshError("the mesh has no triangles; nothing to scan.", problem="empty")
    used = V[np.unique(T)]
    if bounds is None:
        lo, hi = used[:, :2].min(0), used[:, :2].max(0)
    else:
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape != (2, 2) or not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
            raise ScanFormatError(
                f"bounds must be ((xmin, ymin), (xmax, ymax)) mm with max > min, got {bounds!r}."
            )
        lo, hi = b
    xs = grid_axes(lo[0], hi[0], res)
    ys = grid_axes(lo[1], hi[1], res)
    nr, nc = ys.size, xs.size
    if nr == 0 or nc == 0:
        raise ScanFormatError(
            f"the scan window {lo.tolist()}..{hi.tolist()} mm holds no grid node at "
            f"resolution {res:g} mm; widen the bounds or lower the resolution."
        )
    if nr > 65535 or nc > 65535 or nr * nc > MAX_GRID_PIXELS:
        raise ScanFormatError(
            f"a {nr} x {nc} grid at {res:g} mm is too large (limit {MAX_GRID_PIXELS} pixels, 65535 "
            f"per side): is the mesh in mm (extent {hi - lo} mm)? Use a coarser resolution or "
            f"give the input units."
        )
    hits = cast_grid(V, T, xs, ys)
    valid = np.array(hits.valid)
    xyz = np.array(hits.xyz)
    if max_angle_deg is not None and valid.any():
        n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
        nz = np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
        steep = valid & (
            nz[np.maximum(hits.triangle, 0)] < np.cos(np.radians(float(max_angle_deg)))
        )
        valid &= ~steep
    if not valid.any():
        raise ScanFormatError(
            f"no ray of the {nr} x {nc} grid ({res:g} mm) hits the mesh inside the window "
            f"{lo.tolist()}..{hi.tolist()} mm; check the bounds and that the face looks along +z."
        )
    if noise_mm > 0:
        rng = np.random.default_rng(seed)
        xyz[valid, 2] += rng.normal(0.0, float(noise_mm), int(valid.sum()))
    xyz[~valid] = 0.0
    scan = Scan.from_grid(
        xyz, valid, zmin=zmin, image_name=image_name, landmarks=landmarks, path=path
    )
    if return_hits:
        if not np.array_equal(valid, hits.valid):
            hits = dataclasses.replace(
                hits,
                valid=valid,
                triangle=np.where(valid, hits.triangle, -1),
                bary=np.where(valid[..., None], hits.bary, 0.0),
                xyz=np.where(valid[..., None], hits.xyz, np.nan),
            )
        return scan, hits
    return scan


@dataclasses.dataclass(frozen=True)
class SkinLandmarks:
    """Landmarks bound to a skin mesh, carried along when the skin deforms.

    Each landmark is attached to the closest point of the rest skin (triangle id and
    barycentric coordinates), then evaluated on any deformed copy of the same topology: the
    landmarks of a synthesised expression are where the skin took them.

    Attributes:
        names: landmark labels; triangles: ``(K,)`` triangle ids; bary: ``(K, 3)``
            barycentric coordinates; skin_triangles: ``(F, 3)`` the skin's triangles.
    """

    names: tuple
    triangles: np.ndarray
    bary: np.ndarray
    skin_triangles: np.ndarray

    @classmethod
    def bind(cls, rest, triangles, landmarks: Landmarks) -> SkinLandmarks:
        """Bind ``landmarks`` (mm) to the rest skin ``(V, 3)`` mm with ``(F, 3)`` triangles."""
        tris = np.asarray(triangles)
        cp = SurfaceIndex(np.asarray(rest, dtype=np.float64), tris).query(
            np.asarray(landmarks.positions)
        )
        return cls(tuple(landmarks.names), np.asarray(cp.triangles), np.asarray(cp.bary), tris)

    @classmethod
    def of_rig(cls, rig) -> SkinLandmarks:
        """The rig's own landmarks (``rig.info.landmarks``) on its rest skin."""
        return cls.bind(np.asarray(rig.rest), np.asarray(rig.triangles), rig.info.landmarks)

    def positions(self, vertices) -> np.ndarray:
        """``(K, 3)`` landmark positions on deformed skin vertices ``(V, 3)``, mm."""
        x = np.asarray(vertices, dtype=np.float64)
        return np.einsum("kc,kcd->kd", self.bary, x[self.skin_triangles[self.triangles]])

    def landmarks(self, vertices) -> Landmarks:
        """The same as a :class:`jaxface.landmarks.Landmarks`."""
        return Landmarks(list(self.names), self.positions(vertices))


def scan_skin(
    vertices,
    bound: SkinLandmarks,
    resolution: float = 1.0,
    *,
    max_angle_deg: float | None = 80.0,
    **kwargs,
) -> Scan:
    """Bosphorus-style scan of a (simulated) skin with its landmarks carried along.

    Args:
        vertices: ``(V, 3)`` skin vertices, mm (the topology ``bound`` was made on).
        bound: :class:`SkinLandmarks` of that skin.
        resolution: grid spacing, mm.
        max_angle_deg: grazing-angle cut-off (see :func:`scan_mesh`).
        **kwargs: passed to :func:`scan_mesh` (``noise_mm``, ``path``, ...).

    Returns:
        the grid :class:`jaxface.io.Scan` (mm) with the landmarks at their deformed positions.
    """
    x = np.asarray(vertices, dtype=np.float64)
    return scan_mesh(
        (x, bound.skin_triangles),
        resolution,
        landmarks=bound.landmarks(x),
        max_angle_deg=max_angle_deg,
        **kwargs,
    )
