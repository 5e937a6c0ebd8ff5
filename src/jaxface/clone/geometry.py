"""Geometry of motion cloning (mm): meshes and landmarks as inputs, the MPEG-4 eye-nose
separation ENS0, fixed-length ray (segment) casting (:func:`cast_segments`), and the mapping
of points onto a surface along their normals (:func:`map_onto_surface`, :class:`SurfaceMap`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from ..errors import LandmarkError, MeshError
from ..landmarks import Landmarks
from ..mesh import TriMesh

__all__ = [
    "ENS0_DEFINITIONS",
    "SurfaceMap",
    "as_trimesh",
    "eye_nose_separation",
    "cast_segments",
    "map_onto_surface",
]

#: (eye points, nose tip) landmark names tried, in order, to measure the MPEG-4 ENS0
ENS0_DEFINITIONS: tuple[tuple[tuple[str, ...], str], ...] = (
    (
        (
            "Outer left eye corner",
            "Inner left eye corner",
            "Inner right eye corner",
            "Outer right eye corner",
        ),
        "Nose tip",
    ),
    (("36", "39", "42", "45"), "30"),
)


# ------------------------------------------------------------------------------------------
# small helpers
# ------------------------------------------------------------------------------------------
def as_trimesh(mesh, name: str = "mesh"):
    """A :class:`jaxface.mesh.TriMesh` from a TriMesh, a ``trimesh.Trimesh`` or a
    ``(vertices (V, 3) mm, triangles (F, 3))`` pair (not re-validated)."""
    if isinstance(mesh, TriMesh):
        return mesh
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return TriMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), validate=False)
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return TriMesh(np.asarray(mesh[0]), np.asarray(mesh[1]), validate=False)
    raise MeshError(
        f"{name} must be a TriMesh, a trimesh.Trimesh or a (vertices, triangles) pair; got "
        f"{type(mesh).__name__}.",
        problem="bad_type",
    )


def _as_landmarks(lm, name: str):
    if isinstance(lm, Landmarks):
        return lm
    if isinstance(lm, Mapping):
        return Landmarks.from_dict(lm)
    raise LandmarkError(
        f"{name} must be a jaxface.landmarks.Landmarks or a dict name -> (3,) position in mm; "
        f"got {type(lm).__name__}."
    )


def eye_nose_separation(landmarks) -> float:
    """MPEG-4 FAPU ENS0: vertical (y) distance from the middle of the eyes to the nose tip, mm.

    The middle of the eyes is the mean of the four eye corners (Bosphorus labels, or Multi-PIE
    points "36", "39", "42", "45" with nose tip "30").

    Raises:
        LandmarkError: none of the known definitions is fully present (pass ``ens0=``).
    """
    lm = _as_landmarks(landmarks, "landmarks")
    for eyes, nose in ENS0_DEFINITIONS:
        if not lm.missing(list(eyes) + [nose]):
            mid = lm.array(eyes).mean(axis=0)
            ens = abs(float(mid[1] - lm[nose][1]))
            if ens > 0:
                return ens
    raise LandmarkError(
        "cannot measure the eye-nose separation ENS0: the landmarks lack the four eye corners "
        "and the nose tip (Bosphorus labels, or Multi-PIE '36', '39', '42', '45', '30'). Pass "
        "ens0=<mm> explicitly.",
        missing=tuple(lm.missing(list(ENS0_DEFINITIONS[0][0]) + [ENS0_DEFINITIONS[0][1]])),
    )


# ------------------------------------------------------------------------------------------
# fixed-length ray (segment) casting
# ------------------------------------------------------------------------------------------
def cast_segments(
    origins,
    directions,
    length: float,
    vertices=None,
    triangles=None,
    *,
    two_sided: bool = True,
    normal_dot_min: float | None = 0.0,
    mesh=None,
):
    """Intersect fixed-length rays with a triangle mesh; keep the nearest hit of each.

    A thin layer over :meth:`jaxface.mesh.TriMesh.ray_cast` (r-tree candidates, exact
    Möller-Trumbore): each segment is cast as a ray from its far end, every hit on it is
    kept, hits on triangles facing the wrong way are dropped, and the hit nearest to the
    origin (smallest ``|t|``) wins. The rays are first cast over ``L / 16`` (short segments
    have few candidate triangles); only those that miss there are cast over ``L``.

    Arguments:
        origins: ``(R, 3)`` ray origins, mm.
        directions: ``(R, 3)`` ray directions (normalised here; zero rows never hit).
        length: ray length ``L``, mm; with ``two_sided`` the segment is
            ``[o - L d, o + L d]``, otherwise ``[o, o + L d]``.
        vertices, triangles: the mesh, ``(V, 3)`` mm and ``(F, 3)`` int; or
        mesh: the same as a :class:`~jaxface.mesh.TriMesh` (its r-tree is built once and
            reused across calls).
        normal_dot_min: ignore hits on triangles whose unit normal ``n_f`` has
            ``dot(n_f, d) < normal_dot_min`` (``None``: keep all).

    Returns:
        ``(hit (R,) bool, tri (R,) int64, bary (R, 3), t (R,) signed distance along d in mm)``;
        rays that missed have ``tri = -1``, ``bary = 0``, ``t = inf``.
    """
    if mesh is None:
        if vertices is None or triangles is None:
            raise MeshError(
                "cast_segments needs the target mesh: pass vertices and triangles, "
                "or mesh=TriMesh.",
                problem="bad_arguments",
            )
        mesh = TriMesh(
            np.asarray(vertices, dtype=np.float64), np.asarray(triangles), validate=False
        )
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    r = o.shape[0]
    nrm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.divide(d, nrm, out=np.zeros_like(d), where=nrm > 0)
    hit = np.zeros(r, bool)
    tri_out = np.full(r, -1, np.int64)
    bary_out = np.zeros((r, 3))
    t_out = np.full(r, np.inf)
    rays = np.flatnonzero((nrm[:, 0] > 0) & np.isfinite(o).all(axis=1) & np.isfinite(nrm[:, 0]))
    if rays.size == 0 or mesh.n_triangles == 0:
        return hit, tri_out, bary_out, t_out
    L = float(length)
    # near hits first (the usual case once two surfaces are roughly aligned): short segments
    # give small r-tree boxes with few candidates; only the rays that missed search further
    for frac in (1.0 / 16.0, 1.0):
        if rays.size == 0:
            break
        Lk = frac * L
        back = Lk if two_sided else 0.0
        h = mesh.ray_cast(
            o[rays] - back * d[rays],
            d[rays],
            all_hits=True,
            max_distance=Lk + back,
            merge_coincident=False,
        )
        ray = rays[np.asarray(h.ray_index)]
        tri = np.asarray(h.points.tri, dtype=np.int64)
        bary = h.barycentric
        t = np.asarray(h.distances) - back
        if normal_dot_min is not None:
            ok = np.einsum("ij,ij->i", mesh.face_normals[tri], d[ray]) >= normal_dot_min
            ray, tri, bary, t = ray[ok], tri[ok], bary[ok], t[ok]
        if ray.size:
            order = np.lexsort((np.abs(t), ray))
            ray, tri, bary, t = ray[order], tri[order], bary[order], t[order]
            first = np.unique(ray, return_index=True)[1]
            ray, tri, bary, t = ray[first], tri[first], bary[first], t[first]
            hit[ray] = True
            tri_out[ray] = tri
            bary_out[ray] = bary
            t_out[ray] = t
        rays = rays[~hit[rays]]
    return hit, tri_out, bary_out, t_out


@dataclasses.dataclass(frozen=True)
class SurfaceMap:
    """Points expressed on a triangle mesh (here: target vertices on the deformed source).

    Attributes:
        tri: ``(K,)`` int64 triangle ids of the surface mesh.
        bary: ``(K, 3)`` barycentric coordinates (non-negative, sum 1).
        offset: ``(K,)`` signed distance from the point to its surface point along the ray, mm
            (for closest-point fallbacks the unsigned distance).
        by_ray: ``(K,)`` bool: found by the fixed-length ray (True) or by closest point.
    """

    tri: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    by_ray: np.ndarray

    def positions(self, vertices, triangles) -> np.ndarray:
        """``(K, 3)`` the surface points on a mesh with these ``(V, 3)`` vertices (mm)."""
        v = np.asarray(vertices, dtype=np.float64)
        return np.einsum("kj,kjd->kd", self.bary, v[np.asarray(triangles)[self.tri]])


def map_onto_surface(points, normals, length: float, vertices, triangles) -> SurfaceMap:
    """Project points onto a mesh with fixed-length rays along their normals (both ways; the
    nearest hit wins), falling back to the closest surface point where the ray misses.

    Arguments:
        points: ``(K, 3)`` mm; normals: ``(K, 3)``; length: ray length, mm.
        vertices, triangles: the surface, ``(V, 3)`` mm and ``(F, 3)``.

    Returns:
        :class:`SurfaceMap`.
    """
    p = np.asarray(points, dtype=np.float64)
    surface = TriMesh(np.asarray(vertices, dtype=np.float64), np.asarray(triangles), validate=False)
    hit, tri, bary, t = cast_segments(p, normals, length, mesh=surface)
    miss = np.flatnonzero(~hit)
    offset = np.where(hit, t, 0.0)
    if miss.size:
        sp, dist = surface.closest_points(p[miss])
        tri[miss] = np.asarray(sp.tri, dtype=np.int64)
        bary[miss] = np.asarray(sp.bary, dtype=np.float64)
        offset[miss] = dist
    return SurfaceMap(tri=tri, bary=bary, offset=offset, by_ray=hit)
