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

Layout: :mod:`.muscle_system` (parameters, data, volumes), :mod:`.muscle_build` (build time),
:mod:`.muscle_targets` (run time: targets, sweep, solve); every name is re-exported here.
"""

from __future__ import annotations

from .muscle_build import _ring_end as _ring_end
from .muscle_build import build_muscle_system
from .muscle_system import DISTANCE_GROUP as DISTANCE_GROUP
from .muscle_system import MODIOLUS_GAIN as MODIOLUS_GAIN
from .muscle_system import MODIOLUS_MAX_OFFSET_MM as MODIOLUS_MAX_OFFSET_MM
from .muscle_system import MODIOLUS_SIGMA_MM as MODIOLUS_SIGMA_MM
from .muscle_system import POSITION_STIFFNESS as POSITION_STIFFNESS
from .muscle_system import (
    SHELL_STIFFNESS,
    STIFFNESS,
    THICKENING_RANGE,
    MuscleSystem,
    SupportPoints,
    muscle_volumes,
)
from .muscle_system import PendingMuscles as PendingMuscles
from .muscle_targets import fibre_thickening as fibre_thickening
from .muscle_targets import moved_skull_points as moved_skull_points
from .muscle_targets import muscle_sweep as muscle_sweep
from .muscle_targets import sample_targets as sample_targets
from .muscle_targets import shell_targets, solve_muscles
from .muscle_targets import warm_start as warm_start

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
