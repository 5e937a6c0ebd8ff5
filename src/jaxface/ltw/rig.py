"""The Lee-Terzopoulos-Waters backend: a rig with the same controls as the PBD rig.

:func:`build_ltw_rig` turns a skin (+ landmarks, optional skull and muscle map) into an
:class:`LTWRig`; :func:`synthesize_ltw` maps the *same* activation vector (ordered as
``rig.muscle_names``, identical to the PBD rig built from the same map) and a
:class:`~jaxface.anatomy.jaw.JawPose` to the deformed skin, by a quasi-static solve of the
layered tissue (:func:`jaxface.ltw.integrate.relax`).

How the anatomy maps onto the paper's model:

* skull nodes: the estimated skull (:func:`jaxface.anatomy.skull.estimate_skull`, an inward
  offset of the skin by the soft-tissue depth, with the same topology) gives one skull node per
  skin vertex; for a user skull, the skull node is where the inward ray (smoothed normal) meets
  the cranium or mandible (fallback: the tissue-depth offset). Skull nodes on the mandible move
  rigidly with the jaw (``JawModel.transform``).
* muscles (:func:`jaxface.anatomy.muscle_map.place_muscles`): linear -> one Waters fibre from
  the placed origin (bone) to the insertion; sheet -> its ``k`` fibres, half-width = fibre
  spacing; sphincter (orbicularis oris / oculi) -> four piecewise-linear arcs on the middle ring
  (corners to the midline, see :mod:`jaxface.ltw.waters`); passive -> no force (the control
  exists but does nothing here); eyelid -> the paper's kinematic eyelids: the lid vertices are
  rotated about the lid axis like in the PBD rig (same angles) and held there.
* fibres whose origin lies on the mandible (:func:`~jaxface.anatomy.skull.mandible_mask`) move
  with the jaw.
* cheek puff: the paper's "outwardly directed radial forces": a force along the PBD rig's
  cheek-puff field on the fascia nodes (``puff_force`` per mm of the field).

Units: mm, degrees for the jaw angles; forces in the paper's model units.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..anatomy.cheek_puff import cheek_bump, puff_scale
from ..anatomy.frame import face_frame
from ..anatomy.geometry import smooth_normals
from ..anatomy.interface import RigConfig, register_backend
from ..anatomy.jaw import JawModel
from ..anatomy.muscle_map import place_muscles
from ..anatomy.rig_common import (
    BuildInfo,
    RigBase,
    check_activations,
    check_jaw,
    eyelid_regions,
    muscle_controls,
)
from ..anatomy.skull import estimate_skull, mandible_mask, tissue_depth
from ..errors import RigError
from ..mesh import TriMesh
from ..rigid import rotate_about_axes
from .forces import kinematic_positions
from .integrate import LTWModel, make_model, relax, residual
from .tissue import LTWParams, build_tissue
from .waters import Fibre, build_waters, linear_fibre, sphincter_fibres

__all__ = [
    "LTWRig",
    "LTWRigConfig",
    "LTWInfo",
    "build_ltw_rig",
    "synthesize_ltw",
    "synthesize_nodes",
    "equilibrium_residual",
]


class LTWInfo(BuildInfo):
    """Build-time (NumPy) objects of an LTW rig
    (:class:`~jaxface.anatomy.rig_common.BuildInfo`: skin, landmarks, frame, skull, placed,
    specs; compared by identity), and: depth ``(V,)`` skin-to-skull depth, mm; mandible
    ``(V,)`` bool, the skull nodes on the mandible; fibres: the :class:`Fibre` list.
    """

    depth: Any
    mandible: Any
    fibres: Any


class LTWRig(RigBase, eqx.Module):
    """A face rig on the layered-tissue backend (JAX pytree). The control accessors
    (``n_controls``, ``triangles``, ``index``, ``activations``) are
    :class:`~jaxface.anatomy.rig_common.RigBase`'s.

    Attributes:
        model: :class:`~jaxface.ltw.integrate.LTWModel` (tissue, muscles, params).
        jaw: :class:`~jaxface.anatomy.jaw.JawModel`.
        lid_nodes: ``(K,)`` int32 node ids driven by the eyelid controls.
        lid_fall: ``(K,)`` falloff; lid_upper: ``(K,)`` bool; lid_side: ``(K,)`` int32.
        lid_pivot, lid_axis: ``(S, 3)`` per eye; lid_angles: ``(M, S, 2)`` degrees at activation 1.
        puff_field: ``(V, 3)`` cheek-puff field, mm (force direction and weight);
            puff_left: ``(V,)`` bool, its left cheek's part.
        n_steps: quasi-static relaxation steps (static).
        muscle_names, muscle_aus: static tuples (the control order, shared with the PBD rig).
        info: static :class:`LTWInfo`.
    """

    model: LTWModel
    jaw: JawModel
    lid_nodes: jax.Array
    lid_fall: jax.Array
    lid_upper: jax.Array
    lid_side: jax.Array
    lid_pivot: jax.Array
    lid_axis: jax.Array
    lid_angles: jax.Array
    puff_field: jax.Array
    puff_left: jax.Array
    puff_force: jax.Array
    n_steps: int = eqx.field(static=True)
    muscle_names: tuple = eqx.field(static=True)
    muscle_aus: tuple = eqx.field(static=True)
    info: LTWInfo = eqx.field(static=True)

    backend = "ltw"

    @property
    def n_vertices(self) -> int:
        """Number of skin (epidermal) vertices ``V``."""
        return self.model.tissue.n_vertices

    @property
    def rest(self) -> jax.Array:
        """``(V, 3)`` rest skin, mm."""
        return self.model.tissue.rest[: self.n_vertices]

    @property
    def params(self) -> LTWParams:
        """The tissue and muscle constants (:class:`LTWParams`)."""
        return self.model.params

    def with_params(self, **kw) -> LTWRig:
        """A copy with some :class:`LTWParams` fields replaced (quasi-static constants kept)."""
        p = self.model.params
        for k, v in kw.items():
            if not hasattr(p, k):
                raise RigError(f"unknown LTW parameter {k!r}; see jaxface.ltw.LTWParams.")
            p = eqx.tree_at(
                lambda q, k=k: getattr(q, k), p, jnp.asarray(v, dtype=getattr(p, k).dtype)
            )
        return eqx.tree_at(lambda r: r.model.params, self, p)

    def with_iterations(self, n_steps: int) -> LTWRig:
        """A copy with another static number of relaxation steps."""
        return dataclasses.replace(self, n_steps=int(n_steps))

    def synthesize(self, activations, jaw=None, cheek_puff=0.0) -> jax.Array:
        """:func:`synthesize_ltw` of this rig: ``(V, 3)`` skin, mm (the
        :class:`~jaxface.anatomy.interface.FaceRig` method)."""
        return synthesize_ltw(self, activations, jaw, cheek_puff)


@dataclass(frozen=True)
class LTWRigConfig(RigConfig):
    """Options of the layered-tissue rig
    (``build_rig(..., backend="ltw", config=LTWRigConfig(...))``); every default is
    :func:`build_ltw_rig`'s, whose arguments these are.

    Attributes:
        params: :class:`LTWParams` (paper defaults when None).
        fascia_fraction: fascia depth as a fraction of the skin-to-skull depth.
        diagonals: shear (cross) springs in the dermal-fatty and muscle layers.
        n_steps: quasi-static relaxation steps of :func:`synthesize_ltw` (static).
        eyelid_threshold: normalised geodesic size of the eyelid regions (as the PBD rig).
        puff_force: cheek-puff force per mm of the cheek-puff field, model units.
        safety: safety factor on the largest eigenvalue for the relaxation constants.
    """

    backend: ClassVar[str] = "ltw"

    params: LTWParams | None = None
    fascia_fraction: float = 0.5
    diagonals: bool = True
    n_steps: int = 300
    eyelid_threshold: float = 0.04
    puff_force: float = 4.0
    safety: float = 1.6


# ----------------------------------------------------------------------------- build


def _as_mesh(skin):
    if isinstance(skin, TriMesh):
        return skin, None
    if hasattr(skin, "mesh") and isinstance(skin.mesh, TriMesh):
        return skin.mesh, skin
    raise RigError(
        f"build_ltw_rig needs the skin as a jaxface TriMesh (mm), got {type(skin).__name__}."
    )


def _skull_columns(mesh, frame, skull, depth):
    """Skull node per skin vertex ``(V, 3)`` and mandible mask ``(V,)``."""
    V = mesh.n_vertices
    off = skull.extras.get("offset_mesh") if getattr(skull, "extras", None) else None
    if off is not None and off.n_vertices == V:
        pts = np.asarray(off.vertices, float)
        mand = np.asarray(skull.extras.get("mandible_vertices", mandible_mask(pts, frame)), bool)
        return pts, mand
    n = smooth_normals(mesh, 8)
    fallback = mesh.vertices - depth[:, None] * n
    pts = fallback.copy()
    mand = mandible_mask(fallback, frame)
    best = np.full(V, np.inf)
    for k, part in enumerate((skull.cranium, skull.mandible)):
        hits = part.ray_cast(mesh.vertices, -n, min_distance=1.0, max_distance=40.0)
        idx = np.flatnonzero(hits.hit)
        if len(idx) == 0:
            continue
        dist = np.asarray(hits.distances)
        closer = dist < best[idx]
        sel = idx[closer]
        best[sel] = dist[closer]
        pts[sel] = np.asarray(hits.locations)[closer]
        mand[sel] = k == 1
    return pts, mand


def _fibres_for(pm, ci, frame, mean_edge):
    kind = pm.kind
    m = ci[pm.name]
    if kind in ("linear", "sheet"):
        o = np.asarray(pm.origin, float).reshape(-1, 3)
        ins = np.asarray(pm.insertion, float).reshape(-1, 3)
        jaw = mandible_mask(o, frame)
        w_spec = 0.5 * float(np.mean(pm.spec.width)) * float(frame.scale[0])
        if len(o) == 1:
            width = max(w_spec, 2.5 * mean_edge)
            return [linear_fibre(o[0], ins[0], width, m, jaw=bool(jaw[0]))]
        spacing = float(np.mean(np.linalg.norm(np.diff(ins, axis=0), axis=1)))
        width = max(spacing, 2.5 * mean_edge)
        return [linear_fibre(a, b, width, m, jaw=bool(j)) for a, b, j in zip(o, ins, jaw)]
    if kind == "sphincter":
        c = np.asarray(pm.centre, float)
        u, v = np.asarray(pm.axes[0], float), np.asarray(pm.axes[1], float)
        mid = np.asarray(pm.fibres[1].positions, float) if len(pm.fibres) >= 2 else None
        if mid is None:
            a, b = (float(s) for s in pm.semi_axes)
        else:
            a = float(np.mean(np.abs((mid - c) @ u).max()))
            b = float(np.abs((mid - c) @ v).max())
        inner = np.asarray(pm.insertion, float)
        outer = np.asarray(pm.origin, float)
        band = (
            0.5 * float(np.mean(np.linalg.norm(outer - inner, axis=1)))
            if len(inner) == len(outer)
            else 0.5 * b
        )
        width = max(band, 2.5 * mean_edge)
        return sphincter_fibres(c, u, v, a, b, m, n_segments=4, width=width)
    return []


def build_ltw_rig(
    skin,
    landmarks=None,
    skull=None,
    muscle_map=None,
    *,
    params: LTWParams | None = None,
    fascia_fraction: float = 0.5,
    diagonals: bool = True,
    n_steps: int = 300,
    eyelid_threshold: float = 0.04,
    puff_force: float = 4.0,
    safety: float = 1.6,
) -> LTWRig:
    """Build the layered-tissue rig of a face (NumPy/SciPy, build time).

    Args:
        skin: skin :class:`~jaxface.mesh.TriMesh` (mm, face looking +z) or a
            :class:`~jaxface.head.Head` (then its landmarks are the default).
        landmarks: the Bosphorus landmarks of the face.
        skull: optional :class:`~jaxface.anatomy.skull.Skull`; estimated when None.
        muscle_map: path of a muscle-map JSON, a list of ``MuscleSpec``, or None (default map).
        params, fascia_fraction, diagonals, n_steps, eyelid_threshold, puff_force, safety:
            the options of :class:`LTWRigConfig` (see there, with their units).

    Returns:
        :class:`LTWRig`; ``rig.muscle_names`` is the PBD rig's control order for the same map.

    Raises:
        RigError, LandmarkError, MeshError: unusable inputs (named in the message).
    """
    mesh, head = _as_mesh(skin)
    if landmarks is None and head is not None:
        landmarks = head.landmarks
    if landmarks is None:
        raise RigError("build_ltw_rig needs the face's landmarks.")
    frame = face_frame(landmarks)
    if skull is None:
        skull = estimate_skull(mesh, landmarks)
    depth = skull.extras.get("depth") if getattr(skull, "extras", None) else None
    if depth is None or len(depth) != mesh.n_vertices:
        depth = tissue_depth(mesh, frame)
    skull_pts, mand = _skull_columns(mesh, frame, skull, np.asarray(depth, float))

    specs, controls, names = muscle_controls(muscle_map)
    ci = {n: i for i, n in enumerate(names)}
    placed = place_muscles(mesh, landmarks, skull, specs)

    # eyelids (kinematic, as the paper): the same regions and angles as the PBD rig
    V = mesh.n_vertices
    lid_nodes, lid_fall, lid_upper, lid_side, piv, axs, angs = [], [], [], [], [], [], []
    for ids, fall, upper, k, pivot, axis, angles in eyelid_regions(
        mesh, frame, controls, placed, eyelid_threshold
    ):
        for layer in (0, 1):
            lid_nodes.append(layer * V + ids)
            lid_fall.append(fall)
            lid_upper.append(upper)
            lid_side.append(np.full(len(ids), k))
        piv.append(np.asarray(pivot, float))
        axs.append(np.asarray(axis, float))
        angs.append(angles)

    tissue = build_tissue(
        mesh.vertices,
        mesh.triangles,
        skull_points=skull_pts,
        fascia_fraction=fascia_fraction,
        mandible=mand,
        diagonals=diagonals,
    )
    if lid_nodes:
        ln = np.concatenate(lid_nodes)
        free = np.asarray(tissue.free).copy()
        free[ln] = 0.0
        tissue = eqx.tree_at(lambda t: t.free, tissue, jnp.asarray(free, tissue.free.dtype))

    mean_edge = float(np.mean(mesh.edge_lengths)) if hasattr(mesh, "edge_lengths") else 3.0
    fibres: list[Fibre] = []
    for pm in placed:
        if pm.kind in ("linear", "sheet", "sphincter"):
            fibres.extend(_fibres_for(pm, ci, frame, mean_edge))
    fascia_rest = np.asarray(tissue.rest[V : 2 * V], float)
    muscles = build_waters(
        fibres,
        fascia_rest,
        V + np.arange(V),
        np.asarray(mesh.vertex_normals, float),
        len(names),
        candidate_mask=np.asarray(tissue.free[V : 2 * V]) > 0.5,
    )
    params = LTWParams() if params is None else params
    model = make_model(tissue, muscles, params, safety=safety)
    jaw = JawModel.from_landmarks(frame)

    # cheek puff field of the PBD rig's definition (outward bump over the buccal area)
    puff, puff_left = _puff_field(mesh, frame)

    fdt = tissue.rest.dtype
    nS = len(piv)
    info = LTWInfo(
        skin=mesh,
        landmarks=landmarks,
        frame=frame,
        skull=skull,
        placed=placed,
        specs=specs,
        depth=np.asarray(depth, float),
        mandible=mand,
        fibres=fibres,
    )
    return LTWRig(
        model=model,
        jaw=jaw,
        lid_nodes=jnp.asarray(np.concatenate(lid_nodes) if lid_nodes else np.zeros(0), jnp.int32),
        lid_fall=jnp.asarray(np.concatenate(lid_fall) if lid_fall else np.zeros(0), fdt),
        lid_upper=jnp.asarray(np.concatenate(lid_upper) if lid_upper else np.zeros(0, bool)),
        lid_side=jnp.asarray(np.concatenate(lid_side) if lid_side else np.zeros(0), jnp.int32),
        lid_pivot=jnp.asarray(np.stack(piv) if nS else np.zeros((0, 3)), fdt),
        lid_axis=jnp.asarray(np.stack(axs) if nS else np.zeros((0, 3)), fdt),
        lid_angles=jnp.asarray(np.stack(angs, axis=1) if nS else np.zeros((len(names), 0, 2)), fdt),
        puff_field=jnp.asarray(puff, fdt),
        puff_left=jnp.asarray(puff_left),
        puff_force=jnp.asarray(puff_force, fdt),
        n_steps=int(n_steps),
        muscle_names=names,
        muscle_aus=tuple(tuple(s.aus) for s in controls),
        info=info,
    )


def _puff_field(mesh, frame) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3)`` cheek-puff field: outward smoothed normals times the PBD rig's cheek bump
    (:func:`jaxface.anatomy.cheek_puff.cheek_bump`; dimensionless weight in [0, 1] times a
    unit vector), and ``(V,)`` bool, the left cheek's part."""
    n0 = smooth_normals(mesh, 3)
    bump, left = cheek_bump(np.asarray(mesh.vertices, float), frame)
    return bump[:, None] * n0, left


# ----------------------------------------------------------------------------- synthesis


def _solve(rig: LTWRig, activations, jaw, cheek_puff, n_steps: int):
    a = check_activations(rig, activations)
    jaw = check_jaw(jaw)
    model = rig.model
    tis = model.tissue
    dt = jnp.result_type(a.dtype, jaw.pitch_deg.dtype, tis.rest.dtype)
    a = a.astype(dt)
    R, t = rig.jaw.transform(jaw)
    R, t = R.astype(dt), t.astype(dt)
    kin, ext = _drives(rig, a, R, t, puff_scale(cheek_puff, rig.puff_left, dt))
    return relax(model, a, R, t, n_steps=n_steps, external=ext, kinematic=kin)


def _drives(rig: LTWRig, a, R, t, puff):
    """Kinematic node positions (jaw + eyelids) ``(N, 3)`` mm and external forces ``(N, 3)``."""
    tis = rig.model.tissue
    V = tis.n_vertices
    kin = kinematic_positions(tis, R, t)
    if rig.lid_nodes.shape[0]:
        ang = jnp.einsum("c,csl->sl", a, rig.lid_angles.astype(a.dtype)) * (jnp.pi / 180.0)
        per = jnp.where(rig.lid_upper, ang[rig.lid_side, 0], ang[rig.lid_side, 1]) * rig.lid_fall
        p0 = kin[rig.lid_nodes]
        rot = rotate_about_axes(p0, rig.lid_pivot[rig.lid_side], rig.lid_axis[rig.lid_side], per)
        kin = kin.at[rig.lid_nodes].set(rot)
    ext = jnp.zeros_like(tis.rest).at[V : 2 * V].set(puff * rig.puff_force * rig.puff_field)
    return kin, ext


@eqx.filter_jit
def synthesize_nodes(rig: LTWRig, activations, jaw=None, cheek_puff=0.0):
    """:func:`synthesize_ltw` returning all ``(3V, 3)`` tissue nodes (epidermis, fascia,
    skull layers), mm."""
    return _solve(rig, activations, jaw, cheek_puff, rig.n_steps)


@eqx.filter_jit
def synthesize_ltw(rig: LTWRig, activations, jaw=None, cheek_puff=0.0):
    """Synthesize the face on the layered-tissue backend (quasi-static).

    Args:
        rig: the :class:`LTWRig`.
        activations: ``(M,)`` in [0, 1], ordered as ``rig.muscle_names`` (same as the PBD rig).
        jaw: :class:`~jaxface.anatomy.jaw.JawPose` (degrees, mm); neutral if None.
        cheek_puff: AU33/34 pressure in [0, 1] (0 = off), or ``[left, right]``
            (:mod:`jaxface.anatomy.cheek_puff`).

    Returns:
        ``(V, 3)`` skin (epidermal node) positions, mm. jit-compiled; vmap-, grad- and
        jvp-able with respect to activations, jaw pose, cheek puff and ``rig.model.params``.

    Raises:
        RigError: activations of the wrong shape, or a jaw that is not a JawPose.
    """
    x = _solve(rig, activations, jaw, cheek_puff, rig.n_steps)
    return x[: rig.model.tissue.n_vertices]


def equilibrium_residual(rig: LTWRig, activations, jaw=None, cheek_puff=0.0) -> float:
    """Largest equilibrium residual (mm, see :func:`jaxface.ltw.integrate.residual`) after
    ``rig.n_steps`` relaxation steps: a convergence check of a synthesis."""
    jaw = check_jaw(jaw)
    x = synthesize_nodes(rig, activations, jaw, cheek_puff)
    a = check_activations(rig, activations).astype(x.dtype)
    R, t = rig.jaw.transform(jaw)
    R, t = R.astype(x.dtype), t.astype(x.dtype)
    _, ext = _drives(rig, a, R, t, puff_scale(cheek_puff, rig.puff_left, x.dtype))
    return float(jnp.max(residual(rig.model, x, a, R, t, external=ext)))


def _build_from_config(skin, landmarks, skull, muscle_map, config: LTWRigConfig) -> LTWRig:
    """The LTW backend's builder for :func:`jaxface.anatomy.rig.build_rig`."""
    return build_ltw_rig(skin, landmarks, skull=skull, muscle_map=muscle_map, **config.options())


register_backend("ltw", LTWRigConfig, _build_from_config)
