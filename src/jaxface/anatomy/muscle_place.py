"""Placement of the muscle map on a head (thesis sec. 4.2): the surface registry, action lines
and :class:`PlacedMuscle`, and :func:`place_muscles` (fibred sheets, sphincters, eyelids) with
:func:`placement_registry`. Units: mm; +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import RigError
from ..mesh import TriMesh
from .frame import FaceFrame, face_frame
from .geometry import radial_project, smooth_normals
from .muscle_geometry import MuscleGrid, ellipse_points, grid_topology, sample_polyline
from .muscle_map_load import _SEGMENTS_PER_LINE, MuscleSpec, load_muscle_map
from .skull import Skull, head_centre


# ------------------------------------------------------------------------------ placement
@dataclass
class SurfaceRegistry:
    """The surfaces action lines and skin anchors can lie on, indexed by position.

    ``names[0] == "cranium"``, ``names[1] == "mandible"``, then placed muscles in placement
    order. ``meshes[k]`` is the rest :class:`TriMesh` of surface ``k``. The two skull
    surfaces carry their teeth (:func:`skull_registry`): a sphincter projected
    ``"backward"`` (the range variant's orbicularis oris) lies on them. ``bones`` are the
    same two bones without the teeth, whose triangles come first in ``meshes[0]`` and
    ``meshes[1]`` (a triangle index into a bone is one into its surface): every other muscle
    and the skin lie on the bones, never through the lips onto a tooth.
    """

    names: list[str] = field(default_factory=list)
    meshes: list[TriMesh] = field(default_factory=list)
    bones: list[TriMesh] = field(default_factory=list)

    def add(self, name: str, mesh: TriMesh) -> int:
        self.names.append(name)
        self.meshes.append(mesh)
        return len(self.names) - 1

    def index(self, name: str) -> int:
        return self.names.index(name)

    def skull(self, *, teeth: bool) -> list[TriMesh]:
        """The cranium and the mandible (surfaces 0 and 1): with their teeth, or the bare
        ``bones`` (the first two meshes when no bones are set)."""
        return self.meshes[:2] if teeth or not self.bones else self.bones


def _with_teeth(bone: TriMesh, teeth: TriMesh | None) -> TriMesh:
    """``bone`` and ``teeth`` as one surface, the bone's vertices and triangles first."""
    return bone if teeth is None else TriMesh.concatenate([bone, teeth])


def skull_registry(skull: Skull) -> SurfaceRegistry:
    """A :class:`SurfaceRegistry` holding the skull: the cranium with the upper teeth and
    the mandible with the lower teeth (each a bone's triangles, then its teeth hull's), and
    the bare bones in ``bones``.

    Behind the lips there is no bone at the height of the mouth slit, only the teeth, and
    the orbicularis oris lies on them (through the mucosa and the gums). On the bone alone
    the ring's samples at the slit fell to the nearest bone, up to 9 mm above it.
    """
    reg = SurfaceRegistry(bones=[skull.cranium, skull.mandible])
    reg.add("cranium", _with_teeth(skull.cranium, skull.upper_teeth))
    reg.add("mandible", _with_teeth(skull.mandible, skull.lower_teeth))
    return reg


@dataclass(frozen=True)
class ActionLine:
    """A polyline of surface points (thesis 4.2.1), at rest.

    Attributes:
        positions: ``(m, 3)`` rest positions, mm.
        normals: ``(m, 3)`` unit outward normals of the surfaces at the points.
        surface: ``(m,)`` int, index of the surface each point lies on
            (:class:`SurfaceRegistry`).
        tri: ``(m,)`` int triangle ids; bary: ``(m, 3)`` barycentric coordinates.
    """

    positions: np.ndarray
    normals: np.ndarray
    surface: np.ndarray
    tri: np.ndarray
    bary: np.ndarray


@dataclass
class PlacedMuscle:
    """A muscle placed on one face (mm).

    Attributes:
        spec: its :class:`MuscleSpec`.
        origin: ``(k, 3)`` fibre origins on the surface it lies on (``k = 1`` for linear
            muscles: the centre line; ``k = w`` fibres for sheets; the outer ring for a
            sphincter); mm.
        insertion: ``(k, 3)`` fibre insertions (sphincter: the inner ring); mm.
        origin_skin, insertion_skin: the same points at the skin, mm.
        thickness: mm (scaled to the face).
        fibres: the ``w`` action lines (sheets/linear: origin -> insertion; sphincter: the
            inner, middle and outer rings, closed).
        grid: the :class:`MuscleGrid` topology; rest_vertices: ``(2 w h, 3)`` mm;
            mesh: the closed rest :class:`TriMesh` (outward oriented).
        surface_id: index of this muscle in the :class:`SurfaceRegistry` (-1 for eyelids).
        centre, semi_axes, axes, normal: sphincter ellipse (centre ``(3,)`` mm, ``(a, b)`` mm,
            ``(2, 3)`` unit directions of a and b, ``(3,)`` unit normal of the contraction
            plane) - thesis sec. 4.3.2; eyelids: ``centre`` is the rotation pivot and
            ``axes[0]`` the rotation axis.
    """

    spec: MuscleSpec
    origin: np.ndarray
    insertion: np.ndarray
    origin_skin: np.ndarray
    insertion_skin: np.ndarray
    thickness: float = 0.0
    fibres: list = field(default_factory=list, repr=False)
    grid: MuscleGrid | None = field(default=None, repr=False)
    rest_vertices: np.ndarray | None = field(default=None, repr=False)
    mesh: TriMesh | None = field(default=None, repr=False)
    surface_id: int = -1
    centre: np.ndarray | None = None
    semi_axes: np.ndarray | None = None
    axes: np.ndarray | None = None
    normal: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def kind(self) -> str:
        return self.spec.kind


def _resolve(frame: FaceFrame, pt: dict) -> np.ndarray:
    """World position (mm) of a map point (before projection)."""
    acc = np.zeros(3)
    wsum = 0.0
    for key, w in pt["at"].items():
        if key.startswith("@"):
            k = key[1:]
            if k == "condyle_left":
                p = frame.condyles[0]
            elif k == "condyle_right":
                p = frame.condyles[1]
            elif k == "gonion_left":
                p = frame.gonions[0]
            elif k == "gonion_right":
                p = frame.gonions[1]
            elif k == "menton":
                p = frame.menton
            elif k in ("eye_centre", "eye_center"):
                p = frame.origin
            else:
                raise RigError(
                    f"unknown pseudo-landmark {key!r} in the muscle map; use "
                    "@condyle_left/right, @gonion_left/right, @menton, @eye_centre."
                )
        else:
            if key not in frame.points:
                raise RigError(
                    f"the muscle map refers to landmark {key!r}, which is not one of "
                    f"the 22 Bosphorus face labels {sorted(frame.points)}."
                )
            p = frame.points[key]
        acc += w * p
        wsum += w
    base = acc / wsum
    return base + (np.asarray(pt.get("offset", [0, 0, 0]), float) * frame.scale) @ frame.axes


class _Placer:
    """Projection machinery shared by all muscles of one face."""

    def __init__(self, skin: TriMesh, frame: FaceFrame, skull: Skull):
        self.skin = skin
        self.frame = frame
        self.centre = head_centre(frame)
        self.normals = smooth_normals(skin, 6)
        self.registry = skull_registry(skull)

    def to_skin(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radial projection onto the skin: positions (K, 3) and smoothed normals (K, 3)."""
        hits = radial_project(self.skin, pts, self.centre)
        corners_n = self.normals[self.skin.triangles[hits.tri]]
        n = np.einsum("kj,kjd->kd", hits.bary, corners_n)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return hits.positions, n

    def to_support(
        self, skin_pts: np.ndarray, skin_n: np.ndarray, support: list[int], *, teeth=False
    ) -> ActionLine:
        """Project skin-level points inward (along -normal) onto the support surfaces: the
        muscles and the bare bones, or with ``teeth`` the bones with their teeth (a bone's
        triangle indices are the same in both, :func:`skull_registry`)."""
        skull = self.registry.skull(teeth=teeth)
        meshes = [skull[k] if k < 2 else self.registry.meshes[k] for k in support]
        start = skin_pts + 40.0 * self.frame.mean_scale * skin_n
        hits = radial_project(
            meshes,
            start,
            None,
            directions=-skin_n,
            far=0.0,
            reach=80.0 * self.frame.mean_scale,
            fallback_closest=False,
        )
        surf = np.where(hits.mesh_index >= 0, np.asarray(support)[hits.mesh_index], -1)
        miss = np.flatnonzero(surf < 0)
        if miss.size:  # no support under these points: attach to the nearer skull part
            best = np.full(miss.size, np.inf)
            for k in (0, 1):
                m = skull[k]
                sp_, dist = m.closest_points(skin_pts[miss])
                better = dist < best
                best[better] = dist[better]
                surf[miss[better]] = k
                hits.tri[miss[better]] = np.asarray(sp_.tri)[better]
                hits.bary[miss[better]] = np.asarray(sp_.bary)[better]
                corners = m.vertices[m.triangles[np.asarray(sp_.tri)[better]]]
                hits.positions[miss[better]] = np.einsum(
                    "kj,kjd->kd", np.asarray(sp_.bary)[better], corners
                )
        normals = np.zeros_like(skin_pts)
        for k in np.unique(surf):
            sel = surf == k
            m = self.registry.meshes[k]
            vn = m.vertex_normals[m.triangles[hits.tri[sel]]]
            nn = np.einsum("kj,kjd->kd", hits.bary[sel], vn)
            normals[sel] = nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
        return ActionLine(
            hits.positions.copy(),
            normals,
            surf.astype(np.int64),
            hits.tri.astype(np.int64),
            hits.bary.copy(),
        )

    def support_ids(self, spec: MuscleSpec, placed: dict) -> list[int]:
        ids = []
        for sup in spec.lies_on:
            if sup == "skull":
                ids += [0, 1]
                continue
            cands = (
                [sup + "_L", sup + "_R", sup]
                if spec.side == "mid"
                else ([sup + ("_L" if spec.side == "left" else "_R"), sup])
            )
            for c in cands:
                if c in placed and placed[c].surface_id >= 0:
                    if placed[c].spec.layer >= spec.layer:
                        raise RigError(
                            f"muscle {spec.name} (layer {spec.layer}) lies on {c} "
                            f"(layer {placed[c].spec.layer}); a muscle can only lie "
                            "on deeper layers."
                        )
                    ids.append(placed[c].surface_id)
        if not ids:
            ids = [0, 1]
        return ids


def _line(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    u = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - u) * a[None] + u * b[None]


def _orient(grid: MuscleGrid, verts: np.ndarray) -> np.ndarray:
    """Triangles of the grid oriented outward (positive signed volume)."""
    t = grid.triangles
    v = verts[t]
    vol = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    return t if vol > 0 else t[:, ::-1].copy()


def _mirror_split(grid: MuscleGrid, x: np.ndarray) -> MuscleGrid:
    """Split the quads (sheets and side walls) on the subject's right (``x < 0``, the face
    frame's lateral coordinate of each vertex, mm) along their other diagonal.

    :func:`~jaxface.anatomy.muscle_geometry.grid_topology` splits every quad along the same
    grid diagonal, which a muscle on the left and its mirror image on the right (or the two
    halves of a mid-line ring) run in mirrored directions: on a mirror-symmetric face no
    triangle of a left muscle matched its right twin's, the two surfaces differed by up to
    0.8 mm, the muscles placed on them differed as much, and 45 skin vertices bound to other
    muscles than their mirror images (a full AU12 moved the skin below one mouth corner 13.6
    mm further than below the other). Splitting the right side's quads the other way makes
    the halves mirror images; a quad centred on ``x = 0`` keeps the grid's diagonal."""
    s = grid.triangles
    t = s.copy()
    q = 4 * (grid.h - 1) * (grid.w if grid.periodic else grid.w - 1)
    a, b, c = s[0:q:4].T
    d = s[1:q:4, 2]
    A, C, B = s[2:q:4].T
    D = s[3:q:4, 1]
    f = (x[a] + x[b] + x[c] + x[d]) < -1e-9
    t[0:q:4][f] = np.stack([a, b, d], 1)[f]
    t[1:q:4][f] = np.stack([b, c, d], 1)[f]
    t[2:q:4][f] = np.stack([A, D, B], 1)[f]
    t[3:q:4][f] = np.stack([B, D, C], 1)[f]
    p0, p1, p1n = s[q::2].T  # walls: (p0, p1, p1 + n), (p0, p1 + n, p0 + n)
    p0n = s[q + 1 :: 2, 2]
    f = (x[p0] + x[p1]) < -1e-9
    t[q::2][f] = np.stack([p0, p1, p0n], 1)[f]
    t[q + 1 :: 2][f] = np.stack([p1, p1n, p0n], 1)[f]
    return MuscleGrid(
        grid.w,
        grid.h,
        grid.periodic,
        t,
        grid.latitudinal_up,
        grid.longitudinal_up,
        grid.latitudinal_low,
        grid.longitudinal_low,
        grid.connection,
        grid.shear_up,
        grid.shear_low,
    )


def _build_mesh(pm: PlacedMuscle, grid: MuscleGrid, bottom: np.ndarray, normals: np.ndarray, frame):
    top = bottom + normals * pm.thickness  # thesis eq. 4.10
    verts = np.concatenate([bottom, top])
    grid = _mirror_split(grid, frame.to_local(verts)[:, 0])
    tris = _orient(grid, verts)
    pm.grid = MuscleGrid(
        grid.w,
        grid.h,
        grid.periodic,
        tris,
        grid.latitudinal_up,
        grid.longitudinal_up,
        grid.latitudinal_low,
        grid.longitudinal_low,
        grid.connection,
        grid.shear_up,
        grid.shear_low,
    )
    pm.rest_vertices = verts
    pm.mesh = TriMesh(verts, tris, validate=False)


def _place_fibred(P: _Placer, spec: MuscleSpec, support: list[int], tscale: float) -> PlacedMuscle:
    fr = P.frame
    assert spec.origin is not None and spec.insertion is not None  # checked by load_muscle_map
    o_guess = _resolve(fr, spec.origin)
    i_guess = _resolve(fr, spec.insertion)
    (o_s, i_s), (o_n, i_n) = P.to_skin(np.stack([o_guess, i_guess]))
    u = i_s - o_s
    if np.linalg.norm(u) < 1e-6:
        raise RigError(f"muscle {spec.name}: origin and insertion coincide on this face.")
    nrm = o_n + i_n
    v = np.cross(nrm, u)
    v /= np.linalg.norm(v)
    w, h = spec.grid
    wo, wi = np.asarray(spec.width) * fr.scale[0]
    # origin line (A3) and insertion line (A1) at the skin, sampled with w points (eq. 4.1)
    o_line = _line(o_s - 0.5 * wo * v, o_s + 0.5 * wo * v, w)
    i_line = _line(i_s - 0.5 * wi * v, i_s + 0.5 * wi * v, w)
    seg = _SEGMENTS_PER_LINE
    raw = np.concatenate([_line(o_line[j], i_line[j], seg + 1) for j in range(w)])
    sk, skn = P.to_skin(raw)
    al_all = P.to_support(sk, skn, support)
    fibres = []
    bottoms = np.zeros((h, w, 3))
    bnorms = np.zeros((h, w, 3))
    for j in range(w):
        sl = slice(j * (seg + 1), (j + 1) * (seg + 1))
        al = ActionLine(
            al_all.positions[sl],
            al_all.normals[sl],
            al_all.surface[sl],
            al_all.tri[sl],
            al_all.bary[sl],
        )
        fibres.append(al)
        s, n = sample_polyline(al.positions, h, 0.0, normals=al.normals)
        bottoms[:, j] = s
        bnorms[:, j] = n
    thickness = spec.thickness * fr.mean_scale * tscale
    k = 1 if spec.kind == "linear" else w
    org = bottoms[0] if k > 1 else bottoms[0].mean(axis=0, keepdims=True)
    ins = bottoms[-1] if k > 1 else bottoms[-1].mean(axis=0, keepdims=True)
    osk = o_line if k > 1 else o_s[None]
    isk = i_line if k > 1 else i_s[None]
    pm = PlacedMuscle(
        spec=spec,
        origin=org,
        insertion=ins,
        origin_skin=osk,
        insertion_skin=isk,
        thickness=thickness,
        fibres=fibres,
    )
    _build_mesh(pm, grid_topology(w, h, False), bottoms.reshape(-1, 3), bnorms.reshape(-1, 3), fr)
    return pm


def _place_sphincter(
    P: _Placer, spec: MuscleSpec, support: list[int], tscale: float
) -> PlacedMuscle:
    fr = P.frame
    assert spec.centre is not None  # checked by load_muscle_map
    c_guess = _resolve(fr, spec.centre)
    n = spec.n_around
    (ai, bi), (ao, bo) = (
        np.asarray(spec.inner) * fr.scale[:2],
        np.asarray(spec.outer) * fr.scale[:2],
    )
    guess = np.concatenate(
        [
            ellipse_points(c_guess, fr.axes[0], fr.axes[1], a, b, n)
            for a, b in ((ai, bi), (0.5 * (ai + ao), 0.5 * (bi + bo)), (ao, bo))
        ]
    )
    sk, skn = P.to_skin(guess)
    # "backward": straight back along the face's -z instead of the skin normal, onto the
    # teeth too (the lips lie on them)
    back = spec.project == "backward"
    along = np.tile(fr.axes[2], (len(skn), 1)) if back else skn
    al_all = P.to_support(sk, along, support, teeth=back)
    rings_skin, fibres = [], []
    # three rings: inner (A1), middle, outer (A3); each a closed action line of n points
    for r in range(3):
        sl = slice(r * n, (r + 1) * n)
        rings_skin.append(sk[sl])
        fibres.append(
            ActionLine(
                al_all.positions[sl],
                al_all.normals[sl],
                al_all.surface[sl],
                al_all.tri[sl],
                al_all.bary[sl],
            )
        )
    bottom = np.concatenate([f.positions for f in fibres])  # (3 n, 3): ring i is row i
    normals = np.concatenate([f.normals for f in fibres])
    # contraction plane (least squares through all samples) and the ellipse (sec. 4.3.2)
    mean = bottom.mean(axis=0)
    _, _, vt = np.linalg.svd(bottom - mean)
    ncp = vt[2] * np.sign(vt[2] @ fr.axes[2] if abs(vt[2] @ fr.axes[2]) > 1e-9 else 1.0)
    proj = lambda x: x - np.outer((x - mean) @ ncp, ncp)  # noqa: E731
    inner_p = proj(fibres[0].positions)
    outer_p = proj(fibres[2].positions)
    o_guess = inner_p.mean(axis=0)  # eq. 4.12
    # lines through opposite inner/outer sample pairs; points closest to o_guess, averaged
    cs = []
    for i in range(n):
        p0, p1 = inner_p[i], outer_p[(n - 1 - i) % n]
        d = p1 - p0
        dd = d @ d
        t = ((o_guess - p0) @ d) / dd if dd > 0 else 0.0
        cs.append(p0 + t * d)
    o = np.mean(cs, axis=0)
    da = fr.axes[0] - ncp * (fr.axes[0] @ ncp)
    da /= np.linalg.norm(da)
    db = fr.axes[1] - ncp * (fr.axes[1] @ ncp)
    db -= da * (db @ da)
    db /= np.linalg.norm(db)
    # semi-axes: the ellipse about the contraction centre the solver uses (the inner ring's mean,
    # eq. 4.12) that reaches the farthest sample on either side, so a ring and its mirror image
    # (the two eyes) get the same ellipse
    rel = proj(bottom) - o_guess
    a_len = np.max(np.abs(rel @ da))
    b_len = np.max(np.abs(rel @ db))
    thickness = spec.thickness * fr.mean_scale * tscale
    pm = PlacedMuscle(
        spec=spec,
        origin=fibres[2].positions,
        insertion=fibres[0].positions,
        origin_skin=rings_skin[2],
        insertion_skin=rings_skin[0],
        thickness=thickness,
        fibres=fibres,
        centre=o,
        semi_axes=np.array([a_len, b_len]),
        axes=np.stack([da, db]),
        normal=ncp,
    )
    _build_mesh(pm, grid_topology(n, 3, True), bottom, normals, fr)
    return pm


def _place_eyelid(P: _Placer, spec: MuscleSpec) -> PlacedMuscle:
    fr = P.frame
    side = "left" if spec.side == "left" else "right"
    inner = fr.points[f"Inner {side} eye corner"]
    outer = fr.points[f"Outer {side} eye corner"]
    axis = (outer - inner) if side == "left" else (inner - outer)  # points to +x on both
    axis = axis / np.linalg.norm(axis)
    # the lids slide over the eyeball: the axis through the corners, moved back by the
    # eyeball radius (12 reference mm)
    pivot = 0.5 * (inner + outer) - fr.axes[2] * 12.0 * fr.scale[2]
    pm = PlacedMuscle(
        spec=spec,
        origin=np.stack([inner]),
        insertion=np.stack([outer]),
        origin_skin=np.stack([inner]),
        insertion_skin=np.stack([outer]),
        centre=pivot,
        axes=np.stack([axis, fr.axes[1]]),
    )
    return pm


def place_muscles(skin: TriMesh, landmarks, skull: Skull, specs=None) -> list[PlacedMuscle]:
    """Place a muscle map on a face.

    Args:
        skin: the skin mesh, mm.
        landmarks: its Bosphorus landmarks (22 face labels).
        skull: the :class:`Skull` under it (estimated, fitted or user-supplied), mm.
        specs: the map (:func:`load_muscle_map`); the default map when None.

    Returns:
        the placed muscles, in layer order (deepest first); ``PlacedMuscle.surface_id``
        indexes the surfaces ``["cranium", "mandible", <muscles with meshes>...]``, which
        :func:`placement_registry` rebuilds.

    Raises:
        RigError: a muscle cannot be placed (named), or the map is inconsistent.
    """
    specs = load_muscle_map() if specs is None else list(specs)
    frame = face_frame(landmarks)
    P = _Placer(skin, frame, skull)
    placed: dict[str, PlacedMuscle] = {}
    out: list[PlacedMuscle] = []
    for spec in sorted(specs, key=lambda s: s.layer):
        if spec.kind == "eyelid":
            pm = _place_eyelid(P, spec)
        else:
            support = P.support_ids(spec, placed)
            if spec.kind == "sphincter":
                pm = _place_sphincter(P, spec, support, skull.thickness_scale)
            else:
                pm = _place_fibred(P, spec, support, skull.thickness_scale)
            assert pm.mesh is not None  # both placements build the muscle's mesh
            pm.surface_id = P.registry.add(spec.name, pm.mesh)
        placed[spec.name] = pm
        out.append(pm)
    return out


def placement_registry(skull: Skull, placed: list[PlacedMuscle]) -> SurfaceRegistry:
    """The :class:`SurfaceRegistry` matching ``PlacedMuscle.surface_id`` values."""
    reg = skull_registry(skull)
    for pm in sorted([p for p in placed if p.surface_id >= 0], key=lambda p: p.surface_id):
        if pm.mesh is None:
            raise RigError(
                f"placed muscle {pm.spec.name!r} has a surface id but no mesh; place the "
                "muscles with place_muscles."
            )
        k = reg.add(pm.spec.name, pm.mesh)
        if k != pm.surface_id:
            raise RigError(
                "placed muscles are inconsistent with their surface ids; place them "
                "again with place_muscles."
            )
    return reg
