"""Headless pictures of meshes (NumPy z-buffer rasteriser + matplotlib figures).

Everything here is build-time/post-processing NumPy (never on the jit path) and works with
the ``Agg`` backend, so it runs on machines without a display.

The core is :func:`rasterize`: an orthographic, z-buffered, supersampled software rasteriser
with smooth (interpolated vertex normal) Lambert + a little specular shading from a headlight.
It renders one or more :class:`Layer` s (a mesh with a flat colour, per-vertex colours or
per-vertex scalars mapped through a colour map) into an RGBA image and keeps the camera, so
that 3D points (landmarks) and 3D polylines (muscles) can be drawn over the picture with
occlusion tests (:meth:`Render.project`, :meth:`Render.visible`).

On top of that, :func:`draw` puts a render into a matplotlib ``Axes`` (with landmarks, labels,
polylines), and :func:`figure_views` / :func:`save_views` build a figure with several views
(front + side by default) and a colour bar when scalars are shown (error heat maps in mm).

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.
Named views (``VIEWS``) give the camera direction by azimuth about +y (0 = camera on +z, in
front of the face; 90 = camera on +x, the subject's left) and elevation (positive = from
above). ``"side"`` is the subject's left profile (the face looks to the left of the image).

Example::

    from jaxface import generic_head
    from jaxface.render import save_views
    head = generic_head()
    save_views("head.png", head.mesh, landmarks=head.landmarks, labels=True)
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .normals import vertex_normals as _vertex_normals

__all__ = [
    "VIEWS",
    "SKIN",
    "Layer",
    "Camera",
    "Render",
    "camera",
    "rasterize",
    "draw",
    "figure_views",
    "save_views",
    "save_figure",
    "as_layers",
    "vertex_normals",
]

#: named views: name -> (azimuth_deg about +y, elevation_deg). Camera on +z looks at the face.
VIEWS: dict[str, tuple[float, float]] = {
    "front": (0.0, 0.0),
    "side": (90.0, 0.0),  # the subject's left profile (camera on +x)
    "left": (90.0, 0.0),  # camera on the subject's left (+x)
    "right": (-90.0, 0.0),  # camera on the subject's right (-x)
    "back": (180.0, 0.0),
    "top": (0.0, 89.0),
    "bottom": (0.0, -89.0),
    "three_quarter": (35.0, 10.0),  # from the front-left and a little above
    "three_quarter_right": (-35.0, 10.0),
}

#: default skin colour (linear-ish RGB in [0, 1])
SKIN = (0.87, 0.72, 0.62)
_BACKGROUND = (1.0, 1.0, 1.0)


# ----------------------------------------------------------------------------- geometry helpers
def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(V, 3)``; isolated vertices get ``(0, 0, 1)``.

    Args:
        vertices: ``(V, 3)`` positions, mm.
        triangles: ``(F, 3)`` vertex ids, counter-clockwise from outside.
    """
    n = _vertex_normals(vertices, triangles)
    return np.where(np.any(n != 0.0, axis=1, keepdims=True), n, np.array([0.0, 0.0, 1.0]))


@dataclasses.dataclass(frozen=True)
class Layer:
    """One mesh to draw.

    Attributes:
        vertices: ``(V, 3)`` positions, mm.
        triangles: ``(F, 3)`` vertex ids.
        color: flat RGB colour in ``[0, 1]`` (used when neither ``colors`` nor ``scalars``).
        colors: optional ``(V, 3)`` per-vertex RGB in ``[0, 1]`` (interpolated).
        scalars: optional ``(V,)`` per-vertex values (e.g. an error in mm), mapped through
            ``cmap`` between ``vmin`` and ``vmax`` (default: the min/max of the finite
            values); NaN scalars are drawn in ``color``.
        cmap: matplotlib colour-map name for ``scalars``.
        vmin, vmax: colour range of ``scalars`` (same unit as the scalars).
        shade: 0..1, how much Lambert shading modulates the colour (1 = full shading; heat
            maps use ~0.5 so colours stay readable).
        specular: strength of the highlight.
        label: optional name (legend/colour-bar label).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    color: tuple[float, float, float] = SKIN
    colors: np.ndarray | None = None
    scalars: np.ndarray | None = None
    cmap: str = "viridis"
    vmin: float | None = None
    vmax: float | None = None
    shade: float = 1.0
    specular: float = 0.12
    label: str | None = None

    def scalar_range(self) -> tuple[float, float]:
        """``(vmin, vmax)`` used for the scalars (explicit values or the finite min/max)."""
        s = np.asarray(self.scalars, dtype=np.float64)
        finite = s[np.isfinite(s)]
        lo = self.vmin if self.vmin is not None else (float(finite.min()) if finite.size else 0.0)
        hi = self.vmax if self.vmax is not None else (float(finite.max()) if finite.size else 1.0)
        if not hi > lo:
            hi = lo + 1.0
        return float(lo), float(hi)

    def vertex_colors(self) -> np.ndarray:
        """``(V, 3)`` RGB per vertex from ``colors`` / ``scalars`` / ``color``."""
        nv = len(self.vertices)
        if self.scalars is not None:
            import matplotlib

            s = np.asarray(self.scalars, dtype=np.float64).reshape(-1)
            if s.shape[0] != nv:
                raise ValueError(f"scalars has {s.shape[0]} values for {nv} vertices")
            lo, hi = self.scalar_range()
            cm = matplotlib.colormaps[self.cmap]
            rgb = cm(np.clip((np.nan_to_num(s, nan=lo) - lo) / (hi - lo), 0.0, 1.0))[:, :3]
            rgb[~np.isfinite(s)] = self.color
            return rgb
        if self.colors is not None:
            c = np.asarray(self.colors, dtype=np.float64)
            if c.shape != (nv, 3):
                raise ValueError(f"colors must be ({nv}, 3), got {c.shape}")
            return np.clip(c, 0.0, 1.0)
        return np.broadcast_to(np.asarray(self.color, dtype=np.float64), (nv, 3))


def as_layers(meshes: Any, **layer_kwargs) -> list[Layer]:
    """Normalise ``meshes`` to a list of :class:`Layer`.

    Accepts a :class:`Layer`, anything with ``.vertices`` and ``.triangles`` (``TriMesh``,
    ``trimesh.Trimesh``), a ``(vertices, triangles)`` tuple, or a list of these.
    ``layer_kwargs`` apply to the items that are not already layers.
    """
    if isinstance(meshes, Layer):
        return [meshes]
    if hasattr(meshes, "vertices") and hasattr(meshes, "faces"):  # trimesh.Trimesh
        return [Layer(np.asarray(meshes.vertices), np.asarray(meshes.faces), **layer_kwargs)]
    if hasattr(meshes, "vertices") and hasattr(meshes, "triangles"):  # TriMesh
        return [Layer(np.asarray(meshes.vertices), np.asarray(meshes.triangles), **layer_kwargs)]
    if (
        isinstance(meshes, tuple)
        and len(meshes) == 2
        and np.ndim(meshes[0]) == 2
        and np.ndim(meshes[1]) == 2
    ):
        return [Layer(np.asarray(meshes[0]), np.asarray(meshes[1]), **layer_kwargs)]
    if isinstance(meshes, Iterable):
        out: list[Layer] = []
        for m in meshes:
            out.extend(as_layers(m, **layer_kwargs))
        return out
    raise TypeError(f"cannot draw an object of type {type(meshes).__name__}")


# ----------------------------------------------------------------------------- camera
@dataclasses.dataclass(frozen=True)
class Camera:
    """Orthographic camera.

    Attributes:
        right, up, toward: ``(3,)`` orthonormal basis; ``toward`` points from the scene to the
            camera (larger ``p . toward`` = closer).
        center: ``(2,)`` image-plane point (mm) at the image centre.
        scale: pixels per mm.
        width, height: image size in pixels.
    """

    right: np.ndarray
    up: np.ndarray
    toward: np.ndarray
    center: np.ndarray
    scale: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> np.ndarray:
        """``(..., 3)`` world points (mm) -> ``(..., 3)``: pixel column, pixel row, depth (mm,
        larger = closer to the camera). Pixel centres are at half-integers."""
        p = np.asarray(points, dtype=np.float64)
        u = p @ self.right
        v = p @ self.up
        d = p @ self.toward
        col = (u - self.center[0]) * self.scale + 0.5 * self.width
        row = (self.center[1] - v) * self.scale + 0.5 * self.height
        return np.stack([col, row, d], axis=-1)


def _view_basis(view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(
                f"unknown view {view!r}; use one of {sorted(VIEWS)} or (azimuth, elevation)"
            )
        az, el = VIEWS[view]
    else:
        az, el = (float(a) for a in view)
    a, e = np.deg2rad(az), np.deg2rad(el)
    toward = np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])
    world_up = np.array([0.0, 1.0, 0.0])
    right = np.cross(world_up, toward)
    if np.linalg.norm(right) < 1e-8:  # straight from above/below
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(toward, right)
    return right, up, toward


def camera(
    view,
    points: np.ndarray,
    width: int = 512,
    height: int = 512,
    *,
    margin: float = 0.06,
    bounds: np.ndarray | None = None,
) -> Camera:
    """A camera for ``view`` framing ``points`` (``(N, 3)`` mm) or the world box ``bounds``.

    Args:
        view: a name from :data:`VIEWS` or ``(azimuth_deg, elevation_deg)``.
        points: ``(N, 3)`` points that must be in the picture, mm.
        width, height: image size, pixels.
        margin: free border as a fraction of the image size.
        bounds: optional ``(2, 3)`` world box (mm) to frame instead of ``points`` (use the same
            box for several panels so that they share a scale).
    """
    right, up, toward = _view_basis(view)
    if bounds is not None:
        b = np.asarray(bounds, dtype=np.float64)
        corners = np.array(
            [[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        )
        pts = corners
    else:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    u, v = pts @ right, pts @ up
    umin, umax, vmin, vmax = u.min(), u.max(), v.min(), v.max()
    extent_u = max(umax - umin, 1e-9)
    extent_v = max(vmax - vmin, 1e-9)
    usable = 1.0 - 2.0 * margin
    scale = min(width * usable / extent_u, height * usable / extent_v)
    center = np.array([(umin + umax) / 2, (vmin + vmax) / 2])
    return Camera(right, up, toward, center, float(scale), int(width), int(height))


# ----------------------------------------------------------------------------- rasteriser
@dataclasses.dataclass
class Render:
    """Result of :func:`rasterize`.

    Attributes:
        image: ``(H, W, 4)`` float RGBA in ``[0, 1]`` (alpha 0 on the background).
        depth: ``(H, W)`` depth of the nearest surface (mm along the view direction, larger =
            closer), ``-inf`` on the background (from the central sample of each pixel).
        camera: the :class:`Camera` used.
        layers: the layers drawn.
    """

    image: np.ndarray
    depth: np.ndarray
    camera: Camera
    layers: list[Layer]

    def project(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` world points, mm -> ``(N, 3)`` pixel column, row, depth."""
        return self.camera.project(points)

    def visible(self, points: np.ndarray, tol: float = 1.5) -> np.ndarray:
        """``(N,)`` bool: the points are inside the image and not hidden behind a surface by
        more than ``tol`` mm."""
        p = self.project(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        h, w = self.depth.shape
        col = np.floor(p[:, 0]).astype(np.int64)
        row = np.floor(p[:, 1]).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(len(p), dtype=bool)
        if inside.any():
            # the nearest surface in a 3x3 neighbourhood (points sit on silhouettes and edges)
            best = np.full(inside.sum(), -np.inf)
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    r = np.clip(row[inside] + dr, 0, h - 1)
                    c = np.clip(col[inside] + dc, 0, w - 1)
                    best = np.maximum(
                        best, np.where(np.isfinite(self.depth[r, c]), self.depth[r, c], -np.inf)
                    )
            # visible if nothing is clearly in front of the point; on background -> visible
            out[inside] = (p[inside, 2] >= best - tol) | ~np.isfinite(best)
        return out


def _light_dir(right, up, toward) -> np.ndarray:
    """Headlight from the camera, a little from the upper left of the picture."""
    d = toward + 0.35 * up - 0.25 * right
    return d / np.linalg.norm(d)


def rasterize(
    meshes,
    view: str | tuple[float, float] = "front",
    width: int = 512,
    height: int = 512,
    *,
    supersample: int = 2,
    bounds: np.ndarray | None = None,
    cam: Camera | None = None,
    background=_BACKGROUND,
    cull_backfaces: bool = False,
) -> Render:
    """Render meshes into an RGBA image with a z-buffer (orthographic, smooth shading).

    Args:
        meshes: what :func:`as_layers` accepts (``TriMesh``, ``(V, F)`` tuples, layers, lists).
        view: a name from :data:`VIEWS` or ``(azimuth_deg, elevation_deg)``.
        width, height: output size in pixels.
        supersample: samples per pixel along each axis (anti-aliasing); 1 disables it.
        bounds: optional ``(2, 3)`` world box (mm) to frame (shared scale between panels).
        cam: an explicit camera (overrides ``view``/``bounds``; its size must be
            ``width x height``).
        background: RGB of the background.
        cull_backfaces: skip triangles facing away from the camera (faster; hides the inside
            of a mesh seen through its holes).

    Returns:
        a :class:`Render` (image, depth map and camera).

    The default head with eyes and teeth (~39k triangles) at 512 x 512 with 2x supersampling
    takes ~0.3 s of CPU.
    """
    layers = as_layers(meshes)
    if not layers:
        raise ValueError("nothing to render: no meshes given")
    ss = max(int(supersample), 1)
    all_pts = np.concatenate(
        [np.asarray(L.vertices, dtype=np.float64).reshape(-1, 3) for L in layers]
    )
    if cam is None:
        cam = camera(view, all_pts, width, height, bounds=bounds)
    W, H = cam.width * ss, cam.height * ss
    right, up, toward = cam.right, cam.up, cam.toward
    light = _light_dir(right, up, toward)

    # gather all triangles of all layers
    P_list, N_list, C_list, T_list, S_list = [], [], [], [], []
    offset = 0
    for L in layers:
        v = np.asarray(L.vertices, dtype=np.float64)
        t = np.asarray(L.triangles, dtype=np.int64)
        if len(t) == 0:
            continue
        P_list.append(cam.project(v))
        N_list.append(vertex_normals(v, t))
        C_list.append(np.asarray(L.vertex_colors(), dtype=np.float64))
        S_list.append(np.broadcast_to(np.array([L.shade, L.specular]), (len(v), 2)))
        T_list.append(t + offset)
        offset += len(v)
    P = np.concatenate(P_list)
    P[:, 0] *= ss
    P[:, 1] *= ss
    Nrm = np.concatenate(N_list)
    Col = np.concatenate(C_list)
    Shd = np.concatenate(S_list)
    T = np.concatenate(T_list)

    # per-triangle screen geometry
    x0, y0, z0 = (P[T[:, 0], k] for k in range(3))
    x1, y1, z1 = (P[T[:, 1], k] for k in range(3))
    x2, y2, z2 = (P[T[:, 2], k] for k in range(3))
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)  # signed, in pixel^2 (rows grow down)
    keep = np.abs(area2) > 1e-12
    if cull_backfaces:
        # rows grow downwards, so a counter-clockwise triangle facing the camera has a
        # negative signed screen area
        keep &= area2 < 0
    ymin = np.clip(np.ceil(np.minimum(np.minimum(y0, y1), y2) - 0.5), 0, H).astype(np.int64)
    ymax = np.clip(np.floor(np.maximum(np.maximum(y0, y1), y2) - 0.5), -1, H - 1).astype(np.int64)
    nrows = np.where(keep, np.maximum(ymax - ymin + 1, 0), 0)

    # edge functions per triangle: w_k(cx, cy) = A_k * cx + B_k * cy + C_k (barycentrics)
    inv = np.where(keep, 1.0 / np.where(keep, area2, 1.0), 0.0)
    A0, B0 = (y1 - y2) * inv, (x2 - x1) * inv
    C0 = (x1 * y2 - x2 * y1) * inv
    A1, B1 = (y2 - y0) * inv, (x0 - x2) * inv
    C1 = (x2 * y0 - x0 * y2) * inv

    # 1) row spans: for each (triangle, pixel row) the covered columns
    tri_r = np.repeat(np.arange(len(T)), nrows)
    row = np.arange(tri_r.size) - np.repeat(np.cumsum(nrows) - nrows, nrows) + ymin[tri_r]
    cy = row + 0.5
    xl = np.full(tri_r.size, np.inf)
    xr = np.full(tri_r.size, -np.inf)
    for xa, ya, xb, yb in ((x0, y0, x1, y1), (x1, y1, x2, y2), (x2, y2, x0, y0)):
        xa_, ya_, xb_, yb_ = xa[tri_r], ya[tri_r], xb[tri_r], yb[tri_r]
        lo, hi = np.minimum(ya_, yb_), np.maximum(ya_, yb_)
        ok = (cy >= lo) & (cy <= hi) & (hi > lo)
        dy = np.where(ok, yb_ - ya_, 1.0)
        xc = xa_ + (cy - ya_) * (xb_ - xa_) / dy
        xl = np.where(ok, np.minimum(xl, xc), xl)
        xr = np.where(ok, np.maximum(xr, xc), xr)
    c0 = np.clip(np.ceil(xl - 0.5), 0, W).astype(np.int64)
    c1 = np.clip(np.floor(xr - 0.5), -1, W - 1).astype(np.int64)
    ncol = np.where(np.isfinite(xl), np.maximum(c1 - c0 + 1, 0), 0)

    zbuf = np.full(W * H, -np.inf)
    owner = np.full(W * H, -1, dtype=np.int64)  # winning triangle per sample
    bary_best = np.zeros((W * H, 2))

    # 2) pixels of the spans, in chunks so memory stays bounded
    span_ids = np.nonzero(ncol > 0)[0]
    csum = np.cumsum(ncol[span_ids])
    chunk = 2_000_000
    start = 0
    while start < len(span_ids):
        base = csum[start - 1] if start > 0 else 0
        stop = max(int(np.searchsorted(csum, base + chunk, side="right")), start + 1)
        ids = span_ids[start:stop]
        n = ncol[ids]
        span = np.repeat(ids, n)
        px = np.arange(span.size) - np.repeat(np.cumsum(n) - n, n) + c0[span]
        py = row[span]
        tri = tri_r[span]
        cxp, cyp = px + 0.5, py + 0.5
        w0 = np.clip(A0[tri] * cxp + B0[tri] * cyp + C0[tri], 0.0, 1.0)
        w1 = np.clip(A1[tri] * cxp + B1[tri] * cyp + C1[tri], 0.0, 1.0 - w0)
        depth = z2[tri] + w0 * (z0[tri] - z2[tri]) + w1 * (z1[tri] - z2[tri])
        pix = py * W + px
        np.maximum.at(zbuf, pix, depth)
        win = depth >= zbuf[pix]
        pw = pix[win]
        owner[pw] = tri[win]
        bary_best[pw, 0] = w0[win]
        bary_best[pw, 1] = w1[win]
        start = stop

    # Gouraud shading: light every vertex (both sides), interpolate the colour per sample
    half = light + toward
    half /= np.linalg.norm(half)
    lit = []
    for sign, dim in ((1.0, 1.0), (-1.0, 0.45)):  # outside, and inside seen through holes
        nn = sign * Nrm
        lam = np.clip(nn @ light, 0.0, 1.0)
        diffuse = 1.0 - Shd[:, 0] * (1.0 - (0.28 + 0.72 * lam))
        spec = Shd[:, 1] * np.clip(nn @ half, 0.0, 1.0) ** 24
        lit.append(dim * np.clip(Col * diffuse[:, None] + spec[:, None], 0.0, 1.0))
    vcol = np.concatenate(lit).astype(np.float32)
    nv = len(Nrm)
    hit = owner >= 0
    rgb = np.empty((W * H, 3), dtype=np.float32)
    rgb[:] = background
    if hit.any():
        tri = owner[hit]
        back = (area2[tri] > 0).astype(np.int64) * nv  # facing away: use the inside colours
        b0 = bary_best[hit, 0].astype(np.float32)[:, None]
        b1 = bary_best[hit, 1].astype(np.float32)[:, None]
        c = vcol[T[tri, 2] + back]
        c += b0 * (vcol[T[tri, 0] + back] - c) + b1 * (vcol[T[tri, 1] + back] - c)
        rgb[hit] = c
    alpha = hit.astype(np.float64)
    img = np.concatenate([rgb.reshape(H, W, 3), alpha.reshape(H, W, 1)], axis=2)
    zimg = zbuf.reshape(H, W)
    if ss > 1:
        img = img.reshape(cam.height, ss, cam.width, ss, 4).mean(axis=(1, 3))
        zimg = zimg.reshape(cam.height, ss, cam.width, ss)[:, ss // 2, :, ss // 2]
    return Render(image=img, depth=zimg, camera=cam, layers=layers)


# ----------------------------------------------------------------------------- matplotlib
def _landmark_arrays(landmarks) -> tuple[list[str], np.ndarray]:
    """Accept a ``Landmarks`` object, a ``{name: (3,)}`` mapping, or an ``(N, 3)`` array."""
    if landmarks is None:
        return [], np.zeros((0, 3))
    if hasattr(landmarks, "names") and hasattr(landmarks, "positions"):
        return list(landmarks.names), np.asarray(landmarks.positions, dtype=np.float64).reshape(
            -1, 3
        )
    if isinstance(landmarks, Mapping):
        names = list(landmarks)
        return names, np.asarray([landmarks[k] for k in names], dtype=np.float64).reshape(-1, 3)
    arr = np.asarray(landmarks, dtype=np.float64).reshape(-1, 3)
    return [str(i) for i in range(len(arr))], arr


def draw(
    ax,
    meshes,
    view: str | tuple[float, float] = "front",
    *,
    width: int = 512,
    height: int = 512,
    landmarks=None,
    labels: bool = False,
    hidden_landmarks: bool = False,
    landmark_color="tab:red",
    polylines: Sequence[np.ndarray] | None = None,
    polyline_colors=None,
    polyline_width: float = 1.5,
    bounds=None,
    title: str | None = None,
    supersample: int = 2,
    render: Render | None = None,
    label_fontsize: float = 5.5,
) -> Render:
    """Render ``meshes`` and show them in the matplotlib axes ``ax``.

    Args:
        ax: a matplotlib ``Axes``.
        meshes: what :func:`as_layers` accepts.
        view: a name from :data:`VIEWS` or ``(azimuth_deg, elevation_deg)``.
        width, height: render size in pixels.
        landmarks: optional ``Landmarks`` / ``{name: (3,)}`` / ``(N, 3)`` array, mm.
        labels: write the landmark names next to the points.
        hidden_landmarks: also draw landmarks hidden behind the surface (hollow markers).
        polylines: optional list of ``(n_i, 3)`` 3D polylines (mm), e.g. muscle action lines;
            hidden parts are drawn dashed.
        polyline_colors: one colour or a list of colours for the polylines.
        bounds: ``(2, 3)`` world box (mm) to frame (shared scale between panels).
        title: axes title.
        render: reuse an existing :class:`Render` instead of rasterising again.

    Returns:
        the :class:`Render` (for further overlays with :meth:`Render.project`).
    """
    if render is None:
        render = rasterize(meshes, view, width, height, bounds=bounds, supersample=supersample)
    img = render.image
    ax.imshow(img, interpolation="lanczos" if max(img.shape[:2]) < 400 else "antialiased")
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=9)
    names, pts = _landmark_arrays(landmarks)
    if len(pts):
        proj = render.project(pts)
        vis = render.visible(pts)
        ax.scatter(
            proj[vis, 0] - 0.5,
            proj[vis, 1] - 0.5,
            s=14,
            c=landmark_color,
            edgecolors="white",
            linewidths=0.5,
            zorder=3,
        )
        if hidden_landmarks and (~vis).any():
            ax.scatter(
                proj[~vis, 0] - 0.5,
                proj[~vis, 1] - 0.5,
                s=12,
                facecolors="none",
                edgecolors=landmark_color,
                linewidths=0.6,
                alpha=0.6,
                zorder=3,
            )
        if labels:
            for name, (c, r, _), v in zip(names, proj, vis):
                if v:
                    ax.annotate(
                        name,
                        (c - 0.5, r - 0.5),
                        xytext=(3, 2),
                        textcoords="offset points",
                        fontsize=label_fontsize,
                        color="black",
                        zorder=4,
                    )
    if polylines:
        cols = polyline_colors
        if (
            cols is None
            or isinstance(cols, str)
            or (np.ndim(cols) == 1 and len(cols) in (3, 4) and not isinstance(cols[0], str))
        ):
            cols = [cols if cols is not None else "tab:blue"] * len(polylines)
        for line, c in zip(polylines, cols):
            line = np.asarray(line, dtype=np.float64).reshape(-1, 3)
            pr = render.project(line)
            vis = render.visible(line, tol=3.0)
            ax.plot(
                pr[:, 0] - 0.5,
                pr[:, 1] - 0.5,
                color=c,
                lw=polyline_width * 0.6,
                ls=(0, (2, 2)),
                alpha=0.5,
                zorder=2,
            )
            vv = np.where(vis, pr[:, 1] - 0.5, np.nan)
            ax.plot(pr[:, 0] - 0.5, vv, color=c, lw=polyline_width, zorder=2)
    ax.set_xlim(-0.5, render.camera.width - 0.5)
    ax.set_ylim(render.camera.height - 0.5, -0.5)
    return render


def _scalar_layer(layers: list[Layer]) -> Layer | None:
    for L in layers:
        if L.scalars is not None:
            return L
    return None


def figure_views(
    meshes,
    views: Sequence = ("front", "side"),
    *,
    landmarks=None,
    labels: bool = False,
    scalars: np.ndarray | None = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    colorbar_label: str = "mm",
    title: str | None = None,
    panel_px: int = 480,
    titles: Sequence[str] | None = None,
    polylines=None,
    polyline_colors=None,
    bounds=None,
):
    """A matplotlib figure with one panel per view (front + side by default).

    Args:
        meshes: what :func:`as_layers` accepts. ``scalars``/``cmap``/``vmin``/``vmax`` apply to
            the first layer (e.g. a per-vertex error in mm), which adds a colour bar.
        views: view names or ``(azimuth, elevation)`` pairs.
        landmarks: optional landmarks (mm) drawn on every panel.
        labels: write landmark names (on the first panel only, to keep the figure readable).
        colorbar_label: label of the colour bar (say the unit).
        title: figure title.
        panel_px: pixels per panel side.
        titles: one title per panel (default: the view names).
        polylines, polyline_colors: 3D polylines drawn on every panel (see :func:`draw`).
        bounds: ``(2, 3)`` world box (mm) framing every panel.

    Returns:
        ``matplotlib.figure.Figure``.
    """
    import matplotlib
    import matplotlib.cm
    import matplotlib.colors
    from matplotlib.figure import Figure

    layers = as_layers(meshes)
    if scalars is not None:
        layers[0] = dataclasses.replace(
            layers[0],
            scalars=np.asarray(scalars),
            cmap=cmap,
            vmin=vmin,
            vmax=vmax,
            shade=0.55,
            specular=0.04,
        )
    sl = _scalar_layer(layers)
    n = len(views)
    dpi = 100
    cb_w = 1.0 if sl is not None else 0.0
    fig = Figure(
        figsize=(n * panel_px / dpi + cb_w, panel_px / dpi + (0.35 if title else 0.1)), dpi=dpi
    )
    axes = fig.subplots(1, n, squeeze=False)[0]
    if bounds is None:
        allp = np.concatenate([np.asarray(L.vertices).reshape(-1, 3) for L in layers])
        bounds = np.stack([allp.min(0), allp.max(0)])
    fig.subplots_adjust(
        left=0.005,
        right=0.995 - (0.9 / fig.get_figwidth() if sl is not None else 0.0),
        bottom=0.005,
        top=0.99 - (0.35 / fig.get_figheight() if title else 0.0) - 0.04,
        wspace=0.02,
    )
    for i, (ax, v) in enumerate(zip(axes, views)):
        name = (
            titles[i]
            if titles is not None
            else (v if isinstance(v, str) else f"az {v[0]:g}, el {v[1]:g}")
        )
        draw(
            ax,
            layers,
            v,
            width=panel_px,
            height=panel_px,
            landmarks=landmarks,
            labels=labels and i == 0,
            title=name,
            polylines=polylines,
            polyline_colors=polyline_colors,
            bounds=bounds,
        )
    if sl is not None:
        lo, hi = sl.scalar_range()
        sm = matplotlib.cm.ScalarMappable(
            norm=matplotlib.colors.Normalize(lo, hi), cmap=matplotlib.colormaps[sl.cmap]
        )
        cax = fig.add_axes((1.0 - 0.75 / fig.get_figwidth(), 0.12, 0.18 / fig.get_figwidth(), 0.72))
        cbar = fig.colorbar(sm, cax=cax)
        cbar.set_label(colorbar_label)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def save_figure(fig, path, *, dpi: int | None = None, close: bool = False) -> Path:
    """Write a matplotlib figure (PNG/PDF/SVG by suffix), creating parent folders; ``close``
    also closes the figure (frees it in pyplot's figure manager)."""
    from .atomic import atomic_path, ensure_out_dir

    path = Path(path)
    ensure_out_dir(path.parent, "picture folder")
    with atomic_path(path) as tmp:  # written whole or not at all
        fig.savefig(tmp, dpi=dpi or fig.dpi, facecolor="white")
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)
    return path


def save_views(path, meshes, views: Sequence = ("front", "side"), **kwargs) -> Path:
    """Render ``meshes`` from ``views`` with :func:`figure_views` and write the picture.

    Args:
        path: output file (``.png`` recommended).
        meshes: what :func:`as_layers` accepts.
        views: view names or ``(azimuth, elevation)`` pairs.
        **kwargs: passed to :func:`figure_views` (landmarks, labels, scalars, colorbar_label...).

    Returns:
        the path written.
    """
    os.environ.setdefault("MPLBACKEND", "Agg")
    fig = figure_views(meshes, views, **kwargs)
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- heads
IRIS = (0.36, 0.42, 0.46)
SCLERA = (0.94, 0.93, 0.90)
TEETH = (0.95, 0.93, 0.84)


def eye_colors(
    vertices: np.ndarray,
    center: np.ndarray,
    gaze=(0.0, 0.0, 1.0),
    *,
    iris_deg: float = 28.0,
    pupil_deg: float = 11.0,
    iris=IRIS,
) -> np.ndarray:
    """``(V, 3)`` RGB of an eyeball mesh: pupil, iris and sclera by the angle between each
    vertex direction (from ``center``, mm) and the gaze direction."""
    d = np.asarray(vertices, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    g = np.asarray(gaze, dtype=np.float64)
    g = g / np.linalg.norm(g)
    ang = np.degrees(np.arccos(np.clip(d @ g, -1.0, 1.0)))
    col = np.tile(np.asarray(SCLERA), (len(d), 1))
    t = _smooth01((iris_deg + 1.5 - ang) / 3.0)  # soft limbus
    col = col * (1 - t[:, None]) + np.asarray(iris) * t[:, None]
    p = _smooth01((pupil_deg + 1.0 - ang) / 2.0)
    col = col * (1 - p[:, None]) + 0.04 * p[:, None]
    return col


def _smooth01(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def head_layers(
    head,
    *,
    skin=None,
    scalars=None,
    cmap: str = "viridis",
    vmin=None,
    vmax=None,
    skin_color=SKIN,
    eyes=None,
    upper_teeth=None,
    lower_teeth=None,
    show_eyes: bool = True,
    show_teeth: bool = True,
) -> list[Layer]:
    """Layers for a :class:`jaxface.head.Head`: skin, eyeballs (with iris and pupil) and teeth.

    Any part can be given as deformed ``(V, 3)`` vertex positions (mm) of the same topology
    (``skin``, ``eyes=(left, right)``, ``upper_teeth``, ``lower_teeth``), e.g. a simulated
    expression. ``scalars`` (``(V,)``, e.g. an error in mm) colour the skin through ``cmap``.
    """
    sv = head.mesh.vertices if skin is None else np.asarray(skin)
    layers = [
        Layer(
            sv,
            head.mesh.triangles,
            color=skin_color,
            scalars=scalars,
            cmap=cmap,
            vmin=vmin,
            vmax=vmax,
            shade=0.55 if scalars is not None else 1.0,
            specular=0.04 if scalars is not None else 0.12,
            label="skin",
        )
    ]
    if show_eyes:
        for k, (mesh, c) in enumerate(zip(head.eyes, head.eye_centers)):
            v = mesh.vertices if eyes is None else np.asarray(eyes[k])
            shift = v.mean(axis=0) - mesh.vertices.mean(axis=0)
            layers.append(
                Layer(
                    v,
                    mesh.triangles,
                    colors=eye_colors(v, c + shift),
                    specular=0.35,
                    label=f"eye_{'left' if k == 0 else 'right'}",
                )
            )
    if show_teeth:
        for mesh, v, name in (
            (head.upper_teeth, upper_teeth, "upper_teeth"),
            (head.lower_teeth, lower_teeth, "lower_teeth"),
        ):
            layers.append(
                Layer(
                    mesh.vertices if v is None else np.asarray(v),
                    mesh.triangles,
                    color=TEETH,
                    specular=0.2,
                    label=name,
                )
            )
    return layers
