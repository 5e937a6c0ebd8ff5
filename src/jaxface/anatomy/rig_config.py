"""The options of the PBD face rig (:class:`PBDRigConfig`) and their default constants.

:func:`jaxface.anatomy.rig.build_rig` takes them as a :class:`PBDRigConfig` (``config=``) or
as keyword arguments; the LTW backend has its own :class:`jaxface.ltw.rig.LTWRigConfig`
(:mod:`jaxface.anatomy.interface`).

Units: reference mm (the face frame's scale) where a name says ``_mm``; +y up, +z forward,
subject's left +x.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from .interface import RigConfig
from .jaw import PITCH_LIMITS_DEG, PROTRUSION_LIMITS_MM
from .muscles import SHELL_STIFFNESS

__all__ = [
    "FAT_VOLUME",
    "FOOTPRINT_CLUSTER_MM",
    "FOOTPRINT_MM",
    "JAW_FOLLOW_MM",
    "PBDRigConfig",
]

JAW_FOLLOW_MM = (30.0, 100.0)
"""Default ``(full, reach)`` distances from the chin of the jaw's pull on the soft tissue,
reference mm (:func:`jaw_follow_weights`)."""

#: Default sigma of the tissue footprint, reference mm, ``(lower, upper)``: 10 mm over the
#: whole face (the pair blends from the eyes up to the brows,
#: :func:`~jaxface.anatomy.skin.footprint_sigma`). A single 5 mm let the smile fold the skin
#: over itself below the mouth corners: under the left corner the lower lip ring, pulled up
#: 15 mm by the modiolus, was followed 2-5 mm lower by skin rising 10 mm and, 2 mm lower
#: again, by skin rising 4 mm, and 30 anchor-target triangles (40 skin triangles) of AU12 on
#: the default head inverted; 6 mm still inverted 10, 7 mm and more none. The wider footprint also fits the Bosphorus-style scans better
#: (``benchmarks/bench_fit.py``, mean over the 20 expression scans): 0.821 mm with 5 mm,
#: 0.787 with 7, 0.773 with 8, 0.752 with 10 (16 scans within 1 mm, was 15) and 0.757 with
#: 14 mm, where the smiles got worse again (the last four with the eyelids' corner taper,
#: :data:`~jaxface.anatomy.skin.LID_CORNER_TAPER`). The forehead had 5 mm until the brow
#: depressor (``depressor_supercilii`` of the muscle map) came: a lowered brow drags the
#: forehead skin down with it (the ICT brow lowerer slides it 2-3 mm 20 mm above the brow),
#: and with 5 mm the skin bound to the still frontalis stayed put. 10 mm on the forehead too
#: took the brow-lowering scans from 0.395 / 0.440 mm to 0.310 / 0.392 (bs900 / bs901) and the
#: brow raisers from 0.331-0.385 to 0.313-0.348 mm; 14 mm gave 0.297 / 0.398 (measured with
#: the fitting code of ``benchmarks/bench_fit.py``, float64). The cost: the exact footprint matrix of the
#: ICT face has 3x the entries (2.9 M) and made a synthesis there 1.45x as long (65 against
#: 45 ms), which :data:`FOOTPRINT_CLUSTER_MM` mostly wins back; the lower-face muscles are
#: less distinguishable in the synthetic round trip (on the ICT face the zygomaticus major,
#: levator anguli oris and risorius have VIFs of 19-38).
FOOTPRINT_MM = (10.0, 10.0)

#: Default width of the vertex clusters the wide rows of the tissue footprint draw on,
#: reference mm (:func:`~jaxface.anatomy.skin.footprint_operator`): rows at least 1.5 cluster
#: widths wide (the 10 mm lower face) weight clusters instead of single vertices, with the
#: mean of their weights of the cluster's vertices. On the ICT face the operator has 1.16 M
#: entries instead of 2.92 M, and a synthesis takes 49.5 against 70.2 ms with the exact
#: footprint, timed side by side (``bench_synth.py --footprint-clusters 0``), 0.23 mm from it
#: at most for that benchmark's AU6 + AU12 + AU26 (0.13 mm 99th percentile). Anger, disgust,
#: fear, sadness, surprise, AU1, AU4, AU9, AU15 and AU20 stay within 0.09 mm of it; AU12
#: and happiness within 0.3 mm but for one vertex under the lower lip, 1.5 mm off (it lags
#: its neighbours by 1-2 mm with either footprint). 6 mm clusters were only 3 % faster
#: again. The mean fit error on the Bosphorus-style scans stayed 0.752 mm.
#: 0 = the exact footprint.
FOOTPRINT_CLUSTER_MM = 5.0

#: Default gain of the fat layer's volume preservation, ``(lower, upper)``
#: (:func:`~jaxface.anatomy.skin.fat_thickness`): half in the lower face, blended to none
#: from the eyes up to the brows. On the Bosphorus-style scans (``benchmarks/bench_fit.py``,
#: float64, measured before the muscle quads were split as mirror images) it lowered the mean
#: error from 0.889 to 0.854 mm (jaw opening LFAU_26 1.11 -> 0.91 mm on both subjects;
#: E_SURPRISE 0.89 -> 0.83); gains 0.35 and 0.7 gave 0.858 mm each; gain 0.5 over the whole
#: face 0.861 mm (the brow raisers got 0.02-0.07 mm worse with the forehead thickening under
#: the frontalis). 0 turns it off.
FAT_VOLUME = (0.5, 0.0)


@dataclass(frozen=True)
class PBDRigConfig(RigConfig):
    """Options of the PBD rig (``build_rig(..., backend="pbd", config=PBDRigConfig(...))``);
    every default is the rig's default.

    Attributes:
        upper_teeth, lower_teeth: teeth meshes (mm) for the lip collisions (default: the
            skull's).
        muscle_iterations, skin_iterations: static sweeps of the quasi-static solves.
        footprint_mm: sigma of the tissue footprint (reference mm), or a ``(lower, upper)``
            pair: ``lower`` up to the inner eye corners, ``upper`` from the inner eyebrows up,
            blended in between (:func:`~jaxface.anatomy.skin.footprint_sigma`; see
            :data:`FOOTPRINT_MM` for why the default is ``(10, 10)``).
        footprint_cluster_mm: width of the vertex clusters the footprint's wide rows draw on
            (reference mm, :data:`FOOTPRINT_CLUSTER_MM`); 0 = the exact footprint.
        influence_radius: influence-map falloff in normalised geodesic distance.
        eyelid_threshold: normalised geodesic distance of the eyelid region (thesis 0.04).
        bending: include the skin's dihedral bending constraints (thesis 0.95; off by default:
            with the tissue footprint they change the result by < 0.1 mm at 3x the cost).
        jaw_follow_mm: ``(full, reach)``, reference mm: the tissue attached to the skull
            follows the jaw fully within ``full`` of the chin, less further away, not at
            all beyond ``reach`` (:func:`~jaxface.anatomy.rig.jaw_follow_weights`); ``(0, 0)`` = the thesis's
            rigid split (mandible fully, cranium not at all).
        jaw_membrane: the skin under the jaw that is bound to the cranium (no bone moves it)
            takes the harmonic interpolation of the skin around it instead of following its
            bound points (:func:`~jaxface.anatomy.skin.membrane_interpolation`). It removes
            the crease folds left under the chin at wide jaw openings (78 inverted
            triangles at 18 degrees on the default head, none with it) for animation; off by
            default because it fits jaw-opening scans less well (0.07 mm on the
            Bosphorus-style LFAU_26 and E_SURPRISE scans).
        skin_chebyshev_rho: spectral-radius estimate in ``[0, 1)`` for the Chebyshev
            acceleration of the skin solve (:func:`jaxface.pbd.iterate`); 0 = plain
            sweeps (the default). With many sweeps (a converged reference, animation at
            30+ sweeps) 0.95-0.97 reaches the plain solve's fixed point in several times
            fewer sweeps; at the default 8 sweeps it changes little. There is no such option
            for the muscle solve: its re-sampled action lines make it non-linear enough that
            the accelerated iteration settled at other equilibria (up to 10 mm away on the
            ICT face) or oscillated.
        muscle_shell_stiffness: in [0, 1], stiffness of the muscles' shell constraint
            (:func:`jaxface.anatomy.muscles.shell_targets`: each muscle stays a layer lying on
            its support, shortening and bulging when it contracts). 0 gives the thesis's
            muscle, whose top sheet sheared over the bottom one (up to 130 degrees, inverted)
            and whose solve had not settled after 2,000 sweeps on the ICT face; with the
            default 1 it settles within 0.15 mm in 32 sweeps.
        fat_volume: in [0, 1], the volume preservation of the fat under the skin
            (:func:`~jaxface.anatomy.skin.fat_thickness`): where the surface points the skin
            is bound to squeeze together (a shortening muscle, the cheek ahead of a pulled
            mouth corner, the soft tissue under the chin of an opened jaw) the skin rises,
            where they spread (the lips of a widened mouth) it sinks. One value or a
            ``(lower, upper)`` pair blended like ``footprint_mm``; 0 = off; default
            :data:`FAT_VOLUME`.
        jaw_pitch_limits_deg: ``(closing, opening)`` limits of the jaw's pitch, degrees
            (:class:`~jaxface.anatomy.jaw.JawModel`; default
            :data:`~jaxface.anatomy.jaw.PITCH_LIMITS_DEG`).
        jaw_protrusion_limits_mm: ``(retrusion, protrusion)`` limits of the jaw's
            translation along its protrusion direction, mm (default
            :data:`~jaxface.anatomy.jaw.PROTRUSION_LIMITS_MM`).
    """

    backend: ClassVar[str] = "pbd"

    upper_teeth: Any = None
    lower_teeth: Any = None
    muscle_iterations: int = 32
    skin_iterations: int = 8
    footprint_mm: float | tuple = FOOTPRINT_MM
    footprint_cluster_mm: float = FOOTPRINT_CLUSTER_MM
    influence_radius: float = 0.15
    eyelid_threshold: float = 0.04
    bending: bool = False
    jaw_follow_mm: tuple[float, float] = JAW_FOLLOW_MM
    jaw_membrane: bool = False
    skin_chebyshev_rho: float = 0.0
    muscle_shell_stiffness: float = SHELL_STIFFNESS
    fat_volume: float | tuple = FAT_VOLUME
    jaw_pitch_limits_deg: tuple[float, float] = PITCH_LIMITS_DEG
    jaw_protrusion_limits_mm: tuple[float, float] = PROTRUSION_LIMITS_MM
