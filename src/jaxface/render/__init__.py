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

Layout: :mod:`.layers` (:class:`Layer`), :mod:`.camera` (views, :class:`Camera`),
:mod:`.raster` (:func:`rasterize`, :class:`Render`), :mod:`.figures` (matplotlib figures),
:mod:`.heads` (head colours and layers).
"""

from __future__ import annotations

from .camera import VIEWS, Camera, camera
from .figures import draw, figure_views, save_figure, save_views
from .heads import IRIS as IRIS  # not in __all__ (as before), still importable
from .heads import SCLERA as SCLERA
from .heads import TEETH as TEETH
from .heads import eye_colors as eye_colors
from .heads import head_layers as head_layers
from .layers import SKIN, Layer, as_layers, vertex_normals
from .raster import Render, rasterize

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
