"""Erdoğdu (2010) thin-plate-spline facial animation: FACS action units transferred from a
source subject's neutral/AU scan pair onto a new neutral face.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.

The method (thesis §5.5-5.6; equations numbered as in ``shared/notes/erdogdu-2010-notes.md``)
--------------------------------------------------------------------------------------------
1. **Control points.** Each supported AU (1, 2, 4, 12, 14, 15, 17, 20) has *muscle* control
   points placed where the muscle fibres lie and *wrinkle* control points where the skin
   folds (:data:`AU_LAYOUTS`). They are placed once on the source neutral face S_n.
2. **Source motion** (eqs. 5.5, 5.6). The source AU scan S_e is rigidly aligned to S_n
   (stable landmarks + robust ICP, :func:`jaxface.io.preprocess.align_points`); a TPS
   fitted on the landmarks (S_n -> S_e, eq. 5.5) carries each control point P_i onto S_e,
   where it is snapped to S_e (``snap``); ``v_i = P'_i - P_i``.
3. **Transfer** (eq. 5.7). A TPS on the landmarks (S_n -> T_n) carries the control points
   onto the target neutral T_n, where they are snapped to T_n: ``Q_i``.
4. **Warp** (eqs. 5.8-5.10). ``Q_i`` move to ``Q_i + m * v_i * s_t / s_s`` in the lower
   face (``s`` = mouth width, the distance between the mouth corners) and to
   ``Q_i + m * v_i`` in the upper face; a TPS (kernel ``U(r) = r^2 log r^2``, exact
   interpolation, :func:`jaxface.rbf.fit_numpy`) through these correspondences moves the
   vertices of the AU's region (upper face for AU1/2/4, lower face for the others).
   Displacements are not reoriented (thesis), unless ``reorient=True``.
   Asymmetric AUs (``"12L"``, ``"12R"``): only the control points on that side (and on
   the midline) move; the other side's points are held fixed.

Our design where the thesis is silent (the layouts are only in its figures 5-8 to 5-11)
---------------------------------------------------------------------------------------
* **Control-point layouts** are ours, built from the muscle table of the facial-anatomy
  notes: each point is a weighted mean of Bosphorus landmarks plus an in-plane offset in
  the face frame (:class:`ControlPoint`), in units of the outer-eye-corner distance ``D``;
  left-side points are mirrored to the right. The face frame: ``x`` along the outer eye
  corners (toward the subject's left), ``y`` from the mouth-corner midpoint to the eye
  midpoint (orthogonalised), ``z = x × y`` toward the viewer. A placed point is projected
  along ``-z`` onto the frontmost vertex of S_n within ``0.02 D`` of the projection line.
* **Region border.** The upper/lower split is the plane ``h = h_eye - 0.12 (h_eye -
  h_mouth)`` across the face frame (``h`` = height along frame ``y``): just below the
  lower eyelids, above the nose tip. The thesis does not give the border.
* **Fixed anchors (deviation from the thesis).** Zero-displacement points are added to
  every region warp: (a) target vertices along the region border (on the far side of
  the border, one per ``0.06 D``), (b) a shell of target vertices at ``influence`` to
  ``influence + 0.1 D`` from the nearest control point (one per ``0.06 D``), and (c) the
  AU's fixed landmarks (e.g. the nose tip for the lower-face AUs). Vertices farther than
  the shell are not moved; inside the shell the warp is blended to zero with a smoothstep.
  Without anchors the affine part of the TPS moves the whole region (the notes' remark).
  Anchors closer than ``0.03 D`` to a control point are dropped (the system would be
  ill-conditioned, and their targets contradict).
* **Source anchors (deviation).** The same border/shell anchors, built on the source
  neutral, are also held still in the source landmark TPS of eq. 5.5
  (``source_anchors=True``). With the 22 landmarks alone, the TPS extrapolates the motion
  of the brows and mouth corners to control points far from them (its affine part
  stretches the whole face when the mouth corners move apart), and the nearest-vertex
  snap only corrects the normal component. On the ICT-made data (bs900, same mesh
  topology, so the material displacement of each control vertex is known) the mean error
  of ``v_i`` drops from 2.3 to 0.03 mm for AU2 (forehead points) and from 2.5 to 1.2 mm for
  AU20 (risorius points lateral of the mouth).
* **Alignment instead of the thesis's 4-point affine normalisation** to its average face:
  the source AU scan is aligned rigidly to the source neutral on expression-stable
  landmarks and ICP, as the notes recommend (the chin moves with expressions).
* ``snap="surface"`` (closest point on the triangles) is offered beside the thesis's
  nearest vertex (``snap="vertex"``, default).

The thesis gives no numbers (notes sec. 5); the tests in ``tests/erdogdu/test_erdogdu.py`` measure
ours on the Bosphorus-style data.

Layout: :mod:`.layouts` (control-point layouts, AU names), :mod:`.face` (faces and frames),
:mod:`.place` (placing and snapping control points), :mod:`.animation` (:func:`animate`),
:mod:`.extras` (grid resampling, oracle magnitude).
"""

from __future__ import annotations

from .animation import Animation, animate
from .extras import fit_magnitude, resample_grid
from .face import Face, FaceFrame, as_face, face_frame
from .layouts import AU_LAYOUTS, SUPPORTED_AUS, AULayout, ControlPoint
from .layouts import parse_au as parse_au  # not in __all__ (as before), still importable
from .place import place_control_points

__all__ = [
    "ControlPoint",
    "AULayout",
    "AU_LAYOUTS",
    "SUPPORTED_AUS",
    "Face",
    "FaceFrame",
    "Animation",
    "as_face",
    "face_frame",
    "place_control_points",
    "animate",
    "resample_grid",
    "fit_magnitude",
]
