"""The expressive-range benchmark (issue 44): every one of the 57 ICT-FaceKit expressions,
fitted on the ICT face and on other identities of its identity model.

Run from the repository root (needs ``ict_face.npz`` and ``truth.json`` of the shared data:
``JAXFACE_SHARED`` or ``../shared``)::

    python benchmarks/bench_ict57.py [--identities 0,1,2] [--scan exact|virtual|both]
                                     [--expressions NAME,...] [--batch 8] [--results DIR]
                                     [--muscle-map PATH | --range-variant] [--tag NAME]
                                     [--no-cheek-puff]

``--muscle-map`` builds the subjects' rigs from another muscle map, ``--range-variant`` from
the default map with :data:`jaxface.anatomy.muscle_map.RANGE_EDITS` (the pursing orbicularis
oris and the longer frontalis of ``docs/design/anatomy.md``); ``--tag`` names the results file
(``bench_ict57[_TAG].json``).

For each identity ``k`` (0: the generic ICT face; ``k > 0``: identity weights
``w ~ N(0, 1)`` drawn with seed ``k`` over the 10 identity modes) the neutral is the ICT face
region (vertices 0..9408) of ``neutral + sum_i w_i mode_i``, with the 22 Bosphorus landmarks
at their ICT vertices (``truth.json``). The subject is built from that neutral
(:func:`jaxface.fit.pipeline.prepare_subject`: the default head registered into it, its rig,
the reduced model), then each expression ``e`` is fitted
(:func:`jaxface.fit.pipeline.fit_expressions`) from

* ``exact``: the expression's own surface, ``neutral_k + delta_e`` (noise-free, hole-free);
* ``virtual``: a virtual Bosphorus-style range scan of it (:func:`jaxface.io.scanner.scan_mesh`,
  1 mm grid, 80 degree grazing cut-off), with the landmarks carried by the skin.

``mouthClose`` is a corrective shape (lips closed over an open jaw): alone it would push the
lips 42 mm through each other, so it is fitted as ``jawOpen + mouthClose``. The pupil shapes
(``PupilDilate_L/R``) move no skin and are listed, not fitted.

Measures, per expression (mm, degrees):

* the moving region: face vertices that the expression moves by more than 1 mm (and, for
  virtual scans, that the scan sees, :func:`jaxface.fit.evaluation.scan_coverage`);
* ``fit``: mean distance from the region's true vertices to the fitted skin; ``B0``: the same
  to the neutral (no motion) placed in the scan frame; ``ratio = B0 / fit``;
* the same over the *modelled* part of the region (``fit_modelled_mm``, ``B0_modelled_mm``,
  ``ratio_modelled``): the vertices whose neutral position lies within ``MODELLED_MM`` (2 mm)
  of the subject's registered neutral skin. The ICT face region reaches places the template
  has no skin for (the neck below its lower edge, the insides of the nostrils, parts of the
  ears; about 17 % of the face vertices on identity 1), where the fitted skin is 3-30 mm away
  whatever the motion while B0, the scan's own neutral, is exact; the modelled columns
  measure the motion where the model has a surface, the plain ones include that gap;
* the solver status, the jaw pose, the three strongest AUs of the fit's readout
  (``au_intensities``, :func:`jaxface.fit.au_motion.read_aus`) and of the table's inverse of the
  activations (``au_from_activations``), the coded AUs' intensities and FACS letters;
* the readout checks of ``au_checks.py`` for both readouts: the coded AUs within the top
  (number coded + 1), single-AU shapes with more than 2 bilateral AUs at >= 0.99, and AUs at
  >= 0.5 whose removal moves the skin less than 0.05 mm.

Summary per identity and scan kind: the mean fit error over all fitted expressions, how many
are within 1 mm, and how many at least 2x better than B0 (the issue's targets: mean <= 0.5 mm,
each <= 1.0 mm and >= 2x B0). The same three over the modelled regions. Prints a table and writes
``benchmarks/results/bench_ict57.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import warnings
from pathlib import Path

import numpy as np

from au_checks import au_check, summarise
from jaxface.anatomy.muscle_map import RANGE_EDITS, load_muscle_map
from jaxface.closest import SurfaceIndex
from jaxface.fit.evaluation import ICT_FACE_VERTICES, load_truth, scan_coverage
from jaxface.fit.options import FitOptions
from jaxface.fit.pipeline import SubjectOptions, fit_expressions, prepare_subject
from jaxface.io import Scan
from jaxface.io.scanner import scan_mesh
from jaxface.landmarks import Landmarks
from jaxface.testing import shared_path

MOVING_MM = 1.0  # a vertex is in an expression's moving region when it moves more than this
#: a truth vertex is "modelled" when the subject's registered neutral skin passes within this
#: distance of its neutral position (mm); the rest (the nostrils' insides, the neck below the
#: template's edge) has no model surface to fit
MODELLED_MM = 2.0
NO_SKIN = ("PupilDilate_L", "PupilDilate_R")  # shapes that move no skin: listed, not fitted
CORRECTIVE = {"mouthClose": ("jawOpen",)}  # fitted together with these shapes at weight 1


def load_ict():
    """The ICT arrays and the face region's triangles (ids < 9409)."""
    d = np.load(shared_path("data", "ict", "ict_face.npz"))
    tris = np.asarray(d["triangles"], np.int64)
    face_tris = tris[(tris < ICT_FACE_VERTICES).all(axis=1)]
    return {
        "neutral": np.asarray(d["neutral"], np.float64),
        "names": [str(n) for n in d["expression_names"]],
        "deltas": np.asarray(d["expression_deltas"], np.float64),
        "modes": np.asarray(d["identity_deltas"], np.float64),
        "face_tris": face_tris,
    }


def identity_neutral(ict, k: int) -> np.ndarray:
    """``(21451, 3)`` mm: identity 0 is the generic face; ``k > 0`` draws ``w ~ N(0, 1)``."""
    if k == 0:
        return ict["neutral"].copy()
    w = np.random.default_rng(k).standard_normal(len(ict["modes"]))
    return ict["neutral"] + np.einsum("m,mvd->vd", w, ict["modes"])


def expression_vertices(ict, base, name: str) -> np.ndarray:
    """``(21451, 3)`` mm: the expression on the identity (with its corrective partners)."""
    idx = {n: i for i, n in enumerate(ict["names"])}
    v = base + ict["deltas"][idx[name]]
    for other in CORRECTIVE.get(name, ()):
        v = v + ict["deltas"][idx[other]]
    return v


def make_scan(v, ict, lm_ids, kind: str, path: str) -> Scan:
    """The face region of ``v`` as a mesh scan (``exact``) or a virtual range scan."""
    face = v[:ICT_FACE_VERTICES]
    names = list(lm_ids)
    lm = Landmarks(names, face[[lm_ids[n] for n in names]])
    if kind == "exact":
        return Scan(points=face, triangles=ict["face_tris"], landmarks=lm, path=path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return scan_mesh((face, ict["face_tris"]), 1.0, landmarks=lm, max_angle_deg=80.0, path=path)


#: The FACS action units each ICT-FaceKit (ARKit-named) shape codes, by the shapes' published
#: descriptions: a tuple of groups, each a tuple of alternatives (``jawOpen`` is AU26 or, at its
#: full 42 mm, AU27; ``mouthClose`` is fitted over ``jawOpen``). Sides are read from the bilateral AU. Shapes with no AU in the model's set
#: (gaze, ``mouthLeft``/``mouthRight``, ``mouthShrugUpper``) are not coded.
CODED_AUS: dict[str, tuple[tuple[str, ...], ...]] = {
    "browDown": (("AU4",),),
    "browInnerUp": (("AU1",),),
    "browOuterUp": (("AU2",),),
    "cheekPuff": (("AU33", "AU34"),),
    "cheekRaiser": (("AU6",),),
    "cheekSquint": (("AU6",),),
    "eyeBlink": (("AU43", "AU45", "AU46"),),
    "eyeSquint": (("AU7",),),
    "eyeWide": (("AU5",),),
    "jawForward": (("AU29",),),
    "jawLeft": (("AU30",),),
    "jawRight": (("AU30",),),
    "jawOpen": (("AU26", "AU27"),),
    "mouthClose": (("AU26", "AU27"), ("AU23", "AU24")),  # lips closed over the open jaw
    "mouthDimple": (("AU14",),),
    "mouthFrown": (("AU15",),),
    "mouthFunnel": (("AU22",),),
    "mouthLowerDown": (("AU16",),),
    "mouthPress": (("AU24",),),
    "mouthPucker": (("AU18",),),
    "mouthRollLower": (("AU28",),),
    "mouthRollUpper": (("AU28",),),
    "mouthShrugLower": (("AU17",),),
    "mouthSmile": (("AU12",),),
    "mouthStretch": (("AU20",),),
    "mouthUpperUp": (("AU10",),),
    "noseSneer": (("AU9",),),
}


def coded_aus(expression: str) -> tuple[tuple[str, ...], ...]:
    """The coded AU groups of an ICT shape (its side suffix dropped); ``()`` when uncoded."""
    base = expression[:-2] if expression[-2:] in ("_L", "_R") else expression
    return CODED_AUS.get(base, ())


def run_identity(
    ict, lm_ids, k: int, kinds, expressions, batch: int, options, subject_options=None
) -> dict:
    base = identity_neutral(ict, k)
    t = time.perf_counter()
    neutral = make_scan(base, ict, lm_ids, "exact", f"ict{k}_neutral")
    subject = prepare_subject(neutral, options=subject_options)
    build_s = time.perf_counter() - t
    print(f"identity {k}: subject built in {build_s:.1f} s", flush=True)
    reg_skin = SurfaceIndex(subject.registration.vertices, np.asarray(subject.rig.triangles))
    modelled = reg_skin.query(base[:ICT_FACE_VERTICES]).distances <= MODELLED_MM
    print(
        f"  modelled: {modelled.mean():.1%} of the face vertices lie within {MODELLED_MM} mm "
        "of the registered neutral skin",
        flush=True,
    )
    out = {
        "identity": k,
        "build_s": build_s,
        "modelled_fraction": float(modelled.mean()),
        "kinds": {},
    }
    for kind in kinds:
        rows = []
        truths, scans = [], []
        for name in expressions:
            v = expression_vertices(ict, base, name)
            truths.append(v[:ICT_FACE_VERTICES])
            scans.append(make_scan(v, ict, lm_ids, kind, f"ict{k}_{name}_{kind}"))
        t = time.perf_counter()
        fits = []
        for s in range(0, len(scans), batch):
            fits += fit_expressions(subject, scans[s : s + batch], options=options, arkit=None)
            print(f"  {kind}: {len(fits)}/{len(scans)} fitted", flush=True)
        fit_s = time.perf_counter() - t
        for name, v, sc, r in zip(expressions, truths, scans, fits):
            moved = np.linalg.norm(v - base[:ICT_FACE_VERTICES], axis=1) > MOVING_MM
            ids = np.flatnonzero(moved)
            if kind == "virtual" and len(ids):
                ids = ids[scan_coverage(v[ids], sc)]
            pts = v[ids]
            fit_d = SurfaceIndex.from_mesh(r.fitted).query(pts).distances
            b0_d = SurfaceIndex.from_mesh(r.baseline_meshes["B0"]).query(pts).distances
            fit_mm, b0_mm = float(fit_d.mean()), float(b0_d.mean())
            inside = modelled[ids]
            fit_in = float(fit_d[inside].mean()) if inside.any() else float("nan")
            b0_in = float(b0_d[inside].mean()) if inside.any() else float("nan")
            top = r.strongest_aus(3, bilateral_only=True)
            top_act = r.strongest_aus(3, bilateral_only=True, by="activations")
            groups = coded_aus(name)
            coded = [max(g, key=lambda a: r.au_intensities.get(a, 0.0)) for g in groups]
            rows.append(
                {
                    "expression": name,
                    "n_region": int(len(ids)),
                    "fit_mm": fit_mm,
                    "fit_max_mm": float(fit_d.max()),
                    "B0_mm": b0_mm,
                    "ratio_B0_over_fit": b0_mm / fit_mm if fit_mm > 0 else None,
                    "n_region_modelled": int(inside.sum()),
                    "fit_modelled_mm": fit_in,
                    "B0_modelled_mm": b0_in,
                    "ratio_modelled": b0_in / fit_in if fit_in > 0 else None,
                    "status": r.status,
                    "jaw": r.jaw,
                    "activations": r.activations,
                    "top_aus": [[a, round(float(x), 3)] for a, x in top],
                    "top_aus_from_activations": [[a, round(float(x), 3)] for a, x in top_act],
                    "coded_aus": [list(g) for g in groups],
                    "coded_intensity": {a: round(r.au_intensities.get(a, 0.0), 3) for a in coded},
                    "letters": r.to_dict()["au_intensity_letters"],
                    "readout_misfit_mm": r.au_readout.misfit_mm if r.au_readout else None,
                    "au_check_intensity": au_check(
                        r.au_intensities, groups, subject.response, subject.muscle_names
                    ),
                    "au_check_activations": au_check(
                        r.au_from_activations, groups, subject.response, subject.muscle_names
                    ),
                }
            )
        out["kinds"][kind] = {"fit_s_per_scan": fit_s / max(len(scans), 1), "rows": rows}
    return out


def summary(rows) -> dict:
    f = np.array([r["fit_mm"] for r in rows])
    ratio = np.array([r["ratio_B0_over_fit"] or 0.0 for r in rows])
    fm = np.array([r["fit_modelled_mm"] for r in rows])
    rm = np.array([r["ratio_modelled"] or 0.0 for r in rows])
    return {
        "n": len(rows),
        "mean_fit_mm": float(f.mean()),
        "mean_B0_mm": float(np.mean([r["B0_mm"] for r in rows])),
        "n_within_1mm": int((f <= 1.0).sum()),
        "n_2x_B0": int((ratio >= 2.0).sum()),
        "worse_than_B0": [r["expression"] for r in rows if (r["ratio_B0_over_fit"] or 0) < 1.0],
        "modelled": {
            "mean_fit_mm": float(np.mean(fm)),
            "mean_B0_mm": float(np.mean([r["B0_modelled_mm"] for r in rows])),
            "n_within_1mm": int((fm <= 1.0).sum()),
            "n_2x_B0": int((rm >= 2.0).sum()),
            "worse_than_B0": [r["expression"] for r in rows if (r["ratio_modelled"] or 0) < 1.0],
        },
        **{
            f"au_{how}": summarise(
                [r[f"au_check_{how}"] for r in rows], [len(r["coded_aus"]) == 1 for r in rows]
            )
            for how in ("intensity", "activations")
        },
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--identities", default="0,1,2")
    p.add_argument("--scan", choices=("exact", "virtual", "both"), default="both")
    p.add_argument("--expressions", default="", help="comma-separated subset (default: all)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--results", default=str(Path(__file__).parent / "results"))
    p.add_argument("--muscle-map", default=None, help="muscle-map JSON for the rigs")
    p.add_argument("--range-variant", action="store_true", help="the map with RANGE_EDITS")
    p.add_argument("--tag", default="", help="results file bench_ict57_TAG.json")
    p.add_argument(
        "--rig-option",
        action="append",
        default=[],
        metavar="NAME=JSON",
        help="a build_rig option for the rigs, e.g. jaw_pitch_limits_deg=[-4,28] (repeatable)",
    )
    p.add_argument("--pitch-knots", type=int, default=None, help="SubjectOptions.pitch_knots")
    p.add_argument(
        "--no-cheek-puff",
        action="store_true",
        help="fit the muscles and the jaw only (SubjectOptions.cheek_puff=False)",
    )
    a = p.parse_args(argv)
    ict = load_ict()
    lm_ids = load_truth().landmark_vertex_ids
    exprs = [n for n in ict["names"] if n not in NO_SKIN]
    if a.expressions:
        want = [s.strip() for s in a.expressions.split(",") if s.strip()]
        bad = [w for w in want if w not in exprs]
        if bad:
            raise SystemExit(f"unknown expressions {bad}; have {exprs}")
        exprs = want
    kinds = ("exact", "virtual") if a.scan == "both" else (a.scan,)
    ids = [int(s) for s in a.identities.split(",") if s.strip()]
    results = {
        "machine": platform.platform(),
        "excepted_no_skin": list(NO_SKIN),
        "corrective": {k: list(v) for k, v in CORRECTIVE.items()},
        "moving_threshold_mm": MOVING_MM,
        "muscle_map": "range variant" if a.range_variant else (a.muscle_map or "default"),
        "identities": [],
    }
    rig_kwargs: dict = {}
    for item in a.rig_option:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--rig-option wants NAME=JSON, got {item!r}")
        v = json.loads(value)
        rig_kwargs[name.strip()] = tuple(v) if isinstance(v, list) else v
    if a.range_variant:
        rig_kwargs["muscle_map"] = load_muscle_map(edits=RANGE_EDITS)
    elif a.muscle_map:
        rig_kwargs["muscle_map"] = a.muscle_map
    sk: dict = {"rig_kwargs": rig_kwargs} if rig_kwargs else {}
    if a.pitch_knots is not None:
        sk["pitch_knots"] = a.pitch_knots
    if a.no_cheek_puff:
        sk["cheek_puff"] = False
    sopt = SubjectOptions(**sk) if sk else None
    results["rig_options"] = {k: v for k, v in rig_kwargs.items() if k != "muscle_map"}
    results["pitch_knots"] = a.pitch_knots
    results["cheek_puff"] = not a.no_cheek_puff
    opt = FitOptions()
    for k in ids:
        res = run_identity(ict, lm_ids, k, kinds, exprs, a.batch, opt, sopt)
        for kind, blk in res["kinds"].items():
            blk["summary"] = summary(blk["rows"])
            print(f"\nidentity {k}, {kind} surfaces ({blk['fit_s_per_scan']:.1f} s per fit)")
            print(
                f"{'expression':18s} {'fit':>6s} {'B0':>6s} {'B0/fit':>6s} {'fit_m':>6s} "
                f"{'B0_m':>6s} {'ratio':>6s} {'jaw':>6s}  top AUs  (_m: the modelled region)"
            )
            for r in blk["rows"]:
                print(
                    f"{r['expression']:18s} {r['fit_mm']:6.2f} {r['B0_mm']:6.2f} "
                    f"{(r['ratio_B0_over_fit'] or 0):6.2f} {r['fit_modelled_mm']:6.2f} "
                    f"{r['B0_modelled_mm']:6.2f} {(r['ratio_modelled'] or 0):6.2f} "
                    f"{r['jaw']['pitch_deg']:6.1f}  "
                    + " ".join(f"{n}={x:.2f}" for n, x in r["top_aus"])
                )
            s = blk["summary"]
            print(
                f"mean fit {s['mean_fit_mm']:.3f} mm (B0 {s['mean_B0_mm']:.3f}); "
                f"{s['n_within_1mm']}/{s['n']} within 1 mm; {s['n_2x_B0']}/{s['n']} at 2x B0; "
                f"worse than B0: {s['worse_than_B0']}",
                flush=True,
            )
            m = s["modelled"]
            print(
                f"modelled region: mean fit {m['mean_fit_mm']:.3f} mm (B0 {m['mean_B0_mm']:.3f}); "
                f"{m['n_within_1mm']}/{s['n']} within 1 mm; {m['n_2x_B0']}/{s['n']} at 2x B0; "
                f"worse than B0: {m['worse_than_B0']}",
                flush=True,
            )
            for how in ("intensity", "activations"):
                c = s["au_" + how]
                print(
                    f"AU readout ({'au_intensities' if how == 'intensity' else 'au_from_activations'}): "
                    f"coded AUs within the top (n coded + 1) {c['n_coded_rank_ok']}/{c['n_coded']}; "
                    f"single-AU shapes with > 2 bilateral AUs at >= 0.99: "
                    f"{c['n_single_over_2_saturated']}/{c['n_single']}; AUs at >= 0.5 whose removal "
                    f"moves the skin < 0.05 mm: {c['n_idle_strong']} (on {c['n_with_idle_strong']} fits)",
                    flush=True,
                )
        results["identities"].append(res)
        out = Path(a.results)
        out.mkdir(parents=True, exist_ok=True)
        name = f"bench_ict57{'_' + a.tag if a.tag else ''}.json"
        tmp = out / (name + ".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(out / name)


if __name__ == "__main__":
    main()
