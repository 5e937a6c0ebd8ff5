"""The skin (thesis sec. 5.5-5.7): constraints, binding, influence map, eyelids, teeth collision.

Build time (NumPy):

* **constraints** with the thesis values: stretch on every edge and across adjacent triangles
  (0.15), bending (0.95), triangle area (0.95) and the skin volume (1.0), built with the
  :mod:`jaxface.pbd` constraint kinds on the part of the skin that can move;
* **binding**: each skin vertex casts a ray along its (smoothed) normal, outward first against
  the muscles, then inward against the muscles (the first surface met, i.e. the most
  superficial) and then the skull (cranium or mandible); the hit becomes a surface point and
  the vertex is tied to it by an anchor (stiffness 0.2). The thesis adds a particle ``q`` bound
  to the surface point and a stretch link ``p-q``; here ``q`` carries the rest offset
  ``p0 - sp0`` (the link has zero rest length), which makes the tie resist tangential sliding
  so that the quasi-static problem is well posed;
* **tissue footprint**: the anchor displacement of a vertex is the geodesic-Gaussian average
  (sigma ``footprint_mm``, one value or a ``(lower, upper)`` pair blended from the eyes up to
  the brows, :func:`footprint_sigma`) of the displacements of the surface points bound around
  it, a model of the fat layer that spreads a muscle's pull over the skin (without it the skin
  would shear sharply along every muscle border); the wide rows average over geodesic clusters
  of vertices instead of single vertices (:func:`footprint_operator`), for speed;
* **fat volume** (our addition, after the volume preservation of Lee, Terzopoulos and Waters
  1995): the offset ``p0 - sp0`` is the fat between the skin and its surface point; where the
  bound surface points around a vertex squeeze together its fat thickens, where they spread it
  thins, keeping area x thickness (:func:`fat_thickness`, gain ``fat_volume``, one value or a
  ``(lower, upper)`` pair like the footprint);
* **influence map**: ``w = 1 - smoothstep(d / radius)`` of the normalised geodesic distance
  ``d`` from the vertices bound to a muscle or to the mandible; it scales each vertex's anchor
  displacement (thesis line 17 scales the particle's displacement; scaling the target keeps
  the final state consistent with the collisions), and vertices with ``w = 0`` are kinematic;
* **eyelids**: vertices within normalised geodesic distance 0.04 (tunable) of the eye border
  rotate about the axis through the eye corners (moved back onto the eyeball centre), upper
  lid above the axis, lower lid below, with a smooth falloff toward the threshold and a taper
  to no rotation at the corners themselves (:data:`LID_CORNER_TAPER`: the lids hinge there);
* **teeth**: convex hulls of the upper and lower teeth (:func:`jaxface.pbd.hull_planes`); the
  lower hull moves with the jaw (:func:`jaxface.pbd.transform_planes`); lip vertices inside a
  hull are pushed out through the nearest face (unilateral, resolved fully every sweep).

Units: mm.

Layout: :mod:`.skin_binding` (binding, influence map), :mod:`.skin_footprint` (tissue
footprint), :mod:`.skin_eyelids` (eyelid vertices), :mod:`.skin_system` (constraints, targets,
fat volume, solve); every name is re-exported here.
"""

from __future__ import annotations

from .skin_binding import Binding as Binding  # not in __all__ (as before), still importable
from .skin_binding import bind_skin, influence_map
from .skin_eyelids import LID_CORNER_TAPER as LID_CORNER_TAPER
from .skin_eyelids import eyelid_vertices
from .skin_footprint import CLUSTER_RATIO as CLUSTER_RATIO
from .skin_footprint import (
    Footprint,
    footprint_clusters,
    footprint_matrix,
    footprint_operator,
    footprint_sigma,
    mirror_vertices,
)
from .skin_footprint import membrane_interpolation as membrane_interpolation
from .skin_system import FAT_RATIO_RANGE as FAT_RATIO_RANGE
from .skin_system import (
    SKIN_STIFFNESS,
    SkinSystem,
    build_skin_system,
    fat_thickness,
    skin_targets,
    solve_skin,
    vertex_areas,
)

__all__ = [
    "SKIN_STIFFNESS",
    "SkinSystem",
    "bind_skin",
    "influence_map",
    "footprint_matrix",
    "footprint_clusters",
    "footprint_operator",
    "Footprint",
    "footprint_sigma",
    "mirror_vertices",
    "eyelid_vertices",
    "build_skin_system",
    "skin_targets",
    "solve_skin",
    "vertex_areas",
    "fat_thickness",
]
