"""The files of ``jaxface fit-db`` under ``DIR`` and when a scan counts as done.

Per scan, under ``DIR/<subject>/``:

* ``<stem>.json`` and ``<stem>.fitted.ply``: exactly what ``jaxface fit`` writes;
* ``<stem>.fitdb.json``: the run record, written last: ``{"subject", "code", "scan",
  "status" ("fitted" | "failed"), "error" ("Type: message", or "" when the fit ran),
  "wall_s", "subject_wall_s", "worker"}``.

Every file is written to a temporary name in the same folder and renamed into place
(``os.replace``, atomic on POSIX), in this order: the old record deleted, ply, json, the new
record. A scan is *complete* (:func:`is_complete`) when its record says ``fitted`` and both
other files exist, so an interrupted run leaves either a complete scan or one that the next
run fits again. A failed scan's record holds the reason (and the scan keeps no fit files);
it counts as done (:func:`is_done`) unless the failures are to be tried again
(``jaxface fit-db --retry-failed``).

Temporary names start with ``.`` (``.<name>.<random>.tmp``, staging folders
``.staging-<random>``); :func:`remove_stale` deletes those a killed run left behind, and the
fit files of scans without a ``fitted`` record.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

__all__ = [
    "RECORD_SUFFIX",
    "STAGING_PREFIX",
    "atomic_write_bytes",
    "atomic_write_text",
    "is_complete",
    "is_done",
    "read_record",
    "record_path",
    "remove_stale",
    "scan_files",
    "write_record",
]

RECORD_SUFFIX = ".fitdb.json"
#: the files ``jaxface fit`` writes per scan (``<stem><suffix>``)
FIT_SUFFIXES = (".fitted.ply", ".fit.png", ".json")
STAGING_PREFIX = ".staging-"


def scan_files(out: Path, subject: str, stem: str) -> dict[str, Path]:
    """``{"json", "ply", "record"}`` paths of a scan's outputs."""
    d = Path(out) / subject
    return {
        "json": d / f"{stem}.json",
        "ply": d / f"{stem}.fitted.ply",
        "record": d / f"{stem}{RECORD_SUFFIX}",
    }


def record_path(out: Path, subject: str, stem: str) -> Path:
    return scan_files(out, subject, stem)["record"]


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and
    ``os.replace`` (readers see the old file or the whole new one, never a part)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp"
    # mode 0o666 less the umask, as a plain open() would give the file
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_record(out: Path, record: dict) -> Path:
    """Write a scan's run record (see the module docstring) atomically."""
    return atomic_write_text(
        record_path(out, record["subject"], record["scan"]), json.dumps(record, indent=1)
    )


def read_record(out: Path, subject: str, stem: str) -> dict | None:
    """The scan's run record, or None when there is none (or it cannot be read)."""
    p = record_path(out, subject, stem)
    try:
        rec = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def is_complete(out: Path, subject: str, stem: str) -> bool:
    """True when the scan was fitted and all its files are in place (see the module
    docstring)."""
    rec = read_record(out, subject, stem)
    if rec is None or rec.get("status") != "fitted":
        return False
    f = scan_files(out, subject, stem)
    return f["json"].is_file() and f["ply"].is_file()


def is_done(out: Path, subject: str, stem: str, *, retry_failed: bool = False) -> bool:
    """True when a resumed run skips the scan: it is complete, or (unless ``retry_failed``)
    its record says it failed."""
    if is_complete(out, subject, stem):
        return True
    if retry_failed:
        return False
    rec = read_record(out, subject, stem)
    return rec is not None and rec.get("status") == "failed"


def remove_stale(out: Path) -> int:
    """Delete what an interrupted run left under ``out/<subject>/``: temporary files, staging
    folders, and the fit files (``.json``, ``.fitted.ply``, ``.fit.png``) of scans whose
    record does not say ``fitted`` (a run stopped between their renames). Returns how many
    were removed. Only call it while no worker writes into ``out``."""
    n = 0
    out = Path(out)
    if not out.is_dir():
        return 0
    for sub in out.iterdir():
        if not sub.is_dir():
            continue
        for p in list(sub.iterdir()):
            if p.name.startswith(STAGING_PREFIX) and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
                n += 1
            elif p.name.startswith(".") and p.name.endswith(".tmp") and p.is_file():
                p.unlink(missing_ok=True)
                n += 1
            elif p.name.endswith(FIT_SUFFIXES) and not p.name.endswith(RECORD_SUFFIX):
                stem = next(p.name[: -len(s)] for s in FIT_SUFFIXES if p.name.endswith(s))
                rec = read_record(out, sub.name, stem)
                if rec is None or rec.get("status") != "fitted":
                    p.unlink(missing_ok=True)
                    n += 1
    return n
