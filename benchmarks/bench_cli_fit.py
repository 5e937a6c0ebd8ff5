"""Wall time of ``jaxface fit`` of one scan in a fresh process, with the caches cold and warm.

Each row is one ``jaxface fit`` subprocess (bs900's neutral and one expression scan of the
shared Bosphorus-style set, default options):

* ``cold``: empty XLA compile cache and empty subject cache;
* ``compile cache warm``: the compile cache of the run before, subject cache off;
* ``both caches warm``: the compile cache and the subject cache of the runs before.

``--baseline-src DIR`` runs the same rows with another source tree first (``DIR`` is a
``src`` folder holding ``jaxface``, e.g. a ``git worktree`` of an earlier commit), in the
same session, so the two are compared side by side; a tree without ``--subject-cache``
gets no third row. The fits' JSON are compared (all but timings) and must be equal.

    python benchmarks/bench_cli_fit.py [--scan bs900_LFAU_12_0] [--baseline-src /tmp/base/src]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from jaxface.testing import shared_path

RUNNER = "import sys; from jaxface.cli import main; sys.argv = ['jaxface'] + sys.argv[1:]; main()"


def _run(src: Path | None, args: list[str]) -> float:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    env.pop("JAXFACE_SUBJECT_CACHE", None)
    env.pop("JAXFACE_COMPILE_CACHE", None)
    t = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-c", RUNNER, *args], env=env, capture_output=True, text=True
    )
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise SystemExit(
            f"jaxface fit failed ({p.returncode}):\n{p.stdout[-2000:]}{p.stderr[-2000:]}"
        )
    return wall


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in ("seconds", "time_s")}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def rows_for(src: Path | None, stem: str, work: Path, subject_cache: bool) -> dict:
    root = shared_path("data", "bosphorus_style")
    cc, sc = work / "xla", work / "subjects"
    base = ["fit", "-n", str(root / "bs900_N_N_0.bnt"), "-s", str(root / f"{stem}.bnt")]
    out: dict = {}
    sc_off = ["--subject-cache", "off"] if subject_cache else []
    sc_on = ["--subject-cache", str(sc)] if subject_cache else []
    out["cold"] = _run(src, ["--compile-cache", str(cc), *base, "-o", str(work / "a"), *sc_on])
    out["compile cache warm"] = _run(
        src, ["--compile-cache", str(cc), *base, "-o", str(work / "b"), *sc_off]
    )
    if subject_cache:
        out["both caches warm"] = _run(
            src, ["--compile-cache", str(cc), *base, "-o", str(work / "c"), *sc_on]
        )
    fits = [
        _strip(json.loads((work / d / f"{stem}.json").read_text()))
        for d in ("a", "b", "c")
        if (work / d / f"{stem}.json").is_file()
    ]
    out["same fits"] = all(f == fits[0] for f in fits)
    out["_fit"] = fits[0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scan", default="bs900_LFAU_12_0")
    ap.add_argument("--baseline-src", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = ap.parse_args()
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-cli-fit-") as tmp:
        if args.baseline_src is not None:
            src = args.baseline_src.resolve()
            has_cache = "subject_cache" in (src / "jaxface" / "commands" / "fit.py").read_text()
            results["baseline"] = rows_for(src, args.scan, Path(tmp) / "base", has_cache)
        here = Path(__file__).resolve().parents[1] / "src"
        results["this code"] = rows_for(here, args.scan, Path(tmp) / "new", True)
    if "baseline" in results:
        results["same fits as the baseline"] = (
            results["baseline"].pop("_fit") == results["this code"]["_fit"]
        )
    results["this code"].pop("_fit", None)
    print(f"jaxface fit of {args.scan}, one fresh process each (wall s):")
    for name in ("baseline", "this code"):
        if name in results:
            r = results[name]
            cols = ", ".join(f"{k} {v:.1f}" for k, v in r.items() if isinstance(v, float))
            print(f"  {name}: {cols}; fits equal across rows: {r['same fits']}")
    if "same fits as the baseline" in results:
        print(f"  fits equal to the baseline's: {results['same fits as the baseline']}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
