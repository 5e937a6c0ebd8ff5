"""The orthographic camera of the rasteriser: named :data:`VIEWS` (azimuth about +y,
elevation, degrees), :class:`Camera` and :func:`camera` (framing points given in mm)."""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["VIEWS", "Camera", "camera"]

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
