"""Builders of the constraint kinds from NumPy arrays (build time), and hull planes.

Thin wrappers with the thesis's names (sec. 3.2, 5.5); all re-exported by :mod:`jaxface.pbd`.
Units: mm, rad, mm^2, mm^3.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from scipy.spatial import ConvexHull, QhullError

from ..errors import MeshError
from ..mesh import TriMesh
from .base import Constraints
from .elastic import AreaConstraints, BendingConstraints, DistanceConstraints
from .position import AnchorConstraints, HalfSpaceConstraints, HullConstraints
from .volume import VolumeConstraint

__all__ = [
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


def distance_constraints(
    pairs, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None
):
    """Stretch constraints (eq. 3.15). See :meth:`DistanceConstraints.build`.

    Args:
        pairs: ``(M, 2)`` int particle ids.
        x_rest: ``(N, 3)`` mm rest positions (rest lengths measured there).
        rest: ``(M,)`` mm rest lengths, instead of ``x_rest``.
        stiffness: ``k`` in ``[0, 1]`` (scalar or ``(M,)``).
        compliance: XPBD compliance, ``None`` for PBD.
    """
    return DistanceConstraints.build(
        pairs, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def bending_constraints(
    edge_pairs, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None
):
    """Dihedral bending constraints (eq. 3.20) on ``(M, 4)`` rows ``[a, b, c, d]``
    (:attr:`jaxface.mesh.TriMesh.edge_pairs`); rest angles (rad) measured on ``x_rest`` (mm)."""
    return BendingConstraints.build(
        edge_pairs, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def area_constraints(
    triangles, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None
):
    """Triangle area constraints (eq. 3.21); rest areas (mm^2) measured on ``x_rest`` (mm)."""
    return AreaConstraints.build(
        triangles, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def volume_constraint(
    triangles,
    x_rest=None,
    *,
    rest=None,
    origin=None,
    owner=None,
    stiffness: ArrayLike = 1.0,
    compliance=None,
):
    """Volume constraints (eq. 3.22) of closed or capped surfaces, one per body (``owner``
    ``(F,)`` gives each triangle's body; default one); ``rest`` mm^3 (default: measured on
    ``x_rest``), ``origin`` mm cap point. See :class:`VolumeConstraint`."""
    return VolumeConstraint.build(
        triangles,
        x_rest,
        rest=rest,
        origin=origin,
        owner=owner,
        stiffness=stiffness,
        compliance=compliance,
    )


def anchor_constraints(indices, targets, *, stiffness: ArrayLike = 1.0, compliance=None):
    """Position constraints (eq. 3.23) of particles ``(M,)`` to targets ``(M, 3)`` mm; move
    the targets at run time with ``system.set(name, target=...)``."""
    return AnchorConstraints.build(indices, targets, stiffness=stiffness, compliance=compliance)


def halfspace_constraints(
    indices, normals, offsets, *, stiffness: ArrayLike = 1.0, compliance=None
):
    """Unilateral plane constraints ``n . p >= d`` (mm) for particles ``(M,)``."""
    return HalfSpaceConstraints.build(
        indices, normals, offsets, stiffness=stiffness, compliance=compliance
    )


def hull_constraints(
    indices, normals, offsets, *, clearance=0.0, stiffness: ArrayLike = 1.0, compliance=None
):
    """Convex-hull collision for particles ``(M,)`` against the planes ``(H, 3)``, ``(H,)`` mm
    of one convex hull (:func:`hull_planes`); run-time planes via ``system.set(name,
    normals=..., offsets=...)`` (:func:`transform_planes` for a hull moving with the jaw)."""
    return HullConstraints.build(
        indices, normals, offsets, clearance=clearance, stiffness=stiffness, compliance=compliance
    )


def hull_planes(points) -> tuple[np.ndarray, np.ndarray]:
    """Planes of the convex hull of a point set (NumPy, build time).

    Args:
        points: ``(K, 3)`` mm, at least 4 points not all coplanar (e.g. teeth vertices).

    Returns:
        ``(normals (H, 3), offsets (H,))``: outward unit normals and offsets in mm; the hull is
        ``{q : normals @ q <= offsets}``. Coplanar facets are merged.

    Raises:
        MeshError: fewer than 4 points, or all coplanar.
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 4:
        raise MeshError(
            f"hull_planes needs (K, 3) points with K >= 4, got {p.shape}.", problem="shape"
        )
    try:
        h = ConvexHull(p)
    except QhullError as err:  # flat or degenerate input
        raise MeshError(
            f"cannot build a convex hull of {p.shape[0]} points (coplanar or degenerate): "
            f"{str(err).splitlines()[0]}",
            problem="degenerate_hull",
        ) from err
    eq = h.equations  # n . x + c <= 0 inside
    scale = float(np.ptp(p, axis=0).max())
    key = np.round(np.concatenate([eq[:, :3], eq[:, 3:] / scale], 1) * 1e9).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    eq = eq[np.sort(first)]
    return eq[:, :3].copy(), -eq[:, 3].copy()


def transform_planes(normals, offsets, rotation, translation):
    """Planes after the rigid motion ``q' = R q + t`` (JAX, differentiable).

    Args:
        normals: ``(H, 3)`` unit normals; offsets: ``(H,)`` mm.
        rotation: ``(3, 3)`` rotation matrix; translation: ``(3,)`` mm.

    Returns:
        ``(normals' (H, 3), offsets' (H,) mm)`` of the moved hull.
    """
    n = jnp.asarray(normals) @ jnp.asarray(rotation).T
    return n, jnp.asarray(offsets) + n @ jnp.asarray(translation)


def skin_constraints(
    mesh,
    triangles=None,
    *,
    stretch=0.15,
    cross=None,
    bend=0.95,
    area=0.95,
    volume=1.0,
    origin=None,
    compliance=None,
) -> dict[str, Constraints]:
    """The thesis's skin constraint set (sec. 5.5): stretch along every edge, stretch between
    the opposite vertices of adjacent triangles, bending on every interior edge, area on every
    triangle and one volume constraint, rest values measured on the mesh.

    Args:
        mesh: a :class:`jaxface.mesh.TriMesh`, or ``(V, 3)`` mm vertices with ``triangles``.
        triangles: ``(F, 3)`` int when ``mesh`` is a vertex array.
        stretch, cross, bend, area, volume: stiffness of each kind (thesis values 0.15, 0.15,
            0.95, 0.95, 1.0; ``cross`` defaults to ``stretch``); ``None`` or 0 leaves the kind
            out.
        origin: ``(3,)`` mm cap point of the volume (see :class:`VolumeConstraint`).
        compliance: optional dict kind -> XPBD compliance (e.g. ``{"stretch": 1e-6}``).

    Returns:
        dict with keys ``"stretch"``, ``"cross"``, ``"bend"``, ``"area"``, ``"volume"`` (those
        enabled), ready for :func:`build_system`.
    """
    if not isinstance(mesh, TriMesh):
        mesh = TriMesh(mesh, triangles)
    x = mesh.vertices
    comp = dict(compliance or {})
    cross = stretch if cross is None else cross
    out: dict[str, Constraints] = {}
    if stretch:
        out["stretch"] = distance_constraints(
            mesh.edges, x, stiffness=stretch, compliance=comp.get("stretch")
        )
    pairs = mesh.edge_pairs
    if cross and len(pairs):
        out["cross"] = distance_constraints(
            pairs[:, 2:], x, stiffness=cross, compliance=comp.get("cross")
        )
    if bend and len(pairs):
        out["bend"] = bending_constraints(pairs, x, stiffness=bend, compliance=comp.get("bend"))
    if area:
        out["area"] = area_constraints(
            mesh.triangles, x, stiffness=area, compliance=comp.get("area")
        )
    if volume:
        out["volume"] = volume_constraint(
            mesh.triangles, x, origin=origin, stiffness=volume, compliance=comp.get("volume")
        )
    return out
