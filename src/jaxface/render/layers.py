"""What to draw: :class:`Layer` (a mesh in mm with a flat colour, per-vertex colours or
scalars through a colour map), :func:`as_layers`, and the rendering's vertex normals."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np

from ..normals import vertex_normals as _vertex_normals

__all__ = ["SKIN", "Layer", "as_layers", "vertex_normals"]

#: default skin colour (linear-ish RGB in [0, 1])
SKIN = (0.87, 0.72, 0.62)


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
