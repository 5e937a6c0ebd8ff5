"""The subject of an expression fit (mm): :class:`SubjectOptions`, :class:`Subject` (the
registered template, its rig, compiled forward model and reduced response model), built from
a neutral scan (:func:`prepare_subject`) or from an existing rig (:func:`subject_from_rig`);
:func:`warp_teeth` carries the template's teeth along the registration."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..anatomy.rig import build_rig
from ..errors import FitError, LandmarkError
from ..head import generic_head
from ..io import load_scan
from ..io.scanner import SkinLandmarks
from ..landmarks import Landmarks
from ..mesh import TriMesh
from ..rbf import fit_numpy
from ..surface import SurfacePoints
from .forward import ForwardModel
from .metrics import SurfaceIndex, landmark_dict
from .reduced import ResponseModel, build_response_model
from .register import Registration, Template, register_template
from .subject_cache import CachedParts, UncacheableError, resolve_subject_cache, subject_key

__all__ = ["SubjectOptions", "Subject", "prepare_subject", "subject_from_rig", "warp_teeth"]


@dataclass(frozen=True)
class SubjectOptions:
    """Settings of :func:`prepare_subject`.

    Attributes:
        backend: ``"pbd"`` or ``"ltw"``.
        levels: activation knots of the reduced model (above 0).
        pitch_knots: jaw pitch knots of the reduced model, evenly spaced over the jaw's pitch
            limits (12 over the default 22 degrees: about 2.2 degrees apart; raise it with a
            wider ``jaw_pitch_limits_deg`` to keep the spacing).
        register: :class:`jaxface.fit.register.RegisterOptions` (None = defaults).
        rig_kwargs: extra keyword arguments of :func:`jaxface.anatomy.rig.build_rig`
            (e.g. ``muscle_iterations``); PBD backend only.
        chunk: rig syntheses dispatched at a time (between progress updates).
        controls: sample only these controls in the reduced model (default all; the fit
            must then hold the others at 0 with ``FitOptions.controls``).
        cheek_puff: the two cheeks' pressures (AU34) are controls of the fit, after the
            muscles (:class:`~jaxface.fit.forward.ForwardModel`).
    """

    backend: str = "pbd"
    levels: int = 4
    pitch_knots: int = 12
    register: Any = None
    rig_kwargs: dict = field(default_factory=dict)
    chunk: int = 8
    controls: tuple[str, ...] | None = None
    cheek_puff: bool = True


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
        cache, cache_key: the :class:`~jaxface.fit.subject_cache.SubjectCache` and key the
            subject was stored under or loaded from (None without a cache); the fit keeps
            the noise floor beside it.
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
    cache: Any = None
    cache_key: str | None = None

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


def _fit_ids(tris, face_tri, l_tri) -> np.ndarray:
    """The fit vertices: those of the face triangles and of the landmark triangles."""
    return np.unique(np.concatenate([tris[face_tri].ravel(), tris[np.asarray(l_tri)].ravel()]))


def _compile(rig, opt: SubjectOptions, say, timings: dict) -> ForwardModel:
    """The compiled rig (one synthesis at rest); records ``compile_s``."""
    t = time.perf_counter()
    say("compiling the rig")
    forward = ForwardModel(rig, chunk=opt.chunk, cheek_puff=opt.cheek_puff)
    forward(np.zeros(forward.n_controls), np.zeros(3))
    timings["compile_s"] = time.perf_counter() - t
    return forward


def _sample(forward, fit_ids, opt: SubjectOptions, say, timings: dict) -> ResponseModel:
    """The reduced model over ``fit_ids``; records ``response_s``."""
    t = time.perf_counter()
    say(
        f"sampling the reduced model ({forward.n_controls * opt.levels + 5 * opt.pitch_knots} syntheses)"
    )
    response = build_response_model(
        forward, fit_ids, levels=opt.levels, pitch_knots=opt.pitch_knots, controls=opt.controls
    )
    timings["response_s"] = time.perf_counter() - t
    return response


def _compile_and_sample(rig, tris, face_tri, l_tri, opt: SubjectOptions, say, timings: dict):
    """The fit vertices, the compiled rig and its reduced model over them."""
    fit_ids = _fit_ids(tris, face_tri, l_tri)
    forward = _compile(rig, opt, say, timings)
    return fit_ids, forward, _sample(forward, fit_ids, opt, say, timings)


def prepare_subject(
    neutral,
    neutral_landmarks=None,
    *,
    template=None,
    template_landmarks=None,
    options: SubjectOptions | None = None,
    progress: Callable[[str], None] | None = None,
    cache=None,
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
        cache: the subject cache (:mod:`jaxface.fit.subject_cache`): None reads
            ``$JAXFACE_SUBJECT_CACHE`` (unset: off), ``"default"``, ``"off"``, a folder or a
            :class:`~jaxface.fit.subject_cache.SubjectCache`. On a hit the registration,
            the rig and the reduced model are loaded (``timings["cache_load_s"]``) and only
            the compilation runs; the subject is the same as a fresh build's.

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
    v, tr, _ = neutral.mesh_arrays()
    store = resolve_subject_cache(cache)
    key = None
    if store is not None:
        try:
            key = subject_key(
                v, tr, landmark_dict(neutral.landmarks), template, template_landmarks, opt
            )
        except UncacheableError as e:
            say(f"subject cache not used ({e})")
    t = time.perf_counter()
    parts = store.load(key) if store is not None and key is not None else None
    neutral_index = SurfaceIndex(v, tr)
    if parts is not None:
        assert store is not None
        say(f"loaded the registered neutral, rig and reduced model from {store.folder}")
        timings["cache_load_s"] = time.perf_counter() - t
        forward = _compile(parts.rig, opt, say, timings)
    else:
        parts, forward = _build_parts(
            neutral, neutral_index, template, template_landmarks, opt, say, timings
        )
        if store is not None and key is not None:
            say(f"saving the subject in the cache {store.folder}")
            store.store(key, parts)
    rig, reg = parts.rig, parts.registration
    tris = np.asarray(rig.triangles)
    face_index = SurfaceIndex(reg.vertices, tris, parts.face_triangles)
    return Subject(
        neutral=neutral,
        registration=reg,
        rig=rig,
        forward=forward,
        response=parts.response,
        fit_ids=parts.fit_ids,
        face_triangles=parts.face_triangles,
        landmark_names=parts.landmark_names,
        landmark_tri=parts.landmark_tri,
        landmark_bary=parts.landmark_bary,
        neutral_index=neutral_index,
        face_index=face_index,
        backend=opt.backend,
        timings=timings,
        cache=store if key is not None else None,
        cache_key=key,
    )


def _build_parts(neutral, neutral_index, template, template_landmarks, opt, say, timings):
    """Register, build the rig, compile it and sample its reduced model: the
    :class:`~jaxface.fit.subject_cache.CachedParts` and the compiled forward model."""
    if template is None:
        template = generic_head()
    t = time.perf_counter()
    say("registering the template to the neutral scan")
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
        rig = build_rig(reg.mesh, lm, backend=opt.backend, **opt.rig_kwargs)
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
    parts = CachedParts(
        registration=reg,
        rig=rig,
        response=response,
        fit_ids=fit_ids,
        face_triangles=face_tri,
        landmark_names=tuple(lm.names),
        landmark_tri=l_tri,
        landmark_bary=l_bary,
        timings=dict(timings),
    )
    return parts, forward


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
