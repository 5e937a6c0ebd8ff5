"""Benchmark of the scan-side fitter: template registration and rigid alignment (mm, s).

Run from the repository root (needs the shared data, ``JAXFACE_SHARED`` or ``../shared``)::

    python benchmarks/bench_register.py [--repeat N] [--baselines]

Measures, on the Bosphorus-style scans of ``shared/data/bosphorus_style``:

* registration of the default head and of the ICT neutral to the bs900 and bs901 neutral
  scans: wall and CPU seconds, residual to the scan, and mean error against the neutral
  ``.truth.ply`` where the scan has data (the issue-7 number, <= 0.3 mm required);
* alignment of every expression scan to its subject's neutral: seconds, and the rotation
  (deg) / translation (mm, at the origin) / mean displacement (mm, over the face) errors
  against the motions recorded in ``truth.json``;
* with ``--baselines``: B0 and B1 mean errors over the evaluation region of every
  expression scan (default-head registration, estimated alignment).

Prints tables and writes ``benchmarks/results/bench_register.json``.
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


def _timed(fn, repeat):
    best_wall, best_cpu, out = np.inf, np.inf, None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        best_wall = min(best_wall, time.perf_counter() - w)
        best_cpu = min(best_cpu, time.process_time() - c)
    return out, best_wall, best_cpu


def _rot_err(T, T_true, pts):
    dR = T.rotation @ T_true.rotation.T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    dt = float(np.linalg.norm(T.translation - T_true.translation))
    disp = float(np.linalg.norm(T.apply(pts) - T_true.apply(pts), axis=1).mean())
    return ang, dt, disp


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=1, help="repetitions per timing (best is kept)")
    ap.add_argument("--baselines", action="store_true", help="also compute the B0/B1 table")
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    from jaxface.fit.align import align_scans
    from jaxface.fit.baselines import baseline_b0, baseline_b1
    from jaxface.fit.evaluation import evaluate_against_truth, ict_template, load_truth
    from jaxface.fit.register import Template, register_template
    from jaxface.head import generic_head
    from jaxface.testing import shared_path

    ts = load_truth(shared_path("data", "bosphorus_style", pytest_skip=False))
    head = Template.from_head(generic_head())
    ict = ict_template(truth=ts)
    templates = {
        "default_head": head,
        "ict_neutral": Template(ict.mesh, ict.landmarks, ict.face_mask, "ict_neutral"),
    }

    results: dict = {
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_avg": os.getloadavg(),
        },
        "registration": [],
        "alignment": [],
        "baselines": [],
    }
    regs = {}
    print("registration (template -> neutral scan)")
    print(
        f"{'template':14s} {'scan':12s} {'wall s':>7s} {'cpu s':>7s} {'V':>6s} {'resid mm':>9s} {'truth mean':>10s} {'p95':>6s}"
    )
    for subj in ts.subjects():
        ns = ts.neutral_stem(subj)
        scan = ts.scan(ns)
        idx = ts.scan_index(ns)
        for name, tpl in templates.items():
            reg, wall, cpu = _timed(
                lambda: register_template(scan, template=tpl, scan_index=idx), args.repeat
            )
            ev = evaluate_against_truth(reg.mesh, ts, ns)
            if name == "default_head":
                regs[subj] = reg
            row = {
                "template": name,
                "scan": ns,
                "wall_s": wall,
                "cpu_s": cpu,
                "n_vertices": int(len(reg.residuals)),
                "n_solves": len(reg.history),
                "residual_mean_mm": reg.stats().mean,
                "truth_mm": ev.error["all"].to_dict(),
                "truth_n": ev.n_region,
            }
            results["registration"].append(row)
            print(
                f"{name:14s} {ns:12s} {wall:7.2f} {cpu:7.2f} {row['n_vertices']:6d} {row['residual_mean_mm']:9.3f} "
                f"{ev.mean:10.3f} {ev.error['all'].p95:6.3f}"
            )

    print("\nalignment (expression scan -> neutral scan), errors vs truth.json")
    print(
        f"{'scan':22s} {'wall s':>7s} {'cpu s':>7s} {'rot deg':>8s} {'t mm':>7s} {'disp mm':>8s} {'(landmarks only: deg, mm)':>26s}"
    )
    for subj in ts.subjects():
        ns = ts.neutral_stem(subj)
        fixed_idx = ts.scan_index(ns)
        for stem in ts.stems(subj):
            if stem == ns:
                continue
            scan = ts.scan(stem)
            al, wall, cpu = _timed(
                lambda: align_scans(scan, ts.scan(ns), fixed_index=fixed_idx), args.repeat
            )
            T_true = ts.relative_transform(stem, ns)
            face = ts.truth_vertices(stem)[:9409]
            ang, dt, disp = _rot_err(al.transform, T_true, face)
            ang0, dt0, disp0 = _rot_err(al.landmark_transform, T_true, face)
            results["alignment"].append(
                {
                    "scan": stem,
                    "wall_s": wall,
                    "cpu_s": cpu,
                    "rot_err_deg": ang,
                    "trans_err_mm": dt,
                    "mean_disp_err_mm": disp,
                    "landmark_only": {
                        "rot_err_deg": ang0,
                        "trans_err_mm": dt0,
                        "mean_disp_err_mm": disp0,
                    },
                    "converged": al.converged,
                }
            )
            print(
                f"{stem:22s} {wall:7.2f} {cpu:7.2f} {ang:8.3f} {dt:7.3f} {disp:8.3f}   ({ang0:.3f}, {dt0:.3f})"
            )
            if args.baselines:
                reg = regs[subj]
                e0 = evaluate_against_truth(baseline_b0(reg, al), ts, stem)
                e1 = evaluate_against_truth(baseline_b1(reg, scan.landmarks, al), ts, stem)
                results["baselines"].append(
                    {"scan": stem, "n_region": e0.n_region, "B0": e0.to_dict(), "B1": e1.to_dict()}
                )

    if args.baselines:
        print(
            "\nbaselines (default head registration, estimated alignment): mean error over the evaluation region, mm"
        )
        print(f"{'scan':22s} {'n':>6s} {'B0':>7s} {'B1':>7s}")
        for r in results["baselines"]:
            print(
                f"{r['scan']:22s} {r['n_region']:6d} {r['B0']['error']['all']['mean']:7.3f} {r['B1']['error']['all']['mean']:7.3f}"
            )
        b0 = np.mean([r["B0"]["error"]["all"]["mean"] for r in results["baselines"]])
        b1 = np.mean([r["B1"]["error"]["all"]["mean"] for r in results["baselines"]])
        print(f"{'average':22s} {'':6s} {b0:7.3f} {b1:7.3f}")

    out = Path(__file__).resolve().parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_register.json").write_text(json.dumps(results, indent=1))
    print(f"\nwrote {out / 'bench_register.json'}")


if __name__ == "__main__":
    main()
