"""The skin's PBD system (thesis sec. 5.5-5.7): constraints with the thesis stiffness values,
teeth hulls, eyelid rotations, the anchor targets (:func:`skin_targets`), the fat volume
(:func:`fat_thickness`) and the solve (:func:`solve_skin`). Units: mm.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import pbd
from .._arrays import to_jax
from ..errors import RigError
from ..mesh import TriMesh
from ..rigid import rotate_about_axes
from .cheek_puff import cheek_bump, puff_scale
from .frame import FaceFrame
from .geometry import smooth_normals
from .skin_binding import Binding
from .skin_footprint import (
    _lower_upper_field,
    footprint_operator,
    footprint_sigma,
    membrane_interpolation,
    mirror_vertices,
)
from .skull import head_centre

#: Range of the fat layer's thickness factor (:func:`fat_thickness`): the layer at most halves
#: or doubles.
FAT_RATIO_RANGE = (0.5, 2.0)


#: Thesis skin stiffness values (sec. 5.5).
SKIN_STIFFNESS = dict(
    stretch=0.15, cross=0.15, bend=0.95, area=0.95, anchor=0.2, volume=1.0, damping=0.2
)


class SkinSystem(eqx.Module):
    """Run-time skin data (JAX pytree). See :func:`build_skin_system`.

    Attributes:
        rest: ``(V, 3)`` rest skin, mm.
        bind_ids, bind_w: ``(V, 3)`` support ids / weights of each vertex's surface point.
        bind_offset: ``(V, 3)`` rest offset ``p0 - sp0``, mm.
        fp_rows, fp_cols, fp_vals: the footprint operator's matrix (COO, :class:`Footprint`);
            fp_member_v, fp_member_c, fp_member_w: the cluster membership (COO); fp_count:
            ``(C,)`` vertices per cluster (its length is the static ``C``); all ``(0,)``
            without clusters.
        influence: ``(V,)``; inv_mass: ``(V,)`` (0 = kinematic).
        anchors: the engine's anchor group of every vertex (stiffness ``(V,)``; targets set
            per solve from :func:`skin_targets`).
        lid_ids, lid_fall, lid_pivot, lid_axis, lid_ctrl_angles: eyelids.
        puff_dir: ``(V, 3)`` cheek-puff displacement per unit pressure, mm; puff_left:
            ``(V,)`` bool, the left cheek's part (:mod:`jaxface.anatomy.cheek_puff`).
        mem_ids, mem_border, mem_H: the unsupported skin whose targets are interpolated from
            its border (:func:`membrane_interpolation`): ``(F,)``, ``(B,)``, ``(F, B)``.
        fat_tri, fat_area0, fat_gain, fat_ratio: the fat layer (:func:`fat_thickness`):
            ``(T, 3)`` triangles (none when off), ``(V,)`` rest areas mm^2, ``(V,)`` gains,
            the static ratio range.
        groups: the engine's stretch/cross, area, bending groups (:mod:`jaxface.pbd`);
            volume: the skin volume group (or None; its rest volume is set per solve).
        upper_hull, lower_hull: hull collision groups (or None); lower_planes: rest planes.
        iterations: static sweeps of the quasi-static solve.
        checkpoint: static; checkpoint every sweep for reverse mode
            (:func:`jaxface.pbd.iterate`; on by default, the muscles' off: see
            :class:`jaxface.anatomy.muscles.MuscleSystem`).
    """

    rest: jax.Array
    bind_ids: jax.Array
    bind_w: jax.Array
    bind_offset: jax.Array
    fp_rows: jax.Array
    fp_cols: jax.Array
    fp_vals: jax.Array
    fp_member_v: jax.Array
    fp_member_c: jax.Array
    fp_member_w: jax.Array
    fp_count: jax.Array
    influence: jax.Array
    inv_mass: jax.Array
    anchors: pbd.Group
    lid_ids: jax.Array
    lid_fall: jax.Array
    lid_upper: jax.Array
    lid_side: jax.Array
    lid_pivot: jax.Array
    lid_axis: jax.Array
    lid_angles: jax.Array
    puff_dir: jax.Array
    puff_left: jax.Array
    mem_ids: jax.Array
    mem_border: jax.Array
    mem_H: jax.Array
    fat_tri: jax.Array
    fat_area0: jax.Array
    fat_gain: jax.Array
    groups: tuple[pbd.Group, ...]
    volume: pbd.Group | None
    upper_hull: pbd.Group | None
    lower_hull: pbd.Group | None
    lower_planes: tuple | None
    iterations: int = eqx.field(static=True, default=12)
    chebyshev_rho: float = eqx.field(static=True, default=0.0)
    fat_ratio: tuple = eqx.field(static=True, default=FAT_RATIO_RANGE)
    checkpoint: bool = eqx.field(static=True, default=True)

    @property
    def n_vertices(self) -> int:
        return int(self.rest.shape[0])


def _hull_group(
    teeth: TriMesh | None,
    skin_x: np.ndarray,
    candidates_margin: float,
    n: int,
    inv_mass: np.ndarray,
    clearance: float,
):
    if teeth is None:
        return None, None
    N, d = pbd.hull_planes(teeth.vertices)
    sd = skin_x @ N.T - d[None]
    depth = sd.max(axis=1)  # signed distance-like (>0 outside)
    cand = np.flatnonzero((depth < candidates_margin) & (inv_mass > 0))
    if cand.size == 0:
        return None, (N, d)
    # vertices inside at rest keep their rest penetration (the rest state is collision-free)
    clr = np.minimum(clearance, depth[cand] - 1e-6)
    g = pbd.hull_constraints(cand, N, d, clearance=clr, stiffness=1.0)
    return pbd.make_group(g, n, name="teeth"), (N, d)


def build_skin_system(
    skin: TriMesh,
    frame: FaceFrame,
    binding: Binding,
    support_ids,
    support_w,
    *,
    influence: np.ndarray,
    eyelids: list,
    teeth=(None, None),
    footprint_mm: float | tuple = 3.5,
    footprint_cluster_mm: float = 0.0,
    stiffness: dict | None = None,
    bending: bool = True,
    iterations: int = 12,
    lid_stiffness: float = 0.9,
    puff_mm: float = 8.0,
    membrane: np.ndarray | None = None,
    fat_volume: float | tuple = 0.0,
) -> SkinSystem:
    """Assemble the skin system (NumPy build time).

    Args:
        skin: the skin mesh, mm; frame: its :class:`FaceFrame`.
        binding: :func:`bind_skin` result; support_ids, support_w: ``(V, 3)`` its surface
            points as rows of the support array (see :class:`~jaxface.anatomy.muscles.SupportPoints`).
        influence: ``(V,)`` influence map.
        eyelids: list of ``(ids, falloff, upper, side_index, pivot (3,), axis (3,), angles (C, 2))``
            where ``angles[c] = (upper_deg, lower_deg)`` per control ``c`` (0 for non-eyelid
            controls).
        teeth: ``(upper, lower)`` teeth meshes or None.
        footprint_mm: sigma of the tissue footprint (reference mm), or a ``(lower, upper)``
            pair (:func:`footprint_sigma`).
        footprint_cluster_mm: width of the vertex clusters the wide footprint rows draw on
            (reference mm; :func:`footprint_operator`); 0 = none.
        stiffness: overrides of :data:`SKIN_STIFFNESS`.
        bending: include the dihedral bending constraints.
        iterations: static sweeps of the quasi-static solve.
        lid_stiffness: anchor stiffness of the eyelid vertices.
        puff_mm: outward displacement of the cheeks at cheek-puff 1, mm.
        membrane: optional ``(V,)`` bool, skin with no bone or muscle under it whose targets
            are the harmonic interpolation of the targets around it (a stretched membrane)
            instead of its bound points; it is anchored with stiffness 1.
        fat_volume: in [0, 1], the fat layer's volume preservation (:func:`fat_thickness`):
            0 = off, 1 = full; one value, or a ``(lower, upper)`` pair blended like
            ``footprint_mm``.
    """
    fat_gain = _lower_upper_field(
        skin,
        frame,
        fat_volume,
        "fat_volume",
        "numbers in [0, 1] (0 = off, 1 = the fat layer keeps its volume)",
        low=0.0,
        high=1.0,
    )
    k = dict(SKIN_STIFFNESS)
    k.update(stiffness or {})
    x = skin.vertices
    V = x.shape[0]
    infl = np.asarray(influence, np.float64)
    dyn = infl > 1e-4
    if not dyn.any():
        raise RigError(
            "no skin vertex is under the influence of a muscle or the jaw: the "
            "muscle map and the skin do not overlap. Check the landmarks."
        )
    inv_mass = dyn.astype(np.float64)
    groups = []
    e = skin.edges
    pairs = skin.edge_pairs
    te = np.concatenate([e, pairs[:, 2:]]) if len(pairs) else e
    tk = np.concatenate([np.full(len(e), k["stretch"]), np.full(len(pairs), k["cross"])])
    keep = dyn[te].any(axis=1)
    groups.append(
        pbd.make_group(
            pbd.distance_constraints(te[keep], x, stiffness=tk[keep]),
            V,
            omega=1.5,
            name="skin stretch",
        )
    )
    tri = skin.triangles
    tkeep = dyn[tri].any(axis=1)
    if k["area"] > 0 and tkeep.any():
        groups.append(
            pbd.make_group(
                pbd.area_constraints(tri[tkeep], x, stiffness=k["area"]),
                V,
                omega=1.0,
                name="skin area",
            )
        )
    if bending and k["bend"] > 0 and len(pairs):
        bkeep = dyn[pairs].any(axis=1)
        groups.append(
            pbd.make_group(
                pbd.bending_constraints(pairs[bkeep], x, stiffness=k["bend"]),
                V,
                omega=1.0,
                name="skin bending",
            )
        )

    vol = None
    if k["volume"] > 0:
        vol = pbd.make_group(
            pbd.volume_constraint(tri, x, origin=head_centre(frame), stiffness=k["volume"]),
            V,
            name="skin volume",
        )
    # footprint
    F = footprint_operator(
        skin,
        footprint_sigma(skin, frame, footprint_mm),
        cluster_mm=float(footprint_cluster_mm) * frame.mean_scale,
        mirror=mirror_vertices(skin, frame),
    )
    # eyelids
    lid_ids, lid_fall, lid_upper, lid_side, piv, axs, angs = [], [], [], [], [], [], []
    for ids, fall, upper, side, pivot, axis, angles in eyelids:
        lid_ids.append(ids)
        lid_fall.append(fall)
        lid_upper.append(upper)
        lid_side.append(np.full(len(ids), side))
        piv.append(pivot)
        axs.append(axis)
        angs.append(angles)
    anchor_k = np.full(V, k["anchor"])
    if lid_ids:
        li = np.concatenate(lid_ids)
        anchor_k[li] = np.maximum(anchor_k[li], lid_stiffness * np.concatenate(lid_fall))
    # cheek puff: outward along the normal, weighted by a cheek bump around the buccal area
    n0 = smooth_normals(skin, 3)
    bump, puff_left = cheek_bump(x, frame)
    puff = (puff_mm * frame.mean_scale) * bump[:, None] * n0 * infl[:, None]
    up_g, up_planes = _hull_group(teeth[0], x, 20.0 * frame.mean_scale, V, inv_mass, 0.3)
    lo_g, lo_planes = _hull_group(teeth[1], x, 30.0 * frame.mean_scale, V, inv_mass, 0.3)
    mem = np.zeros(V, bool) if membrane is None else (np.asarray(membrane, bool) & dyn)
    mem_ids, mem_border, mem_H = membrane_interpolation(skin, mem)
    anchor_k[mem_ids] = 1.0
    if mem_ids.size:
        # the membrane has no layer under it; its border, which it is interpolated from, keeps
        # its rest thickness too (a thickened border bulged the membrane's edge into 2 folds)
        fat_gain[mem_ids] = 0.0
        fat_gain[mem_border] = 0.0
    fat_tri = tri[tkeep] if fat_gain.max() > 0 else np.zeros((0, 3), np.int64)
    return SkinSystem(
        rest=to_jax(x),
        bind_ids=to_jax(support_ids),
        bind_w=to_jax(support_w),
        bind_offset=to_jax(x - binding.point),
        fp_rows=to_jax(F.rows),
        fp_cols=to_jax(F.cols),
        fp_vals=to_jax(F.vals),
        fp_member_v=to_jax(F.member_v),
        fp_member_c=to_jax(F.member_c),
        fp_member_w=to_jax(F.member_w),
        fp_count=to_jax(np.bincount(F.member_c, weights=F.member_w, minlength=F.n_clusters)),
        influence=to_jax(infl),
        inv_mass=to_jax(inv_mass),
        anchors=pbd.make_group(
            pbd.anchor_constraints(np.arange(V), x, stiffness=anchor_k), V, name="skin anchors"
        ),
        lid_ids=to_jax(np.concatenate(lid_ids) if lid_ids else np.zeros(0, np.int64)),
        lid_fall=to_jax(np.concatenate(lid_fall) if lid_fall else np.zeros(0)),
        lid_upper=to_jax(np.concatenate(lid_upper) if lid_upper else np.zeros(0, bool)),
        lid_side=to_jax(np.concatenate(lid_side) if lid_side else np.zeros(0, np.int64)),
        lid_pivot=to_jax(np.stack(piv) if piv else np.zeros((0, 3))),
        lid_axis=to_jax(np.stack(axs) if axs else np.zeros((0, 3))),
        lid_angles=to_jax(np.stack(angs) if angs else np.zeros((0, 1, 2))),
        puff_dir=to_jax(puff),
        puff_left=to_jax(puff_left),
        mem_ids=to_jax(mem_ids),
        mem_border=to_jax(mem_border),
        mem_H=to_jax(mem_H),
        fat_tri=to_jax(fat_tri),
        fat_area0=to_jax(vertex_areas(binding.point, fat_tri, V)),
        fat_gain=to_jax(fat_gain),
        fat_ratio=tuple(float(v) for v in FAT_RATIO_RANGE),
        groups=tuple(groups),
        volume=vol,
        upper_hull=up_g,
        lower_hull=lo_g,
        lower_planes=(None if lo_planes is None else (to_jax(lo_planes[0]), to_jax(lo_planes[1]))),
        iterations=int(iterations),
    )


def skin_targets(sk: SkinSystem, G, activations, cheek_puff: jax.typing.ArrayLike = 0.0):
    """Anchor targets ``(V, 3)`` mm of the skin for the current support ``G``.

    Bound surface points evaluated on ``G``, offsets scaled by the fat layer's thickness
    (:func:`fat_thickness`), displacements averaged over the tissue
    footprint and scaled by the influence map, the membrane skin interpolated from its border,
    eyelid rotations and cheek puff added.
    """
    dt = G.dtype
    rest = sk.rest.astype(dt)
    sp_ = jnp.einsum("vk,vkd->vd", sk.bind_w.astype(dt), G[sk.bind_ids])
    offset = sk.bind_offset.astype(dt)
    if sk.fat_tri.shape[0]:
        fat = fat_thickness(sp_, sk.fat_tri, sk.fat_area0, sk.fat_gain, sk.fat_ratio)
        offset = offset * fat[:, None]
    disp = sp_ + offset - rest
    src = disp
    if sk.fp_count.shape[0]:
        sums = jax.ops.segment_sum(
            sk.fp_member_w.astype(dt)[:, None] * disp[sk.fp_member_v],
            sk.fp_member_c,
            num_segments=sk.fp_count.shape[0],
        )
        src = jnp.concatenate([disp, sums])
    disp = jax.ops.segment_sum(
        sk.fp_vals.astype(dt)[:, None] * src[sk.fp_cols], sk.fp_rows, num_segments=rest.shape[0]
    )
    disp = disp * sk.influence.astype(dt)[:, None]
    if sk.mem_ids.shape[0]:
        disp = disp.at[sk.mem_ids].set(sk.mem_H.astype(dt) @ disp[sk.mem_border])
    if sk.lid_ids.shape[0]:
        a = jnp.asarray(activations, dt)
        ang = jnp.einsum("c,scl->sl", a, sk.lid_angles.astype(dt)) * (jnp.pi / 180.0)  # (sides, 2)
        per = jnp.where(
            sk.lid_upper, ang[sk.lid_side, 0], ang[sk.lid_side, 1]
        ) * sk.lid_fall.astype(dt)
        p0 = rest[sk.lid_ids]
        rot = rotate_about_axes(
            p0, sk.lid_pivot.astype(dt)[sk.lid_side], sk.lid_axis.astype(dt)[sk.lid_side], per
        )
        disp = disp.at[sk.lid_ids].add(rot - p0)
    disp = disp + puff_scale(cheek_puff, sk.puff_left, dt) * sk.puff_dir.astype(dt)
    return rest + disp


def vertex_areas(points, tri, n: int, xp=np):
    """``(n,)`` mm^2: the summed area of the triangles ``tri`` ``(T, 3)`` around each vertex,
    with the vertices at ``points`` ``(n, 3)`` mm. NumPy (``xp=np``) or JAX (``xp=jnp``)."""
    if tri.shape[0] == 0:
        return xp.zeros(n)
    p = points[tri]  # (T, 3, 3)
    c = xp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    a = 0.5 * xp.sqrt(xp.sum(c * c, axis=1) + 1e-24)
    if xp is np:
        return np.bincount(tri.ravel(), weights=np.repeat(a, 3), minlength=n)
    return jax.ops.segment_sum(jnp.repeat(a, 3), tri.reshape(-1), num_segments=n)


def fat_thickness(surface_points, tri, area0, gain, ratio_range=FAT_RATIO_RANGE):
    """``(V,)`` factor on each skin vertex's tissue offset (the fat between the skin and the
    surface point it is bound to) that keeps the fat layer's volume.

    A prism of the layer with base area ``A`` and height ``h`` keeps ``A h`` when its base is
    squeezed or stretched: the volume preservation of Lee, Terzopoulos and Waters (1995),
    applied to the layer under the skin. ``A`` is the area of the bound surface points around
    the vertex over the skin's triangles, so where a muscle shortens, or the tissue ahead of a
    pulled mouth corner bunches up, the skin above it rises, and where the surface stretches
    (the lips around a widened mouth, the cheeks over an opened jaw) it sinks.

    The factor is ``(A0 / A) ** gain`` with ``A0 / A`` clipped to ``ratio_range``. A vertex in
    no triangle (``area0 = 0``) keeps 1. Zero-area triangles are safe (no NaN, also in the
    reverse pass).

    Arguments:
        surface_points: ``(V, 3)`` mm, the current bound surface points.
        tri: ``(T, 3)`` skin triangles.
        area0: ``(V,)`` mm^2, :func:`vertex_areas` of the rest surface points.
        gain: ``(V,)`` or scalar in [0, 1]: 1 keeps the volume, 0 is off.
        ratio_range: ``(low, high)`` bounds of ``A0 / A``.
    """
    dt = surface_points.dtype
    a0 = jnp.asarray(area0, dt)
    a = vertex_areas(surface_points, tri, a0.shape[0], xp=jnp)
    ok = a0 > 0
    lo, hi = ratio_range
    ratio = jnp.where(ok, a0 / jnp.maximum(a, jnp.where(ok, a0, 1.0) / hi), 1.0)
    return jnp.exp(jnp.asarray(gain, dt) * jnp.log(jnp.clip(ratio, lo, hi)))


def solve_skin(sk: SkinSystem, targets, R, t, *, iterations: int | None = None, x0=None):
    """Quasi-static skin solve: anchors to ``targets``, thesis constraints, teeth collisions.

    Each sweep of the engine (fused Jacobi, :func:`jaxface.pbd.sweep`) projects, in order:
    the anchors, stretch/cross, area, bending, the capped volume (its rest volume is the one
    the targets imply) and the two teeth hulls (the lower one moved with the jaw).

    Args:
        sk: the :class:`SkinSystem`.
        targets: ``(V, 3)`` anchor targets, mm (:func:`skin_targets`).
        R, t: jaw motion (moves the lower-teeth hull).
        iterations: static sweeps (default ``sk.iterations``).
        x0: optional warm start (default: the targets).

    Returns:
        ``(V, 3)`` mm.
    """
    iters = sk.iterations if iterations is None else int(iterations)
    dt = targets.dtype
    inv_mass = sk.inv_mass.astype(dt)
    rest = sk.rest.astype(dt)
    dyn = (inv_mass > 0)[:, None]
    x = jnp.where(dyn, targets, rest) if x0 is None else jnp.asarray(x0, dt)
    groups = (sk.anchors.set(target=targets),) + tuple(sk.groups)
    if sk.volume is not None:
        # the volume the underlying structures imply: the capped volume of the targets
        vol = sk.volume.c
        assert isinstance(vol, pbd.VolumeConstraint)
        vol = eqx.tree_at(lambda q: q.origin, vol, vol.origin.astype(dt))
        groups += (sk.volume.set(rest=vol.volume(jnp.where(dyn, targets, rest))),)
    if sk.upper_hull is not None:
        groups += (sk.upper_hull,)
    if sk.lower_hull is not None:
        assert sk.lower_planes is not None  # built together with the lower hull
        n, d = pbd.transform_planes(
            sk.lower_planes[0].astype(dt), sk.lower_planes[1].astype(dt), R.astype(dt), t.astype(dt)
        )
        groups += (sk.lower_hull.set(normals=n, offsets=d),)
    return pbd.iterate(
        lambda x: pbd.sweep(groups, x, inv_mass),
        x,
        iters,
        sk.chebyshev_rho,
        checkpoint_every=1 if sk.checkpoint else None,
    )
