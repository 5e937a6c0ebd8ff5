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

``--fit``: per subject, ``jaxface fit`` (quick settings) of each expression scan once per
``--pairs NEUTRAL:SCANS`` of landmark sources (``truth`` or ``detected``; default the truth
landmarks, then detected ones for the neutral and the scans; ``--detected-landmark-weight``
sets :attr:`jaxface.fit.options.FitOptions.detected_landmark_weight`), side by side: the mean error of
the fitted skin against the scan's truth mesh (:func:`jaxface.fit.evaluation.evaluate_against_truth`,
mm), the scan -> fit mean distance (mm) and the three strongest AUs. Expensive (two fits per
subject).
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


def _detected_lm3(paths, folder: Path) -> dict[Path, Path]:
    """Detect the landmarks of each scan once and write them as ``.lm3`` into ``folder``, with
    the header of ``jaxface landmarks`` (so the fit reads them as detected)."""
    from jaxface.landmarks import DETECTED_LM3_HEADER, write_lm3

    out = {}
    for p in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scan = load_scan(p, landmarks=False, warn_missing=False)
            det = detect_landmarks(scan)
        out[p] = folder / f"{p.stem}.lm3"
        write_lm3(out[p], det.landmarks, comment=DETECTED_LM3_HEADER)
    return out


def bench_fit(stems, root: Path, pairs=("truth:truth", "detected:detected"), weight=None) -> dict:
    """Fit each subject's expression scans once per ``neutral:scans`` landmark source pair
    (``truth`` = the ``.lm3`` beside the scan, ``detected`` = detected by
    :mod:`jaxface.detect`); the first pair is the reference of the ratios."""
    import dataclasses

    from jaxface.commands.fit import run_fit
    from jaxface.fit.evaluation import evaluate_against_truth, load_truth
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions

    opts = FitOptions(n_points=600, outer_iterations=3, max_steps=20)
    if weight is not None:
        opts = dataclasses.replace(opts, detected_landmark_weight=float(weight))
    sopts = SubjectOptions(levels=2, pitch_knots=6)
    truth = load_truth()
    out = []
    for subject in sorted({s.split("_")[0] for s in stems}):
        scans = [root / f"{s}.bnt" for s in stems if s.startswith(subject) and "_N_N_" not in s]
        neutral = root / f"{subject}_N_N_0.bnt"
        res = {}
        with tempfile.TemporaryDirectory() as lm_dir:
            det = (
                _detected_lm3([neutral, *scans], Path(lm_dir))
                if any("detected" in p for p in pairs)
                else {}
            )
            for pair in pairs:
                n_src, s_src = pair.split(":")
                with tempfile.TemporaryDirectory() as tmp:
                    t0 = time.perf_counter()
                    fits = run_fit(
                        neutral,
                        scans,
                        Path(tmp),
                        neutral_landmarks=det[neutral] if n_src == "detected" else None,
                        scan_landmarks=[det[p] for p in scans] if s_src == "detected" else None,
                        options=opts,
                        subject_options=sopts,
                        notice=lambda s: None,
                    )
                res[pair] = {
                    r.stem: {
                        "truth_error_mm": float(
                            evaluate_against_truth(r.fitted, truth, r.stem).error["all"].mean
                        ),
                        "scan_to_fit_mean_mm": float(r.metrics.scan_to_fit["all"].mean),
                        "top_aus": [k for k, _ in r.strongest_aus(3, bilateral_only=True)],
                    }
                    for r in fits
                }
                print(f"{subject} {pair}: {time.perf_counter() - t0:.0f} s")
        ref = pairs[0]
        for stem in res[ref]:
            a = res[ref][stem]
            row = {"stem": stem, ref: a}
            line = f"{stem:22s} {ref} {a['truth_error_mm']:.3f} mm {a['top_aus']}"
            for pair in pairs[1:]:
                b = res[pair][stem]
                row[pair] = dict(b, ratio=b["truth_error_mm"] / a["truth_error_mm"])
                line += f" | {pair} {b['truth_error_mm']:.3f} mm {b['top_aus']} ratio {row[pair]['ratio']:.2f}"
            print(line)
            out.append(row)
        for pair in pairs[1:]:
            r = np.array([o[pair]["ratio"] for o in out if o["stem"].startswith(subject)])
            e = np.mean([o[pair]["truth_error_mm"] for o in out if o["stem"].startswith(subject)])
            print(
                f"{subject} {pair}: mean error {e:.3f} mm, ratio to {ref} mean {r.mean():.3f}, "
                f"within 10 % on {(r <= 1.1).sum()} of {len(r)}"
            )
    return {
        "fit": out,
        "pairs": list(pairs),
        "detected_landmark_weight": opts.detected_landmark_weight,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--stems", nargs="*", default=None, help="scan stems (default: all)")
    ap.add_argument("--fit", action="store_true", help="fit with truth vs detected landmarks")
    ap.add_argument(
        "--pairs",
        nargs="*",
        default=["truth:truth", "detected:detected"],
        help="--fit: landmark sources NEUTRAL:SCANS (truth|detected), the first the reference",
    )
    ap.add_argument(
        "--detected-landmark-weight",
        type=float,
        default=None,
        help="--fit: FitOptions.detected_landmark_weight (default: the library's)",
    )
    args = ap.parse_args()
    for pair in args.pairs:
        if sorted(pair.split(":")) not in (
            ["truth", "truth"],
            ["detected", "truth"],
            ["detected", "detected"],
        ):
            ap.error(f"--pairs {pair!r}: use NEUTRAL:SCANS with truth or detected")
    root = shared_path("data", "bosphorus_style", pytest_skip=False)
    stems = args.stems or sorted(p.name[: -len(".bnt")] for p in root.glob("*.bnt"))
    result = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "load_avg_at_start": os.getloadavg(),
        "stems": stems,
    }
    result.update(
        bench_fit(stems, root, tuple(args.pairs), args.detected_landmark_weight)
        if args.fit
        else bench_detection(stems, root)
    )
    dest = Path(__file__).parent / "results"
    dest.mkdir(exist_ok=True)
    name = "bench_landmarks_fit.json" if args.fit else "bench_landmarks.json"
    (dest / name).write_text(json.dumps(result, indent=1))
    print(f"wrote {dest / name}")


if __name__ == "__main__":
    main()
