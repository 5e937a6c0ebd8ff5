"""The :class:`Head` container, its assembly (:func:`build_head`), the cached
:func:`generic_head` and :func:`save_head` (PLY, ``.lm3``, PNG).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..landmarks import BOSPHORUS_LABELS, Landmarks, write_lm3
from ..mesh import TriMesh, save_mesh
from ..render import head_layers, save_views
from .base import (
    _CANTHUS_IN,
    _CANTHUS_OUT,
    _EYE_CENTER,
    _MOUTH_CORNER,
    _MOUTH_MID_Y,
    EYE_RADIUS,
    _base_normals,
    _base_points,
)
from .grid import _build_grid, _Slit
from .parts import _eyeball, _teeth
from .relief import (
    _LOWER_LIP_BORDER,
    _brow_line,
    _ear_frame,
    _ear_point,
    _front_base_z,
    _lid_margin_curves,
    _mouth_line,
    _nose_z,
    _relief_z,
    _upper_vermilion_border,
)


# ----------------------------------------------------------------------------- assembly
def _first_hits(V: np.ndarray, F: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """First intersection points ``(R, 3)`` (mm) of rays with a triangle mesh (Moller-Trumbore,
    vectorised over the triangles); NaN where a ray misses."""
    out = np.full((len(origins), 3), np.nan)
    tri = V[F]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    for i, (o, d) in enumerate(zip(origins, dirs)):
        d = d / np.linalg.norm(d)
        # candidate triangles: bounding box meets the ray's line (axis-aligned rays: exact cut)
        axis = int(np.argmax(np.abs(d)))
        other = [k for k in range(3) if k != axis]
        if np.abs(d[other]).max() < 1e-12:
            cand = np.all(
                (lo[:, other] <= o[other] + 1e-9) & (hi[:, other] >= o[other] - 1e-9), axis=1
            )
        else:
            cand = np.ones(len(F), dtype=bool)
        if not cand.any():
            continue
        a, b, c = tri[cand, 0], tri[cand, 1], tri[cand, 2]
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - a
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12) & (t > 0)
        if hit.any():
            out[i] = o + t[hit].min() * d
    return out


def _front_hits(V, F, xy: np.ndarray) -> np.ndarray:
    """Points (mm) of the skin seen from the front (+z) above ``(N, 2)`` positions (x, y)."""
    xy = np.atleast_2d(xy)
    o = np.column_stack([xy, np.full(len(xy), 400.0)])
    return _first_hits(V, F, o, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))


def _most_anterior(V, F, y_lo: float, y_hi: float, step: float = 0.1) -> np.ndarray:
    """The most anterior (max z) skin point on the midline x = 0 with y in [y_lo, y_hi]."""
    ys = np.arange(y_lo, y_hi + step / 2, step)
    # only the triangles near the midline matter
    near = np.abs(V[F].mean(axis=1)[:, 0]) < 6.0
    pts = _front_hits(V, F[near], np.column_stack([np.zeros_like(ys), ys]))
    i = int(np.nanargmax(pts[:, 2]))
    return pts[i]


@dataclasses.dataclass(frozen=True)
class Head:
    """The embedded default head (all in mm; +y up, face along +z, subject's left at +x).

    Attributes:
        mesh: the skin, a :class:`TriMesh` closed behind; its only boundaries are the two
            palpebral fissures, the closed mouth slit and the neck cut.
        landmarks: the 24 Bosphorus landmarks (:data:`BOSPHORUS_LABELS`), on the skin surface.
        face_mask: ``(V,)`` bool, the face region (forehead to under the chin, ear to ear in
            front of the ears).
        upper_teeth, lower_teeth: closed dental arches (crowns and gum band) behind the lips.
        regions: named ``(V,)`` bool vertex masks: ``face``, ``upper_lip``, ``lower_lip``,
            ``lips``, ``nose``, ``eye_left``/``eye_right`` (lids and surroundings),
            ``upper_lid_left``, ``lower_lid_left``, ``upper_lid_right``, ``lower_lid_right``,
            ``jaw`` (skin carried by the mandible: lower lip, chin, jaw line, below the mouth
            line back to the ear), ``forehead``, ``cheek_left``, ``cheek_right``, ``ear_left``,
            ``ear_right``, ``neck``, ``scalp``.
        edges: named ordered vertex-id paths, ``(n,)`` int64: ``upper_lip_edge`` and
            ``lower_lip_edge`` (the two edges of the mouth slit, from the right mouth corner
            to the left one, both ending at the shared corner vertices),
            ``upper_lid_left``/``lower_lid_left``/``upper_lid_right``/``lower_lid_right``
            (lid margins from the inner to the outer eye corner), ``neck`` (the neck cut loop).
        eyes: ``(left, right)`` closed eyeball meshes (radius :data:`EYE_RADIUS` + cornea).
        eye_centers: ``(2, 3)`` eyeball centres (left, right).
        landmark_vertex: for the landmarks that are mesh vertices (eye and mouth corners,
            inner lip midpoints), the vertex id.
        mirror: ``(V,)`` int64, the vertex mirrored through the plane x = 0 (the head is
            exactly symmetric: ``vertices[mirror] == vertices * (-1, 1, 1)`` up to rounding,
            and the triangulation is mirrored too).
    """

    mesh: TriMesh
    landmarks: Landmarks
    face_mask: np.ndarray
    upper_teeth: TriMesh
    lower_teeth: TriMesh
    regions: dict
    edges: dict
    eyes: tuple
    eye_centers: np.ndarray
    landmark_vertex: dict
    mirror: np.ndarray

    @property
    def eye_radius(self) -> float:
        """Eyeball radius, mm."""
        return EYE_RADIUS

    def eye_axis(self, side: str = "left") -> tuple[np.ndarray, np.ndarray]:
        """(inner corner, outer corner) positions (mm) of the ``"left"`` or ``"right"`` eye:
        the axis about which the lids turn."""
        s = "left" if side.startswith("l") else "right"
        lm = self.landmarks
        return lm[f"Inner {s} eye corner"].copy(), lm[f"Outer {s} eye corner"].copy()

    def parts(self) -> dict:
        """All meshes by name: ``skin``, ``eye_left``, ``eye_right``, ``upper_teeth``,
        ``lower_teeth``."""
        return {
            "skin": self.mesh,
            "eye_left": self.eyes[0],
            "eye_right": self.eyes[1],
            "upper_teeth": self.upper_teeth,
            "lower_teeth": self.lower_teeth,
        }


def _readonly(a):
    a = np.array(a)
    a.setflags(write=False)
    return a


def build_head() -> Head:
    """Build the procedural default head (deterministic; ~1 s). Prefer the cached
    :func:`generic_head`."""
    g = _build_grid()
    V, F = g.vertices, g.triangles
    mesh = TriMesh(V, F)

    # ---- ordered edges of the slits
    def slit_path(s: _Slit, upper: bool) -> np.ndarray:
        on = (g.ring == s.ring) & (g.theta > s.theta_a + 1e-12) & (g.theta < s.theta_b - 1e-12)
        on &= g.upper_copy if upper else ~g.upper_copy
        ids = np.nonzero(on)[0]
        ids = ids[np.argsort(g.theta[ids])]
        corners = corner_ids(s)
        return np.concatenate([[corners[0]], ids, [corners[1]]]).astype(np.int64)

    def corner_ids(s: _Slit) -> tuple[int, int]:
        ring = np.nonzero(g.ring == s.ring)[0]
        a = ring[np.argmin(np.abs(g.theta[ring] - s.theta_a))]
        b = ring[np.argmin(np.abs(g.theta[ring] - s.theta_b))]
        return int(a), int(b)

    edges = {}
    mouth = g.slits["mouth"]
    edges["upper_lip_edge"] = slit_path(mouth, True)
    edges["lower_lip_edge"] = slit_path(mouth, False)
    for side in ("left", "right"):
        s = g.slits[f"eye_{side}"]
        up, lo = slit_path(s, True), slit_path(s, False)
        if side == "right":  # order from the inner corner (near x = 0) outward
            up, lo = up[::-1], lo[::-1]
        edges[f"upper_lid_{side}"] = up
        edges[f"lower_lid_{side}"] = lo
    neck = np.nonzero(g.ring == 0)[0]
    edges["neck"] = neck[np.argsort(g.theta[neck])].astype(np.int64)

    # ---- landmarks
    mid_up = edges["upper_lip_edge"][np.argmin(np.abs(V[edges["upper_lip_edge"], 0]))]
    mid_lo = edges["lower_lip_edge"][np.argmin(np.abs(V[edges["lower_lip_edge"], 0]))]
    vid = {
        "Inner left eye corner": edges["upper_lid_left"][0],
        "Outer left eye corner": edges["upper_lid_left"][-1],
        "Inner right eye corner": edges["upper_lid_right"][0],
        "Outer right eye corner": edges["upper_lid_right"][-1],
        "Right mouth corner": edges["upper_lip_edge"][0],
        "Left mouth corner": edges["upper_lip_edge"][-1],
        "Upper lip inner middle": mid_up,
        "Lower lip inner middle": mid_lo,
    }
    vid = {k: int(v) for k, v in vid.items()}
    pos = {k: V[v] for k, v in vid.items()}
    brow_x = {"Outer": 58.2, "Middle": 37.9, "Inner": 11.7}
    front_xy, front_names = [], []
    for which, bx in brow_x.items():
        for side, sx in (("left", 1.0), ("right", -1.0)):
            front_names.append(f"{which} {side} eyebrow")
            front_xy.append((sx * bx, float(_brow_line(bx))))
    for side, sx in (("left", 1.0), ("right", -1.0)):
        front_names.append(f"Nose saddle {side}")
        front_xy.append((sx * 8.5, 27.4))
        front_names.append(f"{side.capitalize()} nose peak")
        front_xy.append((sx * 19.8, -2.5))
    hits = _front_hits(V, F, np.array(front_xy))
    pos.update(dict(zip(front_names, hits)))
    pos["Nose tip"] = _most_anterior(V, F, -6.0, 14.0)
    # labrale superius / inferius: the midpoints of the upper and lower vermilion borders
    lips = _front_hits(
        V,
        F,
        np.array(
            [[0.0, float(_upper_vermilion_border(0.0))], [0.0, _MOUTH_MID_Y - _LOWER_LIP_BORDER]]
        ),
    )
    pos["Upper lip outer middle"], pos["Lower lip outer middle"] = lips[0], lips[1]
    pos["Chin middle"] = _most_anterior(V, F, -74.0, -52.0)
    # ear lobes: lowest part of the lobe relief, seen from the side
    ly, lz = _ear_point(-1.0, -26.0)  # the lower part of the lobe
    lobe = _first_hits(
        V,
        F,
        np.array([[200.0, ly, lz], [-200.0, ly, lz]]),
        np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
    )
    pos["Left ear lobe"], pos["Right ear lobe"] = lobe[0], lobe[1]
    landmarks = Landmarks(BOSPHORUS_LABELS, np.array([pos[n] for n in BOSPHORUS_LABELS]))

    # ---- regions
    p0 = _base_points(g.theta, g.phi)
    n0 = _base_normals(p0)
    x, y, z = V[:, 0], V[:, 1], V[:, 2]
    ax = np.abs(x)
    face = (p0[:, 2] > 15.0) & (y > -90.0) & (y < 88.0) & (n0[:, 2] > 0.3)
    # which side of the mouth slit: vertices of the slit ring by their copy, others by ring
    mouth_side = np.where(
        g.ring == mouth.ring, np.where(g.upper_copy, 1, -1), np.sign(g.ring - mouth.ring)
    )
    in_mouth_x = ax < _MOUTH_CORNER[0] + 3.0
    upper_lip = (
        face
        & in_mouth_x
        & (mouth_side > 0)
        & (y < -12.5)
        & (y > _mouth_line(np.minimum(ax, _MOUTH_CORNER[0])) - 1.0)
    )
    lower_lip = face & in_mouth_x & (mouth_side < 0) & (y > -48.0) & (y < -30.0)
    regions = {
        "face": face,
        "upper_lip": upper_lip,
        "lower_lip": lower_lip,
        "lips": upper_lip | lower_lip,
    }
    nose = face & (ax < 23.0) & (y > -14.0) & (y < 42.0)
    nose &= _nose_z(x, y) > _front_base_z(x, y) + _relief_z(x, y) - 1.0
    regions["nose"] = nose
    eye_ring = g.slits["eye_left"].ring
    eye_side = np.where(
        g.ring == eye_ring, np.where(g.upper_copy, 1, -1), np.sign(g.ring - eye_ring)
    )
    for side, sx in (("left", 1.0), ("right", -1.0)):
        c = _EYE_CENTER * np.array([sx, 1.0, 1.0])
        near = face & (np.abs(x - c[0]) < 17.0) & (y > 20.0) & (y < 47.0) & (sx * x > 12.0)
        regions[f"eye_{side}"] = near
        lid_x = (sx * x > _CANTHUS_IN[0] - 1.0) & (sx * x < _CANTHUS_OUT[0] + 1.0)
        line, up, lo = _lid_margin_curves(np.clip(sx * x, _CANTHUS_IN[0], _CANTHUS_OUT[0]))
        regions[f"upper_lid_{side}"] = near & lid_x & (eye_side > 0) & (y < up + 8.0)
        regions[f"lower_lid_{side}"] = near & lid_x & (eye_side < 0) & (y > lo - 6.0)
    # jaw: below the mouth line in front, below a line from the mouth corner to under the ear
    t = np.clip((ax - _MOUTH_CORNER[0]) / (70.0 - _MOUTH_CORNER[0]), 0.0, 1.0)
    jaw_line = _MOUTH_CORNER[1] + t * (-22.0 - _MOUTH_CORNER[1])
    below = np.where(in_mouth_x & (np.abs(y - _MOUTH_MID_Y) < 6.0), mouth_side < 0, y < jaw_line)
    regions["jaw"] = below & (y > -92.0) & (p0[:, 2] > -15.0) & (z > -15.0)
    regions["forehead"] = face & (y > 45.0)
    for side, sx in (("left", 1.0), ("right", -1.0)):
        regions[f"cheek_{side}"] = (
            face & (sx * x > 18.0) & (y < 24.0) & (y > -40.0) & ~regions["jaw"]
        )
        eu, ev = _ear_frame(y, z)
        regions[f"ear_{side}"] = (sx * x > 55.0) & ((ev / 31.0) ** 2 + (eu / 17.5) ** 2 < 1.0)
    regions["neck"] = (y < -85.0) & ~face
    regions["scalp"] = (y > 60.0) & ~face
    regions = {k: _readonly(v.astype(bool)) for k, v in regions.items()}

    eyes = (_eyeball(1.0), _eyeball(-1.0))
    centers = np.stack([_EYE_CENTER, _EYE_CENTER * np.array([-1.0, 1.0, 1.0])])
    return Head(
        mesh=mesh,
        landmarks=landmarks,
        face_mask=regions["face"],
        upper_teeth=_teeth(True),
        lower_teeth=_teeth(False),
        regions=regions,
        edges={k: _readonly(v) for k, v in edges.items()},
        eyes=eyes,
        eye_centers=_readonly(centers),
        landmark_vertex=vid,
        mirror=_readonly(g.mirror.astype(np.int64)),
    )


@functools.lru_cache(maxsize=1)
def generic_head() -> Head:
    """The embedded procedural default head (cached; see :class:`Head`). All units mm."""
    return build_head()


def save_head(
    head: Head,
    directory,
    *,
    stem: str = "head",
    picture: bool = True,
    panel_px: int = 600,
    labels: bool = False,
    units: str = "mm",
) -> dict:
    """Write a head to ``directory``: the skin ``<stem>.ply``, its landmarks ``<stem>.lm3``,
    ``upper_teeth.ply``, ``lower_teeth.ply``, ``eye_left.ply``, ``eye_right.ply`` and, if
    ``picture``, ``<stem>.png`` (front and side views with the landmarks).

    Args:
        head: the :class:`Head` (mm).
        directory: output folder (created if needed).
        stem: file name stem of the skin mesh, landmarks and picture.
        picture: also render the PNG (matplotlib, headless).
        panel_px: picture panel size, pixels.
        labels: write the landmark names on the picture.
        units: unit of the written meshes ("mm", "cm" or "m"); landmarks are always mm.

    Returns:
        ``{name: Path}`` of the files written.
    """
    from pathlib import Path

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    files["skin"] = out / f"{stem}.ply"
    save_mesh(files["skin"], head.mesh, units=units)
    files["landmarks"] = out / f"{stem}.lm3"
    write_lm3(
        files["landmarks"],
        head.landmarks,
        comment=f"jaxface default head: 24 Bosphorus landmarks (mm) on {stem}.ply",
    )
    for name, mesh in (
        ("upper_teeth", head.upper_teeth),
        ("lower_teeth", head.lower_teeth),
        ("eye_left", head.eyes[0]),
        ("eye_right", head.eyes[1]),
    ):
        files[name] = out / f"{name}.ply"
        save_mesh(files[name], mesh, units=units)
    if picture:
        files["picture"] = save_views(
            out / f"{stem}.png",
            head_layers(head),
            ("front", "side"),
            landmarks=head.landmarks,
            labels=labels,
            panel_px=panel_px,
            title="jaxface default head (mm): front and left side",
        )
    return files
