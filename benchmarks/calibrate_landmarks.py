"""Calibrate the detector's landmark definitions (``src/jaxface/data/landmark_definitions.json``)
on ICT-FaceKit identities, and measure them on held-out ICT identities.

Run from the repository root::

    JAXFACE_SHARED=../shared python benchmarks/calibrate_landmarks.py [--identities 11-34]
        [--write] [--check 1-4]

Calibration faces: a virtual Bosphorus-style range scan (:func:`jaxface.io.scanner.scan_mesh`,
1 mm) of the neutral of each ICT identity ``k`` (identity modes ``w ~ N(0, 1)`` drawn with seed
``k``, as in ``bench_ict57.py``), labelled by the ICT vertex of each Bosphorus label
(``truth.json``'s ``landmark_vertex_ids_ict``: the convention of the Bosphorus-style data).
The identities are disjoint from those of the shared scans (the generic face and one other
draw) and from the ``--check`` identities.

``--check``: detection on held-out identities (default 1-4), each neutral and eight
expressions of all face regions (virtual scans with ``--noise`` mm of depth noise, default
0.1), with the definitions being calibrated and with the head's own
definitions, side by side (mean detected-to-truth distance per label, mm). ``--write`` stores
the calibration in the package. Writes ``benchmarks/results/calibrate_landmarks.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from bench_ict57 import expression_vertices, identity_neutral, load_ict
from jaxface.detect import detect_landmarks
from jaxface.detect.calibrate import calibrate_definitions
from jaxface.detect.definitions import CALIBRATED_LABELS, _default_path, save_definitions
from jaxface.detect.transfer import build_face_template
from jaxface.fit.evaluation import ICT_FACE_VERTICES, load_truth
from jaxface.io.scanner import scan_mesh
from jaxface.landmarks import FACE_LABELS, Landmarks

#: held-out check: the neutral (None) and shapes over the brows, eyes, cheeks, nose and mouth
CHECK_EXPRESSIONS = (
    None,
    "browInnerUp_L",
    "eyeSquint_L",
    "eyeBlink_R",
    "noseSneer_L",
    "mouthSmile_L",
    "mouthPucker",
    "mouthFunnel",
    "jawOpen",
)


def _ids(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def _scan(ict, lm_ids, v, noise_mm: float = 0.0, seed: int = 0):
    """A virtual 1 mm range scan of the face region of ``v`` (depth noise ``noise_mm``) and
    the true landmarks: ``(vertices, triangles, Landmarks)``, mm."""
    face = v[:ICT_FACE_VERTICES]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = scan_mesh(
            (face, ict["face_tris"]), 1.0, max_angle_deg=80.0, noise_mm=noise_mm, seed=seed
        )
    pts, tri, _ = s.mesh_arrays()
    names = list(lm_ids)
    return np.asarray(pts), np.asarray(tri), Landmarks(names, face[[lm_ids[n] for n in names]])


def check(ict, lm_ids, identities, templates, noise_mm: float) -> dict:
    """Detection errors (mm) per label on the held-out faces, for each template."""
    errs: dict[str, dict[str, list[float]]] = {k: {} for k in templates}
    for k in identities:
        base = identity_neutral(ict, k)
        for e in CHECK_EXPRESSIONS:
            v = base if e is None else expression_vertices(ict, base, e)
            pts, tri, truth = _scan(ict, lm_ids, v, noise_mm, seed=k)
            for name, tpl in templates.items():
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    det = detect_landmarks((pts, tri), template=tpl)
                for n in det.landmarks.names:
                    if n in truth:
                        d = float(np.linalg.norm(det.landmarks[n] - truth[n]))
                        errs[name].setdefault(n, []).append(d)
            print(f"  check: identity {k} {e or 'neutral'}", flush=True)
    return errs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--identities", default="11-34", help="calibration identities (default 11-34)")
    ap.add_argument("--check", default="1-4", help="held-out identities ('' to skip)")
    ap.add_argument("--noise", type=float, default=0.1, help="check scans' depth noise, mm")
    ap.add_argument("--write", action="store_true", help="store the result in the package")
    a = ap.parse_args(argv)
    ict = load_ict()
    lm_ids = load_truth().landmark_vertex_ids
    cal = _ids(a.identities)
    held = _ids(a.check) if a.check else []
    if set(cal) & set(held):
        sys.exit("the calibration and check identities overlap")
    t0 = time.perf_counter()

    def faces():
        for k in cal:
            yield _scan(ict, lm_ids, identity_neutral(ict, k))

    defs = calibrate_definitions(
        faces(),
        source=(
            f"virtual 1 mm range scans of the neutral of ICT-FaceKit identities {a.identities} "
            f"(identity modes w ~ N(0, 1), seed = identity); labels = the ICT vertices of "
            f"truth.json; python benchmarks/calibrate_landmarks.py --identities {a.identities}"
        ),
        progress=lambda i: print(f"  calibrated on {i}/{len(cal)} faces", flush=True),
    )
    print(f"calibration: {len(cal)} faces in {time.perf_counter() - t0:.0f} s")
    own = build_face_template(None)
    for n in CALIBRATED_LABELS:
        if n in defs.points:
            shift = np.linalg.norm(defs.points[n] - own.landmarks[n])
            print(f"{n:24s} point moved {shift:5.2f} mm  spread {defs.spread_mm[n]:5.2f} mm")
    for n, o in defs.offsets_mm.items():
        print(f"{n:24s} offset {np.round(o, 2)} mm  spread {defs.spread_mm[n]:5.2f} mm")
    out: dict = {"calibration": defs.to_dict()}
    if held:
        errs = check(
            ict,
            lm_ids,
            held,
            {"head": own, "calibrated": build_face_template(defs)},
            a.noise,
        )
        print(f"\n{'label':24s} {'head':>8s} {'calibrated':>11s}   (mean mm, held-out identities)")
        table = {}
        for n in FACE_LABELS:
            if n in errs["head"] and n in errs["calibrated"]:
                h, c = np.mean(errs["head"][n]), np.mean(errs["calibrated"][n])
                table[n] = {"head": float(h), "calibrated": float(c)}
                print(f"{n:24s} {h:8.2f} {c:11.2f}")
        means = {k: float(np.mean([x for xs in errs[k].values() for x in xs])) for k in errs}
        print(f"{'all':24s} {means['head']:8.2f} {means['calibrated']:11.2f}")
        out["check"] = {
            "identities": held,
            "noise_mm": a.noise,
            "per_label": table,
            "mean_mm": means,
        }
    if a.write:
        print(f"wrote {save_definitions(defs, Path(str(_default_path())))}")
    res = Path(__file__).parent / "results"
    res.mkdir(exist_ok=True)
    (res / "calibrate_landmarks.json").write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
