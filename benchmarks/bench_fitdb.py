"""Benchmark of ``jaxface fit-db``: scans per hour for a database, against ``jaxface fit``
batches run one after another, and an extrapolation to the Bosphorus database.

Run from the repository root (needs the shared data: ``JAXFACE_SHARED`` or ``../shared``)::

    python benchmarks/bench_fitdb.py [--subjects bs900,bs901] [--scans 2] [--workers 1,2]
                                     [--full] [--json PATH]

It builds a small database (symbolic links into ``shared/data/bosphorus_style``: each
subject's neutral and its first ``--scans`` expression scans) and times, on the same scans
and settings:

* ``fit``: one fresh process per subject, run one after another, each calling
  :func:`jaxface.commands.fit.run_fit` (what ``jaxface fit -n N -s S1 -s S2 ...`` runs:
  start, import, rig, compile, batch fit, write);
* ``fit-db`` with each ``--workers`` count: :func:`jaxface.fitdb.runner.run_database` on an
  embedded LocalCluster (worker start-up included), ``--no-resume``.

Settings: by default the quick settings of ``tests/fitdb/test_fitdb.py`` (two controls sampled and
fitted, 200 points, one outer iteration): a full fit of a subject takes minutes on 2 cores,
and the comparison is about scheduling, not the fit; ``--full`` uses ``jaxface fit``'s
defaults. The compile cache is off in every process (a warm cache would favour whichever
runs second).

Extrapolation: from the fit-db run with one worker, the per-subject task time
``T = R + k f`` (``R``: neutral, rig and compilation; ``f``: per scan, from the scans'
``solver.time_s`` and evaluation) gives the Bosphorus database (105 subjects, 4,666 scans,
44.4 per subject) on N workers as ``105 (R + 44.4 f) / N`` plus one worker start-up, if each
worker has the cores the measured one had (2 here) and the subjects spread evenly.
Prints a table and writes ``--json`` (default ``benchmarks/results/bench_fitdb.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq

from jaxface.fit.options import FitOptions
from jaxface.fit.pipeline import SubjectOptions
from jaxface.fitdb.discover import discover_database
from jaxface.fitdb.runner import ClusterSpec, run_database
from jaxface.fitdb.task import FitSettings
from jaxface.testing import shared_path

BOSPHORUS_SUBJECTS = 105
BOSPHORUS_SCANS = 4666
QUICK_CONTROLS = ("zygomaticus_major_L", "zygomaticus_major_R")


def settings(full: bool) -> FitSettings:
    if full:
        return FitSettings()
    return FitSettings(
        options=FitOptions(
            n_points=200,
            outer_iterations=1,
            extra_iterations=0,
            restart_iterations=0,
            max_steps=5,
            jaw_starts=(0.0,),
            controls=QUICK_CONTROLS,
        ),
        subject_options=SubjectOptions(levels=2, pitch_knots=3, controls=QUICK_CONTROLS),
    )


_FIT_ONE = """
import sys, jax
jax.config.update("jax_enable_x64", True)
from pathlib import Path
sys.path.insert(0, {bench!r})
from bench_fitdb import settings
from jaxface.commands.fit import run_fit
s = settings({full!r})
run_fit(Path({neutral!r}), [Path(p) for p in {scans!r}], Path({out!r}), options=s.options,
        subject_options=s.subject_options)
"""


def make_db(root: Path, subjects: list[str], n_scans: int, db: Path) -> int:
    db.mkdir(parents=True)
    n = 0
    for subj in subjects:
        stems = sorted(p.stem for p in root.glob(f"{subj}_*.bnt") if "_N_N_" not in p.name)
        for stem in [f"{subj}_N_N_0", *stems[:n_scans]]:
            for ext in (".bnt", ".lm3"):
                (db / f"{stem}{ext}").symlink_to(root / f"{stem}{ext}")
        n += len(stems[:n_scans])
    return n


def run_fit_batches(jobs, out: Path, full: bool) -> float:
    env = dict(os.environ, JAXFACE_COMPILE_CACHE="off")
    t = time.perf_counter()
    for job in jobs:
        code = _FIT_ONE.format(
            bench=str(Path(__file__).resolve().parent),
            full=full,
            neutral=str(job.neutral),
            scans=[str(e.path) for e in job.scans],
            out=str(out / job.subject),
        )
        subprocess.run([sys.executable, "-c", code], check=True, env=env)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--subjects", default="bs900,bs901")
    ap.add_argument("--scans", type=int, default=2, help="expression scans per subject")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--full", action="store_true", help="jaxface fit's default settings")
    ap.add_argument("--json", type=Path, default=Path("benchmarks/results/bench_fitdb.json"))
    args = ap.parse_args()
    root = shared_path("data", "bosphorus_style", pytest_skip=False)
    subjects = args.subjects.split(",")
    res: dict = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average_start": os.getloadavg(),
        "settings": "full (jaxface fit defaults)"
        if args.full
        else "quick (tests/fitdb/test_fitdb.py)",
        "subjects": subjects,
        "runs": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        n = make_db(root, subjects, args.scans, tmp / "db")
        jobs = discover_database(tmp / "db")
        res["scans"] = n
        print(f"{n} scan(s) of {len(jobs)} subject(s); load average {os.getloadavg()}", flush=True)
        wall = run_fit_batches(jobs, tmp / "fit", args.full)
        res["runs"]["fit (one process per subject, in turn)"] = {
            "wall_s": wall,
            "scans_per_hour": n * 3600 / wall,
        }
        print(f"fit batches: {wall:.1f} s, {n * 3600 / wall:.1f} scans/h", flush=True)
        per_subject = None
        startup = 0.0
        for w in (int(x) for x in args.workers.split(",")):
            t = time.perf_counter()
            rep = run_database(
                jobs,
                tmp / f"db{w}",
                settings(args.full),
                ClusterSpec(workers=w, compile_cache="off"),
                resume=False,
            )
            wall = time.perf_counter() - t
            if rep.failed or rep.fitted != n:
                raise SystemExit(f"fit-db with {w} worker(s): {rep}")
            rows = pq.read_table(rep.table).to_pylist()
            sub = {r["subject"]: r["subject_wall_s"] for r in rows}
            fit_s = []
            for r in rows:
                doc = json.loads((tmp / f"db{w}" / r["subject"] / f"{r['scan']}.json").read_text())
                fit_s.append(doc["solver"]["time_s"])
            res["runs"][f"fit-db, {w} worker(s)"] = {
                "wall_s": wall,
                "scans_per_hour": n * 3600 / wall,
                "subject_task_s": sub,
                "scan_fit_s_mean": sum(fit_s) / len(fit_s),
            }
            print(
                f"fit-db {w} worker(s): {wall:.1f} s, {n * 3600 / wall:.1f} scans/h; "
                f"subject tasks {', '.join(f'{k} {v:.0f} s' for k, v in sub.items())}",
                flush=True,
            )
            if w == 1:
                k = n / len(jobs)
                T = sum(sub.values()) / len(sub)
                f = sum(fit_s) / len(fit_s)
                per_subject = {"task_s": T, "scans": k, "scan_s": f, "rig_s": max(T - k * f, 0.0)}
                startup = wall - sum(sub.values())
    res["load_average_end"] = os.getloadavg()
    if per_subject is not None:
        per_scan_db = BOSPHORUS_SCANS / BOSPHORUS_SUBJECTS
        one = per_subject["rig_s"] + per_scan_db * per_subject["scan_s"]
        res["per_subject"] = per_subject
        res["extrapolation_4666"] = {
            str(N): {"hours": (BOSPHORUS_SUBJECTS * one / N + startup) / 3600}
            for N in (1, 2, 4, 8, 16, 32, 64)
        }
        print(
            f"per subject (1 worker): task {per_subject['task_s']:.0f} s for "
            f"{per_subject['scans']:.1f} scan(s) = rig {per_subject['rig_s']:.0f} s + "
            f"{per_subject['scan_s']:.0f} s per scan; a Bosphorus subject "
            f"({per_scan_db:.1f} scans) {one:.0f} s"
        )
        for N, v in res["extrapolation_4666"].items():
            print(f"  4,666 scans on {N:>2} worker(s) of 2 cores: {v['hours']:.1f} h")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=1))
    print(f"load average at the end {os.getloadavg()}; wrote {args.json}")


if __name__ == "__main__":
    main()
