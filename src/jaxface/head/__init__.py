"""The embedded procedural default head: :func:`generic_head`.

jaxface ships its own deterministic, human-proportioned head so that every command works on a
fresh machine with no data: it stands in for a scan (the default face of synthesis, scanning
and fitting). No outside mesh or data is used. Proportions follow adult anthropometric norms
and the landmark spacing of a neutral Bosphorus-style face (inter-canthal and bi-ocular
widths, nose-tip height and projection, mouth width, lip and chin heights, midline profile).

Construction (all in mm, +y up, face looking along +z, the subject's left at +x):

1. **Base head**: a loft of horizontal super-ellipses (front and back halves with their own
   depth and exponent; width, depths and exponent by height, smoothing splines through design
   values) joined to an ellipsoidal cranial dome: head length ~194 mm, breadth ~158 mm,
   vertex to menton ~225 mm.
2. **Parametrisation**: rays from :data:`RAY_ORIGIN` hit the base head (a deformed sphere).
   Rings of rays run around the head, nearly horizontal, spaced ~2.9 mm on the face band and
   ~1.7 mm at the eye, nose-base and mouth heights; each ring has its own columns (~2.8 mm on
   the face and the ears, ~7 mm at the back). Neighbouring rings are stitched by a merge
   ("zipper") triangulation of the left half, mirrored to the right half (the mesh is exactly
   symmetric, :attr:`Head.mirror`), and the vertex is closed by a fan; the neck is cut open
   horizontally at y = -118 mm.
3. **Openings**: the mouth and the two eyes are slits along a ring: the slit vertices are
   duplicated, so the upper and lower lip (lid) edges are distinct vertices that meet at the
   shared mouth (eye) corner vertices. A smooth warp of the ring elevations bends each slit
   onto its designed line and opens it: almond-shaped palpebral fissures (~10 mm high) and a
   closed mouth whose lips touch with a 0.76 mm gap.
4. **Relief**: displacement fields along +z on the face (brow ridge, glabella, eye sockets
   with the upper-lid crease, cheek bones, perioral mound, lips with vermilion, cupid's bow,
   philtrum and the inward roll at the slit, nasolabial folds, chin) and along +-x on the sides
   (ears: helix rim, antihelix, concha, tragus, lobe). The nose is the smooth maximum of
   height-field primitives (dorsum ridge, tip lobule, columella, alae) with nostril
   impressions; the lids are the smooth maximum of the socket and a shell 1.8 mm outside the
   eyeball. A tangential relaxation on the face (vertices stay on the exact surface) evens
   out the triangles on steep parts (nose base, lip roll).

The result (:class:`Head`) carries the skin mesh (:class:`jaxface.mesh.TriMesh`, ~12k
vertices, every triangle angle above 17 degrees), the 24 Bosphorus landmarks on its surface,
named vertex regions and ordered slit edges, two eyeballs and upper/lower teeth (closed
meshes). :func:`save_head` writes it all (PLY, ``.lm3``, PNG). Building takes ~1 s (CPU).

Layout: :mod:`.base` (design values, helpers, base loft), :mod:`.relief` (face and ear relief,
skin surface, relaxation), :mod:`.grid` (rings, columns, slits), :mod:`.parts` (eyeballs,
teeth), :mod:`.model` (:class:`Head`, :func:`build_head`, :func:`generic_head`,
:func:`save_head`).
"""

from __future__ import annotations

from .base import EYE_RADIUS, RAY_ORIGIN
from .model import Head, build_head, generic_head, save_head

__all__ = ["Head", "generic_head", "build_head", "save_head", "RAY_ORIGIN", "EYE_RADIUS"]
