"""The unit of work of ``jaxface fit-db``: one subject, run on a Dask worker.

:func:`fit_subject` builds the subject's rig once from its neutral and fits its scans as one
batch, with the library calls of ``jaxface fit``
(:func:`jaxface.commands.fit.load_fit_scan`, :func:`~jaxface.commands.fit.prepare_fit_subject`,
:func:`~jaxface.commands.fit.fit_and_write`), so each scan's ``<stem>.json`` and
``<stem>.fitted.ply`` are the ones ``jaxface fit`` writes for the same scan and options.
Nothing stops the subject: a scan that cannot be loaded is a failed record and the rest are
fitted; a rig that cannot be built fails the subject's scans with the reason; a batch that
raises is fitted again scan by scan (each scan gets the fit it gets in the batch, see
:func:`jaxface.fit.pipeline.fit_expressions`), so only the scan at fault fails.

The files are written into a staging folder and moved into ``DIR/<subject>/`` one by one
(see :mod:`jaxface.fitdb.outputs`). The task returns the scans' run records.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import jax
from distributed import get_worker

from ..commands.fit import fit_and_write, load_fit_scan, prepare_fit_subject
from ..errors import DataNotFoundError
from ..fit.options import FitOptions
from ..fit.pipeline import SubjectOptions
from .discover import ScanEntry, SubjectJob
from .outputs import STAGING_PREFIX, scan_files, write_record

__all__ = ["FitSettings", "fit_subject", "error_text", "EVENT_TOPIC", "CRASH_ONCE_ENV"]

#: Dask event topic of the per-scan progress events (``{"subject", "scan", "status"}``)
EVENT_TOPIC = "jaxface-fitdb"

#: Test hook, read by :func:`fit_subject`: ``SUBJECT=MARKER``. The first attempt of
#: SUBJECT's task (while the file MARKER does not exist) creates MARKER and ends its worker
#: process at once (``os._exit(1)``), as a crash would; Dask then runs the task again.
CRASH_ONCE_ENV = "JAXFACE_FITDB_CRASH_ONCE"


@dataclass(frozen=True)
class FitSettings:
    """The ``jaxface fit`` settings every subject is fitted with.

    Attributes:
        options: :class:`~jaxface.fit.options.FitOptions`; subject_options:
            :class:`~jaxface.fit.pipeline.SubjectOptions` (its ``backend`` is used).
        template, template_landmarks: a template skin (mm) and its ``.lm3`` (None: the
            built-in head).
        pictures: also write ``<stem>.fit.png``; batch_size: as ``jaxface fit --batch-size``.
        landmarks: ``"file"`` or ``"auto"``, as ``jaxface fit --landmarks``.
        arkit: the ARKit readout's ICT data (``"auto"``: ``$JAXFACE_ICT``; a path; None: off),
            as ``jaxface fit --ict`` / ``--no-arkit``.
        subject_cache: the subject cache folder, ``"default"`` or ``"off"``, as
            ``jaxface fit --subject-cache`` (None: ``$JAXFACE_SUBJECT_CACHE`` of the worker).
    """

    options: FitOptions = field(default_factory=FitOptions)
    subject_options: SubjectOptions = field(default_factory=SubjectOptions)
    template: Path | None = None
    template_landmarks: Path | None = None
    pictures: bool = False
    batch_size: int | None = None
    landmarks: str = "file"
    arkit: object = "auto"
    subject_cache: str | None = None


def error_text(e: BaseException) -> str:
    """``Type: message`` of an exception (the ``error`` column)."""
    msg = str(e).strip().replace("\n", " ")
    return f"{type(e).__name__}: {msg}" if msg else type(e).__name__


def _worker_name() -> str:
    try:
        w = get_worker()
    except ValueError:  # run outside a Dask worker (in-process)
        return f"local-{os.getpid()}"
    return f"{w.name}@{w.address}"


def _event(subject: str, stem: str, status: str) -> None:
    try:
        get_worker().log_event(EVENT_TOPIC, {"subject": subject, "scan": stem, "status": status})
    except ValueError:
        pass


def _crash_hook(subject: str) -> None:
    spec = os.environ.get(CRASH_ONCE_ENV, "")
    if "=" not in spec:
        return
    who, marker = spec.split("=", 1)
    if who != subject:
        return
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return
    os.close(fd)
    os._exit(1)


def fit_subject(job: SubjectJob, settings: FitSettings, out: str | Path) -> list[dict]:
    """Fit ``job``'s scans (all of them: the caller leaves out the complete ones) and write
    their outputs and run records under ``out/<subject>/``. Returns the run records (see
    :mod:`jaxface.fitdb.outputs`), in the order of ``job.scans``.

    ``wall_s`` of a fitted scan is its subject's task time (loading, rig, fits, writes;
    ``subject_wall_s``) divided by the number of scans fitted in it; of a failed one 0.
    """
    _crash_hook(job.subject)
    # as `jaxface fit`: the fit runs in float64
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    out = Path(out)
    worker = _worker_name()
    sdir = out / job.subject
    sdir.mkdir(parents=True, exist_ok=True)
    records: dict[str, dict] = {}

    def fail(entry: ScanEntry, e: BaseException | str) -> None:
        rec = {
            "subject": job.subject,
            "code": entry.code,
            "scan": entry.stem,
            "status": "failed",
            "error": e if isinstance(e, str) else error_text(e),
            "wall_s": 0.0,
            "subject_wall_s": None,
            "worker": worker,
        }
        # a failed scan keeps no fit files of an earlier run (the table would disagree)
        files = scan_files(out, job.subject, entry.stem)
        files["record"].unlink(missing_ok=True)
        files["ply"].unlink(missing_ok=True)
        files["json"].unlink(missing_ok=True)
        write_record(out, rec)
        records[entry.stem] = rec
        _event(job.subject, entry.stem, "failed")

    if job.neutral is None:
        why = error_text(
            DataNotFoundError(
                f"subject {job.subject} has no neutral scan ({job.subject}_N_N_0.bnt, or a "
                "manifest's neutral column); its rig cannot be built."
            )
        )
        for entry in job.scans:
            fail(entry, why)
        return [records[e.stem] for e in job.scans]

    loaded: list[tuple[ScanEntry, object]] = []
    for entry in job.scans:
        try:
            loaded.append(
                (
                    entry,
                    load_fit_scan(
                        entry.path, entry.landmarks, "scan", settings.landmarks == "auto"
                    ),
                )
            )
        except Exception as e:  # noqa: BLE001 - one bad scan is a failed row, not a stop
            fail(entry, e)
    by_stem = {entry.stem: entry for entry, _ in loaded}
    staging = sdir / f"{STAGING_PREFIX}{uuid.uuid4().hex}"
    fitted: list[dict] = []
    subject = None

    def commit(result, files) -> None:
        entry = by_stem[result.stem]
        dst = scan_files(out, job.subject, entry.stem)
        # no record while the files change: a stop in between leaves an incomplete scan
        dst["record"].unlink(missing_ok=True)
        os.replace(files["ply"], dst["ply"])
        os.replace(files["json"], dst["json"])
        if "picture" in files:
            os.replace(files["picture"], sdir / Path(files["picture"]).name)
        rec = {
            "subject": job.subject,
            "code": entry.code,
            "scan": entry.stem,
            "status": "fitted",
            "error": "",
            "wall_s": None,
            "subject_wall_s": None,
            "worker": worker,
        }
        rec["subject_wall_s"] = time.perf_counter() - t0
        rec["wall_s"] = rec["subject_wall_s"] / max(len(loaded), 1)
        write_record(out, rec)
        records[entry.stem] = rec
        fitted.append(rec)
        _event(job.subject, entry.stem, "fitted")

    def fit(scans: list) -> None:
        fit_and_write(
            subject,
            scans,
            staging,
            options=settings.options,
            pictures=settings.pictures,
            batch_size=settings.batch_size,
            on_written=commit,
            arkit=settings.arkit,
        )

    try:
        if loaded:
            try:
                neutral = load_fit_scan(
                    job.neutral,
                    job.neutral_landmarks,
                    "neutral scan",
                    settings.landmarks == "auto",
                )
                subject = prepare_fit_subject(
                    neutral,
                    template=settings.template,
                    template_landmarks=settings.template_landmarks,
                    backend=settings.subject_options.backend,
                    subject_options=settings.subject_options,
                    cache=settings.subject_cache,
                )
            except Exception as e:  # noqa: BLE001 - recorded on every scan of the subject
                why = f"{error_text(e)} (building the rig of {job.subject} from {job.neutral.name})"
                for entry, _ in loaded:
                    fail(entry, why)
                loaded = []
            todo = [s for _, s in loaded]
            if todo:
                try:
                    fit(todo)
                except Exception:  # noqa: BLE001 - isolate the scan at fault below
                    for entry, scan in loaded:
                        if entry.stem in records:
                            continue
                        try:
                            fit([scan])
                        except Exception as e:  # noqa: BLE001
                            fail(entry, e)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    # the final per-scan share of the subject's time
    total = time.perf_counter() - t0
    for rec in fitted:
        rec["subject_wall_s"] = total
        rec["wall_s"] = total / len(fitted)
        write_record(out, rec)
    return [records[e.stem] for e in job.scans if e.stem in records]
