"""Erdoğdu AU animation (:func:`animate`, thesis eqs. 5.5-5.10): source motion of the control
points, transfer to the target, region TPS warp with fixed anchors; result :class:`Animation`
(mm, target frame)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..errors import RigError
from ..io.preprocess import RigidTransform, align_landmarks, align_points
from ..landmarks import FACE_LABELS, STABLE_LABELS
from ..mesh import TriMesh
from ..rbf import fit_numpy
from .face import Face, FaceFrame, as_face, face_frame
from .layouts import AU_LAYOUTS, parse_au
from .place import _landmark_tps, _snap, place_control_points

__all__ = ["Animation", "animate"]


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
