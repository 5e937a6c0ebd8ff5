"""What ``jaxface fit-db`` fits: the subjects of a database and their scans.

Three layouts (:func:`discover_database`):

* a folder per subject, Bosphorus style: ``ROOT/bs000/bs000_N_N_0.bnt`` with the ``.lm3``
  beside each scan;
* a flat folder of ``bsNNN_<class>_<code>_<n>.bnt`` (with their ``.lm3``);
* a CSV manifest (:func:`read_manifest`) with the columns ``subject``, ``neutral``, ``scan``
  (one row per expression scan; optional ``neutral_landmarks``, ``scan_landmarks``, ``code``)
  for any other layout, e.g. PLY/OBJ scans. Relative paths are relative to the CSV's folder.

A Bosphorus subject's neutral is its ``N_N_0`` scan; every other scan of the subject is fitted
except class ``IGN`` (scans the database marks to be ignored). A subject without a neutral
is still listed (``neutral`` None): its scans become failed rows saying so.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

from ..errors import DataNotFoundError, ScanFormatError
from ..fit.pipeline import scan_stem as pipeline_stem
from ..io.bosphorus import parse_scan_name

__all__ = ["ScanEntry", "SubjectJob", "discover_database", "read_manifest", "scan_stem"]

#: scan file types a folder layout is searched for
SCAN_SUFFIXES = (".bnt",)


@dataclass(frozen=True)
class ScanEntry:
    """One expression scan to fit.

    Attributes:
        stem: the output stem (``<stem>.json``, ``<stem>.fitted.ply``), as ``jaxface fit``
            names it.
        code: the expression code, e.g. ``LFAU_12`` or ``E_HAPPY`` (Bosphorus class and code;
            a manifest's ``code`` column, else the stem).
        path: the scan file; landmarks: its ``.lm3`` (None: the one beside the scan).
    """

    stem: str
    code: str
    path: Path
    landmarks: Path | None = None


@dataclass(frozen=True)
class SubjectJob:
    """A subject: its neutral scan (the rig is built on it once) and its expression scans.

    Attributes:
        subject: the subject's name (``bs000``); also its output folder ``DIR/<subject>/``.
        neutral: the neutral scan, or None when the database has none for this subject.
        neutral_landmarks: its ``.lm3`` (None: beside the scan).
        scans: the expression scans, sorted by stem.
    """

    subject: str
    neutral: Path | None
    scans: tuple[ScanEntry, ...]
    neutral_landmarks: Path | None = None


def scan_stem(path: Path) -> str:
    """The stem ``jaxface fit`` gives a scan file's outputs (``x.truth.ply`` -> ``x``)."""
    return pipeline_stem(SimpleNamespace(path=Path(path)))


def _code_of(stem: str) -> str:
    info = parse_scan_name(stem)
    return f"{info.kind}_{info.code}" if info is not None else stem


def discover_database(root: Path) -> list[SubjectJob]:
    """The subjects of the database at ``root`` (a folder or a ``.csv`` manifest), sorted by
    name.

    Raises:
        DataNotFoundError: ``root`` does not exist, or holds no Bosphorus-named scan.
        ScanFormatError: a malformed manifest.
    """
    root = Path(root)
    if not root.exists():
        raise DataNotFoundError(f"database not found: {root}")
    if root.is_file():
        if root.suffix.lower() != ".csv":
            raise ScanFormatError(
                f"{root}: a database is a folder (Bosphorus layout) or a .csv manifest with the "
                "columns subject, neutral, scan."
            )
        return read_manifest(root)
    files = [p for p in root.iterdir() if p.is_file()]
    for sub in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        files.extend(p for p in sub.iterdir() if p.is_file())
    found: dict[str, dict] = {}
    for p in sorted(files):
        if p.suffix.lower() not in SCAN_SUFFIXES:
            continue
        info = parse_scan_name(p.name)
        if info is None or info.kind == "IGN":
            continue
        entry = found.setdefault(info.subject, {"neutral": None, "scans": []})
        if info.is_neutral and info.index == 0:
            entry["neutral"] = p
        else:
            entry["scans"].append(ScanEntry(info.stem, f"{info.kind}_{info.code}", p))
    if not found:
        raise DataNotFoundError(
            f"no Bosphorus scan (bsNNN_<class>_<code>_<n>.bnt) in {root} or its subject folders; "
            "for another layout give a CSV manifest with the columns subject, neutral, scan."
        )
    return [
        SubjectJob(name, f["neutral"], tuple(sorted(f["scans"], key=lambda e: e.stem)))
        for name, f in sorted(found.items())
    ]


def read_manifest(path: Path) -> list[SubjectJob]:
    """Subjects from a CSV manifest: columns ``subject``, ``neutral``, ``scan`` (required),
    ``neutral_landmarks``, ``scan_landmarks``, ``code`` (optional; empty = default). One row
    per expression scan; every row of a subject names the same neutral.

    Raises:
        ScanFormatError: a missing column, an empty required cell, two neutrals for one
            subject, or a scan listed twice for a subject (its outputs would collide).
    """
    path = Path(path)
    base = path.parent

    def resolve(cell: str | None) -> Path | None:
        cell = (cell or "").strip()
        if not cell:
            return None
        p = Path(cell).expanduser()
        return p if p.is_absolute() else base / p

    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        cols = {c.strip() for c in reader.fieldnames or []}
        missing = [c for c in ("subject", "neutral", "scan") if c not in cols]
        if missing:
            raise ScanFormatError(
                f"{path}: the manifest lacks the column(s) {missing}; it needs a header row with "
                "subject, neutral, scan (optional: neutral_landmarks, scan_landmarks, code)."
            )
        subjects: dict[str, dict] = {}
        for i, raw in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in raw.items() if k is not None}
            if not any(row.values()):
                continue
            for c in ("subject", "neutral", "scan"):
                if not row.get(c):
                    raise ScanFormatError(f"{path}, line {i}: the column {c!r} is empty.")
            neutral = resolve(row["neutral"])
            nlm = resolve(row.get("neutral_landmarks"))
            s = subjects.setdefault(
                row["subject"], {"neutral": neutral, "nlm": nlm, "scans": {}, "line": i}
            )
            if (s["neutral"], s["nlm"]) != (neutral, nlm):
                raise ScanFormatError(
                    f"{path}, line {i}: subject {row['subject']!r} has another neutral than on line "
                    f"{s['line']} ({s['neutral']}); give one neutral per subject."
                )
            scan = resolve(row["scan"])
            assert scan is not None
            stem = scan_stem(scan)
            if stem in s["scans"]:
                raise ScanFormatError(
                    f"{path}, line {i}: subject {row['subject']!r} lists the scan stem {stem!r} "
                    "twice; the outputs would overwrite each other."
                )
            code = row.get("code") or _code_of(stem)
            s["scans"][stem] = ScanEntry(stem, code, scan, resolve(row.get("scan_landmarks")))
    if not subjects:
        raise ScanFormatError(f"{path}: the manifest lists no scan.")
    return [
        SubjectJob(name, s["neutral"], tuple(s["scans"][k] for k in sorted(s["scans"])), s["nlm"])
        for name, s in sorted(subjects.items())
    ]
