"""Assembly of the face rig (thesis ch. 4-5): :func:`build_rig` (any registered backend), the
``pbd`` backend's builder and :func:`jaw_follow_weights`. Units: mm; +y up, +z forward,
subject's left +x.
"""

from __future__ import annotations

import numpy as np

from ..errors import RigError
from ..mesh import TriMesh
from ..validate import checked_build
from .frame import face_frame
from .interface import RigConfig, configure, register_backend, rig_backend
from .jaw import PROTRUSION_LIMITS_MM, JawModel
from .muscle_map import place_muscles, placement_registry
from .muscles import (
    build_muscle_system,
)
from .rig_common import eyelid_regions, muscle_controls
from .rig_config import JAW_FOLLOW_MM, PBDRigConfig
from .rig_synth import Rig, RigInfo
from .skin import (
    bind_skin,
    build_skin_system,
    influence_map,
)
from .skull import Skull, estimate_skull


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
    jaw_pitch_limits_deg: tuple[float, float] | None = None,
    jaw_protrusion_limits_mm: tuple[float, float] | None = None,
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
        jaw_pitch_limits_deg=jaw_pitch_limits_deg,
        jaw_protrusion_limits_mm=jaw_protrusion_limits_mm,
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
    plo, phi = (float(x) for x in c.jaw_pitch_limits_deg)
    if not (np.isfinite([plo, phi]).all() and plo <= 0.0 < phi <= 45.0):
        raise RigError(
            f"jaw_pitch_limits_deg must be (closing, opening) degrees with closing <= 0 < "
            f"opening <= 45; got {c.jaw_pitch_limits_deg}. The default is (-4, 18); (-4, 28) "
            f"opens the anatomical range."
        )
    qlo, qhi = (float(x) for x in c.jaw_protrusion_limits_mm)
    if not (np.isfinite([qlo, qhi]).all() and -10.0 <= qlo <= 0.0 < qhi <= 20.0):
        raise RigError(
            f"jaw_protrusion_limits_mm must be (retrusion, protrusion) mm with -10 <= "
            f"retrusion <= 0 < protrusion <= 20; got {c.jaw_protrusion_limits_mm}. The "
            f"default is {PROTRUSION_LIMITS_MM}."
        )
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
    specs, controls, names = muscle_controls(muscle_map)
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
    eyelids = eyelid_regions(mesh, frame, controls, placed, eyelid_threshold)
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
    jaw = JawModel.from_landmarks(frame, pitch_limits=(plo, phi), protrusion_limits=(qlo, qhi))
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
