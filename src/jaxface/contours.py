"""Eye and lip contour extraction on triangle meshes (thesis sec. 6.2.1), for motion cloning.

A *feature* (an eye, the mouth) is described by two *arcs*, upper and lower, each a list of
landmark names from the feature's right end (-x, subject's right) to its left end (+x). The
landmarks are snapped to their nearest mesh vertices (the waypoints) and each arc is turned
into a path of mesh vertices by one of three methods, recorded as the contour's ``kind``:

* ``"loop"``: if the arcs have no interior waypoints (only the two corners) and a boundary loop
  of the mesh (an eye or mouth opening) passes within ``loop_tol`` of both corners, the loop is
  split at the loop vertices nearest to the corners; its upper and lower halves are the arcs.
* ``"path"``: otherwise the arc joins the waypoints by edge-graph shortest paths (default,
  ``method="geodesic"``), or by the thesis's greedy walk (``method="greedy"``): from the
  current vertex step to the neighbour ``n`` minimising ``|v + h (n - v)/|n - v| - end|``
  (``h`` the mean edge length at ``v``; the thesis uses a unit step), never revisiting a
  vertex, finishing along the shortest path if it gets stuck. The greedy walk is what the
  thesis does, but on dense meshes with inner-lip surfaces it wanders (on the ICT face it
  took 186 vertices for a 50 mm lip arc, and different paths on two meshes of the same
  topology), so the shortest path is the default.
* ``"lip"``: the thesis's inner-lip walk (:func:`lip_path`), used for a mouth given only by
  its corners on a mesh without a mouth opening.

All coordinates are millimetres; the frame is +y up, the face looks along +z, the subject's
left is +x. Two contours of the same feature on two meshes are matched by arc length
(:func:`match_arcs`) only when their kinds agree; callers skip mismatched features (an open
eye hole on one mesh, a closed eye surface on the other) rather than pairing unlike curves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .errors import LandmarkError, MeshError
from .landmarks import Landmarks

__all__ = [
    "BOSPHORUS_CONTOURS",
    "MULTIPIE68_CONTOURS",
    "Contour",
    "greedy_path",
    "lip_path",
    "loop_arcs",
    "extract_contour",
    "extract_contours",
    "arc_length_fractions",
    "resample_polyline",
    "match_arcs",
    "closest_on_polyline",
    "match_nearest",
]

#: default feature specification for the Bosphorus landmark labels: feature name ->
#: (upper arc, lower arc), each a landmark list from the feature's -x end to its +x end
BOSPHORUS_CONTOURS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "eye_right": (
        ("Outer right eye corner", "Inner right eye corner"),
        ("Outer right eye corner", "Inner right eye corner"),
    ),
    "eye_left": (
        ("Inner left eye corner", "Outer left eye corner"),
        ("Inner left eye corner", "Outer left eye corner"),
    ),
    "mouth": (
        ("Right mouth corner", "Upper lip inner middle", "Left mouth corner"),
        ("Right mouth corner", "Lower lip inner middle", "Left mouth corner"),
    ),
}

#: the same for the 68 Multi-PIE points named by their 0-based index as strings ("0".."67"):
#: eyes through the eyelid points, mouth through the inner-lip points
MULTIPIE68_CONTOURS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "eye_right": (("36", "37", "38", "39"), ("36", "41", "40", "39")),
    "eye_left": (("42", "43", "44", "45"), ("42", "47", "46", "45")),
    "mouth": (("48", "61", "62", "63", "54"), ("48", "67", "66", "65", "54")),
}


@dataclasses.dataclass(frozen=True)
class Contour:
    """One feature's contour on one mesh.

    Attributes:
        name: feature name (``"eye_left"``, ``"mouth"``, ...).
        kind: ``"loop"``, ``"path"`` or ``"lip"`` (how it was extracted, see the module doc).
        upper: ``(a,)`` int64 vertex ids of the upper arc, from the -x end to the +x end.
        lower: ``(b,)`` int64 vertex ids of the lower arc, same ends.
    """

    name: str
    kind: str
    upper: np.ndarray
    lower: np.ndarray

    @property
    def vertices(self) -> np.ndarray:
        """All contour vertex ids (unique, sorted)."""
        return np.unique(np.concatenate([self.upper, self.lower]))


# ------------------------------------------------------------------------------------------
# graph helpers
# ------------------------------------------------------------------------------------------
def _ring(mesh):
    indptr, indices = mesh.one_ring
    return indptr, indices


def _shortest_path(mesh, start: int, end: int) -> list[int]:
    """Edge-length Dijkstra path from start to end (inclusive), or raise if disconnected."""
    e = mesh.edges
    w = np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1)
    nv = mesh.n_vertices
    g = coo_matrix((np.maximum(w, 1e-12), (e[:, 0], e[:, 1])), shape=(nv, nv)).tocsr()
    _, pred = dijkstra(g, directed=False, indices=int(start), return_predecessors=True)
    if end != start and pred[end] < 0:
        raise MeshError(
            f"no path on the mesh edge graph between vertices {start} and {end}: they are on "
            "different connected components. Check the landmarks of this feature.",
            problem="disconnected",
            elements=(start, end),
        )
    path = [int(end)]
    while path[-1] != start:
        path.append(int(pred[path[-1]]))
    return path[::-1]


def greedy_path(mesh, start: int, end: int, *, step: float | None = None) -> np.ndarray:
    """The thesis's greedy eye-contour walk from vertex ``start`` to vertex ``end``.

    At each vertex ``v`` the next vertex is the unvisited neighbour ``n`` minimising
    ``|v + h (n - v)/|n - v| - end|``, with ``h`` = ``step`` (mm) or, by default, the mean
    length of the edges at ``v``. If every neighbour was visited (a dead end) the path
    finishes along the Dijkstra shortest path, so the walk always terminates.

    Arguments:
        mesh: a :class:`jaxface.mesh.TriMesh` (mm).
        start, end: vertex ids.

    Returns:
        ``(k,)`` int64 vertex ids from ``start`` to ``end`` inclusive; consecutive ids share an
        edge.
    """
    V = mesh.vertices
    indptr, indices = _ring(mesh)
    start, end = int(start), int(end)
    path = [start]
    visited = {start}
    v = start
    target = V[end]
    for _ in range(mesh.n_vertices):
        if v == end:
            break
        nb = indices[indptr[v] : indptr[v + 1]]
        nb = np.array([n for n in nb if n not in visited], dtype=np.int64)
        if nb.size == 0:
            tail = _shortest_path(mesh, v, end)
            path.extend(tail[1:])
            return np.asarray(path, dtype=np.int64)
        if end in nb:
            nxt = end
        else:
            e = V[nb] - V[v]
            ln = np.linalg.norm(e, axis=1)
            h = float(step) if step is not None else float(ln.mean())
            d = np.linalg.norm(V[v] + h * e / np.maximum(ln, 1e-300)[:, None] - target, axis=1)
            nxt = int(nb[np.argmin(d)])
        path.append(nxt)
        visited.add(nxt)
        v = nxt
    if path[-1] != end:  # pragma: no cover - bounded by V steps
        tail = _shortest_path(mesh, path[-1], end)
        path.extend(tail[1:])
    return np.asarray(path, dtype=np.int64)


def _path_through(mesh, waypoints: Sequence[int], method: str = "geodesic") -> np.ndarray:
    out = [int(waypoints[0])]
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        if method == "greedy":
            seg = greedy_path(mesh, a, b)
        elif method == "geodesic":
            seg = np.asarray(_shortest_path(mesh, int(a), int(b)), dtype=np.int64)
        else:
            raise ValueError(f"unknown contour path method {method!r}; use 'geodesic' or 'greedy'.")
        out.extend(int(x) for x in seg[1:])
    return np.asarray(out, dtype=np.int64)


def lip_path(mesh, start: int, end: int, upper: bool) -> np.ndarray:
    """The thesis's inner-lip walk from the right mouth corner ``start`` to the left ``end``.

    With ``dir`` the image-plane (x, y) direction from start to end, each step goes to the
    unvisited neighbour whose image-plane step makes the smallest (upper lip) or the greatest
    (lower lip) signed angle with ``dir``, among those within (-90°, 90°) of it. On a mesh
    whose lips are not connected this follows the lowest row of the upper lip / the highest
    row of the lower lip. The walk stops when it reaches ``end`` or passes it along ``dir``
    (then it finishes along the Dijkstra shortest path).

    Returns:
        ``(k,)`` int64 vertex ids from ``start`` to ``end`` inclusive.
    """
    V = mesh.vertices
    indptr, indices = _ring(mesh)
    start, end = int(start), int(end)
    d = (V[end] - V[start])[:2]
    dn = np.linalg.norm(d)
    if dn == 0:
        raise MeshError(
            f"the mouth corners (vertices {start}, {end}) coincide in the image plane; check "
            "the mouth landmarks.",
            problem="degenerate_feature",
            elements=(start, end),
        )
    d = d / dn
    s_end = float(d @ (V[end, :2] - V[start, :2]))
    path = [start]
    visited = {start}
    v = start
    for _ in range(mesh.n_vertices):
        if v == end:
            break
        nb = np.array(
            [n for n in indices[indptr[v] : indptr[v + 1]] if n not in visited], dtype=np.int64
        )
        if end in nb:
            path.append(end)
            v = end
            break
        if nb.size:
            w = V[nb, :2] - V[v, :2]
            ang = np.arctan2(d[0] * w[:, 1] - d[1] * w[:, 0], w @ d)
            ok = np.abs(ang) < np.pi / 2
        if nb.size == 0 or not ok.any():
            break
        cand, ang = nb[ok], ang[ok]
        nxt = int(cand[np.argmin(ang)] if upper else cand[np.argmax(ang)])
        path.append(nxt)
        visited.add(nxt)
        v = nxt
        if float(d @ (V[v, :2] - V[start, :2])) > s_end:
            break
    if path[-1] != end:
        path.extend(_shortest_path(mesh, path[-1], end)[1:])
    return np.asarray(path, dtype=np.int64)


def loop_arcs(mesh, loop: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Split a boundary loop at its vertices ``a`` and ``b`` into two arcs from ``a`` to ``b``.

    Returns:
        ``(upper, lower)`` int64 vertex-id arcs, both from ``a`` to ``b`` inclusive; ``upper``
        is the one lying higher (+y) relative to the chord ``a``-``b`` on average.
    """
    loop = np.asarray(loop, dtype=np.int64)
    ia = int(np.flatnonzero(loop == a)[0])
    ib = int(np.flatnonzero(loop == b)[0])
    n = loop.size
    fwd = loop[(ia + np.arange((ib - ia) % n + 1)) % n]
    bwd = loop[(ia - np.arange((ia - ib) % n + 1)) % n]
    V = mesh.vertices

    def height(arc):
        if arc.size <= 2:
            return 0.0
        return float(np.mean(V[arc[1:-1], 1]) - 0.5 * (V[a, 1] + V[b, 1]))

    return (fwd, bwd) if height(fwd) >= height(bwd) else (bwd, fwd)


# ------------------------------------------------------------------------------------------
# feature extraction
# ------------------------------------------------------------------------------------------
def _snap(mesh, points: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    return (
        cKDTree(mesh.vertices)
        .query(np.asarray(points, dtype=np.float64).reshape(-1, 3))[1]
        .astype(np.int64)
    )


def extract_contour(
    mesh,
    name: str,
    upper: Sequence[int] | np.ndarray,
    lower: Sequence[int] | np.ndarray,
    *,
    loop_tol: float = 0.25,
    use_loops: bool = True,
    method: str = "geodesic",
) -> Contour:
    """Extract one feature's contour through the given waypoint vertices.

    Arguments:
        mesh: :class:`jaxface.mesh.TriMesh` (mm).
        name: feature name; a name starting with ``"mouth"`` or ``"lip"`` enables the lip walk.
        upper, lower: waypoint vertex ids of the two arcs, each from the -x end to the +x end;
            both must start and end at the same two corner vertices.
        loop_tol: a boundary loop is used when it passes within ``loop_tol`` times the corner
            distance of both corners (and the arcs have no interior waypoints).
        use_loops: set False to ignore boundary loops.
        method: how waypoints are joined for ``"path"`` contours: ``"geodesic"`` (default,
            the edge-graph shortest path: stable under small changes of the mesh) or
            ``"greedy"`` (the thesis's walk, :func:`greedy_path`).

    Returns:
        the :class:`Contour`.
    """
    upper = [int(x) for x in upper]
    lower = [int(x) for x in lower]
    if len(upper) < 2 or len(lower) < 2 or upper[0] != lower[0] or upper[-1] != lower[-1]:
        raise LandmarkError(
            f"contour {name!r}: both arcs need at least two waypoints and must share their end "
            f"corners (got upper {upper}, lower {lower}); check the feature specification."
        )
    a, b = upper[0], upper[-1]
    if a == b:
        raise LandmarkError(
            f"contour {name!r}: both corners snap to the same vertex {a}; the landmarks of this "
            "feature are too close together for this mesh resolution."
        )
    V = mesh.vertices
    width = float(np.linalg.norm(V[a] - V[b]))
    corners_only = len(upper) == 2 and len(lower) == 2
    if use_loops and corners_only:
        for loop in mesh.boundary_loops:
            lv = V[loop]
            da = np.linalg.norm(lv - V[a], axis=1)
            db = np.linalg.norm(lv - V[b], axis=1)
            if da.min() <= loop_tol * width and db.min() <= loop_tol * width:
                la, lb = int(loop[np.argmin(da)]), int(loop[np.argmin(db)])
                if la == lb:
                    continue
                up, lo = loop_arcs(mesh, loop, la, lb)
                # connect the landmark corners to the loop
                head = (
                    _path_through(mesh, [a, la], method)[:-1] if la != a else np.zeros(0, np.int64)
                )
                tail = (
                    _path_through(mesh, [lb, b], method)[1:] if lb != b else np.zeros(0, np.int64)
                )
                up = np.concatenate([head, up, tail])
                lo = np.concatenate([head, lo, tail])
                return Contour(name, "loop", up, lo)
    if corners_only and (name.startswith("mouth") or name.startswith("lip")):
        return Contour(name, "lip", lip_path(mesh, a, b, True), lip_path(mesh, a, b, False))
    return Contour(
        name, "path", _path_through(mesh, upper, method), _path_through(mesh, lower, method)
    )


def extract_contours(
    mesh,
    landmarks,
    spec: Mapping[str, tuple[Sequence[str], Sequence[str]]] | None = None,
    *,
    loop_tol: float = 0.25,
    use_loops: bool = True,
    method: str = "geodesic",
) -> dict[str, Contour]:
    """Extract every feature of ``spec`` whose landmarks are all present.

    Arguments:
        mesh: :class:`jaxface.mesh.TriMesh` (mm).
        landmarks: :class:`jaxface.landmarks.Landmarks` or ``{name: (3,) mm}``.
        spec: ``{feature: (upper names, lower names)}``; default :data:`BOSPHORUS_CONTOURS`.

    Returns:
        ``{feature: Contour}`` (features with missing landmarks are left out).
    """
    lm = landmarks if isinstance(landmarks, Landmarks) else Landmarks.from_dict(landmarks)
    spec = BOSPHORUS_CONTOURS if spec is None else spec
    out: dict[str, Contour] = {}
    for name, (up, lo) in spec.items():
        names = list(up) + list(lo)
        if lm.missing(names):
            continue
        ids_up = _snap(mesh, lm.array(up))
        ids_lo = _snap(mesh, lm.array(lo))
        out[name] = extract_contour(
            mesh, name, ids_up, ids_lo, loop_tol=loop_tol, use_loops=use_loops, method=method
        )
    return out


# ------------------------------------------------------------------------------------------
# arc-length matching
# ------------------------------------------------------------------------------------------
def arc_length_fractions(points: np.ndarray) -> np.ndarray:
    """``(k,)`` cumulative arc length of a ``(k, 3)`` polyline divided by its length (0..1)."""
    p = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return s / s[-1] if s[-1] > 0 else np.linspace(0.0, 1.0, p.shape[0])


def resample_polyline(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points at arc-length fractions ``t`` (``(m,)`` in [0, 1]) of a ``(k, 3)`` polyline (mm)."""
    p = np.asarray(points, dtype=np.float64)
    s = arc_length_fractions(p)
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return np.stack([np.interp(t, s, p[:, k]) for k in range(3)], axis=1)


def match_arcs(
    src_vertices: np.ndarray, src: Contour, dst_vertices: np.ndarray, dst: Contour
) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences between two contours of the same feature by arc length.

    Every vertex of the source arcs is paired with the point at the same arc-length fraction
    of the matching target arc (upper with upper, lower with lower).

    Arguments:
        src_vertices: ``(Vs, 3)`` source mesh vertices, mm; ``src``: its contour.
        dst_vertices: ``(Vt, 3)`` target mesh vertices, mm; ``dst``: its contour.

    Returns:
        ``(ids (k,) int64 source vertex ids, points (k, 3) target points in mm)``, one row per
        distinct source vertex (a vertex on both arcs, e.g. a corner, keeps its first match).
    """
    ids, pts = [], []
    for sa, da in ((src.upper, dst.upper), (src.lower, dst.lower)):
        t = arc_length_fractions(src_vertices[sa])
        ids.append(sa)
        pts.append(resample_polyline(dst_vertices[da], t))
    ids = np.concatenate(ids)
    pts = np.concatenate(pts)
    _, first = np.unique(ids, return_index=True)
    first = np.sort(first)
    return ids[first], pts[first]


def closest_on_polyline(points: np.ndarray, polyline: np.ndarray, *, tangents: bool = False):
    """``(k, 3)`` closest points (mm) on a ``(m, 3)`` polyline to ``(k, 3)`` query points; with
    ``tangents=True`` also the ``(k, 3)`` unit direction of the segment each lies on (zero for
    a one-point polyline)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(polyline, dtype=np.float64)
    if a.shape[0] == 1:
        c = np.repeat(a, p.shape[0], axis=0)
        return (c, np.zeros_like(c)) if tangents else c
    s0, s1 = a[:-1], a[1:]
    e = s1 - s0
    ee = np.einsum("ij,ij->i", e, e)
    w = p[:, None, :] - s0[None]
    t = np.clip(np.einsum("kij,ij->ki", w, e) / np.where(ee > 0, ee, 1.0)[None], 0.0, 1.0)
    c = s0[None] + t[..., None] * e[None]
    best = np.argmin(np.einsum("kij,kij->ki", p[:, None] - c, p[:, None] - c), axis=1)
    out = c[np.arange(p.shape[0]), best]
    if not tangents:
        return out
    d = e[best]
    return out, d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def match_nearest(
    src_points: np.ndarray, src: Contour, dst_vertices: np.ndarray, dst: Contour
) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences between two contours by proximity (thesis 6.2.2): each source contour
    vertex, at its roughly fitted position, is paired with the closest point of the matching
    target arc (upper with upper, lower with lower).

    Arguments:
        src_points: ``(Vs, 3)`` the source vertices *after* the rough fit, mm.
        src, dst: the source and target contours; dst_vertices: ``(Vt, 3)`` target vertices.

    Returns:
        ``(ids (k,) int64 source vertex ids, points (k, 3) target points in mm)``.
    """
    ids, pts = [], []
    for sa, da in ((src.upper, dst.upper), (src.lower, dst.lower)):
        ids.append(sa)
        pts.append(closest_on_polyline(src_points[sa], dst_vertices[da]))
    ids = np.concatenate(ids)
    pts = np.concatenate(pts)
    _, first = np.unique(ids, return_index=True)
    first = np.sort(first)
    return ids[first], pts[first]
