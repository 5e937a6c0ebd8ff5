"""PBD constraint kinds: struct-of-arrays pytrees and their projection kernels (JAX).

Every kind is an :class:`equinox.Module` holding, for ``M`` constraints of that kind, the
particle ids, the rest values, the stiffness ``k`` in ``[0, 1]`` (thesis sec. 3.2.1: the
correction is multiplied by ``k``) and optionally an XPBD compliance ``alpha`` (Macklin et al.
2016). Everything that is a float array is a pytree leaf and can be differentiated (rest values,
stiffness, compliance, anchor targets, collision planes). The user-facing order of the
constraints is the order given to the builder; internally :func:`jaxface.pbd.build_system`
sorts them by graph colour (``perm``) and :meth:`Constraints.set` / :meth:`Constraints.values`
translate between the two orders.

Constraint functions ``C`` and gradients (units in brackets, ``p`` in mm):

============================  ==========================================================  =====
kind                          ``C`` (satisfied when ``C = 0``, unilateral: ``C >= 0``)     unit
============================  ==========================================================  =====
:class:`DistanceConstraints`  ``|p1 - p2| - d`` (eq. 3.15)                                mm
:class:`BendingConstraints`   signed dihedral angle ``theta - theta0`` (eq. 3.20)         rad
:class:`AreaConstraints`      ``|(p2 - p1) x (p3 - p1)| / 2 - A0`` (eq. 3.21)              mm^2
:class:`VolumeConstraint`     ``sum_t ((pa-o) x (pb-o)) . (pc-o) / 6 - V0`` (eq. 3.22)     mm^3
:class:`AnchorConstraints`    ``p - t`` per axis; ``|p - t|`` reported (eq. 3.23)         mm
:class:`HalfSpaceConstraints` ``n . p - d >= 0``                                          mm
:class:`HullConstraints`      ``max_h (n_h . p - d_h) - clearance >= 0``                  mm
============================  ==========================================================  =====

Projection (thesis eqs. 3.11-3.14, with XPBD as an option): with inverse masses ``w_i`` and
gradients ``g_i = dC/dp_i``, ``s = sum_i w_i |g_i|^2``;
PBD: ``dlambda = -k C / s``; XPBD: ``dlambda = k (-C - a lambda) / (s + a)``, ``a = alpha / dt^2``,
``lambda += dlambda`` (for XPBD ``k`` only relaxes, it does not change the equilibrium); then
``p_i += w_i g_i dlambda``. Unilateral constraints are skipped when ``C >= 0`` (XPBD: the
accumulated ``lambda`` is clamped at 0).

Robustness: a degenerate constraint (zero-length edge, zero-area triangle, a dihedral with a
zero-area face or zero-length hinge, coincident particles) has ``C = 0`` and zero gradient, i.e.
it is skipped for that projection; square roots and divisions are guarded with the double-
``where`` trick so that neither values nor derivatives (``jax.grad``, ``jax.jvp``) become NaN.
The bending angle is the *signed* dihedral angle from ``atan2(sin, cos)`` (``0`` when flat,
``+-pi`` when folded) rather than the thesis's ``arccos`` of eq. 3.20, whose gradient is
singular exactly at the flat rest configuration of a smooth skin.

Geometry inside kernels is structure-of-arrays: a point set of ``m`` points is a ``(3, m)``
array (``x``, ``y``, ``z`` rows), which vectorises best on CPU.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import to_jax
from .errors import MeshError

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
]


# ----------------------------------------------------------------------------------------
# (3, m) vector helpers
# ----------------------------------------------------------------------------------------


def _dot(a, b):
    # written out elementwise (not jnp.sum(a * b, axis=0)): a reduction is its own XLA kernel,
    # and on the CPU the launch of ~200 small kernels dominated a muscle bending projection
    # (4,314 constraints: 0.38 -> 0.27 ms per sweep; ICT skin stretch and area groups 10-20%
    # faster; the coloured Gauss-Seidel of jaxface.pbd unchanged, measured)
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _tiny(dtype) -> float:
    """Squared-length threshold (mm^2) below which a length counts as zero: ``eps(dtype)^2``."""
    eps = float(jnp.finfo(dtype).eps)
    return eps * eps


def _safe_sqrt(s, ok):
    """``sqrt(s)`` where ``ok`` else 0, with finite derivatives everywhere (double where)."""
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, s, 1.0)), 0.0)


def safe_norm(v, axis: int = -1):
    """Euclidean norm with a zero (not NaN) derivative at ``v = 0``.

    Args:
        v: array of vectors (any unit), reduced over ``axis``.

    Returns:
        ``|v|`` in the unit of ``v``.
    """
    s = jnp.sum(v * v, axis=axis)
    return _safe_sqrt(s, s > _tiny(v.dtype))


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
# base class
# ----------------------------------------------------------------------------------------


def _as_float(a, shape=None, name="value"):
    arr = np.asarray(a, dtype=np.float64)
    if shape is not None:
        arr = np.broadcast_to(arr, shape).copy()
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(1)) if arr.ndim else []
        raise MeshError(
            f"{name} contains NaN or inf (constraints {list(bad[:10])}); pass finite values.",
            problem="nonfinite",
            elements=bad[:100] if len(bad) else (),
        )
    return arr


def _check_stiffness(k, name):
    bad = np.flatnonzero((k < 0) | (k > 1))
    if bad.size:
        raise MeshError(
            f"{name} stiffness must lie in [0, 1] (thesis sec. 3.2.1); constraints "
            f"{bad[:10].tolist()} have {k[bad[:3]].tolist()}. Use compliance= for XPBD "
            "material stiffness instead.",
            problem="stiffness_out_of_range",
            elements=bad[:100],
        )


def _check_compliance(a, name):
    bad = np.flatnonzero(a < 0)
    if bad.size:
        raise MeshError(
            f"{name} compliance must be >= 0 (0 = rigid); constraints {bad[:10].tolist()} "
            f"have {a[bad[:3]].tolist()}.",
            problem="negative_compliance",
            elements=bad[:100],
        )


def _check_indices(idx, arity, name):
    idx = np.asarray(idx)
    if idx.ndim == 1 and arity == 1:
        idx = idx[:, None]
    if (
        idx.ndim != 2
        or idx.shape[1] != arity
        or not (np.issubdtype(idx.dtype, np.integer) or idx.size == 0)
    ):
        raise MeshError(
            f"{name} indices must be an (M, {arity}) integer array, got shape {idx.shape} "
            f"dtype {idx.dtype}.",
            problem="shape",
        )
    bad = np.flatnonzero((idx < 0).any(1))
    if bad.size:
        raise MeshError(
            f"{name} constraints {bad[:10].tolist()} have negative particle ids.",
            problem="index_out_of_range",
            elements=bad[:100],
        )
    return idx.astype(np.int64)


class Constraints(eqx.Module):
    """Base class of the constraint kinds (struct of arrays, ``M`` constraints).

    Storage: as built, the arrays are in the user's order (``layout = (1, M)``). Inside a
    :class:`jaxface.pbd.System` they are *arranged*: sorted into ``K`` balanced colours of ``S``
    slots each (``layout = (K, S)``, flattened colour-major, ``T = K * S`` slots) where padding
    slots point at dummy particles ``N, N + 1, ...`` and are inert.

    Attributes:
        idx: ``(T, arity)`` int32 particle ids.
        stiffness: ``(T,)`` PBD stiffness ``k`` in ``[0, 1]`` (dimensionless).
        compliance: ``(T,)`` XPBD compliance ``alpha`` (``[C]^2 / energy``, energy in
            ``g mm^2 / s^2`` when inverse masses are in 1/g), or ``None`` for plain PBD.
        perm: ``(T,)`` int32, slot ``s`` holds the user's constraint ``perm[s]`` (-1: padding).
        inv_perm: ``(M,)`` int32, the slot of each user constraint.
        layout: static ``(K, S)``.
    """

    idx: jax.Array
    stiffness: jax.Array
    compliance: jax.Array | None
    perm: jax.Array
    inv_perm: jax.Array
    layout: tuple[int, int] = eqx.field(static=True)

    arity: ClassVar[int] = 2
    unilateral: ClassVar[bool] = False
    unit: ClassVar[str] = "mm"
    # fields whose leading axis is the constraint axis (arranged by colour, set in user order)
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance")

    # -- sizes ---------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Number of constraints ``M``."""
        return int(self.inv_perm.shape[0])

    @property
    def xpbd(self) -> bool:
        """True when the group uses XPBD compliance (``compliance is not None``)."""
        return self.compliance is not None

    @property
    def n_colors(self) -> int:
        return self.layout[0]

    @property
    def arranged(self) -> bool:
        return self.layout != (1, self.size) or bool(np.any(np.asarray(self.perm) < 0))

    def lambda_shape(self) -> tuple[int, ...]:
        """Shape of the XPBD multiplier block of this group: ``(K, S)`` (anchors ``(K, 3, S)``)."""
        return self.layout

    def _arranged_fields(self):
        return self.per_constraint

    # -- layout ----------------------------------------------------------------------------
    def user_order(self) -> Constraints:
        """Copy in the user's order (``layout (1, M)``), undoing an arrangement."""
        if not self.arranged and np.array_equal(np.asarray(self.perm), np.arange(self.size)):
            return self
        inv = np.asarray(self.inv_perm)
        changes = {
            f: getattr(self, f)[inv]
            for f in self._arranged_fields()
            if getattr(self, f) is not None
        }
        ident = jnp.arange(inv.size, dtype=jnp.int32)
        return dataclasses.replace(
            self, **changes, perm=ident, inv_perm=ident, layout=(1, int(inv.size))
        )

    def arrange(self, colors, n_particles: int) -> Constraints:
        """Copy arranged in the padded colour layout (NumPy, build time).

        Args:
            colors: ``(M,)`` valid colours of the constraints (user order), see
                :func:`jaxface.coloring.balanced_coloring`.
            n_particles: ``N``; padding slots point at dummy particles ``N + r``.
        """
        from .coloring import padded_layout

        g = self.user_order()
        slot, K, S = padded_layout(colors)
        T = K * S
        perm = np.full(T, -1, np.int64)
        perm[slot] = np.arange(slot.size)
        src = np.where(perm < 0, 0, perm)
        changes = {}
        for f in g._arranged_fields():
            v = getattr(g, f)
            if v is None:
                continue
            changes[f] = to_jax(np.asarray(v)[src]) if slot.size else v
        # padding rows -> dummy particles, unique inside each colour
        pad = perm < 0
        rank = (np.cumsum(pad.reshape(K, S), axis=1) - 1).reshape(-1)
        idx = np.asarray(changes.get("idx", g.idx)).copy()
        idx[pad] = (n_particles + rank[pad])[:, None]
        changes["idx"] = jnp.asarray(idx, jnp.int32)
        return dataclasses.replace(
            g,
            **changes,
            perm=jnp.asarray(perm, jnp.int32),
            inv_perm=jnp.asarray(slot, jnp.int32),
            layout=(K, S),
        )

    @property
    def n_dummy(self) -> int:
        """Number of dummy particles the padding refers to."""
        perm = np.asarray(self.perm)
        if perm.size == 0:
            return 0
        return int((perm.reshape(self.layout) < 0).sum(1).max())

    def blocks(self) -> dict:
        """Per-constraint fields reshaped to ``(K, S, ...)`` (the ``lax.scan`` inputs)."""
        K, S = self.layout
        out = {}
        for f in self._arranged_fields():
            v = getattr(self, f)
            if v is not None:
                out[f] = v.reshape((K, S) + v.shape[1:])
        return out

    def block_view(self, fields: dict) -> Constraints:
        """This group restricted to one colour block (``fields`` from one row of
        :meth:`blocks`); used inside the solver's scan body."""
        return dataclasses.replace(self, **fields)

    # -- runtime updates -------------------------------------------------------------------
    def set(self, **fields) -> Constraints:
        """Copy with fields replaced; per-constraint fields are given in the user's order.

        Example: ``anchors.set(target=t)`` with ``t`` ``(M, 3)`` mm. Differentiable in the new
        values (a gather by ``perm``); scalars broadcast to every constraint.
        """
        new = self
        src = jnp.asarray(np.where(np.asarray(self.perm) < 0, 0, np.asarray(self.perm)), jnp.int32)
        for name, value in fields.items():
            if name not in self._settable():
                raise MeshError(
                    f"{type(self).__name__} has no settable field {name!r}; settable: "
                    f"{sorted(self._settable())}.",
                    problem="unknown_field",
                )
            old = getattr(self, name)
            if old is None:
                raise MeshError(
                    f"{type(self).__name__}.{name} is None (the group was built without "
                    f"it); rebuild it with {name}= to make it settable.",
                    problem="unknown_field",
                )
            value = jnp.asarray(value, dtype=old.dtype)
            if name in self.per_constraint:
                value = jnp.broadcast_to(value, (self.size,) + old.shape[1:])[src]
            else:
                value = jnp.broadcast_to(value, old.shape)
            new = eqx.tree_at(lambda g: getattr(g, name), new, value)
        return new

    def _settable(self):
        return [
            f for f in self.__dataclass_fields__ if f not in ("perm", "inv_perm", "layout", "idx")
        ]

    # -- kernels ---------------------------------------------------------------------------
    def terms(self, P):
        """Constraint values and gradients for all stored slots of this (block) group.

        Args:
            P: tuple of ``arity`` arrays ``(3, m)`` mm, the gathered particle positions.

        Returns:
            ``(C, grads, g2)``: ``C`` ``(m,)``; ``grads`` tuple of ``(3, m)``; ``g2`` tuple of
            ``(m,)`` squared gradient norms.
        """
        raise NotImplementedError

    def _gather_all(self, x):
        x = jnp.asarray(x)
        need = int(np.asarray(self.idx).max()) + 1 if self.idx.size else 0
        if need > x.shape[0]:
            x = jnp.concatenate([x, jnp.zeros((need - x.shape[0], 3), x.dtype)])
        xt = x.T
        return tuple(xt[:, self.idx[:, k]] for k in range(self.arity))

    def values(self, x) -> jax.Array:
        """Constraint values ``C`` at positions ``x`` ``(N, 3)`` mm, in the user's order.

        Returns:
            ``(M,)`` in the unit of the kind (see the module table); for unilateral kinds the
            signed value (negative = violated).
        """
        C = self.terms(self._gather_all(x))[0]
        return C[self.inv_perm]

    def violation(self, x) -> jax.Array:
        """``|C|`` for bilateral kinds, ``max(-C, 0)`` for unilateral ones, user order, ``(M,)``."""
        C = self.values(x)
        return jnp.maximum(-C, 0.0) if self.unilateral else jnp.abs(C)


def _base_fields(idx, stiffness, compliance, name):
    m = idx.shape[0]
    k = _as_float(stiffness, (m,), f"{name} stiffness")
    _check_stiffness(k, name)
    if compliance is not None:
        a = _as_float(compliance, (m,), f"{name} compliance")
        _check_compliance(a, name)
        a = to_jax(a)
    else:
        a = None
    ident = jnp.arange(m, dtype=jnp.int32)
    return dict(
        idx=jnp.asarray(idx, jnp.int32),
        stiffness=to_jax(k),
        compliance=a,
        perm=ident,
        inv_perm=ident,
        layout=(1, m),
    )


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
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance", "rest")

    @classmethod
    def build(cls, pairs, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
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

    def project_pbd(self, P, W):
        """PBD correction of a block (eqs. 3.16-3.19 written out; same result as the generic
        projection, fewer operations: this is the hot loop of every skin).

        Args: ``P`` two ``(3, m)`` mm; ``W`` ``(2, m)`` inverse masses.
        Returns: the two corrections ``(3, m)`` mm.
        """
        d = P[0] - P[1]
        l2 = _dot(d, d)
        ok = l2 > _tiny(d.dtype)
        inv = jax.lax.rsqrt(jnp.where(ok, l2, 1.0))
        ws = W[0] + W[1]
        okw = ws > 0
        kw = jnp.where(okw, -self.stiffness / jnp.where(okw, ws, 1.0), 0.0)
        coef = jnp.where(ok, (l2 * inv - self.rest) * inv, 0.0) * kw
        return [(W[0] * coef) * d, (-W[1] * coef) * d]


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
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance", "rest")

    @classmethod
    def build(cls, edge_pairs, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
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
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance", "rest")

    @classmethod
    def build(cls, triangles, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
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


# ----------------------------------------------------------------------------------------
# global volume (3.22)
# ----------------------------------------------------------------------------------------


class VolumeConstraint(Constraints):
    """Volume enclosed by a closed (or capped) triangle surface, one global constraint (3.22).

    ``V = sum_t ((pa - o) x (pb - o)) . (pc - o) / 6`` (mm^3), the signed volume of the cones
    from the point ``o`` to the triangles: for a closed, outward-oriented surface it is the
    enclosed volume for any ``o``; for an open surface (the face skin) it is the volume of the
    surface capped by the cone to ``o`` (put ``o`` inside the head). Note the thesis's eq. 3.22
    omits the factor 1/6.

    Here ``idx``, ``perm``, ``inv_perm`` and ``layout`` describe the ``(F, 3)`` triangles
    (arranged by a colouring of the triangles so that the gradient is summed without scatter
    conflicts; padding triangles are collapsed onto a dummy particle and add nothing);
    ``stiffness``, ``compliance`` and ``rest`` have shape ``(1,)``.

    Attributes:
        rest: ``(1,)`` mm^3 target volume ``V0`` (inflate by setting a larger value).
        origin: ``(3,)`` mm cap point ``o``.
    """

    rest: jax.Array
    origin: jax.Array

    arity: ClassVar[int] = 3
    unit: ClassVar[str] = "mm^3"
    per_constraint: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def build(
        cls, triangles, x_rest=None, *, rest=None, origin=None, stiffness=1.0, compliance=None
    ):
        """Build from ``(F, 3)`` outward-oriented triangles.

        Args:
            triangles: ``(F, 3)`` int.
            x_rest: ``(N, 3)`` mm; the rest volume is measured there unless ``rest`` is given.
            rest: scalar mm^3 target volume.
            origin: ``(3,)`` mm cap point (default: the centroid of the triangles' vertices in
                ``x_rest``, or 0).
            stiffness: scalar ``k`` in ``[0, 1]``.
            compliance: scalar XPBD compliance (``mm^6 / energy``) or ``None``.
        """
        tri = _check_indices(triangles, 3, "volume")
        if origin is None:
            if x_rest is not None:
                origin = np.asarray(x_rest, np.float64)[np.unique(tri)].mean(0)
            else:
                origin = np.zeros(3)
        origin = _as_float(origin, (3,), "volume origin")
        if rest is None:
            if x_rest is None:
                raise MeshError("volume constraint needs x_rest or rest.", problem="shape")
            x = _as_float(x_rest, name="x_rest") - origin
            rest = np.einsum("ij,ij->", np.cross(x[tri[:, 0]], x[tri[:, 1]]), x[tri[:, 2]]) / 6.0
        rest = _as_float(rest, (1,), "volume rest")
        k = _as_float(stiffness, (1,), "volume stiffness")
        _check_stiffness(k, "volume")
        a = None
        if compliance is not None:
            a = _as_float(compliance, (1,), "volume compliance")
            _check_compliance(a, "volume")
            a = to_jax(a)
        F = tri.shape[0]
        ident = jnp.arange(F, dtype=jnp.int32)
        return cls(
            idx=jnp.asarray(tri, jnp.int32),
            stiffness=to_jax(k),
            compliance=a,
            perm=ident,
            inv_perm=ident,
            layout=(1, F),
            rest=to_jax(rest),
            origin=to_jax(origin),
        )

    @property
    def size(self) -> int:
        return 1

    @property
    def n_triangles(self) -> int:
        """Number of triangles ``F`` (without padding)."""
        return int(self.inv_perm.shape[0])

    @property
    def arranged(self) -> bool:
        return self.layout != (1, self.n_triangles) or bool(np.any(np.asarray(self.perm) < 0))

    def lambda_shape(self):
        return (1,)

    def _arranged_fields(self):
        return ("idx",)

    def user_order(self):
        if not self.arranged and np.array_equal(np.asarray(self.perm), np.arange(self.n_triangles)):
            return self
        inv = np.asarray(self.inv_perm)
        ident = jnp.arange(inv.size, dtype=jnp.int32)
        return dataclasses.replace(
            self, idx=self.idx[inv], perm=ident, inv_perm=ident, layout=(1, int(inv.size))
        )

    def set(self, **fields):
        """Copy with ``rest`` (mm^3), ``origin`` (mm), ``stiffness`` or ``compliance`` replaced."""
        new = self
        for name, value in fields.items():
            if name not in ("rest", "origin", "stiffness", "compliance"):
                raise MeshError(
                    f"VolumeConstraint has no settable field {name!r}; settable: rest, "
                    "origin, stiffness, compliance.",
                    problem="unknown_field",
                )
            old = getattr(self, name)
            if old is None:
                raise MeshError(
                    f"VolumeConstraint.{name} is None; rebuild with {name}= to set it.",
                    problem="unknown_field",
                )
            value = jnp.broadcast_to(jnp.asarray(value, old.dtype), old.shape)
            new = eqx.tree_at(lambda g: getattr(g, name), new, value)
        return new

    def volume_terms(self, P):
        """Per-triangle volume and gradient pieces for gathered ``P`` = 3 arrays ``(3, F)``.

        Returns ``(V (scalar mm^3), (ga, gb, gc))`` with the per-triangle gradients ``(3, F)``
        (mm^2) of ``V`` with respect to the three corners.
        """
        o = self.origin[:, None]
        a, b, c = (q - o for q in P)
        ab = _cross(a, b)
        V = jnp.sum(_dot(ab, c)) / 6.0
        return V, (_cross(b, c) / 6.0, _cross(c, a) / 6.0, ab / 6.0)

    def volume(self, x):
        """Current volume (mm^3) of positions ``x`` ``(N, 3)`` mm."""
        return self.volume_terms(self._gather_all(x))[0]

    def values(self, x):
        """``(1,)`` mm^3: ``V(x) - V0``."""
        return (self.volume(x) - self.rest[0])[None]


# ----------------------------------------------------------------------------------------
# position / anchor (3.23)
# ----------------------------------------------------------------------------------------


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
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance", "target")

    @classmethod
    def build(cls, indices, targets, *, stiffness=1.0, compliance=None):
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
        K, S = self.layout
        return (K, 3, S)

    def values(self, x):
        """``(M,)`` mm distances ``|p - t|`` (eq. 3.23), user order."""
        p = self._gather_all(x)[0].T
        return safe_norm(p - self.target)[self.inv_perm]

    def violation(self, x):
        return self.values(x)

    def project(self, p, W, alpha_t, lam):
        """Anchor correction of a block: gathered ``p`` ``(3, m)`` mm, inverse masses ``W``
        ``(m,)``, ``alpha_t`` ``(m,)`` (``alpha / dt^2``) or ``None``, multipliers ``(3, m)``.

        Returns ``(dp (3, m) mm, dlambda (3, m) or None)``.
        """
        C = p - self.target.T
        k = self.stiffness
        if alpha_t is None:
            dp = jnp.where(W > 0, -k * C, 0.0)
            return dp, None
        den = W + alpha_t
        ok = den > 0
        dlam = jnp.where(ok, k * (-C - alpha_t * lam) / jnp.where(ok, den, 1.0), 0.0)
        return W * dlam, dlam


# ----------------------------------------------------------------------------------------
# unilateral: half-space and convex hull collisions
# ----------------------------------------------------------------------------------------


def _unit_rows(n):
    """Normalise ``(..., 3)`` rows safely (zero rows stay zero)."""
    nn = safe_norm(n)
    return n / jnp.where(nn > 0, nn, 1.0)[..., None]


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
        "idx",
        "stiffness",
        "compliance",
        "normal",
        "offset",
    )

    @classmethod
    def build(cls, indices, normals, offsets, *, stiffness=1.0, compliance=None):
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
    per_constraint: ClassVar[tuple[str, ...]] = ("idx", "stiffness", "compliance", "clearance")

    @classmethod
    def build(cls, indices, normals, offsets, *, clearance=0.0, stiffness=1.0, compliance=None):
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
        h = jnp.argmax(sd, axis=0)
        C = jnp.max(sd, axis=0) - self.clearance
        n = N[h].T  # (3, m)
        return C, (n,), (_dot(n, n),)
