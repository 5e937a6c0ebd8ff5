"""Eyelid vertices of the skin (thesis sec. 5.7): the vertices near each eye border that rotate
about the axis through the eye corners, with the taper toward the corners (mm, radians).
"""

from __future__ import annotations

import numpy as np

from ..mesh import TriMesh
from .frame import FaceFrame
from .skin_binding import _smoothstep

#: Fraction of the eye width, from each corner, over which the lid rotation grows from 0 to
#: full (:func:`eyelid_vertices`); 0 turns the taper off. The tapered lids move less, and the
#: fit sees the lid controls less: the synthetic round trip's condition number on the ICT
#: face went from 217 to 1590 (its smallest singular value is a lid control held at 0).
LID_CORNER_TAPER = 0.4


def eyelid_vertices(skin: TriMesh, frame: FaceFrame, side: str, threshold: float = 0.04):
    """The lid vertices of one eye (thesis sec. 5.5.1).

    The eye border is the skin boundary loop around the eye (when the skin has an eye
    opening) or else the vertices closest to the segment between the eye corners. Vertices
    whose normalised geodesic distance from the border is below ``threshold`` are lid
    vertices.

    Returns:
        ``(ids (K,), falloff (K,) in (0, 1], upper (K,) bool)``; the falloff is the
        geodesic one times a taper that is 0 at the eye corners and 1 from
        :data:`LID_CORNER_TAPER` of the eye width inward.
    """
    inner = frame.points[f"Inner {side} eye corner"]
    outer = frame.points[f"Outer {side} eye corner"]
    centre = 0.5 * (inner + outer)
    width = np.linalg.norm(outer - inner)
    border = None
    for loop in skin.boundary_loops:
        c = skin.vertices[loop].mean(axis=0)
        ext = np.ptp(skin.vertices[loop], axis=0).max()
        if np.linalg.norm(c - centre) < 0.35 * width and ext < 2.0 * width:
            border = np.asarray(loop)
            break
    if border is None:
        # vertices closest to the corner-to-corner segment
        x = skin.vertices
        u = outer - inner
        t = np.clip(((x - inner) @ u) / (u @ u), 0.0, 1.0)
        dist = np.linalg.norm(x - (inner + t[:, None] * u), axis=1)
        border = np.flatnonzero(dist < max(np.sort(dist)[min(8, len(dist) - 1)], 1e-9) + 1e-9)
    d = skin.geodesic_distance(border, normalise=True)
    ids = np.flatnonzero(d < threshold)
    fall = 1.0 - _smoothstep(d[ids] / threshold)
    rel = skin.vertices[ids] - inner
    u = (outer - inner) / width
    # the lids hinge at the eye corners: the pivot axis lies on the eyeball centre, 12 mm
    # behind the corners, so an untapered rotation would swing the corner vertices too and
    # fold the upper lid over the lower one there (on the ICT face AU43 inverted 90 skin
    # triangles and AU7 54; tapered, 28 and 2)
    if LID_CORNER_TAPER > 0:
        t = (rel @ u) / width
        fall = fall * _smoothstep(np.clip(np.minimum(t, 1.0 - t) / LID_CORNER_TAPER, 0.0, 1.0))
    # upper / lower: above or below the corner line (in the face's up direction)
    up_dir = frame.axes[1] - u * (frame.axes[1] @ u)
    upper = rel @ up_dir > 0
    return ids, np.maximum(fall, 1e-3), upper
