"""Run ``jaxface fit-db`` on Dask distributed: one task per subject, resumable.

:func:`run_database` decides what is left to fit (``resume``: the scans without complete
outputs, :func:`jaxface.fitdb.outputs.is_complete`), starts an embedded
:class:`distributed.LocalCluster` with worker *processes* (started with ``spawn``: a worker
never forks a process that has imported JAX) or connects to a running scheduler, registers
:class:`~jaxface.fitdb.plugin.JaxWorkerSetup` (float64, compile cache, one GPU per worker),
submits :func:`jaxface.fitdb.task.fit_subject` per subject, and rebuilds
``DIR/results.parquet`` from the per-scan files at the end, also after a Ctrl-C.

A worker that dies (a crash, the out-of-memory killer) takes its running task with it; the
scheduler runs it again on another worker until ``retries`` workers died running it
(``distributed.scheduler.allowed-failures``; set for the embedded cluster; a running
scheduler keeps its own setting), then its scans become failed rows
(``KilledWorker: ...``). An exception escaping the task (it records the fits' own errors
itself) is retried as often with Dask's ``retries``.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import dask.config
from distributed import Client, LocalCluster, as_completed

from .discover import SubjectJob
from .outputs import is_complete, is_done, remove_stale, write_record
from .plugin import JaxWorkerSetup
from .table import build_rows, write_table
from .task import EVENT_TOPIC, FitSettings, error_text, fit_subject

__all__ = ["ClusterSpec", "RunReport", "detect_gpus", "pending_jobs", "run_database"]


@dataclass(frozen=True)
class ClusterSpec:
    """Where the tasks run.

    Attributes:
        scheduler: ``tcp://HOST:PORT`` of a running Dask scheduler, or None for an embedded
            LocalCluster of ``workers`` worker processes with ``threads_per_worker`` threads.
        workers: worker processes (None: one per GPU, else the core count / 2, at least 1).
        threads_per_worker: Dask threads per worker (1: one subject at a time per JAX
            process, which then uses all its cores).
        gpus: device ids for the embedded cluster's workers (:func:`detect_gpus`), one per
            worker, round-robin; empty: none.
        compile_cache: the workers' XLA compile cache folder, ``"default"`` or ``"off"``.
        retries: how often a subject runs again after its worker died (or it raised).
    """

    scheduler: str | None = None
    workers: int | None = None
    threads_per_worker: int = 1
    gpus: tuple[str, ...] = ()
    compile_cache: str | None = "off"
    retries: int = 1

    def n_workers(self) -> int:
        if self.workers is not None:
            return max(1, int(self.workers))
        if self.gpus:
            return len(self.gpus)
        return max(1, (os.cpu_count() or 2) // 2)


@dataclass
class RunReport:
    """What a run did. ``fitted``/``failed``: scans this run fitted or recorded as failed;
    ``skipped``: done before the run (complete, or failed without ``retry_failed``); ``pending``: not run (interrupted); ``table``: the
    results table; ``dashboard``: the Dask dashboard address, if there is one."""

    scans: int = 0
    fitted: int = 0
    failed: int = 0
    skipped: int = 0
    pending: int = 0
    subjects_run: int = 0
    wall_s: float = 0.0
    table: Path | None = None
    dashboard: str | None = None
    workers: list[str] = field(default_factory=list)
    interrupted: bool = False


def detect_gpus() -> tuple[str, ...]:
    """The visible NVIDIA GPUs, without starting JAX: the ``CUDA_VISIBLE_DEVICES`` entries if
    it is set, else the ``nvidia-smi -L`` indices; empty where there is none."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return tuple(d.strip() for d in env.split(",") if d.strip() and d.strip() != "-1")
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return ()
    try:
        out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return ()
    return tuple(
        str(i) for i, line in enumerate(l for l in out.splitlines() if l.startswith("GPU"))
    )


def pending_jobs(
    jobs: Sequence[SubjectJob], out: Path, resume: bool, retry_failed: bool = False
) -> tuple[list[SubjectJob], int]:
    """The jobs with only the scans left to fit (``resume``: those not done,
    :func:`~jaxface.fitdb.outputs.is_done`; otherwise all), subjects with none dropped; and
    the number of scans skipped."""
    todo, skipped = [], 0
    for job in jobs:
        left = tuple(
            e
            for e in job.scans
            if not (resume and is_done(out, job.subject, e.stem, retry_failed=retry_failed))
        )
        skipped += len(job.scans) - len(left)
        if left:
            todo.append(SubjectJob(job.subject, job.neutral, left, job.neutral_landmarks))
    return todo, skipped


#: Dask settings of a run (the whole run: some are read when used). A subject's task holds
#: its worker busy for minutes (compiling, fitting) and a loaded machine answers slowly: the
#: defaults (30 s without an answer on a connection, 5 minutes without a heartbeat) took
#: busy workers for dead ones and removed them.
DASK_CONFIG = {
    "distributed.comm.timeouts.connect": "120s",
    "distributed.comm.timeouts.tcp": "600s",
    "distributed.scheduler.worker-ttl": None,
    # a worker process never forks a parent that imported JAX
    "distributed.worker.multiprocessing-method": "spawn",
    # one subject per worker thread at a time (subjects are long; keep the rest queued)
    "distributed.scheduler.worker-saturation": 1.0,
}


def _start_client(spec: ClusterSpec) -> tuple[Client, LocalCluster | None]:
    if spec.scheduler:
        return Client(spec.scheduler), None
    # the dashboard needs bokeh; without it, no dashboard (and no warning about it)
    dash: dict = (
        {} if importlib.util.find_spec("bokeh") is not None else {"dashboard_address": None}
    )
    cluster = LocalCluster(
        n_workers=spec.n_workers(),
        threads_per_worker=spec.threads_per_worker,
        processes=True,
        silence_logs=logging.ERROR,
        **dash,
    )
    return Client(cluster), cluster


def run_database(
    jobs: Sequence[SubjectJob],
    out: Path,
    settings: FitSettings,
    cluster: ClusterSpec,
    *,
    resume: bool = True,
    retry_failed: bool = False,
    on_start: Callable[[RunReport, int], None] | None = None,
    on_scan: Callable[[str, str, str], None] | None = None,
) -> RunReport:
    """Fit the database ``jobs`` into ``out`` and write ``out/results.parquet``.

    Arguments:
        resume: skip the scans that are done (complete, or failed before); False fits every
            scan again.
        retry_failed: with ``resume``, fit the scans that failed before again too.
        on_start: ``(report, n_to_fit)`` once the cluster is up (``report.dashboard`` set).
        on_scan: ``(subject, stem, status)`` as each scan is written (``fitted``/``failed``),
            from the workers' events; also for the scans of a subject whose task was lost.

    Returns:
        the :class:`RunReport`. A KeyboardInterrupt stops the run: the tasks are cancelled,
        the embedded cluster closed, the table rebuilt from the complete outputs, and the
        interrupt raised again (the report is lost; the files are what counts).
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_stale(out)
    todo, skipped = pending_jobs(jobs, out, resume, retry_failed)
    report = RunReport(scans=sum(len(j.scans) for j in jobs), skipped=skipped)
    if settings.template is not None:
        settings = _absolute(settings)
    if todo:
        try:
            _run(todo, out, settings, cluster, report, on_start, on_scan)
        except KeyboardInterrupt:
            # only complete outputs are left (atomic renames); the table lists what is done
            write_table(out, build_rows(out, jobs))
            raise
    elif on_start is not None:
        on_start(report, 0)
    rows = build_rows(out, jobs)
    report.table = write_table(out, rows)
    report.pending = sum(r["status"] == "pending" for r in rows)
    report.wall_s = time.perf_counter() - t0
    return report


def _absolute(settings: FitSettings) -> FitSettings:
    tl = settings.template_landmarks
    return replace(
        settings,
        template=Path(settings.template).resolve() if settings.template else None,
        template_landmarks=Path(tl).resolve() if tl else None,
    )


def _run(todo, out, settings, cluster, report, on_start, on_scan) -> None:
    config = dict(DASK_CONFIG)
    config["distributed.scheduler.allowed-failures"] = cluster.retries
    with dask.config.set(config):
        _run_configured(todo, out, settings, cluster, report, on_start, on_scan)


def _run_configured(todo, out, settings, cluster, report, on_start, on_scan) -> None:
    n_scans = sum(len(j.scans) for j in todo)
    client, local = _start_client(cluster)
    seen: set[tuple[str, str]] = set()

    def event(ev) -> None:
        # ev = (timestamp, {"subject", "scan", "status"})
        msg = ev[1] if isinstance(ev, tuple) else ev
        key = (msg.get("subject"), msg.get("scan"))
        if key in seen:
            return
        seen.add(key)
        if on_scan is not None:
            on_scan(msg["subject"], msg["scan"], msg["status"])

    try:
        client.register_plugin(JaxWorkerSetup(cluster.compile_cache, cluster.gpus))
        info = client.scheduler_info()
        report.workers = sorted(str(w.get("name", a)) for a, w in info.get("workers", {}).items())
        if "dashboard" in info.get("services", {}):
            report.dashboard = client.dashboard_link
        client.subscribe_topic(EVENT_TOPIC, event)
        if on_start is not None:
            on_start(report, n_scans)
        futures = {
            client.submit(
                fit_subject,
                job,
                settings,
                str(out.resolve()),
                key=f"fit-subject-{job.subject}",
                retries=cluster.retries,
                pure=False,
            ): job
            for job in todo
        }
        report.subjects_run = len(futures)
        for fut in as_completed(futures):
            job = futures[fut]
            try:
                records = fut.result()
            except Exception as e:  # noqa: BLE001 - a lost task fails its unfinished scans
                records = _fail_lost(out, job, e, cluster.retries)
            for rec in records:
                if rec["status"] == "fitted":
                    report.fitted += 1
                else:
                    report.failed += 1
                if on_scan is not None:
                    event(
                        (
                            0.0,
                            {"subject": job.subject, "scan": rec["scan"], "status": rec["status"]},
                        )
                    )
    except KeyboardInterrupt:
        report.interrupted = True
        raise
    finally:
        try:
            client.unsubscribe_topic(EVENT_TOPIC)
        except Exception:  # noqa: BLE001 - closing anyway
            pass
        client.close()
        if local is not None:
            local.close()
        if report.interrupted and local is not None:
            # the embedded cluster's workers are gone: their staging files are stale now
            remove_stale(out)


def _fail_lost(out: Path, job: SubjectJob, e: BaseException, retries: int) -> list[dict]:
    """Records for a subject whose task was lost (its worker died, or it raised, ``retries``
    + 1 times): the scans it completed stay fitted, the others fail with the reason."""
    records = []
    why = f"{error_text(e)} (the subject's task was lost {retries + 1} times)"
    for entry in job.scans:
        if is_complete(out, job.subject, entry.stem):
            records.append({"scan": entry.stem, "status": "fitted"})
            continue
        rec = {
            "subject": job.subject,
            "code": entry.code,
            "scan": entry.stem,
            "status": "failed",
            "error": why,
            "wall_s": 0.0,
            "subject_wall_s": None,
            "worker": "",
        }
        write_record(out, rec)
        records.append(rec)
    return records
