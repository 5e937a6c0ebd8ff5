"""The skin (thesis sec. 5.5-5.7): constraints, binding, influence map, eyelids, teeth collision.

Build time (NumPy):

* **constraints** with the thesis values: stretch on every edge and across adjacent triangles
  (0.15), bending (0.95), triangle area (0.95) and the skin volume (1.0), built with the
  :mod:`jaxface.pbd` constraint kinds on the part of the skin that can move;
* **binding**: each skin vertex casts a ray along its (smoothed) normal, outward first against
  the muscles, then inward against the muscles (the first surface met, i.e. the most
  superficial) and then the skull (cranium or mandible); the hit becomes a surface point and
  the vertex is tied to it by an anchor (stiffness 0.2). The thesis adds a particle ``q`` bound
  to the surface point and a stretch link ``p-q``; here ``q`` carries the rest offset
  ``p0 - sp0`` (the link has zero rest length), which makes the tie resist tangential sliding
  so that the quasi-static problem is well posed;
* **tissue footprint**: the anchor displacement of a vertex is the geodesic-Gaussian average
  (sigma ``footprint_mm``, one value or a ``(lower, upper)`` pair blended from the eyes up to
  the brows, :func:`footprint_sigma`) of the displacements of the surface points bound around
  it, a model of the fat layer that spreads a muscle's pull over the skin (without it the skin
  would shear sharply along every muscle border); the wide rows average over geodesic clusters
  of vertices instead of single vertices (:func:`footprint_operator`), for speed;
* **fat volume** (our addition, after the volume preservation of Lee, Terzopoulos and Waters
  1995): the offset ``p0 - sp0`` is the fat between the skin and its surface point; where the
  bound surface points around a vertex squeeze together its fat thickens, where they spread it
  thins, keeping area x thickness (:func:`fat_thickness`, gain ``fat_volume``, one value or a
  ``(lower, upper)`` pair like the footprint);
* **influence map**: ``w = 1 - smoothstep(d / radius)`` of the normalised geodesic distance
  ``d`` from the vertices bound to a muscle or to the mandible; it scales each vertex's anchor
  displacement (thesis line 17 scales the particle's displacement; scaling the target keeps
  the final state consistent with the collisions), and vertices with ``w = 0`` are kinematic;
* **eyelids**: vertices within normalised geodesic distance 0.04 (tunable) of the eye border
  rotate about the axis through the eye corners (moved back onto the eyeball centre), upper
  lid above the axis, lower lid below, with a smooth falloff toward the threshold and a taper
  to no rotation at the corners themselves (:data:`LID_CORNER_TAPER`: the lids hinge there);
* **teeth**: convex hulls of the upper and lower teeth (:func:`jaxface.pbd.hull_planes`); the
  lower hull moves with the jaw (:func:`jaxface.pbd.transform_planes`); lip vertices inside a
  hull are pushed out through the nearest face (unilateral, resolved fully every sweep).

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from .. import pbd
from .._arrays import to_jax
from ..errors import RigError
from ..mesh import TriMesh
from ..rigid import rotate_about_axes
from .frame import FaceFrame
from .geometry import segment_cast, smooth_normals
from .skull import head_centre

__all__ = [
    "SKIN_STIFFNESS",
    "SkinSystem",
    "bind_skin",
    "influence_map",
    "footprint_matrix",
    "footprint_clusters",
    "footprint_operator",
    "Footprint",
    "footprint_sigma",
    "mirror_vertices",
    "eyelid_vertices",
    "build_skin_system",
    "skin_targets",
    "solve_skin",
    "vertex_areas",
    "fat_thickness",
]

#: Range of the fat layer's thickness factor (:func:`fat_thickness`): the layer at most halves
#: or doubles.
FAT_RATIO_RANGE = (0.5, 2.0)
#: Fraction of the eye width, from each corner, over which the lid rotation grows from 0 to
#: full (:func:`eyelid_vertices`); 0 turns the taper off. The tapered lids move less, and the
#: fit sees the lid controls less: the synthetic round trip's condition number on the ICT
#: face went from 217 to 1590 (its smallest singular value is a lid control held at 0).
LID_CORNER_TAPER = 0.4
#: Thesis skin stiffness values (sec. 5.5).
SKIN_STIFFNESS = dict(
    stretch=0.15, cross=0.15, bend=0.95, area=0.95, anchor=0.2, volume=1.0, damping=0.2
)


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

    def cast(ids, origins, dirs, length, targets, sign):
        for s in targets:
            h = segment_cast(registry.meshes[s], origins, dirs, length)
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
        mv, mt, owner, off = [], [], [], 0
        for s in muscles:
            m = registry.meshes[s]
            mv.append(m.vertices)
            mt.append(m.triangles + off)
            owner.append(np.full(m.n_triangles, s))
            off += m.n_vertices
        union = TriMesh(np.concatenate(mv), np.concatenate(mt), validate=False)
        tri_owner = np.concatenate(owner)
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
            spts, dist = registry.meshes[s].closest_points(x[todo])
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


def _edge_lengths(skin: TriMesh) -> np.ndarray:
    e = skin.edges
    return np.linalg.norm(skin.vertices[e[:, 0]] - skin.vertices[e[:, 1]], axis=1)


def _geodesic_graph(skin: TriMesh) -> sp.csr_matrix:
    """The skin's edge graph weighted by edge length (mm, floored at 1e-9), for Dijkstra."""
    return _edge_matrix(skin, np.maximum(_edge_lengths(skin), 1e-9))


def _edge_matrix(skin: TriMesh, values: np.ndarray) -> sp.csr_matrix:
    """Symmetric ``(V, V)`` sparse matrix with ``values`` (one per edge) on the mesh edges."""
    e = skin.edges
    V = skin.n_vertices
    g = sp.coo_matrix(
        (
            np.concatenate([values, values]),
            (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])),
        ),
        shape=(V, V),
    ).tocsr()
    return cast(sp.csr_matrix, g)


def membrane_interpolation(skin: TriMesh, free: np.ndarray):
    """Harmonic interpolation into the ``free`` vertices from the vertices around them.

    Solves the graph Laplace equation (edge weights ``1 / length``, all positive, so every
    value is a convex combination of the border values and the interpolated field has no
    folds where the border has none) with the free vertices' neighbours as the border.

    Args:
        skin: the skin mesh, mm.
        free: ``(V,)`` bool, the vertices to interpolate. Connected pieces of it that touch no
            other vertex are left out.

    Returns:
        ``(ids (F,), border (B,), H (F, B))``: ``x[ids] = H @ x[border]`` interpolates a field
        ``x``; the rows of ``H`` sum to 1.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    free = np.asarray(free, bool)
    L = _edge_lengths(skin)
    W = _edge_matrix(skin, 1.0 / np.maximum(L, 1e-6 * max(float(np.median(L)), 1e-12)))
    ids = np.flatnonzero(free)
    if ids.size:
        # drop the free pieces without a border (nothing to interpolate from)
        rows = W[ids]
        n, lab = connected_components(rows[:, ids], directed=False)
        touches = np.zeros(n, bool)
        touches[lab[np.asarray(rows[:, ~free].sum(axis=1)).ravel() > 0]] = True
        ids = ids[touches[lab]]
    if ids.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 0))
    rows = W[ids]
    border = np.setdiff1d(rows.indices, ids)
    deg = np.asarray(rows.sum(axis=1)).ravel()
    A = (sp.diags(deg) - rows[:, ids]).tocsc()
    H = splu(A).solve(rows[:, border].toarray())
    return ids, border, H


def footprint_matrix(skin: TriMesh, sigma, *, chunk: int = 512) -> sp.csr_matrix:
    """Row-normalised geodesic Gaussian ``(V, V)`` sparse matrix (support ``2.5 sigma`` mm).

    Geodesic (edge-graph Dijkstra) rather than Euclidean neighbourhoods, so that the upper
    and lower lips, or the two eyelids, do not average across the mouth or eye openings.
    ``sigma`` (mm) is a scalar or one value per vertex (the width of that vertex's row).
    """
    V = skin.n_vertices
    sig = np.broadcast_to(np.asarray(sigma, np.float64), (V,))
    if not np.all(np.isfinite(sig)) or sig.min() <= 0:
        raise RigError("the tissue footprint's sigma must be positive and finite (mm).")
    g = _geodesic_graph(skin)
    rows, cols, vals = [], [], []
    for s in range(0, V, chunk):
        ids = np.arange(s, min(V, s + chunk))
        sr = sig[ids]
        D = dijkstra(g, directed=False, indices=ids, limit=2.5 * float(sr.max()))
        keep = np.isfinite(D) & (D <= 2.5 * sr[:, None])
        r, c = np.nonzero(keep)
        rows.append(ids[r])
        cols.append(c)
        vals.append(np.exp(-0.5 * (D[r, c] / sr[r]) ** 2))
    M = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(V, V)
    )
    rs = np.asarray(M.sum(axis=1)).ravel()
    return sp.diags(1.0 / np.maximum(rs, 1e-300)) @ M


def mirror_vertices(skin: TriMesh, frame: FaceFrame, tol_mm: float = 1e-6) -> np.ndarray | None:
    """``(V,)`` each vertex's mirror image across the face's mid-sagittal plane, when the
    skin is a mirror image of itself to ``tol_mm`` (mm); None otherwise (scans, the ICT face)."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    R = frame.to_local(skin.vertices)
    d, m = cKDTree(R).query(R * np.array([-1.0, 1.0, 1.0]))
    if d.max() > tol_mm or np.any(m[m] != np.arange(len(m))):
        return None
    return m


def footprint_clusters(
    skin: TriMesh, spacing_mm: float, mirror: np.ndarray | None = None
) -> sp.csr_matrix:
    """Geodesic clusters of the skin's vertices, about ``spacing_mm`` (mm) across.

    Centres are picked greedily (vertex order): a vertex farther than ``spacing_mm / 2``
    along the surface from every centre so far becomes one. Every vertex then joins the centre
    nearest along the surface (edge-graph Dijkstra), so a cluster never reaches across the
    mouth or eye openings, and every vertex lies within ``spacing_mm / 2`` of its centre.

    With ``mirror`` ``(V,)`` (each vertex's mirror image on a symmetric face) the clusters are
    mirror images too: a centre's mirror image becomes a centre with it, and a vertex equally
    far from two centres (on the mid-line: from a centre and its mirror image) belongs half
    to each.

    Returns:
        ``(V, C)`` membership: row ``v`` holds the share of vertex ``v`` in each cluster (rows
        sum to 1), the columns are ordered by centre vertex.
    """
    if not np.isfinite(spacing_mm) or spacing_mm <= 0:
        raise RigError(
            f"the footprint's cluster spacing must be positive and finite (mm), got {spacing_mm!r}."
        )
    V = skin.n_vertices
    g = _geodesic_graph(skin)
    covered = np.zeros(V, bool)
    centres = []
    for v in range(V):
        if covered[v]:
            continue
        pick = [v] if mirror is None else sorted({v, int(mirror[v])})
        centres += pick
        covered |= np.isfinite(
            dijkstra(g, directed=False, indices=pick, limit=0.5 * spacing_mm)
        ).any(axis=0)
    centres = np.asarray(sorted(centres), np.int64)
    _, _, src = dijkstra(
        g, directed=False, indices=centres, min_only=True, return_predecessors=True
    )
    own = np.searchsorted(centres, src)
    rows, cols = [np.arange(V)], [own]
    if mirror is not None:
        cmirror = np.searchsorted(centres, np.asarray(mirror)[centres])
        other = cmirror[own[np.asarray(mirror)]]  # the mirror image of the mirror vertex's cluster
        rows.append(np.arange(V))
        cols.append(other)
    r, c = np.concatenate(rows), np.concatenate(cols)
    P = sp.csr_matrix((np.ones(len(r)), (r, c)), shape=(V, len(centres)))
    P.data = np.minimum(P.data, 1.0)  # a vertex counted twice for one cluster
    return sp.diags(1.0 / np.asarray(P.sum(axis=1)).ravel()) @ P


#: A footprint row whose sigma is at least this many cluster widths draws on clusters
#: (:func:`footprint_operator`).
CLUSTER_RATIO = 1.5


@dataclass(frozen=True)
class Footprint:
    """The tissue footprint as an operator (:func:`footprint_operator`): ``out = W @ s`` with
    ``s = [d; P^T d]``, the ``(V,)`` per-vertex values ``d`` followed by their ``(C,)`` sums
    over each cluster (``P`` the ``(V, C)`` membership, :func:`footprint_clusters`).

    Attributes:
        rows, cols, vals: ``W`` in COO form, ``(V, V + C)``; a row draws either on single
            vertices (columns ``< V``) or on clusters (columns ``>= V``).
        member_v, member_c, member_w: ``P`` in COO form (empty when no row uses clusters).
        n_clusters: ``C``.
    """

    rows: np.ndarray
    cols: np.ndarray
    vals: np.ndarray
    member_v: np.ndarray
    member_c: np.ndarray
    member_w: np.ndarray
    n_clusters: int

    def apply(self, d: np.ndarray) -> np.ndarray:
        """``W @ [d; P^T d]`` for ``d`` ``(V, ...)`` (NumPy reference of the JAX path)."""
        d = np.asarray(d, np.float64).reshape(len(d), -1)
        s = d
        if self.n_clusters:
            P = sp.csr_matrix(
                (self.member_w, (self.member_v, self.member_c)), shape=(len(d), self.n_clusters)
            )
            s = np.concatenate([d, P.T @ d])
        W = sp.csr_matrix((self.vals, (self.rows, self.cols)), shape=(len(d), s.shape[0]))
        return W @ s

    def dense(self, n_vertices: int) -> np.ndarray:
        """The equivalent ``(V, V)`` matrix (tests; memory grows as ``V^2``)."""
        return self.apply(np.eye(n_vertices))


def footprint_operator(
    skin: TriMesh, sigma, *, cluster_mm: float = 0.0, mirror: np.ndarray | None = None
) -> Footprint:
    """The row-normalised geodesic Gaussian footprint (:func:`footprint_matrix`), with the
    wide rows summed over clusters of vertices instead of single vertices.

    A row whose ``sigma`` (mm) is at least ``CLUSTER_RATIO * cluster_mm`` gives each cluster
    (:func:`footprint_clusters`, ``cluster_mm`` across, mirror images of each other with
    ``mirror``) the mean of its weights of the cluster's vertices, and is applied to the
    cluster sums: it averages a constant exactly, and a field that varies linearly over each
    cluster to within the covariance of the Gaussian and the field over a cluster. Such a row
    draws on several times fewer entries; the other rows are those of
    :func:`footprint_matrix`. ``cluster_mm = 0``: no clusters (the exact matrix).
    """
    if not np.isfinite(cluster_mm) or cluster_mm < 0:
        raise RigError(
            f"footprint_cluster_mm must be 0 (the exact footprint) or a positive width in mm, "
            f"got {cluster_mm!r}."
        )
    V = skin.n_vertices
    F = footprint_matrix(skin, sigma).tocsr()  # also checks sigma
    sig = np.broadcast_to(np.asarray(sigma, np.float64), (V,))
    wide = sig >= CLUSTER_RATIO * cluster_mm if cluster_mm > 0 else np.zeros(V, bool)
    none = np.zeros(0, np.int64)
    if not wide.any():
        F = F.tocoo()
        return Footprint(
            F.row.astype(np.int64), F.col.astype(np.int64), F.data, none, none, np.zeros(0), 0
        )
    P = footprint_clusters(skin, cluster_mm, mirror)
    C = cast(tuple[int, int], P.shape)[1]
    count = np.asarray(P.sum(axis=0)).ravel()
    narrow, wide_ids = np.flatnonzero(~wide), np.flatnonzero(wide)
    Fn = F[narrow].tocoo()
    # a wide row's weight of a cluster: the mean of its weights of the cluster's vertices
    Fw = (F[wide_ids] @ P @ sp.diags(1.0 / count)).tocoo()
    Pc = P.tocoo()
    return Footprint(
        np.concatenate([narrow[Fn.row], wide_ids[Fw.row]]).astype(np.int64),
        np.concatenate([Fn.col, V + Fw.col]).astype(np.int64),
        np.concatenate([Fn.data, Fw.data]),
        Pc.row.astype(np.int64),
        Pc.col.astype(np.int64),
        Pc.data,
        C,
    )


def _upper_face_blend(skin: TriMesh, frame: FaceFrame) -> np.ndarray:
    """``(V,)`` in [0, 1]: 0 up to the height of the inner eye corners, 1 from the height of
    the inner eyebrows, smoothstep in between (the lower/upper split of the face's tissue)."""
    y = frame.to_local(skin.vertices)[:, 1]

    def height(*names):
        return float(np.mean([frame.to_local(frame.points[n])[1] for n in names]))

    y0 = height("Inner left eye corner", "Inner right eye corner")
    y1 = height("Inner left eyebrow", "Inner right eyebrow")
    return _smoothstep(np.clip((y - y0) / max(y1 - y0, 1e-9), 0.0, 1.0))


def _lower_upper_field(
    skin: TriMesh,
    frame: FaceFrame,
    value,
    name: str,
    what: str,
    *,
    low: float,
    high: float = np.inf,
    strict: bool = False,
) -> np.ndarray:
    """``(V,)`` field of one value, or of a ``(lower, upper)`` pair blended from the eyes up to
    the brows (:func:`_upper_face_blend`).

    Raises:
        RigError: not one number or a pair of numbers in ``[low, high]`` (above ``low`` when
            ``strict``); ``what`` says what the numbers are.
    """
    v = np.atleast_1d(np.asarray(value, np.float64))
    below = (v.min() <= low if strict else v.min() < low) if v.size else True
    if v.shape not in ((1,), (2,)) or not np.all(np.isfinite(v)) or below or v.max() > high:
        raise RigError(
            f"{name} must be a number or a (lower, upper) pair of {what}, got {value!r}."
        )
    if v.size == 1 or v[0] == v[1]:
        return np.full(skin.n_vertices, v[0])
    return v[0] + (v[1] - v[0]) * _upper_face_blend(skin, frame)


def footprint_sigma(skin: TriMesh, frame: FaceFrame, footprint_mm) -> np.ndarray:
    """``(V,)`` sigma (mm) of the tissue footprint of each vertex.

    ``footprint_mm`` (reference mm, scaled by the face) is one value, or a pair
    ``(lower, upper)``: ``lower`` up to the height of the inner eye corners, ``upper`` from
    the height of the inner eyebrows, blended smoothly in between. The pair lets the
    forehead, where the tissue moves as a broad plate over the frontalis, spread a muscle's
    pull further than around the eyes, the cheeks and the mouth, where it stays local.

    Raises:
        RigError: not a positive number or a pair of positive numbers.
    """
    return (
        _lower_upper_field(
            skin,
            frame,
            footprint_mm,
            "footprint_mm",
            "positive numbers (reference mm)",
            low=0.0,
            strict=True,
        )
        * frame.mean_scale
    )


def eyelid_vertices(skin: TriMesh, frame: FaceFrame, side: str, threshold: float = 0.04):
    """The lid vertices of one eye (thesis sec. 5.5.1).

    The eye border is the skin boundary loop around the eye (when the skin has an eye
    opening) or else the vertices closest to the segment between the eye corners. Vertices
    whose normalised geodesic distance from the border is below ``threshold`` are lid
    vertices.

    Returns:
        ``(ids (K,), falloff (K,) in (0, 1], upper (K,) bool)``; the falloff is the
        geodesic one times a taper that is 0 at the eye corners and 1 from
        :data:`LID_CORNER_TAPER` of the eye width inward.
    """
    inner = frame.points[f"Inner {side} eye corner"]
    outer = frame.points[f"Outer {side} eye corner"]
    centre = 0.5 * (inner + outer)
    width = np.linalg.norm(outer - inner)
    border = None
    for loop in skin.boundary_loops:
        c = skin.vertices[loop].mean(axis=0)
        ext = np.ptp(skin.vertices[loop], axis=0).max()
        if np.linalg.norm(c - centre) < 0.35 * width and ext < 2.0 * width:
            border = np.asarray(loop)
            break
    if border is None:
        # vertices closest to the corner-to-corner segment
        x = skin.vertices
        u = outer - inner
        t = np.clip(((x - inner) @ u) / (u @ u), 0.0, 1.0)
        dist = np.linalg.norm(x - (inner + t[:, None] * u), axis=1)
        border = np.flatnonzero(dist < max(np.sort(dist)[min(8, len(dist) - 1)], 1e-9) + 1e-9)
    d = skin.geodesic_distance(border, normalise=True)
    ids = np.flatnonzero(d < threshold)
    fall = 1.0 - _smoothstep(d[ids] / threshold)
    rel = skin.vertices[ids] - inner
    u = (outer - inner) / width
    # the lids hinge at the eye corners: the pivot axis lies on the eyeball centre, 12 mm
    # behind the corners, so an untapered rotation would swing the corner vertices too and
    # fold the upper lid over the lower one there (on the ICT face AU43 inverted 90 skin
    # triangles and AU7 54; tapered, 28 and 2)
    if LID_CORNER_TAPER > 0:
        t = (rel @ u) / width
        fall = fall * _smoothstep(np.clip(np.minimum(t, 1.0 - t) / LID_CORNER_TAPER, 0.0, 1.0))
    # upper / lower: above or below the corner line (in the face's up direction)
    up_dir = frame.axes[1] - u * (frame.axes[1] @ u)
    upper = rel @ up_dir > 0
    return ids, np.maximum(fall, 1e-3), upper


class SkinSystem(eqx.Module):
    """Run-time skin data (JAX pytree). See :func:`build_skin_system`.

    Attributes:
        rest: ``(V, 3)`` rest skin, mm.
        bind_ids, bind_w: ``(V, 3)`` support ids / weights of each vertex's surface point.
        bind_offset: ``(V, 3)`` rest offset ``p0 - sp0``, mm.
        fp_rows, fp_cols, fp_vals: the footprint operator's matrix (COO, :class:`Footprint`);
            fp_member_v, fp_member_c, fp_member_w: the cluster membership (COO); fp_count:
            ``(C,)`` vertices per cluster (its length is the static ``C``); all ``(0,)``
            without clusters.
        influence: ``(V,)``; inv_mass: ``(V,)`` (0 = kinematic).
        anchors: the engine's anchor group of every vertex (stiffness ``(V,)``; targets set
            per solve from :func:`skin_targets`).
        lid_ids, lid_fall, lid_pivot, lid_axis, lid_ctrl_angles: eyelids.
        puff_dir: ``(V, 3)`` cheek-puff displacement per unit pressure, mm.
        mem_ids, mem_border, mem_H: the unsupported skin whose targets are interpolated from
            its border (:func:`membrane_interpolation`): ``(F,)``, ``(B,)``, ``(F, B)``.
        fat_tri, fat_area0, fat_gain, fat_ratio: the fat layer (:func:`fat_thickness`):
            ``(T, 3)`` triangles (none when off), ``(V,)`` rest areas mm^2, ``(V,)`` gains,
            the static ratio range.
        groups: the engine's stretch/cross, area, bending groups (:mod:`jaxface.pbd`);
            volume: the skin volume group (or None; its rest volume is set per solve).
        upper_hull, lower_hull: hull collision groups (or None); lower_planes: rest planes.
        iterations: static sweeps of the quasi-static solve.
        checkpoint: static; checkpoint every sweep for reverse mode
            (:func:`jaxface.pbd.iterate`; on by default, the muscles' off: see
            :class:`jaxface.anatomy.muscles.MuscleSystem`).
    """

    rest: jax.Array
    bind_ids: jax.Array
    bind_w: jax.Array
    bind_offset: jax.Array
    fp_rows: jax.Array
    fp_cols: jax.Array
    fp_vals: jax.Array
    fp_member_v: jax.Array
    fp_member_c: jax.Array
    fp_member_w: jax.Array
    fp_count: jax.Array
    influence: jax.Array
    inv_mass: jax.Array
    anchors: pbd.Group
    lid_ids: jax.Array
    lid_fall: jax.Array
    lid_upper: jax.Array
    lid_side: jax.Array
    lid_pivot: jax.Array
    lid_axis: jax.Array
    lid_angles: jax.Array
    puff_dir: jax.Array
    mem_ids: jax.Array
    mem_border: jax.Array
    mem_H: jax.Array
    fat_tri: jax.Array
    fat_area0: jax.Array
    fat_gain: jax.Array
    groups: tuple[pbd.Group, ...]
    volume: pbd.Group | None
    upper_hull: pbd.Group | None
    lower_hull: pbd.Group | None
    lower_planes: tuple | None
    iterations: int = eqx.field(static=True, default=12)
    chebyshev_rho: float = eqx.field(static=True, default=0.0)
    fat_ratio: tuple = eqx.field(static=True, default=FAT_RATIO_RANGE)
    checkpoint: bool = eqx.field(static=True, default=True)

    @property
    def n_vertices(self) -> int:
        return int(self.rest.shape[0])


def _hull_group(
    teeth: TriMesh | None,
    skin_x: np.ndarray,
    candidates_margin: float,
    n: int,
    inv_mass: np.ndarray,
    clearance: float,
):
    if teeth is None:
        return None, None
    N, d = pbd.hull_planes(teeth.vertices)
    sd = skin_x @ N.T - d[None]
    depth = sd.max(axis=1)  # signed distance-like (>0 outside)
    cand = np.flatnonzero((depth < candidates_margin) & (inv_mass > 0))
    if cand.size == 0:
        return None, (N, d)
    # vertices inside at rest keep their rest penetration (the rest state is collision-free)
    clr = np.minimum(clearance, depth[cand] - 1e-6)
    g = pbd.hull_constraints(cand, N, d, clearance=clr, stiffness=1.0)
    return pbd.make_group(g, n, name="teeth"), (N, d)


def build_skin_system(
    skin: TriMesh,
    frame: FaceFrame,
    binding: Binding,
    support_ids,
    support_w,
    *,
    influence: np.ndarray,
    eyelids: list,
    teeth=(None, None),
    footprint_mm: float | tuple = 3.5,
    footprint_cluster_mm: float = 0.0,
    stiffness: dict | None = None,
    bending: bool = True,
    iterations: int = 12,
    lid_stiffness: float = 0.9,
    puff_mm: float = 8.0,
    membrane: np.ndarray | None = None,
    fat_volume: float | tuple = 0.0,
) -> SkinSystem:
    """Assemble the skin system (NumPy build time).

    Args:
        skin: the skin mesh, mm; frame: its :class:`FaceFrame`.
        binding: :func:`bind_skin` result; support_ids, support_w: ``(V, 3)`` its surface
            points as rows of the support array (see :class:`~jaxface.anatomy.muscles.SupportPoints`).
        influence: ``(V,)`` influence map.
        eyelids: list of ``(ids, falloff, upper, side_index, pivot (3,), axis (3,), angles (C, 2))``
            where ``angles[c] = (upper_deg, lower_deg)`` per control ``c`` (0 for non-eyelid
            controls).
        teeth: ``(upper, lower)`` teeth meshes or None.
        footprint_mm: sigma of the tissue footprint (reference mm), or a ``(lower, upper)``
            pair (:func:`footprint_sigma`).
        footprint_cluster_mm: width of the vertex clusters the wide footprint rows draw on
            (reference mm; :func:`footprint_operator`); 0 = none.
        stiffness: overrides of :data:`SKIN_STIFFNESS`.
        bending: include the dihedral bending constraints.
        iterations: static sweeps of the quasi-static solve.
        lid_stiffness: anchor stiffness of the eyelid vertices.
        puff_mm: outward displacement of the cheeks at cheek-puff 1, mm.
        membrane: optional ``(V,)`` bool, skin with no bone or muscle under it whose targets
            are the harmonic interpolation of the targets around it (a stretched membrane)
            instead of its bound points; it is anchored with stiffness 1.
        fat_volume: in [0, 1], the fat layer's volume preservation (:func:`fat_thickness`):
            0 = off, 1 = full; one value, or a ``(lower, upper)`` pair blended like
            ``footprint_mm``.
    """
    fat_gain = _lower_upper_field(
        skin,
        frame,
        fat_volume,
        "fat_volume",
        "numbers in [0, 1] (0 = off, 1 = the fat layer keeps its volume)",
        low=0.0,
        high=1.0,
    )
    k = dict(SKIN_STIFFNESS)
    k.update(stiffness or {})
    x = skin.vertices
    V = x.shape[0]
    infl = np.asarray(influence, np.float64)
    dyn = infl > 1e-4
    if not dyn.any():
        raise RigError(
            "no skin vertex is under the influence of a muscle or the jaw: the "
            "muscle map and the skin do not overlap. Check the landmarks."
        )
    inv_mass = dyn.astype(np.float64)
    groups = []
    e = skin.edges
    pairs = skin.edge_pairs
    te = np.concatenate([e, pairs[:, 2:]]) if len(pairs) else e
    tk = np.concatenate([np.full(len(e), k["stretch"]), np.full(len(pairs), k["cross"])])
    keep = dyn[te].any(axis=1)
    groups.append(
        pbd.make_group(
            pbd.distance_constraints(te[keep], x, stiffness=tk[keep]),
            V,
            omega=1.5,
            name="skin stretch",
        )
    )
    tri = skin.triangles
    tkeep = dyn[tri].any(axis=1)
    if k["area"] > 0 and tkeep.any():
        groups.append(
            pbd.make_group(
                pbd.area_constraints(tri[tkeep], x, stiffness=k["area"]),
                V,
                omega=1.0,
                name="skin area",
            )
        )
    if bending and k["bend"] > 0 and len(pairs):
        bkeep = dyn[pairs].any(axis=1)
        groups.append(
            pbd.make_group(
                pbd.bending_constraints(pairs[bkeep], x, stiffness=k["bend"]),
                V,
                omega=1.0,
                name="skin bending",
            )
        )

    vol = None
    if k["volume"] > 0:
        vol = pbd.make_group(
            pbd.volume_constraint(tri, x, origin=head_centre(frame), stiffness=k["volume"]),
            V,
            name="skin volume",
        )
    # footprint
    F = footprint_operator(
        skin,
        footprint_sigma(skin, frame, footprint_mm),
        cluster_mm=float(footprint_cluster_mm) * frame.mean_scale,
        mirror=mirror_vertices(skin, frame),
    )
    # eyelids
    lid_ids, lid_fall, lid_upper, lid_side, piv, axs, angs = [], [], [], [], [], [], []
    for ids, fall, upper, side, pivot, axis, angles in eyelids:
        lid_ids.append(ids)
        lid_fall.append(fall)
        lid_upper.append(upper)
        lid_side.append(np.full(len(ids), side))
        piv.append(pivot)
        axs.append(axis)
        angs.append(angles)
    anchor_k = np.full(V, k["anchor"])
    if lid_ids:
        li = np.concatenate(lid_ids)
        anchor_k[li] = np.maximum(anchor_k[li], lid_stiffness * np.concatenate(lid_fall))
    # cheek puff: outward along the normal, weighted by a cheek bump around the buccal area
    n0 = smooth_normals(skin, 3)
    bump = np.zeros(V)
    for sgn in (1.0, -1.0):
        c = frame.to_world([sgn * 42.0, -58.0, 0.0])
        loc = frame.to_local(x)
        cl = frame.to_local(c)
        r2 = ((loc[:, 0] - cl[0]) / 22.0) ** 2 + ((loc[:, 1] - cl[1]) / 20.0) ** 2
        side_ok = (loc[:, 0] * sgn) > 8.0
        bump = np.maximum(bump, np.where(side_ok, np.exp(-r2 * 2.0), 0.0))
    puff = (puff_mm * frame.mean_scale) * bump[:, None] * n0 * infl[:, None]
    up_g, up_planes = _hull_group(teeth[0], x, 20.0 * frame.mean_scale, V, inv_mass, 0.3)
    lo_g, lo_planes = _hull_group(teeth[1], x, 30.0 * frame.mean_scale, V, inv_mass, 0.3)
    mem = np.zeros(V, bool) if membrane is None else (np.asarray(membrane, bool) & dyn)
    mem_ids, mem_border, mem_H = membrane_interpolation(skin, mem)
    anchor_k[mem_ids] = 1.0
    if mem_ids.size:
        # the membrane has no layer under it; its border, which it is interpolated from, keeps
        # its rest thickness too (a thickened border bulged the membrane's edge into 2 folds)
        fat_gain[mem_ids] = 0.0
        fat_gain[mem_border] = 0.0
    fat_tri = tri[tkeep] if fat_gain.max() > 0 else np.zeros((0, 3), np.int64)
    return SkinSystem(
        rest=to_jax(x),
        bind_ids=to_jax(support_ids),
        bind_w=to_jax(support_w),
        bind_offset=to_jax(x - binding.point),
        fp_rows=to_jax(F.rows),
        fp_cols=to_jax(F.cols),
        fp_vals=to_jax(F.vals),
        fp_member_v=to_jax(F.member_v),
        fp_member_c=to_jax(F.member_c),
        fp_member_w=to_jax(F.member_w),
        fp_count=to_jax(np.bincount(F.member_c, weights=F.member_w, minlength=F.n_clusters)),
        influence=to_jax(infl),
        inv_mass=to_jax(inv_mass),
        anchors=pbd.make_group(
            pbd.anchor_constraints(np.arange(V), x, stiffness=anchor_k), V, name="skin anchors"
        ),
        lid_ids=to_jax(np.concatenate(lid_ids) if lid_ids else np.zeros(0, np.int64)),
        lid_fall=to_jax(np.concatenate(lid_fall) if lid_fall else np.zeros(0)),
        lid_upper=to_jax(np.concatenate(lid_upper) if lid_upper else np.zeros(0, bool)),
        lid_side=to_jax(np.concatenate(lid_side) if lid_side else np.zeros(0, np.int64)),
        lid_pivot=to_jax(np.stack(piv) if piv else np.zeros((0, 3))),
        lid_axis=to_jax(np.stack(axs) if axs else np.zeros((0, 3))),
        lid_angles=to_jax(np.stack(angs) if angs else np.zeros((0, 1, 2))),
        puff_dir=to_jax(puff),
        mem_ids=to_jax(mem_ids),
        mem_border=to_jax(mem_border),
        mem_H=to_jax(mem_H),
        fat_tri=to_jax(fat_tri),
        fat_area0=to_jax(vertex_areas(binding.point, fat_tri, V)),
        fat_gain=to_jax(fat_gain),
        fat_ratio=tuple(float(v) for v in FAT_RATIO_RANGE),
        groups=tuple(groups),
        volume=vol,
        upper_hull=up_g,
        lower_hull=lo_g,
        lower_planes=(None if lo_planes is None else (to_jax(lo_planes[0]), to_jax(lo_planes[1]))),
        iterations=int(iterations),
    )


def skin_targets(sk: SkinSystem, G, activations, cheek_puff: jax.typing.ArrayLike = 0.0):
    """Anchor targets ``(V, 3)`` mm of the skin for the current support ``G``.

    Bound surface points evaluated on ``G``, offsets scaled by the fat layer's thickness
    (:func:`fat_thickness`), displacements averaged over the tissue
    footprint and scaled by the influence map, the membrane skin interpolated from its border,
    eyelid rotations and cheek puff added.
    """
    dt = G.dtype
    rest = sk.rest.astype(dt)
    sp_ = jnp.einsum("vk,vkd->vd", sk.bind_w.astype(dt), G[sk.bind_ids])
    offset = sk.bind_offset.astype(dt)
    if sk.fat_tri.shape[0]:
        fat = fat_thickness(sp_, sk.fat_tri, sk.fat_area0, sk.fat_gain, sk.fat_ratio)
        offset = offset * fat[:, None]
    disp = sp_ + offset - rest
    src = disp
    if sk.fp_count.shape[0]:
        sums = jax.ops.segment_sum(
            sk.fp_member_w.astype(dt)[:, None] * disp[sk.fp_member_v],
            sk.fp_member_c,
            num_segments=sk.fp_count.shape[0],
        )
        src = jnp.concatenate([disp, sums])
    disp = jax.ops.segment_sum(
        sk.fp_vals.astype(dt)[:, None] * src[sk.fp_cols], sk.fp_rows, num_segments=rest.shape[0]
    )
    disp = disp * sk.influence.astype(dt)[:, None]
    if sk.mem_ids.shape[0]:
        disp = disp.at[sk.mem_ids].set(sk.mem_H.astype(dt) @ disp[sk.mem_border])
    if sk.lid_ids.shape[0]:
        a = jnp.asarray(activations, dt)
        ang = jnp.einsum("c,scl->sl", a, sk.lid_angles.astype(dt)) * (jnp.pi / 180.0)  # (sides, 2)
        per = jnp.where(
            sk.lid_upper, ang[sk.lid_side, 0], ang[sk.lid_side, 1]
        ) * sk.lid_fall.astype(dt)
        p0 = rest[sk.lid_ids]
        rot = rotate_about_axes(
            p0, sk.lid_pivot.astype(dt)[sk.lid_side], sk.lid_axis.astype(dt)[sk.lid_side], per
        )
        disp = disp.at[sk.lid_ids].add(rot - p0)
    disp = disp + jnp.asarray(cheek_puff, dt) * sk.puff_dir.astype(dt)
    return rest + disp


def vertex_areas(points, tri, n: int, xp=np):
    """``(n,)`` mm^2: the summed area of the triangles ``tri`` ``(T, 3)`` around each vertex,
    with the vertices at ``points`` ``(n, 3)`` mm. NumPy (``xp=np``) or JAX (``xp=jnp``)."""
    if tri.shape[0] == 0:
        return xp.zeros(n)
    p = points[tri]  # (T, 3, 3)
    c = xp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    a = 0.5 * xp.sqrt(xp.sum(c * c, axis=1) + 1e-24)
    if xp is np:
        return np.bincount(tri.ravel(), weights=np.repeat(a, 3), minlength=n)
    return jax.ops.segment_sum(jnp.repeat(a, 3), tri.reshape(-1), num_segments=n)


def fat_thickness(surface_points, tri, area0, gain, ratio_range=FAT_RATIO_RANGE):
    """``(V,)`` factor on each skin vertex's tissue offset (the fat between the skin and the
    surface point it is bound to) that keeps the fat layer's volume.

    A prism of the layer with base area ``A`` and height ``h`` keeps ``A h`` when its base is
    squeezed or stretched: the volume preservation of Lee, Terzopoulos and Waters (1995),
    applied to the layer under the skin. ``A`` is the area of the bound surface points around
    the vertex over the skin's triangles, so where a muscle shortens, or the tissue ahead of a
    pulled mouth corner bunches up, the skin above it rises, and where the surface stretches
    (the lips around a widened mouth, the cheeks over an opened jaw) it sinks.

    The factor is ``(A0 / A) ** gain`` with ``A0 / A`` clipped to ``ratio_range``. A vertex in
    no triangle (``area0 = 0``) keeps 1. Zero-area triangles are safe (no NaN, also in the
    reverse pass).

    Arguments:
        surface_points: ``(V, 3)`` mm, the current bound surface points.
        tri: ``(T, 3)`` skin triangles.
        area0: ``(V,)`` mm^2, :func:`vertex_areas` of the rest surface points.
        gain: ``(V,)`` or scalar in [0, 1]: 1 keeps the volume, 0 is off.
        ratio_range: ``(low, high)`` bounds of ``A0 / A``.
    """
    dt = surface_points.dtype
    a0 = jnp.asarray(area0, dt)
    a = vertex_areas(surface_points, tri, a0.shape[0], xp=jnp)
    ok = a0 > 0
    lo, hi = ratio_range
    ratio = jnp.where(ok, a0 / jnp.maximum(a, jnp.where(ok, a0, 1.0) / hi), 1.0)
    return jnp.exp(jnp.asarray(gain, dt) * jnp.log(jnp.clip(ratio, lo, hi)))


def solve_skin(sk: SkinSystem, targets, R, t, *, iterations: int | None = None, x0=None):
    """Quasi-static skin solve: anchors to ``targets``, thesis constraints, teeth collisions.

    Each sweep of the engine (fused Jacobi, :func:`jaxface.pbd.sweep`) projects, in order:
    the anchors, stretch/cross, area, bending, the capped volume (its rest volume is the one
    the targets imply) and the two teeth hulls (the lower one moved with the jaw).

    Args:
        sk: the :class:`SkinSystem`.
        targets: ``(V, 3)`` anchor targets, mm (:func:`skin_targets`).
        R, t: jaw motion (moves the lower-teeth hull).
        iterations: static sweeps (default ``sk.iterations``).
        x0: optional warm start (default: the targets).

    Returns:
        ``(V, 3)`` mm.
    """
    iters = sk.iterations if iterations is None else int(iterations)
    dt = targets.dtype
    inv_mass = sk.inv_mass.astype(dt)
    rest = sk.rest.astype(dt)
    dyn = (inv_mass > 0)[:, None]
    x = jnp.where(dyn, targets, rest) if x0 is None else jnp.asarray(x0, dt)
    groups = (sk.anchors.set(target=targets),) + tuple(sk.groups)
    if sk.volume is not None:
        # the volume the underlying structures imply: the capped volume of the targets
        vol = sk.volume.c
        assert isinstance(vol, pbd.VolumeConstraint)
        vol = eqx.tree_at(lambda q: q.origin, vol, vol.origin.astype(dt))
        groups += (sk.volume.set(rest=vol.volume(jnp.where(dyn, targets, rest))),)
    if sk.upper_hull is not None:
        groups += (sk.upper_hull,)
    if sk.lower_hull is not None:
        assert sk.lower_planes is not None  # built together with the lower hull
        n, d = pbd.transform_planes(
            sk.lower_planes[0].astype(dt), sk.lower_planes[1].astype(dt), R.astype(dt), t.astype(dt)
        )
        groups += (sk.lower_hull.set(normals=n, offsets=d),)
    return pbd.iterate(
        lambda x: pbd.sweep(groups, x, inv_mass),
        x,
        iters,
        sk.chebyshev_rho,
        checkpoint_every=1 if sk.checkpoint else None,
    )
