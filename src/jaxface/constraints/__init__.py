"""PBD constraint kinds (struct-of-arrays pytrees), their projections, and their builders.

* :mod:`~jaxface.constraints.base` - the base class and the one PBD / XPBD projection;
* :mod:`~jaxface.constraints.elastic` - stretch, bending, area (eqs. 3.15-3.21);
* :mod:`~jaxface.constraints.volume` - volumes of closed or capped surfaces (eq. 3.22);
* :mod:`~jaxface.constraints.position` - anchors (eq. 3.23), half-spaces, convex hulls;
* :mod:`~jaxface.constraints.build` - NumPy builders and hull planes.

The solver that projects them is :mod:`jaxface.pbd`. Units: mm, rad, 1/g.
"""

from __future__ import annotations

from .base import Constraints, safe_norm
from .build import (
    anchor_constraints,
    area_constraints,
    bending_constraints,
    distance_constraints,
    halfspace_constraints,
    hull_constraints,
    hull_planes,
    skin_constraints,
    transform_planes,
    volume_constraint,
)
from .elastic import AreaConstraints, BendingConstraints, DistanceConstraints, dihedral_angle
from .position import AnchorConstraints, HalfSpaceConstraints, HullConstraints
from .volume import VolumeConstraint

__all__ = [
    "Constraints",
    "DistanceConstraints",
    "BendingConstraints",
    "AreaConstraints",
    "VolumeConstraint",
    "AnchorConstraints",
    "HalfSpaceConstraints",
    "HullConstraints",
    "dihedral_angle",
    "safe_norm",
    "distance_constraints",
    "bending_constraints",
    "area_constraints",
    "volume_constraint",
    "anchor_constraints",
    "halfspace_constraints",
    "hull_constraints",
    "skin_constraints",
    "hull_planes",
    "transform_planes",
]
