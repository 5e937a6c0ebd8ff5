"""Facial motion cloning (thesis chapter 6): copy a source face's morph targets onto a new face.

Units mm; frame +y up, face looking along +z, subject's left at +x.

Pipeline (thesis sec. 6.2-6.3), :func:`clone_motion`:

1. **Landmarks.** The named landmarks common to both faces (any set: the thesis's MPEG-4
   FDPs, our Bosphorus labels, the 68 Multi-PIE points) are the first correspondences
   ``(P_i, Q_i)``; a first RBF volume morph ``G`` (Hardy multiquadric with affine part, thesis
   sec. 3.4, :mod:`jaxface.rbf`) roughly fits the source into the target.
2. **Contours.** Eye and inner-lip contours are extracted on both meshes
   (:mod:`jaxface.contours`, thesis 6.2.1) and matched by arc length; every source contour
   vertex with its target point joins the set and ``G`` is refitted.
3. **Refinement** (6.2.3). A source vertex is *movable* if it moves in any morph target. Each
   iteration morphs the source with ``G``, casts fixed-length rays (``0.3125 * ENS0``, the
   MPEG-4 eye-nose separation, both ways along the deformed vertex normal) from the movable
   vertices onto the target, and inserts the ``125`` pairs with the largest error
   ``|Q_i - G(P_i)|`` (updating ``Q_i`` of pairs already present); ``G`` is refitted. It stops
   when an iteration inserts no new vertex (or after ``max_iterations``).
4. **Mapping** (6.3). Each target vertex is projected on the deformed source ``G(S_0)`` with
   the same fixed-length rays along the target normals (closest point where a ray misses) and
   expressed in barycentric coordinates of a source triangle.
5. **Cloning.** For each source morph target ``S_j``, ``G`` is applied to its moving vertices
   only, and each target vertex follows its source triangle.

Deviations from the thesis, all documented in the result:

* ``mode="displacement"`` (default) moves a target vertex by the barycentric interpolation of
  the source triangle's displacement ``G(S_j) - G(S_0)``; the thesis (``mode="thesis"``) sets
  it to the barycentric interpolation of the positions ``G(S_j)``, which also snaps the target
  vertex onto the source triangle's plane whenever that triangle moves. Both agree when the
  target lies exactly on the deformed source.
* landmark pairs are kept fixed during refinement (the user's correspondences are trusted);
  contour and refined pairs are updated as in the thesis.
* pairs are only inserted when their error exceeds ``error_tol`` (default ``0.01 * ENS0``), so
  an already fitted source stops the refinement at once.
* contours are joined along shortest edge paths rather than the thesis's greedy walk (which
  wanders on dense meshes), contour pairs far from the rough fit are dropped, and the whole
  contour step is undone when it makes the fit worse (reported in ``contours_skipped``).
* ray hits on target triangles facing away from the ray's source normal are ignored.
* the global head motion and the teeth/tongue affine transforms (thesis's last step) are not
  cloned: only surface morph targets.

Fixed-length ray casting (:func:`cast_segments`) goes through
:meth:`jaxface.mesh.TriMesh.ray_cast` bounded to the segment (r-tree candidates, exact
Möller-Trumbore), which is much faster than an unbounded ray cast for this purpose.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from . import contours as _contours
from .errors import LandmarkError, MeshError
from .landmarks import Landmarks
from .mesh import TriMesh
from .normals import vertex_normals
from .rbf import KernelName, Morph, fit_numpy

__all__ = [
    "SurfaceMap",
    "FitResult",
    "CloneResult",
    "as_trimesh",
    "eye_nose_separation",
    "cast_segments",
    "map_onto_surface",
    "fit_source_to_target",
    "clone_motion",
    "apply_clone",
    "clone_error",
    "delta_error",
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


# ------------------------------------------------------------------------------------------
# fitting the source into the target
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FitResult:
    """The refined source -> target volume morph and how it was obtained.

    Attributes:
        morph: the final :class:`jaxface.rbf.Morph` ``G`` (mm -> mm).
        rough_morph: the morph before refinement (landmarks and accepted contours).
        source_neutral: ``(Vs, 3)`` the source neutral vertices, mm.
        deformed: ``(Vs, 3)`` ``G`` applied to the source neutral vertices, mm.
        src_points, dst_points: ``(n, 3)`` the final correspondence set, mm.
        n_landmark_pairs, n_contour_pairs, n_refined_pairs: its composition.
        landmark_names: the landmark names used.
        contours_used: features whose contours were matched; ``contours_skipped``: feature ->
            reason.
        movable: ``(Vs,)`` bool movable source vertices.
        ens0: eye-nose separation of the target, mm; ``ray_length``: ``ray_factor * ens0``.
        iterations: refinement iterations run; ``converged``: stopped because nothing new
            was inserted.
        history: per step (0: landmarks, 1: + contours, 2..: refinement) a dict with the
            number of pairs, the number of movable vertices whose ray hit the target and the
            mean/max hit error (mm) *before* that step's refit.
        timings: seconds per stage.
    """

    morph: Morph
    rough_morph: Morph
    source_neutral: np.ndarray
    deformed: np.ndarray
    src_points: np.ndarray
    dst_points: np.ndarray
    n_landmark_pairs: int
    n_contour_pairs: int
    n_refined_pairs: int
    landmark_names: tuple[str, ...]
    contours_used: tuple[str, ...]
    contours_skipped: dict
    movable: np.ndarray
    ens0: float
    ray_length: float
    iterations: int
    converged: bool
    history: list
    timings: dict


def fit_source_to_target(
    source,
    target,
    source_landmarks,
    target_landmarks,
    *,
    movable=None,
    kernel: KernelName = "multiquadric",
    reg: float = 0.0,
    contour_spec=None,
    use_contours: bool = True,
    contour_matching: str = "arclength",
    contour_gate: float = 0.1,
    check_contours: bool = True,
    ray_factor: float = 0.3125,
    pairs_per_iteration: int = 125,
    max_iterations: int = 100,
    error_tol: float | None = None,
    ens0: float | None = None,
) -> FitResult:
    """Fit the source neutral face into the target neutral face (thesis 6.2.2-6.2.3).

    Arguments:
        source, target: neutral meshes (TriMesh, trimesh.Trimesh or (vertices, triangles)), mm.
        source_landmarks, target_landmarks: ``Landmarks`` or ``{name: (3,) mm}``; the names
            common to both (at least 4, not coplanar) are used.
        movable: ``(Vs,)`` bool mask of source vertices allowed into the refinement (default:
            all).
        kernel, reg: RBF kernel and ridge (:func:`jaxface.rbf.fit`); the thesis uses the Hardy
            ``"multiquadric"`` with exact interpolation (``reg=0``). The refined exact ``G``
            fits the surface but bends between its many surface centres, which distorts motion
            off the surface: on ICT identities (``benchmarks/bench_clone.py``) the transferred
            displacements are 12-14 % off with ``reg=0`` and 9-10.5 % with ``reg=1``, at the
            price of a looser surface fit (mean ray error 0.05 -> 0.2 mm).
        contour_spec: feature specification (default
            :data:`jaxface.contours.BOSPHORUS_CONTOURS`, with
            :data:`~jaxface.contours.MULTIPIE68_CONTOURS` tried when those names are absent).
        use_contours: set False to skip the contour enrichment.
        contour_matching: ``"arclength"`` (pair each source contour vertex with the target
            arc point at the same arc-length fraction) or ``"nearest"`` (the thesis: with the
            closest point of the target arc to its roughly fitted position).
        contour_gate: contour pairs whose target point is farther than ``contour_gate * ENS0``
            from the source vertex's roughly fitted position are dropped (mis-extracted
            contours).
        check_contours: keep the contour pairs only if they do not raise the mean ray error
            of the movable vertices (the thesis's step 1 is meant to improve the alignment);
            otherwise they are dropped and the reason is put in ``contours_skipped``.
        ray_factor: ray length as a fraction of the target's ENS0 (thesis: 0.3125).
        pairs_per_iteration: pairs inserted per refinement iteration (thesis: 125).
        max_iterations: cap on refinement iterations.
        error_tol: pairs with error (mm) at or below this are not inserted; default
            ``0.01 * ENS0`` (about 0.3 mm on an adult face: tighter values add many more
            pairs, and time, without improving the clone).
        ens0: the target's eye-nose separation in mm (default: from its landmarks).

    Returns:
        :class:`FitResult`.

    Raises:
        LandmarkError: fewer than 4 common landmarks, or ENS0 not measurable.
        RBFError: degenerate correspondences (coplanar landmarks, ...).
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    src = as_trimesh(source, "source")
    tgt = as_trimesh(target, "target")
    slm = _as_landmarks(source_landmarks, "source_landmarks")
    tlm = _as_landmarks(target_landmarks, "target_landmarks")
    names = tuple(n for n in slm.names if n in tlm)
    if len(names) < 4:
        raise LandmarkError(
            f"motion cloning needs at least 4 landmarks common to source and target; found "
            f"{len(names)}: {list(names)}. Source has {list(slm.names)}, target has "
            f"{list(tlm.names)}."
        )
    P_lm = slm.array(names)
    Q_lm = tlm.array(names)
    if ens0 is None:
        ens0 = eye_nose_separation(tlm)
    ens0 = float(ens0)
    L = ray_factor * ens0
    tol = 1e-2 * ens0 if error_tol is None else float(error_tol)
    S0 = src.vertices
    Vs = S0.shape[0]
    mov = np.ones(Vs, bool) if movable is None else np.asarray(movable, bool).reshape(Vs)

    # vertices too close to a landmark centre may not become centres themselves
    e = src.edges
    h = float(np.median(np.linalg.norm(S0[e[:, 0]] - S0[e[:, 1]], axis=1))) if e.size else 1.0
    near_lm = cKDTree(P_lm).query(S0)[0] < 0.25 * h
    pairs: dict[int, np.ndarray] = {}
    origin: dict[int, str] = {}

    def refit():
        ids = np.fromiter(pairs.keys(), dtype=np.int64, count=len(pairs))
        q = np.array([pairs[i] for i in ids]).reshape(-1, 3)
        P = np.concatenate([P_lm, S0[ids]])
        Q = np.concatenate([Q_lm, q])
        return fit_numpy(P, Q, kernel, reg, merge_duplicates=True), P, Q

    history = []

    def errors(G):
        D = G.apply_np(S0)
        n = vertex_normals(D, src.triangles)
        cand = np.flatnonzero(mov & ~near_lm)
        hit, tri, bary, t = cast_segments(D[cand], n[cand], L, mesh=tgt)
        err = np.abs(t[hit])
        q = np.einsum("kj,kjd->kd", bary[hit], tgt.vertices[tgt.triangles[tri[hit]]])
        return D, cand[hit], err, q

    def record(step, P, ids, err):
        history.append(
            dict(
                step=step,
                pairs=len(P),
                hits=int(ids.size),
                mean_error=float(err.mean()) if err.size else 0.0,
                max_error=float(err.max()) if err.size else 0.0,
            )
        )

    # step 0: landmarks only
    G, P, Q = refit()
    timings["landmark_fit"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    D, ids, err, q = errors(G)
    record(0, P, ids, err)

    # step 1: contours
    used, skipped = [], {}
    if use_contours:
        spec = contour_spec
        if spec is None:
            spec = _contours.BOSPHORUS_CONTOURS
            flat = [n for up, lo in spec.values() for n in list(up) + list(lo)]
            flat68 = [
                n for up, lo in _contours.MULTIPIE68_CONTOURS.values() for n in list(up) + list(lo)
            ]
            if slm.missing(flat) and not slm.missing(flat68):
                spec = _contours.MULTIPIE68_CONTOURS
        cs = _contours.extract_contours(src, slm, spec)
        ct = _contours.extract_contours(tgt, tlm, spec)
        for feat in spec:
            if feat not in cs or feat not in ct:
                skipped[feat] = "landmarks missing"
                continue
            if cs[feat].kind != ct[feat].kind:
                skipped[feat] = f"source contour is a {cs[feat].kind}, target a {ct[feat].kind}"
                continue
            if contour_matching == "arclength":
                cid, cq = _contours.match_arcs(S0, cs[feat], tgt.vertices, ct[feat])
            elif contour_matching == "nearest":
                cid, cq = _contours.match_nearest(D, cs[feat], tgt.vertices, ct[feat])
            else:
                raise MeshError(
                    f"unknown contour_matching {contour_matching!r}; use 'arclength' or 'nearest'.",
                    problem="bad_arguments",
                )
            far = np.linalg.norm(cq - D[cid], axis=1) > contour_gate * ens0
            if far.all():
                skipped[feat] = (
                    f"every contour pair is farther than {contour_gate} * ENS0 from the rough fit"
                )
                continue
            for i, qq in zip(cid[~far], cq[~far]):
                if not near_lm[i]:
                    pairs[int(i)] = qq
                    origin[int(i)] = "contour"
            used.append(feat)
        if used:
            G1, P1, Q1 = refit()
            D1, ids1, err1, q1 = errors(G1)
            before = float(err.mean()) if err.size else 0.0
            after = float(err1.mean()) if err1.size else 0.0
            if after <= before or not check_contours:
                G, P, Q, D, ids, err, q = G1, P1, Q1, D1, ids1, err1, q1
                record(1, P, ids, err)
            else:  # the contours made the fit worse: drop them (reported)
                for feat in used:
                    skipped[feat] = (
                        f"rejected: the contour pairs raised the mean ray error of "
                        f"the movable vertices from {before:.3g} to {after:.3g} mm"
                    )
                used = []
                for i in [i for i, o in origin.items() if o == "contour"]:
                    del pairs[i], origin[i]
    timings["contours"] = time.perf_counter() - t1
    G_rough = G

    # step 2..: iterative refinement
    t2 = time.perf_counter()
    it = 0
    converged = False
    while it < max_iterations:
        big = err > tol
        ids, err, q = ids[big], err[big], q[big]
        top = np.argsort(-err, kind="stable")[:pairs_per_iteration]
        new = [int(i) for i in ids[top] if int(i) not in pairs]
        changed = False
        for i, qq in zip(ids[top], q[top]):
            i = int(i)
            if i in pairs and np.array_equal(pairs[i], qq):
                continue
            pairs[i] = qq
            origin.setdefault(i, "refined")
            changed = True
        it += 1
        if changed:
            G, P, Q = refit()
        if not new:
            converged = True
            break
        D, ids, err, q = errors(G)
        record(len(history), P, ids, err)
    D = G.apply_np(S0)
    timings["refinement"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    n_contour = sum(1 for v in origin.values() if v == "contour")
    return FitResult(
        morph=G,
        rough_morph=G_rough,
        source_neutral=S0,
        deformed=D,
        src_points=P,
        dst_points=Q,
        n_landmark_pairs=len(names),
        n_contour_pairs=n_contour,
        n_refined_pairs=len(pairs) - n_contour,
        landmark_names=names,
        contours_used=tuple(used),
        contours_skipped=skipped,
        movable=mov,
        ens0=ens0,
        ray_length=L,
        iterations=it,
        converged=converged,
        history=history,
        timings=timings,
    )


# ------------------------------------------------------------------------------------------
# cloning
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CloneResult:
    """Cloned morph targets and everything needed to reuse or inspect the clone.

    Attributes:
        targets: ``(T, Vt, 3)`` target morph targets (vertex positions), mm.
        deltas: ``(T, Vt, 3)`` the same as displacements from the target neutral, mm.
        names: ``T`` morph-target names (or ``"0"``, ``"1"``, ... when none were given).
        fit: the :class:`FitResult` (the morph ``G``, correspondences, iterations).
        mapping: :class:`SurfaceMap` of the target vertices on the deformed source.
        moving: ``(T, Vs)`` bool, the moving source vertices of each morph target.
        mode: ``"displacement"`` or ``"thesis"``; transfer: ``"morph"``, ``"rough"`` or
            ``"affine"``.
        timings: seconds: ``fit`` (refinement time RT), ``clone`` (mapping + cloning, CT),
            ``total``.
    """

    targets: np.ndarray
    deltas: np.ndarray
    names: tuple[str, ...]
    fit: FitResult
    mapping: SurfaceMap
    moving: np.ndarray
    mode: str
    transfer: str
    timings: dict


def _source_deltas(S0, source_targets, source_deltas):
    if (source_targets is None) == (source_deltas is None):
        raise MeshError(
            "pass exactly one of source_targets ((T, Vs, 3) morph-target positions, mm) or "
            "source_deltas ((T, Vs, 3) displacements from the neutral, mm).",
            problem="bad_arguments",
        )
    arr = np.asarray(source_targets if source_deltas is None else source_deltas, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != S0.shape:
        raise MeshError(
            f"source morph targets must have shape (T, {S0.shape[0]}, 3) to match the source "
            f"neutral mesh; got {arr.shape}.",
            problem="shape",
        )
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
    if bad.size:
        raise MeshError(
            f"source morph target(s) {bad.tolist()} contain NaN/inf coordinates.",
            problem="nonfinite",
            elements=bad,
        )
    return arr - S0 if source_deltas is None else arr


def apply_clone(
    fit: FitResult,
    mapping: SurfaceMap,
    source_triangles,
    target_vertices,
    deltas: np.ndarray,
    moving: np.ndarray,
    mode: str = "displacement",
    transfer: str = "morph",
) -> np.ndarray:
    """Clone source morph targets with a fitted ``G`` and a target-on-source mapping.

    Arguments:
        fit: the :class:`FitResult`; mapping: target vertices on ``fit.deformed``.
        source_triangles: ``(F, 3)`` source triangles; target_vertices: ``(Vt, 3)`` mm.
        deltas: ``(T, Vs, 3)`` source morph-target displacements, mm.
        moving: ``(T, Vs)`` bool moving vertices (only they are transformed).
        mode: ``"displacement"`` or ``"thesis"`` (see the module doc).
        transfer: how a moving source vertex's displacement is carried to the target frame:
            ``"morph"`` (thesis: ``G(S_j) - G(S_0)``, with ``G`` evaluated at the moving
            vertices of ``S_j``), ``"rough"`` (the same with the morph before refinement,
            ``fit.rough_morph``: the refined ``G`` still places the target on the source,
            but its many surface centres leave it wavy off the surface, which distorts the
            transferred motion), or ``"affine"`` (only the affine part ``M`` of ``G``:
            ``M (S_j - S_0)``; keeps the global rotation/scale between the faces but not the
            local stretching of the RBF).

    Returns:
        ``(T, Vt, 3)`` cloned target morph-target positions, mm.
    """
    D = fit.deformed
    T = deltas.shape[0]
    tri_v = np.asarray(source_triangles)[mapping.tri]  # (Vt, 3)
    # only the source vertices the target vertices are mapped onto matter
    used = np.zeros(D.shape[0], bool)
    used[tri_v.ravel()] = True
    tt, vv = np.nonzero(np.asarray(moving, bool) & used[None])
    disp = np.zeros((T,) + D.shape)
    if transfer in ("morph", "rough"):
        G = fit.morph if transfer == "morph" else fit.rough_morph
        pts = fit.source_neutral[vv] + deltas[tt, vv]
        moved = G.apply_np(pts) if pts.size else np.zeros((0, 3))
        if transfer == "morph":
            base = D[vv]
        else:
            base = np.zeros_like(D)
            u = np.flatnonzero(used)
            base[u] = G.apply_np(fit.source_neutral[u])
            base = base[vv]
        disp[tt, vv] = moved - base
    elif transfer == "affine":
        M, _ = fit.morph.affine_part()
        disp[tt, vv] = deltas[tt, vv] @ np.asarray(M, dtype=np.float64).T
    else:
        raise MeshError(
            f"unknown transfer {transfer!r}; use 'morph', 'rough' or 'affine'.",
            problem="bad_arguments",
        )
    tv = np.asarray(target_vertices, dtype=np.float64)
    out = tv[None] + np.einsum("vk,tvkd->tvd", mapping.bary, disp[:, tri_v])
    if mode == "thesis":
        snapped = np.einsum("vk,vkd->vd", mapping.bary, D[tri_v])
        touched = np.asarray(moving[:, tri_v].any(axis=2))  # (T, Vt)
        out = np.where(touched[..., None], out - tv[None] + snapped[None], out)
    elif mode != "displacement":
        raise MeshError(
            f"unknown cloning mode {mode!r}; use 'displacement' or 'thesis'.",
            problem="bad_arguments",
        )
    return out


def clone_motion(
    source_neutral,
    target_neutral,
    source_landmarks,
    target_landmarks,
    *,
    source_targets=None,
    source_deltas=None,
    names: Sequence[str] | None = None,
    move_tol: float = 0.01,
    mode: str = "displacement",
    transfer: str = "morph",
    **fit_kwargs,
) -> CloneResult:
    """Clone a source face's morph targets onto a target face (thesis chapter 6).

    Arguments:
        source_neutral, target_neutral: neutral meshes (TriMesh, trimesh.Trimesh or
            ``(vertices, triangles)``), mm, same frame conventions.
        source_landmarks, target_landmarks: ``Landmarks`` or ``{name: (3,) mm}``; every name
            common to both is a correspondence.
        source_targets: ``(T, Vs, 3)`` source morph targets as positions, mm; or
        source_deltas: ``(T, Vs, 3)`` as displacements from the source neutral, mm.
        names: optional ``T`` morph-target names.
        move_tol: a source vertex moves in a morph target if it is displaced by more than
            this (mm); movable vertices are those moving in any target.
        mode: ``"displacement"`` (default) or ``"thesis"``.
        transfer: ``"morph"`` (default, thesis), ``"rough"`` or ``"affine"``, see
            :func:`apply_clone`.
        **fit_kwargs: passed to :func:`fit_source_to_target` (``kernel``, ``ray_factor``,
            ``pairs_per_iteration``, ``max_iterations``, ``error_tol``, ``ens0``, ...).

    Returns:
        :class:`CloneResult` with the ``(T, Vt, 3)`` target morph targets.
    """
    t0 = time.perf_counter()
    src = as_trimesh(source_neutral, "source_neutral")
    tgt = as_trimesh(target_neutral, "target_neutral")
    deltas = _source_deltas(src.vertices, source_targets, source_deltas)
    moving = np.linalg.norm(deltas, axis=2) > move_tol
    if names is None:
        names = tuple(str(i) for i in range(deltas.shape[0]))
    names = tuple(names)
    if len(names) != deltas.shape[0]:
        raise MeshError(f"{len(names)} names for {deltas.shape[0]} morph targets.", problem="shape")
    fit = fit_source_to_target(
        src, tgt, source_landmarks, target_landmarks, movable=moving.any(axis=0), **fit_kwargs
    )
    t1 = time.perf_counter()
    tn = vertex_normals(tgt.vertices, tgt.triangles)
    mapping = map_onto_surface(tgt.vertices, tn, fit.ray_length, fit.deformed, src.triangles)
    targets = apply_clone(fit, mapping, src.triangles, tgt.vertices, deltas, moving, mode, transfer)
    t2 = time.perf_counter()
    return CloneResult(
        targets=targets,
        deltas=targets - tgt.vertices[None],
        names=names,
        fit=fit,
        mapping=mapping,
        moving=moving,
        mode=mode,
        transfer=transfer,
        timings=dict(fit=t1 - t0, clone=t2 - t1, total=t2 - t0),
    )


# ------------------------------------------------------------------------------------------
# error measures
# ------------------------------------------------------------------------------------------
def clone_error(reference, cloned) -> float:
    """Thesis eq. 6.1, in percent: the mean over morph targets of
    ``sum_i |v_i^S - v_i^T| / sum_i |v_i^S|`` (positions in mm, so the value depends on the
    origin; the thesis's self-clone table uses it).

    Arguments:
        reference, cloned: ``(T, V, 3)`` (or ``(V, 3)``) morph-target positions, mm.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(cloned, dtype=np.float64)
    if a.ndim == 2:
        a, b = a[None], b[None]
    num = np.linalg.norm(a - b, axis=2).sum(axis=1)
    den = np.linalg.norm(a, axis=2).sum(axis=1)
    return float(np.mean(num / den) * 100.0)


def delta_error(reference_deltas, cloned_deltas) -> float:
    """Origin-independent relative error in percent: ``100 * sum |d_ref - d_clone| / sum
    |d_ref|`` over all morph targets and vertices (displacements in mm)."""
    a = np.asarray(reference_deltas, dtype=np.float64)
    b = np.asarray(cloned_deltas, dtype=np.float64)
    den = np.linalg.norm(a, axis=-1).sum()
    return float(np.linalg.norm(a - b, axis=-1).sum() / den * 100.0) if den > 0 else 0.0
