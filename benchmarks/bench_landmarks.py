"""Benchmark: automatic landmarks (:mod:`jaxface.detect`) against the truth ``.lm3`` of the
shared Bosphorus-style scans, per label.

Run from the repository root::

    JAXFACE_SHARED=../shared python benchmarks/bench_landmarks.py [--stems bs900_N_N_0 ...]
    JAXFACE_SHARED=../shared python benchmarks/bench_landmarks.py --fit [--stems ...]

Default mode, per scan: detection on the scan as stored, and on the scan rotated by
(pitch, yaw) = (+20, +30) and (-20, -30) degrees with two extra holes (every triangle within
12 mm of two random face points removed). Errors are distances (mm) detected -> truth over
the labels both have; a truth label the detector leaves out counts as "missed". Prints a
per-label table (mean / max error, missed count) for the upright and the rotated+holes sets,
the overall mean / max and the wall time per detection, and writes
``benchmarks/results/bench_landmarks.json``. Timings are wall-clock on whatever machine runs
it (say which, and how loaded, when you quote them).

``--fit``: per subject, ``jaxface fit`` (quick settings) of each expression scan with the
truth landmarks and with detected ones (neutral and scans), side by side: scan -> fit mean
error (mm) and the three strongest AUs. Expensive (two fits per subject).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from jaxface.detect import detect_landmarks
from jaxface.fit.align import rotation_from_euler
from jaxface.io import load_scan
from jaxface.landmarks import FACE_LABELS
from jaxface.testing import shared_path

POSES = {"upright": (0.0, 0.0), "rot+20+30_holes": (20.0, 30.0), "rot-20-30_holes": (-20.0, -30.0)}


def _holes(v, f, truth, rng):
    """Remove the triangles within 12 mm of two random truth-near face points."""
    names = [n for n in truth.names if n in FACE_LABELS]
    keep = np.ones(len(f), bool)
    cen = v[f].mean(axis=1)
    for n in rng.choice(names, 2, replace=False):
        c = truth[n] + rng.normal(0, 10.0, 3)
        keep &= np.linalg.norm(cen - c, axis=1) > 12.0
    return f[keep]


def bench_detection(stems, root: Path) -> dict:
    rng = np.random.default_rng(0)
    per: dict[str, dict[str, list]] = {k: {} for k in POSES}
    missed: dict[str, dict[str, int]] = {k: {} for k in POSES}
    times = []
    rows = []
    for stem in stems:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scan = load_scan(root / f"{stem}.bnt")
        v, f, _ = scan.mesh_arrays()
        v, f = np.asarray(v), np.asarray(f)
        truth = scan.landmarks
        assert truth is not None, f"{stem}: no truth .lm3"
        for pose, (pitch, yaw) in POSES.items():
            R = rotation_from_euler(pitch, yaw)
            ff = f if pose == "upright" else _holes(v, f, truth, rng)
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    det = detect_landmarks((v @ R.T, ff))
                except Exception as e:  # noqa: BLE001 - a benchmark reports failures
                    rows.append({"stem": stem, "pose": pose, "error": repr(e)})
                    print(f"{stem:22s} {pose:18s} FAILED {e}")
                    continue
            dt = time.perf_counter() - t0
            times.append(dt)
            err = {}
            for n in truth.names:
                if n in det.landmarks:
                    err[n] = float(np.linalg.norm(det.landmarks[n] - R @ truth[n]))
                    per[pose].setdefault(n, []).append(err[n])
                else:
                    missed[pose][n] = missed[pose].get(n, 0) + 1
            e = list(err.values())
            rows.append(
                {
                    "stem": stem,
                    "pose": pose,
                    "seconds": dt,
                    "errors_mm": err,
                    "omitted": det.omitted,
                    "jaw_opening_deg": det.jaw_opening_deg,
                }
            )
            print(
                f"{stem:22s} {pose:18s} {dt:5.1f} s  jaw {det.jaw_opening_deg:4.1f}  mean "
                f"{np.mean(e):5.2f}  max {np.max(e):5.2f} mm  missed {[n for n in truth.names if n not in det.landmarks]}"
            )
    summary = {}
    for pose in POSES:
        allv = [x for xs in per[pose].values() for x in xs]
        summary[pose] = {
            "mean_mm": float(np.mean(allv)) if allv else None,
            "max_mm": float(np.max(allv)) if allv else None,
            "per_label": {
                n: {
                    "mean_mm": float(np.mean(per[pose][n])),
                    "max_mm": float(np.max(per[pose][n])),
                    "n": len(per[pose][n]),
                    "missed": missed[pose].get(n, 0),
                }
                for n in FACE_LABELS
                if n in per[pose]
            },
        }
    print(f"\n{'label':24s}" + "".join(f"{p:>28s}" for p in POSES))
    for n in FACE_LABELS:
        cells = []
        for pose in POSES:
            d = summary[pose]["per_label"].get(n)
            cells.append(
                f"{d['mean_mm']:7.2f} /{d['max_mm']:6.2f} miss {d['missed']:2d}" if d else " " * 28
            )
        print(f"{n:24s}" + "".join(f"{c:>28s}" for c in cells))
    for pose in POSES:
        s = summary[pose]
        print(f"{pose:18s} mean {s['mean_mm']:.2f} mm, max {s['max_mm']:.2f} mm")
    print(f"time per detection: median {np.median(times):.2f} s, max {np.max(times):.2f} s")
    return {"summary": summary, "rows": rows, "seconds_median": float(np.median(times))}


def bench_fit(stems, root: Path) -> dict:
    from jaxface.commands.fit import run_fit
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions

    opts = FitOptions(n_points=600, outer_iterations=3, max_steps=20)
    sopts = SubjectOptions(levels=2, pitch_knots=6)
    out = []
    for subject in sorted({s.split("_")[0] for s in stems}):
        scans = [root / f"{s}.bnt" for s in stems if s.startswith(subject) and "_N_N_" not in s]
        neutral = root / f"{subject}_N_N_0.bnt"
        res = {}
        for mode in ("file", "auto"):
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                fits = run_fit(
                    neutral,
                    scans,
                    Path(tmp),
                    options=opts,
                    subject_options=sopts,
                    landmarks=mode,
                    notice=lambda s: None,
                )
                res[mode] = {
                    r.stem: {
                        "scan_to_fit_mean_mm": float(r.metrics.scan_to_fit["all"].mean),
                        "top_aus": [k for k, _ in r.strongest_aus(3, bilateral_only=True)],
                    }
                    for r in fits
                }
                print(f"{subject} {mode}: {time.perf_counter() - t0:.0f} s")
        for stem in res["file"]:
            a, b = res["file"][stem], res["auto"][stem]
            ratio = b["scan_to_fit_mean_mm"] / a["scan_to_fit_mean_mm"]
            print(
                f"{stem:22s} truth lm {a['scan_to_fit_mean_mm']:.3f} mm {a['top_aus']}  |  "
                f"detected {b['scan_to_fit_mean_mm']:.3f} mm {b['top_aus']}  ratio {ratio:.2f}"
            )
            out.append({"stem": stem, "truth": a, "detected": b, "ratio": ratio})
    return {"fit": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--stems", nargs="*", default=None, help="scan stems (default: all)")
    ap.add_argument("--fit", action="store_true", help="fit with truth vs detected landmarks")
    args = ap.parse_args()
    root = shared_path("data", "bosphorus_style", pytest_skip=False)
    stems = args.stems or sorted(p.name[: -len(".bnt")] for p in root.glob("*.bnt"))
    result = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "load_avg_at_start": os.getloadavg(),
        "stems": stems,
    }
    result.update(bench_fit(stems, root) if args.fit else bench_detection(stems, root))
    dest = Path(__file__).parent / "results"
    dest.mkdir(exist_ok=True)
    name = "bench_landmarks_fit.json" if args.fit else "bench_landmarks.json"
    (dest / name).write_text(json.dumps(result, indent=1))
    print(f"wrote {dest / name}")


if __name__ == "__main__":
    main()
