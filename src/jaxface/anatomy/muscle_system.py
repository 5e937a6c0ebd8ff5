"""The muscle system's data (thesis sec. 4.3): stiffness values per muscle kind, the modiolus
and shell parameters, the skull support points (:class:`SupportPoints`), the JAX
:class:`MuscleSystem` and the muscle volumes. Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import pbd
from .._arrays import to_jax

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
