"""Volume constraints of closed (or capped) triangle surfaces (eq. 3.22), one per body.

``V_b = sum_{t in b} ((pa - o) x (pb - o)) . (pc - o) / 6`` (mm^3), the signed volume of the
cones from the point ``o`` to the triangles of body ``b``: for a closed, outward-oriented
surface it is the enclosed volume for any ``o``; for an open surface (the face skin) it is the
volume of the surface capped by the cone to ``o`` (put ``o`` inside the head). The thesis's
eq. 3.22 omits the factor 1/6.

Projection (one global constraint per body, exact to first order): with
``G_i = dV_b / dp_i = sum_{t ∋ i} (corner term) / 6`` (mm^2),
``dlambda_b = -k_b (V_b - V0_b) / sum_{i in b} w_i |G_i|^2`` (XPBD: ``k_b (-C - a lambda) /
(s + a)``), ``dp_i = w_i dlambda_b G_i``. The gradient is summed per particle with one
``segment_sum`` (no colouring needed).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._arrays import to_jax
from ..errors import MeshError
from .base import (
    Constraints,
    _as_float,
    _check_compliance,
    _check_indices,
    _check_stiffness,
    _cross,
    _dot,
)

__all__ = ["VolumeConstraint"]


class VolumeConstraint(Constraints):
    """One volume constraint per body: ``B`` bodies made of ``F`` triangles in all.

    ``idx`` holds the ``(F, 3)`` outward-oriented triangles; ``stiffness``, ``compliance`` and
    ``rest`` have one entry per body.

    Attributes:
        rest: ``(B,)`` mm^3 target volumes ``V0`` (inflate by setting a larger value).
        origin: ``(3,)`` mm cap point ``o`` (shared by the bodies).
        owner: ``(F,)`` int32 body of each triangle.
        particles: ``(P,)`` int32 the particles of the triangles; particle_body: ``(P,)``
            int32 their body (a particle belongs to one body).
        n_bodies: static ``B``.
    """

    rest: jax.Array
    origin: jax.Array
    owner: jax.Array
    particles: jax.Array
    particle_body: jax.Array
    n_bodies: int = eqx.field(static=True, default=1)

    arity: ClassVar[int] = 3
    unit: ClassVar[str] = "mm^3"
    per_constraint: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def build(
        cls,
        triangles,
        x_rest=None,
        *,
        rest=None,
        origin=None,
        owner=None,
        stiffness: ArrayLike = 1.0,
        compliance=None,
    ):
        """Build from ``(F, 3)`` outward-oriented triangles.

        Args:
            triangles: ``(F, 3)`` int.
            x_rest: ``(N, 3)`` mm; the rest volumes are measured there unless ``rest`` is given.
            rest: ``(B,)`` (or scalar) mm^3 target volumes.
            origin: ``(3,)`` mm cap point (default: the centroid of the triangles' vertices in
                ``x_rest``, or 0).
            owner: ``(F,)`` int body of each triangle (default: one body).
            stiffness: ``k`` in ``[0, 1]``, scalar or ``(B,)``.
            compliance: XPBD compliance (``mm^6 / energy``), scalar or ``(B,)``, or ``None``.

        Raises:
            MeshError: bad shapes, non-finite values, or a particle shared by two bodies.
        """
        tri = _check_indices(triangles, 3, "volume")
        own = np.zeros(len(tri), np.int64) if owner is None else np.asarray(owner, np.int64)
        if own.shape != (len(tri),) or (own.size and own.min() < 0):
            raise MeshError(
                f"volume owner must be ({len(tri)},) non-negative body ids, got {own.shape}.",
                problem="shape",
            )
        B = int(own.max()) + 1 if own.size else 1
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
            tv = np.einsum("ij,ij->i", np.cross(x[tri[:, 0]], x[tri[:, 1]]), x[tri[:, 2]])
            rest = np.bincount(own, tv, minlength=B) / 6.0
        rest = _as_float(rest, (B,), "volume rest")
        k = _as_float(stiffness, (B,), "volume stiffness")
        _check_stiffness(k, "volume")
        a = None
        if compliance is not None:
            a = _as_float(compliance, (B,), "volume compliance")
            _check_compliance(a, "volume")
            a = to_jax(a)
        pts, first = np.unique(tri.ravel(), return_index=True)
        pbody = np.repeat(own, 3)[first]
        pairs = np.unique(np.stack([tri.ravel(), np.repeat(own, 3)], 1), axis=0)
        if len(pairs) != len(pts):
            raise MeshError("a particle belongs to two volume bodies.", problem="shape")
        return cls(
            idx=jnp.asarray(tri, jnp.int32),
            stiffness=to_jax(k),
            compliance=a,
            rest=to_jax(rest),
            origin=to_jax(origin),
            owner=jnp.asarray(own, jnp.int32),
            particles=jnp.asarray(pts, jnp.int32),
            particle_body=jnp.asarray(pbody, jnp.int32),
            n_bodies=B,
        )

    @property
    def size(self) -> int:
        """Number of constraints (bodies) ``B``."""
        return self.n_bodies

    @property
    def n_triangles(self) -> int:
        """Number of triangles ``F``."""
        return int(self.idx.shape[0])

    def lambda_shape(self):
        return (self.n_bodies,)

    def _settable(self):
        return ["rest", "origin", "stiffness", "compliance"]

    def volume_terms(self, P):
        """Per-body volumes and per-triangle gradient pieces for gathered ``P`` = 3 arrays
        ``(3, F)`` mm.

        Returns:
            ``(V (B,) mm^3, (ga, gb, gc))``: the per-triangle gradients ``(3, F)`` (mm^2) of
            the body's volume with respect to the three corners.
        """
        o = self.origin[:, None]
        a, b, c = (q - o for q in P)
        ab = _cross(a, b)
        V = jax.ops.segment_sum(_dot(ab, c), self.owner, self.n_bodies) / 6.0
        return V, (_cross(b, c) / 6.0, _cross(c, a) / 6.0, ab / 6.0)

    def volume(self, x):
        """``(B,)`` current volumes (mm^3) at positions ``x`` ``(N, 3)`` mm."""
        return self.volume_terms(self._gather_all(x))[0]

    def values(self, x):
        """``(B,)`` mm^3: ``V(x) - V0``."""
        return self.volume(x) - self.rest

    def correct(self, x, inv_mass, alpha_t=None, lam=None):
        """Project every body's volume once (all particles at once).

        Args:
            x: ``(N, 3)`` mm; inv_mass: ``(N,)`` 1/g; alpha_t: ``(B,)`` XPBD ``alpha / dt^2``
                or ``None``; lam: ``(B,)`` multipliers (XPBD).

        Returns:
            ``(x' (N, 3) mm, dlambda (B,) or None)``.
        """
        n = x.shape[0]
        xt = x.T
        P = tuple(xt[:, self.idx[:, k]] for k in range(3))
        V, gt = self.volume_terms(P)
        G = jax.ops.segment_sum(
            jnp.concatenate([gt[k].T for k in range(3)]), self.idx.T.reshape(-1), num_segments=n
        )
        p = self.particles
        Gp = G[p]
        w = inv_mass[p]
        denom = jax.ops.segment_sum(w * jnp.sum(Gp * Gp, axis=1), self.particle_body, self.n_bodies)
        C = V - self.rest
        if alpha_t is None:
            ok = denom > 0
            dlam = jnp.where(ok, -self.stiffness * C / jnp.where(ok, denom, 1.0), 0.0)
            new = None
        else:
            den = denom + alpha_t
            ok = den > 0
            dlam = jnp.where(
                ok, self.stiffness * (-C - alpha_t * lam) / jnp.where(ok, den, 1.0), 0.0
            )
            new = dlam
        return x.at[p].add((w * dlam[self.particle_body])[:, None] * Gp), new
