"""Triangle meshes in NumPy: validation, topology, normals, geodesics, ray casting, OBJ/PLY I/O.

:class:`TriMesh` is the build-time mesh container of jaxface. It never sits on the jit path:
constraint topology (edges, bending pairs, boundary loops), geodesic weights, ray-cast skin
bindings and landmark attachments are computed here once, in NumPy/SciPy/trimesh, and handed to
the JAX solvers as plain arrays or :class:`jaxface.surface.SurfacePoints`.

Units and frame: millimetres, +y up, the face looks along +z, the subject's left is +x.
File I/O converts from/to ``units=`` ("mm", "cm", "m") at the boundary only.

Validation (:meth:`TriMesh.validate`) raises :class:`jaxface.errors.MeshError` with a
machine-readable ``problem`` tag and the offending ``elements``:

=============================  ===============================================  ==============
problem                        meaning                                          elements
=============================  ===============================================  ==============
``shape``                      arrays are not (V, 3) float / (F, 3) int         ()
``empty``                      no triangles                                     ()
``nonfinite_vertices``         NaN or inf coordinates                           vertex ids
``index_out_of_range``         triangle refers to a vertex id < 0 or >= V       triangle ids
``degenerate_triangles``       repeated vertex id, or area <= tol * diag^2      triangle ids
``non_manifold_edges``         an edge shared by more than two triangles        triangle ids
``inconsistent_orientation``   two triangles traverse a shared edge the same    triangle ids
                               way (their normals disagree)
=============================  ===============================================  ==============

For the edge problems the error also carries ``error.edges`` (``(n, 2)`` vertex ids).

**Degenerate tolerance.** A triangle is degenerate if two of its vertex ids are equal or if its
area is at most ``degenerate_tol * D**2`` where ``D`` is the diagonal of the bounding box of
the mesh (so the test is scale-free). The default ``degenerate_tol = 1e-10`` flags triangles
that are zero-area up to float32 rounding of the coordinates; real meshes pass: the ICT-FaceKit
head (D = 475 mm) has a smallest triangle of 4.6e-3 mm^2 = 2.0e-8 D^2, 200 times above the
threshold, no duplicate vertices, no non-manifold edges and a consistent orientation (it has
34 connected components and 200 boundary edges; its "face" group, 18,878 triangles, has four
boundary loops: the outer border, the mouth slit and the two eye openings).

Layout: :mod:`.arrays` (array checks), :mod:`.barycentric` (closest point on triangles),
:mod:`.base` (data and geometry), :mod:`.topology` (edges, loops, geodesics), :mod:`.raycast`
(closest points, ray casting, :class:`RayHits`), :mod:`.core` (:class:`TriMesh`, validation),
:mod:`.units` (units, size and input-file checks), :mod:`.io` (OBJ/PLY).
"""

from __future__ import annotations

from .arrays import check_finite_vertices
from .barycentric import closest_point_barycentric
from .core import DEGENERATE_TOL, TriMesh
from .io import load_mesh, save_mesh
from .raycast import RayHits
from .units import PLAUSIBLE_SIZE_MM, UNIT_SCALE, check_input_file, check_plausible_size, unit_scale

__all__ = [
    "TriMesh",
    "RayHits",
    "load_mesh",
    "save_mesh",
    "unit_scale",
    "check_plausible_size",
    "check_finite_vertices",
    "check_input_file",
    "closest_point_barycentric",
    "DEGENERATE_TOL",
    "UNIT_SCALE",
    "PLAUSIBLE_SIZE_MM",
]
