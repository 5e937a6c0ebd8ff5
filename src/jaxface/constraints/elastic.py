"""Elastic PBD constraint kinds: stretch (eq. 3.15), bending (eq. 3.20), area (eq. 3.21).

============================  ==========================================================  =====
kind                          ``C`` (satisfied when ``C = 0``)                            unit
============================  ==========================================================  =====
:class:`DistanceConstraints`  ``|p1 - p2| - d`` (eq. 3.15)                                mm
:class:`BendingConstraints`   signed dihedral angle ``wrap(theta - theta0)`` (eq. 3.20)   rad
:class:`AreaConstraints`      ``|(p2 - p1) x (p3 - p1)| / 2 - A0`` (eq. 3.21)              mm^2
============================  ==========================================================  =====

Robustness: a degenerate constraint (zero-length edge, zero-area triangle, a dihedral with a
zero-area face or zero-length hinge, coincident particles) has ``C = 0`` and zero gradient, i.e.
it is skipped; square roots and divisions are guarded with the double-``where`` trick so that
neither values nor derivatives become NaN. The bending angle is the *signed* dihedral angle from
``atan2(sin, cos)`` (``0`` when flat, ``+-pi`` when folded) rather than the thesis's ``arccos``
of eq. 3.20, whose gradient is singular exactly at the flat rest configuration of a smooth skin.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._arrays import to_jax
from ..errors import MeshError
from .base import (
    Constraints,
    _as_float,
    _base_fields,
    _check_indices,
    _cross,
    _dot,
    _safe_sqrt,
    _tiny,
)

__all__ = [
    "DistanceConstraints",
    "BendingConstraints",
    "AreaConstraints",
    "dihedral_angle",
    "REST_HINGE_PRECISION",
]


def dihedral_angle(a, b, c, d):
    """Signed dihedral angle of the triangles ``(a, b, c)`` and ``(b, a, d)`` about edge ``a-b``.

    Args:
        a, b: ``(..., 3)`` mm, the shared edge.
        c, d: ``(..., 3)`` mm, the vertices opposite the edge in the two triangles.

    Returns:
        ``(...)`` rad in ``(-pi, pi]``: 0 when the two (consistently oriented) triangles are
        coplanar and unfolded, ``+-pi`` when folded onto each other; 0 (with zero gradient)
        for a degenerate configuration. Positive when ``d`` lies on the side ``n1`` points to.
    """
    P = [jnp.moveaxis(jnp.asarray(q), -1, 0) for q in (a, b, c, d)]
    theta, *_ = _bend_geometry(*P)
    return theta


def _hinge_ok(L2, n1s, n2s, w1s, w2s, r):
    """Non-degenerate hinges: a shared edge (squared length ``L2``) and two wings (squared
    lengths ``w1s = |c - a|^2``, ``w2s = |d - b|^2``, normals ``|n|^2 = n1s, n2s``) that are
    not negligible relative to each other, at relative precision ``r`` (squared ratios).

    Scale-free on purpose: an absolute threshold (``eps^2`` mm^2) let a hinge whose edge had
    collapsed to 4e-7 mm next to 5 mm wings through, and the reverse pass of its projection
    (squared gradients of ~1e7 / mm) overflowed float32 into NaN. The wings are judged against
    the edge too: a wing collapsed onto an end of the edge (two particles on one point, 1e-7 mm
    apart beside a 5 mm edge) passes the normal tests, its normal pointing wherever rounding
    puts it, and the float32 reverse pass through the default head's rig at rest came out NaN.
    """
    # a zero edge or zero wings fail the normal tests (0 > 0), so no absolute floor is needed
    return (
        (L2 > r * (w1s + w2s))
        & (w1s > r * L2)
        & (w2s > r * L2)
        & (n1s > r * L2 * w1s)
        & (n2s > r * L2 * w2s)
    )


def _bend_geometry(a, b, c, d):
    """theta (m,), ok mask, and the pieces for the gradient, for (3, m) inputs.

    ``ok`` is False (theta 0, zero gradient) for a degenerate hinge (:func:`_hinge_ok` at
    the precision ``eps`` of the dtype: an edge shorter than ``sqrt(eps)`` times the wings,
    or a wing within ``sqrt(eps)`` rad of the edge's line).
    """
    r = float(jnp.finfo(a.dtype).eps)
    e = b - a
    ca = c - a
    db = d - b
    n1 = _cross(e, ca)
    n2 = _cross(a - b, db)
    L2 = _dot(e, e)
    n1s = _dot(n1, n1)
    n2s = _dot(n2, n2)
    ok = _hinge_ok(L2, n1s, n2s, _dot(ca, ca), _dot(db, db), r)
    L = _safe_sqrt(L2, ok)
    y = _dot(_cross(n1, n2), e)
    xx = L * _dot(n1, n2)
    theta = jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, xx, 1.0))
    return theta, ok, e, L, n1, n2, n1s, n2s


def _wrap(angle):
    """Wrap an angle (rad) to ``[-pi, pi]`` (derivative 1): ``angle - 2 pi round(angle / 2 pi)``."""
    two_pi = 2.0 * jnp.pi
    return angle - two_pi * jax.lax.stop_gradient(jnp.round(angle / two_pi))


# ----------------------------------------------------------------------------------------
# distance / stretch (3.15 - 3.19)
# ----------------------------------------------------------------------------------------


class DistanceConstraints(Constraints):
    """Stretch constraints ``|p1 - p2| = d`` (eq. 3.15); corrections 3.16-3.19.

    Attributes:
        rest: ``(M,)`` mm rest lengths ``d``.
    """

    rest: jax.Array

    arity: ClassVar[int] = 2
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance", "rest")

    @classmethod
    def build(cls, pairs, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None):
        """Build from particle pairs.

        Args:
            pairs: ``(M, 2)`` int particle ids (mesh edges, or the opposite vertices of
                ``edge_pairs`` for cross-edge stretch).
            x_rest: ``(N, 3)`` mm rest positions (rest lengths measured there), or ``None``
                when ``rest`` is given.
            rest: ``(M,)`` mm rest lengths (overrides ``x_rest``).
            stiffness: ``k`` in ``[0, 1]``, scalar or ``(M,)``.
            compliance: XPBD compliance (``mm^2 / energy``), scalar or ``(M,)``; ``None`` = PBD.
        """
        idx = _check_indices(pairs, 2, "distance")
        if rest is None:
            if x_rest is None:
                raise MeshError("distance constraints need x_rest or rest.", problem="shape")
            x = _as_float(x_rest, name="x_rest")
            rest = np.linalg.norm(x[idx[:, 0]] - x[idx[:, 1]], axis=1)
        rest = _as_float(rest, (idx.shape[0],), "distance rest")
        return cls(rest=to_jax(rest), **_base_fields(idx, stiffness, compliance, "distance"))

    def terms(self, P):
        d = P[0] - P[1]
        l2 = _dot(d, d)
        ok = l2 > _tiny(d.dtype)
        inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, l2, 1.0)), 0.0)
        n = d * inv
        C = jnp.where(ok, l2 * inv - self.rest, 0.0)
        g2 = ok.astype(d.dtype)
        return C, (n, -n), (g2, g2)


# ----------------------------------------------------------------------------------------
# bending (3.20, signed and robust)
# ----------------------------------------------------------------------------------------


class BendingConstraints(Constraints):
    """Dihedral-angle bending ``theta(p1, p2, p3, p4) = theta0`` (eq. 3.20).

    Rows are ``[a, b, c, d]`` as in :attr:`jaxface.mesh.TriMesh.edge_pairs`: ``(a, b)`` the
    shared edge, ``(a, b, c)`` and ``(b, a, d)`` the two triangles. ``theta`` is the signed
    dihedral angle (:func:`dihedral_angle`), ``C = wrap(theta - theta0)`` in rad.

    Attributes:
        rest: ``(M,)`` rad rest angles ``theta0``.
    """

    rest: jax.Array

    arity: ClassVar[int] = 4
    unit: ClassVar[str] = "rad"
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance", "rest")

    @classmethod
    def build(
        cls, edge_pairs, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None
    ):
        """Build from ``(M, 4)`` edge pairs; rest angles from ``x_rest`` ``(N, 3)`` mm or
        ``rest`` ``(M,)`` rad. ``stiffness`` / ``compliance`` as in
        :meth:`DistanceConstraints.build` (compliance in ``rad^2 / energy``)."""
        idx = _check_indices(edge_pairs, 4, "bending")
        if rest is None:
            if x_rest is None:
                raise MeshError("bending constraints need x_rest or rest.", problem="shape")
            x = _as_float(x_rest, name="x_rest")
            rest = _np_dihedral(x, idx)
            # a hinge degenerate at rest (e.g. two particles of a muscle ring placed on the
            # same surface point) has no rest angle: it is kept, inert (stiffness 0)
            flat = ~_np_hinge_ok(x, idx)
            if flat.any():
                k = np.broadcast_to(np.asarray(stiffness, np.float64), (idx.shape[0],)).copy()
                k[flat] = 0.0
                stiffness = k
        rest = _as_float(rest, (idx.shape[0],), "bending rest")
        return cls(rest=to_jax(rest), **_base_fields(idx, stiffness, compliance, "bending"))

    def terms(self, P):
        a, b, c, d = P
        theta, ok, edge, L, n1, n2, n1s, n2s = _bend_geometry(a, b, c, d)
        okf = ok.astype(a.dtype)
        q1 = n1 * (okf / jnp.where(ok, n1s, 1.0))
        q2 = n2 * (okf / jnp.where(ok, n2s, 1.0))
        invL = okf / jnp.where(ok, L, 1.0)
        # d theta / dp: the negated hinge modes of Bridson et al. 2003
        gc = -L * q1
        gd = -L * q2
        ga = -(_dot(c - b, edge) * invL * q1 + _dot(d - b, edge) * invL * q2)
        gb = _dot(c - a, edge) * invL * q1 + _dot(d - a, edge) * invL * q2
        C = jnp.where(ok, _wrap(theta - self.rest), 0.0)
        grads = (ga, gb, gc, gd)
        return C, grads, tuple(_dot(g, g) for g in grads)


#: Relative precision (squared length ratio) below which a rest hinge counts as degenerate
#: at build time: float32's eps, so that a hinge the float32 solve treats as degenerate is
#: never given a rest angle.
REST_HINGE_PRECISION = float(np.finfo(np.float32).eps)


def _np_hinge_ok(x, idx) -> np.ndarray:
    """``(M,)`` bool: the rest hinges ``x[idx]`` are not degenerate (:func:`_hinge_ok`)."""
    a, b, c, d = (np.asarray(x, np.float64)[idx[:, k]] for k in range(4))
    e, ca, db = b - a, c - a, d - b
    n1 = np.cross(e, ca)
    n2 = np.cross(a - b, db)
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    return _hinge_ok(
        dot(e, e), dot(n1, n1), dot(n2, n2), dot(ca, ca), dot(db, db), REST_HINGE_PRECISION
    )


def _np_dihedral(x, idx):
    a, b, c, d = (x[idx[:, k]] for k in range(4))
    e = b - a
    n1 = np.cross(e, c - a)
    n2 = np.cross(a - b, d - b)
    L = np.linalg.norm(e, axis=1)
    y = np.einsum("ij,ij->i", np.cross(n1, n2), e)
    xx = L * np.einsum("ij,ij->i", n1, n2)
    return np.arctan2(y, xx)


# ----------------------------------------------------------------------------------------
# triangle area (3.21)
# ----------------------------------------------------------------------------------------


class AreaConstraints(Constraints):
    """Triangle area preservation ``|(p2 - p1) x (p3 - p1)| / 2 = A0`` (eq. 3.21).

    Attributes:
        rest: ``(M,)`` mm^2 rest areas ``A0``.
    """

    rest: jax.Array

    arity: ClassVar[int] = 3
    unit: ClassVar[str] = "mm^2"
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance", "rest")

    @classmethod
    def build(
        cls, triangles, x_rest=None, *, rest=None, stiffness: ArrayLike = 1.0, compliance=None
    ):
        """Build from ``(M, 3)`` triangles; rest areas from ``x_rest`` ``(N, 3)`` mm or
        ``rest`` ``(M,)`` mm^2 (compliance in ``mm^4 / energy``)."""
        idx = _check_indices(triangles, 3, "area")
        if rest is None:
            if x_rest is None:
                raise MeshError("area constraints need x_rest or rest.", problem="shape")
            x = _as_float(x_rest, name="x_rest")
            n = np.cross(x[idx[:, 1]] - x[idx[:, 0]], x[idx[:, 2]] - x[idx[:, 0]])
            rest = 0.5 * np.linalg.norm(n, axis=1)
        rest = _as_float(rest, (idx.shape[0],), "area rest")
        return cls(rest=to_jax(rest), **_base_fields(idx, stiffness, compliance, "area"))

    def terms(self, P):
        a, b, c = P
        n = _cross(b - a, c - a)
        n2 = _dot(n, n)
        ok = n2 > _tiny(a.dtype)
        inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, n2, 1.0)), 0.0)
        nh = n * inv
        C = jnp.where(ok, 0.5 * n2 * inv - self.rest, 0.0)
        ga = 0.5 * _cross(nh, c - b)
        gb = 0.5 * _cross(nh, a - c)
        gc = 0.5 * _cross(nh, b - a)
        grads = (ga, gb, gc)
        return C, grads, tuple(_dot(g, g) for g in grads)
