"""The ``jaxface demo`` showcase on the embedded default head: forward and inverse in one run.

:func:`run_showcase` (units mm, degrees; frame +y up, face along +z, subject's left +x):

1. builds the default head and writes it (``head.ply``, ``head.lm3``, teeth, eyes, ``head.png``);
2. builds its rig (estimated skull, jaw, default muscle map), draws the muscle map
   (``muscle_map.png``) and the jaw model (``jaw.png``), and synthesises the six emotion
   presets (``emotions.png``, ``emotion_<name>.png``) and single action units (``aus.png``);
3. makes Bosphorus-style range scans (``.bnt`` + ``.lm3``, 1 mm grid, virtual scanner) of the
   neutral and of a few synthetic expressions with known activations and jaw pose;
4. fits them back with the inverse solver (:func:`jaxface.fit.pipeline.fit_expressions`) and
   writes per scan ``<stem>.json``, ``<stem>.fitted.ply`` and the before/after panel
   ``<stem>.fit.png`` (scan, neutral, fit, fit-to-scan distance in mm);
5. writes ``report.json`` (everything measured) and ``report.md`` (a short readable summary
   with the pictures linked).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .anatomy.jaw import JawPose
from .anatomy.pictures import (
    emotion_pictures,
    expression_sheet,
    jaw_diagram,
    muscle_map_picture,
)
from .anatomy.rig import build_rig, synthesize
from .atomic import write_json_atomic, write_text_atomic
from .fit.options import FitOptions
from .fit.pipeline import SubjectOptions, fit_expressions, subject_from_rig
from .head import generic_head, save_head
from .io.bosphorus import write_bnt
from .io.scanner import SkinLandmarks, scan_skin
from .landmarks import write_lm3

__all__ = ["SYNTHETIC_SCANS", "run_showcase"]

#: synthetic expression scans the demo makes and fits back: name -> (activations, jaw pose)
SYNTHETIC_SCANS: dict[str, tuple[dict[str, float], tuple[float, float, float]]] = {
    "demo_E_HAPPY_0": (
        {
            "zygomaticus_major_L": 0.7,
            "zygomaticus_major_R": 0.7,
            "orbicularis_oculi_L": 0.3,
            "orbicularis_oculi_R": 0.3,
        },
        (2.0, 0.0, 0.0),
    ),
    "demo_E_SURPRISE_0": (
        {
            "frontalis_medial_L": 0.7,
            "frontalis_medial_R": 0.7,
            "frontalis_lateral_L": 0.5,
            "frontalis_lateral_R": 0.5,
        },
        (9.0, 0.0, 0.0),
    ),
    "demo_LFAU_12L_0": ({"zygomaticus_major_L": 0.6}, (0.0, 0.0, 0.0)),
}


def run_showcase(
    out, *, fit: bool = True, panel_px: int = 600, progress: Callable[[str], None] | None = None
) -> dict:
    """Run the showcase into folder ``out``; returns the report dict (also ``report.json``).

    Args:
        out: output folder (created).
        fit: also scan and fit back the synthetic expressions (steps 3-4; the slow part).
        panel_px: size of the head picture panels, pixels.
        progress: called with a short text before each step.
    """
    import jax

    say = progress or (lambda s: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    report: dict = {
        "units": "mm",
        "frame": "+y up, face looks along +z, subject's left is +x",
        "files": {},
    }

    def timed(key, fn, *a, **kw):
        t = time.perf_counter()
        r = fn(*a, **kw)
        timings[key] = time.perf_counter() - t
        return r

    say("building the default head")
    head = timed("head_s", generic_head)
    files = save_head(head, out, picture=True, panel_px=panel_px)
    report["files"].update({k: Path(v).name for k, v in files.items()})
    report["head"] = {
        "vertices": head.mesh.n_vertices,
        "triangles": head.mesh.n_triangles,
        "landmarks": len(head.landmarks.names),
    }

    say("building the rig (skull, jaw, muscle map, skin binding)")
    rig = timed("rig_s", build_rig, head)
    report["rig"] = {"controls": list(rig.muscle_names), "n_controls": rig.n_controls}

    say("drawing the muscle map and the jaw model")
    report["files"]["muscle_map"] = timed(
        "muscle_map_s", muscle_map_picture, out / "muscle_map.png", rig
    ).name
    report["files"]["jaw"] = timed("jaw_s", jaw_diagram, out / "jaw.png", rig).name

    say("synthesising and rendering the six emotions")
    paths = timed("emotions_s", emotion_pictures, rig, out, head=head)
    report["files"]["emotions"] = [p.name for p in paths]
    say("synthesising and rendering single action units")
    aus = ["AU1", "AU2", "AU4", "AU6", "AU9", "AU10", "AU12", "AU15", "AU20", "AU26"]
    p = timed(
        "aus_s",
        expression_sheet,
        out / "aus.png",
        rig,
        [(a, {a: 1.0}) for a in aus],
        views=("front",),
        ncol=5,
        title="single action units (intensity 1)",
        head=head,
    )
    report["files"]["aus"] = p.name

    if fit:
        report["fits"] = _scan_and_fit(rig, head, out, say, timings)
    timings["total_s"] = time.perf_counter() - t_all
    report["timings"] = timings
    report["machine"] = {"jax": jax.__version__, "backend": jax.default_backend()}
    write_json_atomic(out / "report.json", report)
    write_text_atomic(out / "report.md", _markdown(report))
    return report


def _scan_and_fit(rig, head, out: Path, say, timings) -> list[dict]:
    scans_dir = out / "scans"
    fits_dir = out / "fits"
    scans_dir.mkdir(exist_ok=True)
    bound = SkinLandmarks.of_rig(rig)

    def scan_of(x, stem):
        s = scan_skin(x, bound, path=f"{stem}.bnt")
        write_bnt(scans_dir / f"{stem}.bnt", s)
        assert s.landmarks is not None  # scan_skin carries the landmarks
        write_lm3(scans_dir / f"{stem}.lm3", s.landmarks)
        return s

    say("making Bosphorus-style scans of synthetic expressions")
    t = time.perf_counter()
    neutral = scan_of(np.asarray(rig.rest), "demo_N_N_0")
    truths, scans = {}, []
    for stem, (acts, jaw) in SYNTHETIC_SCANS.items():
        a = rig.activations(acts)
        x = np.asarray(synthesize(rig, a, JawPose(*jaw)))
        truths[stem] = (np.asarray(a), jaw, x)
        scans.append(scan_of(x, stem))
    timings["scans_s"] = time.perf_counter() - t

    say("preparing the fit (reduced model of the rig)")
    t = time.perf_counter()
    subject = subject_from_rig(
        rig, neutral, face_mask=head.face_mask, options=SubjectOptions(levels=3, pitch_knots=8)
    )
    timings["subject_s"] = time.perf_counter() - t
    say(f"fitting {len(scans)} scans back (one batch)")
    t = time.perf_counter()
    results = fit_expressions(subject, scans, options=FitOptions(n_points=1000))
    timings["fit_s"] = time.perf_counter() - t
    rows = []
    names = list(subject.muscle_names)  # the rig's muscles, then the two cheek pressures
    fm = subject.face_mask
    for r in results:
        files = r.write(fits_dir, pictures=True)
        a_rig, jaw_true, x_true = truths[r.stem]
        truth = dict(zip(subject.rig.muscle_names, a_rig))  # no puff in the demo's scans
        a_true = np.array([truth.get(n, 0.0) for n in names])
        err = np.linalg.norm(np.asarray(r.fitted.vertices)[fm] - x_true[fm], axis=1)
        a_fit = np.array([r.activations[n] for n in names])
        big = [n for n, v in zip(names, a_true) if v > 0]
        rows.append(
            {
                "stem": r.stem,
                "status": r.status,
                "scan_to_fit_mean_mm": r.metrics.scan_to_fit["all"].mean,
                "skin_error_mm": {"mean": float(err.mean()), "max": float(err.max())},
                "jaw_true": dict(zip(("pitch_deg", "yaw_deg", "protrusion_mm"), jaw_true)),
                "jaw_fit": r.jaw,
                "activations_true": {n: float(v) for n, v in zip(names, a_true) if v > 0},
                "activations_fit": {n: r.activations[n] for n in big},
                "max_activation_error": float(np.abs(a_fit - a_true).max()),
                "strongest_aus": r.strongest_aus(4, sided=True),
                "most_visible_aus_mm": r.strongest_aus(4, by="motion", sided=True),
                "aus_from_activations": r.strongest_aus(4, by="activations", sided=True),
                "files": {k: str(Path(v).relative_to(out)) for k, v in files.items()},
            }
        )
    return rows


def _markdown(rep: dict) -> str:
    L = [
        "# jaxface demo report",
        "",
        f"Default head: {rep['head']['vertices']} vertices, {rep['head']['landmarks']} landmarks; "
        f"rig with {rep['rig']['n_controls']} muscle controls. Units: mm, degrees. Frame: {rep['frame']}.",
        "",
        "## Anatomy: muscle map and jaw",
        "",
        "![muscle map](muscle_map.png)",
        "",
        "![jaw](jaw.png)",
        "",
        "## Forward: emotions and action units",
        "",
        "![emotions](emotions.png)",
        "",
        "![aus](aus.png)",
        "",
    ]
    if rep.get("fits"):
        L += [
            "## Inverse: synthetic Bosphorus-style scans fitted back",
            "",
            "| scan | status | scan -> fit (mm) | skin error mean / max (mm) | jaw pitch true / fit (deg) | "
            "max activation error | AUs (intensity) | most visible AUs (mm) | AUs from the activations |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for f in rep["fits"]:
            aus = ", ".join(f"{k} {v:.2f}" for k, v in f["strongest_aus"])
            vis = ", ".join(f"{k} {v:.2f}" for k, v in f["most_visible_aus_mm"])
            spa = ", ".join(f"{k} {v:.2f}" for k, v in f["aus_from_activations"])
            L.append(
                f"| {f['stem']} | {f['status']} | {f['scan_to_fit_mean_mm']:.3f} | "
                f"{f['skin_error_mm']['mean']:.3f} / {f['skin_error_mm']['max']:.2f} | "
                f"{f['jaw_true']['pitch_deg']:.1f} / {f['jaw_fit']['pitch_deg']:.2f} | "
                f"{f['max_activation_error']:.3f} | {aus} | {vis} | {spa} |"
            )
        L.append("")
        for f in rep["fits"]:
            if "picture" in f["files"]:
                L += [f"![{f['stem']}]({f['files']['picture']})", ""]
    t = rep["timings"]
    L += ["## Timings (s)", "", ", ".join(f"{k[:-2]} {v:.1f}" for k, v in t.items()), ""]
    return "\n".join(L)
