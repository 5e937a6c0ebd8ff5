"""Facial motion cloning (thesis chapter 6): copy a source face's morph targets onto a new face.

Units mm; frame +y up, face looking along +z, subject's left at +x.

Pipeline (thesis sec. 6.2-6.3), :func:`clone_motion`:

1. **Landmarks.** The named landmarks common to both faces (any set: the thesis's MPEG-4
   FDPs, our Bosphorus labels, the 68 Multi-PIE points) are the first correspondences
   ``(P_i, Q_i)``; a first RBF volume morph ``G`` (Hardy multiquadric with affine part, thesis
   sec. 3.4, :mod:`jaxface.rbf`) roughly fits the source into the target.
2. **Contours.** Eye and inner-lip contours are extracted on both meshes
   (:mod:`jaxface.contours`, thesis 6.2.1) and matched by arc length; every source contour
   vertex with its target point joins the set and ``G`` is refitted.
3. **Refinement** (6.2.3). A source vertex is *movable* if it moves in any morph target. Each
   iteration morphs the source with ``G``, casts fixed-length rays (``0.3125 * ENS0``, the
   MPEG-4 eye-nose separation, both ways along the deformed vertex normal) from the movable
   vertices onto the target, and inserts the ``125`` pairs with the largest error
   ``|Q_i - G(P_i)|`` (updating ``Q_i`` of pairs already present); ``G`` is refitted. It stops
   when an iteration inserts no new vertex (or after ``max_iterations``).
4. **Mapping** (6.3). Each target vertex is projected on the deformed source ``G(S_0)`` with
   the same fixed-length rays along the target normals (closest point where a ray misses) and
   expressed in barycentric coordinates of a source triangle.
5. **Cloning.** For each source morph target ``S_j``, ``G`` is applied to its moving vertices
   only, and each target vertex follows its source triangle.

Deviations from the thesis, all documented in the result:

* ``mode="displacement"`` (default) moves a target vertex by the barycentric interpolation of
  the source triangle's displacement ``G(S_j) - G(S_0)``; the thesis (``mode="thesis"``) sets
  it to the barycentric interpolation of the positions ``G(S_j)``, which also snaps the target
  vertex onto the source triangle's plane whenever that triangle moves. Both agree when the
  target lies exactly on the deformed source.
* landmark pairs are kept fixed during refinement (the user's correspondences are trusted);
  contour and refined pairs are updated as in the thesis.
* pairs are only inserted when their error exceeds ``error_tol`` (default ``0.01 * ENS0``), so
  an already fitted source stops the refinement at once.
* contours are joined along shortest edge paths rather than the thesis's greedy walk (which
  wanders on dense meshes), contour pairs far from the rough fit are dropped, and the whole
  contour step is undone when it makes the fit worse (reported in ``contours_skipped``).
* ray hits on target triangles facing away from the ray's source normal are ignored.
* the global head motion and the teeth/tongue affine transforms (thesis's last step) are not
  cloned: only surface morph targets.

Fixed-length ray casting (:func:`cast_segments`) goes through
:meth:`jaxface.mesh.TriMesh.ray_cast` bounded to the segment (r-tree candidates, exact
Möller-Trumbore), which is much faster than an unbounded ray cast for this purpose.

Layout: :mod:`.geometry` (inputs, ENS0, segment casting, surface mapping), :mod:`.source_fit`
(fitting the source into the target), :mod:`.transfer` (cloning the morph targets),
:mod:`.measures` (error measures).
"""

from __future__ import annotations

from .geometry import ENS0_DEFINITIONS as ENS0_DEFINITIONS  # not in __all__ (as before)
from .geometry import SurfaceMap, as_trimesh, cast_segments, eye_nose_separation, map_onto_surface
from .measures import clone_error, delta_error
from .source_fit import FitResult, fit_source_to_target
from .transfer import CloneResult, apply_clone, clone_motion

__all__ = [
    "SurfaceMap",
    "FitResult",
    "CloneResult",
    "as_trimesh",
    "eye_nose_separation",
    "cast_segments",
    "map_onto_surface",
    "fit_source_to_target",
    "clone_motion",
    "apply_clone",
    "clone_error",
    "delta_error",
]
