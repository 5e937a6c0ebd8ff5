"""The skull: soft-tissue depth, the estimated skull, user-supplied skulls and template fitting.

* :func:`tissue_depth` interpolates the table of average soft-tissue depths
  (``shared/notes/facial-anatomy.md``) over the skin with a biharmonic RBF, from sites derived
  from the Bosphorus landmarks (:data:`TISSUE_DEPTH_MM`, :func:`depth_sites`).
* :func:`estimate_skull` builds the Lee-Terzopoulos-Waters style skull when none is given: the
  skin offset inward along smoothed normals by the local tissue depth, smoothed, and split
  into cranium and mandible by a landmark-derived side profile of the mandible
  (:func:`mandible_mask`).
* :func:`load_skull` takes a user-supplied skull (cranium + separate mandible, optional teeth)
  in any unit; :func:`load_artisynth_skull` reads the ArtiSynth example (metres, its own axes).
* :func:`fit_skull` fits a template skull, built for a template skin with landmarks, into any
  other skin with a landmark RBF (thesis sec. 5.4), enriched with extra correspondences found
  by cylindrical ray casting through the midpoints of landmark pairs.

Units: mm; +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from matplotlib.path import Path as MplPath

from ..errors import DataNotFoundError, MeshError, RigError
from ..mesh import TriMesh, load_mesh, unit_scale
from ..rbf import KernelName, fit_numpy
from .frame import REQUIRED_LABELS, FaceFrame, face_frame
from .geometry import radial_project, smooth_field, smooth_normals

__all__ = [
    "TISSUE_DEPTH_MM",
    "Skull",
    "depth_sites",
    "tissue_depth",
    "mandible_mask",
    "estimate_skull",
    "load_skull",
    "load_artisynth_skull",
    "ARTISYNTH_TO_JAXFACE",
    "enrich_correspondences",
    "fit_skull",
    "head_centre",
]

#: Average adult soft-tissue depth over the skull, mm (facial-anatomy.md).
TISSUE_DEPTH_MM: dict[str, float] = {
    "glabella": 5.5,
    "nasion": 6.5,
    "mid-nasal": 3.0,
    "supraorbital": 6.0,
    "infraorbital": 7.0,
    "zygomatic": 7.0,
    "mid-philtrum": 11.0,
    "upper lip": 12.0,
    "lower lip": 13.0,
    "chin": 11.0,
    "mentolabial sulcus": 11.0,
    "menton": 8.0,
    "mid-masseter": 18.0,
    "gonion": 13.0,
    "forehead": 5.0,
    "temple": 10.0,
}

# depth over the cranial vault (scalp) and the front of the neck, used at far sites so that
# the interpolation stays bounded away from the face (mm)
_SCALP_DEPTH_MM = 6.0
_NECK_DEPTH_MM = 16.0
_DEPTH_RANGE_MM = (2.0, 25.0)

# head centre in reference-mm frame offsets (radial projections aim at it)
_HEAD_CENTRE = np.array([0.0, -10.0, -45.0])


def head_centre(frame: FaceFrame) -> np.ndarray:
    """``(3,)`` mm: the point radial projections aim at (inside the head, behind the nose)."""
    return frame.to_world(_HEAD_CENTRE)


@dataclass(frozen=True)
class Skull:
    """A skull: the static cranium (with maxilla) and the movable mandible, in mm.

    Attributes:
        cranium: :class:`TriMesh`, static.
        mandible: :class:`TriMesh`, moved rigidly by the jaw.
        upper_teeth: optional :class:`TriMesh`, static (moves with the cranium).
        lower_teeth: optional :class:`TriMesh`, moves with the mandible.
        source: "estimated", "user" or "fitted".
        thickness_scale: factor applied to muscle thickness when the skull was fitted from a
            template (thesis sec. 5.4: ratio of head to skull bounding-box diagonals).
    """

    cranium: TriMesh
    mandible: TriMesh
    upper_teeth: TriMesh | None = None
    lower_teeth: TriMesh | None = None
    source: str = "user"
    thickness_scale: float = 1.0
    extras: dict = field(default_factory=dict, repr=False)

    @property
    def parts(self) -> list[TriMesh]:
        """``[cranium, mandible]``."""
        return [self.cranium, self.mandible]

    def with_teeth(self, upper_teeth: TriMesh | None, lower_teeth: TriMesh | None) -> Skull:
        """A copy with the given teeth (mm)."""
        return replace(self, upper_teeth=upper_teeth, lower_teeth=lower_teeth)


# ------------------------------------------------------------------------------ depth sites
def _mirror(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])


def depth_sites(skin: TriMesh, landmarks) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The tissue-depth table placed on a skin.

    Sites come from the landmarks (e.g. "chin" = Chin middle, "supraorbital" = middle
    eyebrows) or from frame offsets (gonion, masseter, temple), projected onto the skin by
    radial ray casting. Far sites over the scalp and the neck (6 and 16 mm) are added where the
    skin reaches them, so that the interpolation stays bounded.

    Args:
        skin: the skin mesh, mm.
        landmarks: its Bosphorus landmarks (or a :class:`FaceFrame`).

    Returns:
        ``(names (n,), positions (n, 3) mm on the skin, depths (n,) mm)``.
    """
    fr = landmarks if isinstance(landmarks, FaceFrame) else face_frame(landmarks)
    P = fr.points
    L = fr.to_local
    sites: list[tuple] = []  # name, world point, depth, strict, inward ray direction or None

    def add(name, pt, depth, strict=False, direction=None):
        sites.append((name, np.asarray(pt, dtype=np.float64), float(depth), strict, direction))

    T = TISSUE_DEPTH_MM
    glab = 0.5 * (P["Inner left eyebrow"] + P["Inner right eyebrow"])
    saddle = 0.5 * (P["Nose saddle left"] + P["Nose saddle right"])
    add("glabella", glab, T["glabella"])
    add("nasion", 0.35 * glab + 0.65 * saddle, T["nasion"])
    add("mid-nasal", saddle + 0.45 * (P["Nose tip"] - saddle), T["mid-nasal"])
    peaks_l = L(0.5 * (P["Left nose peak"] + P["Right nose peak"]))
    ulo = L(P["Upper lip outer middle"])
    add("mid-philtrum", fr.to_world([0.0, 0.5 * (peaks_l[1] + ulo[1]), ulo[2]]), T["mid-philtrum"])
    add("upper lip", P["Upper lip outer middle"], T["upper lip"])
    add("lower lip", P["Lower lip outer middle"], T["lower lip"])
    add("chin", P["Chin middle"], T["chin"])
    add(
        "mentolabial sulcus",
        0.5 * (P["Lower lip outer middle"] + P["Chin middle"]),
        T["mentolabial sulcus"],
    )
    add("menton", fr.menton, T["menton"], True, fr.axes[1])  # ray from below the chin
    brow_y = L(glab)[1]
    add("forehead", fr.to_world([0.0, brow_y + 34.0, 15.0]), T["forehead"], True)
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        eye = L(0.5 * (P[f"Outer {side} eye corner"] + P[f"Inner {side} eye corner"]))
        add(f"supraorbital {side}", P[f"Middle {side} eyebrow"], T["supraorbital"])
        add(f"infraorbital {side}", fr.to_world(eye + [0.0, -14.0, 0.0]), T["infraorbital"], True)
        oc = L(P[f"Outer {side} eye corner"])
        add(f"zygomatic {side}", fr.to_world(oc + [sgn * 4.0, -22.0, 0.0]), T["zygomatic"], True)
        add(
            f"mid-masseter {side}", fr.to_world([sgn * 50.0, -62.0, -35.0]), T["mid-masseter"], True
        )
        add(f"gonion {side}", fr.gonions[0 if sgn > 0 else 1], T["gonion"], True)
        add(f"temple {side}", fr.to_world([sgn * 62.0, 22.0, -35.0]), T["temple"], True)
        add(f"forehead {side}", fr.to_world([sgn * 32.0, brow_y + 28.0, 5.0]), T["forehead"], True)
        add(f"scalp {side}", fr.to_world([sgn * 65.0, 75.0, -90.0]), _SCALP_DEPTH_MM, True)
        add(f"neck {side}", fr.to_world([sgn * 45.0, -135.0, -55.0]), _NECK_DEPTH_MM, True)
    add("scalp top", fr.to_world([0.0, 112.0, -50.0]), _SCALP_DEPTH_MM, True)
    add("scalp back", fr.to_world([0.0, 40.0, -175.0]), _SCALP_DEPTH_MM, True)
    add("neck front", fr.to_world([0.0, -150.0, -15.0]), _NECK_DEPTH_MM, True)

    names = [s[0] for s in sites]
    pts = np.stack([s[1] for s in sites])
    depth = np.array([s[2] for s in sites])
    strict = np.array([s[3] for s in sites])
    centre = head_centre(fr)
    dirs = np.stack([s[4] if s[4] is not None else centre - s[1] for s in sites])
    hits = radial_project(skin, pts, None, directions=dirs, fallback_closest=False)
    dist = np.linalg.norm(hits.positions - pts, axis=1)
    # landmark-based sites always project (they lie on the skin); frame-offset estimates
    # only where the skin really reaches them (an open face mask has no scalp)
    ok = hits.hit & (~strict | (dist < 40.0 * fr.mean_scale))
    if not ok[~strict].all():
        # fall back to closest points for landmark sites (on the skin by construction)
        miss = np.flatnonzero(~ok & ~strict)
        sp_, _ = skin.closest_points(pts[miss])
        corners = skin.vertices[skin.triangles[np.asarray(sp_.tri)]]
        hits.positions[miss] = np.einsum("kj,kjd->kd", np.asarray(sp_.bary), corners)
        ok[miss] = True
    keep = np.flatnonzero(ok)
    return [names[i] for i in keep], hits.positions[keep], depth[keep]


def tissue_depth(skin: TriMesh, landmarks, *, reg: float = 1e-3) -> np.ndarray:
    """Soft-tissue depth at every skin vertex, mm.

    The depth table (:data:`TISSUE_DEPTH_MM`) placed at landmark-derived sites
    (:func:`depth_sites`) and interpolated over the skin with a biharmonic RBF (a small
    ridge ``reg`` keeps it from overshooting), then clamped to 2..25 mm.

    Args:
        skin: the skin mesh, mm.
        landmarks: its Bosphorus landmarks (or a :class:`FaceFrame`).
        reg: RBF ridge (normalised units, see :mod:`jaxface.rbf`).

    Returns:
        ``(V,)`` float64 depths, mm.
    """
    _, pos, depth = depth_sites(skin, landmarks)
    dst = pos.copy()
    dst[:, 0] += depth  # a scalar RBF through the first coordinate of a vector morph
    morph = fit_numpy(pos, dst, kernel="biharmonic", reg=reg, merge_duplicates=True)
    vals = morph.apply_np(skin.vertices)[:, 0] - skin.vertices[:, 0]
    return np.clip(vals, *_DEPTH_RANGE_MM)


# ------------------------------------------------------------------------------ mandible
def mandible_mask(points, landmarks) -> np.ndarray:
    """Which points belong to the mandible, by a landmark-derived side profile.

    In the face frame's (z, y) plane the mandible is the polygon bounded above by the line
    from the condyles down to the mouth corners at the height of the mouth slit (stomion) and
    then forward along the slit, and below by the line from the menton back to the gonion and
    up to the condyle (6 mm of margin below the bone border).

    Args:
        points: ``(K, 3)`` mm (skull or skin points of this face).
        landmarks: Bosphorus landmarks or a :class:`FaceFrame`.

    Returns:
        ``(K,)`` bool.
    """
    fr = landmarks if isinstance(landmarks, FaceFrame) else face_frame(landmarks)
    loc = fr.to_local(np.atleast_2d(points))
    cz, cy = fr.to_local(fr.condyles[0])[[2, 1]]
    mc = 0.5 * (
        fr.to_local(fr.points["Left mouth corner"]) + fr.to_local(fr.points["Right mouth corner"])
    )
    st = fr.to_local(fr.stomion)
    me = fr.to_local(fr.menton)
    go = fr.to_local(fr.gonions[0])
    poly = np.array(
        [
            (cz - 12.0, cy + 6.0),
            (cz + 10.0, cy + 6.0),
            (mc[2] - 6.0, st[1]),
            (400.0, st[1]),
            (400.0, me[1] - 6.0),
            (me[2], me[1] - 6.0),
            (go[2] - 8.0, go[1] - 6.0),
            (cz - 12.0, cy - 10.0),
        ]
    )
    return MplPath(poly).contains_points(loc[:, [2, 1]])


# ------------------------------------------------------------------------------ estimate
def estimate_skull(
    skin: TriMesh,
    landmarks,
    *,
    normal_smoothing: int = 8,
    surface_smoothing: int = 10,
    upper_teeth: TriMesh | None = None,
    lower_teeth: TriMesh | None = None,
) -> Skull:
    """Estimate a skull under a skin (Lee-Terzopoulos-Waters 1995 offset surface).

    Each skin vertex is moved inward along its smoothed normal by the local soft-tissue depth
    (:func:`tissue_depth`); the offset surface is smoothed (``surface_smoothing`` one-ring
    passes) to remove folds in concave regions (nostrils, lips, eyes), then split into the
    static cranium and the mandible by :func:`mandible_mask` (a triangle belongs to the
    mandible when at least two of its vertices do).

    Args:
        skin: the skin mesh, mm.
        landmarks: its Bosphorus landmarks.
        normal_smoothing: one-ring passes over the vertex normals before offsetting.
        surface_smoothing: one-ring passes over the offset positions.
        upper_teeth, lower_teeth: optional teeth meshes (mm) to carry along.

    Returns:
        :class:`Skull` with ``source="estimated"``; ``extras["depth"]`` holds the ``(V,)``
        depths and ``extras["mandible_vertices"]`` the ``(V,)`` bool vertex mask.

    Raises:
        RigError: the landmarks put no skin triangle in the mandible or in the cranium.
    """
    fr = face_frame(landmarks)
    depth = tissue_depth(skin, fr)
    n = smooth_normals(skin, normal_smoothing)
    off = skin.vertices - depth[:, None] * n
    off = smooth_field(skin, off, surface_smoothing, lam=0.5)
    vmask = mandible_mask(off, fr)
    tmask = vmask[skin.triangles].sum(axis=1) >= 2
    if tmask.all() or not tmask.any():
        raise RigError(
            "estimate_skull: the landmark-derived mandible outline selects "
            f"{'every' if tmask.all() else 'no'} triangle of the skin; check that the skin "
            "covers the lower face and that the landmarks are in mm with +y up and +z forward."
        )
    offset_mesh = TriMesh(off, skin.triangles, validate=False)
    cranium, _ = offset_mesh.submesh(~tmask)
    mandible, _ = offset_mesh.submesh(tmask)
    return Skull(
        cranium=cranium,
        mandible=mandible,
        upper_teeth=upper_teeth,
        lower_teeth=lower_teeth,
        source="estimated",
        extras={"depth": depth, "mandible_vertices": vmask, "offset_mesh": offset_mesh},
    )


# ------------------------------------------------------------------------------ loading
def _as_mesh(m, units: str, what: str, rotation=None) -> TriMesh:
    if m is None:
        raise RigError(f"load_skull needs a {what} mesh (a TriMesh or an OBJ/PLY path); got None.")
    if isinstance(m, TriMesh):
        mesh = m
        if units != "mm":
            mesh = mesh.with_vertices(mesh.vertices * unit_scale(units))
    else:
        p = Path(m)
        if not p.exists():
            raise DataNotFoundError(f"{what} mesh file not found: {p}.")
        mesh = load_mesh(p, units=units, validate=False)
    if rotation is not None:
        mesh = mesh.with_vertices(mesh.vertices @ np.asarray(rotation, np.float64).T)
    return mesh


def load_skull(
    cranium, mandible, *, units: str = "mm", upper_teeth=None, lower_teeth=None, rotation=None
) -> Skull:
    """A user-supplied skull: cranium (with maxilla) and a separate mandible.

    Args:
        cranium, mandible: :class:`TriMesh` or OBJ/PLY paths (a list of meshes/paths for the
            cranium is merged, e.g. cranium + maxilla).
        units: their unit ("mm", "cm" or "m"); converted to mm.
        upper_teeth, lower_teeth: optional meshes/paths, same unit.
        rotation: optional ``(3, 3)`` matrix taking the file's axes to jaxface's (+y up,
            +z forward, +x subject's left), applied after the unit conversion.

    Returns:
        :class:`Skull` (``source="user"``).
    """
    if isinstance(cranium, (list, tuple)):
        cranium_mesh = TriMesh.concatenate(
            [_as_mesh(c, units, "cranium", rotation) for c in cranium]
        )
    else:
        cranium_mesh = _as_mesh(cranium, units, "cranium", rotation)
    return Skull(
        cranium=cranium_mesh,
        mandible=_as_mesh(mandible, units, "mandible", rotation),
        upper_teeth=(
            None if upper_teeth is None else _as_mesh(upper_teeth, units, "upper teeth", rotation)
        ),
        lower_teeth=(
            None if lower_teeth is None else _as_mesh(lower_teeth, units, "lower teeth", rotation)
        ),
        source="user",
    )


#: Rotation from ArtiSynth's face-model axes (x backward, y toward the subject's right,
#: z up) to jaxface's (+x subject's left, +y up, +z forward).
ARTISYNTH_TO_JAXFACE = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])


def load_artisynth_skull(folder) -> Skull:
    """The ArtiSynth example skull (``ubccranium.obj`` + ``ubcmaxilla.obj`` as the cranium,
    ``ubcjaw.obj`` as the mandible), converted from metres to mm and rotated into jaxface's
    axes (:data:`ARTISYNTH_TO_JAXFACE`). Its frame matches ArtiSynth's ``face.node`` skin, not
    other heads: fit it into a skin with :func:`fit_skull`.

    Args:
        folder: the ``artisynth`` data folder.

    Raises:
        DataNotFoundError: a file is missing.
    """
    folder = Path(folder)
    files = {
        k: folder / f
        for k, f in (
            ("cranium", "ubccranium.obj"),
            ("maxilla", "ubcmaxilla.obj"),
            ("jaw", "ubcjaw.obj"),
        )
    }
    for k, f in files.items():
        if not f.exists():
            raise DataNotFoundError(f"ArtiSynth {k} mesh not found: {f}.")
    return load_skull(
        [files["cranium"], files["maxilla"]], files["jaw"], units="m", rotation=ARTISYNTH_TO_JAXFACE
    )


# ------------------------------------------------------------------------------ fitting
#: Landmark pairs whose midpoints are projected (cylindrically) onto both skins to enrich the
#: correspondences of the template fit (thesis sec. 5.4 uses 16 such pairs).
ENRICHMENT_PAIRS: tuple[tuple[str, str], ...] = (
    ("Outer left eyebrow", "Outer left eye corner"),
    ("Outer right eyebrow", "Outer right eye corner"),
    ("Middle left eyebrow", "Inner left eyebrow"),
    ("Middle right eyebrow", "Inner right eyebrow"),
    ("Outer left eye corner", "Left mouth corner"),
    ("Outer right eye corner", "Right mouth corner"),
    ("Inner left eye corner", "Left nose peak"),
    ("Inner right eye corner", "Right nose peak"),
    ("Left nose peak", "Left mouth corner"),
    ("Right nose peak", "Right mouth corner"),
    ("Left mouth corner", "Chin middle"),
    ("Right mouth corner", "Chin middle"),
    ("Nose tip", "Upper lip outer middle"),
    ("Lower lip outer middle", "Chin middle"),
    ("Outer left eye corner", "Chin middle"),
    ("Outer right eye corner", "Chin middle"),
)


def enrich_correspondences(skin: TriMesh, landmarks, pairs=ENRICHMENT_PAIRS) -> np.ndarray:
    """Extra skin points for a landmark fit (thesis sec. 5.4).

    For each pair of landmarks, the midpoint is projected onto the skin by a ray perpendicular
    to the vertical axis (the frame's y axis) through the skin's barycentre, coming from
    outside and aimed at that axis; the first hit is kept (closest point if it misses).

    Args:
        skin: the skin mesh, mm.
        landmarks: its Bosphorus landmarks.
        pairs: landmark-name pairs.

    Returns:
        ``(len(pairs), 3)`` mm.
    """
    fr = face_frame(landmarks)
    mids = np.stack([0.5 * (fr.points[a] + fr.points[b]) for a, b in pairs])
    bary = skin.vertices.mean(axis=0)
    y = fr.axes[1]
    # closest point of the vertical axis to each midpoint: the ray aims there horizontally
    foot = bary + np.outer((mids - bary) @ y, y)
    hits = radial_project(skin, mids, None, directions=foot - mids)
    return hits.positions


def fit_skull(
    skull: Skull,
    template_skin: TriMesh,
    template_landmarks,
    skin: TriMesh,
    landmarks,
    *,
    kernel: KernelName = "multiquadric",
    enrich: bool = True,
) -> Skull:
    """Fit a template skull into another skin with a landmark RBF (thesis sec. 5.4).

    The morph is fitted on the landmark pairs (template skin -> target skin) plus, if
    ``enrich``, the cylindrical-ray-cast midpoints of :data:`ENRICHMENT_PAIRS` on both skins,
    and applied to the cranium, mandible and teeth. The muscle thickness scale is the ratio
    of the target's to the template's skin bounding-box diagonal (thesis ``t' = t d_head /
    d_skull``, written for a skin-to-skin fit).

    Args:
        skull: the template skull (mm), in the template skin's frame.
        template_skin, template_landmarks: the skin the template skull was made for.
        skin, landmarks: the target skin and its landmarks.
        kernel: RBF kernel (:mod:`jaxface.rbf`), Hardy multiquadric by default as in the thesis.
        enrich: add the ray-cast correspondences.

    Returns:
        the fitted :class:`Skull` (``source="fitted"``).
    """
    fs, ft = face_frame(template_landmarks), face_frame(landmarks)
    src = [fs.points[n] for n in REQUIRED_LABELS]
    dst = [ft.points[n] for n in REQUIRED_LABELS]
    src, dst = np.stack(src), np.stack(dst)
    if enrich:
        src = np.concatenate([src, enrich_correspondences(template_skin, template_landmarks)])
        dst = np.concatenate([dst, enrich_correspondences(skin, landmarks)])
    # anatomical anchors deep inside (condyles, skull top) keep the back of the skull in place
    src = np.concatenate([src, fs.condyles, fs.skull_top[None]])
    dst = np.concatenate([dst, ft.condyles, ft.skull_top[None]])
    morph = fit_numpy(src, dst, kernel=kernel, reg=1e-4, merge_duplicates=True)

    def warp(m: TriMesh) -> TriMesh:
        return m.with_vertices(morph.apply_np(m.vertices))

    try:
        diag_t = np.linalg.norm(np.ptp(template_skin.vertices, axis=0))
        diag = np.linalg.norm(np.ptp(skin.vertices, axis=0))
    except ValueError as e:  # pragma: no cover - empty mesh
        raise MeshError(f"fit_skull: empty skin mesh ({e}).") from None
    return Skull(
        cranium=warp(skull.cranium),
        mandible=warp(skull.mandible),
        upper_teeth=None if skull.upper_teeth is None else warp(skull.upper_teeth),
        lower_teeth=None if skull.lower_teeth is None else warp(skull.lower_teeth),
        source="fitted",
        thickness_scale=float(diag / diag_t) * skull.thickness_scale,
        extras={"morph": morph},
    )
