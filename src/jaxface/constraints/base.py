"""The base of the PBD constraint kinds and the one projection every kind shares (JAX).

Every kind is an :class:`equinox.Module` holding, for ``M`` constraints of that kind in the
order given to its builder, the particle ids, the rest values, the stiffness ``k`` in ``[0, 1]``
(thesis sec. 3.2.1: the correction is multiplied by ``k``) and optionally an XPBD compliance
``alpha`` (Macklin et al. 2016). Every float array is a pytree leaf and can be differentiated
(rest values, stiffness, compliance, anchor targets, collision planes). A kind carries no
solver data: the colour blocks of the Gauss-Seidel scheme and the averaging counts of the
Jacobi scheme live in :class:`jaxface.sweep.Group`.

Projection (thesis eqs. 3.11-3.14, XPBD as an option), :meth:`Constraints.correction`: with
inverse masses ``w_i`` and gradients ``g_i = dC/dp_i``, ``s = sum_i w_i |g_i|^2``;
PBD: ``dlambda = -k C / s``; XPBD: ``dlambda = k (-C - a lambda) / (s + a)``, ``a = alpha / dt^2``,
``lambda += dlambda``; then ``dp_i = w_i g_i dlambda``. Unilateral constraints are skipped when
``C >= 0`` (XPBD: the accumulated ``lambda`` is clamped at 0). A kind supplies only ``C`` and its
gradients (:meth:`Constraints.terms`); anchors (linear, per axis) and the global volume override
the correction.

Geometry inside kernels is structure-of-arrays: a point set of ``m`` points is a ``(3, m)``
array (``x``, ``y``, ``z`` rows), which vectorises best on CPU. Units: mm, rad, 1/g.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import to_jax
from ..errors import MeshError

__all__ = ["Constraints", "safe_norm"]

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
    """Base class of the constraint kinds (struct of arrays, ``M`` constraints, user order).

    Attributes:
        idx: ``(M, arity)`` int32 particle ids.
        stiffness: ``(M,)`` PBD stiffness ``k`` in ``[0, 1]`` (dimensionless).
        compliance: ``(M,)`` XPBD compliance ``alpha`` (``[C]^2 / energy``, energy in
            ``g mm^2 / s^2`` when inverse masses are in 1/g), or ``None`` for plain PBD.
    """

    idx: jax.Array
    stiffness: jax.Array
    compliance: jax.Array | None

    arity: ClassVar[int] = 2
    unilateral: ClassVar[bool] = False
    unit: ClassVar[str] = "mm"
    # fields whose leading axis is the constraint axis (gathered into colour blocks)
    per_constraint: ClassVar[tuple[str, ...]] = ("stiffness", "compliance")

    @property
    def size(self) -> int:
        """Number of constraints ``M``."""
        return int(self.idx.shape[0])

    @property
    def xpbd(self) -> bool:
        """True when the group uses XPBD compliance (``compliance is not None``)."""
        return self.compliance is not None

    def lambda_shape(self) -> tuple[int, ...]:
        """Shape of the XPBD multipliers of the group: ``(M,)`` (anchors ``(3, M)``)."""
        return (self.size,)

    # -- runtime updates -------------------------------------------------------------------
    def set(self, **fields) -> Constraints:
        """Copy with fields replaced, e.g. ``anchors.set(target=t)`` with ``t`` ``(M, 3)`` mm.

        Works on concrete and traced values alike (inside ``jax.jit`` with the group as an
        argument) and is differentiable in the new values; scalars broadcast to every
        constraint.

        Raises:
            MeshError: an unknown or absent field.
        """
        new = self
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
            value = jnp.broadcast_to(jnp.asarray(value, dtype=old.dtype), old.shape)
            new = eqx.tree_at(lambda g, n=name: getattr(g, n), new, value)
        return new

    def _settable(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if f.name != "idx"]

    # -- kernels ---------------------------------------------------------------------------
    def terms(self, P):
        """Constraint values and gradients at gathered positions.

        Args:
            P: tuple of ``arity`` arrays ``(3, m)`` mm, the positions of each constraint's
                particles (``m`` = this group's constraints, or one colour block of them).

        Returns:
            ``(C, grads, g2)``: ``C`` ``(m,)``; ``grads`` tuple of ``(3, m)``; ``g2`` tuple of
            ``(m,)`` squared gradient norms.
        """
        raise NotImplementedError

    def correction(self, P, W, alpha_t=None, lam=None):
        """The PBD / XPBD correction of every constraint, from the same positions.

        Args:
            P: ``arity`` arrays ``(3, m)`` mm, gathered positions.
            W: ``arity`` arrays ``(m,)``, inverse masses of those particles (1/g).
            alpha_t: ``(m,)`` XPBD ``alpha / dt^2``, or ``None`` for plain PBD.
            lam: ``(m,)`` accumulated XPBD multipliers (``None`` for PBD).

        Returns:
            ``(dps, dlambda)``: one ``(3, m)`` mm correction per corner, and the multiplier
            increments ``(m,)`` (``None`` for PBD). Degenerate constraints (zero gradient)
            and kinematic particles get no correction.
        """
        C, grads, g2 = self.terms(P)
        denom = W[0] * g2[0]
        for k in range(1, len(P)):
            denom = denom + W[k] * g2[k]
        kk = self.stiffness
        if alpha_t is None:
            ok = denom > 0
            dlam = jnp.where(ok, -kk * C / jnp.where(ok, denom, 1.0), 0.0)
            if self.unilateral:
                dlam = jnp.where(C < 0, dlam, 0.0)
            new = None
        else:
            lam = jnp.zeros_like(C) if lam is None else lam
            den = denom + alpha_t
            ok = den > 0
            dlam = jnp.where(ok, kk * (-C - alpha_t * lam) / jnp.where(ok, den, 1.0), 0.0)
            if self.unilateral:
                dlam = jnp.maximum(lam + dlam, 0.0) - lam
            new = dlam
        return [(W[k] * dlam) * grads[k] for k in range(len(P))], new

    def _gather_all(self, x):
        xt = jnp.asarray(x).T
        return tuple(xt[:, self.idx[:, k]] for k in range(self.arity))

    def values(self, x) -> jax.Array:
        """Constraint values ``C`` at positions ``x`` ``(N, 3)`` mm, user order.

        Returns:
            ``(M,)`` in the unit of the kind; for unilateral kinds the signed value
            (negative = violated).
        """
        return self.terms(self._gather_all(x))[0]

    def violation(self, x) -> jax.Array:
        """``|C|`` for bilateral kinds, ``max(-C, 0)`` for unilateral ones, user order, ``(M,)``."""
        C = self.values(x)
        return jnp.maximum(-C, 0.0) if self.unilateral else jnp.abs(C)


def _base_fields(idx, stiffness, compliance, name) -> dict[str, Any]:
    m = idx.shape[0]
    k = _as_float(stiffness, (m,), f"{name} stiffness")
    _check_stiffness(k, name)
    a = None
    if compliance is not None:
        a = _as_float(compliance, (m,), f"{name} compliance")
        _check_compliance(a, name)
        a = to_jax(a)
    return dict(idx=jnp.asarray(idx, jnp.int32), stiffness=to_jax(k), compliance=a)


def _unit_rows(n):
    """Normalise ``(..., 3)`` rows safely (zero rows stay zero)."""
    nn = safe_norm(n)
    return n / jnp.where(nn > 0, nn, 1.0)[..., None]
