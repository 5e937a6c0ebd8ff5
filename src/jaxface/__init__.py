"""jaxface: a differentiable, physically based simulator of the human face in JAX.

Forward: muscle contractions and jaw pose in, an expressive face mesh (mm) out, through a
jit-compiled position-based dynamics (PBD) solver over a skull with a movable jaw.
Inverse: muscle activations, jaw pose and FACS action-unit intensities fitted to 3D scans.

Frame and units everywhere inside: millimetres; +y up; the face looks along +z; the
subject's left is +x.

The public API is small and imported lazily (``import jaxface`` does not import JAX until a
name that needs it is used):

* meshes and landmarks: :class:`TriMesh`, :func:`load_mesh`, :func:`save_mesh`,
  :class:`Landmarks`, :func:`generic_head`
* morphs: :mod:`jaxface.rbf` (Hardy multiquadric and thin-plate-spline morphs)
* simulation: :mod:`jaxface.pbd` (the PBD solver), :func:`build_rig`, :func:`synthesize`,
  :class:`JawPose` (the anatomical face rig), :mod:`jaxface.facs` (AU tables)
* errors: :mod:`jaxface.errors` (every user-facing error derives from ``JaxfaceError``)
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# public name -> module that defines it
_LAZY = {
    "TriMesh": "jaxface.mesh",
    "load_mesh": "jaxface.mesh",
    "save_mesh": "jaxface.mesh",
    "SurfacePoints": "jaxface.surface",
    "Head": "jaxface.head",
    "save_head": "jaxface.head",
    "Landmarks": "jaxface.landmarks",
    "read_lm3": "jaxface.landmarks",
    "write_lm3": "jaxface.landmarks",
    "load_scan": "jaxface.io",
    "generic_head": "jaxface.head",
    "JaxfaceError": "jaxface.errors",
    "build_rig": "jaxface.anatomy",
    "synthesize": "jaxface.anatomy",
    "JawPose": "jaxface.anatomy",
}
_SUBMODULES = {
    "rbf",
    "pbd",
    "reference",
    "mesh",
    "surface",
    "landmarks",
    "errors",
    "testing",
    "head",
    "render",
    "io",
    "erdogdu",
    "clone",
    "contours",
    "anatomy",
    "facs",
    "fit",
    "ltw",
}

__all__ = sorted(set(_LAZY) | _SUBMODULES | {"__version__"})


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        mod = importlib.import_module(f"jaxface.{name}")
        globals()[name] = mod
        return mod
    raise AttributeError(f"module 'jaxface' has no attribute {name!r}")


def __dir__():
    return __all__
