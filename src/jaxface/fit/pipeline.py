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
   (:mod:`jaxface.fit.baselines`), and the AU readout (:func:`jaxface.fit.au_motion.read_aus`).

:class:`ExpressionFit` writes ``<stem>.json`` and ``<stem>.fitted.ply`` (and optionally a
before/after picture); the JSON layout is the ``jaxface fit`` contract. The subject lives in
:mod:`jaxface.fit.subject`, the per-scan result in :mod:`jaxface.fit.expression_fit` (both
re-exported here).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._parallel import thread_map
from ..anatomy.jaw import JawPose
from ..errors import FitError, LandmarkError
from ..facs import au_intensities
from ..interop.arkit import readout_for_subject
from ..io import load_scan
from ..mesh import TriMesh
from .align import align_scans
from .au_motion import au_skin_motion, motion_gram, read_aus
from .baselines import baseline_b0, baseline_b1
from .expression_fit import JSON_KEYS, ExpressionFit
from .expression_fit import _jsonable as _jsonable  # used by benchmarks/bench_fit.py
from .metrics import SurfaceIndex, fit_metrics, landmark_dict
from .options import FitOptions
from .quality import assess, check_mirror, check_usable, coverage
from .solve import fit_points
from .subject import Subject, SubjectOptions, prepare_subject, subject_from_rig, warp_teeth
from .subject_cache import UncacheableError, digest

__all__ = [
    "SubjectOptions",
    "Subject",
    "prepare_subject",
    "subject_from_rig",
    "ExpressionFit",
    "fit_expressions",
    "set_noise_floor",
    "scan_fit_inputs",
    "scan_stem",
    "warp_teeth",
    "JSON_KEYS",
]


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
    detected_landmark_weight: float = FitOptions.detected_landmark_weight,
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
    invalid), weighted ``landmark_scale = detected_landmark_weight`` when the scan's or the
    neutral's landmarks were detected (``Scan.landmarks_detected``), else 1.

    Returns:
        dict with ``points``, ``normals``, ``valid``, ``landmarks``, ``landmark_valid``,
        ``landmark_scale``.
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
        "landmark_scale": float(detected_landmark_weight)
        if getattr(scan, "landmarks_detected", False)
        or getattr(subject.neutral, "landmarks_detected", False)
        else 1.0,
        "n_candidates": int(len(P)),
        "n_moving": int(len(moving)),
        "n_moving_drawn": int(n_moving),
    }


def scan_stem(scan) -> str:
    p = getattr(scan, "path", None)
    if p is None:
        return "scan"
    name = Path(p).name
    for suf in (".truth.ply",):
        if name.lower().endswith(suf):
            return name[: -len(suf)]
    return Path(p).stem


def _noise_floor_entry(subject: Subject, opt: FitOptions) -> str | None:
    """The subject cache's side entry of the noise floor under ``opt`` (None: no cache)."""
    if getattr(subject, "cache", None) is None or getattr(subject, "cache_key", None) is None:
        return None
    try:
        return f"noise-floor-{digest(opt)[:24]}"
    except UncacheableError:
        return None


def set_noise_floor(subject: Subject, opt: FitOptions, self_fit, say=None) -> None:
    """Set ``subject.au_noise_floor``: from the subject cache's side entry for ``opt``
    (:mod:`jaxface.fit.subject_cache`) when there is one, else ``self_fit()`` (the neutral
    fitted to itself: AU -> intensity), then kept beside the subject's cache entry."""
    say = say or (lambda s: None)
    entry = _noise_floor_entry(subject, opt)
    if entry is not None:
        cached = subject.cache.load_json(subject.cache_key, entry)
        if isinstance(cached, dict) and cached:
            say("the AU readout's noise floor from the subject cache")
            subject.au_noise_floor = {str(k): float(v) for k, v in cached.items()}
            return
    say("fitting the neutral to itself (the AU readout's noise floor)")
    subject.au_noise_floor = dict(self_fit())
    if entry is not None:  # the same value a recomputation gives
        subject.cache.store_json(subject.cache_key, entry, subject.au_noise_floor)


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
            detected_landmark_weight=opt.detected_landmark_weight,
        )

    def read(f):
        """The AU readout of a fit (:func:`~jaxface.fit.au_motion.read_aus`)."""
        return read_aus(
            subject.response,
            f.activations,
            f.jaw_effective,
            subject.muscle_names,
            weight=opt.au_sparse_weight,
            min_motion_mm=opt.au_min_motion_mm,
            gram=gram,
        )

    def evaluate(item):
        s, al, f, motion, readout_aus = item
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
        ak, ak_detail = (
            readout.from_scan(
                s,
                subject.neutral,
                al.transform,
                tris,
                subject.landmark_names,
                subject.landmark_tri,
                subject.landmark_bary,
                fitted_skin=f.skin,
            )
            if readout is not None
            else (None, {})
        )
        je = f.jaw_effective
        table = au_intensities(
            f.activations, subject.muscle_names, JawPose(float(je[0]), float(je[1]), float(je[2]))
        )
        aus = readout_aus.intensities
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
            au_from_activations=table,
            au_motion_mm=motion,
            au_readout=readout_aus,
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

        def self_fit() -> dict:
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
            return read(f_n).intensities

        set_noise_floor(subject, opt, self_fit, say)
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
        readouts = [read(f) for f in fits]
        for ef in thread_map(
            evaluate, list(zip(batch, aligns, fits, motions, readouts)), outer=True
        ):
            results.append(ef)
            if on_result is not None:
                on_result(ef)
    return results
