"""The muscle map: a readable JSON file of muscles defined relative to the landmarks, and
their placement on one face (thesis sec. 5.3-5.4).

:func:`load_muscle_map` reads ``jaxface/data/muscle_map.json`` (or a user file in the same
format; its ``description`` field documents the format) into face-independent
:class:`MuscleSpec` entries, expanding bilateral muscles into separate left (``_L``) and right
(``_R``) controls. :func:`place_muscles` puts them on a face:

1. each landmark-relative point is mapped to the face with the :class:`FaceFrame` and
   projected onto the skin by a radial ray;
2. the muscle outline (fibres from an origin line to an insertion line, or the inner, middle
   and outer ellipses of a sphincter) is drawn at the skin, each action line split into
   segments and every split point projected inward along the smoothed skin normal onto the
   surfaces the muscle lies on (other muscles, then the skull; the outermost hit wins) -
   the action lines of surface points of thesis sec. 4.2.1 and 4.4 (Fig. 4.15). A
   sphincter with ``"project": "backward"`` (the mouth ring of :data:`RANGE_EDITS`) is
   projected straight back instead, onto the skull with its teeth (:func:`skull_registry`);
3. muscles are placed layer by layer, deepest first, so that a muscle can lie on the meshes of
   the layers below it (passive deformation, sec. 4.3.3); each placed muscle gets its rest
   hexahedral mesh (sec. 4.2.2, :mod:`jaxface.anatomy.muscle_geometry`).

Units: mm; +y up, +z forward, subject's left +x.

Layout: :mod:`.muscle_map_load` (specs, loading, checks), :mod:`.muscle_place` (placement);
every name is re-exported here.
"""

from __future__ import annotations

from .muscle_map_load import (
    KINDS,
    RANGE_EDITS,
    MuscleSpec,
    check_sphincter_rings,
    default_muscle_map_path,
    load_muscle_map,
)
from .muscle_place import ActionLine, PlacedMuscle, SurfaceRegistry, place_muscles, skull_registry
from .muscle_place import placement_registry as placement_registry

__all__ = [
    "MuscleSpec",
    "PlacedMuscle",
    "ActionLine",
    "SurfaceRegistry",
    "load_muscle_map",
    "RANGE_EDITS",
    "check_sphincter_rings",
    "default_muscle_map_path",
    "place_muscles",
    "skull_registry",
    "KINDS",
]
