"""The face rig: :func:`build_rig` assembles skull, jaw, muscles and skin for one face, and
:func:`synthesize` turns muscle activations and a jaw pose into the deformed skin.

Forward model (thesis sec. 5.7, quasi-static):

1. the jaw pose gives the rigid motion of the mandible and lower teeth (:mod:`.jaw`); the
   tissue attached to the skull follows it with the weights of :func:`jaw_follow_weights`;
2. the muscles are solved (:func:`jaxface.anatomy.muscles.solve_muscles`): action lines
   re-sampled with the activations, layers deepest first, thesis constraints;
3. the skin anchors are refreshed from the surface points they are bound to, averaged over the
   tissue footprint and weighted by the influence map; eyelids rotate; optional cheek puff;
4. the skin is solved (:func:`jaxface.anatomy.skin.solve_skin`) with the thesis constraints and
   the teeth collisions.

:func:`synthesize` is jit-compiled (``eqx.filter_jit``), works under ``jax.vmap`` over batches
of activations / jaw poses, and is differentiable in forward and reverse mode with respect to
the activations, the jaw pose and the cheek puff. :func:`simulate` runs the dynamic version
(time steps of 16.6 ms with damping 0.2) for animation.

Units: mm, degrees (jaw angles); +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

import dataclasses
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import pbd
from ..errors import RigError
from ..mesh import TriMesh
from ..validate import checked_build, checked_controls
from .frame import face_frame
from .interface import RigConfig, configure, register_backend, rig_backend
from .jaw import JawModel, JawPose
from .muscle_map import MuscleSpec, load_muscle_map, place_muscles, placement_registry
from .muscles import (
    MuscleSystem,
    build_muscle_system,
    moved_skull_points,
    muscle_sweep,
    solve_muscles,
)
from .rig_config import (
    FAT_VOLUME,
    FOOTPRINT_CLUSTER_MM,
    FOOTPRINT_MM,
    JAW_FOLLOW_MM,
    PBDRigConfig,
)
from .skin import (
    SkinSystem,
    bind_skin,
    build_skin_system,
    eyelid_vertices,
    influence_map,
    skin_targets,
    solve_skin,
)
from .skull import Skull, estimate_skull

__all__ = [
    "FAT_VOLUME",
    "FOOTPRINT_CLUSTER_MM",
    "FOOTPRINT_MM",
    "JAW_FOLLOW_MM",
    "PBDRigConfig",
    "Rig",
    "RigInfo",
    "SynthState",
    "build_rig",
    "equilibrium_gap",
    "jaw_follow_weights",
    "synthesize",
    "synthesize_state",
    "simulate",
]


class RigInfo:
    """Build-time (NumPy) objects of a rig, kept for inspection and pictures; compared by
    identity so that it can sit in a static field of the :class:`Rig` pytree.

    Attributes:
        skin: the rest skin :class:`TriMesh`; landmarks: the landmarks used; frame: the
        :class:`~jaxface.anatomy.frame.FaceFrame`; skull: the :class:`Skull`;
        placed: the :class:`PlacedMuscle` list; specs: the :class:`MuscleSpec` list;
        binding: the skin :class:`~jaxface.anatomy.skin.Binding`; influence: ``(V,)``.
    """

    skin: Any
    landmarks: Any
    frame: Any
    skull: Any
    placed: Any
    specs: Any
    binding: Any
    influence: Any

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def __hash__(self):
        return id(self)

    def __eq__(self, other):
        return self is other


class Rig(eqx.Module):
    """A face rig (JAX pytree): the model of one face.

    Attributes:
        jaw: :class:`JawModel`.
        muscles: :class:`~jaxface.anatomy.muscles.MuscleSystem`.
        skin: :class:`~jaxface.anatomy.skin.SkinSystem`.
        muscle_names: static tuple, the order of the activation vector.
        muscle_aus: static tuple of the AUs of each control.
        info: static :class:`RigInfo` (build-time objects).
    """

    backend = "pbd"  # which simulator synthesize() runs; LTWRig says "ltw"

    jaw: JawModel
    muscles: MuscleSystem
    skin: SkinSystem
    muscle_names: tuple = eqx.field(static=True)
    muscle_aus: tuple = eqx.field(static=True)
    info: RigInfo = eqx.field(static=True)

    @property
    def n_controls(self) -> int:
        """Number of activations ``M``."""
        return len(self.muscle_names)

    @property
    def n_vertices(self) -> int:
        return self.skin.n_vertices

    @property
    def rest(self) -> jax.Array:
        """``(V, 3)`` rest skin, mm."""
        return self.skin.rest

    @property
    def triangles(self) -> np.ndarray:
        """``(F, 3)`` skin triangles."""
        return self.info.skin.triangles

    def index(self, name: str) -> int:
        """Index of a control in the activation vector (RigError listing the names if unknown)."""
        try:
            return self.muscle_names.index(name)
        except ValueError:
            raise RigError(
                f"unknown muscle {name!r}; the rig's controls are {list(self.muscle_names)}."
            ) from None

    def activations(self, values: dict | None = None, **kw) -> jax.Array:
        """``(M,)`` activation vector from ``{name: value}`` (others 0)."""
        a = np.zeros(self.n_controls)
        for k, v in {**(values or {}), **kw}.items():
            a[self.index(k)] = float(v)
        return jnp.asarray(a)

    def synthesize(self, activations, jaw: JawPose | None = None, cheek_puff=0.0) -> jax.Array:
        """:func:`synthesize` of this rig: ``(V, 3)`` skin, mm (the
        :class:`~jaxface.anatomy.interface.FaceRig` method)."""
        return synthesize(self, activations, jaw, cheek_puff)

    def with_iterations(
        self,
        muscles: int | None = None,
        skin: int | None = None,
        *,
        muscle_rho: float | None = None,
        skin_rho: float | None = None,
        checkpoint: bool | None = None,
    ) -> Rig:
        """A copy with other static sweep counts (e.g. many for a converged reference) and,
        optionally, other Chebyshev spectral-radius estimates of the two quasi-static solves
        (:func:`jaxface.pbd.iterate`; 0 = plain sweeps). ``muscle_rho`` is for
        experiments only: the muscle iteration is too non-linear for it (see
        :func:`build_rig`, ``skin_chebyshev_rho``). ``checkpoint`` turns the per-sweep
        ``jax.checkpoint`` of both solves on or off (by default the skin's is on, the
        muscles' off): it only changes the reverse pass's memory and time.

        Raises:
            RigError: a sweep count below 1 or a spectral radius outside ``[0, 1)``.
        """
        for label, v in (("muscles", muscles), ("skin", skin)):
            if v is not None and int(v) < 1:
                raise RigError(f"{label} sweeps must be at least 1, got {v}.")
        for label, v in (("muscle_rho", muscle_rho), ("skin_rho", skin_rho)):
            if v is not None:
                pbd.check_rho(v, f"{label} (a Chebyshev spectral-radius estimate)")
        r = self
        mk, sk = {}, {}
        if muscles is not None:
            mk["iterations"] = int(muscles)
        if muscle_rho is not None:
            mk["chebyshev_rho"] = float(muscle_rho)
        if skin is not None:
            sk["iterations"] = int(skin)
        if skin_rho is not None:
            sk["chebyshev_rho"] = float(skin_rho)
        if checkpoint is not None:
            mk["checkpoint"] = sk["checkpoint"] = bool(checkpoint)
        if mk:
            r = eqx.tree_at(lambda q: q.muscles, r, _replace_static(r.muscles, **mk))
        if sk:
            r = eqx.tree_at(lambda q: q.skin, r, _replace_static(r.skin, **sk))
        return r


def _replace_static(module, **kw):
    return dataclasses.replace(module, **kw)


def _as_mesh(skin) -> TriMesh:
    if isinstance(skin, TriMesh):
        return skin
    if hasattr(skin, "mesh") and isinstance(skin.mesh, TriMesh):
        return skin.mesh
    raise RigError(
        f"build_rig needs the skin as a jaxface TriMesh (mm), got {type(skin).__name__}."
    )


@checked_build  # NaN, huge or unwelded skins refused (jaxface.validate)
def build_rig(
    skin,
    landmarks=None,
    skull: Skull | None = None,
    muscle_map=None,
    backend: str = "pbd",
    *,
    config: RigConfig | None = None,
    upper_teeth: TriMesh | None = None,
    lower_teeth: TriMesh | None = None,
    muscle_iterations: int | None = None,
    skin_iterations: int | None = None,
    footprint_mm: float | tuple | None = None,
    footprint_cluster_mm: float | None = None,
    influence_radius: float | None = None,
    eyelid_threshold: float | None = None,
    bending: bool | None = None,
    jaw_follow_mm: tuple[float, float] | None = None,
    jaw_membrane: bool | None = None,
    skin_chebyshev_rho: float | None = None,
    muscle_shell_stiffness: float | None = None,
    fat_volume: float | tuple | None = None,
):
    """Build the rig of a face with either backend.

    Args:
        skin: the skin :class:`TriMesh` (mm, face looking +z), or a
            :class:`jaxface.head.Head` (then ``landmarks`` and the teeth default to the head's).
        landmarks: its Bosphorus landmarks (22 face labels at least).
        skull: a :class:`Skull` (user-supplied or fitted); estimated when None.
        muscle_map: path of a muscle-map JSON, a list of :class:`MuscleSpec`, or None for the
            packaged default map.
        backend: "pbd" (this module) or "ltw" (the Lee-Terzopoulos-Waters backend,
            :func:`jaxface.ltw.rig.build_ltw_rig`).
        config: the backend's options: a :class:`PBDRigConfig` for "pbd", a
            :class:`jaxface.ltw.rig.LTWRigConfig` for "ltw"; None = the backend's defaults.
        upper_teeth, lower_teeth, muscle_iterations, ...: the options of
            :class:`PBDRigConfig` (see there), as keywords; None = the config's value. Given
            with ``config``, they replace its fields. With ``backend="ltw"`` only those the
            LTW backend has too (``eyelid_threshold``) are accepted.

    Returns:
        :class:`Rig` ("pbd") or :class:`jaxface.ltw.rig.LTWRig` ("ltw"); both are
        :class:`~jaxface.anatomy.interface.FaceRig`.

    Raises:
        RigOptionError: an option or a config that the backend does not take (instead of
            silently ignoring it).
        RigError, LandmarkError, MeshError: unusable inputs (named in the message).
    """
    options = dict(
        upper_teeth=upper_teeth,
        lower_teeth=lower_teeth,
        muscle_iterations=muscle_iterations,
        skin_iterations=skin_iterations,
        footprint_mm=footprint_mm,
        footprint_cluster_mm=footprint_cluster_mm,
        influence_radius=influence_radius,
        eyelid_threshold=eyelid_threshold,
        bending=bending,
        jaw_follow_mm=jaw_follow_mm,
        jaw_membrane=jaw_membrane,
        skin_chebyshev_rho=skin_chebyshev_rho,
        muscle_shell_stiffness=muscle_shell_stiffness,
        fat_volume=fat_volume,
    )
    rb = rig_backend(backend)
    return rb.build(skin, landmarks, skull, muscle_map, configure(rb, config, options))


def _build_pbd(skin, landmarks, skull, muscle_map, config: PBDRigConfig) -> Rig:
    """The PBD backend's builder (:func:`build_rig` with a complete :class:`PBDRigConfig`)."""
    c = config
    upper_teeth, lower_teeth = c.upper_teeth, c.lower_teeth
    muscle_iterations, skin_iterations = c.muscle_iterations, c.skin_iterations
    footprint_mm, footprint_cluster_mm = c.footprint_mm, c.footprint_cluster_mm
    influence_radius, eyelid_threshold, bending = c.influence_radius, c.eyelid_threshold, c.bending
    jaw_follow_mm, jaw_membrane = c.jaw_follow_mm, c.jaw_membrane
    skin_chebyshev_rho, muscle_shell_stiffness = c.skin_chebyshev_rho, c.muscle_shell_stiffness
    fat_volume = c.fat_volume
    if not isinstance(skin, TriMesh) and hasattr(skin, "mesh"):
        head = skin
        landmarks = head.landmarks if landmarks is None else landmarks
        upper_teeth = getattr(head, "upper_teeth", None) if upper_teeth is None else upper_teeth
        lower_teeth = getattr(head, "lower_teeth", None) if lower_teeth is None else lower_teeth
    mesh = _as_mesh(skin)
    if landmarks is None:
        raise RigError("build_rig needs the face's landmarks.")
    frame = face_frame(landmarks)
    if skull is None:
        skull = estimate_skull(mesh, landmarks, upper_teeth=upper_teeth, lower_teeth=lower_teeth)
    elif upper_teeth is not None or lower_teeth is not None:
        skull = skull.with_teeth(upper_teeth or skull.upper_teeth, lower_teeth or skull.lower_teeth)
    if isinstance(muscle_map, (list, tuple)):
        specs = list(muscle_map)
        if not all(isinstance(s, MuscleSpec) for s in specs):
            raise RigError("muscle_map must be a path, None, or a list of MuscleSpec.")
    else:
        specs = load_muscle_map(muscle_map)
    controls = [s for s in specs if s.active]
    names = tuple(s.name for s in controls)
    ci = {n: i for i, n in enumerate(names)}
    placed = place_muscles(mesh, landmarks, skull, specs)
    registry = placement_registry(skull, placed)
    if not 0.0 <= float(muscle_shell_stiffness) <= 1.0:
        raise RigError(
            f"muscle_shell_stiffness must be in [0, 1], got {muscle_shell_stiffness} "
            "(1 = default, 0 = the thesis's muscle without the shell)."
        )
    pend, sp = build_muscle_system(
        placed, registry, ci, iterations=muscle_iterations, shell_stiffness=muscle_shell_stiffness
    )
    binding = bind_skin(mesh, registry, scale=frame.mean_scale)
    ids, w = sp.add(binding.surface, binding.tri, binding.bary, binding.point, registry.meshes)
    muscles = pend.finalize(
        jaw_weight=lambda p, onm: jaw_follow_weights(p, onm, frame, *jaw_follow_mm)
    )
    ids = sp.resolve(ids)
    membrane = None
    if jaw_membrane:
        # skin under the chin bound to the cranium where that follows the jaw:
        # no bone moves it, so it hangs between the jaw-borne skin and the still skin
        S = int(muscles.skull_rest.shape[0])
        jw = np.asarray(muscles.skull_jaw_weight)
        wj = np.sum(w * np.where(ids < S, jw[np.minimum(ids, S - 1)], 0.0), axis=1)
        chin_y = frame.to_local(frame.points["Chin middle"])[1]
        membrane = (
            (binding.surface == 0) & (wj > 1e-6) & (frame.to_local(mesh.vertices)[:, 1] < chin_y)
        )
    sources = binding.surface != 0
    infl = influence_map(mesh, sources, influence_radius)
    # eyelids: one lid region per eye; angles per control from the map
    eyelids = []
    for side in ("left", "right"):
        angles = np.zeros((len(names), 2))
        for s in controls:
            if s.kind == "eyelid" and s.side == side and s.angles_deg:
                angles[ci[s.name]] = (
                    float(s.angles_deg.get("upper", 0.0)),
                    float(s.angles_deg.get("lower", 0.0)),
                )
        if not np.any(angles):
            continue
        lid_ids, fall, upper = eyelid_vertices(mesh, frame, side, eyelid_threshold)
        pm = next(p for p in placed if p.kind == "eyelid" and p.spec.side == side)
        axes = cast(np.ndarray, pm.axes)  # an eyelid's placement always has its axes
        eyelids.append((lid_ids, fall, upper, len(eyelids), pm.centre, axes[0], angles))
    skin_sys = build_skin_system(
        mesh,
        frame,
        binding,
        ids,
        w,
        influence=infl,
        eyelids=eyelids,
        teeth=(skull.upper_teeth, skull.lower_teeth),
        footprint_mm=footprint_mm,
        footprint_cluster_mm=footprint_cluster_mm,
        bending=bending,
        iterations=skin_iterations,
        membrane=membrane,
        fat_volume=fat_volume,
    )
    jaw = JawModel.from_landmarks(frame)
    info = RigInfo(
        skin=mesh,
        landmarks=landmarks,
        frame=frame,
        skull=skull,
        placed=placed,
        specs=specs,
        binding=binding,
        influence=infl,
        registry=registry,
    )
    rig = Rig(
        jaw=jaw,
        muscles=muscles,
        skin=skin_sys,
        muscle_names=names,
        muscle_aus=tuple(tuple(s.aus) for s in controls),
        info=info,
    )
    return rig.with_iterations(skin_rho=skin_chebyshev_rho)


register_backend("pbd", PBDRigConfig, _build_pbd)


def jaw_follow_weights(
    points,
    on_mandible,
    frame,
    full_mm: float = JAW_FOLLOW_MM[0],
    reach_mm: float = JAW_FOLLOW_MM[1],
) -> np.ndarray:
    """How much of the jaw motion the tissue attached at each skull point follows, in [0, 1].

    The skin and the muscles are attached to surface points of the skull. The thesis moves
    the points on the mandible rigidly with it and leaves the cranium still. Real soft tissue
    slides over the bone: in ICT-FaceKit's scan-based ``jawOpen`` expression the skin moves
    with the mandible at the chin (ratio 0.9), about half as far 40 mm from it and 0.1-0.2 over
    the ramus, and the skin under the jaw and on the upper neck is pulled along a little.
    Carrying all the tissue over the mandible rigidly drags the whole jaw line with the bone
    while the neck below stays, and the skin there folds when the jaw opens (28 / 152 / 258
    inverted triangles on the default head at 10 / 14 / 18 degrees; 2 / 24 / 78 with these
    weights, left in the crease under the chin).

    The weight is ``1 - smoothstep((d - full) / (reach - full))`` of the distance ``d`` from
    the chin landmark (reference mm) on the mandible; on the cranium it is faded out above
    the mouth slit (8 mm ramp), so the upper lip and the cheeks above it never follow the jaw.
    The defaults (30, 100) keep the surface around the chin moving with the bone (which is
    what the jaw-opening scans show: a smaller ``full`` matches ICT's per-vertex sliding
    better but fits the surface of LFAU_26 scans worse) and spread the pull over the jaw
    line and the neck.

    Args:
        points: ``(S, 3)`` skull surface points, mm.
        on_mandible: ``(S,)`` bool.
        frame: the face's :class:`~jaxface.anatomy.frame.FaceFrame`.
        full_mm, reach_mm: distances from the chin where the following starts to fall and
            where it ends (reference mm); ``reach_mm <= 0`` gives the rigid split (1 on the
            mandible, 0 elsewhere).

    Returns:
        ``(S,)`` weights.

    Raises:
        RigError: ``full_mm`` not below ``reach_mm``.
    """
    onm = np.asarray(on_mandible, bool)
    if reach_mm <= 0 or len(onm) == 0:
        return onm.astype(np.float64)
    if not 0.0 <= full_mm < reach_mm:
        raise RigError(
            f"jaw_follow_mm must be (full, reach) with 0 <= full < reach (mm); got "
            f"({full_mm}, {reach_mm})."
        )
    pts = np.asarray(points, np.float64)
    d = np.linalg.norm(pts - frame.points["Chin middle"], axis=1) / frame.mean_scale
    t = np.clip((d - full_mm) / (reach_mm - full_mm), 0.0, 1.0)
    w = 1.0 - t * t * (3.0 - 2.0 * t)
    st = frame.to_local(frame.stomion)[1]
    below = np.clip((st - frame.to_local(pts)[:, 1]) / 8.0, 0.0, 1.0)
    return np.where(onm, w, w * below)


class SynthState(eqx.Module):
    """Everything a synthesis computes (for tests and pictures).

    Attributes:
        skin: ``(V, 3)`` mm; muscles: ``(Nm, 3)`` mm; targets: ``(V, 3)`` skin anchor
        targets, mm; R, t: the mandible motion.
    """

    skin: jax.Array
    muscles: jax.Array
    targets: jax.Array
    R: jax.Array
    t: jax.Array


def _check_acts(rig: Rig, activations):
    a = jnp.asarray(activations)
    if a.ndim != 1 or a.shape[0] != rig.n_controls:
        raise RigError(
            f"activations must have shape ({rig.n_controls},) ordered as "
            f"rig.muscle_names; got {tuple(a.shape)}. Use jax.vmap for batches."
        )
    if not jnp.issubdtype(a.dtype, jnp.floating):
        a = a.astype(jnp.result_type(float))
    return a


def _synth(rig: Rig, activations, jaw: JawPose, cheek_puff):
    a = _check_acts(rig, activations)
    if not isinstance(jaw, JawPose):
        raise RigError(f"jaw must be a JawPose, got {type(jaw).__name__}.")
    dt = jnp.result_type(a.dtype, jaw.pitch_deg.dtype)
    a = a.astype(dt)
    R, t = rig.jaw.transform(jaw)
    R, t = R.astype(dt), t.astype(dt)
    xm, skull = solve_muscles(rig.muscles, a, R, t)
    G = rig.muscles.support(skull, xm)
    tg = skin_targets(rig.skin, G, a, jnp.asarray(cheek_puff, dt))
    x = solve_skin(rig.skin, tg, R, t)
    return SynthState(skin=x, muscles=xm, targets=tg, R=R, t=t)


@eqx.filter_jit
def synthesize_state(
    rig: Rig, activations, jaw: JawPose | None = None, cheek_puff=0.0
) -> SynthState:
    """:func:`synthesize`, returning the whole :class:`SynthState`."""
    jaw = JawPose() if jaw is None else jaw
    return _synth(rig, activations, jaw, cheek_puff)


@eqx.filter_jit
def equilibrium_gap(
    rig: Rig,
    activations,
    jaw: JawPose | None = None,
    cheek_puff=0.0,
    *,
    sweeps: tuple[int, int] = (1000, 1000),
):
    """How far a synthesis still is from the equilibrium it is heading for, mm per vertex.

    The synthesis of ``rig`` (at its own sweep counts) is continued with ``sweeps`` =
    ``(muscle, skin)`` more *plain* sweeps, warm-started from its muscles and its skin, and the
    distance each skin vertex moves on the way is returned. A converged synthesis moves
    nowhere.

    This measures convergence where a distance to a deep solve from rest cannot: with contact
    against the teeth, and where compressed skin buckles (under the brows in a smile, in the
    crease under the chin of an open jaw), the quasi-static problem has more than one
    equilibrium, and an accelerated solve can settle in another one than plain sweeps from
    rest reach. Such a result is converged (it is a fixed point of the sweep) although it lies
    away from the plain solve's. Where the equilibrium is unique the two measures agree.

    Args:
        rig: a :class:`Rig` (the PBD backend).
        activations: ``(M,)`` in [0, 1], ordered as ``rig.muscle_names``.
        jaw: :class:`JawPose` (degrees, mm); neutral if None.
        cheek_puff: AU33/34 pressure in [0, 1].
        sweeps: static ``(muscle, skin)`` plain sweeps of the continuation. 1,000 skin sweeps
            are slow enough to show a creeping buckle (a plain 64-sweep solve of a smile on
            the ICT face still moves 0.34 mm in them) and cheap next to a deep solve.

    Returns:
        ``(V,)`` mm, the distance from the synthesis to its continuation. Jit-compiled and
        vmap-able; a diagnostic, not meant for differentiation.

    Raises:
        RigError: an LTW rig, a sweep count below 1, or activations of the wrong shape.
    """
    if rig.backend == "ltw":
        raise RigError(
            "equilibrium_gap measures the PBD solve; an LTW rig integrates in time "
            "(see jaxface.ltw.rig.synthesize_ltw and its steps)."
        )
    try:
        m_sweeps, s_sweeps = (int(v) for v in sweeps)
    except (TypeError, ValueError):
        raise RigError(f"sweeps must be two integers (muscle, skin), got {sweeps!r}.") from None
    if m_sweeps < 1 or s_sweeps < 1:
        raise RigError(f"sweeps must be at least 1 each, got {sweeps!r}.")
    jaw = JawPose() if jaw is None else jaw
    st = _synth(rig, activations, jaw, cheek_puff)
    dt = st.skin.dtype
    a = _check_acts(rig, activations).astype(dt)
    plain = rig.with_iterations(muscle_rho=0.0, skin_rho=0.0)
    xm, skull = solve_muscles(plain.muscles, a, st.R, st.t, iterations=m_sweeps, x0=st.muscles)
    tg = skin_targets(plain.skin, plain.muscles.support(skull, xm), a, jnp.asarray(cheek_puff, dt))
    x = solve_skin(plain.skin, tg, st.R, st.t, iterations=s_sweeps, x0=st.skin)
    return jnp.sqrt(jnp.sum((x - st.skin) ** 2, axis=1))


@checked_controls  # NaN / out-of-range controls refused (jaxface.validate)
@eqx.filter_jit
def synthesize(rig: Rig, activations, jaw: JawPose | None = None, cheek_puff=0.0):
    """Synthesize the face for muscle activations and a jaw pose (quasi-static).

    Args:
        rig: the :class:`Rig`, or any other :class:`~jaxface.anatomy.interface.FaceRig`
            (a :class:`jaxface.ltw.rig.LTWRig` from ``build_rig(..., backend="ltw")``).
        activations: ``(M,)`` in [0, 1], ordered as ``rig.muscle_names``.
        jaw: :class:`JawPose` (degrees, mm; smoothly clamped to the limits); neutral if None.
        cheek_puff: AU33/34 air pressure in [0, 1] (outward cheek displacement of
            ``puff_mm`` at 1; 0 = off).

    Returns:
        ``(V, 3)`` skin vertices, mm.

    Raises:
        RigError: activations of the wrong shape (use ``jax.vmap`` for batches).

    A rig built with ``backend="ltw"`` is synthesized by
    :func:`jaxface.ltw.rig.synthesize_ltw` (same controls, same units).
    """
    if rig.backend != "pbd":  # another backend's rig synthesizes itself (FaceRig)
        return rig.synthesize(activations, jaw, cheek_puff)
    jaw = JawPose() if jaw is None else jaw
    return _synth(rig, activations, jaw, cheek_puff).skin


def simulate(
    rig: Rig,
    activations,
    jaw: JawPose | None = None,
    *,
    dt: float = 0.0166,
    damping: float = 0.2,
    muscle_sweeps: int = 4,
    skin_sweeps: int = 4,
    cheek_puff=None,
):
    """Dynamic animation (thesis sec. 5.7): one time step per frame.

    Each frame: jaw transform; ``muscle_sweeps`` sweeps of the muscles from the previous frame;
    skin anchors refreshed; the skin integrated with position-based dynamics (velocity damped
    by ``damping``, prediction ``p = x + dt v``, ``skin_sweeps`` sweeps of the constraints and
    collisions, ``v = (p - x) / dt``).

    Args:
        rig: the :class:`Rig`.
        activations: ``(T, M)`` per frame.
        jaw: :class:`JawPose` with ``(T,)`` leaves (neutral if None).
        dt: time step, s (16.6 ms).
        damping: velocity damping per step (thesis 0.2).
        muscle_sweeps, skin_sweeps: static sweeps per frame.
        cheek_puff: optional ``(T,)``.

    Returns:
        ``(T, V, 3)`` skin per frame, mm.
    """
    A = jnp.asarray(activations)
    if A.ndim != 2 or A.shape[1] != rig.n_controls:
        raise RigError(
            f"simulate needs activations of shape (T, {rig.n_controls}); got {tuple(A.shape)}."
        )
    T = A.shape[0]
    dtp = A.dtype if jnp.issubdtype(A.dtype, jnp.floating) else jnp.result_type(float)
    A = A.astype(dtp)
    if jaw is None:
        jaw = JawPose(jnp.zeros(T, dtp), jnp.zeros(T, dtp), jnp.zeros(T, dtp))
    puff = jnp.zeros(T, dtp) if cheek_puff is None else jnp.asarray(cheek_puff, dtp)
    return _simulate(
        rig, A, jaw, puff, float(dt), float(damping), int(muscle_sweeps), int(skin_sweeps)
    )


@eqx.filter_jit
def _simulate(rig, A, jaw, puff, dt, damping, muscle_sweeps, skin_sweeps):
    ms = rig.muscles
    dtp = A.dtype
    x_m0 = ms.rest.astype(dtp)
    x_s0 = rig.skin.rest.astype(dtp)
    v0 = jnp.zeros_like(x_s0)
    inv_m = ms.inv_mass.astype(dtp)

    def frame(carry, inp):
        xm, xs, v = carry
        a, pose, p = inp
        R, t = rig.jaw.transform(pose)
        R, t = R.astype(dtp), t.astype(dtp)
        skull = moved_skull_points(ms, R, t)
        xm = pbd.iterate(
            lambda x: muscle_sweep(ms, x, skull, a, inv_m),
            xm,
            muscle_sweeps,
            checkpoint_every=None,
        )
        tg = skin_targets(rig.skin, ms.support(skull, xm), a, p)
        new, v = pbd.time_step(
            lambda q: solve_skin(rig.skin, tg, R, t, iterations=skin_sweeps, x0=q),
            xs,
            v,
            rig.skin.inv_mass,
            dt=dt,
            damping=damping,
        )
        return (xm, new, v), new

    poses = JawPose(
        jaw.pitch_deg.astype(dtp), jaw.yaw_deg.astype(dtp), jaw.protrusion_mm.astype(dtp)
    )
    _, out = jax.lax.scan(frame, (x_m0, x_s0, v0), (A, poses, puff))
    return out
