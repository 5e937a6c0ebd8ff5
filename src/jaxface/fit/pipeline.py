"""End-to-end expression fitting: neutral scan -> subject rig; expression scans -> activations,
jaw pose, AU intensities, fitted skin, metrics and baselines (issue 7).

Units and frame: millimetres, degrees; +y up; the face looks along +z; the subject's left
is +x. NumPy orchestration around the JAX solver of :mod:`jaxface.fit.solve`.

1. :func:`prepare_subject` (once per subject): register the template (default head, or a
   user mesh with landmarks) to the neutral scan (:func:`jaxface.fit.register.register_template`);
   carry the template's teeth along with a TPS of the registration; build the rig on the
   registered neutral (:func:`jaxface.anatomy.build_rig`: skull, muscles, skin binding);
   compile the rig (:class:`~jaxface.fit.forward.ForwardModel`) and sample its reduced model
   (:func:`~jaxface.fit.reduced.build_response_model`) over the face region.
2. :func:`fit_expressions` (a batch of scans of that subject): rigid alignment of each scan
   to the neutral (:func:`jaxface.fit.align.align_scans`), scan points and normals moved into
   the neutral frame and subsampled, landmark targets (the rig's landmarks displaced by the
   scan's landmark motion), the batched fit (:func:`~jaxface.fit.solve.fit_points`), then per
   scan: the fitted skin moved into the scan's own frame, metrics
   (:func:`jaxface.fit.metrics.fit_metrics`), baselines B0/B1
   (:mod:`jaxface.fit.baselines`), and the AU readout (:func:`jaxface.facs.au_intensities`).

:class:`ExpressionFit` writes ``<stem>.json`` and ``<stem>.fitted.ply`` (and optionally a
before/after picture); the JSON layout is the ``jaxface fit`` contract.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._parallel import thread_map
from ..anatomy.jaw import JawPose
from ..anatomy.rig import build_rig
from ..atomic import ensure_out_dir, write_json_atomic
from ..errors import FitError, LandmarkError
from ..facs import au_intensities, intensity_letters
from ..head import generic_head
from ..interop.arkit import readout_for_subject
from ..io import load_scan
from ..io.scanner import SkinLandmarks
from ..landmarks import Landmarks
from ..mesh import TriMesh, save_mesh
from ..rbf import fit_numpy
from ..render import Layer, draw, save_figure
from ..surface import SurfacePoints
from .align import align_scans
from .au_motion import au_skin_motion, au_sparse, motion_gram
from .baselines import baseline_b0, baseline_b1
from .forward import ForwardModel
from .metrics import SurfaceIndex, fit_metrics, landmark_dict
from .options import FitOptions
from .params import rigid_numpy
from .quality import assess, check_mirror, check_usable, coverage
from .reduced import ResponseModel, build_response_model
from .register import Registration, Template, register_template
from .solve import PointFit, fit_points

__all__ = [
    "SubjectOptions",
    "Subject",
    "prepare_subject",
    "subject_from_rig",
    "ExpressionFit",
    "fit_expressions",
    "scan_fit_inputs",
    "scan_stem",
    "warp_teeth",
    "JSON_KEYS",
]

#: top-level keys of the ``<stem>.json`` written by :meth:`ExpressionFit.write`
JSON_KEYS = (
    "activations",
    "au_intensities",
    "au_motion_mm",
    "au_sparse",
    "jaw",
    "rigid",
    "metrics",
    "baselines",
    "solver",
    "frame",
    "quality",
    "arkit",
    "arkit_detail",
)


@dataclass(frozen=True)
class SubjectOptions:
    """Settings of :func:`prepare_subject`.

    Attributes:
        backend: ``"pbd"`` or ``"ltw"``.
        levels: activation knots of the reduced model (above 0).
        pitch_knots: jaw pitch knots of the reduced model.
        register: :class:`jaxface.fit.register.RegisterOptions` (None = defaults).
        rig_kwargs: extra keyword arguments of :func:`jaxface.anatomy.rig.build_rig`
            (e.g. ``muscle_iterations``); PBD backend only.
        chunk: rig syntheses dispatched at a time (between progress updates).
        controls: sample only these controls in the reduced model (default all; the fit
            must then hold the others at 0 with ``FitOptions.controls``).
    """

    backend: str = "pbd"
    levels: int = 4
    pitch_knots: int = 12
    register: Any = None
    rig_kwargs: dict = field(default_factory=dict)
    chunk: int = 8
    controls: tuple[str, ...] | None = None


@dataclass
class Subject:
    """A subject ready for expression fitting (all in the neutral scan's frame, mm).

    Attributes:
        neutral: the neutral :class:`jaxface.io.Scan` (with landmarks).
        registration: :class:`jaxface.fit.register.Registration` of the template.
        rig: the rig built on the registered neutral.
        forward: its :class:`~jaxface.fit.forward.ForwardModel`.
        response: its :class:`~jaxface.fit.reduced.ResponseModel` over ``fit_ids``.
        fit_ids: ``(P,)`` vertex ids of the face triangles and landmark triangles.
        face_triangles: ``(F,)`` bool face region of the rig skin.
        landmark_names: labels of the rig's landmarks; landmark_tri, landmark_bary: their
            attachment on the rig skin.
        neutral_index: :class:`jaxface.fit.metrics.SurfaceIndex` of the neutral scan.
        face_index: :class:`SurfaceIndex` of the registered neutral's face region.
        timings: seconds per build step.
        au_noise_floor: AU -> intensity of the self-fit (the neutral fitted to itself), the
            AU readout's noise floor (:mod:`jaxface.fit.quality`); set by the first
            :func:`fit_expressions` call with ``noise_floor=True``.
    """

    neutral: Any
    registration: Any
    rig: Any
    forward: ForwardModel
    response: ResponseModel
    fit_ids: np.ndarray
    face_triangles: np.ndarray
    landmark_names: tuple[str, ...]
    landmark_tri: np.ndarray
    landmark_bary: np.ndarray
    neutral_index: Any
    face_index: Any
    backend: str
    timings: dict = field(default_factory=dict)
    au_noise_floor: dict | None = None

    @property
    def muscle_names(self) -> tuple[str, ...]:
        return tuple(self.forward.muscle_names)

    @property
    def triangles(self) -> np.ndarray:
        return np.asarray(self.forward.triangles)

    @property
    def face_mask(self) -> np.ndarray:
        """``(V,)`` bool face region of the rig skin."""
        return np.asarray(self.registration.face_mask, bool)

    def landmarks_on(self, vertices) -> Any:
        """The rig's landmarks on a skin with the rig's topology (Landmarks, mm)."""
        bound = SkinLandmarks(
            self.landmark_names, self.landmark_tri, self.landmark_bary, self.triangles
        )
        return bound.landmarks(vertices)


def warp_teeth(template, registration, radius_mm: float = 60.0):
    """The template's teeth carried onto the registered neutral (mm): a thin-plate spline
    through up to 400 template vertices within ``radius_mm`` of the mouth landmarks and their
    registered positions. ``(None, None)`` when the template has no teeth."""
    if (
        getattr(template, "upper_teeth", None) is None
        or getattr(template, "lower_teeth", None) is None
    ):
        return None, None
    tv = np.asarray(registration.template.mesh.vertices, np.float64)
    rv = registration.vertices
    lm = landmark_dict(registration.template.landmarks)
    mouth = [
        lm[n]
        for n in (
            "Left mouth corner",
            "Right mouth corner",
            "Upper lip outer middle",
            "Lower lip outer middle",
        )
        if n in lm
    ]
    centre = np.mean(mouth, axis=0) if mouth else tv.mean(axis=0)
    near = np.flatnonzero(np.linalg.norm(tv - centre, axis=1) < radius_mm)
    if near.size < 20:
        return None, None
    sel = near[np.linspace(0, near.size - 1, min(400, near.size)).astype(np.int64)]
    morph = fit_numpy(tv[sel], rv[sel], kernel="tps", reg=1e-6, merge_duplicates=True)
    return tuple(
        TriMesh(morph.apply_np(np.asarray(t.vertices)), np.asarray(t.triangles), validate=False)
        for t in (template.upper_teeth, template.lower_teeth)
    )


def _compile_and_sample(rig, tris, face_tri, l_tri, opt: SubjectOptions, say, timings: dict):
    """The fit vertices (face triangles + landmark triangles), the compiled rig and its reduced
    model over them; records ``compile_s`` and ``response_s`` in ``timings``."""
    fit_ids = np.unique(np.concatenate([tris[face_tri].ravel(), tris[np.asarray(l_tri)].ravel()]))
    t = time.perf_counter()
    say("compiling the rig")
    forward = ForwardModel(rig, chunk=opt.chunk)
    forward(np.zeros(forward.n_controls), np.zeros(3))
    timings["compile_s"] = time.perf_counter() - t
    t = time.perf_counter()
    say(
        f"sampling the reduced model ({forward.n_controls * opt.levels + 5 * opt.pitch_knots} syntheses)"
    )
    response = build_response_model(
        forward, fit_ids, levels=opt.levels, pitch_knots=opt.pitch_knots, controls=opt.controls
    )
    timings["response_s"] = time.perf_counter() - t
    return fit_ids, forward, response


def prepare_subject(
    neutral,
    neutral_landmarks=None,
    *,
    template=None,
    template_landmarks=None,
    options: SubjectOptions | None = None,
    progress: Callable[[str], None] | None = None,
) -> Subject:
    """Build the subject's rig from its neutral scan.

    Arguments:
        neutral: the neutral :class:`jaxface.io.Scan` (or a path to a ``.bnt``/mesh scan),
            mm.
        neutral_landmarks: its landmarks (default: the scan's own).
        template: ``None`` (the default head with its teeth), a ``Head``-like object, a
            :class:`jaxface.fit.register.Template`, or a mesh (then ``template_landmarks``).
        template_landmarks: landmarks of a template mesh, mm.
        options: :class:`SubjectOptions`.
        progress: called with a short text before each step.

    Raises:
        LandmarkError: the neutral has no landmarks; FitError / RigError: registration or
            rig building failed (named in the message).
    """
    opt = options or SubjectOptions()
    say = progress or (lambda s: None)
    timings: dict[str, float] = {}
    if isinstance(neutral, (str, Path)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            neutral = load_scan(neutral, landmarks=neutral_landmarks)
        neutral_landmarks = None
    if neutral_landmarks is not None:
        neutral = neutral.with_landmarks(neutral_landmarks)
    if getattr(neutral, "landmarks", None) is None:
        raise LandmarkError(
            f"the neutral scan {getattr(neutral, 'path', '')} has no landmarks: give its .lm3 file "
            "(--neutral-landmarks) or put it beside the scan."
        )
    if template is None:
        template = generic_head()
    t = time.perf_counter()
    say("registering the template to the neutral scan")
    v, tr, _ = neutral.mesh_arrays()
    neutral_index = SurfaceIndex(v, tr)
    reg = register_template(
        neutral,
        template=template,
        template_landmarks=template_landmarks,
        options=opt.register,
        scan_index=neutral_index,
    )
    timings["register_s"] = time.perf_counter() - t
    t = time.perf_counter()
    say(f"building the {opt.backend} rig on the registered neutral")
    upper, lower = warp_teeth(template, reg) if template_landmarks is None else (None, None)
    lm = reg.landmarks
    if opt.backend == "pbd":
        rig = build_rig(reg.mesh, lm, upper_teeth=upper, lower_teeth=lower, **opt.rig_kwargs)
    else:
        rig = build_rig(reg.mesh, lm, backend=opt.backend)
    timings["rig_s"] = time.perf_counter() - t
    tris = np.asarray(rig.triangles)
    if tris.shape != np.asarray(reg.mesh.triangles).shape or not np.array_equal(
        tris, reg.mesh.triangles
    ):
        raise FitError(
            "the rig's skin topology differs from the registered template's; cannot attach "
            "the landmarks and the face mask."
        )
    face_tri = np.asarray(np.asarray(reg.face_mask, bool)[tris].all(axis=1))
    if not face_tri.any():
        raise FitError("the template's face mask selects no triangle of the skin.")
    lp = reg.landmark_points
    l_tri = np.asarray(lp.tri, np.int64)
    l_bary = np.asarray(lp.bary, np.float64)
    fit_ids, forward, response = _compile_and_sample(rig, tris, face_tri, l_tri, opt, say, timings)
    face_index = SurfaceIndex(reg.vertices, tris, face_tri)
    return Subject(
        neutral=neutral,
        registration=reg,
        rig=rig,
        forward=forward,
        response=response,
        fit_ids=fit_ids,
        face_triangles=face_tri,
        landmark_names=tuple(lm.names),
        landmark_tri=l_tri,
        landmark_bary=l_bary,
        neutral_index=neutral_index,
        face_index=face_index,
        backend=opt.backend,
        timings=timings,
    )


def subject_from_rig(
    rig,
    neutral,
    *,
    face_mask=None,
    options: SubjectOptions | None = None,
    progress: Callable[[str], None] | None = None,
) -> Subject:
    """A :class:`Subject` from an existing rig, without registration (the rig's rest skin is
    taken as registered to ``neutral``): for synthetic round trips, where the scans are
    made from this very rig.

    Arguments:
        rig: a rig (its rest skin and landmarks in ``neutral``'s frame, mm).
        neutral: the neutral :class:`jaxface.io.Scan` with landmarks (e.g. a virtual scan of
            the rest skin, :func:`jaxface.io.scanner.scan_mesh`).
        face_mask: ``(V,)`` bool face region of the rig skin (default: every vertex).
        options: :class:`SubjectOptions` (reduced-model knots, chunk, controls).
    """
    opt = options or SubjectOptions()
    say = progress or (lambda s: None)
    if getattr(neutral, "landmarks", None) is None:
        raise LandmarkError("subject_from_rig needs the neutral scan's landmarks.")
    timings: dict[str, float] = {}
    rest = np.asarray(rig.rest, np.float64)
    tris = np.asarray(rig.triangles)
    V = len(rest)
    fm = np.ones(V, bool) if face_mask is None else np.asarray(face_mask, bool)
    if fm.shape != (V,):
        raise FitError(f"face_mask must be ({V},) bool over the rig skin, got {fm.shape}.")
    face_tri = np.asarray(fm[tris].all(axis=1))
    lm = landmark_dict(rig.info.landmarks)
    names = list(lm)
    cp = SurfaceIndex(rest, tris).query(np.stack([lm[n] for n in names]))
    l_tri, l_bary = cp.triangles, cp.bary
    mesh = TriMesh(rest, tris, validate=False)
    reg_lm = Landmarks(tuple(names), cp.points)
    nl = landmark_dict(neutral.landmarks)
    common = tuple(n for n in names if n in nl)
    reg = Registration(
        mesh=mesh,
        template=Template(mesh, reg_lm, fm, "rig rest skin"),
        landmarks=reg_lm,
        landmark_points=SurfacePoints(l_tri, l_bary),
        face_mask=fm,
        residuals=np.zeros(V),
        has_data=np.ones(V, bool),
        coarse=mesh,
        scan_landmarks=Landmarks(common, np.stack([nl[n] for n in common])),
        labels=common,
    )
    fit_ids, forward, response = _compile_and_sample(rig, tris, face_tri, l_tri, opt, say, timings)
    v, tr, _ = neutral.mesh_arrays()
    return Subject(
        neutral=neutral,
        registration=reg,
        rig=rig,
        forward=forward,
        response=response,
        fit_ids=fit_ids,
        face_triangles=face_tri,
        landmark_names=tuple(names),
        landmark_tri=np.asarray(l_tri),
        landmark_bary=np.asarray(l_bary),
        neutral_index=SurfaceIndex(v, tr),
        face_index=SurfaceIndex(rest, tris, face_tri),
        backend=getattr(rig, "backend", "pbd"),
        timings=timings,
    )


# --------------------------------------------------------------------------------------
# one expression scan
# --------------------------------------------------------------------------------------
def scan_fit_inputs(
    subject: Subject,
    scan,
    transform,
    n_points: int,
    *,
    seed: int = 0,
    preselect_mm: float = 20.0,
    motion_fraction: float = FitOptions.motion_fraction,
    motion_threshold_mm: float = FitOptions.motion_threshold_mm,
) -> dict:
    """The fitter's view of one scan, in the neutral frame (mm).

    Scan vertices (off the scan border, with a normal) are moved by ``transform`` (scan ->
    neutral), kept when they lie within ``preselect_mm`` of the registered neutral's face
    region (and not beyond its border by more than 3 mm), and subsampled (seeded) to
    ``n_points`` (padded with invalid rows): up to ``motion_fraction`` of them from the points
    farther than ``motion_threshold_mm`` from the registered neutral (the expression's moving
    region; defaults and meaning: :class:`~jaxface.fit.options.FitOptions`), the rest evenly
    from all. Scan normals are flipped when most of them
    point into the face (a mesh scan wound the other way round). Landmark targets: the rig's
    rest landmarks displaced by ``T(q_scan) - q_neutral`` (labels missing in either scan are
    invalid).

    Returns:
        dict with ``points``, ``normals``, ``valid``, ``landmarks``, ``landmark_valid``.
    """
    v, tr, _ = scan.mesh_arrays()
    si = SurfaceIndex(v, tr)
    used = np.zeros(len(v), bool)
    used[tr.ravel()] = True
    nrm = si.vertex_normals
    ok = used & ~si.boundary_vertices & (np.linalg.norm(nrm, axis=1) > 0.5)
    ids = np.flatnonzero(ok)
    P = transform.apply(v[ids])
    N = transform.apply_vectors(nrm[ids])
    cp = subject.face_index.query(P, max_distance=preselect_mm * 2)
    keep = (cp.distances <= preselect_mm) & (~cp.on_boundary | (cp.distances <= 3.0))
    if keep.any() and np.median(np.einsum("kd,kd->k", N[keep], cp.normals[keep])) < 0:
        N = -N  # a mesh scan whose triangles are wound the other way round: normals inward
    P, N = P[keep], N[keep]
    if len(P) == 0:
        raise FitError(
            f"no point of the scan {getattr(scan, 'path', '')} lies within {preselect_mm} mm of the "
            "subject's face after the rigid alignment; check the landmarks of both scans."
        )
    rng = np.random.default_rng(seed)
    moving = np.flatnonzero(cp.distances[keep] > motion_threshold_mm)
    n_moving = min(int(round(motion_fraction * n_points)), len(moving))
    if n_moving > 0:
        first = rng.permutation(moving)[:n_moving]
        rest = np.setdiff1d(np.arange(len(P)), first, assume_unique=True)
        order = np.concatenate([first, rng.permutation(rest)[: n_points - n_moving]])
    else:
        order = rng.permutation(len(P))[:n_points]
    order.sort()
    pts = np.zeros((n_points, 3))
    nn = np.zeros((n_points, 3))
    nn[:, 2] = 1.0
    valid = np.zeros(n_points, bool)
    pts[: len(order)] = P[order]
    nn[: len(order)] = N[order]
    valid[: len(order)] = True
    # landmarks
    rest_lm = subject.landmarks_on(subject.forward.rest)
    rest = landmark_dict(rest_lm)
    q_n = landmark_dict(subject.neutral.landmarks)
    q_e = landmark_dict(scan.landmarks)
    tgt = np.zeros((len(subject.landmark_names), 3))
    lv = np.zeros(len(subject.landmark_names), bool)
    for i, name in enumerate(rest):
        if name in q_n and name in q_e:
            tgt[i] = rest[name] + transform.apply(q_e[name][None])[0] - q_n[name]
            lv[i] = True
        else:
            tgt[i] = rest[name]
    return {
        "points": pts,
        "normals": nn,
        "valid": valid,
        "landmarks": tgt,
        "landmark_valid": lv,
        "n_candidates": int(len(P)),
        "n_moving": int(len(moving)),
        "n_moving_drawn": int(n_moving),
    }


@dataclass
class ExpressionFit:
    """The fit of one expression scan (see :meth:`to_dict` for the JSON contract).

    Attributes:
        stem: the scan's file stem; scan: the :class:`jaxface.io.Scan`.
        alignment: :class:`jaxface.fit.align.AlignmentResult` (scan -> neutral frame).
        fit: the :class:`~jaxface.fit.solve.PointFit` (neutral frame).
        fitted: the fitted skin, :class:`jaxface.mesh.TriMesh` in the scan's own frame, mm.
        fitted_landmarks: the rig's landmarks on it (scan frame, mm).
        activations: muscle -> activation; au_intensities: AU -> intensity.
        au_motion_mm: AU -> RMS skin motion (mm) that AU's share of the fit produces alone
            (:func:`jaxface.fit.au_motion.au_skin_motion`): which AUs the expression *shows*.
        au_sparse: AU -> intensity of the sparsest AU combination that reproduces the fit's
            skin motion (:func:`jaxface.fit.au_motion.au_sparse`); au_sparse_misfit_mm: the RMS
            distance (mm) between that combination's motion and the fit's.
        metrics: :class:`jaxface.fit.metrics.FitMetrics` of the fit; baselines: ``{"B0":
            FitMetrics, "B1": FitMetrics}``; baseline_meshes: ``{"B0": TriMesh, "B1": TriMesh}``.
        muscle_names: the rig's control order.
        arkit: ARKit-52 name -> coefficient in [0, 1] read from the fitted skin motion
            (:mod:`jaxface.interop.arkit`), or None when unavailable; arkit_detail: each
            coefficient's contribution (mm), the residual (mm), or the reason it is missing.
    """

    stem: str
    scan: Any
    alignment: Any
    fit: PointFit
    fitted: Any
    fitted_landmarks: Any
    activations: dict
    au_intensities: dict
    au_motion_mm: dict
    metrics: Any
    baselines: dict
    baseline_meshes: dict
    muscle_names: tuple
    backend: str
    options: FitOptions
    notes: list = field(default_factory=list)
    face_mask: np.ndarray | None = None
    au_sparse: dict = field(default_factory=dict)
    au_sparse_misfit_mm: float | None = None
    quality: Any = None
    arkit: dict | None = None
    arkit_detail: dict = field(default_factory=dict)

    @property
    def status(self) -> str:
        return self.fit.status

    @property
    def jaw(self) -> dict:
        j = self.fit.jaw_effective
        return {"pitch_deg": float(j[0]), "yaw_deg": float(j[1]), "protrusion_mm": float(j[2])}

    def rigid_dict(self) -> dict:
        R, t = rigid_numpy(self.fit.rigid, self.fit.centre)
        Tn = self.alignment.transform  # scan -> neutral
        # fitted skin in the scan frame = Tn^-1 (R x + t) for rig coordinates x
        Ti = Tn.inverse()
        M = Ti.rotation @ R
        tt = Ti.rotation @ t + Ti.translation
        return {
            "alignment": {
                "description": "scan frame -> neutral scan frame (p_neutral = R p_scan + t), mm",
                **self.alignment.to_dict(),
            },
            "correction": {
                "description": "fitted rigid correction in the neutral frame: x -> c + R(w) (x - c) + t",
                "rotation_vector_deg": [float(x) for x in self.fit.rigid[:3]],
                "translation_mm": [float(x) for x in self.fit.rigid[3:]],
                "centre_mm": [float(x) for x in self.fit.centre],
            },
            "rig_to_scan": {
                "description": "rig (registered neutral) coordinates -> this scan's frame: p = R x + t, mm",
                "rotation": M.tolist(),
                "translation": tt.tolist(),
            },
        }

    def solver_dict(self) -> dict:
        f = self.fit
        return {
            "status": f.status,
            "converged": f.status == "successful",
            "steps": f.steps,
            "time_s": f.seconds,
            "method": "optimistix LevenbergMarquardt (forward-mode Jacobian) on the rig's reduced model "
            "with exact-rig defect correction; correspondences refreshed per outer iteration"
            + (
                f"; {self.options.exact_steps} exact-rig LM steps at the end"
                if self.options.exact_steps
                else ""
            ),
            "backend": self.backend,
            "outer_iterations": [r.to_dict() for r in f.reports],
            "jaw_start_pitch_deg": f.start_pitch,
            "jaw_as_fitted": {
                "pitch_deg": float(f.jaw[0]),
                "yaw_deg": float(f.jaw[1]),
                "protrusion_mm": float(f.jaw[2]),
            },
            "residual_mm": f.residual_mm,
            "restart": dict(f.restart) if f.restart else None,
            "notes": list(self.notes),
        }

    def frame_dict(self) -> dict:
        return {
            "name": "scan",
            "description": "the input scan's own coordinate frame (the .fitted.ply and every landmark "
            "and metric are in it)",
            "scan": str(getattr(self.scan, "path", "") or self.stem),
            "units": "mm",
            "axes": "+y up, +z toward the viewer (the face looks along +z), subject's left +x",
        }

    def to_dict(self) -> dict:
        """The JSON contract of ``jaxface fit`` (mm, degrees)."""
        return {
            "scan": self.stem,
            "activations": {k: float(v) for k, v in self.activations.items()},
            "au_intensities": {k: float(v) for k, v in self.au_intensities.items()},
            "au_intensity_letters": intensity_letters(self.au_intensities),
            "au_motion_mm": {k: float(v) for k, v in self.au_motion_mm.items()},
            "au_sparse": {k: float(v) for k, v in self.au_sparse.items()},
            "au_sparse_misfit_mm": self.au_sparse_misfit_mm,
            "jaw": self.jaw,
            "rigid": self.rigid_dict(),
            "metrics": self.metrics.to_dict(),
            "baselines": {k: v.to_dict() for k, v in self.baselines.items()},
            "solver": self.solver_dict(),
            "frame": self.frame_dict(),
            "quality": None if self.quality is None else self.quality.to_dict(),
            "arkit": None if self.arkit is None else {k: float(v) for k, v in self.arkit.items()},
            "arkit_detail": dict(self.arkit_detail),
        }

    def strongest_aus(
        self, n: int = 5, *, bilateral_only: bool = False, by: str = "intensity"
    ) -> list[tuple[str, float]]:
        """The ``n`` strongest AUs, strongest first: ``(name, intensity)`` with
        ``by="intensity"`` (:attr:`au_intensities`), ``(name, mm)`` with ``by="motion"``
        (:attr:`au_motion_mm`, the skin motion each AU accounts for), ``(name, intensity)``
        with ``by="sparse"`` (:attr:`au_sparse`, the fewest AUs that reproduce the motion)."""
        srcs = {
            "intensity": self.au_intensities,
            "motion": self.au_motion_mm,
            "sparse": self.au_sparse,
        }
        if by not in srcs:
            raise ValueError(f"by must be 'intensity', 'motion' or 'sparse', got {by!r}.")
        src = srcs[by]
        items = [(k, v) for k, v in src.items() if not (bilateral_only and k[-1] in "LR")]
        return sorted(items, key=lambda kv: -kv[1])[:n]

    def write(self, out_dir, *, pictures: bool = False) -> dict[str, Path]:
        """Write ``<stem>.json``, ``<stem>.fitted.ply`` (and ``<stem>.fit.png``). Returns the
        paths."""
        out = ensure_out_dir(out_dir)
        files = {}
        p = out / f"{self.stem}.json"
        write_json_atomic(p, _jsonable(self.to_dict()))
        files["json"] = p
        m = out / f"{self.stem}.fitted.ply"
        save_mesh(m, self.fitted, units="mm")
        files["ply"] = m
        if pictures:
            files["picture"] = self.picture(out / f"{self.stem}.fit.png")
        return files

    def picture(self, path) -> Path:
        """Before/after panel: the scan, B0 (before), the fit, and the fit coloured by its
        distance to the scan (mm, colour bar)."""
        import os

        os.environ.setdefault("MPLBACKEND", "Agg")
        import matplotlib
        import matplotlib.cm
        import matplotlib.colors
        from matplotlib.figure import Figure

        v, tr, _ = self.scan.mesh_arrays()
        fv = np.asarray(self.fitted.vertices)
        ft = np.asarray(self.fitted.triangles)
        face = self._face_mask()
        err = np.full(len(fv), np.nan)
        cp = SurfaceIndex(v, tr).query(fv[face], max_distance=20.0)
        e = np.where(cp.on_boundary, np.nan, cp.distances)
        err[face] = e
        hi = float(np.nanpercentile(err, 98)) if np.isfinite(err).any() else 1.0
        hi = max(hi, 0.5)
        ftri = face[ft].all(axis=1)
        sub = ft[ftri]
        b0 = self.baseline_meshes["B0"]
        bounds = np.stack([v.min(0), v.max(0)])
        panels = [
            ("scan", Layer(v, tr)),
            ("before (B0: neutral)", Layer(np.asarray(b0.vertices), sub)),
            ("fit", Layer(fv, sub)),
            (
                "fit: distance to scan",
                Layer(
                    fv, sub, scalars=err, cmap="magma", vmin=0.0, vmax=hi, shade=0.55, specular=0.04
                ),
            ),
        ]
        dpi, px = 100, 360
        fig = Figure(figsize=(len(panels) * px / dpi + 1.0, px / dpi + 0.4), dpi=dpi)
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        fig.subplots_adjust(
            left=0.005, right=1.0 - 1.0 / fig.get_figwidth(), bottom=0.01, top=0.88, wspace=0.02
        )
        for ax, (name, layer) in zip(axes, panels):
            draw(ax, [layer], "front", width=px, height=px, bounds=bounds, title=name)
        sm = matplotlib.cm.ScalarMappable(
            norm=matplotlib.colors.Normalize(0.0, hi), cmap=matplotlib.colormaps["magma"]
        )
        cax = fig.add_axes((1.0 - 0.8 / fig.get_figwidth(), 0.12, 0.18 / fig.get_figwidth(), 0.7))
        fig.colorbar(sm, cax=cax).set_label("distance to scan (mm)")
        s = self.metrics.scan_to_fit["all"]
        fig.suptitle(
            f"{self.stem}: scan-to-fit mean {s.mean:.2f} mm (B0 "
            f"{self.baselines['B0'].scan_to_fit['all'].mean:.2f} mm), status {self.status}",
            fontsize=10,
        )
        return save_figure(fig, path)

    def _face_mask(self) -> np.ndarray:
        m = self.face_mask
        return np.ones(len(self.fitted.vertices), bool) if m is None else np.asarray(m, bool)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def scan_stem(scan) -> str:
    p = getattr(scan, "path", None)
    if p is None:
        return "scan"
    name = Path(p).name
    for suf in (".truth.ply",):
        if name.lower().endswith(suf):
            return name[: -len(suf)]
    return Path(p).stem


def fit_expressions(
    subject: Subject,
    scans: Sequence,
    *,
    options: FitOptions | None = None,
    scan_landmarks: Sequence | None = None,
    progress: Callable[[str], None] | None = None,
    batch_size: int | None = None,
    on_result: Callable[[ExpressionFit], None] | None = None,
    noise_floor: bool = False,
    arkit: Any = "auto",
) -> list[ExpressionFit]:
    """Fit a batch of expression scans of the subject.

    Arguments:
        subject: from :func:`prepare_subject`.
        scans: :class:`jaxface.io.Scan` objects (with landmarks) or paths.
        options: :class:`~jaxface.fit.options.FitOptions`.
        scan_landmarks: optional landmarks per scan (override the scans' own).
        progress: called with short texts.
        batch_size: scans fitted together (default: all;
            :func:`~jaxface.fit.inner.solve_inner`). The alignment, the exact syntheses
            and inner solves of every outer iteration, and the evaluation (metrics,
            baselines) of a batch's scans run concurrently on the outer thread pool
            (:mod:`jaxface._parallel`), so a batch costs less per scan than single fits
            (README, "A batch fits its scans two at a time"), and each scan gets the fit it
            gets alone.
        on_result: called with each finished :class:`ExpressionFit` (e.g. to write it).
        noise_floor: fit the subject's neutral to itself once (stored in
            ``subject.au_noise_floor``, one more fit per subject) for the AU readout's noise
            floor in each result's ``quality`` (``jaxface fit`` does); False (default): no
            noise check unless ``subject.au_noise_floor`` is already set.
        arkit: the ARKit readout's ICT data: ``"auto"`` (``$JAXFACE_ICT`` or the shared
            folder), a path to ``ict_face.npz``, an ``ArkitBasis``, or None (off);
            :func:`jaxface.interop.arkit.readout_for_subject`.

    Returns:
        one :class:`ExpressionFit` per scan, in order.

    Raises:
        LandmarkError: a scan without landmarks; FitError: the fit failed numerically.
    """
    opt = options or FitOptions()
    say = progress or (lambda s: None)
    loaded = []
    for i, s in enumerate(scans):
        if isinstance(s, (str, Path)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lmk = (
                    None
                    if scan_landmarks is None or scan_landmarks[i] is None
                    else scan_landmarks[i]
                )
                s = load_scan(s, landmarks=lmk)
        elif scan_landmarks is not None and scan_landmarks[i] is not None:
            s = s.with_landmarks(scan_landmarks[i])
        if getattr(s, "landmarks", None) is None:
            raise LandmarkError(
                f"the scan {getattr(s, 'path', i)} has no landmarks: give its .lm3 file (--scan-landmarks) "
                "or put it beside the scan with the same stem."
            )
        loaded.append(s)
    bs = batch_size or max(len(loaded), 1)
    results: list[ExpressionFit] = []
    gram = (
        motion_gram(subject.response) if loaded else None
    )  # the sparse AU readout's, once per call
    reg = subject.registration
    tris = subject.triangles
    readout = readout_for_subject(subject, arkit) if loaded else None

    hands_of: dict[int, tuple] = {}  # alignment -> landmark handedness (neutral, scan)
    index_of: dict[int, Any] = {}  # alignment -> SurfaceIndex of its scan

    def prepare(s):
        hands = check_mirror(subject.neutral.landmarks, s.landmarks, f"the scan {scan_stem(s)}")
        al = align_scans(s, subject.neutral, fixed_index=subject.neutral_index)
        index = SurfaceIndex(*s.mesh_arrays()[:2])
        check_usable(
            coverage(al.transform.inverse().apply(reg.vertices), reg.face_mask, index),
            f"the scan {scan_stem(s)}",
        )
        hands_of[id(al)] = hands
        index_of[id(al)] = index
        return al, scan_fit_inputs(
            subject,
            s,
            al.transform,
            opt.n_points,
            seed=opt.seed,
            motion_fraction=opt.motion_fraction,
            motion_threshold_mm=opt.motion_threshold_mm,
        )

    def evaluate(item):
        s, al, f, motion, sparse = item
        Ti = al.transform.inverse()
        fitted = TriMesh(Ti.apply(f.skin), tris, validate=False)
        flm = subject.landmarks_on(fitted.vertices)
        metrics = fit_metrics(
            fitted, s, face_mask=reg.face_mask, fitted_landmarks=flm, scan_landmarks=s.landmarks
        )
        b0m = baseline_b0(reg, al)
        b1m = baseline_b1(reg, s.landmarks, al, neutral_landmarks=subject.neutral.landmarks)
        base = {}
        for name, mesh in (("B0", b0m), ("B1", b1m)):
            base[name] = fit_metrics(
                mesh,
                s,
                face_mask=reg.face_mask,
                fitted_landmarks=subject.landmarks_on(mesh.vertices),
                scan_landmarks=s.landmarks,
            )
        ak, ak_detail = readout(f.skin) if readout is not None else (None, {})
        je = f.jaw_effective
        aus = au_intensities(
            f.activations, subject.muscle_names, JawPose(float(je[0]), float(je[1]), float(je[2]))
        )
        quality = assess(
            fitted_vertices=fitted.vertices,
            face_mask=reg.face_mask,
            neutral_landmarks=subject.neutral.landmarks,
            scan_landmarks=s.landmarks,
            scan_index=index_of[id(al)],
            au_intensities=aus,
            noise_floor=subject.au_noise_floor,
            hands=hands_of.get(id(al), (None, None)),
        )
        notes = list(al.notes)
        if f.status != "successful":
            notes.append(
                f"the last inner solve ended with '{f.status}' (see solver.outer_iterations)"
            )
        return ExpressionFit(
            stem=scan_stem(s),
            scan=s,
            alignment=al,
            fit=f,
            fitted=fitted,
            fitted_landmarks=flm,
            activations=dict(zip(subject.muscle_names, map(float, f.activations))),
            au_intensities=aus,
            au_motion_mm=motion,
            au_sparse=sparse[0],
            au_sparse_misfit_mm=sparse[1],
            metrics=metrics,
            baselines=base,
            baseline_meshes={"B0": b0m, "B1": b1m},
            muscle_names=subject.muscle_names,
            backend=subject.backend,
            options=opt,
            notes=notes,
            face_mask=np.asarray(reg.face_mask, bool),
            quality=quality,
            arkit=ak,
            arkit_detail=ak_detail,
        )

    if noise_floor and loaded and subject.au_noise_floor is None:
        say("fitting the neutral to itself (the AU readout's noise floor)")
        _, inp_n = prepare(subject.neutral)
        (f_n,) = fit_points(
            subject.forward,
            subject.response,
            subject.fit_ids,
            subject.face_triangles,
            [inp_n],
            subject.landmark_tri,
            subject.landmark_bary,
            opt,
            progress=say,
        )
        jn = f_n.jaw_effective
        subject.au_noise_floor = au_intensities(
            f_n.activations, subject.muscle_names, JawPose(float(jn[0]), float(jn[1]), float(jn[2]))
        )
    for b0 in range(0, len(loaded), bs):
        batch = loaded[b0 : b0 + bs]
        say(
            f"aligning {scan_stem(batch[0]) if len(batch) == 1 else f'{len(batch)} scans'} to the neutral"
        )
        # independent per-scan work runs on the outer thread pool (both cores on a 2-core CPU)
        prepared = thread_map(prepare, batch, outer=True)
        aligns = [a for a, _ in prepared]
        inputs = [i for _, i in prepared]
        say(f"fitting {len(batch)} scan(s)")
        fits = fit_points(
            subject.forward,
            subject.response,
            subject.fit_ids,
            subject.face_triangles,
            inputs,
            subject.landmark_tri,
            subject.landmark_bary,
            opt,
            progress=say,
        )
        say(f"evaluating {len(batch)} fit(s) and the baselines")
        motions = [
            au_skin_motion(subject.response, f.activations, f.jaw_effective, subject.muscle_names)
            for f in fits
        ]  # JAX, on this thread (one compilation per subject)
        sparse = [
            au_sparse(
                subject.response,
                f.activations,
                f.jaw_effective,
                subject.muscle_names,
                weight=opt.au_sparse_weight,
                gram=gram,
            )
            for f in fits
        ]
        for ef in thread_map(evaluate, list(zip(batch, aligns, fits, motions, sparse)), outer=True):
            results.append(ef)
            if on_result is not None:
                on_result(ef)
    return results
