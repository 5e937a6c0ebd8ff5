"""Skin binding (thesis sec. 5.6): each skin vertex is tied to the first muscle or skull surface
its smoothed normal ray meets (:func:`bind_skin`), and the influence map of the bound vertices
(:func:`influence_map`). Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh import TriMesh
from .geometry import segment_cast, smooth_normals


@dataclass
class Binding:
    """Result of :func:`bind_skin` (NumPy).

    Attributes:
        surface: ``(V,)`` surface index (0 cranium, 1 mandible, 2+ muscles in the registry).
        tri: ``(V,)``; bary: ``(V, 3)``; point: ``(V, 3)`` rest hit positions, mm.
        direction: ``(V,)`` +1 outward hit, -1 inward hit, 0 closest-point fallback.
    """

    surface: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    point: np.ndarray
    direction: np.ndarray


def bind_skin(skin: TriMesh, registry, *, scale: float = 1.0, normal_smoothing: int = 3) -> Binding:
    """Bind every skin vertex to the muscles or the skull by ray casting (thesis sec. 5.5).

    Args:
        skin: the skin mesh, mm.
        registry: the :class:`~jaxface.anatomy.muscle_map.SurfaceRegistry` (cranium, mandible,
            muscles).
        scale: face scale (ray lengths: 12 mm outward, 45 mm inward to muscles, 60 mm to the
            skull, times ``scale``).
        normal_smoothing: one-ring passes over the vertex normals.

    Returns:
        :class:`Binding`.
    """
    x = skin.vertices
    n = smooth_normals(skin, normal_smoothing)
    V = x.shape[0]
    surf = np.full(V, -1, np.int64)
    tri = np.zeros(V, np.int64)
    bary = np.zeros((V, 3))
    t_best = np.full(V, np.inf)
    direction = np.zeros(V, np.int64)
    muscles = list(range(2, len(registry.meshes)))

    # the skull without its teeth (their triangles come after the bone's, so a bone hit is a
    # hit on the registry surface): lip skin binds to the orbicularis oris or the bone
    bones = registry.skull(teeth=False)

    def cast(ids, origins, dirs, length, targets, sign):
        for s in targets:
            h = segment_cast(bones[s], origins, dirs, length)
            better = h.hit & (h.t < t_best[ids])
            sel = np.flatnonzero(better)
            if sel.size:
                rows = ids[sel]
                t_best[rows] = h.t[sel]
                surf[rows] = s
                tri[rows] = h.tri[sel]
                bary[rows] = h.bary[sel]
                direction[rows] = sign

    # all muscles as one mesh (one r-tree), triangle -> registry surface
    if muscles:
        union = TriMesh.concatenate([registry.meshes[s] for s in muscles])
        tri_owner = np.concatenate([np.full(registry.meshes[s].n_triangles, s) for s in muscles])
        tri_first = {s: int(np.flatnonzero(tri_owner == s)[0]) for s in muscles}

        def cast_union(ids, origins, dirs, length, sign):
            h = segment_cast(union, origins, dirs, length)
            sel = np.flatnonzero(h.hit & (h.t < t_best[ids]))
            rows = ids[sel]
            t_best[rows] = h.t[sel]
            own = tri_owner[h.tri[sel]]
            surf[rows] = own
            tri[rows] = h.tri[sel] - np.array([tri_first[o] for o in own], dtype=np.int64)
            bary[rows] = h.bary[sel]
            direction[rows] = sign

        allv = np.arange(V)
        cast_union(allv, x, n, 12.0 * scale, +1)  # outward, muscles
        todo = np.flatnonzero(surf < 0)
        cast_union(todo, x[todo], -n[todo], 45.0 * scale, -1)  # inward, muscles
    todo = np.flatnonzero(surf < 0)
    cast(todo, x[todo], -n[todo], 60.0 * scale, [0, 1], -1)  # inward, skull
    todo = np.flatnonzero(surf < 0)
    if todo.size:  # closest skull point
        best = np.full(todo.size, np.inf)
        for s in (0, 1):
            spts, dist = bones[s].closest_points(x[todo])
            b = dist < best
            best[b] = dist[b]
            surf[todo[b]] = s
            tri[todo[b]] = np.asarray(spts.tri)[b]
            bary[todo[b]] = np.asarray(spts.bary)[b]
    point = np.zeros((V, 3))
    for s in np.unique(surf):
        sel = surf == s
        m = registry.meshes[s]
        point[sel] = np.einsum("kj,kjd->kd", bary[sel], m.vertices[m.triangles[tri[sel]]])
    return Binding(surf, tri, bary, point, direction)


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def influence_map(skin: TriMesh, sources: np.ndarray, radius: float = 0.15) -> np.ndarray:
    """Influence weights ``(V,)`` in [0, 1] (thesis sec. 5.5, Fig. 5.14).

    Args:
        skin: the skin mesh.
        sources: ``(V,)`` bool, the vertices bound to a muscle or to the mandible.
        radius: falloff radius in normalised geodesic distance (fraction of the largest
            distance from the sources over the skin).

    Returns:
        ``(V,)``: 1 on the sources, ``1 - smoothstep(d / radius)`` elsewhere (0 where not
        connected to any source).
    """
    if not np.any(sources):
        return np.zeros(skin.n_vertices)
    d = skin.geodesic_distance(np.flatnonzero(sources), normalise=True)
    d = np.where(np.isfinite(d), d, np.inf)
    return 1.0 - _smoothstep(d / radius)
