"""``jaxface landmarks``: the Bosphorus landmarks of a scan that has no landmark file.

Contract::

    jaxface landmarks SCAN.(bnt|ply|obj) [--out SCAN.lm3] [--units mm] [--pictures]

Writes the visible labels as a Bosphorus ``.lm3`` (default: beside the scan), a
``<out>.json`` with per-landmark confidence, the omitted labels with their reason and the
detected pose, and with ``--pictures`` a ``<out>.png`` (front and side views of the scan with
the landmarks coloured by confidence). Units: mm (``--units`` converts the input); the
landmarks are written in the scan's own frame. Method: :mod:`jaxface.detect`.

:func:`detect_for` is the hook used by ``jaxface fit`` and ``jaxface synth --mesh`` to detect
landmarks when none are given.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import typer

__all__ = ["register", "run_landmarks", "detect_for"]


def _atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def detect_for(scan, what: str, notice=None):
    """Detect landmarks on ``scan`` (a :class:`jaxface.io.Scan` or a mesh, mm) and say so
    through ``notice(text)``. Returns the :class:`jaxface.detect.Detection`."""
    from ..detect import detect_landmarks

    det = detect_landmarks(scan)
    if notice is not None:
        conf = det.confidence.values()
        notice(
            f"no landmark file for the {what}: detected {len(det.landmarks)} landmarks "
            f"automatically (mean confidence {sum(conf) / max(len(conf), 1):.2f}"
            + (f"; left out: {', '.join(det.omitted)}" if det.omitted else "")
            + ")"
        )
    return det


def run_landmarks(scan_path: Path, out: Path | None = None, *, units: str = "mm", pictures=False):
    """Detect the landmarks of ``scan_path`` and write ``out`` (``.lm3``), ``out``.json and,
    with ``pictures``, ``out``.png. Returns ``(Detection, {kind: path})``."""
    from ..detect import detect_landmarks
    from ..errors import DataNotFoundError
    from ..io import load_scan
    from ..landmarks import DETECTED_LM3_HEADER, write_lm3

    scan_path = Path(scan_path)
    if not scan_path.is_file():
        raise DataNotFoundError(f"scan file not found: {scan_path}")
    scan = load_scan(scan_path, landmarks=False, units=units, warn_missing=False)
    det = detect_landmarks(scan)
    out = Path(out) if out is not None else scan_path.with_suffix(".lm3")
    out.parent.mkdir(parents=True, exist_ok=True)
    comment = (
        f"{DETECTED_LM3_HEADER} from {scan_path.name} (mm, scan frame)\n"
        + "".join(f"omitted {n}: {r}\n" for n, r in det.omitted.items())
    ).rstrip("\n")
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".lm3")
    os.close(fd)
    try:
        write_lm3(tmp, det.landmarks, comment=comment)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    files = {"lm3": out, "json": out.with_suffix(".json")}
    info = {"scan": str(scan_path), "units_in": units, **det.to_dict()}
    _atomic_write_text(files["json"], json.dumps(info, indent=1))
    if pictures:
        files["png"] = _picture(out.with_suffix(".png"), scan, det)
    return det, files


def _picture(path: Path, scan, det) -> Path:
    """Front and side views of the scan (in the detected face frame) with the landmarks."""
    import numpy as np

    from ..detect import scan_arrays
    from ..render import save_views

    v, f = scan_arrays(scan)
    T = det.pose.transform.inverse()  # scan -> jaxface frame, so "front" faces the viewer
    lm = det.landmarks.with_positions(T.apply(det.landmarks.positions))
    conf = np.array([det.confidence[n] for n in lm.names])
    title = (
        f"{Path(str(getattr(scan, 'path', '') or 'scan')).name}: {len(lm)} landmarks, "
        f"confidence {conf.min():.2f}-{conf.max():.2f}"
        + (f"; omitted {len(det.omitted)}" if det.omitted else "")
    )
    return save_views(path, (T.apply(v), f), ("front", "side"), landmarks=lm, title=title)


def register(app: typer.Typer) -> None:
    """Add ``jaxface landmarks`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors

    @app.command(epilog=_EPILOG)
    @handle_errors
    def landmarks(
        scan: Path = typer.Argument(..., help="Scan (.bnt, .ply, .obj) without landmarks."),
        out: Path | None = typer.Option(  # noqa: UP007
            None, "--out", "-o", help="Output .lm3 (default: beside the scan)."
        ),
        units: str = typer.Option("mm", "--units", help="Units of the scan: mm, cm or m."),
        pictures: bool = typer.Option(False, "--pictures", help="Also write <out>.png."),
    ):
        """Find the Bosphorus landmarks on a scan that has no .lm3 (any frame; no input
        landmarks) and write them as .lm3, with confidences and omitted labels in .json.

        Example:

          jaxface landmarks bs000_N_N_0.bnt --out bs000_N_N_0.lm3 --pictures
        """
        det, files = run_landmarks(scan, out, units=units, pictures=pictures)
        console.print(
            f"{len(det.landmarks)} landmarks in {det.seconds:.1f} s "
            f"(pose fit median {det.pose.median_mm:.2f} mm) -> {files['lm3']}"
        )
        for n in det.landmarks.names:
            console.print(f"  {n:24s} confidence {det.confidence[n]:.2f}")
        for n, r in det.omitted.items():
            console.print(f"  [yellow]omitted[/] {n}: {r}", markup=True)
        if det.side_problem:
            console.print(f"[yellow]warning:[/] {det.side_problem}", markup=True)
        for k in ("json", "png"):
            if k in files:
                console.print(f"wrote {files[k]}")
