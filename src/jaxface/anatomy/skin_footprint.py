"""The tissue footprint of the skin: geodesic-Gaussian averaging of the bound surface points'
displacements (:func:`footprint_matrix`, clustered :func:`footprint_operator`), its sigma per
vertex (:func:`footprint_sigma`), the membrane interpolation and the mirror map. Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..errors import RigError
from ..mesh import TriMesh
from .frame import FaceFrame
from .skin_binding import _smoothstep


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


def _geodesic_near(g: sp.csr_matrix, tree, ids: np.ndarray, limit: float):
    """The vertex pairs at most ``limit`` (mm) apart along the edge graph ``g`` (symmetric,
    edge weights the lengths between the points of the KD-tree ``tree``), from the sources
    ``ids``: ``(rows, cols, distances)``, ``rows`` indexing ``ids``.

    A path no longer than ``limit`` stays within ``limit`` of its source in space, so Dijkstra
    runs on the subgraph of the vertices within ``limit`` (and a rounding margin) of one of
    the sources: the same paths, and the same distances to the last digit, as on the whole
    graph, at a fraction of the cost. The graph is symmetric, so it runs as a directed one
    (no transposed copy).
    """
    reach = limit * (1.0 + 1e-9) + 1e-9
    sub = np.unique(np.concatenate(tree.query_ball_point(tree.data[ids], reach)))
    D = dijkstra(g[sub][:, sub], directed=True, indices=np.searchsorted(sub, ids), limit=limit)
    r, c = np.nonzero(np.isfinite(D))
    return r, sub[c], D[r, c]


def _within(g: sp.csr_matrix, points: np.ndarray, limit: float, chunk: int = 256):
    """``(V, V)`` pattern of the vertex pairs at most ``limit`` (mm) apart along the edge
    graph ``g`` of ``points`` ``(V, 3)`` mm (:func:`_geodesic_near`)."""
    V = len(points)
    tree = cKDTree(points)
    rows, cols = [], []
    for s in range(0, V, chunk):
        ids = np.arange(s, min(V, s + chunk))
        r, c, _ = _geodesic_near(g, tree, ids, limit)
        rows.append(ids[r])
        cols.append(c)
    r, c = np.concatenate(rows), np.concatenate(cols)
    return sp.csr_matrix((np.ones(len(r), bool), (r, c)), shape=(V, V))


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
    near = _within(g, skin.vertices, 0.5 * spacing_mm)
    covered = np.zeros(V, bool)
    centres = []
    for v in range(V):
        if covered[v]:
            continue
        pick = [v] if mirror is None else sorted({v, int(mirror[v])})
        centres += pick
        for c in pick:
            covered[near.indices[near.indptr[c] : near.indptr[c + 1]]] = True
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
