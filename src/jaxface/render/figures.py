"""Matplotlib figures of renders: :func:`draw` (a render with landmarks, labels and polylines
into an ``Axes``), :func:`figure_views` / :func:`save_views` (several views, colour bar for
scalars in mm) and :func:`save_figure`."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, ensure_out_dir
from .layers import Layer, as_layers
from .raster import Render, rasterize

__all__ = ["draw", "figure_views", "save_views", "save_figure"]


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
