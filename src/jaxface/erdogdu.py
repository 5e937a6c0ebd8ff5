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

The thesis gives no numbers (notes sec. 5); the tests in ``tests/test_erdogdu.py`` measure
ours on the Bosphorus-style data.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from .errors import LandmarkError, RBFError, RigError, ScanFormatError
from .io.bosphorus import Scan
from .io.preprocess import RigidTransform, align_landmarks, align_points
from .landmarks import FACE_LABELS, MIRROR_PAIRS, STABLE_LABELS, Landmarks
from .mesh import TriMesh
from .rbf import fit_numpy

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


# ---------------------------------------------------------------------------------------------
# control-point layouts
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControlPoint:
    """One control point, defined relative to the Bosphorus landmarks.

    Position on a face: ``sum_k w_k L_k + D * (dx * side_sign * x_f + dy * y_f)`` projected
    along ``-z_f`` onto the surface, where ``L_k`` are landmarks, ``D`` the outer-eye-corner
    distance (mm), ``(x_f, y_f, z_f)`` the face frame (:func:`face_frame`), and
    ``side_sign`` = +1 for left-side points (toward the subject's left) and -1 for their
    mirrored right-side twins.

    Attributes:
        name: e.g. ``"zygomaticus_major_3"``; right-side twins get the suffix ``"_R"``,
            left-side points ``"_L"``.
        kind: ``"muscle"`` or ``"wrinkle"``.
        base: ``((label, weight), ...)``, weights summing to 1; left-side labels for
            sided points.
        offset: ``(dx, dy)`` in units of ``D``: ``dx`` lateral (away from the midline for
            sided points), ``dy`` up.
        side: ``"L"`` (mirrored to ``"R"`` automatically) or ``"C"`` (midline).
    """

    name: str
    kind: str
    base: tuple[tuple[str, float], ...]
    offset: tuple[float, float] = (0.0, 0.0)
    side: str = "L"

    def mirrored(self) -> ControlPoint:
        """The right-side twin of a left-side point (labels swapped, lateral offset mirrored)."""
        if self.side != "L":
            return self
        swap = {}
        for left, right in MIRROR_PAIRS:
            swap[left], swap[right] = right, left
        base = tuple((swap.get(l, l), w) for l, w in self.base)
        return ControlPoint(
            self.name[:-2] + "_R" if self.name.endswith("_L") else self.name + "_R",
            self.kind,
            base,
            self.offset,
            "R",
        )


@dataclass(frozen=True)
class AULayout:
    """Control points of one action unit (our design; see the module doc).

    Attributes:
        au: FACS number.
        name: FACS name.
        muscles: muscular basis (thesis Fig. 5-7 table).
        region: ``"upper"`` or ``"lower"`` face.
        points: left-side and midline definitions (right side generated by mirroring).
        fixed_landmarks: landmarks held still in the warp (anchors).
        influence: influence-zone radius in units of ``D`` (the AU's reach beyond its
            control points).
    """

    au: int
    name: str
    muscles: tuple[str, ...]
    region: str
    points: tuple[ControlPoint, ...]
    fixed_landmarks: tuple[str, ...] = ()
    influence: float = 0.3

    def expanded(self) -> tuple[ControlPoint, ...]:
        """All control points: left-side ones, their mirrored right-side twins, midline ones."""
        out = []
        for p in self.points:
            out.append(p)
            if p.side == "L":
                out.append(p.mirrored())
        return tuple(out)

    @property
    def landmarks_used(self) -> tuple[str, ...]:
        names = []
        for p in self.expanded():
            names += [l for l, _ in p.base]
        return tuple(dict.fromkeys(names + list(self.fixed_landmarks)))


def _cp(
    name: str, kind: str, base, dx: float = 0.0, dy: float = 0.0, side: str = "L"
) -> ControlPoint:
    if isinstance(base, str):
        base = ((base, 1.0),)
    elif isinstance(base, Mapping):
        base = tuple(base.items())
    suffix = "_L" if side == "L" else ""
    return ControlPoint(name + suffix, kind, tuple((l, float(w)) for l, w in base), (dx, dy), side)


# landmark short-hands (canonical Bosphorus labels)
_OLB, _MLB, _ILB = "Outer left eyebrow", "Middle left eyebrow", "Inner left eyebrow"
_IRB = "Inner right eyebrow"
_OLE, _ILE = "Outer left eye corner", "Inner left eye corner"
_NSL, _NSR = "Nose saddle left", "Nose saddle right"
_LNP, _NT = "Left nose peak", "Nose tip"
_LMC, _RMC = "Left mouth corner", "Right mouth corner"
_ULO, _ULI, _LLI, _LLO = (
    "Upper lip outer middle",
    "Upper lip inner middle",
    "Lower lip inner middle",
    "Lower lip outer middle",
)
_CM = "Chin middle"
_BROW_MID = {_ILB: 0.5, _IRB: 0.5}
_ROOT = {_NSL: 0.5, _NSR: 0.5}


def _zygomatic_line(t: float) -> tuple[dict, float, float]:
    """Point at fraction t from the mouth corner (modiolus) to the zygomatic origin, which we
    put at the outer eye corner + (0.2, -0.27) D (lateral zygomatic bone)."""
    return {_LMC: 1.0 - t, _OLE: t}, 0.02 * (1 - t) + 0.2 * t, -0.27 * t


def _nasolabial(t: float) -> tuple[dict, float, float]:
    """Point at fraction t along the nasolabial fold, from beside the nose wing to beside
    the mouth corner."""
    return {_LNP: 1.0 - t, _LMC: t}, 0.03 + 0.03 * t, -0.02 + 0.05 * t


_UPPER_FIXED = (
    "Outer left eye corner",
    "Inner left eye corner",
    "Inner right eye corner",
    "Outer right eye corner",
)
_LOWER_FIXED = ("Nose tip",)

#: Control-point layouts of the eight AUs of the thesis (our design, see the module doc).
AU_LAYOUTS: dict[int, AULayout] = {
    1: AULayout(
        1,
        "Inner Brow Raiser",
        ("frontalis, pars medialis",),
        "upper",
        (
            _cp("frontalis_medial_1", "muscle", _ILB),
            _cp("frontalis_medial_2", "muscle", _ILB, 0.0, 0.08),
            _cp("frontalis_medial_3", "muscle", _ILB, 0.0, 0.16),
            _cp("frontalis_medial_4", "muscle", {_ILB: 0.5, _MLB: 0.5}, 0.0, 0.03),
            _cp("frontalis_medial_5", "muscle", {_ILB: 0.5, _MLB: 0.5}, 0.0, 0.12),
            _cp("forehead_medial_wrinkle", "wrinkle", _ILB, 0.06, 0.12),
            _cp("glabella_upper", "muscle", _BROW_MID, 0.0, 0.08, side="C"),
            _cp("forehead_middle_wrinkle", "wrinkle", _BROW_MID, 0.0, 0.16, side="C"),
        ),
        _UPPER_FIXED,
    ),
    2: AULayout(
        2,
        "Outer Brow Raiser",
        ("frontalis, pars lateralis",),
        "upper",
        (
            _cp("frontalis_lateral_1", "muscle", _OLB),
            _cp("frontalis_lateral_2", "muscle", _OLB, 0.0, 0.08),
            _cp("frontalis_lateral_3", "muscle", _OLB, -0.02, 0.16),
            _cp("frontalis_lateral_4", "muscle", _MLB),
            _cp("frontalis_lateral_5", "muscle", {_MLB: 0.5, _OLB: 0.5}, 0.0, 0.05),
            _cp("frontalis_lateral_6", "muscle", {_MLB: 0.5, _OLB: 0.5}, 0.0, 0.14),
            _cp("forehead_lateral_wrinkle", "wrinkle", _MLB, 0.0, 0.10),
        ),
        _UPPER_FIXED,
    ),
    4: AULayout(
        4,
        "Brow Lowerer",
        ("corrugator supercilii", "depressor supercilii", "procerus"),
        "upper",
        (
            _cp("corrugator_1", "muscle", _ILB),
            _cp("corrugator_2", "muscle", {_ILB: 0.5, _MLB: 0.5}),
            _cp("corrugator_3", "muscle", _MLB),
            _cp("corrugator_4", "muscle", _ILB, 0.0, 0.07),
            _cp("corrugator_5", "muscle", {_ILB: 0.5, _MLB: 0.5}, 0.0, 0.08),
            _cp("depressor_supercilii", "muscle", _OLB),
            _cp("glabella_furrow_1", "wrinkle", _ILB, -0.04, -0.01),
            _cp("glabella_furrow_2", "wrinkle", _ILB, -0.04, 0.05),
            _cp("procerus_1", "muscle", _BROW_MID, 0.0, 0.0, side="C"),
            _cp("procerus_2", "muscle", _ROOT, 0.0, 0.06, side="C"),
            _cp("nasal_root_wrinkle", "wrinkle", _BROW_MID, 0.0, 0.09, side="C"),
        ),
        _UPPER_FIXED,
    ),
    12: AULayout(
        12,
        "Lip Corner Puller",
        ("zygomaticus major",),
        "lower",
        (
            *(
                _cp(f"zygomaticus_major_{k + 1}", "muscle", *_zygomatic_line(t))
                for k, t in enumerate((0.0, 0.25, 0.5, 0.75, 1.0))
            ),
            *(
                _cp(f"nasolabial_{k + 1}", "wrinkle", *_nasolabial(t))
                for k, t in enumerate((0.0, 0.5, 1.0))
            ),
            _cp("cheek_bulge", "wrinkle", {_LNP: 0.5, _OLE: 0.5}, 0.06, -0.08),
            _cp("upper_lip_lateral", "muscle", {_LMC: 0.5, _ULO: 0.5}),
            _cp("lower_lip_lateral", "muscle", {_LMC: 0.5, _LLO: 0.5}),
            _cp("chin_lateral", "muscle", {_LMC: 0.5, _CM: 0.5}),
            _cp("upper_lip_middle", "muscle", _ULO, side="C"),
            _cp("lower_lip_middle", "muscle", _LLO, side="C"),
            _cp("mentolabial", "muscle", {_LLO: 0.5, _CM: 0.5}, side="C"),
            _cp("chin_middle", "muscle", _CM, side="C"),
        ),
        _LOWER_FIXED,
        0.35,
    ),
    14: AULayout(
        14,
        "Dimpler",
        ("buccinator",),
        "lower",
        (
            _cp("buccinator_1", "muscle", _LMC),
            _cp("buccinator_2", "muscle", _LMC, 0.05, 0.0),
            _cp("buccinator_3", "muscle", _LMC, 0.10, 0.0),
            _cp("buccinator_4", "muscle", _LMC, 0.10, 0.07),
            _cp("buccinator_5", "muscle", _LMC, 0.10, -0.07),
            _cp("dimple", "wrinkle", _LMC, 0.06, -0.01),
            _cp("upper_lip_lateral", "muscle", {_LMC: 0.5, _ULO: 0.5}),
            _cp("lower_lip_lateral", "muscle", {_LMC: 0.5, _LLO: 0.5}),
            _cp("upper_lip_middle", "muscle", _ULO, side="C"),
            _cp("lower_lip_middle", "muscle", _LLO, side="C"),
        ),
        _LOWER_FIXED,
    ),
    15: AULayout(
        15,
        "Lip Corner Depressor",
        ("depressor anguli oris (triangularis)",),
        "lower",
        (
            _cp("triangularis_1", "muscle", _LMC),
            _cp("triangularis_2", "muscle", _LMC, 0.03, -0.08),
            _cp("triangularis_3", "muscle", _LMC, 0.06, -0.16),
            _cp("triangularis_4", "muscle", _LMC, 0.09, -0.26),
            _cp("corner_bulge_1", "wrinkle", _LMC, 0.06, 0.03),
            _cp("corner_bulge_2", "wrinkle", _LMC, 0.08, -0.04),
            _cp("upper_lip_lateral", "muscle", {_LMC: 0.5, _ULO: 0.5}),
            _cp("lower_lip_lateral", "muscle", {_LMC: 0.5, _LLO: 0.5}),
            _cp("lower_lip_middle", "muscle", _LLO, side="C"),
        ),
        _LOWER_FIXED,
    ),
    17: AULayout(
        17,
        "Chin Raiser",
        ("mentalis",),
        "lower",
        (
            _cp("mentalis_1", "muscle", _CM, 0.08, 0.03),
            _cp("mentalis_2", "muscle", _CM, 0.12, -0.03),
            _cp("chin_lateral", "muscle", {_LMC: 0.5, _CM: 0.5}),
            _cp("chin_dimpling", "wrinkle", _CM, 0.05, 0.06),
            _cp("lower_lip_lateral", "muscle", {_LMC: 0.5, _LLO: 0.5}),
            _cp("mentalis_centre", "muscle", _CM, side="C"),
            _cp("mentalis_upper", "muscle", {_LLO: 0.5, _CM: 0.5}, side="C"),
            _cp("chin_lower", "muscle", _CM, 0.0, -0.06, side="C"),
            _cp("lower_lip_middle", "muscle", _LLO, side="C"),
        ),
        _LOWER_FIXED,
    ),
    20: AULayout(
        20,
        "Lip Stretcher",
        ("risorius", "platysma"),
        "lower",
        (
            _cp("risorius_1", "muscle", _LMC),
            _cp("risorius_2", "muscle", _LMC, 0.08, -0.01),
            _cp("risorius_3", "muscle", _LMC, 0.16, -0.02),
            _cp("risorius_4", "muscle", _LMC, 0.25, -0.03),
            _cp("platysma_fold", "wrinkle", _LMC, 0.05, -0.08),
            _cp("nasolabial_lower", "wrinkle", _LMC, 0.08, 0.06),
            _cp("upper_lip_lateral", "muscle", {_LMC: 0.5, _ULO: 0.5}),
            _cp("lower_lip_lateral", "muscle", {_LMC: 0.5, _LLO: 0.5}),
            _cp("chin_lateral", "muscle", {_LMC: 0.5, _CM: 0.5}),
            _cp("upper_lip_middle", "muscle", _ULO, side="C"),
            _cp("lower_lip_middle", "muscle", _LLO, side="C"),
            _cp("chin_middle", "muscle", _CM, side="C"),
        ),
        _LOWER_FIXED,
        0.35,
    ),
}

SUPPORTED_AUS: tuple[int, ...] = tuple(sorted(AU_LAYOUTS))


def parse_au(au) -> tuple[int, str | None]:
    """``12`` / ``"12"`` / ``"AU12L"`` / ``"LFAU_12R"`` -> ``(12, side)`` with side None/"L"/"R".

    Raises:
        RigError: not one of the supported AUs (1, 2, 4, 12, 14, 15, 17, 20).
    """
    if isinstance(au, (int, np.integer)):
        num, side = int(au), None
    else:
        m = re.match(r"^(?:[LU]?FAU_?|AU)?(\d+)([LR]?)[A-Z]*$", str(au).strip().upper())
        if m is None:
            raise RigError(f"cannot read the action unit {au!r}; use e.g. 12, '12L', 'AU4'.")
        num, side = int(m.group(1)), (m.group(2) or None)
    if num not in AU_LAYOUTS:
        raise RigError(
            f"AU{num} is not covered by the Erdoğdu method; supported: "
            f"{', '.join(f'AU{a}' for a in SUPPORTED_AUS)}."
        )
    return num, side


# ---------------------------------------------------------------------------------------------
# faces and frames
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Face:
    """A face surface with landmarks, mm.

    Attributes:
        vertices: (V, 3) mm.
        triangles: (F, 3) int64 or ``None`` (point set).
        landmarks: :class:`jaxface.landmarks.Landmarks`, mm.
        name: for messages.
    """

    vertices: np.ndarray
    triangles: np.ndarray | None
    landmarks: Landmarks
    name: str = "face"

    def tree(self) -> cKDTree:
        t = self.__dict__.get("_tree")
        if t is None:
            t = cKDTree(self.vertices)
            object.__setattr__(self, "_tree", t)
        return t

    def mesh(self):
        m = self.__dict__.get("_mesh")
        if m is None and self.triangles is not None:
            m = TriMesh(self.vertices, self.triangles, validate=False)
            object.__setattr__(self, "_mesh", m)
        return m


def as_face(obj, landmarks: Landmarks | None = None, name: str | None = None) -> Face:
    """Normalise a face given as :class:`Face`, :class:`jaxface.io.Scan` (range grids are
    meshed), :class:`jaxface.mesh.TriMesh`, ``(V, 3)`` vertex array, or a tuple
    ``(mesh_or_vertices, landmarks)``.

    Raises:
        LandmarkError: no landmarks given or found.
        ScanFormatError: vertices not (V, 3) finite.
    """
    if isinstance(obj, Face):
        return obj if landmarks is None else Face(obj.vertices, obj.triangles, landmarks, obj.name)
    if isinstance(obj, tuple) and len(obj) == 2 and isinstance(obj[1], Landmarks):
        return as_face(obj[0], obj[1] if landmarks is None else landmarks, name)
    tri = None
    if isinstance(obj, Scan):
        lm = landmarks if landmarks is not None else obj.landmarks
        nm = name or (obj.path.name if obj.path is not None else "scan")
        if obj.is_grid:
            v, tri, _ = obj.mesh_arrays()  # range grid meshed, unreferenced points dropped
        else:
            v, tri = obj.points, obj.triangles  # mesh scan: vertex order kept
    elif isinstance(obj, TriMesh):
        v, tri, lm, nm = obj.vertices, obj.triangles, landmarks, name or "mesh"
    else:
        v, lm, nm = obj, landmarks, name or "vertices"
    v = np.asarray(v, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or not np.all(np.isfinite(v)):
        raise ScanFormatError(
            f"{nm}: face vertices must be a finite (V >= 4, 3) array in mm, got shape {v.shape}."
        )
    if lm is None:
        raise LandmarkError(
            f"{nm}: no landmarks; pass (mesh, Landmarks) or a Scan loaded with its .lm3 file.",
            missing=FACE_LABELS,
        )
    return Face(v, None if tri is None else np.asarray(tri, dtype=np.int64), lm, nm)


@dataclass(frozen=True)
class FaceFrame:
    """Face-aligned frame built from landmarks (mm).

    Attributes:
        origin: (3,) midpoint of the eye corners, mm.
        axes: (3, 3) rows x (toward the subject's left), y (up), z (toward the viewer).
        size: outer-eye-corner distance ``D``, mm.
        eye_height, mouth_height: heights (along y, relative to origin) of the eye-corner and
            mouth-corner midpoints, mm.
    """

    origin: np.ndarray
    axes: np.ndarray
    size: float
    eye_height: float
    mouth_height: float

    def local(self, p: np.ndarray) -> np.ndarray:
        """(..., 3) mm -> (..., 3) frame coordinates, mm."""
        return (np.asarray(p, dtype=np.float64) - self.origin) @ self.axes.T

    def border_height(self, fraction: float = 0.12) -> float:
        """Height of the upper/lower region border (mm, frame y)."""
        return self.eye_height - fraction * (self.eye_height - self.mouth_height)


def face_frame(landmarks: Landmarks) -> FaceFrame:
    """:class:`FaceFrame` from the eye corners and mouth corners.

    Raises:
        LandmarkError: any of the four eye corners or two mouth corners missing.
    """
    need = (
        "Outer left eye corner",
        "Inner left eye corner",
        "Inner right eye corner",
        "Outer right eye corner",
        "Left mouth corner",
        "Right mouth corner",
    )
    lm = landmarks.require(need)
    ole, ile, ire, ore, lmc, rmc = (np.asarray(lm[n]) for n in need)
    eye = (ole + ile + ire + ore) / 4
    mouth = (lmc + rmc) / 2
    x = ole - ore
    D = float(np.linalg.norm(x))
    if D <= 0:
        raise LandmarkError(
            "the outer eye corners coincide; cannot build the face frame", missing=()
        )
    x = x / D
    y = eye - mouth
    y = y - (y @ x) * x
    ny = np.linalg.norm(y)
    if ny <= 1e-9 * D:
        raise LandmarkError(
            "eye and mouth midpoints are aligned with the eye axis; cannot build the face frame",
            missing=(),
        )
    y = y / ny
    z = np.cross(x, y)
    return FaceFrame(eye, np.stack([x, y, z]), D, 0.0, float((mouth - eye) @ y))


# ---------------------------------------------------------------------------------------------
# snapping and TPS helpers
# ---------------------------------------------------------------------------------------------


def _project_frontmost(
    face: Face, frame: FaceFrame, points: np.ndarray, radius: float
) -> np.ndarray:
    """Index of the frontmost (largest frame z) vertex within ``radius`` mm of the line
    through each point along frame z; grows the radius up to 8x if nothing is found."""
    loc = frame.local(face.vertices)
    tree2 = cKDTree(loc[:, :2])
    out = np.empty(len(points), dtype=np.int64)
    for k, p in enumerate(frame.local(points)):
        r = radius
        for _ in range(4):
            idx = tree2.query_ball_point(p[:2], r)
            if idx:
                idx = np.asarray(idx)
                out[k] = idx[np.argmax(loc[idx, 2])]
                break
            r *= 2
        else:
            out[k] = int(face.tree().query(points[k])[1])
    return out


def _snap(face: Face, points: np.ndarray, mode: str) -> np.ndarray:
    """Snap (K, 3) mm points onto ``face``: nearest vertex (thesis) or closest surface point."""
    if mode == "vertex" or face.triangles is None:
        return face.vertices[face.tree().query(points)[1]]
    if mode != "surface":
        raise RigError(f"unknown snap mode {mode!r}; use 'vertex' or 'surface'")
    mesh = face.mesh()
    assert mesh is not None  # the face has triangles here
    sp, _ = mesh.closest_points(points)
    tri = np.asarray(sp.tri, dtype=np.int64)
    bary = np.asarray(sp.bary, dtype=np.float64)
    return np.einsum("kj,kjd->kd", bary, face.vertices[face.triangles[tri]])


def _landmark_tps(
    src: Landmarks, dst: Landmarks, reg: float, what: str, still: np.ndarray | None = None
):
    """TPS on the landmarks common to both (matched by label), plus optional ``still`` (n, 3)
    mm points mapped to themselves."""
    common = [n for n in src.names if n in dst]
    if len(common) < 5:
        raise LandmarkError(
            f"{what}: only {len(common)} landmarks in common ({common}); the TPS "
            f"needs at least 5 non-coplanar ones (ideally the 22 Bosphorus landmarks).",
            missing=[n for n in FACE_LABELS if n not in common],
        )
    try:
        a, b = src.array(common), dst.array(common)
        if still is not None and len(still):
            a, b = np.concatenate([a, still]), np.concatenate([b, still])
        return fit_numpy(a, b, kernel="tps", reg=reg), tuple(common)
    except RBFError as e:
        raise LandmarkError(f"{what}: landmark TPS failed: {e}", missing=()) from e


# ---------------------------------------------------------------------------------------------
# placing control points
# ---------------------------------------------------------------------------------------------


def place_control_points(
    face, au, *, landmarks: Landmarks | None = None, radius: float = 0.02
) -> tuple[tuple[ControlPoint, ...], np.ndarray]:
    """Place an AU's control points on a neutral face (the thesis places them once, on the
    source neutral).

    Args:
        face: anything :func:`as_face` accepts.
        au: AU number or code (``12``, ``"12L"``); the side is ignored here.
        radius: projection tolerance in units of ``D`` (see :func:`_project_frontmost`).

    Returns:
        ``(control points (K,), vertex indices (K,) into the face's vertices)``.

    Raises:
        LandmarkError: a landmark used by the layout or the frame is missing (all listed).
    """
    face = as_face(face, landmarks)
    num, _ = parse_au(au)
    layout = AU_LAYOUTS[num]
    miss = face.landmarks.missing(layout.landmarks_used)
    if miss:
        raise LandmarkError(
            f"{face.name}: AU{num} control points need landmark(s) {list(miss)}, "
            f"which are missing.",
            missing=miss,
        )
    frame = face_frame(face.landmarks)
    pts = layout.expanded()
    raw = np.empty((len(pts), 3))
    for k, cp in enumerate(pts):
        base = sum(w * np.asarray(face.landmarks[l]) for l, w in cp.base)
        sgn = -1.0 if cp.side == "R" else 1.0
        raw[k] = base + frame.size * (
            sgn * cp.offset[0] * frame.axes[0] + cp.offset[1] * frame.axes[1]
        )
    idx = _project_frontmost(face, frame, raw, radius * frame.size)
    # distinct vertices: duplicates would make the TPS singular
    _, first = np.unique(idx, return_index=True)
    keep = np.sort(first)
    return tuple(pts[i] for i in keep), idx[keep]


# ---------------------------------------------------------------------------------------------
# animation
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Animation:
    """Result of :func:`animate` (all positions in mm, in the target's frame).

    Attributes:
        vertices: (V, 3) animated target vertices.
        triangles: (F, 3) target triangles or ``None``.
        neutral: (V, 3) the target neutral vertices.
        au: AU number; side: ``"L"``, ``"R"`` or ``None``; magnitude: ``m``.
        region: ``"upper"`` or ``"lower"``.
        region_mask: (V,) bool, target vertices of the warped region.
        moved_mask: (V,) bool, vertices inside the influence zone (may move).
        control_names: (K,) names of the control points.
        control_source: (K, 3) control points on the source neutral ``P_i``.
        control_target: (K, 3) control points on the target neutral ``Q_i``.
        displacement: (K, 3) source displacements ``v_i`` (before scaling, source frame).
        control_active: (K,) bool, points that move (False: held by side selection).
        anchors: (A, 3) zero-displacement anchor points used in the warp.
        scale: the factor applied to ``v_i`` besides ``m`` (``s_t / s_s`` in the lower face).
        source_alignment: rigid transform of the source AU scan onto the source neutral.
        notes: readable remarks (landmarks missing, alignment status, ...).
    """

    vertices: np.ndarray
    triangles: np.ndarray | None
    neutral: np.ndarray
    au: int
    side: str | None
    magnitude: float
    region: str
    region_mask: np.ndarray
    moved_mask: np.ndarray
    control_names: tuple[str, ...]
    control_source: np.ndarray
    control_target: np.ndarray
    displacement: np.ndarray
    control_active: np.ndarray
    anchors: np.ndarray
    scale: float
    source_alignment: object = None
    notes: tuple[str, ...] = field(default=())
    _unit_field: np.ndarray | None = field(default=None, repr=False)

    @property
    def vertex_displacement(self) -> np.ndarray:
        """(V, 3) mm, animated minus neutral."""
        return self.vertices - self.neutral

    def mesh(self):
        """The animated target as a :class:`jaxface.mesh.TriMesh` (needs triangles)."""
        if self.triangles is None:
            raise RigError("the target was given as bare vertices; no mesh to return")
        return TriMesh(self.vertices, self.triangles, validate=False)

    def at_magnitude(self, m: float) -> np.ndarray:
        """(V, 3) animated vertices at another magnitude ``m`` (the warp is linear in ``m``)."""
        assert self._unit_field is not None  # animate() sets it
        return self.neutral + float(m) * self._unit_field


def _region_anchors(
    face: Face,
    frame: FaceFrame,
    region: str,
    controls: np.ndarray,
    influence: float,
    spacing: float,
    border_fraction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Region mask, influence-zone distance and anchor points (see the module doc)."""
    loc = frame.local(face.vertices)
    hb = frame.border_height(border_fraction)
    in_region = loc[:, 1] >= hb if region == "upper" else loc[:, 1] < hb
    dist = cKDTree(controls).query(face.vertices)[0]
    D = frame.size
    shell_w = 0.1 * D
    zone = dist < influence + shell_w
    # (a) border anchors: vertices just across the border, inside the zone
    band = zone & ~in_region & (np.abs(loc[:, 1] - hb) < 0.04 * D)
    # (b) shell anchors: region vertices in the outer shell of the zone
    shell = in_region & (dist >= influence) & (dist < influence + shell_w)
    cand = face.vertices[band | shell]
    anchors = _thin(cand, spacing)
    return in_region, dist, anchors


def _thin(points: np.ndarray, spacing: float) -> np.ndarray:
    """Greedy Poisson-disc thinning: keep points at least ``spacing`` mm apart (deterministic)."""
    if len(points) == 0:
        return points.reshape(0, 3)
    key = np.floor(points / spacing).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    cand = points[np.sort(first)]
    tree = cKDTree(cand)
    taken = np.zeros(len(cand), bool)
    alive = np.ones(len(cand), bool)
    for i in range(len(cand)):
        if alive[i]:
            taken[i] = True
            alive[tree.query_ball_point(cand[i], spacing * 0.999)] = False
    return cand[taken]


def animate(
    source_neutral,
    source_au_scan,
    target_neutral,
    au,
    m: float = 1.0,
    *,
    snap: str = "vertex",
    align: bool = True,
    influence: float | None = None,
    anchor_spacing: float = 0.06,
    border_fraction: float = 0.12,
    reorient: bool = False,
    upper_scale: str | None = None,
    reg: float = 0.0,
    source_anchors: bool = True,
) -> Animation:
    """Animate ``target_neutral`` with action unit ``au`` copied from a source subject
    (Erdoğdu 2010, eqs. 5.5-5.10; see the module doc for the steps and our design choices).

    Args:
        source_neutral, source_au_scan, target_neutral: faces with landmarks: a
            :class:`jaxface.io.Scan`, a :class:`Face`, or ``(TriMesh | (V, 3) vertices,
            Landmarks)``; mm.
        au: 1, 2, 4, 12, 14, 15, 17 or 20, optionally with a side: ``"12L"``, ``"AU12R"``.
        m: expression magnitude (0 = neutral, 1 = the source's level); the warp is linear
            in ``m``.
        snap: ``"vertex"`` (thesis: nearest vertex) or ``"surface"`` (closest point on the
            triangles; faces given as bare vertices fall back to ``"vertex"``).
        align: rigidly align the source AU scan to the source neutral first (stable
            landmarks + robust ICP when it has triangles).
        influence: influence-zone radius around the control points, in units of ``D``
            (outer-eye-corner distance of the target); default the layout's.
        anchor_spacing: spacing of the border/shell anchors, in units of ``D``.
        border_fraction: upper/lower border height, see :meth:`FaceFrame.border_height`.
        reorient: rotate ``v_i`` by the source-to-target stable-landmark rotation (not in
            the thesis).
        upper_scale: ``None`` (thesis eq. 5.10) or ``"eyes"``: scale upper-face
            displacements by the target/source outer-eye-corner distance ratio.
        reg: ridge of the landmark TPS fits (0 = exact, as in the thesis).
        source_anchors: hold the source's own border/shell anchors still in the source
            landmark TPS (eq. 5.5) as well (our deviation, see the module doc); ``False``
            is the thesis's landmarks-only TPS.

    Returns:
        :class:`Animation` (``.vertices`` (V, 3) mm, in target vertex order; for a range-grid
        :class:`jaxface.io.Scan` target that is the order of ``scan.to_mesh()`` /
        ``scan.mesh_arrays()``).

    Raises:
        RigError: unsupported AU or option.
        LandmarkError: landmarks needed by the layout, the face frame or the alignment missing.
    """
    num, side = parse_au(au)
    layout = AU_LAYOUTS[num]
    sn = as_face(source_neutral, name="source neutral")
    se = as_face(source_au_scan, name="source AU scan")
    tn = as_face(target_neutral, name="target neutral")
    notes: list[str] = []
    for f in (sn, se, tn):
        miss = f.landmarks.missing(FACE_LABELS)
        if miss:
            notes.append(
                f"{f.name}: landmark(s) {list(miss)} missing; the landmark TPS uses the others"
            )
    info = getattr(source_au_scan, "info", None)
    if info is not None and info.aus and num not in info.au_numbers:
        warnings.warn(
            f"{se.name} is labelled {info.code}, not AU{num}; animating AU{num} anyway",
            stacklevel=2,
        )
    if upper_scale not in (None, "eyes"):
        raise RigError(f"upper_scale must be None or 'eyes', got {upper_scale!r}")

    # 0. rigid alignment of the source AU scan onto the source neutral (replaces the thesis's
    #    4-point affine normalisation)
    T_align = RigidTransform()
    if align:
        if se.triangles is not None and sn.triangles is not None:
            mesh_n = sn.mesh()
            assert mesh_n is not None  # sn has triangles here
            rej = np.zeros(len(sn.vertices), bool)
            rej[np.asarray(mesh_n.boundary_edges, dtype=np.int64).ravel()] = True
            T_align, _, icp_info, more = align_points(
                se.vertices,
                se.landmarks,
                sn.vertices,
                mesh_n.vertex_normals,
                sn.landmarks,
                fixed_reject=rej,
            )
            notes += more
        else:
            T_align, _ = align_landmarks(se.landmarks, sn.landmarks)
        se = Face(
            T_align.apply(se.vertices),
            se.triangles,
            se.landmarks.transformed(T_align.rotation * T_align.scale, T_align.translation),
            se.name,
        )

    # 1. control points on the source neutral
    cps, idx = place_control_points(sn, num)
    P = sn.vertices[idx]
    names = tuple(c.name for c in cps)

    fs, ft = face_frame(sn.landmarks), face_frame(tn.landmarks)
    influence = layout.influence if influence is None else float(influence)

    # 2. source motion: landmark TPS S_n -> S_e, snap onto S_e  (eqs. 5.5, 5.6); with
    #    source_anchors, the source's own border/shell anchors are held still in this TPS
    extra = np.zeros((0, 3))
    if source_anchors:
        _, _, extra = _region_anchors(
            sn, fs, layout.region, P, influence * fs.size, anchor_spacing * fs.size, border_fraction
        )
        common = [n for n in sn.landmarks.names if n in se.landmarks]
        if len(extra) and common:
            lm_pts = np.concatenate([sn.landmarks.array(common), P])
            extra = extra[cKDTree(lm_pts).query(extra)[0] > 0.03 * fs.size]
    tps_e, _ = _landmark_tps(sn.landmarks, se.landmarks, reg, "source neutral -> source AU", extra)
    P_e = _snap(se, tps_e.apply_np(P), snap)
    v = P_e - P

    # 3. transfer: landmark TPS S_n -> T_n, snap onto T_n  (eq. 5.7)
    tps_t, _ = _landmark_tps(sn.landmarks, tn.landmarks, reg, "source neutral -> target neutral")
    Q = _snap(tn, tps_t.apply_np(P), snap)

    # side selection (asymmetric AUs)
    active = np.array([side is None or c.side in (side, "C") for c in cps])

    # 4. scaling (eqs. 5.8, 5.10)
    if layout.region == "lower":
        s_s = np.linalg.norm(sn.landmarks["Left mouth corner"] - sn.landmarks["Right mouth corner"])
        s_t = np.linalg.norm(tn.landmarks["Left mouth corner"] - tn.landmarks["Right mouth corner"])
        scale = float(s_t / s_s)
    else:
        scale = float(ft.size / fs.size) if upper_scale == "eyes" else 1.0
    vt = v * scale
    if reorient:
        R, _ = align_landmarks(sn.landmarks, tn.landmarks, STABLE_LABELS)
        vt = vt @ R.rotation.T
    vt = np.where(active[:, None], vt, 0.0)

    # 5. region warp with anchors (eq. 5.9), at m = 1; the result is linear in m
    D = ft.size
    in_region, dist, anchors = _region_anchors(
        tn, ft, layout.region, Q, influence * D, anchor_spacing * D, border_fraction
    )
    fixed = [
        tn.vertices[tn.tree().query(np.asarray(tn.landmarks[l]))[1]]
        for l in layout.fixed_landmarks
        if l in tn.landmarks
    ]
    if fixed:
        anchors = np.concatenate([anchors, np.asarray(fixed)])
    if len(anchors):
        far = cKDTree(Q).query(anchors)[0] > 0.03 * D
        anchors = anchors[far]
    src = np.concatenate([Q, anchors])
    dst = np.concatenate([Q + vt, anchors])
    warp = fit_numpy(src, dst, kernel="tps", reg=0.0, merge_duplicates=True)
    R0, R1 = influence * D, influence * D + 0.1 * D
    sel = in_region & (dist < R1)
    field_ = np.zeros_like(tn.vertices)
    if sel.any():
        d = warp.apply_np(tn.vertices[sel]) - tn.vertices[sel]
        t = np.clip((dist[sel] - R0) / (R1 - R0), 0.0, 1.0)
        w = 1.0 - t * t * (3.0 - 2.0 * t)  # smoothstep taper to zero across the shell
        field_[sel] = d * w[:, None]
    out = tn.vertices + float(m) * field_
    return Animation(
        vertices=out,
        triangles=tn.triangles,
        neutral=tn.vertices.copy(),
        au=num,
        side=side,
        magnitude=float(m),
        region=layout.region,
        region_mask=in_region,
        moved_mask=sel,
        control_names=names,
        control_source=P,
        control_target=Q,
        displacement=v,
        control_active=active,
        anchors=anchors,
        scale=scale,
        source_alignment=T_align,
        notes=tuple(notes),
        _unit_field=field_,
    )


# ---------------------------------------------------------------------------------------------
# extras: thesis preprocessing step 1, oracle magnitude (baseline B3)
# ---------------------------------------------------------------------------------------------


def resample_grid(scan, size: int = 150):
    """Thesis preprocessing step 1 (§5.4): resample a scan's valid points on a ``size x size``
    regular x-y grid spanning their bounding box, z by linear interpolation over the
    Delaunay triangulation of the x-y positions (what MATLAB/SciPy ``griddata`` do), which
    also fills holes; nodes outside the convex hull are background. Landmarks are moved to the nearest resampled point (as in the thesis).

    Args:
        scan: :class:`jaxface.io.Scan` (mm).
        size: grid nodes per side (thesis: 150).

    Returns:
        a new grid :class:`jaxface.io.Scan` (mm), rows bottom to top.
    """
    import matplotlib.tri as mtri

    pts = np.asarray(scan.points, dtype=np.float64)
    if size < 2:
        raise ScanFormatError(f"resample size must be at least 2, got {size}")
    xs = np.linspace(pts[:, 0].min(), pts[:, 0].max(), size)
    ys = np.linspace(pts[:, 1].min(), pts[:, 1].max(), size)
    X, Y = np.meshgrid(xs, ys)
    # Delaunay triangulation of the x-y positions (qhull, as griddata) with matplotlib's
    # trapezoid-map point location: the same linear interpolant as
    # griddata(method="linear"), 10x faster on range grids (qhull's walk is slow there)
    tri = mtri.Triangulation(pts[:, 0], pts[:, 1])
    Zm = mtri.LinearTriInterpolator(tri, pts[:, 2])(X, Y)
    Z = np.ma.filled(Zm.astype(np.float64), np.nan)
    xyz = np.stack([X, Y, Z], -1)
    valid = np.isfinite(Z)
    lm = scan.landmarks
    out = Scan.from_grid(
        np.where(valid[..., None], xyz, 0.0), valid, image_name=scan.image_name, path=scan.path
    )
    if lm is not None:
        tree = cKDTree(out.points)
        lm = lm.with_positions(out.points[tree.query(np.asarray(lm.positions))[1]])
        out = out.with_landmarks(lm)
    return out


def fit_magnitude(
    animation: Animation,
    target_points: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    bounds: tuple[float, float] = (0.0, 2.0),
    cap_mm: float | None = None,
) -> tuple[float, float]:
    """Oracle magnitude (baseline B3 of the notes): the ``m`` minimising the mean distance
    from the moved vertices of ``animation`` to the nearest of ``target_points`` (mm, same
    frame), by bounded 1-D search.

    Args:
        mask: ``(V,)`` bool, the vertices to compare (default ``animation.moved_mask``).
        bounds: search interval of ``m``.
        cap_mm: cap each distance at this many mm (robust to vertices where the target has
            no points, e.g. a range scan's holes and the back of a head); None: no cap.

    Returns:
        ``(m, mean (capped) distance at m in mm)``.
    """
    from scipy.optimize import minimize_scalar

    sel = animation.moved_mask if mask is None else np.asarray(mask, bool)
    if not sel.any():
        return 0.0, 0.0
    tree = cKDTree(np.asarray(target_points, dtype=np.float64))
    assert animation._unit_field is not None  # animate() sets it
    x0, u = animation.neutral[sel], animation._unit_field[sel]

    def cost(mm):
        d = tree.query(x0 + mm * u)[0]
        return float((d if cap_mm is None else np.minimum(d, float(cap_mm))).mean())

    r = minimize_scalar(cost, bounds=bounds, method="bounded", options={"xatol": 1e-3})
    return float(r.x), float(r.fun)
