"""Muscle dynamics (thesis sec. 4.3): contraction by re-sampling, sphincters, passive layers.

All placed muscles (:func:`jaxface.anatomy.muscle_map.place_muscles`) become one particle set
(mass 1 each, thesis sec. 4.3) with, per muscle kind, the constraint network of Fig. 4.6 and the
thesis stiffness values:

=============== ===================================================== ========================
kind            constraints (stiffness)                               source
=============== ===================================================== ========================
sheet / linear  latitudinal up 1.0, longitudinal up 0.1, connection   sec. 4.3.1
                1.0, bending 0.4, volume 1.0, position 0.2
sphincter       latitudinal up 0.2, connection 1.0, shear up 0.3,      sec. 4.3.2
                shear low 0.3, bending 1.0, volume 1.0, position 0.2
passive         as sheet (no contraction)                              sec. 4.3.3
=============== ===================================================== ========================

*Position* constraints tie every bottom particle to its action-line sample. Samples are
recomputed from the current positions of the surfaces the action lines lie on - the static
cranium, the mandible moved by the jaw, and the muscles of deeper layers - so a muscle lying on
a deforming structure deforms with it (passive deformation). A fibre contracts by re-sampling
its action line with ``step' = step (1 - c)`` (eq. 4.11), ``c = activation * max_contraction``.
A sphincter moves each radial column of samples by
``delta = c (o - s_inner) cos(pi/2 (1 - r))`` with ``r = sqrt((x/a)^2 + (y/b)^2)`` of the
outer sample in the ellipse frame (sec. 4.3.2; the thesis prints ``(1 - c)`` and the axes
swapped, which would move the muscle at rest; we use the form that is zero at ``c = 0``).

*Shell* (our addition, :func:`shell_targets`, stiffness :data:`SHELL_STIFFNESS`): the thesis
holds the top sheet only by the connections on the grid boundary, the springs within the
sheet and the volume, so on the ICT face a contracting muscle sheared its top sheet over the
bottom one instead of bulging (the depressor anguli oris of sadness tilted its columns by 58
degrees on average, up to 130: inverted) and the solve crept for thousands of sweeps (7.7 mm
between 256 and 2,048 sweeps with every control at 1). With the shell every top particle is
pulled to its place above its bottom particle's sample, in the local frame of the samples,
at the rest thickness times the fibre's thickening; a contracting fibre shortens its top
sheet by ``1 - c`` too and thickens its boundary connections. The muscle then shortens and
bulges at constant volume, and the solve settles within 0.15 mm in 32 sweeps on the six
emotions, a jaw opening and every control at 1 (:func:`solve_muscles`; measured against
2,048 sweeps). ``shell_stiffness = 0`` restores the thesis's muscle.

Solve order per iteration (thesis animation loop, lines 8-11): for each layer, deepest first,
refresh the samples of its action lines, then one fused Jacobi sweep of the engine
(:func:`jaxface.pbd.sweep`) over its constraints: positions, the shell, distances,
bending, and the per-muscle volume constraints.

Units: mm. Everything at run time is JAX (jit/vmap/jvp/grad).
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import pbd
from .._arrays import to_jax
from ..errors import RigError
from ..mesh import TriMesh
from .muscle_map import PlacedMuscle, check_sphincter_rings

__all__ = [
    "STIFFNESS",
    "SHELL_STIFFNESS",
    "THICKENING_RANGE",
    "SupportPoints",
    "MuscleSystem",
    "build_muscle_system",
    "solve_muscles",
    "muscle_volumes",
    "shell_targets",
]

#: Thesis stiffness values per muscle kind (sec. 4.3.1-4.3.2); 0 disables a constraint kind.
STIFFNESS = {
    "sheet": dict(
        lat_up=1.0,
        lon_up=0.1,
        lat_low=0.0,
        lon_low=0.0,
        connection=1.0,
        shear_up=0.0,
        shear_low=0.0,
        bend=0.4,
        volume=1.0,
        position=0.2,
    ),
    "sphincter": dict(
        lat_up=0.2,
        lon_up=0.0,
        lat_low=0.0,
        lon_low=0.0,
        connection=1.0,
        shear_up=0.3,
        shear_low=0.3,
        bend=1.0,
        volume=1.0,
        position=0.2,
    ),
}
STIFFNESS["linear"] = STIFFNESS["sheet"]
POSITION_STIFFNESS = 0.2  # the same for every kind

#: Modiolus: the fibromuscular node at each mouth corner where zygomaticus major, risorius,
#: levator and depressor anguli oris, buccinator and orbicularis oris interlace. The
#: contraction of a corner muscle pulls the whole node: the orbicularis oris's ring samples near
#: a side's modiolus (Gaussian weight, sigma :data:`MODIOLUS_SIGMA_MM`) move, on top of their own
#: support, by ``MODIOLUS_GAIN`` x the summed *contraction* displacement of that side's corner
#: muscles' insertion ends (the contracted minus the uncontracted end of each fibre on the same
#: current support, so jaw motion is not counted twice). Without it the sphincter's corner
#: samples each lie on one of risorius, zygomaticus major or depressor anguli oris, and the
#: corner followed about a quarter of a zygomaticus pull. The gain is 1: the node moves with the
#: muscles inserted into it (0.6 before; 1 fits the ten lower-face Bosphorus-style scans 0.095 mm
#: better on average, every one of them better; 1.5 would fit better still, but a node moving
#: further than the muscles pulling it has no anatomical reading). A sample follows its nearer
#: modiolus, and the samples near the mid-line a blend of both (weights ``g_s^2 / (g_L + g_R)``
#: for the Gaussians ``g``), so a symmetric pull moves the lips symmetrically: giving each
#: sample only its nearer side's pull had moved the lip mid-line 0.46 mm sideways under
#: zygomaticus major at 1 on both sides.
#:
#: *Where* the modiolus sits decides how far along the lips the corner muscles reach. It is the
#: mouth corner: the lateral end of the ring's middle ellipse as drawn on the skin (half-way
#: between the map's inner and outer ellipses, 28 mm from the lips' centre on the reference
#: head), and only the ring the corner muscles insert into has one (a sample within
#: 2 sigma of their insertion ends: the orbicularis oris, not the eyes' rings). It used to be
#: the mean of the corner muscles' insertion ends, which the map places 2-8 mm inside the
#: corner; on bs901's rig that point lay 10 mm medial of the corner and 3 mm below the lips'
#: line, where the projection onto the muscles below had put the ring's lower-lip samples
#: (the upper-lip ones 9 mm higher). Those then took up to 0.67 of the pull against 0.44 at the
#: corner, and the buccinator at 1 drew the lower lip's mid-point 5.3 mm back, as far as the
#: corner; at the mouth corner it draws the corner (3.6, 0.5, -4.1) mm and the lower lip's
#: mid-point 1.2 mm back (README, Known limits, the lip stretcher; the 20 Bosphorus-style scans'
#: mean error 0.601 -> 0.594 mm, bs901's lip stretcher 1.88x -> 2.07x better than B0).
MODIOLUS_GAIN = 1.0
#: ...and, per sphincter, the other way (the map's ``modiolus_drag``, default 0): the ring's
#: own contraction drags the modiolus and with it the insertion ends of the corner muscles
#: (their fibre samples move by ``modiolus_drag`` x the ring's contraction displacement at
#: that mouth corner, fully at the insertion end, fading linearly to the origin). A pucker then
#: draws the corners medially and, with the ring's protrusion, forward; the corner muscles and
#: the cheek skin bound to them follow.
MODIOLUS_SIGMA_MM = 9.0
MODIOLUS_MAX_OFFSET_MM = 10.0  # corner muscles: insertion within this of the mouth corner
STIFFNESS["passive"] = STIFFNESS["sheet"]

#: Shell constraint (our addition to the thesis's muscle, :func:`shell_targets`): stiffness of
#: the pull of every top particle to its place above its bottom particle's action-line sample.
#: 0 gives the thesis's muscle exactly (top sheet held by the boundary connections only, no
#: active shortening of the top sheet, no thickening of the connections).
SHELL_STIFFNESS = 1.0
#: Range of the fibre thickening factor (rest over contracted fibre length) the shell applies.
THICKENING_RANGE = (0.5, 3.0)
DISTANCE_GROUP = (
    "muscle distances"  # name of the fused distance group (first of MuscleSystem.groups)
)


@dataclass
class SupportPoints:
    """Build-time collector of surface points on the support structures.

    Every surface point becomes three ids into the run-time *support array*
    ``G = [skull points moved by the jaw (S, 3); muscle particles (Nm, 3)]`` and three weights:
    a point on the skull is stored once as its own row of the skull-point table (its rest
    position, flagged when it lies on the mandible); a point on a muscle is a barycentric
    combination of three muscle particles.
    """

    skull_rest: list
    skull_on_mandible: list
    muscle_offset: dict  # surface id -> first particle index of that muscle

    def add(
        self, surface: np.ndarray, tri: np.ndarray, bary: np.ndarray, positions: np.ndarray, meshes
    ) -> tuple[np.ndarray, np.ndarray]:
        """Register ``K`` surface points; returns ``(ids (K, 3) into G-without-offset, w (K, 3))``.

        Skull ids are returned as negative numbers ``-(row + 1)`` and resolved by
        :meth:`resolve` once the skull table is complete.
        """
        k = surface.shape[0]
        ids = np.zeros((k, 3), np.int64)
        w = np.zeros((k, 3))
        for r in range(k):
            s = int(surface[r])
            if s in (0, 1):
                self.skull_rest.append(np.asarray(positions[r], np.float64))
                self.skull_on_mandible.append(s == 1)
                ids[r] = -len(self.skull_rest)
                w[r] = (1.0, 0.0, 0.0)
            else:
                tv = meshes[s].triangles[int(tri[r])]
                ids[r] = self.muscle_offset[s] + tv
                w[r] = bary[r]
        return ids, w

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Map the ids returned by :meth:`add` to rows of the final support array."""
        S = len(self.skull_rest)
        return np.where(ids < 0, -ids - 1, ids + S)


class MuscleSystem(eqx.Module):
    """All muscles of a rig (JAX pytree).

    Attributes:
        rest: ``(Nm, 3)`` rest particle positions, mm.
        skull_rest: ``(S, 3)`` rest positions of the surface points on the skull, mm.
        skull_on_mandible: ``(S,)`` bool.
        skull_jaw_weight: ``(S,)`` in [0, 1], how much of the jaw motion the tissue attached at
            each skull point follows (default 1 on the mandible and 0 elsewhere; the rig
            uses :func:`jaxface.anatomy.rig.jaw_follow_weights`: full at the chin, less with
            distance from it, on the cranium only below the mouth slit).
        fib_ids, fib_w: ``(F, m, 3)`` support ids / weights of the action-line points of every
            fibre (sheet, linear and passive muscles).
        fib_ctrl: ``(F,)`` control index (-1 for passive); fib_cmax: ``(F,)``;
            fib_h: ``(F,)`` samples per fibre; fib_valid: ``(P,)`` flat index of the valid
            samples in ``(F, H)``; fib_bottom: ``(P,)`` their bottom particles.
        sph_ids, sph_w: ``(K, 3, n, 3)`` the three rings of every sphincter (inner, middle,
            outer); sph_bottom: ``(K, 3, n)``; sph_ctrl: ``(K,)``; sph_cmax: ``(K,)``;
            sph_axes: ``(K, 2, 3)``; sph_ab: ``(K, 2)`` semi-axes, mm; sph_forward: ``(K, 3)``
            unit normal of each ring's plane, toward the face's front; sph_protrusion: ``(K,)``
            forward mm per mm of radial contraction; sph_drag: ``(K,)`` the ring's
            ``modiolus_drag``.
        mod_w: ``(K, 3, n, 2)`` modiolus weights in [0, 1] of every sphincter ring sample,
            toward the left (0) and the right (1) modiolus; mod_end, mod_last, mod_fw:
            ``(2, J)`` per side the corner-muscle fibres' insertion-end sample (flat index
            into the ``(F * H)`` samples), their action-line end (fibre index) and weight
            (1 / fibres of the muscle; 0 pads): see :data:`MODIOLUS_GAIN`; fib_mod_side:
            ``(F,)`` the modiolus (0 left, 1 right, 2 none) each fibre inserts into, fib_ramp:
            ``(F, H)`` 0 at its origin to 1 at its insertion end (the sphincters' ``modiolus_drag``).
        groups: the engine's distance and bending groups (all muscles, :mod:`jaxface.pbd`).
        positions: anchors of the bottom particles to their action-line samples (targets set
            every sweep, :func:`sample_targets`); shell: anchors of the top particles to their
            shell targets (:func:`shell_targets`); volume: one volume constraint per muscle.
        inv_mass: ``(Nm,)``.
        shell_top: ``(K,)`` every top particle (the bottom one under it is ``below[top]``);
            shell_along: ``(K, 4)`` the bottom's neighbours along its fibre and across;
            shell_mode: ``(K,)`` how the frame is built (:func:`_shell_frames`); shell_tri:
            ``(T, 3)`` the bottom-sheet triangles; shell_local: ``(K, 3)`` the top's rest
            offset in the bottom sheet's frame, mm; shell_sample: ``(K,)`` row of the
            bottom's fibre sample (-1 for sphincters) (:func:`shell_targets`).
        dist_lon_sample, dist_conn_sample: per row of the fused distance group, the fibre
            sample that shortens (top-sheet edge along a fibre) or thickens (boundary
            connection) it, -1 otherwise.
        offsets: static, first particle of each muscle + total; names: static muscle names;
        layers: static layer of each muscle; h_max: static; iterations: static sweeps;
        chebyshev_rho: static (experiments only); shell_stiffness: static, in [0, 1]
        (:data:`SHELL_STIFFNESS`; 0 = the thesis's muscle); checkpoint: static, checkpoint
        every sweep for reverse mode (:func:`jaxface.pbd.iterate`). Off by
        default: the muscle particles are few (1,688 on bs900's rig), so storing a sweep's
        intermediates costs less than recomputing them (reverse pass of a synthesis, 2-core
        CPU, float64: 0.47 s with the skin's sweeps checkpointed and the muscles' not, 0.52 s
        with both, 0.60 s with neither).
    """

    rest: jax.Array
    skull_rest: jax.Array
    skull_on_mandible: jax.Array
    skull_jaw_weight: jax.Array
    fib_ids: jax.Array
    fib_w: jax.Array
    fib_ctrl: jax.Array
    fib_cmax: jax.Array
    fib_h: jax.Array
    fib_valid: jax.Array
    fib_bottom: jax.Array
    fib_len0: jax.Array
    sph_ids: jax.Array
    sph_w: jax.Array
    sph_bottom: jax.Array
    sph_ctrl: jax.Array
    sph_cmax: jax.Array
    sph_axes: jax.Array
    sph_ab: jax.Array
    sph_forward: jax.Array
    sph_protrusion: jax.Array
    sph_drag: jax.Array
    mod_w: jax.Array
    fib_mod_side: jax.Array
    fib_ramp: jax.Array
    mod_end: jax.Array
    mod_last: jax.Array
    mod_fw: jax.Array
    groups: tuple[pbd.Group, ...]
    positions: pbd.Group
    shell: pbd.Group
    volume: pbd.Group
    inv_mass: jax.Array
    particle_layer: jax.Array
    below: jax.Array
    shell_top: jax.Array
    shell_along: jax.Array
    shell_tri: jax.Array
    shell_local: jax.Array
    shell_mode: jax.Array
    shell_sample: jax.Array
    dist_lon_sample: jax.Array
    dist_conn_sample: jax.Array
    offsets: tuple = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    layers: tuple = eqx.field(static=True)
    h_max: int = eqx.field(static=True, default=8)
    iterations: int = eqx.field(static=True, default=24)
    chebyshev_rho: float = eqx.field(static=True, default=0.0)
    shell_stiffness: float = eqx.field(static=True, default=SHELL_STIFFNESS)
    checkpoint: bool = eqx.field(static=True, default=False)

    @property
    def n_particles(self) -> int:
        return int(self.rest.shape[0])

    @property
    def n_muscles(self) -> int:
        return len(self.names)

    def support(self, skull_moved, x):
        """``(S + Nm, 3)`` support array from moved skull points and muscle particles."""
        return jnp.concatenate([skull_moved, x], axis=0)

    def muscle_vertices(self, x, name: str):
        """``(2 w h, 3)`` particles of one muscle from the stacked ``x``."""
        i = self.names.index(name)
        return x[self.offsets[i] : self.offsets[i + 1]]


def _eval_support(G, ids, w):
    return jnp.einsum("...k,...kd->...d", w.astype(G.dtype), G[ids])


def muscle_volumes(system: MuscleSystem, x) -> jax.Array:
    """``(n_muscles,)`` enclosed volume of each muscle mesh at ``x`` ``(Nm, 3)``, mm^3."""
    c = system.volume.c
    assert isinstance(c, pbd.VolumeConstraint)
    return eqx.tree_at(lambda q: q.origin, c, c.origin.astype(x.dtype)).volume(x)


@dataclass
class PendingMuscles:
    """Muscle system waiting for the skull-point table to be complete (the skin binding adds
    skull points); :meth:`finalize` resolves the support ids and converts to JAX."""

    data: dict
    sp: SupportPoints

    def finalize(self, jaw_weight=None) -> MuscleSystem:
        """Args: jaw_weight: optional callable ``(points (S, 3), on_mandible (S,)) -> (S,)``
        weights of the jaw motion (default: 1 on the mandible, 0 elsewhere)."""
        d = dict(self.data)
        res = self.sp.resolve
        d["fib_ids"] = res(d["fib_ids"])
        d["sph_ids"] = res(d["sph_ids"]) if d["sph_ids"].size else d["sph_ids"]
        skull = np.stack(self.sp.skull_rest) if self.sp.skull_rest else np.zeros((0, 3))
        static = {
            k: d.pop(k)
            for k in ("offsets", "names", "layers", "h_max", "iterations", "shell_stiffness")
        }
        engine = {k: d.pop(k) for k in ("groups", "positions", "shell", "volume")}
        arrs = {k: to_jax(v) for k, v in d.items()}
        onm = np.array(self.sp.skull_on_mandible, bool)
        jw = (
            onm.astype(np.float64)
            if jaw_weight is None
            else np.asarray(jaw_weight(skull, onm), np.float64)
        )
        return MuscleSystem(
            skull_rest=to_jax(skull),
            skull_on_mandible=to_jax(onm),
            skull_jaw_weight=to_jax(jw),
            **engine,
            **arrs,
            **static,
        )


def build_muscle_system(
    placed: list[PlacedMuscle],
    registry,
    control_index: dict,
    iterations: int = 24,
    shell_stiffness: float = SHELL_STIFFNESS,
) -> tuple[PendingMuscles, SupportPoints]:
    """Assemble the muscle particle system (NumPy build time).

    Args:
        placed: the placed muscles (layer order).
        registry: their :class:`~jaxface.anatomy.muscle_map.SurfaceRegistry`.
        control_index: muscle name -> index in the activation vector.
        iterations: static number of sweeps of the quasi-static muscle solve.
        shell_stiffness: in [0, 1], :data:`SHELL_STIFFNESS` (0 = the thesis's muscle).

    Returns:
        ``(PendingMuscles, SupportPoints)``: add the skin's skull points to the collector,
        then call ``PendingMuscles.finalize()``.
    """
    meshes = registry.meshes
    with_mesh = [p for p in placed if p.mesh is not None]
    offsets = [0]
    muscle_offset = {}
    rests: list[np.ndarray] = []
    for p in with_mesh:
        assert p.rest_vertices is not None  # placement sets it together with the mesh
        rests.append(p.rest_vertices)
        muscle_offset[p.surface_id] = offsets[-1]
        offsets.append(offsets[-1] + p.rest_vertices.shape[0])
    n = offsets[-1]
    rest = np.concatenate(rests) if with_mesh else np.zeros((0, 3))
    sp = SupportPoints([], [], muscle_offset)
    dist, bend, vol = [], [], []
    dist_key = []
    fib = []  # (ids (m,3), w (m,3), ctrl, cmax, h, bottom (h,))
    mod_fib = {0: [], 1: []}  # side -> (fibre index, weight, insertion-end bottom particle)
    sph = []
    for mi, p in enumerate(with_mesh):
        off = offsets[mi]
        g = p.grid
        assert g is not None  # placement sets it together with the mesh
        kk = STIFFNESS[p.kind]
        ctrl = control_index.get(p.name, -1) if p.spec.active else -1
        cmax = p.spec.max_contraction
        for key, arr in (
            ("lat_up", g.latitudinal_up),
            ("lon_up", g.longitudinal_up),
            ("lat_low", g.latitudinal_low),
            ("lon_low", g.longitudinal_low),
            ("connection", g.connection),
            ("shear_up", g.shear_up),
            ("shear_low", g.shear_low),
        ):
            if kk[key] > 0 and len(arr):
                dist.append((arr + off, kk[key]))
                dist_key.append((key, g.w * g.h))
        tm = TriMesh(p.rest_vertices, g.triangles, validate=False)
        if kk["bend"] > 0 and len(tm.edge_pairs):
            bend.append((np.asarray(tm.edge_pairs) + off, kk["bend"]))
        vol.append((g.triangles + off, kk["volume"], np.arange(off, offsets[mi + 1])))
        if p.kind == "sphincter":
            rings = [sp.add(f.surface, f.tri, f.bary, f.positions, meshes) for f in p.fibres]
            sph.append(
                dict(
                    ids=np.stack([r[0] for r in rings]),
                    w=np.stack([r[1] for r in rings]),
                    bottom=off + np.arange(3 * g.w).reshape(3, g.w),
                    ctrl=ctrl,
                    cmax=cmax,
                    axes=p.axes,
                    ab=p.semi_axes,
                    fwd=_ring_forward(p.axes),
                    prot=float(p.spec.protrusion),
                    drag=float(p.spec.modiolus_drag),
                    skin=np.stack([p.insertion_skin, p.origin_skin]),
                )
            )
        else:
            corner = _is_corner_muscle(p)
            for j, f in enumerate(p.fibres):
                ids, w = sp.add(f.surface, f.tri, f.bary, f.positions, meshes)
                if corner:
                    mod_fib[0 if p.spec.side == "left" else 1].append(
                        (len(fib), 1.0 / len(p.fibres), off + (g.h - 1) * g.w + j)
                    )
                fib.append((ids, w, ctrl, cmax, g.h, off + np.arange(g.h) * g.w + j))
    h_max = max([f[4] for f in fib], default=2)
    m_max = max([f[0].shape[0] for f in fib], default=2)
    check_sphincter_rings([p.spec for p in placed])
    mod = _modiolus(mod_fib, fib, sph, rest, h_max)
    F = len(fib)
    fib_ids = np.zeros((F, m_max, 3), np.int64)
    fib_w = np.zeros((F, m_max, 3))
    for i, f in enumerate(fib):
        m = f[0].shape[0]
        fib_ids[i, :m] = f[0]
        fib_w[i, :m] = f[1]
        fib_ids[i, m:] = f[0][-1]  # pad with the last point (zero-length segments)
        fib_w[i, m:] = f[1][-1]
    valid = (
        np.concatenate([i * h_max + np.arange(f[4]) for i, f in enumerate(fib)])
        if fib
        else np.zeros(0, np.int64)
    )
    fib_len0 = np.zeros(F)
    for i, f in enumerate(fib):
        ids_, w_ = f[0], f[1]
        corner = np.stack(
            [[sp.skull_rest[-k - 1] if k < 0 else rest[k] for k in row] for row in ids_]
        )
        sp_pts = np.einsum("mk,mkd->md", w_, corner)
        fib_len0[i] = np.linalg.norm(np.diff(sp_pts, axis=0), axis=1).sum()
    bottom = np.concatenate([f[5] for f in fib]) if fib else np.zeros(0, np.int64)
    pos_ids = np.concatenate([bottom] + [s["bottom"].ravel() for s in sph])
    groups = []
    if dist:
        pairs = np.concatenate([a for a, _ in dist])
        ks = np.concatenate([np.full(len(a), k) for a, k in dist])
        groups.append(
            pbd.make_group(
                pbd.distance_constraints(pairs, rest, stiffness=ks),
                n,
                omega=1.5,
                name=DISTANCE_GROUP,
            )
        )
    if bend:
        ep = np.concatenate([a for a, _ in bend])
        ks = np.concatenate([np.full(len(a), k) for a, k in bend])
        groups.append(
            pbd.make_group(
                pbd.bending_constraints(ep, rest, stiffness=ks), n, omega=1.0, name="muscle bending"
            )
        )
    # the bottom particles follow their action-line samples (targets set every sweep)
    positions = pbd.make_group(
        pbd.anchor_constraints(pos_ids, rest[pos_ids], stiffness=POSITION_STIFFNESS),
        n,
        name="muscle positions",
    )
    shell = _shell_data(with_mesh, offsets, rest, fib, dist, dist_key)
    tri = np.concatenate([t for t, _, _ in vol])
    owner = np.concatenate([np.full(len(t), i) for i, (t, _, _) in enumerate(vol)])
    volume = pbd.make_group(
        pbd.volume_constraint(
            tri, rest, origin=np.zeros(3), owner=owner, stiffness=np.asarray([k for _, k, _ in vol])
        ),
        n,
        name="muscle volume",
    )
    top = shell["shell_top"]
    if len(np.unique(top)) != len(top):
        raise RigError("a muscle particle is the top of two shell frames; check the muscle grid.")
    shell_group = pbd.make_group(
        pbd.anchor_constraints(top, rest[top], stiffness=shell_stiffness), n, name="muscle shell"
    )
    data = dict(
        rest=rest,
        fib_ids=fib_ids,
        fib_w=fib_w,
        fib_ctrl=np.array([f[2] for f in fib], np.int32),
        fib_cmax=np.array([f[3] for f in fib], float),
        fib_h=np.array([f[4] for f in fib], float),
        fib_valid=valid,
        fib_bottom=bottom,
        fib_len0=fib_len0,
        sph_ids=np.stack([s["ids"] for s in sph]) if sph else np.zeros((0, 3, 2, 3), np.int64),
        sph_w=np.stack([s["w"] for s in sph]) if sph else np.zeros((0, 3, 2, 3)),
        sph_bottom=np.stack([s["bottom"] for s in sph]) if sph else np.zeros((0, 3, 2), np.int64),
        sph_ctrl=np.array([s["ctrl"] for s in sph], np.int32),
        sph_cmax=np.array([s["cmax"] for s in sph], float),
        sph_axes=np.stack([s["axes"] for s in sph]) if sph else np.zeros((0, 2, 3)),
        sph_ab=np.stack([s["ab"] for s in sph]) if sph else np.zeros((0, 2)),
        sph_forward=np.stack([s["fwd"] for s in sph]) if sph else np.zeros((0, 3)),
        sph_protrusion=np.array([s["prot"] for s in sph], float),
        sph_drag=np.array([s["drag"] for s in sph], float),
        **mod,
        groups=tuple(groups),
        positions=positions,
        shell=shell_group,
        volume=volume,
        inv_mass=np.ones(n),
        particle_layer=np.concatenate(
            [np.full(offsets[i + 1] - offsets[i], p.spec.layer) for i, p in enumerate(with_mesh)]
        )
        if with_mesh
        else np.zeros(0, np.int64),
        below=np.concatenate(
            [
                offsets[i] + np.tile(np.arange((offsets[i + 1] - offsets[i]) // 2), 2)
                for i in range(len(with_mesh))
            ]
        )
        if with_mesh
        else np.zeros(0, np.int64),
        **shell,
        offsets=tuple(offsets),
        names=tuple(p.name for p in with_mesh),
        layers=tuple(p.spec.layer for p in with_mesh),
        h_max=int(h_max),
        iterations=int(iterations),
        shell_stiffness=float(shell_stiffness),
    )
    return PendingMuscles(data, sp), sp


def _shell_frames(x, bottom, along, tri, mode=None):
    """Local frames ``(K, 3, 3)`` (rows: tangent, second tangent, normal) of the bottom sheet at
    the ``K`` particles ``bottom``, NumPy or JAX.

    The normal is the area-weighted mean normal of the bottom-sheet triangles ``tri`` ``(T, 3)``
    around the particle. The first tangent is the difference of the particle's neighbours
    along its fibre (``along[:, 0] - along[:, 1]``) with the normal part removed (``mode``
    0); where ``mode`` ``(K,)`` is 1 (fibre direction nearly along the normal, or neighbours
    coincident, e.g. on the inrolled lip) the normal crossed with the difference of its
    neighbours across the fibres (``along[:, 2] - along[:, 3]``); where it is 2 (no usable
    frame at rest) the identity. NaN-safe: degenerate geometry gives zero rows, not NaN.
    """
    xp = jnp if isinstance(x, jax.Array) else np
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    tn = xp.cross(b - a, c - a)
    if xp is jnp:
        vn = jax.ops.segment_sum(jnp.concatenate([tn, tn, tn]), tri.T.reshape(-1), x.shape[0])
    else:
        vn = np.zeros(x.shape)
        for k in range(3):
            np.add.at(vn, tri[:, k], tn)

    def unit(v):
        n2 = xp.sum(v * v, axis=-1, keepdims=True)
        ok = n2 > 1e-18
        return xp.where(ok, v / xp.sqrt(xp.where(ok, n2, 1.0)), 0.0)

    n = unit(vn[bottom])
    tu = x[along[:, 0]] - x[along[:, 1]]
    e1 = tu - xp.sum(tu * n, axis=-1, keepdims=True) * n
    if mode is not None:
        tv = x[along[:, 2]] - x[along[:, 3]]
        e1 = xp.where((mode == 1)[:, None], xp.cross(n, tv), e1)
    e1 = unit(e1)
    F = xp.stack([e1, xp.cross(n, e1), n], axis=1)
    if mode is not None:
        F = xp.where((mode == 2)[:, None, None], xp.eye(3, dtype=F.dtype), F)
    return F


def _shell_data(with_mesh, offsets, rest, fib, dist, dist_key) -> dict:
    """Build-time data of the shell constraint and of the active shortening (NumPy).

    Returns the fields ``shell_*`` (per top particle: its bottom particle, the bottom's
    neighbours along the fibre, the rest offset in the bottom sheet's frame, the row of its
    fibre sample or -1 for sphincters; all bottom-sheet triangles) and, per row of the fused
    distance group, the fibre sample whose contraction shortens a top-sheet edge along the
    fibre (``dist_lon_sample``) or thickens a connection (``dist_conn_sample``), -1 otherwise.
    """
    sample_of = {}  # bottom particle -> its row in the (P,) valid fibre samples
    for f in fib:
        for b in f[5]:
            sample_of[int(b)] = len(sample_of)
    tops, bots, along, tris = [], [], [], []
    for mi, p in enumerate(with_mesh):
        off, w, h = offsets[mi], p.grid.w, p.grid.h
        t = p.grid.triangles
        tris.append(t[(t < w * h).all(axis=1)] + off)
        for i in range(h):
            for j in range(w):
                bots.append(off + i * w + j)
                tops.append(off + w * h + i * w + j)
                jp, jm = (
                    ((j + 1) % w, (j - 1) % w)
                    if p.grid.periodic
                    else (min(j + 1, w - 1), max(j - 1, 0))
                )
                along.append(
                    (
                        off + min(i + 1, h - 1) * w + j,
                        off + max(i - 1, 0) * w + j,
                        off + i * w + jp,
                        off + i * w + jm,
                    )
                )
    top = np.asarray(tops, np.int64)
    bot = np.asarray(bots, np.int64)
    al = np.asarray(along, np.int64).reshape(-1, 4)
    tri = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    # the frame's construction is chosen once, at rest, so that it never switches: from the
    # fibre direction where that is at least ~17 degrees off the normal, else from the
    # neighbours across the fibres, else (degenerate rest geometry) the identity
    F0 = _shell_frames(rest, bot, al, tri)
    tu = rest[al[:, 0]] - rest[al[:, 1]]
    tu_n = np.einsum("kd,kd->k", tu, F0[:, 2])
    mode = np.where(tu_n**2 >= 0.91 * np.einsum("kd,kd->k", tu, tu), 1, 0)
    det = np.linalg.det(_shell_frames(rest, bot, al, tri, mode))
    mode = np.where(np.abs(det) < 0.5, 2, mode)
    local = np.einsum("kij,kj->ki", _shell_frames(rest, bot, al, tri, mode), rest[top] - rest[bot])
    lon, conn = [], []
    for (pairs, _), (key, nwh) in zip(dist, dist_key):
        none = np.full(len(pairs), -1)
        lon.append(
            np.array([sample_of.get(int(e[0]) - nwh, -1) for e in pairs])
            if key == "lon_up"
            else none
        )
        conn.append(
            np.array([sample_of.get(int(e[0]), -1) for e in pairs]) if key == "connection" else none
        )
    cat = lambda v: np.concatenate(v).astype(np.int64) if v else np.zeros(0, np.int64)  # noqa: E731
    return dict(
        shell_top=top,
        shell_along=al,
        shell_tri=tri,
        shell_local=local,
        shell_mode=mode.astype(np.int32),
        shell_sample=np.asarray([sample_of.get(int(b_), -1) for b_ in bot], np.int64),
        dist_lon_sample=cat(lon),
        dist_conn_sample=cat(conn),
    )


def shell_targets(system: MuscleSystem, x, ids, tg, thick):
    """Where the shell constraint puts every top particle, ``(K, 3)`` mm (``K`` = all tops).

    The *shell* is our addition to the thesis's muscle (sec. 4.3.1 holds the top sheet only
    by the connections on the grid boundary, the lateral and longitudinal springs and the
    volume). The target of a top particle is its bottom particle's action-line sample plus the
    top's rest offset expressed in the local frame (:func:`_shell_frames`) of the bottom sheet
    laid on the samples, its normal part scaled by the fibre's thickening (rest over
    contracted fibre length, clipped to :data:`THICKENING_RANGE`): a contracting muscle
    shortens and bulges, keeping its volume, instead of shearing its top sheet over the
    bottom one. The frame is read from the samples (the support and the activations), not
    from the muscle's own particles, so it adds no feedback to the solve. At rest the
    targets are the rest positions.

    Args:
        system: the :class:`MuscleSystem`.
        x: ``(Nm, 3)`` muscle particles, mm.
        ids, tg: ``(P,)`` bottom particles and ``(P, 3)`` their samples, mm
            (:func:`sample_targets`).
        thick: ``(Pf,)`` thickening of every fibre sample (:func:`fibre_thickening`).
    """
    dt = x.dtype
    bottom = system.below[system.shell_top]
    base = x.at[ids].set(tg.astype(dt))
    F = _shell_frames(base, bottom, system.shell_along, system.shell_tri, system.shell_mode)
    th = _padded_thickening(thick, dt)[system.shell_sample]
    loc = system.shell_local.astype(dt)
    loc = jnp.concatenate([loc[:, :2], loc[:, 2:] * th[:, None]], axis=1)
    return base[bottom] + jnp.einsum("kij,ki->kj", F, loc)


def _padded_thickening(thick, dt):
    """``(Pf + 1,)`` fibre thickening clipped to :data:`THICKENING_RANGE`, with a trailing 1
    for the index -1 (no fibre sample)."""
    lo, hi = THICKENING_RANGE
    return jnp.concatenate([jnp.clip(thick.astype(dt), lo, hi), jnp.ones((1,), dt)])


def _active_groups(system: MuscleSystem, activations, thick, dt):
    """The fused groups with the distance rest lengths of the contracted muscle: top-sheet
    edges along a fibre shortened by ``1 - c`` (the fibre contracts, eq. 4.11, in both
    sheets) and boundary connections lengthened by the fibre's thickening."""
    groups = system.groups
    if not groups or groups[0].name != DISTANCE_GROUP:
        return groups
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    c_f = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)
    c_s = jnp.concatenate([jnp.repeat(c_f, system.h_max)[system.fib_valid], jnp.zeros((1,), dt)])
    g0 = groups[0]
    assert isinstance(g0.c, pbd.DistanceConstraints)
    r = (
        g0.c.rest.astype(dt)
        * (1.0 - c_s[system.dist_lon_sample])
        * _padded_thickening(thick, dt)[system.dist_conn_sample]
    )
    return (eqx.tree_at(lambda q: q.c.rest, g0, r),) + tuple(groups[1:])


def _is_corner_muscle(p) -> bool:
    """A fibred, active, sided muscle whose insertion is placed at a mouth corner."""
    ins = p.spec.insertion if isinstance(p.spec.insertion, dict) else {}
    at = ins.get("at", {})
    off = np.asarray(ins.get("offset", [0.0, 0.0, 0.0]), float)
    return (
        p.kind in ("linear", "sheet")
        and p.spec.active
        and p.spec.side in ("left", "right")
        and any("mouth corner" in str(k).lower() for k in at)
        and float(np.linalg.norm(off)) <= MODIOLUS_MAX_OFFSET_MM
    )


def _modiolus(mod_fib, fib, sph, rest, h_max: int) -> dict:
    """Build-time modiolus data (:data:`MODIOLUS_GAIN`): per side the corner muscles' fibres
    (insertion-end sample index, weight), per sphincter ring sample and side a Gaussian weight
    of its rest distance to that side's modiolus.

    The modiolus of a side is the mouth corner: the ring's middle ellipse on the skin (the mean
    of its inner and outer skin rings) at its lateral end on that side (:func:`_ring_end`: sample
    0 on the left, ``n / 2`` on the right). Only a ring with a
    sample within ``2 MODIOLUS_SIGMA_MM`` of the side's corner muscles' insertion ends (the mean
    rest position of those fibres' end particles) has one: the ring they insert into.
    """
    J = max(1, len(mod_fib[0]), len(mod_fib[1]))
    end = np.zeros((2, J), np.int64)
    last = np.zeros((2, J), np.int64)
    fw = np.zeros((2, J))
    ends = np.zeros((2, 3))
    ok = np.zeros(2, bool)
    for s_ in (0, 1):
        for k, (fi, w, _pid) in enumerate(mod_fib[s_]):
            end[s_, k] = fi * h_max + fib[fi][4] - 1
            last[s_, k] = fi
            fw[s_, k] = w
        if mod_fib[s_]:
            ends[s_] = rest[[pid for _, _, pid in mod_fib[s_]]].mean(axis=0)
            ok[s_] = True
    n = sph[0]["ids"].shape[1] if sph else 2
    mod_w = np.zeros((len(sph), 3, n, 2))
    for k, s in enumerate(sph):
        pos = rest[s["bottom"]]  # (3, n, 3)
        mid_skin = 0.5 * (s["skin"][0] + s["skin"][1])  # (n, 3)
        g = np.zeros((3, n, 2))
        for i in (0, 1):
            if not ok[i] or np.linalg.norm(pos - ends[i], axis=-1).min() > 2.0 * MODIOLUS_SIGMA_MM:
                continue
            corner = _ring_end(mid_skin, 0.0 if i == 0 else 0.5 * n)  # left, right
            d = np.linalg.norm(pos - corner, axis=-1)  # (3, n)
            g[..., i] = np.exp(-0.5 * (d / MODIOLUS_SIGMA_MM) ** 2)
        # each sample follows its nearer modiolus, the two blended across the mid-line
        mod_w[k] = g * (g / np.maximum(g.sum(axis=-1, keepdims=True), 1e-300))
    side = np.full(len(fib), 2, np.int32)  # 2: the fibre is not a corner muscle's
    for s_ in (0, 1):
        if np.any(mod_w[..., s_] > 0):
            for fi, _w, _pid in mod_fib[s_]:
                side[fi] = s_
    ramp = np.zeros((len(fib), h_max))
    for i, f in enumerate(fib):
        ramp[i, : f[4]] = np.arange(f[4]) / max(f[4] - 1, 1)
    return dict(
        mod_w=mod_w, fib_mod_side=side, fib_ramp=ramp, mod_end=end, mod_last=last, mod_fw=fw
    )


def _ring_end(ring, u: float):
    """The point at sample parameter ``u`` of a closed ring of samples ``(n, 3)`` (sample ``k``
    at ``u = k``): the sample itself for a whole ``u``, else the cubic through the four samples
    around it. A sphincter's rings are drawn from ``phi = 2 pi k / n`` (:func:`ellipse_points`),
    so its lateral ends are ``u = 0`` (left) and ``u = n / 2`` (right, between two samples when
    ``n`` is odd)."""
    n = len(ring)
    k = int(np.floor(u))
    f = u - k
    if f == 0.0:
        return ring[k % n]
    w = np.array(
        [
            -f * (f - 1) * (f - 2) / 6,
            (f + 1) * (f - 1) * (f - 2) / 2,
            -(f + 1) * f * (f - 2) / 2,
            (f + 1) * f * (f - 1) / 6,
        ]
    )
    return w @ ring[[(k - 1) % n, k % n, (k + 1) % n, (k + 2) % n]]


def _ring_forward(axes) -> np.ndarray:
    """``(3,)`` unit normal of a sphincter ring's plane (its two ``(2, 3)`` ellipse axes),
    oriented toward the face's front (+z)."""
    n = np.cross(np.asarray(axes[0], float), np.asarray(axes[1], float))
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    return n if n[2] >= 0 else -n


def moved_skull_points(system: MuscleSystem, R, t):
    """``(S, 3)`` skull surface points after the jaw motion ``p' = R p + t`` on the mandible."""
    sk = system.skull_rest.astype(R.dtype)
    moved = sk @ R.T + t
    w = system.skull_jaw_weight.astype(sk.dtype)[:, None]
    return sk + w * (moved - sk)


def sample_targets(system: MuscleSystem, G, activations):
    """Targets of every bottom particle: ``(P,)`` particle ids and ``(P, 3)`` mm positions.

    Fibres: action lines evaluated on the support ``G`` and re-sampled with the contraction
    (eq. 4.11). Sphincters: the ring samples displaced toward the contraction centre
    (sec. 4.3.2).
    """
    dt = G.dtype
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    pts = _eval_support(G, system.fib_ids, system.fib_w)  # (F, m, 3)
    c = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)  # ctrl -1 -> 0
    s = _sample_var(pts, system.fib_h.astype(dt), system.h_max, c)  # (F, H, 3)
    if system.sph_ids.shape[0] == 0:
        return system.fib_bottom, s.reshape(-1, 3)[system.fib_valid]
    P = _eval_support(G, system.sph_ids, system.sph_w)  # (K, 3, n, 3)
    # modiolus: contraction displacement of the corner muscles' insertion ends, per side
    pull = s.reshape(-1, 3)[system.mod_end] - pts[system.mod_last, -1]  # (2, J, 3)
    D = jnp.einsum("sj,sjd->sd", system.mod_fw.astype(dt), pull)  # (2, 3)
    P = P + MODIOLUS_GAIN * jnp.einsum("kmns,sd->kmnd", system.mod_w.astype(dt), D)
    inner, outer = P[:, 0], P[:, 2]
    o = jnp.mean(inner, axis=1, keepdims=True)  # (K, 1, 3)
    ax = system.sph_axes.astype(dt)
    xx = jnp.einsum("knd,kd->kn", outer - o, ax[:, 0])
    yy = jnp.einsum("knd,kd->kn", outer - o, ax[:, 1])
    ab = system.sph_ab.astype(dt)
    r2 = (xx / ab[:, :1]) ** 2 + (yy / ab[:, 1:]) ** 2
    r = jnp.minimum(jnp.sqrt(jnp.maximum(r2, 1e-12)), 1.0)
    cs = acts[system.sph_ctrl] * system.sph_cmax.astype(dt)  # (K,)
    falloff = jnp.cos(0.5 * jnp.pi * (1.0 - r))  # (K, n)
    delta = cs[:, None, None] * (o - inner) * falloff[..., None]
    # protrusion: the ring also moves forward by `protrusion` times its radial motion, whose
    # length cs |o - inner| falloff is linear in the activation (smooth at rest)
    radius = jnp.sqrt(jnp.sum((o - inner) ** 2, axis=-1))  # (K, n), > 0 on a placed ring
    fwd = (system.sph_protrusion.astype(dt) * cs)[:, None] * radius * falloff  # (K, n)
    delta = delta + fwd[..., None] * system.sph_forward.astype(dt)[:, None, :]
    tg_s = (P + delta[:, None]).reshape(-1, 3)
    # the ring drags the modiolus too (its modiolus_drag): each side's corner-muscle fibres
    # move by the ring's contraction displacement at that modiolus (the mean over the ring
    # samples weighted by their modiolus weight), fully at the insertion end and fading
    # linearly to the origin
    mw = system.mod_w.astype(dt)[:, 1]  # (K, n, 2): the middle ring
    drag = system.sph_drag.astype(dt)
    dr = jnp.einsum("kns,k,knd->sd", mw, drag, delta) / jnp.maximum(
        jnp.sum(mw, axis=(0, 1))[:, None], 1e-12
    )  # (2, 3)
    dr = jnp.concatenate([dr, jnp.zeros((1, 3), dt)])  # row 2: fibres off the modiolus
    s = s + system.fib_ramp.astype(dt)[..., None] * dr[system.fib_mod_side][:, None, :]
    tg_f = s.reshape(-1, 3)[system.fib_valid]
    return (
        jnp.concatenate([system.fib_bottom, system.sph_bottom.reshape(-1)]),
        jnp.concatenate([tg_f, tg_s]),
    )


def fibre_thickening(system: MuscleSystem, G, activations):
    """``(P,)`` thickness factor of every fibre sample: rest fibre length over current
    (contracted) length, the factor that keeps a fibre's cross-section times length constant."""
    dt = G.dtype
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    pts = _eval_support(G, system.fib_ids, system.fib_w)
    d = pts[:, 1:] - pts[:, :-1]
    L = jnp.sum(jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12), axis=-1)
    c = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)
    ratio = system.fib_len0.astype(dt) / jnp.maximum(L * (1.0 - c), 1e-6)
    H = system.h_max
    return jnp.repeat(ratio, H)[system.fib_valid]


def _sample_var(points, h, h_max: int, c):
    """:func:`jax_sample_polyline` with a per-polyline sample count ``h`` ``(F,)`` (float),
    padded to ``h_max`` samples (extra samples are clamped to the end and discarded)."""
    p = points
    d = p[..., 1:, :] - p[..., :-1, :]
    d2 = jnp.sum(d * d, axis=-1)
    ok = d2 > 1e-24
    seg = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2, 1.0)), 0.0)
    cum = jnp.concatenate([jnp.zeros_like(seg[..., :1]), jnp.cumsum(seg, axis=-1)], axis=-1)
    total = cum[..., -1:]
    i = jnp.arange(h_max, dtype=p.dtype)
    s = i * (total / (h[:, None] - 1.0)) * (1.0 - c[:, None])
    s = jnp.minimum(s, total)
    m1 = seg.shape[-1]
    j = jnp.clip(jnp.sum(cum[..., None, 1:] <= s[..., :, None], axis=-1), 0, m1 - 1)
    cj = jnp.take_along_axis(cum, j, axis=-1)
    lj = jnp.take_along_axis(seg, j, axis=-1)
    okj = lj > 0
    u = jnp.clip(jnp.where(okj, (s - cj) / jnp.where(okj, lj, 1.0), 0.0), 0.0, 1.0)[..., None]
    pj = jnp.take_along_axis(p, j[..., None], axis=-2)
    pj1 = jnp.take_along_axis(p, (j + 1)[..., None], axis=-2)
    return (1 - u) * pj + u * pj1


def muscle_sweep(system: MuscleSystem, x, skull, activations, inv_mass):
    """One sweep of the muscle solve: refresh the samples from the current support, then
    positions, shell, distances and bending (fused Jacobi) and the per-muscle volumes."""
    G = system.support(skull, x)
    ids, tg = sample_targets(system, G, activations)
    x = pbd.sweep((system.positions.set(target=tg),), x, inv_mass)
    groups = system.groups
    if system.shell_stiffness > 0:
        thick = fibre_thickening(system, G, activations)
        shell = system.shell.set(target=shell_targets(system, x, ids, tg, thick))
        groups = (shell,) + _active_groups(system, activations, thick, x.dtype)
    return pbd.sweep(groups + (system.volume,), x, inv_mass)


def warm_start(system: MuscleSystem, skull, activations):
    """Start positions close to the equilibrium, layer by layer (deepest first): bottom
    particles at their samples computed on the already-placed deeper layers, each top particle
    at its shell target (:func:`shell_targets`; without the shell: above its bottom particle
    at the rest offset scaled by the fibre's shortening, the volume-preserving thickening of
    sec. 4.1)."""
    rest = system.rest.astype(skull.dtype)
    x = rest
    below = system.below  # (Nm,) the bottom particle under each particle
    is_top = below != jnp.arange(rest.shape[0])
    off = rest - rest[below]
    for L in sorted(set(system.layers)):
        G = system.support(skull, x)
        ids, tg = sample_targets(system, G, activations)
        thick = fibre_thickening(system, G, activations)
        mine = system.particle_layer[ids] == L
        xb = x.at[ids].set(jnp.where(mine[:, None], tg, x[ids]))
        if system.shell_stiffness > 0:
            lifted = xb.at[system.shell_top].set(shell_targets(system, x, ids, tg, thick))
        else:
            scale = jnp.ones(rest.shape[0], rest.dtype).at[system.fib_bottom].set(thick)
            lifted = jnp.where(is_top[:, None], xb[below] + off * scale[below][:, None], xb)
        x = jnp.where((system.particle_layer == L)[:, None], lifted, x)
    return x


def solve_muscles(
    system: MuscleSystem, activations, R, t, *, iterations: int | None = None, x0=None
):
    """Quasi-static muscle solve for given activations and jaw motion.

    All layers are refreshed in every sweep (a layer's samples are read from the current
    positions of the deeper layers), so after ``iterations`` sweeps the configuration is the
    layered equilibrium of the thesis's deepest-first loop.

    Args:
        system: the :class:`MuscleSystem`.
        activations: ``(M,)`` in [0, 1] (the rig's control vector).
        R, t: mandible motion (:meth:`JawModel.transform`).
        iterations: sweeps (static; default ``system.iterations``).
        x0: optional warm start ``(Nm, 3)`` mm.

    Returns:
        ``(x (Nm, 3) mm, skull_moved (S, 3) mm)``.
    """
    iters = system.iterations if iterations is None else int(iterations)
    activations = jnp.asarray(activations)
    dt = jnp.result_type(activations.dtype, R.dtype)
    skull = moved_skull_points(system, R.astype(dt), t.astype(dt))
    x = warm_start(system, skull, activations.astype(dt)) if x0 is None else jnp.asarray(x0, dt)
    inv_mass = system.inv_mass.astype(dt)
    a = activations.astype(dt)
    x = pbd.iterate(
        lambda x: muscle_sweep(system, x, skull, a, inv_mass),
        x,
        iters,
        system.chebyshev_rho,
        checkpoint_every=1 if system.checkpoint else None,
    )
    return x, skull
