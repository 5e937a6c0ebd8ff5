"""The anatomical face model (Fratarcangeli 2008, ch. 4-5): skull and jaw, layered muscles,
skin binding, and the rig that turns muscle activations and a jaw pose into a face.

Modules (one responsibility each):

* :mod:`~jaxface.anatomy.frame` - the landmark-derived anatomical frame and estimated points;
* :mod:`~jaxface.anatomy.jaw` - :class:`JawPose`, :class:`JawModel` (pitch/yaw/protrusion);
* :mod:`~jaxface.anatomy.skull` - tissue depth, estimated/user/fitted skulls;
* :mod:`~jaxface.anatomy.geometry` - build-time projections and smoothing;
* :mod:`~jaxface.anatomy.muscle_geometry` - action-line sampling, the hexahedral muscle mesh;
* :mod:`~jaxface.anatomy.muscle_map` - the JSON muscle map and its placement on a face;
* :mod:`~jaxface.anatomy.muscles` - muscle dynamics (contraction, layers; JAX);
* :mod:`~jaxface.anatomy.skin` - skin constraints, binding, influence map, eyelids, teeth;
* :mod:`~jaxface.anatomy.interface` - :class:`FaceRig` (the interface both backends
  implement), :class:`RigConfig`, the backend registry;
* :mod:`~jaxface.anatomy.rig_config` - :class:`PBDRigConfig` (the PBD rig's options);
* :mod:`~jaxface.anatomy.rig` - :func:`build_rig`, :func:`synthesize`.

Units: mm, +y up, +z forward, subject's left +x. Names are imported lazily.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "FaceFrame": "frame",
    "face_frame": "frame",
    "JawPose": "jaw",
    "JawModel": "jaw",
    "Skull": "skull",
    "tissue_depth": "skull",
    "estimate_skull": "skull",
    "load_skull": "skull",
    "load_artisynth_skull": "skull",
    "fit_skull": "skull",
    "MuscleSpec": "muscle_map",
    "PlacedMuscle": "muscle_map",
    "load_muscle_map": "muscle_map",
    "place_muscles": "muscle_map",
    "FaceRig": "interface",
    "RigConfig": "interface",
    "PBDRigConfig": "rig_config",
    "Rig": "rig",
    "build_rig": "rig",
    "synthesize": "rig",
    "simulate": "rig",
    "equilibrium_gap": "rig",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f"jaxface.anatomy.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxface.anatomy' has no attribute {name!r}")


def __dir__():
    return __all__
