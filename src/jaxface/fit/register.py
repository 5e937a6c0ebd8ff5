"""Registration of a template skin to a subject's neutral scan (issue 7, "Subject
registration", step 1).

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.
NumPy/SciPy build-time code (the registered neutral becomes the rest state of the rig).

Method (:func:`register_template`):

1. **Landmark TPS.** A thin-plate-spline morph (:func:`jaxface.rbf.fit_numpy`, kernel
   ``"tps"``) sends the template's landmarks onto the scan's (every label present in both)
   and warps all template vertices: the coarse fit, which also carries the template into the
   scan's frame and scale. Result ``X_ref``.
2. **Non-rigid ICP with a Laplacian (bending) regulariser.** We solve for vertex
   displacements ``D`` (V x 3) relative to ``X_ref`` by minimising::

       sum_i a_i w_i |X_ref_i + D_i - c_i|^2                    data (closest scan points)
     + lambda * sum_i |(L D)_i|^2 / a_i                         bending of the displacement
     + mu * sum_l |B_l (X_ref + D) - q_l|^2                     landmarks
     + eps * sum_i a_i |D_i - D_prev_i|^2                       damping (keeps it SPD)

   with ``a_i`` the vertex areas (mm^2), ``L`` the cotangent Laplacian of ``X_ref`` (weights
   clamped to [0, 10]), ``c_i`` the exact closest point of the current vertex on the scan
   surface, ``B_l`` the barycentric attachment of landmark ``l`` on the template and ``q_l``
   the scan landmark. ``lambda = l^4`` with ``l`` a smoothing length in mm: displacement
   detail shorter than ``l`` is suppressed. ``l`` decreases over the schedule
   (:attr:`RegisterOptions.smoothing_mm`), from a near-global correction to millimetre
   detail; correspondences are refreshed before every solve. The normal equations are one
   sparse SPD matrix shared by x, y and z (``scipy.sparse.linalg.splu``).

   The closest-point target is a point-to-plane step in disguise: ``c_i - x_i`` is along
   the scan normal wherever the closest point is inside a triangle, while the tangential
   position is held at the current iterate (not pulled back to ``X_ref``).

   A correspondence is **rejected** when its closest point lies on the scan's border (a
   hole rim or the silhouette: the scan has no data there), when it is farther than
   ``clip(2 l, min_distance_mm, max_distance_mm)``, or when the template and scan normals
   differ by more than ``max_normal_angle_deg``. Vertices without an accepted
   correspondence (holes, outside the scan, the back of the head) follow their
   neighbours smoothly: the bi-Laplacian extends the displacement field into them.

Why this rather than iterated TPS with a decreasing ridge: the TPS system is dense in the
number of centres (10^4 scan correspondences would need a 10^4 x 10^4 dense solve per
iteration), while the Laplacian system is sparse in the template's vertices and its
smoothing length has a direct meaning in mm on the surface (not in the volume).

Output (:class:`Registration`): the registered neutral (same topology and vertex order as
the template, in the scan frame), the face mask, the landmarks attached to it, and per
vertex the distance to the scan surface with a flag telling where the scan has data.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..errors import FitError, LandmarkError
from ..head import generic_head
from ..landmarks import Landmarks
from ..mesh import TriMesh
from ..normals import vertex_normals
from ..rbf import fit_numpy
from ..surface import SurfacePoints
from .metrics import DistanceStats, SurfaceIndex, landmark_dict, landmark_errors, mesh_arrays

__all__ = [
    "RegisterOptions",
    "Template",
    "Registration",
    "register_template",
    "cotangent_laplacian",
    "vertex_areas",
]


# --------------------------------------------------------------------------------------
# options and inputs
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RegisterOptions:
    """Settings of :func:`register_template` (lengths in mm).

    Attributes:
        smoothing_mm: the smoothing lengths ``l`` of the schedule, coarse to fine.
        iterations: correspondence refreshes (solves) per smoothing length.
        final_iterations: extra solves at the last length.
        min_distance_mm, max_distance_mm: bounds of the rejection distance
            ``clip(2 l, min, max)``.
        max_normal_angle_deg: normal-compatibility limit.
        landmark_weight_mm2: weight ``mu`` of each landmark term, in mm^2 of equivalent
            surface (a vertex's data term weighs its area).
        final_landmark_weight_mm2: ``mu`` at the last smoothing length (landmarks of real
            scans are placed by hand to 2-3 mm: the surface should win at the end).
        tps_reg: ridge of the landmark TPS (normalised units of :func:`jaxface.rbf.fit`).
        damping: ``eps`` of the damping term.
        data_tolerance_mm: a registered vertex "has data" when its closest scan point is
            within this distance and off the scan border.
        reverse_weight: weight of the reverse (scan -> template) closest-point term
            relative to the forward one (0 switches it off).
        reverse_face_only: reverse matches only onto the template's face region.
        reverse_stride: use every n-th scan point in the reverse term (weighted n times).
        active_margin_mm: only template vertices within this distance of the scan (after
            the landmark TPS) are solved for; the others keep the TPS result, and the
            bending term blends the two.
    """

    smoothing_mm: tuple[float, ...] = (30.0, 15.0, 8.0, 4.0, 2.5, 1.5)
    iterations: int = 1
    final_iterations: int = 2
    min_distance_mm: float = 2.0
    max_distance_mm: float = 10.0
    max_normal_angle_deg: float = 60.0
    landmark_weight_mm2: float = 20.0
    final_landmark_weight_mm2: float = 2.0
    tps_reg: float = 0.0
    damping: float = 1e-3
    data_tolerance_mm: float = 2.0
    reverse_weight: float = 1.0
    reverse_face_only: bool = True
    reverse_stride: int = 2
    active_margin_mm: float = 30.0


@dataclass(frozen=True)
class Template:
    """A template skin for registration.

    Attributes:
        mesh: the skin, :class:`jaxface.mesh.TriMesh` (or anything with ``vertices`` and
            ``triangles``), mm.
        landmarks: :class:`jaxface.landmarks.Landmarks` on (or near) its surface, mm.
        face_mask: ``(V,)`` bool face region (default: every vertex).
        name: free text for reports.
    """

    mesh: Any
    landmarks: Any
    face_mask: np.ndarray | None = None
    name: str = "template"

    @classmethod
    def from_head(cls, head, name: str = "generic_head") -> Template:
        """From a :class:`jaxface.head.Head` (or any object with ``mesh``, ``landmarks``,
        ``face_mask``)."""
        return cls(head.mesh, head.landmarks, getattr(head, "face_mask", None), name)


def _as_template(template, template_landmarks, face_mask) -> Template:
    if template is None:
        template = Template.from_head(generic_head())
    elif not isinstance(template, Template):
        if hasattr(template, "mesh") and hasattr(template, "landmarks"):
            template = Template(
                template.mesh,
                template.landmarks,
                getattr(template, "face_mask", None),
                type(template).__name__,
            )
        else:
            if template_landmarks is None:
                raise LandmarkError(
                    "a template mesh needs its landmarks (template_landmarks=Landmarks or a .lm3 "
                    "read with jaxface.landmarks.read_lm3) to be registered to a scan."
                )
            template = Template(template, template_landmarks, face_mask, "user mesh")
    if template_landmarks is not None:
        template = Template(template.mesh, template_landmarks, template.face_mask, template.name)
    if face_mask is not None:
        template = Template(template.mesh, template.landmarks, face_mask, template.name)
    return template


# --------------------------------------------------------------------------------------
# discrete operators
# --------------------------------------------------------------------------------------
def vertex_areas(vertices, triangles) -> np.ndarray:
    """Barycentric vertex areas ``(V,)`` mm^2 (a third of the incident triangle areas),
    floored at 1e-3 of their mean so that isolated vertices keep a positive mass."""
    v, f = mesh_arrays((vertices, triangles))
    ar = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    a = np.bincount(f.ravel(), weights=np.repeat(ar / 3.0, 3), minlength=len(v))
    return np.maximum(a, 1e-3 * max(float(a.mean()), 1e-300))


def cotangent_laplacian(
    vertices, triangles, *, clamp: tuple[float, float] = (0.0, 10.0)
) -> sp.csr_matrix:
    """Cotangent Laplacian ``L`` ``(V, V)`` (positive semi-definite, rows sum to 0):
    ``(L u)_i = sum_j w_ij (u_i - u_j)``, ``w_ij = (cot a + cot b) / 2`` clamped to
    ``clamp`` (dimensionless). Zero-area triangles contribute nothing (NaN-safe)."""
    v, f = mesh_arrays((vertices, triangles))
    n = len(v)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = f[:, (k + 1) % 3], f[:, (k + 2) % 3], f[:, k]
        e1 = v[i] - v[o]
        e2 = v[j] - v[o]
        cr = np.linalg.norm(np.cross(e1, e2), axis=1)
        dt = np.einsum("ij,ij->i", e1, e2)
        cot = np.where(cr > 1e-12, dt / np.where(cr > 1e-12, cr, 1.0), 0.0)
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cot, 0.5 * cot]
    W = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    W.data = np.clip(W.data, clamp[0], clamp[1])
    W.eliminate_zeros()
    d = np.asarray(W.sum(axis=1)).ravel()
    return cast(sp.csr_matrix, (sp.diags(d) - W).tocsr())


# --------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Registration:
    """A template registered to a neutral scan (all in the scan's frame, mm).

    Attributes:
        mesh: the registered neutral, :class:`jaxface.mesh.TriMesh` with the template's
            triangles (vertex ``i`` corresponds to template vertex ``i``).
        template: the template as given.
        landmarks: all the template's landmarks carried onto ``mesh`` (Landmarks, mm; the
            ones used for the fit first, in ``labels`` order, then the others, e.g. ear
            lobes the scan lacks).
        landmark_points: their attachment (:class:`jaxface.surface.SurfacePoints`, same
            order), valid on the template and on ``mesh`` alike.
        face_mask: ``(V,)`` bool face region.
        residuals: ``(V,)`` distance of each registered vertex to the scan surface, mm.
        has_data: ``(V,)`` bool: the scan has data under the vertex (closest point within
            ``data_tolerance_mm`` and off the scan border).
        coarse: the landmark-TPS result (before ICP), TriMesh.
        scan_landmarks: the scan landmarks used (Landmarks, ``labels`` order), mm.
        labels: labels used for the TPS and the landmark terms (present on both).
        history: one dict per solve (smoothing length, matches, residual stats, time).
        seconds: wall time of the registration.
    """

    mesh: Any
    template: Template
    landmarks: Any
    landmark_points: Any
    face_mask: np.ndarray
    residuals: np.ndarray
    has_data: np.ndarray
    coarse: Any
    scan_landmarks: Any
    labels: tuple[str, ...]
    history: tuple[dict, ...] = ()
    seconds: float = 0.0

    @property
    def vertices(self) -> np.ndarray:
        """``(V, 3)`` registered vertices, mm."""
        return np.asarray(self.mesh.vertices)

    def stats(self, mask=None) -> DistanceStats:
        """Residual stats (mm) over the face-mask vertices where the scan has data
        (``mask`` restricts further)."""
        m = self.face_mask & self.has_data
        if mask is not None:
            m &= np.asarray(mask, bool)
        return DistanceStats.from_distances(self.residuals[m])

    def landmark_errors(self) -> dict[str, float]:
        """label -> distance registered landmark to scan landmark, mm."""
        return landmark_errors(self.landmarks, self.scan_landmarks)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (mm)."""
        return {
            "template": self.template.name,
            "n_vertices": int(len(self.residuals)),
            "residual_mm": self.stats().to_dict(),
            "coverage": float(
                (self.has_data & self.face_mask).sum() / max(int(self.face_mask.sum()), 1)
            ),
            "labels": list(self.labels),
            "landmark_errors_mm": self.landmark_errors(),
            "history": list(self.history),
            "seconds": self.seconds,
        }


# --------------------------------------------------------------------------------------
# registration
# --------------------------------------------------------------------------------------
def _scan_index_and_landmarks(scan, scan_landmarks, scan_index):
    lm = scan_landmarks if scan_landmarks is not None else getattr(scan, "landmarks", None)
    if lm is None:
        raise LandmarkError(
            "register_template needs the scan's landmarks (scan_landmarks=..., or a Scan loaded "
            "with its .lm3)."
        )
    if scan_index is None:
        if hasattr(scan, "mesh_arrays") and hasattr(scan, "points"):
            v, t, _ = scan.mesh_arrays()
            scan_index = SurfaceIndex(v, t)
        else:
            scan_index = SurfaceIndex.from_mesh(scan)
    return scan_index, lm


def _attach(vertices, triangles, points):
    """SurfacePoints-like attachment (tri ids, bary) of points to a mesh, exact."""
    cp = SurfaceIndex(vertices, triangles).query(points)
    return cp.triangles, cp.bary, cp.distances


def register_template(
    scan,
    scan_landmarks=None,
    template=None,
    template_landmarks=None,
    face_mask=None,
    *,
    options: RegisterOptions | None = None,
    labels: Sequence[str] | None = None,
    data_mask=None,
    scan_index: SurfaceIndex | None = None,
) -> Registration:
    """Register a template skin to a neutral scan (see the module doc for the method).

    Arguments:
        scan: the neutral scan: :class:`jaxface.io.Scan`, TriMesh, ``trimesh.Trimesh`` or
            ``(V, F)``, mm.
        scan_landmarks: its landmarks (Landmarks or dict, mm); default ``scan.landmarks``.
        template: ``None`` (the default head, :func:`jaxface.head.generic_head`), a
            :class:`Template`, a ``Head``-like object (``mesh``, ``landmarks``,
            ``face_mask``) or a mesh (then ``template_landmarks`` is required).
        template_landmarks: landmarks of a template mesh (override those of a Head), mm.
        face_mask: ``(V,)`` bool face region of the template (default: the Head's, or all).
        options: :class:`RegisterOptions`.
        labels: landmark labels to use (default: every label present in both sets).
        data_mask: ``(V,)`` bool: template vertices allowed to take scan correspondences
            (default: all; rejection decides).
        scan_index: a prebuilt :class:`SurfaceIndex` of the scan.

    Returns:
        :class:`Registration`.

    Raises:
        LandmarkError: fewer than 5 common landmarks, or landmarks missing.
        FitError: no scan correspondence accepted (template and scan do not overlap).
    """
    t_start = time.perf_counter()
    opt = options or RegisterOptions()
    tpl = _as_template(template, template_landmarks, face_mask)
    tv, tf = mesh_arrays(tpl.mesh)
    V = len(tv)
    fmask = np.ones(V, bool) if tpl.face_mask is None else np.asarray(tpl.face_mask, bool)
    if fmask.shape != (V,):
        raise FitError(
            f"face_mask must be ({V},) bool over the template vertices, got {fmask.shape}."
        )
    dmask = np.ones(V, bool) if data_mask is None else np.asarray(data_mask, bool)
    if dmask.shape != (V,):
        raise FitError(
            f"data_mask must be ({V},) bool over the template vertices, got {dmask.shape}."
        )
    index, slm = _scan_index_and_landmarks(scan, scan_landmarks, scan_index)
    tl = landmark_dict(tpl.landmarks)
    sl = landmark_dict(slm)
    names = [n for n in (labels if labels is not None else tl) if n in tl and n in sl]
    if labels is not None:
        want = list(landmark_dict({n: np.zeros(3) for n in labels}))
        missing = [n for n in want if n not in tl or n not in sl]
        if missing:
            raise LandmarkError(
                f"landmarks requested for registration but missing: {missing}.", missing=missing
            )
    if len(names) < 5:
        raise LandmarkError(
            f"template registration needs at least 5 landmarks present on both the template and "
            f"the scan; found {len(names)}: {names}. Template has {sorted(tl)}, scan has {sorted(sl)}.",
            missing=tuple(n for n in tl if n not in sl),
        )
    dst = np.stack([sl[n] for n in names])

    # attachment of every template landmark on the template surface; the used ones first
    all_names = list(names) + [n for n in tl if n not in names]
    a_tri, a_bary, _ = _attach(tv, tf, np.stack([tl[n] for n in all_names]))
    l_tri, l_bary = a_tri[: len(names)], a_bary[: len(names)]
    src_on = np.einsum("kj,kjd->kd", l_bary, tv[tf[l_tri]])

    # 1) landmark TPS
    morph = fit_numpy(src_on, dst, kernel="tps", reg=opt.tps_reg)
    X_ref = morph.apply_np(tv)
    if not np.all(np.isfinite(X_ref)):
        raise FitError(
            "the landmark TPS produced non-finite vertices; check the landmarks for duplicates."
        )

    # 2) Laplacian-regularised non-rigid ICP
    area = vertex_areas(X_ref, tf)
    L = cotangent_laplacian(X_ref, tf)
    K = (L.T @ sp.diags(1.0 / area) @ L).tocsc()
    nl = len(names)
    B = sp.csr_matrix(
        (l_bary.ravel(), (np.repeat(np.arange(nl), 3), tf[l_tri].ravel())), shape=(nl, V)
    )
    cos_max = np.cos(np.radians(opt.max_normal_angle_deg))
    D = np.zeros_like(X_ref)
    scan_used = np.unique(index.triangles[index.active_ids])
    # active vertices: near the scan after the TPS; the others keep the TPS result (D = 0),
    # and the bending term blends the two smoothly
    near, _ = cKDTree(index.vertices[scan_used]).query(
        X_ref, distance_upper_bound=opt.active_margin_mm
    )
    active = np.isfinite(near)
    active[tf[l_tri].ravel()] = True
    act = np.flatnonzero(active)
    K_a = K[act][:, act]
    B_a = B[:, act].tocsc()
    BtB_a = (B_a.T @ B_a).tocsc()
    lm_rhs = B_a.T @ (dst - B @ X_ref)
    area_a = area[act]
    data_ids = np.flatnonzero(dmask & active)
    if opt.reverse_weight > 0:
        stride = max(int(opt.reverse_stride), 1)
        rsel = scan_used[::stride]
        scan_pts = index.vertices[rsel]
        scan_nrm = index.vertex_normals[rsel]
        scan_area = stride * vertex_areas(index.vertices, index.triangles[index.active_ids])[rsel]
        face_mask_tri = fmask[tf].all(axis=1) if opt.reverse_face_only else None
        if face_mask_tri is not None and not face_mask_tri.any():
            face_mask_tri = None
    history: list[dict] = []
    schedule: list[float] = []
    for k, ell in enumerate(opt.smoothing_mm):
        n_it = opt.iterations + (opt.final_iterations if k == len(opt.smoothing_mm) - 1 else 0)
        schedule += [float(ell)] * n_it
    ell_last = schedule[-1] if schedule else 0.0
    for step, ell in enumerate(schedule):
        t0 = time.perf_counter()
        X = X_ref + D
        tau = float(np.clip(2.0 * ell, opt.min_distance_mm, opt.max_distance_mm))
        cp = index.query(X[data_ids], max_distance=tau, exact=False)
        nrm = vertex_normals(X, tf)[data_ids]
        ok = (
            (cp.distances <= tau)
            & ~cp.on_boundary
            & (np.einsum("ij,ij->i", nrm, cp.normals) >= cos_max)
        )
        if not ok.any():
            raise FitError(
                "no template vertex found a compatible scan point after the landmark warp; the "
                "template and the scan do not overlap (check both landmark sets and units)."
            )
        w = np.zeros(V)
        C = np.zeros_like(X)
        w[data_ids[ok]] = 1.0
        C[data_ids[ok]] = cp.points[ok]
        mu = opt.final_landmark_weight_mm2 if ell == ell_last else opt.landmark_weight_mm2
        aw = (area * w)[act]
        A = sp.diags(aw + opt.damping * area_a) + (ell**4) * K_a + mu * BtB_a
        rhs = (
            aw[:, None] * (C - X_ref)[act] + mu * lm_rhs + (opt.damping * area_a)[:, None] * D[act]
        )
        n_rev = 0
        if opt.reverse_weight > 0:
            # scan points -> their closest points on the current template surface
            tmpl = SurfaceIndex(X, tf, face_mask_tri)
            rq = tmpl.query(scan_pts, max_distance=tau, exact=False)
            rok = (rq.distances <= tau) & ~rq.on_boundary
            rok &= np.einsum("ij,ij->i", scan_nrm, rq.normals) >= cos_max
            if rok.any():
                r_ids = np.flatnonzero(rok)
                Bs = sp.csr_matrix(
                    (
                        rq.bary[r_ids].ravel(),
                        (np.repeat(np.arange(r_ids.size), 3), tf[rq.triangles[r_ids]].ravel()),
                    ),
                    shape=(r_ids.size, V),
                )
                Bs_a = Bs[:, act]
                ws = opt.reverse_weight * scan_area[r_ids]
                A = A + Bs_a.T @ sp.diags(ws) @ Bs_a
                rhs = rhs + Bs_a.T @ (ws[:, None] * (scan_pts[r_ids] - Bs @ X_ref))
                n_rev = int(r_ids.size)
        try:
            lu = spla.splu(A.tocsc(), permc_spec="COLAMD")
            D_a = lu.solve(np.ascontiguousarray(rhs))
        except RuntimeError as e:  # singular factor
            raise FitError(
                f"the registration system is singular at smoothing {ell} mm ({e})."
            ) from None
        if not np.all(np.isfinite(D_a)):
            raise FitError(f"the registration solve produced NaN/inf at smoothing {ell} mm.")
        D = np.zeros_like(X_ref)
        D[act] = D_a
        res = cp.distances[ok]
        history.append(
            {
                "step": step,
                "smoothing_mm": float(ell),
                "reject_mm": tau,
                "landmark_weight_mm2": float(mu),
                "n_active": int(act.size),
                "n_matches": int(ok.sum()),
                "n_reverse": n_rev,
                "mean_mm": float(res.mean()),
                "median_mm": float(np.median(res)),
                "p95_mm": float(np.percentile(res, 95)),
                "seconds": time.perf_counter() - t0,
            }
        )
    X = X_ref + D
    # final residuals (exact)
    cp = index.query(X, max_distance=max(opt.data_tolerance_mm, 1e-6) * 4)
    nrm = vertex_normals(X, tf)
    has = (
        (cp.distances <= opt.data_tolerance_mm)
        & ~cp.on_boundary
        & (np.einsum("ij,ij->i", nrm, cp.normals) >= cos_max)
        & dmask
    )
    mesh = TriMesh(X, tf, validate=False)
    coarse = TriMesh(X_ref, tf, validate=False)
    lpos = np.einsum("kj,kjd->kd", a_bary, X[tf[a_tri]])
    reg_lm = Landmarks(all_names, lpos)
    return Registration(
        mesh=mesh,
        template=tpl,
        landmarks=reg_lm,
        landmark_points=SurfacePoints(a_tri, a_bary),
        face_mask=fmask,
        residuals=cp.distances,
        has_data=has,
        coarse=coarse,
        scan_landmarks=Landmarks(names, dst),
        labels=tuple(names),
        history=tuple(history),
        seconds=time.perf_counter() - t_start,
    )
