"""The ARKit readout: bounded, L1-weighted, robustly re-weighted least squares of the
coefficients (:func:`box_qp`, :func:`tukey_weights`, :func:`solve_arkit`,
:func:`fit_arkit_to_scan`, :class:`ArkitSolution`) and the landmark motion of a scan (mm)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear

from ...contours import closest_on_polyline
from ...errors import FitError, LandmarkError
from .basis import ArkitBasis
from .names import ARKIT_NAMES

__all__ = [
    "ArkitSolution",
    "box_qp",
    "tukey_weights",
    "solve_arkit",
    "fit_arkit_to_scan",
    "landmark_motion",
    "attached_landmark_motion",
    "EyeRims",
    "eye_rim_motion",
]


# ------------------------------------------------------------------------------------------
# the readout
# ------------------------------------------------------------------------------------------
def box_qp(G, g, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """``argmin_c 0.5 c^T G c - g^T c`` over ``lo <= c <= hi`` (exact, bounded-variable least
    squares on ``R`` with ``R^T R = G + eps I``, ``eps = 1e-10 * trace(G) / n``).

    Args:
        G: ``(n, n)`` symmetric positive semi-definite; g: ``(n,)``.
    """
    G = np.asarray(G, np.float64)
    g = np.asarray(g, np.float64)
    n = len(g)
    eps = 1e-10 * max(float(np.trace(G)) / max(n, 1), 1e-300)
    R = np.linalg.cholesky(G + eps * np.eye(n)).T  # upper: R^T R = G
    b = np.linalg.solve(R.T, g)
    res = lsq_linear(R, b, bounds=(lo, hi), method="bvls", tol=1e-12)
    return np.clip(np.asarray(res.x, np.float64), lo, hi)


def tukey_weights(r, floor: float) -> np.ndarray:
    """Tukey biweight of residual magnitudes ``r`` (mm) at ``max(4.685 * 1.4826 * MAD,
    floor)`` (the fit's robust weights, :mod:`jaxface.fit.solve`); all ones if every weight
    would vanish."""
    r = np.abs(np.asarray(r, np.float64))
    mad = float(np.median(np.abs(r - np.median(r)))) if r.size else 0.0
    c = max(4.685 * 1.4826 * mad, float(floor))
    u = r / c
    w = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    return w if w.sum() > 0 else np.ones_like(r)


@dataclass(frozen=True)
class ArkitSolution:
    """ARKit coefficients read from a motion.

    Attributes:
        coefficients: ARKit name -> coefficient in [0, 1] (all 52; unavailable ones 0).
        contribution_mm: name -> RMS over the readout's vertices of that shape's motion at its
            coefficient, mm.
        residual_mm: RMS (robust-weighted) of the motion the coefficients leave unexplained,
            mm; motion_rms_mm: the same of the motion itself.
        unavailable: names without a source shape (reported as 0).
        iterations: robust re-weighting passes.
    """

    coefficients: dict
    contribution_mm: dict
    residual_mm: float
    motion_rms_mm: float
    unavailable: tuple[str, ...]
    iterations: int

    def strongest(self, n: int = 5) -> list[tuple[str, float]]:
        """The ``n`` largest coefficients, largest first."""
        return sorted(self.coefficients.items(), key=lambda kv: -kv[1])[:n]

    def to_dict(self) -> dict:
        return {
            "contribution_mm": {k: float(v) for k, v in self.contribution_mm.items()},
            "residual_mm": float(self.residual_mm),
            "motion_rms_mm": float(self.motion_rms_mm),
            "unavailable": list(self.unavailable),
            "robust_iterations": int(self.iterations),
        }


def _solution(basis: ArkitBasis, c_av: np.ndarray, ids, res_mm, mot_mm, it) -> ArkitSolution:
    c = np.zeros(len(ARKIT_NAMES))
    c[ids] = c_av
    contrib = basis.scale_mm * c  # c >= 0: the RMS of c_k B_k is c_k s_k
    return ArkitSolution(
        coefficients={n: float(v) for n, v in zip(ARKIT_NAMES, c)},
        contribution_mm={n: float(v) for n, v in zip(ARKIT_NAMES, contrib)},
        residual_mm=float(res_mm),
        motion_rms_mm=float(mot_mm),
        unavailable=tuple(n for n, a in zip(ARKIT_NAMES, basis.available) if not a),
        iterations=it,
    )


def solve_arkit(
    basis: ArkitBasis,
    motion,
    *,
    l1: float = 0.01,
    robust: bool = True,
    robust_floor_mm: float = 1.5,
    iterations: int = 4,
) -> ArkitSolution:
    """ARKit coefficients of a skin motion (e.g. fitted skin minus rest, same topology).

    Minimises ``sum_i w_i |B_i c - d_i|^2 / sum_i w_i + l1 * sum_k s_k c_k`` over
    ``0 <= c <= 1`` on the basis's vertices ``i`` (mask), with Tukey weights ``w_i`` of
    ``|B_i c - d_i|`` re-estimated ``iterations`` times (``robust=False``: ``w = 1``, one
    solve). ``s_k`` is shape ``k``'s RMS motion at coefficient 1 (:attr:`ArkitBasis.scale_mm`),
    so the penalty is on motion in mm, not on coefficients: the lasso on unit-RMS shapes. A
    plain ``l1 * sum_k c_k`` lets the large shapes (``jawOpen``, 11-14 mm RMS) through and
    zeroes the small ones (``eyeWide``, 0.2-0.3 mm RMS, a 3 mm lid raise) whatever the data.

    Args:
        motion: ``(V, 3)`` mm; l1: mm (sparsity; mm^2 of mean squared residual per mm of a
            shape's RMS motion).

    Raises:
        FitError: shape mismatch or non-finite motion.
    """
    d = np.asarray(motion, np.float64)
    if d.shape != basis.deltas.shape[1:]:
        raise FitError(f"motion must be {basis.deltas.shape[1:]} (mm), got {d.shape}.")
    if not np.all(np.isfinite(d[basis.mask])):
        raise FitError("the motion holds NaN/inf on the face region.")
    ids = np.flatnonzero(basis.available)
    B = basis.deltas[ids][:, basis.mask].reshape(len(ids), -1).T  # (3P, K)
    y = d[basis.mask].reshape(-1)
    P = int(basis.mask.sum())
    scale = basis.scale_mm[ids]
    w = np.ones(P)
    c = np.zeros(len(ids))
    n_it = iterations if robust else 1
    for _ in range(n_it):
        w3 = np.repeat(w / w.sum(), 3)
        Bw = B * w3[:, None]
        c = box_qp(B.T @ Bw, Bw.T @ y - 0.5 * l1 * scale)
        r = np.linalg.norm((B @ c - y).reshape(P, 3), axis=1)
        if robust:
            w = tukey_weights(r, robust_floor_mm)
    r = np.linalg.norm((B @ c - y).reshape(P, 3), axis=1)
    wn = w / w.sum()
    res = float(np.sqrt(np.sum(wn * r**2)))
    mot = float(np.sqrt(np.mean(np.sum(d[basis.mask] ** 2, -1))))
    return _solution(basis, c, ids, res, mot, n_it)


def fit_arkit_to_scan(
    basis: ArkitBasis,
    rest_vertices,
    triangles,
    scan_vertices,
    scan_triangles,
    *,
    landmarks=None,
    landmark_weight: float = 1.0,
    rims: EyeRims | None = None,
    rim_weight: float = 1.0,
    l1: float = 0.01,
    robust_floor_mm: float = 1.5,
    max_distance_mm: float = 10.0,
    iterations: int = 6,
) -> ArkitSolution:
    """ARKit coefficients straight from a scan (no rig): point-to-plane ICP of
    ``rest + sum_k c_k B_k`` to the scan surface (both in the same frame, mm).

    Each pass takes the closest scan point ``p_i`` and scan normal ``n_i`` of every basis
    vertex ``x_i(c)`` and solves ``min sum_i w_i (n_i . (rest_i + B_i c - p_i))^2 / sum w +
    landmark_weight * mean_l |B_l c - m_l|^2 + l1 sum_k s_k c_k`` on ``[0, 1]`` (``s_k`` as in
    :func:`solve_arkit`, ``l1`` in mm) with Tukey weights;
    matches on the scan's border or farther than ``max_distance_mm`` are rejected. The
    point-to-plane term leaves motion along the skin (a brow sliding up) free; the landmark
    term pins it. The eyelids slide along the eye too, and a range scan's only record of it is
    the edge of the hole it leaves at each eye: the rim term (``rims``, :func:`eye_rim_motion`)
    adds ``rim_weight * mean_r |P_r (B_r c - m_r)|^2``, the lid margins' motion across the
    hole's edge (``P_r`` removes the component along the edge, which the edge cannot show;
    ``m_r`` and ``P_r`` are matched again each pass, :meth:`EyeRims.motion`).

    Args:
        landmarks: None, or ``(tri (L,), bary (L, 3), motion (L, 3) mm)``: landmarks attached
            to the rest skin's triangles and their motion in the scan (e.g. aligned
            expression landmark minus neutral landmark).
        rims: None, or the :class:`EyeRims` of this scan (:func:`eye_rim_motion`).

    Returns:
        :class:`ArkitSolution` (``motion_rms_mm``: RMS of the recovered motion).
    """
    from ...fit.metrics import SurfaceIndex

    X0 = np.asarray(rest_vertices, np.float64)
    if X0.shape != basis.deltas.shape[1:]:
        raise FitError(f"rest_vertices must be {basis.deltas.shape[1:]}, got {X0.shape}.")
    index = SurfaceIndex(scan_vertices, scan_triangles)
    ids = np.flatnonzero(basis.available)
    m = basis.mask
    Bm = basis.deltas[ids][:, m]  # (K, P, 3)
    scale = basis.scale_mm[ids]
    c = np.zeros(len(ids))
    res = 0.0
    GL = np.zeros((len(ids), len(ids)))
    gL = np.zeros(len(ids))
    if landmarks is not None:
        ltri, lbary, lmot = (np.asarray(a) for a in landmarks)
        corners = np.asarray(triangles, np.int64)[np.asarray(ltri, np.int64)]  # (L, 3)
        BL = np.einsum("lj,kljd->kld", lbary, basis.deltas[ids][:, corners]).reshape(len(ids), -1).T
        ml = np.asarray(lmot, np.float64).reshape(-1)
        if not np.all(np.isfinite(ml)):
            raise FitError("landmark motion holds NaN/inf.")
        s_l = float(landmark_weight) / max(len(ml) // 3, 1)
        GL = s_l * BL.T @ BL
        gL = s_l * BL.T @ ml
    BR = None
    if rims is not None and len(rims.vertices) > 0:
        BR = basis.deltas[ids][:, np.asarray(rims.vertices, np.int64)]  # (K, R, 3)
    for _ in range(iterations):
        x = X0[m] + np.einsum("k,kpd->pd", c, Bm)
        cp = index.query(x, max_distance=2 * max_distance_mm)
        n = cp.normals
        ok = ~cp.on_boundary & (cp.distances <= max_distance_mm)
        if not ok.any():
            raise FitError("no basis vertex found the scan within max_distance_mm.")
        A = np.einsum("pd,kpd->pk", n, Bm)  # (P, K)
        b = np.einsum("pd,pd->p", n, cp.points - X0[m])
        r = np.abs(A @ c - b)
        w = np.where(ok, tukey_weights(np.where(ok, r, 0.0), robust_floor_mm), 0.0)
        if w.sum() <= 0:
            w = ok.astype(np.float64)
        w = w / w.sum()
        Aw = A * w[:, None]
        GR, gR = 0.0, 0.0
        if rims is not None and BR is not None:
            mr, Pr = rims.motion(np.einsum("k,krd->rd", c, BR))
            PB = np.einsum("rde,kre->rdk", Pr, BR)  # (R, 3, K)
            s_r = float(rim_weight) / len(mr)
            GR = s_r * np.einsum("rdk,rdj->kj", PB, PB)
            gR = s_r * np.einsum("rdk,rd->k", PB, mr)
        c = box_qp(A.T @ Aw + GL + GR, Aw.T @ b + gL + gR - 0.5 * l1 * scale)
        res = float(np.sqrt(np.sum(w * (A @ c - b) ** 2)))
    mot = float(np.sqrt(np.mean(np.sum(np.einsum("k,kpd->pd", c, Bm) ** 2, -1))))
    return _solution(basis, c, ids, res, mot, iterations)


def landmark_motion(registration, neutral, scan, transform):
    """The landmark term of :func:`fit_arkit_to_scan`: the registered landmarks' attachment
    (``registration.landmark_points``) and their motion ``T(q_scan) - q_neutral`` (mm) for the
    labels present in both scans; ``transform`` maps the scan into the neutral's frame."""
    lp = registration.landmark_points
    term = attached_landmark_motion(
        registration.landmarks.names, lp.tri, lp.bary, neutral, scan, transform
    )
    if term is None:
        raise LandmarkError("no landmark label common to the registration and both scans.")
    return term


def attached_landmark_motion(names, tri, bary, neutral, scan, transform):
    """:func:`landmark_motion` for landmarks attached by ``(tri (L,), bary (L, 3))`` under
    ``names``: ``(tri, bary, motion (K, 3) mm)`` of the K labels present in both scans, or
    None when there is none."""
    qn = dict(zip(neutral.landmarks.names, np.asarray(neutral.landmarks.positions)))
    qe = dict(zip(scan.landmarks.names, np.asarray(scan.landmarks.positions)))
    names = list(names)
    keep = [i for i, n in enumerate(names) if n in qn and n in qe]
    if not keep:
        return None
    mot = np.stack([transform.apply(qe[names[i]][None])[0] - qn[names[i]] for i in keep])
    return np.asarray(tri)[keep], np.asarray(bary)[keep], mot


# ------------------------------------------------------------------------------------------
# the eye rims of a range scan
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EyeRims:
    """The skin's eye openings and the edges of a range scan's eye holes (mm).

    Attributes:
        vertices: ``(R,)`` rest-skin vertex ids on the skin's eye openings, each opening in
            loop order.
        anchors: ``(R, 3)`` each one's closest point on the neutral scan's hole edge, mm.
        side_of: ``(R,)`` index into ``edges`` of each vertex's eye.
        edges: per eye, ``(m, 3)`` the expression scan's hole edge (a closed polyline, mm, in
            the neutral's frame).
        window: per eye, the half-width (vertices) of the moving mean along the opening.
        sides: the eyes (``"left"``, ``"right"``) that had an opening on the skin and a hole
            in both scans.
    """

    vertices: np.ndarray
    anchors: np.ndarray
    side_of: np.ndarray
    edges: tuple[np.ndarray, ...]
    window: tuple[int, ...]
    sides: tuple[str, ...]

    def motion(self, shift=None) -> tuple[np.ndarray, np.ndarray]:
        """The edge's motion at each opening vertex and what the edge can show of it.

        Args:
            shift: ``(R, 3)`` the vertices' current displacement, mm (default 0).

        Returns:
            ``m`` ``(R, 3)``: ``b - a`` with ``a`` the anchor and ``b`` the closest point on
            the expression's edge to ``a + shift``, averaged along the opening (mm);
            ``P`` ``(R, 3, 3)``: ``I - t t^T``, ``t`` the edge's unit tangent at ``b`` (its
            motion along itself is unknown).
        """
        q = self.anchors if shift is None else self.anchors + np.asarray(shift, np.float64)
        m = np.zeros_like(self.anchors)
        P = np.zeros((len(q), 3, 3))
        for j, edge in enumerate(self.edges):
            sel = self.side_of == j
            b, t = closest_on_polyline(q[sel], edge, tangents=True)
            m[sel] = _circular_mean(b - self.anchors[sel], self.window[j])
            P[sel] = np.eye(3)[None] - t[:, :, None] * t[:, None, :]
        return m, P


def _boundary_loops(vertices: np.ndarray, triangles: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops of a triangle mesh as vertex-id arrays (first id repeated
    last)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, triangles, process=False, validate=False)
    out = []
    for e in mesh.outline().entities:
        idx = np.asarray(e.points, np.int64)
        if len(idx) >= 4 and idx[0] == idx[-1]:
            out.append(idx)
    return out


def _near_loop(vertices: np.ndarray, loops: list[np.ndarray], centre, radius: float):
    """The loop (vertex ids) whose centroid is nearest ``centre`` and within ``radius`` mm
    (or None)."""
    best, dist = None, float(radius)
    for idx in loops:
        d = float(np.linalg.norm(vertices[idx[:-1]].mean(0) - centre))
        if d <= dist:
            best, dist = idx, d
    return best


def _circular_mean(values: np.ndarray, half_width: int) -> np.ndarray:
    """Moving mean over ``2 * half_width + 1`` neighbours of a closed loop's ``(n, d)``
    values."""
    n = len(values)
    if half_width <= 0 or n == 0:
        return values
    k = min(int(half_width), (n - 1) // 2)
    return np.mean([np.roll(values, s, axis=0) for s in range(-k, k + 1)], axis=0)


def eye_rim_motion(
    rest_vertices,
    triangles,
    neutral,
    scan,
    transform,
    *,
    mask=None,
    radius_mm: float = 15.0,
    smooth_mm: float = 6.0,
) -> EyeRims:
    """The rim term of :func:`fit_arkit_to_scan`: where a range scan's eye holes moved.

    Scanners leave a hole at each eye, and its edge is the lid margin. Per eye (centre: the
    midpoint of the neutral's inner and outer eye-corner landmarks), the skin's opening
    (the boundary loop of ``triangles[mask]`` whose centroid is within ``radius_mm`` of the
    centre) and the hole of each scan (likewise) are found. Each opening vertex ``x_r`` is
    anchored at its closest point ``a_r`` on the neutral's hole edge, so an offset between the
    registered skin's opening and the scanner's hole cancels out; its motion is
    ``m_r = b_r - a_r`` with ``b_r`` the closest point on the expression's edge to where the
    anchor has moved with the vertex (:meth:`EyeRims.motion`, matched again in each pass of
    :func:`fit_arkit_to_scan`), averaged along the opening (``smooth_mm``). An eye without
    an opening on the skin or a hole in either scan (a closed eye) is left out.

    Args:
        rest_vertices: ``(V, 3)`` the registered rest skin, mm, in the neutral scan's frame;
            triangles: ``(F, 3)``; mask: ``(V,)`` bool face region (default all).
        neutral, scan: the neutral and the expression :class:`jaxface.io.Scan` (with
            landmarks); transform: maps ``scan`` into the neutral's frame.
        radius_mm: how far a loop's centroid may be from the eye centre.
        smooth_mm: the motion is averaged over the opening's vertices within this arc
            length on either side: a range scan's hole edge is jagged by about its grid
            spacing. On the bs900 scans, against the true motion of the ICT lids, a window of
            +-6 mm (2 vertices of the default head's opening) halves the error where the lids
            barely move (0.27-0.47 -> 0.10-0.24 mm RMS, the motion matched once at rest).

    Returns:
        :class:`EyeRims` (empty when no eye qualifies).
    """
    X = np.asarray(rest_vertices, np.float64)
    T = np.asarray(triangles, np.int64)
    if mask is not None:
        T = T[np.asarray(mask, bool)[T].all(axis=1)]
    lm = dict(zip(neutral.landmarks.names, np.asarray(neutral.landmarks.positions, np.float64)))
    nv, nt, _ = neutral.mesh_arrays()
    ev, et, _ = scan.mesh_arrays()
    nv = np.asarray(nv, np.float64)
    ev = transform.apply(np.asarray(ev, np.float64))
    meshes = ((X, _boundary_loops(X, T)), (nv, _boundary_loops(nv, np.asarray(nt, np.int64))))
    meshes += ((ev, _boundary_loops(ev, np.asarray(et, np.int64))),)
    verts, anchors, side_of, edges, window, sides = [], [], [], [], [], []
    for side in ("left", "right"):
        names = (f"Inner {side} eye corner", f"Outer {side} eye corner")
        if not all(n in lm for n in names):
            continue
        centre = 0.5 * (lm[names[0]] + lm[names[1]])
        skin, hole0, hole1 = (_near_loop(v, loops, centre, radius_mm) for v, loops in meshes)
        if skin is None or hole0 is None or hole1 is None:
            continue
        ids = skin[:-1]  # the opening in loop order
        a = closest_on_polyline(X[ids], nv[hole0])
        spacing = float(np.mean(np.linalg.norm(np.diff(X[skin], axis=0), axis=1)))
        verts.append(ids)
        anchors.append(a)
        side_of.append(np.full(len(ids), len(sides)))
        edges.append(ev[hole1])
        window.append(int(round(smooth_mm / max(spacing, 1e-9))))
        sides.append(side)
    if not verts:
        return EyeRims(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), (), (), ())
    return EyeRims(
        np.concatenate(verts),
        np.concatenate(anchors),
        np.concatenate(side_of),
        tuple(edges),
        tuple(window),
        tuple(sides),
    )
