"""The results table of ``jaxface fit-db``: ``DIR/results.parquet``, one row per scan.

The table is always rebuilt from the per-scan files (:func:`build_rows`): the run record
``<stem>.fitdb.json`` and, for a fitted scan, ``<stem>.json``; so it matches the files
whatever runs, crashes and resumes produced them. Columns (units in the names):

===========================  ===============================================================
``subject``, ``code``,       the subject (``bs000``), the expression code (``LFAU_12``), the
``scan``                     scan's stem (``bs000_LFAU_12_0``)
``status``                   ``fitted``, ``failed`` or ``pending`` (not run yet: an
                             interrupted run)
``error``                    ``Type: message`` of a failed scan; empty otherwise
``solver_status``            the fit's ``solver.status`` (``successful``, ...)
``scan_to_fit_mm``           mean scan-to-fit distance over the face (``metrics.scan_to_fit.
                             all.mean``)
``b0_mm``, ``b1_mm``         the same for the baselines B0 (neutral) and B1 (landmark warp)
``jaw_pitch_deg``,           the fitted jaw pose (``jaw``)
``jaw_yaw_deg``,
``jaw_protrusion_mm``
``AU1`` ... ``AU12L`` ...    FACS AU intensities (``au_intensities``), one column per AU
``act_<control>``            activations in [0, 1] (``activations``: the muscles and the two cheek pressures)
``wall_s``                   the scan's share of its subject's task (s); ``subject_wall_s``
                             the whole task
``worker``                   the Dask worker that ran it (``name@address``)
===========================  ===============================================================

Numbers that do not apply (a failed scan's metrics) are nulls, never NaN.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import DataNotFoundError
from .discover import SubjectJob
from .outputs import atomic_write_bytes, read_record, scan_files

__all__ = ["TABLE_NAME", "build_rows", "rows_to_table", "write_table", "read_table", "summarise"]

TABLE_NAME = "results.parquet"

_TEXT = ("subject", "code", "scan", "status", "error", "solver_status")
_NUM = (
    "scan_to_fit_mm",
    "b0_mm",
    "b1_mm",
    "jaw_pitch_deg",
    "jaw_yaw_deg",
    "jaw_protrusion_mm",
)
_TAIL = (("wall_s", pa.float64()), ("subject_wall_s", pa.float64()), ("worker", pa.string()))


def _num(x) -> float | None:
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def _mean(doc: dict, *keys: str) -> float | None:
    d = doc
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return _num(d)


def _fit_row(doc: dict) -> dict:
    jaw = doc.get("jaw") or {}
    row = {
        "solver_status": (doc.get("solver") or {}).get("status", ""),
        "scan_to_fit_mm": _mean(doc, "metrics", "scan_to_fit", "all", "mean"),
        "b0_mm": _mean(doc, "baselines", "B0", "scan_to_fit", "all", "mean"),
        "b1_mm": _mean(doc, "baselines", "B1", "scan_to_fit", "all", "mean"),
        "jaw_pitch_deg": _num(jaw.get("pitch_deg")),
        "jaw_yaw_deg": _num(jaw.get("yaw_deg")),
        "jaw_protrusion_mm": _num(jaw.get("protrusion_mm")),
    }
    for k, v in (doc.get("au_intensities") or {}).items():
        row[k] = _num(v)
    for k, v in (doc.get("activations") or {}).items():
        row[f"act_{k}"] = _num(v)
    return row


def build_rows(out: Path, jobs: Sequence[SubjectJob]) -> list[dict]:
    """One row per scan of ``jobs`` from the files under ``out`` (see the module docstring):
    the fit's numbers for a complete fitted scan, the reason for a failed one, ``pending``
    for a scan without a usable record."""
    rows = []
    for job in jobs:
        for e in job.scans:
            row: dict = {"subject": job.subject, "code": e.code, "scan": e.stem}
            rec = read_record(out, job.subject, e.stem)
            files = scan_files(out, job.subject, e.stem)
            doc = None
            if rec is not None and rec.get("status") == "fitted" and files["ply"].is_file():
                try:
                    doc = json.loads(files["json"].read_text())
                except (OSError, ValueError):
                    doc = None
            if doc is not None and rec is not None:
                row.update(status="fitted", error="", **_fit_row(doc))
            elif rec is not None and rec.get("status") == "failed":
                row.update(status="failed", error=str(rec.get("error") or ""))
            else:
                row.update(status="pending", error="")
                rec = None
            if rec is not None:
                row.update(
                    wall_s=_num(rec.get("wall_s")),
                    subject_wall_s=_num(rec.get("subject_wall_s")),
                    worker=str(rec.get("worker") or ""),
                )
            rows.append(row)
    return rows


def rows_to_table(rows: Sequence[dict]) -> pa.Table:
    """The Arrow table of ``rows``: text columns, the fit's numbers, the AU columns and the
    ``act_`` columns (in first-seen order), then ``wall_s``, ``subject_wall_s``, ``worker``;
    absent values are nulls."""
    fixed = set(_TEXT) | set(_NUM) | {k for k, _ in _TAIL}
    aus: list[str] = []
    acts: list[str] = []
    seen: set[str] = set()
    for r in rows:
        for k in r:
            if k in fixed or k in seen:
                continue
            seen.add(k)
            (acts if k.startswith("act_") else aus).append(k)
    fields = [pa.field(k, pa.string()) for k in _TEXT]
    fields += [pa.field(k, pa.float64()) for k in (*_NUM, *aus, *acts)]
    fields += [pa.field(k, t) for k, t in _TAIL]
    schema = pa.schema(fields)
    data = {}
    for f in schema:
        vals = [r.get(f.name) for r in rows]
        if pa.types.is_string(f.type):
            vals = ["" if v is None and f.name in ("error", "solver_status") else v for v in vals]
        data[f.name] = vals
    return pa.Table.from_pydict(data, schema=schema)


def write_table(out: Path, rows: Sequence[dict]) -> Path:
    """Write ``out/results.parquet`` atomically; returns its path."""
    buf = io.BytesIO()
    pq.write_table(rows_to_table(rows), buf)
    return atomic_write_bytes(Path(out) / TABLE_NAME, buf.getvalue())


def read_table(path: Path) -> pa.Table:
    """Read a results table: ``path`` is the parquet file or the ``DIR`` holding it."""
    path = Path(path)
    if path.is_dir():
        path = path / TABLE_NAME
    if not path.is_file():
        raise DataNotFoundError(
            f"no results table at {path}: give the --out folder of a `jaxface fit-db` run."
        )
    return pq.read_table(path)


def summarise(table: pa.Table, n_aus: int = 3) -> list[dict]:
    """Per expression code: ``{"code", "scans", "fitted", "failed", "pending",
    "scan_to_fit_mm", "b0_mm", "b1_mm" (means over the fitted scans, mm; None when none),
    "aus": [(AU, mean intensity), ...]}`` with the ``n_aus`` bilateral AUs of highest mean
    intensity, in code order."""
    rows = table.to_pylist()
    au_cols = [c for c in table.column_names if c.startswith("AU") and not c.endswith(("L", "R"))]
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["code"], []).append(r)

    def mean(rs, k):
        v = [r[k] for r in rs if r.get(k) is not None]
        return sum(v) / len(v) if v else None

    out = []
    for code in sorted(by):
        rs = by[code]
        ok = [r for r in rs if r["status"] == "fitted"]
        au = [(c, mean(ok, c)) for c in au_cols]
        au = sorted(((c, m) for c, m in au if m is not None), key=lambda cm: -cm[1])
        out.append(
            {
                "code": code,
                "scans": len(rs),
                "fitted": len(ok),
                "failed": sum(r["status"] == "failed" for r in rs),
                "pending": sum(r["status"] == "pending" for r in rs),
                "scan_to_fit_mm": mean(ok, "scan_to_fit_mm"),
                "b0_mm": mean(ok, "b0_mm"),
                "b1_mm": mean(ok, "b1_mm"),
                "aus": au[:n_aus],
            }
        )
    return out
