"""Lee-Terzopoulos-Waters (SIGGRAPH 95) layered mass-spring tissue: a second simulation backend.

Units: millimetres for positions and lengths (+y up, face along +z, subject's left +x); forces in
the paper's model units (stiffness = force per mm).

* :mod:`.tissue` builds the 9-node prism elements (epidermis / fascia / skull layers) from any
  skin mesh, with the four spring families and the paper's stiffness values;
* :mod:`.forces` spring, volume-preservation, restoration and skull non-penetration forces;
* :mod:`.waters` Waters linear and piecewise-linear (sphincter) muscles;
* :mod:`.integrate` the paper's semi-implicit Euler dynamics and a quasi-static solve;
* :mod:`.rig` the backend: ``build_ltw_rig(skin, landmarks, ...)`` and ``synthesize``.
"""

from __future__ import annotations

from .forces import (
    element_volumes,
    internal_forces,
    prism_volume,
    remove_inward,
    skull_gate,
    spring_forces,
    volume_forces,
)
from .integrate import (
    LTWModel,
    LTWState,
    make_model,
    quasi_static_constants,
    relax,
    residual,
    rest_state,
    simulate,
    total_forces,
)
from .tissue import LTWParams, LTWTissue, build_tissue
from .waters import (
    Fibre,
    WatersMuscles,
    build_waters,
    linear_fibre,
    muscle_forces,
    sheet_fibres,
    sphincter_fibres,
    theta1,
    theta2,
)

__all__ = [
    "LTWParams",
    "LTWTissue",
    "build_tissue",
    "spring_forces",
    "volume_forces",
    "element_volumes",
    "prism_volume",
    "internal_forces",
    "skull_gate",
    "remove_inward",
    "Fibre",
    "WatersMuscles",
    "build_waters",
    "linear_fibre",
    "sheet_fibres",
    "sphincter_fibres",
    "theta1",
    "theta2",
    "muscle_forces",
    "LTWModel",
    "LTWState",
    "make_model",
    "quasi_static_constants",
    "relax",
    "residual",
    "rest_state",
    "simulate",
    "total_forces",
]
