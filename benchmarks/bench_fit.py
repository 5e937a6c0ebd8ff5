"""Benchmark of the inverse fit (issue 7): accuracy on every Bosphorus-style scan against the
ground-truth meshes, the baselines, the AU readout, a synthetic round trip with Jacobian
conditioning, and the time per fit (single scan and batched).

Run from the repository root (needs the shared data: ``JAXFACE_SHARED`` or ``../shared``)::

    python benchmarks/bench_fit.py [--subjects bs900,bs901] [--no-round-trip] [--no-single]
                                   [--round-trip-ict] [--exact-steps N]
                                   [--sweeps MUSCLE/SKIN[/RHO] | fast | converged | reference]
                                   [--results DIR] [--no-b2] [--warm-batch] [--truth-as-scan]
                                   [--motion-fraction F] [--robust-floor FIRST,LAST]

``--truth-as-scan`` fits the face skin of each expression's exact truth mesh (noise-free and
hole-free, with the scan's landmarks) instead of its range scan: how close the model itself
can come.
``--no-b2`` skips baseline B2 (it reads the other subject's scans); ``--warm-batch`` fits the
batch a second time, once its solves are compiled (``batch_warm``: on an accelerator the
first batch compiles the vmapped inner solve for its padded size). ``--sweeps`` builds the subjects' rigs with other quasi-static sweep counts than
:func:`jaxface.anatomy.build_rig`'s 32/8 (as ``jaxface synth --sweeps``; the round trips keep
the defaults); ``--rig-option NAME=JSON`` (repeatable) passes a
:func:`jaxface.anatomy.build_rig` option to the subjects' rigs and ``--pitch-knots`` sets
``SubjectOptions.pitch_knots``; ``--results`` writes the JSON and the picture elsewhere than
``benchmarks/results``.

Measures (units mm, degrees, seconds):

* per subject: the subject build (template registration, rig, compilation, reduced model);
* per scan (all codes, both subjects; fitted as one batch per subject): the
  issue-7 error of the fitted skin against ``<stem>.truth.ply`` over the evaluation region
  (:func:`jaxface.fit.evaluation.evaluate_against_truth`), the same for B0 and B1, and for B2
  (Erdoğdu 2010, :func:`jaxface.fit.baselines.baseline_b2`: the scan's AU transferred from the
  other subject's neutral and same-code scan, magnitude fitted to the scan) on the single-AU
  scans it applies to, the ratio B0 / fit, scan-to-fit metrics, solver status and steps, jaw pose, and the AU readout: the
  rank of each AU named by the file's code among the fitted bilateral AUs (and the side for
  ``LFAU_12L``), by the fit's intensities (``au_intensities``,
  :func:`jaxface.fit.au_motion.read_aus`: the fewest AUs that reproduce the fit's motion), by
  the skin motion each AU accounts for (:func:`jaxface.fit.au_motion.au_skin_motion`, mm) and
  by the table's inverse of the activations (``au_from_activations``,
  :func:`jaxface.facs.au_intensities`), with the checks of ``au_checks.py`` for both readouts;
* the neutral scans: registration error (B0 of ``N_N``) against the truth;
* time per expression scan: one scan alone (cold: includes compiling the solver; warm: a
  second scan with the compiled solver), the batch (wall time / number of scans), and every
  scan of the batch fitted alone after it (``singles``; ``singles_over_batch`` is the batch
  mode's speed-up, measured side by side in one run);
* round trip: activations and a jaw pose synthesised on the default head (and, with
  ``--round-trip-ict``, on the ICT face) with the rig, scanned by the virtual scanner
  (:func:`jaxface.io.scanner.scan_skin`, 1 mm grid), fitted back with every control free:
  scan match, jaw and activation errors, and the Jacobian's singular values per parameter
  group, sensitivity and variance inflation factor per parameter.

Prints tables and writes ``benchmarks/results/bench_fit.json`` and
``benchmarks/results/bench_fit_errors.png`` (each scan's signed error against its truth mesh,
front view).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

from au_checks import au_check, summarise

#: AUs named by each scan code (issue 7: "AU12 for LFAU_12, AU1+2+5+26 for E_SURPRISE")
CODE_AUS = {
    "UFAU_1": ["AU1"],
    "UFAU_2": ["AU2"],
    "UFAU_4": ["AU4"],
    "LFAU_9": ["AU9"],
    "LFAU_12": ["AU12"],
    "LFAU_12L": ["AU12"],
    "LFAU_20": ["AU20"],
    "LFAU_26": ["AU26"],
    "E_HAPPY": ["AU6", "AU12"],
    "E_SURPRISE": ["AU1", "AU2", "AU5", "AU26"],
    "N_N": [],
}


def _machine():
    import jax

    return {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "load_avg": list(os.getloadavg()),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [getattr(d, "device_kind", str(d)) for d in jax.devices()],
    }


def _au_ranks(aus: dict, expected: list[str]) -> dict:
    bil = sorted(((k, v) for k, v in aus.items() if k[-1] not in "LR"), key=lambda kv: -kv[1])
    order = [k for k, _ in bil]
    return {a: (order.index(a) + 1 if a in order else None) for a in expected}


def _stats(d):
    return (
        {k: (None if v is None else float(v)) for k, v in d.to_dict().items()}
        if hasattr(d, "to_dict")
        else d
    )


def _b2(truth, subject, r, stem: str, subject_id: str):
    """B2 for one scan (None where it does not apply or no other subject has the code)."""
    from jaxface.fit.baselines import b2_action_unit, baseline_b2
    from jaxface.fit.evaluation import evaluate_against_truth

    au = b2_action_unit(stem)
    if au is None:
        return None
    code = stem[len(subject_id) + 1 :]
    for src in truth.subjects():
        if src != subject_id and f"{src}_{code}" in truth.records:
            t = time.perf_counter()
            b2 = baseline_b2(
                subject.registration,
                r.scan,
                r.alignment,
                truth.scan(truth.neutral_stem(src)),
                truth.scan(f"{src}_{code}"),
                au,
            )
            ev = evaluate_against_truth(b2.mesh, truth, stem)
            return {
                "source": src,
                "au": au,
                "magnitude": b2.magnitude,
                "mean": ev.mean,
                "error": ev.to_dict()["error"],
                "seconds": time.perf_counter() - t,
            }
    return None


def _signed_error_map(truth, stem: str, fitted, mean: float) -> dict:
    """Truth vertices of the evaluation region of ``stem`` (ICT frame, mm) and the signed
    distance to the fitted skin along the truth normal (mm; + = the fit lies in front)."""
    from jaxface.fit.evaluation import evaluation_region
    from jaxface.fit.metrics import SurfaceIndex
    from jaxface.render import vertex_normals

    m = evaluation_region(truth, stem)
    tm = truth.truth_mesh(stem)
    tv = np.asarray(tm.vertices)
    n = vertex_normals(tv, np.asarray(tm.triangles))[m]
    q = SurfaceIndex.from_mesh(fitted).query(tv[m])
    signed = np.sign(np.einsum("kd,kd->k", q.points - tv[m], n)) * q.distances
    xy = truth.ict_frame_vertices(stem)[m][:, :2]
    return {"xy": xy, "signed": signed, "mean": mean}


def error_figure(subjects: list[tuple[str, dict]], path: Path) -> Path:
    """One panel per scan (rows: subjects; columns: codes): the truth vertices of the
    evaluation region seen from the front, coloured by the signed error of the fit (mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    codes = [c for c in CODE_AUS if any(c in maps for _, maps in subjects)]
    fig, axs = plt.subplots(
        len(subjects),
        len(codes),
        figsize=(1.9 * len(codes) + 1.2, 2.4 * len(subjects) + 0.5),
        squeeze=False,
        layout="constrained",
    )
    xy = np.concatenate([e["xy"] for _, maps in subjects for e in maps.values()])
    lo, hi = xy.min(axis=0) - 3.0, xy.max(axis=0) + 3.0  # one scale for every panel
    sc = None
    for row, (sid, maps) in zip(axs, subjects):
        for ax, code in zip(row, codes):
            ax.set_xticks([])
            ax.set_yticks([])
            if code not in maps:
                ax.set_visible(False)
                continue
            e = maps[code]
            sc = ax.scatter(
                e["xy"][:, 0],
                e["xy"][:, 1],
                c=e["signed"],
                cmap="coolwarm",
                vmin=-3,
                vmax=3,
                s=1.0,
                linewidths=0,
                rasterized=True,
            )
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
            ax.set_title(f"{sid} {code}\nmean {e['mean']:.2f} mm", fontsize=8)
    if sc is not None:
        fig.colorbar(sc, ax=axs, shrink=0.8, label="signed error, mm (+ = fit in front)")
    fig.suptitle(
        "Fit error against the truth meshes over each scan's evaluation region (front view)",
        fontsize=10,
    )
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _jacobian_timing(fit, repeats: int = 20) -> dict:
    """ms per Jacobian of one inner solve's data residuals (a scan's final point set), with the
    custom forward-mode rule the fit uses and with plain forward-mode autodiff, side by side."""
    import jax

    from jaxface.fit.residuals import data_vector, data_vector_plain

    pts, y = fit.points, fit.y
    M = pts.free.shape[0]
    a = jax.numpy.full(M, 0.3)
    out = {}
    for label, fn in (("rule", data_vector), ("plain", data_vector_plain)):
        jac = jax.jit(
            jax.jacfwd(lambda a_, j_, r_, p_: fn(a_, j_, r_, p_, True), argnums=(0, 1, 2))
        )
        jax.block_until_ready(jac(a, y.jaw, y.rigid, pts))
        t = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(jac(a, y.jaw, y.rigid, pts))
        out[f"{label}_ms"] = 1e3 * (time.perf_counter() - t) / repeats
    out["plain_over_rule"] = out["plain_ms"] / out["rule_ms"]
    out["n_residuals"] = int(pts.normal.shape[0] + 3 * pts.w_landmark.shape[0])
    return out


def bench_subject(
    truth,
    subject_id: str,
    opt,
    *,
    single: bool,
    subject_options=None,
    b2_baseline: bool = True,
    warm_batch: bool = False,
    truth_as_scan: bool = False,
) -> dict:
    from jaxface.fit.evaluation import ICT_FACE_VERTICES, evaluate_against_truth
    from jaxface.fit.pipeline import fit_expressions, prepare_subject
    from jaxface.io import Scan

    def expression_scan(stem):
        """The scan to fit: the range scan, or (``truth_as_scan``, expressions only) the face
        skin of the exact mesh that was scanned (ICT vertices 0..9408 and the triangles
        among them; the rest of the truth mesh is the head, the eye sockets, the mouth's
        inside and the teeth, which no range scan sees), with the scan's landmarks:
        noise-free and hole-free, so its fit shows what the model itself can reach."""
        sc = truth.scan(stem)
        if not truth_as_scan or truth.records[stem].code == "N_N":
            return sc
        v = truth.truth_vertices(stem)[:ICT_FACE_VERTICES]
        f = np.asarray(truth.truth_mesh(stem).triangles)
        f = f[(f < ICT_FACE_VERTICES).all(axis=1)]
        return Scan(
            points=v, triangles=f, landmarks=sc.landmarks, path=truth.path(stem, ".truth.ply")
        )

    t = time.perf_counter()
    c = time.process_time()
    S = prepare_subject(truth.scan(truth.neutral_stem(subject_id)), options=subject_options)
    build = {
        "wall_s": time.perf_counter() - t,
        "cpu_s": time.process_time() - c,
        **S.timings,
        "n_vertices": int(len(S.forward.rest)),
        "n_controls": S.forward.n_controls,
        "n_fit_vertices": int(len(S.fit_ids)),
    }
    stems = truth.stems(subject_id)
    out = {"subject": subject_id, "build": build, "scans": []}
    timing = {}
    print(f"  built {subject_id} in {build['wall_s']:.1f} s", flush=True)
    if single:
        # one scan alone: cold (compiles the solver for a batch of one) and warm
        for label, code in (("cold", "LFAU_12"), ("warm", "LFAU_26")):
            stem = f"{subject_id}_{code}_0"
            t = time.perf_counter()
            c = time.process_time()
            (r,) = fit_expressions(S, [expression_scan(stem)], options=opt)
            timing[f"single_{label}"] = {
                "scan": stem,
                "wall_s": time.perf_counter() - t,
                "cpu_s": time.process_time() - c,
                "solver_s": r.fit.seconds,
            }
            print(
                f"  single {label} ({stem}): {timing[f'single_{label}']['wall_s']:.1f} s",
                flush=True,
            )
    t = time.perf_counter()
    c = time.process_time()
    res = fit_expressions(S, [expression_scan(s) for s in stems], options=opt, arkit=_ict_file())
    wall = time.perf_counter() - t
    timing["batch"] = {
        "n_scans": len(stems),
        "wall_s": wall,
        "cpu_s": time.process_time() - c,
        "per_scan_s": wall / len(stems),
    }
    print(f"  batch of {len(stems)}: {wall:.1f} s ({wall / len(stems):.2f} s per scan)", flush=True)
    if warm_batch:
        # the same batch again: what a batch costs once its solves are compiled (on an
        # accelerator the first batch compiles the vmapped inner solve for its padded size)
        t = time.perf_counter()
        c = time.process_time()
        fit_expressions(S, [expression_scan(s) for s in stems], options=opt)
        w2 = time.perf_counter() - t
        timing["batch_warm"] = {
            "n_scans": len(stems),
            "wall_s": w2,
            "cpu_s": time.process_time() - c,
            "per_scan_s": w2 / len(stems),
        }
        print(
            f"  batch again (compiled): {w2:.1f} s ({w2 / len(stems):.2f} s per scan)", flush=True
        )
    timing["jacobian"] = _jacobian_timing(res[0].fit)
    out["timing"] = timing
    maps = {}
    for stem, r in zip(stems, res):
        rec = truth.records[stem]
        ev = evaluate_against_truth(r.fitted, truth, stem)
        maps[rec.code] = _signed_error_map(truth, stem, r.fitted, ev.mean)
        b0 = evaluate_against_truth(r.baseline_meshes["B0"], truth, stem)
        b1 = evaluate_against_truth(r.baseline_meshes["B1"], truth, stem)
        exp = CODE_AUS.get(rec.code, [])
        b2 = _b2(truth, S, r, stem, subject_id) if b2_baseline else None
        row = {
            "stem": stem,
            "code": rec.code,
            "n_region": ev.n_region,
            "fit": ev.to_dict()["error"],
            "B0": b0.to_dict()["error"],
            "B1": b1.to_dict()["error"],
            "fit_mean": ev.mean,
            "B0_mean": b0.mean,
            "B1_mean": b1.mean,
            "B2": b2,
            "B2_mean": None if b2 is None else b2["mean"],
            "ratio_B0_over_fit": b0.mean / ev.mean if ev.mean > 0 else None,
            "scan_to_fit_mean": r.metrics.scan_to_fit["all"].mean,
            "status": r.status,
            "steps": r.fit.steps,
            "jaw": r.jaw,
            "rigid_correction": [float(v) for v in r.fit.rigid],
            "jaw_starts": r.fit.starts,
            "au_ranks": _au_ranks(r.au_intensities, exp),
            "top_aus": r.strongest_aus(6, bilateral_only=True),
            "au12_sides": {k: r.au_intensities.get(k) for k in ("AU12L", "AU12R")},
            "au_motion_ranks": _au_ranks(r.au_motion_mm, exp),
            "top_aus_by_motion_mm": r.strongest_aus(6, bilateral_only=True, by="motion"),
            "au12_sides_motion_mm": {k: r.au_motion_mm.get(k) for k in ("AU12L", "AU12R")},
            "au_activation_ranks": _au_ranks(r.au_from_activations, exp),
            "top_aus_from_activations": r.strongest_aus(6, bilateral_only=True, by="activations"),
            "au12_sides_from_activations": {
                k: r.au_from_activations.get(k) for k in ("AU12L", "AU12R")
            },
            "au_readout_misfit_mm": None if r.au_readout is None else r.au_readout.misfit_mm,
            "letters": r.to_dict()["au_intensity_letters"],
            "au_check_intensity": au_check(
                r.au_intensities, [[a] for a in exp], S.response, S.muscle_names
            ),
            "au_check_activations": au_check(
                r.au_from_activations, [[a] for a in exp], S.response, S.muscle_names
            ),
            "activations": r.activations,
            **_arkit_row(r.arkit, rec.weights),
        }
        out["scans"].append(row)
        print(f"  {stem}: fit {ev.mean:.3f} mm, B0 {b0.mean:.3f}, status {r.status}", flush=True)
    if single:
        # the same scans one at a time (warm), after the batch: batch mode's gain per scan
        t = time.perf_counter()
        c = time.process_time()
        for s in stems:
            fit_expressions(S, [expression_scan(s)], options=opt)
        w1 = time.perf_counter() - t
        timing["singles"] = {
            "n_scans": len(stems),
            "wall_s": w1,
            "cpu_s": time.process_time() - c,
            "per_scan_s": w1 / len(stems),
            "singles_over_batch": w1 / wall,
        }
        if warm_batch:
            timing["singles"]["singles_over_warm_batch"] = w1 / timing["batch_warm"]["wall_s"]
        print(
            f"  singles: {w1 / len(stems):.2f} s per scan, singles/batch {w1 / wall:.2f}",
            flush=True,
        )
    out["error_maps"] = maps  # drawn by main(), not written to the JSON
    return out


def round_trip(which: str, opt_kw: dict) -> dict:
    """Synthesise -> scan -> fit back on the default head (or the ICT face)."""
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, synthesize
    from jaxface.fit.conditioning import jacobian_conditioning
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions, fit_expressions, subject_from_rig
    from jaxface.fit.residuals import make_priors
    from jaxface.io.scanner import SkinLandmarks, scan_skin

    t0 = time.perf_counter()
    if which == "default_head":
        from jaxface.head import generic_head

        head = generic_head()
        rig = build_rig(head)
        face_mask = head.face_mask
    else:
        from jaxface.anatomy.ict import load_ict_face
        from jaxface.testing import shared_path

        ict = load_ict_face(
            shared_path("data", "ict", "ict_face.npz"),
            shared_path("data", "bosphorus_style", "truth.json"),
        )
        rig = build_rig(
            ict.skin, ict.landmarks, upper_teeth=ict.upper_teeth, lower_teeth=ict.lower_teeth
        )
        face_mask = None
    bound = SkinLandmarks.of_rig(rig)

    def scan_of(x):
        return scan_skin(x, bound)

    truth_acts = {
        "zygomaticus_major_L": 0.6,
        "zygomaticus_major_R": 0.45,
        "frontalis_medial_L": 0.5,
        "frontalis_medial_R": 0.5,
        "corrugator_R": 0.3,
        "orbicularis_oris": 0.25,
        "depressor_anguli_oris_L": 0.4,
        "levator_labii_superioris_alaeque_nasi_R": 0.35,
    }
    truth_jaw = (6.0, 1.0, 1.0)
    neutral = scan_of(np.asarray(rig.rest))
    a = rig.activations(truth_acts)
    x = np.asarray(synthesize(rig, a, JawPose(*truth_jaw)))
    expr = scan_of(x)
    build_s = time.perf_counter() - t0
    subject = subject_from_rig(rig, neutral, face_mask=face_mask, options=SubjectOptions())
    opt = FitOptions(**opt_kw)
    t = time.perf_counter()
    (res,) = fit_expressions(subject, [expr], options=opt)
    fit_s = time.perf_counter() - t
    names = list(subject.muscle_names)
    pri = make_priors(names, opt)
    cond = jacobian_conditioning(res.fit.y, res.fit.points, pri, names)
    true_of = dict(zip(rig.muscle_names, np.asarray(a)))  # the cheek pressures' truth is 0
    err = {n: float(res.activations[n] - true_of.get(n, 0.0)) for n in names}
    vif = cond["vif"]
    distinguishable = [n for n in names if vif[n] < 10.0 and cond["sensitivity"][n] > 1e-2]
    fm = subject.face_mask
    surf = np.linalg.norm(np.asarray(res.fitted.vertices)[fm] - x[fm], axis=1)
    return {
        "face": which,
        "build_s": build_s,
        "subject_s": subject.timings,
        "fit_s": fit_s,
        "true_activations": truth_acts,
        "true_jaw": truth_jaw,
        "scan_to_fit_mean": res.metrics.scan_to_fit["all"].mean,
        "skin_vertex_error_mm": {
            "mean": float(surf.mean()),
            "median": float(np.median(surf)),
            "p95": float(np.percentile(surf, 95)),
        },
        "jaw_fit": res.jaw,
        "jaw_error": [
            res.jaw["pitch_deg"] - truth_jaw[0],
            res.jaw["yaw_deg"] - truth_jaw[1],
            res.jaw["protrusion_mm"] - truth_jaw[2],
        ],
        "activation_error": err,
        "max_activation_error_distinguishable": max(
            (abs(err[n]) for n in distinguishable), default=None
        ),
        "max_activation_error_all": max(abs(v) for v in err.values()),
        "distinguishable": distinguishable,
        "status": res.status,
        "steps": res.fit.steps,
        "conditioning": cond,
    }


def _ict_file():
    """The shared ICT-FaceKit file for the fits' ARKit readout (None when absent)."""
    from jaxface.errors import DataNotFoundError
    from jaxface.testing import shared_path

    try:
        return shared_path("data", "ict", "ict_face.npz", pytest_skip=False)
    except DataNotFoundError:
        return None


def _arkit_row(arkit, recipe_weights) -> dict:
    """The fit's ARKit readout against the scan's ICT/ARKit recipe: each recipe shape's rank
    among the 52 coefficients, and pass when every rank <= number in the recipe + 2."""
    if arkit is None:
        return {"arkit": None}
    from jaxface.interop.arkit import arkit_weights_from_ict

    want = arkit_weights_from_ict(recipe_weights)
    order = [k for k, _ in sorted(arkit.items(), key=lambda kv: -kv[1])]
    recipe = [k for k, w in want.items() if w > 0]
    ranks = {k: order.index(k) + 1 for k in recipe}
    return {
        "arkit": {k: float(v) for k, v in arkit.items()},
        "arkit_ranks": ranks,
        "arkit_pass": all(v <= len(recipe) + 2 for v in ranks.values()),
        "arkit_mae": float(np.mean([abs(arkit[k] - want[k]) for k in want if k in arkit])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", default="bs900,bs901")
    ap.add_argument("--no-round-trip", action="store_true")
    ap.add_argument(
        "--round-trip-ict", action="store_true", help="also run the round trip on the ICT face"
    )
    ap.add_argument("--no-single", action="store_true", help="skip the single-scan timings")
    ap.add_argument(
        "--warm-batch",
        action="store_true",
        help="fit the batch a second time, compiled (batch_warm, singles_over_warm_batch)",
    )
    ap.add_argument(
        "--truth-as-scan",
        action="store_true",
        help="fit the exact truth meshes instead of the range scans (what the model can reach)",
    )
    ap.add_argument(
        "--no-b2",
        action="store_true",
        help="skip baseline B2 (it needs the other subject's scans of the same code)",
    )
    ap.add_argument(
        "--exact-steps", type=int, default=0, help="final LM steps through the exact rig"
    )
    ap.add_argument(
        "--outer-iterations",
        type=int,
        default=None,
        help="correspondence refreshes (default: FitOptions')",
    )
    ap.add_argument(
        "--restart-iterations",
        type=int,
        default=None,
        help="bound-flip restart iterations (default: FitOptions')",
    )
    ap.add_argument(
        "--restart-when",
        choices=["unconverged", "saturated"],
        default=None,
        help="which fits with activations at 1 restart (default: FitOptions')",
    )
    ap.add_argument(
        "--landmark-weight",
        type=float,
        default=None,
        help="weight of the landmark term (default: FitOptions')",
    )
    ap.add_argument(
        "--motion-fraction",
        type=float,
        default=None,
        help="share of the scan points drawn from the expression's moving region (default: FitOptions')",
    )
    ap.add_argument(
        "--robust-floor",
        default=None,
        metavar="FIRST,LAST",
        help="lower bound of the Tukey cut-off (mm), annealed from FIRST to LAST (default: FitOptions')",
    )
    ap.add_argument(
        "--no-gradient-correction",
        action="store_true",
        help="fit without the exact-gradient correction of the inner solves",
    )
    ap.add_argument(
        "--sweeps",
        default=None,
        help="the rig's quasi-static sweeps, MUSCLE/SKIN[/RHO] or a preset of jaxface synth "
        "--sweeps (default: build_rig's 32/8)",
    )
    ap.add_argument(
        "--muscle-map",
        default=None,
        help="muscle-map JSON for the subjects' rigs (default: the packaged map)",
    )
    ap.add_argument(
        "--no-cheek-puff",
        action="store_true",
        help="fit the muscles and the jaw only (SubjectOptions.cheek_puff=False)",
    )
    ap.add_argument(
        "--rig-option",
        action="append",
        default=[],
        metavar="NAME=JSON",
        help="a build_rig option of the subjects' rigs, e.g. jaw_protrusion_limits_mm=[-2,10] "
        "(repeatable)",
    )
    ap.add_argument("--pitch-knots", type=int, default=None, help="SubjectOptions.pitch_knots")
    ap.add_argument(
        "--results",
        default=None,
        help="folder of the JSON and the picture (default benchmarks/results)",
    )
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxface.fit.evaluation import load_truth
    from jaxface.fit.options import FitOptions

    truth = load_truth()
    kw = dict(exact_steps=args.exact_steps, gradient_correction=not args.no_gradient_correction)
    if args.outer_iterations is not None:
        kw["outer_iterations"] = args.outer_iterations
    if args.restart_iterations is not None:
        kw["restart_iterations"] = args.restart_iterations
    if args.restart_when is not None:
        kw["restart_when"] = args.restart_when
    if args.landmark_weight is not None:
        kw["landmark_weight"] = args.landmark_weight
    if args.motion_fraction is not None:
        kw["motion_fraction"] = args.motion_fraction
    if args.robust_floor is not None:
        try:
            floor = tuple(float(v) for v in args.robust_floor.split(","))
        except ValueError:
            floor = ()
        if len(floor) != 2:
            ap.error(f"--robust-floor takes two numbers FIRST,LAST (mm), got {args.robust_floor!r}")
        kw["robust_floor_mm"] = floor
    opt = FitOptions(**kw)
    from jaxface.fit.pipeline import SubjectOptions

    rig_kwargs = {}
    if args.sweeps:
        from jaxface.commands.synth import parse_sweeps
        from jaxface.errors import RigError

        try:
            m, k, rho = parse_sweeps(args.sweeps)
        except RigError as e:
            ap.error(str(e))
        rig_kwargs = dict(muscle_iterations=m, skin_iterations=k, skin_chebyshev_rho=rho)
    if args.muscle_map:
        rig_kwargs["muscle_map"] = args.muscle_map
    for item in args.rig_option:
        name, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--rig-option wants NAME=JSON, got {item!r}")
        v = json.loads(value)
        rig_kwargs[name.strip()] = tuple(v) if isinstance(v, list) else v
    knots = {} if args.pitch_knots is None else {"pitch_knots": args.pitch_knots}
    subject_options = SubjectOptions(
        rig_kwargs=rig_kwargs, cheek_puff=not args.no_cheek_puff, **knots
    )
    report = {
        "machine": _machine(),
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in opt.__dict__.items()},
        "rig_kwargs": rig_kwargs,
        "pitch_knots": args.pitch_knots,
        "cheek_puff": not args.no_cheek_puff,
        "subjects": [],
    }
    error_maps = []
    for sid in [s for s in args.subjects.split(",") if s]:
        print(f"== subject {sid}", flush=True)
        r = bench_subject(
            truth,
            sid,
            opt,
            single=not args.no_single,
            subject_options=subject_options,
            b2_baseline=not args.no_b2,
            warm_batch=args.warm_batch,
            truth_as_scan=args.truth_as_scan,
        )
        error_maps.append((sid, r.pop("error_maps")))
        report["subjects"].append(r)
        print(
            f"build {r['build']['wall_s']:.1f} s (register {r['build']['register_s']:.1f}, rig "
            f"{r['build']['rig_s']:.1f}, compile {r['build']['compile_s']:.1f}, reduced model "
            f"{r['build']['response_s']:.1f})"
        )
        for k, v in r["timing"].items():
            print(
                f"  time {k}: "
                + ", ".join(
                    f"{a}={b:.2f}" if isinstance(b, float) else f"{a}={b}" for a, b in v.items()
                )
            )
        print(
            f"{'scan':22s} {'fit':>6s} {'B0':>6s} {'B1':>6s} {'B2':>6s} {'B0/fit':>6s} {'scan':>5s}  status        "
            f"{'pitch':>5s}  AU ranks / top AUs"
        )
        for s in r["scans"]:
            b2s = "     -" if s["B2_mean"] is None else f"{s['B2_mean']:6.3f}"
            print(
                f"{s['stem']:22s} {s['fit_mean']:6.3f} {s['B0_mean']:6.3f} {s['B1_mean']:6.3f} {b2s} "
                f"{(s['ratio_B0_over_fit'] or 0):6.2f} {s['scan_to_fit_mean']:5.2f}  {s['status'][:13]:13s} "
                f"{s['jaw']['pitch_deg']:5.1f}  {s['au_ranks']} {[(k, round(v, 2)) for k, v in s['top_aus'][:4]]}"
                + (
                    f" 12L/12R {s['au12_sides']['AU12L']:.2f}/{s['au12_sides']['AU12R']:.2f}"
                    if s["code"] == "LFAU_12L"
                    else ""
                )
            )
            print(
                f"{'':22s} by skin motion: {s['au_motion_ranks']} "
                f"{[(k, round(v, 2)) for k, v in s['top_aus_by_motion_mm'][:4]]} mm"
                + (
                    f" 12L/12R {s['au12_sides_motion_mm']['AU12L']:.2f}/{s['au12_sides_motion_mm']['AU12R']:.2f} mm"
                    if s["code"] == "LFAU_12L"
                    else ""
                )
            )
            print(
                f"{'':22s} from the activations: {s['au_activation_ranks']} "
                f"{[(k, round(v, 2)) for k, v in s['top_aus_from_activations'][:4]]}"
                + (
                    f" 12L/12R {s['au12_sides_from_activations']['AU12L']:.2f}/"
                    f"{s['au12_sides_from_activations']['AU12R']:.2f}"
                    if s["code"] == "LFAU_12L"
                    else ""
                )
            )
        ex = [s for s in r["scans"] if s["code"] != "N_N"]
        print(
            f"  mean over expressions: fit {np.mean([s['fit_mean'] for s in ex]):.3f}  B0 "
            f"{np.mean([s['B0_mean'] for s in ex]):.3f}  B1 {np.mean([s['B1_mean'] for s in ex]):.3f}",
            flush=True,
        )
    allex = [s for r in report["subjects"] for s in r["scans"] if s["code"] != "N_N"]
    if allex:
        report["summary"] = {
            "mean_fit": float(np.mean([s["fit_mean"] for s in allex])),
            "mean_B0": float(np.mean([s["B0_mean"] for s in allex])),
            "mean_B1": float(np.mean([s["B1_mean"] for s in allex])),
            "B2_scans": {
                s["stem"]: {"fit": s["fit_mean"], "B2": s["B2_mean"]}
                for s in allex
                if s["B2_mean"] is not None
            },
            "mean_fit_on_B2_scans": float(
                np.mean([s["fit_mean"] for s in allex if s["B2_mean"] is not None] or [np.nan])
            ),
            "mean_B2": float(
                np.mean([s["B2_mean"] for s in allex if s["B2_mean"] is not None] or [np.nan])
            ),
            "n_fit_le_1mm": int(sum(s["fit_mean"] <= 1.0 for s in allex)),
            "n_2x_better_than_B0": int(sum((s["ratio_B0_over_fit"] or 0) >= 2.0 for s in allex)),
            "n_expressions": len(allex),
            "arkit_pass": int(sum(bool(s.get("arkit_pass")) for s in allex)),
            "arkit_mean_mae": float(
                np.mean([s["arkit_mae"] for s in allex if "arkit_mae" in s] or [np.nan])
            ),
            "arkit_failures": {
                s["stem"]: s["arkit_ranks"] for s in allex if s.get("arkit_pass") is False
            },
            **{
                f"au_{how}": summarise(
                    [s[f"au_check_{how}"] for s in allex],
                    [len(CODE_AUS.get(s["code"], [])) == 1 for s in allex],
                )
                for how in ("intensity", "activations")
            },
            "neutral_registration_mm": {
                s["stem"]: s["B0_mean"]
                for r in report["subjects"]
                for s in r["scans"]
                if s["code"] == "N_N"
            },
        }
        print("summary:", json.dumps(report["summary"]))
    if not args.no_round_trip:
        faces = ["default_head"] + (["ict"] if args.round_trip_ict else [])
        report["round_trip"] = []
        for face in faces:
            print(f"== round trip on {face}", flush=True)
            rt = round_trip(face, kw)
            report["round_trip"].append(rt)
            print(
                f"scan->fit {rt['scan_to_fit_mean']:.4f} mm, skin error median {rt['skin_vertex_error_mm']['median']:.4f} "
                f"mm, jaw error {np.round(rt['jaw_error'], 3).tolist()}, max activation error (distinguishable) "
                f"{rt['max_activation_error_distinguishable']}, all {rt['max_activation_error_all']:.3f}, status "
                f"{rt['status']}, fit {rt['fit_s']:.1f} s"
            )
            c = rt["conditioning"]
            for g in ("activations", "jaw", "rigid", "all"):
                sv = np.asarray(c["singular_values"][g])
                print(
                    f"  singular values {g}: max {sv[0]:.3g} min {sv[-1]:.3g} cond {c['condition'][g]:.3g}"
                )
            worst = sorted(c["vif"].items(), key=lambda kv: -kv[1])[:8]
            print("  least distinguishable (VIF):", [(k, round(v, 1)) for k, v in worst])
    out = Path(args.results) if args.results else Path(__file__).resolve().parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    from jaxface.fit.pipeline import _jsonable

    (out / "bench_fit.json").write_text(json.dumps(_jsonable(report), indent=1))
    print(f"wrote {out / 'bench_fit.json'}")
    if error_maps:
        print(f"wrote {error_figure(error_maps, out / 'bench_fit_errors.png')}")


if __name__ == "__main__":
    main()
