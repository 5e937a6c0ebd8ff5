"""Position and contact PBD constraint kinds: anchors (eq. 3.23), half-spaces, convex hulls.

============================  ==========================================================  =====
kind                          ``C`` (satisfied when ``C = 0``, unilateral: ``C >= 0``)     unit
============================  ==========================================================  =====
:class:`AnchorConstraints`    ``p - t`` per axis; ``|p - t|`` reported (eq. 3.23)         mm
:class:`HalfSpaceConstraints` ``n . p - d >= 0``                                          mm
:class:`HullConstraints`      ``max_h (n_h . p - d_h) - clearance >= 0``                  mm
============================  ==========================================================  =====

Targets and planes are run-time inputs: ``group.set(target=t)``,
``group.set(normals=n, offsets=d)`` (also on traced values, inside ``jax.jit``).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._arrays import to_jax
from ..errors import MeshError
from .base import Constraints, _as_float, _base_fields, _check_indices, _dot, _unit_rows, safe_norm

__all__ = ["AnchorConstraints", "HalfSpaceConstraints", "HullConstraints"]


class AnchorConstraints(Constraints):
    """Position constraints binding particles to targets ``t`` (eq. 3.23), targets movable at
    run time (fixed points, or surface points evaluated on another mesh every step).

    Projected per axis (``C = p - t``, three linear constraints with unit gradients): for PBD
    this is exactly the correction of 3.23, ``dp = -k (p - t)``; for XPBD it has the same
    energy ``|p - t|^2 / (2 alpha)`` and no normalisation singularity at ``p = t``. Anchors on
    kinematic particles (inverse mass 0) do nothing: move those directly.

    Attributes:
        target: ``(M, 3)`` mm target positions.
    """

    target: jax.Array

    arity: ClassVar[int] = 1
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance", "target")

    @classmethod
    def build(cls, indices, targets, *, stiffness: ArrayLike = 1.0, compliance=None):
        """Build from ``(M,)`` particle ids and ``(M, 3)`` mm targets (compliance in
        ``mm^2 / energy``)."""
        idx = _check_indices(np.asarray(indices).reshape(-1, 1), 1, "anchor")
        t = _as_float(targets, name="anchor targets")
        if t.shape != (idx.shape[0], 3):
            raise MeshError(
                f"anchor targets must be ({idx.shape[0]}, 3) mm, got {t.shape}.",
                problem="shape",
            )
        return cls(target=to_jax(t), **_base_fields(idx, stiffness, compliance, "anchor"))

    def lambda_shape(self):
        return (3, self.size)

    def values(self, x):
        """``(M,)`` mm distances ``|p - t|`` (eq. 3.23)."""
        p = self._gather_all(x)[0].T
        return safe_norm(p - self.target)

    def violation(self, x):
        return self.values(x)

    def correction(self, P, W, alpha_t=None, lam=None):
        """Anchor correction per axis (``C = p - t``, unit gradients): PBD ``dp = -k (p - t)``
        (eq. 3.23); XPBD ``dlambda = k (-C - a lambda) / (w + a)``, ``dp = w dlambda``.

        Args: ``P`` one ``(3, m)`` mm; ``W`` one ``(m,)``; ``alpha_t`` ``(m,)`` or ``None``;
        ``lam`` ``(3, m)``. Returns ``([dp (3, m) mm], dlambda (3, m) or None)``.
        """
        C = P[0] - self.target.T
        k = self.stiffness
        w = W[0]
        if alpha_t is None:
            return [jnp.where(w > 0, -k * C, 0.0)], None
        den = w + alpha_t
        ok = den > 0
        dlam = jnp.where(ok, k * (-C - alpha_t * lam) / jnp.where(ok, den, 1.0), 0.0)
        return [w * dlam], dlam


class HalfSpaceConstraints(Constraints):
    """Unilateral plane constraints ``n . p - d >= 0`` (particle stays on the side ``n``
    points to). Planes are run-time inputs (``set(normal=..., offset=...)``).

    Attributes:
        normal: ``(M, 3)`` unit normals (normalised inside the kernel).
        offset: ``(M,)`` mm plane offsets ``d``.
    """

    normal: jax.Array
    offset: jax.Array

    arity: ClassVar[int] = 1
    unilateral: ClassVar[bool] = True
    per_constraint: ClassVar[tuple[str, ...]] = (
        "stiffness",
        "compliance",
        "normal",
        "offset",
    )

    @classmethod
    def build(cls, indices, normals, offsets, *, stiffness: ArrayLike = 1.0, compliance=None):
        """Build from ``(M,)`` particle ids, ``(M, 3)`` (or ``(3,)``) normals and ``(M,)`` (or
        scalar) mm offsets."""
        idx = _check_indices(np.asarray(indices).reshape(-1, 1), 1, "half-space")
        m = idx.shape[0]
        n = _as_float(normals, (m, 3), "half-space normals")
        nn = np.linalg.norm(n, axis=1)
        bad = np.flatnonzero(nn < 1e-12)
        if bad.size:
            raise MeshError(
                f"half-space constraints {bad[:10].tolist()} have zero normals.",
                problem="zero_normal",
                elements=bad[:100],
            )
        d = _as_float(offsets, (m,), "half-space offsets")
        return cls(
            normal=to_jax(n / nn[:, None]),
            offset=to_jax(d),
            **_base_fields(idx, stiffness, compliance, "half-space"),
        )

    def terms(self, P):
        p = P[0]
        n = _unit_rows(self.normal).T
        C = _dot(n, p) - self.offset
        return C, (n,), (_dot(n, n),)


class HullConstraints(Constraints):
    """Unilateral convex-hull collision: a particle inside the convex polytope
    ``{q : n_h . q <= d_h for all h}`` is pushed out through the face of least penetration.

    ``C = max_h (n_h . p - d_h) - clearance >= 0`` with gradient ``n_{h*}`` (``h*`` the arg
    max). The hull planes are one run-time input shared by the group (set them every step
    for a hull that moves with the jaw: :func:`jaxface.pbd.transform_planes`).

    Attributes:
        normals: ``(H, 3)`` outward unit normals.
        offsets: ``(H,)`` mm.
        clearance: ``(M,)`` mm extra distance kept from the hull (0 = touch the surface).
    """

    normals: jax.Array
    offsets: jax.Array
    clearance: jax.Array

    arity: ClassVar[int] = 1
    unilateral: ClassVar[bool] = True
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance", "clearance")

    @classmethod
    def build(
        cls,
        indices,
        normals,
        offsets,
        *,
        clearance=0.0,
        stiffness: ArrayLike = 1.0,
        compliance=None,
    ):
        """Build from ``(M,)`` particle ids and the hull planes ``(H, 3)`` / ``(H,)`` mm (see
        :func:`jaxface.pbd.hull_planes`)."""
        idx = _check_indices(np.asarray(indices).reshape(-1, 1), 1, "hull")
        m = idx.shape[0]
        n = _as_float(normals, name="hull normals")
        if n.ndim != 2 or n.shape[1] != 3 or n.shape[0] < 4:
            raise MeshError(
                f"hull normals must be (H, 3) with H >= 4 planes, got {n.shape}.",
                problem="shape",
            )
        d = _as_float(offsets, (n.shape[0],), "hull offsets")
        nn = np.linalg.norm(n, axis=1)
        if np.any(nn < 1e-12):
            raise MeshError("hull has zero-length plane normals.", problem="zero_normal")
        c = _as_float(clearance, (m,), "hull clearance")
        return cls(
            normals=to_jax(n / nn[:, None]),
            offsets=to_jax(d),
            clearance=to_jax(c),
            **_base_fields(idx, stiffness, compliance, "hull"),
        )

    def terms(self, P):
        p = P[0]
        N = _unit_rows(self.normals)  # (H, 3)
        sd = N @ p - self.offsets[:, None]  # (H, m) signed distances to the planes
        top = jnp.max(sd, axis=0)
        # normal of the nearest plane as a one-hot product (XLA's CPU argmax over the planes
        # took twice as long as the rest of the projection); on a hull edge (equal distances
        # to two planes) their normals are averaged
        hit = (sd >= top[None]).astype(p.dtype)
        n = (N.T @ hit) / jnp.sum(hit, axis=0)[None]
        C = top - self.clearance
        return C, (n,), (_dot(n, n),)
