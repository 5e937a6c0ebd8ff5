"""Fitting the source face into the target (thesis 6.2): landmark, contour and ray-refined
correspondences of an RBF volume morph (:func:`fit_source_to_target`, :class:`FitResult`, mm)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from .. import contours as _contours
from ..errors import LandmarkError, MeshError
from ..normals import vertex_normals
from ..rbf import KernelName, Morph, fit_numpy
from .geometry import _as_landmarks, as_trimesh, cast_segments, eye_nose_separation

__all__ = ["FitResult", "fit_source_to_target"]


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
