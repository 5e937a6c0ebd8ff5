"""Surface points: a triangle id plus barycentric coordinates, evaluated on deformed vertices.

The thesis (Fratarcangeli 2008, ch. 4-5) attaches muscles, landmarks and the skin-to-skull
binding to the skin through *surface points*: a point is stored as the triangle it lies in and
its barycentric coordinates, and is re-evaluated on the current (deformed) vertex positions.
Here a :class:`SurfacePoints` is a small JAX pytree (``eqx.Module``); evaluating it is a gather
plus a weighted sum, jit-able, vmap-able and differentiable with respect to the vertices (and
the barycentric coordinates).

Units: positions are in the units of the vertices you pass (millimetres everywhere in jaxface);
normals are unit vectors.

Building surface points from 3-D points (closest-point projection) or from rays needs the NumPy
:class:`jaxface.mesh.TriMesh`: see :func:`from_points`, :meth:`TriMesh.closest_points` and
:meth:`TriMesh.ray_cast`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ._arrays import to_jax
from .errors import MeshError

if TYPE_CHECKING:  # pragma: no cover
    from .mesh import TriMesh

__all__ = [
    "SurfacePoints",
    "vertex_normals",
    "face_normals",
    "safe_normalize",
    "from_points",
]


def safe_normalize(x: jax.Array, axis: int = -1) -> jax.Array:
    """``x / |x|`` along ``axis``, with a zero vector (not NaN) where ``|x| == 0``.

    NaN-safe in value *and* gradient (the "double where" trick): for a zero input the
    output and its derivative are zero instead of ``0/0``.

    Args:
        x: ``(..., 3)`` (any trailing size) array of any float dtype.
        axis: the axis to normalise over.

    Returns:
        Same shape and dtype as ``x``; rows of unit length, or zero rows where ``x`` was zero.
    """
    x = jnp.asarray(x)
    n2 = jnp.sum(x * x, axis=axis, keepdims=True)
    ok = n2 > jnp.finfo(x.dtype).tiny if jnp.issubdtype(x.dtype, jnp.floating) else n2 > 0
    n = jnp.sqrt(jnp.where(ok, n2, jnp.ones_like(n2)))
    return jnp.where(ok, x / n, jnp.zeros_like(x))


def _face_cross(vertices: jax.Array, triangles) -> jax.Array:
    """(F, 3) un-normalised face normals ``(v1 - v0) x (v2 - v0)``; length = 2 * area (mm^2)."""
    tri = jnp.asarray(triangles)
    v0 = vertices[tri[:, 0]]
    v1 = vertices[tri[:, 1]]
    v2 = vertices[tri[:, 2]]
    return jnp.cross(v1 - v0, v2 - v0)


def face_normals(vertices: jax.Array, triangles) -> jax.Array:
    """Unit face normals (JAX), right-hand rule on the triangle's vertex order.

    Args:
        vertices: ``(V, 3)`` positions, mm.
        triangles: ``(F, 3)`` int vertex ids (NumPy or JAX), counter-clockwise seen from outside.

    Returns:
        ``(F, 3)`` unit normals; zero rows for zero-area triangles (never NaN, also in gradients).
    """
    vertices = jnp.asarray(vertices)
    return safe_normalize(_face_cross(vertices, triangles))


def vertex_normals(vertices: jax.Array, triangles) -> jax.Array:
    """Area-weighted vertex normals (JAX): the normalised sum of the incident face normals,
    each weighted by its triangle's area.

    Jit-able and differentiable with respect to ``vertices``. NaN-safe: zero-area triangles
    contribute nothing, and a vertex whose weighted sum is zero (isolated vertex, or all incident
    triangles degenerate/cancelling) gets a zero normal instead of NaN, in value and gradient.

    Args:
        vertices: ``(V, 3)`` positions, mm (any float dtype; the output follows it).
        triangles: ``(F, 3)`` int vertex ids (NumPy or JAX).

    Returns:
        ``(V, 3)`` unit normals (zero rows where undefined).
    """
    vertices = jnp.asarray(vertices)
    tri = jnp.asarray(triangles)
    c = _face_cross(vertices, tri)  # (F, 3), |c| = 2 * area, so summing c is area weighting
    # one scatter-add of each face's vector into its three corners
    acc = jnp.zeros_like(vertices).at[tri.reshape(-1)].add(jnp.repeat(c, 3, axis=0))
    return safe_normalize(acc)


class SurfacePoints(eqx.Module):
    """Points attached to a triangle mesh: triangle ids plus barycentric coordinates.

    A JAX pytree. Evaluate it on any deformed copy of the mesh with :meth:`positions` and
    :meth:`normals`; both are jit-able, work under ``jax.vmap`` (over vertices, or over
    stacked SurfacePoints) and are differentiable with respect to the vertices and ``bary``.

    Attributes:
        tri: ``(K,)`` int32 triangle ids into the mesh's ``(F, 3)`` triangle array.
        bary: ``(K, 3)`` barycentric coordinates (float, each row sums to 1) with respect to the
            triangle's vertices in their stored order.
    """

    tri: jax.Array
    bary: jax.Array

    def __init__(self, tri, bary):
        """Args:
        tri: ``(K,)`` integer triangle ids (converted to int32).
        bary: ``(K, 3)`` barycentric coordinates (float; integer input becomes the default
            float dtype). Rows should sum to 1; see :meth:`check` for a value check.
        """
        # concrete input is converted in NumPy (to_jax): jnp.asarray and astype compile a
        # small program for every new K (about 25 ms each on a CPU)
        if isinstance(tri, Tracer):
            tri = tri.astype(jnp.int32)
        else:
            tri = to_jax(np.asarray(tri).astype(np.int32, copy=False))
        if isinstance(bary, Tracer):
            if not jnp.issubdtype(bary.dtype, jnp.floating):
                bary = bary.astype(jnp.result_type(float))
        else:
            b = np.asarray(bary)
            bary = to_jax(b if np.issubdtype(b.dtype, np.floating) else b.astype(np.float64))
        if tri.ndim != 1 or bary.ndim != 2 or bary.shape[-1] != 3 or bary.shape[0] != tri.shape[0]:
            raise MeshError(
                f"SurfacePoints needs tri (K,) and bary (K, 3); got tri {tuple(tri.shape)} and "
                f"bary {tuple(bary.shape)}.",
                problem="surface_points_shape",
            )
        self.tri = tri
        self.bary = bary

    def __len__(self) -> int:
        return int(self.tri.shape[0])

    def positions(self, vertices, triangles) -> jax.Array:
        """Positions of the points on the given (deformed) vertices.

        Args:
            vertices: ``(V, 3)`` positions, mm.
            triangles: ``(F, 3)`` int vertex ids (NumPy or JAX), the mesh these points live on.

        Returns:
            ``(K, 3)`` positions, mm, dtype of ``vertices`` / ``bary`` promoted.
        """
        vertices = jnp.asarray(vertices)
        corners = vertices[jnp.asarray(triangles)[self.tri]]  # (K, 3, 3)
        return jnp.einsum("kj,kjd->kd", self.bary.astype(vertices.dtype), corners)

    def normals(self, vertices, triangles, vnormals=None) -> jax.Array:
        """Smooth normals at the points: the barycentric interpolation of the area-weighted
        vertex normals, renormalised (NaN-safe: zero where the interpolated normal vanishes).

        Args:
            vertices: ``(V, 3)`` positions, mm.
            triangles: ``(F, 3)`` int vertex ids.
            vnormals: optional precomputed ``(V, 3)`` vertex normals (to share the
                computation between several SurfacePoints on the same mesh).

        Returns:
            ``(K, 3)`` unit normals.
        """
        vertices = jnp.asarray(vertices)
        vn = vertex_normals(vertices, triangles) if vnormals is None else jnp.asarray(vnormals)
        corners = vn[jnp.asarray(triangles)[self.tri]]
        return safe_normalize(jnp.einsum("kj,kjd->kd", self.bary.astype(vn.dtype), corners))

    def face_normals(self, vertices, triangles) -> jax.Array:
        """Flat normals of the triangles the points lie in, ``(K, 3)`` unit (zero for
        zero-area triangles)."""
        vertices = jnp.asarray(vertices)
        tri = jnp.asarray(triangles)[self.tri]
        return face_normals(vertices, tri)

    def vertex_ids(self, triangles) -> jax.Array:
        """``(K, 3)`` ids of the three vertices each point is attached to."""
        return jnp.asarray(triangles)[self.tri]

    def take(self, index) -> SurfacePoints:
        """A subset (or reordering) of the points: ``index`` is an int array or bool mask."""
        index = np.asarray(index)
        return SurfacePoints(self.tri[index], self.bary[index])

    @staticmethod
    def concatenate(items) -> SurfacePoints:
        """Concatenate several SurfacePoints on the same mesh into one."""
        items = list(items)
        return SurfacePoints(
            jnp.concatenate([s.tri for s in items]), jnp.concatenate([s.bary for s in items])
        )

    def check(self, n_triangles: int | None = None, atol: float = 1e-6) -> None:
        """Value check (not jit-able): barycentrics finite, >= -atol, rows sum to 1 within atol,
        and triangle ids in ``[0, n_triangles)``. Raises :class:`MeshError` naming the rows."""
        tri = np.asarray(self.tri)
        bary = np.asarray(self.bary, dtype=np.float64)
        bad = ~np.all(np.isfinite(bary), axis=1)
        bad |= np.any(bary < -atol, axis=1) | (np.abs(bary.sum(axis=1) - 1.0) > atol)
        if n_triangles is not None:
            bad |= (tri < 0) | (tri >= n_triangles)
        if bad.any():
            rows = np.flatnonzero(bad)
            raise MeshError(
                f"{rows.size} surface point(s) have invalid barycentrics or triangle ids "
                f"(rows {rows[:10].tolist()}{' ...' if rows.size > 10 else ''}); barycentrics "
                f"must be finite, non-negative and sum to 1, triangle ids in range. Rebuild them "
                f"with TriMesh.closest_points.",
                problem="surface_points_values",
                elements=rows,
            )


def from_points(mesh: TriMesh, points) -> tuple[SurfacePoints, np.ndarray]:
    """Attach 3-D points to a mesh by closest-point projection.

    Args:
        mesh: the :class:`jaxface.mesh.TriMesh` to attach to.
        points: ``(K, 3)`` points, mm.

    Returns:
        ``(SurfacePoints (K,), distances (K,) mm)``: the surface point closest to each input
        point and the distance to it. Same as :meth:`TriMesh.closest_points`.
    """
    return mesh.closest_points(points)
