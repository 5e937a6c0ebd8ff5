"""Benchmark: the inverse fit through the Lee-Terzopoulos-Waters backend (issue 6 + 7).

Run from the repository root (no shared data needed)::

    python benchmarks/bench_fit_ltw.py [--quick]

Synthetic round trip on the default head with ``build_rig(head, backend="ltw")``: a known
activation vector (two zygomatici, two medial frontalis) and jaw pitch 5 degrees are
synthesised by the LTW layered-tissue model, scanned by the virtual scanner (1 mm grid) and
fitted back (:func:`jaxface.fit.pipeline.subject_from_rig`, :func:`fit_expressions`) with
those four controls free, exactly as ``jaxface fit --backend ltw`` fits. Reports the rig
build, reduced-model build and fit times (s), the scan match (mm), the jaw and activation
errors, and the solver status. Writes ``benchmarks/results/bench_fit_ltw.json``. (Too slow
for the test suite on 2 CPU cores: every outer iteration runs exact LTW syntheses.)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

CONTROLS = (
    "zygomaticus_major_L",
    "zygomaticus_major_R",
    "frontalis_medial_L",
    "frontalis_medial_R",
)
TRUE = {
    "zygomaticus_major_L": 0.6,
    "zygomaticus_major_R": 0.3,
    "frontalis_medial_L": 0.5,
    "frontalis_medial_R": 0.5,
}
TRUE_PITCH = 5.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--quick", action="store_true", help="fewer reduced-model knots and outer iterations"
    )
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, synthesize
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions, fit_expressions, subject_from_rig
    from jaxface.head import generic_head
    from jaxface.io.scanner import SkinLandmarks, scan_skin

    rep = {}
    t = time.perf_counter()
    head = generic_head()
    rig = build_rig(head, backend="ltw")
    rep["rig_build_s"] = time.perf_counter() - t
    bound = SkinLandmarks.of_rig(rig)

    def scan_of(x):
        return scan_skin(x, bound)

    t = time.perf_counter()
    x = np.asarray(synthesize(rig, rig.activations(TRUE), JawPose(TRUE_PITCH)))
    rep["synthesis_with_compile_s"] = time.perf_counter() - t
    neutral, expr = scan_of(np.asarray(rig.rest)), scan_of(x)
    t = time.perf_counter()
    levels, knots, outer = (1, 3, 3) if args.quick else (2, 5, 4)
    S = subject_from_rig(
        rig,
        neutral,
        face_mask=head.face_mask,
        options=SubjectOptions(levels=levels, pitch_knots=knots, controls=CONTROLS),
    )
    rep["subject_s"] = time.perf_counter() - t
    t = time.perf_counter()
    (res,) = fit_expressions(
        S,
        [expr],
        options=FitOptions(
            n_points=800, outer_iterations=outer, max_steps=20, jaw_starts=(0.0,), controls=CONTROLS
        ),
    )
    rep["fit_s"] = time.perf_counter() - t
    rep.update(
        {
            "backend": S.backend,
            "status": res.status,
            "scan_to_fit_mean_mm": res.metrics.scan_to_fit["all"].mean,
            "jaw_fit": res.jaw,
            "jaw_pitch_error_deg": res.jaw["pitch_deg"] - TRUE_PITCH,
            "activation_error": {n: res.activations[n] - TRUE[n] for n in CONTROLS},
            "skin_error_mean_mm": float(
                np.linalg.norm(np.asarray(res.fitted.vertices) - x, axis=1)[head.face_mask].mean()
            ),
        }
    )
    for k, v in rep.items():
        print(f"{k:28s} {v}")
    out = Path(__file__).resolve().parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_fit_ltw.json").write_text(json.dumps(rep, indent=1, default=float))


if __name__ == "__main__":
    main()
