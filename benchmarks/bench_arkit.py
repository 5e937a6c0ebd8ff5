"""ARKit readout on the shared Bosphorus-style scans against their ICT/ARKit recipes.

Per subject (``bs900``, ``bs901``): the default head is registered to the neutral scan
(:func:`jaxface.fit.register.register_template`, as ``jaxface fit`` does), the ICT ARKit
shapes are cloned onto it (:func:`jaxface.interop.arkit.transfer_ict_basis`); per expression
scan: rigid alignment to the neutral (:func:`jaxface.fit.align.align_scans`) and the ARKit
coefficients read straight from the scan (:func:`jaxface.interop.arkit.fit_arkit_to_scan`).
(``--source scan``: no rig fit, which the 2-core CPU cannot afford for 20 scans; the
coefficients of ``jaxface fit`` read the fitted skin motion with the same basis and solver.)

Every subject is an ICT identity, so the true transfer is known: each registered vertex's
closest point on the subject's true neutral (the truth mesh, 0.01-0.03 mm median away)
carries the ICT shapes' own displacement, rotated by the scan's rigid motion. The benchmark reports each cloned shape's RMS error
against it, relative to the shape's RMS (``transfer error``).

Reported per scan: the recipe's ARKit shapes, their ranks among the recovered coefficients
(pass: every rank <= number in recipe + 2), the mean absolute coefficient error over the 51
ICT-backed shapes, the residual (mm) and the seconds.

    JAXFACE_SHARED=/work/shared PYTHONPATH=src python benchmarks/bench_arkit.py [--subjects bs900]
        [--codes LFAU_12L,E_HAPPY] [--iterations 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

from jaxface.anatomy.ict import FACE_VERTEX_COUNT
from jaxface.fit.align import align_scans
from jaxface.fit.evaluation import load_truth
from jaxface.fit.register import register_template
from jaxface.interop.arkit import (
    ARKIT_NAMES,
    arkit_weights_from_ict,
    eye_rim_motion,
    fit_arkit_to_scan,
    ict_transfer_error,
    landmark_motion,
    transfer_ict_basis,
)
from jaxface.io import load_scan
from jaxface.testing import shared_path


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--subjects", default="bs900,bs901")
    ap.add_argument("--codes", default="", help="comma-separated codes (default: all)")
    ap.add_argument("--iterations", type=int, default=3, help="clone refinement iterations")
    ap.add_argument("--l1", type=float, default=0.01)
    ap.add_argument("--json", default="")
    ap.add_argument(
        "--no-rims", action="store_true", help="leave the eye-rim term out (eye_rim_motion)"
    )
    args = ap.parse_args()
    root = shared_path("data", "bosphorus_style", pytest_skip=False)
    truth = load_truth(root)
    codes = [c for c in args.codes.split(",") if c]
    rows = []
    for subj in args.subjects.split(","):
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            neutral = load_scan(root / f"{subj}_N_N_0.bnt")
        reg = register_template(neutral)
        t_reg = time.perf_counter() - t
        tris = np.asarray(reg.mesh.triangles)
        basis = transfer_ict_basis(
            reg.vertices, tris, reg.landmarks, reg.face_mask, max_iterations=args.iterations
        )
        print(
            f"{subj}: registration {t_reg:.1f} s, basis {basis.info['seconds']:.1f} s "
            f"({basis.info['iterations']} refinement iterations)",
            flush=True,
        )
        # every subject is an ICT identity: its true neutral (the first 9409 vertices of the
        # truth mesh, ICT face topology, in the scan frame) carries the ICT shapes exactly
        rigid = truth.records[f"{subj}_N_N_0"].rigid
        te = ict_transfer_error(
            basis,
            reg.vertices,
            basis.source,
            truth_neutral=truth.truth_vertices(f"{subj}_N_N_0")[:FACE_VERTEX_COUNT],
            rotation=rigid.rotation,
        )
        if te:
            worst = sorted(te.items(), key=lambda kv: -kv[1])[:6]
            print(
                f"  transfer error vs the ICT shapes: median {100 * np.median(list(te.values())):.0f} %"
                f" over {len(te)}; eyeWide {100 * te['eyeWideLeft']:.0f}/{100 * te['eyeWideRight']:.0f} %,"
                f" jawOpen {100 * te['jawOpen']:.0f} %, mouthSmile {100 * te['mouthSmileLeft']:.0f}/"
                f"{100 * te['mouthSmileRight']:.0f} %, cheekSquint {100 * te['cheekSquintLeft']:.0f}/"
                f"{100 * te['cheekSquintRight']:.0f} %; worst: "
                + ", ".join(f"{k} {100 * v:.0f}" for k, v in worst),
                flush=True,
            )
            rows.append(dict(stem=f"{subj}_transfer", transfer_error=te))
        for stem, rec in sorted(truth.records.items()):
            if rec.subject != subj or (codes and rec.code not in codes):
                continue
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scan = load_scan(root / f"{stem}.bnt")
            al = align_scans(scan, neutral)
            v, tr, _ = scan.mesh_arrays()
            sol = fit_arkit_to_scan(
                basis,
                reg.vertices,
                tris,
                al.transform.apply(v),
                tr,
                landmarks=landmark_motion(reg, neutral, scan, al.transform),
                rims=None
                if args.no_rims
                else eye_rim_motion(
                    reg.vertices, tris, neutral, scan, al.transform, mask=reg.face_mask
                ),
                l1=args.l1,
            )
            secs = time.perf_counter() - t
            want = arkit_weights_from_ict(rec.weights)
            recipe = [k for k, w in want.items() if w > 0]
            order = [k for k, _ in sol.strongest(len(ARKIT_NAMES))]
            ranks = {k: order.index(k) + 1 for k in recipe}
            ok = all(r <= len(recipe) + 2 for r in ranks.values())
            avail = [k for k in ARKIT_NAMES if k not in sol.unavailable]
            mae = float(np.mean([abs(sol.coefficients[k] - want[k]) for k in avail]))
            top = ", ".join(f"{k} {v:.2f}" for k, v in sol.strongest(4))
            print(
                f"  {stem:22s} ranks {ranks} {'PASS' if ok else 'FAIL'}  MAE {mae:.3f}  "
                f"residual {sol.residual_mm:.2f} mm  {secs:.1f} s  top: {top}",
                flush=True,
            )
            rows.append(
                dict(
                    stem=stem,
                    recipe=recipe,
                    ranks=ranks,
                    passed=ok,
                    mae=mae,
                    residual_mm=sol.residual_mm,
                    seconds=secs,
                    coefficients=sol.coefficients,
                )
            )
    scans = [r for r in rows if "passed" in r]
    n_pass = sum(r["passed"] for r in scans)
    print(
        f"{n_pass}/{len(scans)} scans rank their recipe within the top (n + 2); mean MAE "
        f"{np.mean([r['mae'] for r in scans]):.3f}"
    )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
