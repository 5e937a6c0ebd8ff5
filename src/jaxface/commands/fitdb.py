"""``jaxface fit-db``: fit a whole database on Dask distributed, resumable, into one table.

Contract::

    jaxface fit-db ROOT --out DIR [--workers N] [--threads-per-worker T]
                   [--scheduler tcp://HOST:PORT] [--gpus auto|none|0,1,...]
                   [--resume/--no-resume] [--retries R] [jaxface fit's fit options]
    jaxface fit-db --summary DIR

ROOT: a Bosphorus folder (a folder per subject, or a flat folder of ``bsNNN_<class>_<code>_<n>
.bnt`` with their ``.lm3``) or a CSV manifest (columns subject, neutral, scan). Per scan:
``DIR/<subject>/<stem>.json`` and ``<stem>.fitted.ply`` as ``jaxface fit`` writes them, and
``<stem>.fitdb.json`` (the run record); the table ``DIR/results.parquet``. The fit options
are ``jaxface fit``'s, with its defaults. Library: :mod:`jaxface.fitdb`; docs/fit-db.md.
"""

from __future__ import annotations

import time
from pathlib import Path

import typer

from .fit import RestartWhen

__all__ = ["register"]


def _gpus(value: str) -> tuple[str, ...]:
    from ..errors import JaxfaceError
    from ..fitdb.runner import detect_gpus

    v = value.strip().lower()
    if v == "auto":
        return detect_gpus()
    if v in ("none", "off", "0", ""):
        return ()
    ids = tuple(d.strip() for d in value.split(",") if d.strip())
    if not all(d.isdigit() for d in ids):
        raise JaxfaceError(f"--gpus {value!r}: give auto, none, or device ids such as 0,1,2.")
    return ids


def _print_summary(console, directory: Path) -> None:
    from rich.table import Table

    from ..fitdb.table import read_table, summarise

    tab = read_table(directory)
    summary = summarise(tab)
    out = Table(title=f"jaxface fit-db: {tab.num_rows} scan(s) in {directory}")
    out.add_column("code", no_wrap=True)
    for col in ("scans", "fitted", "failed", "scan->fit mm", "B0 mm", "B1 mm"):
        out.add_column(col, justify="right")
    out.add_column("AU means (strongest, bilateral)")

    def mm(v):
        return "-" if v is None else f"{v:.3f}"

    for s in summary:
        out.add_row(
            s["code"],
            str(s["scans"]),
            str(s["fitted"]),
            f"[red]{s['failed']}[/]" if s["failed"] else "0",
            mm(s["scan_to_fit_mm"]),
            mm(s["b0_mm"]),
            mm(s["b1_mm"]),
            ", ".join(f"{k} {v:.2f}" for k, v in s["aus"]),
        )
    console.print(out)


def register(app: typer.Typer) -> None:
    """Add ``jaxface fit-db`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors
    from . import options

    @app.command("fit-db", epilog=_EPILOG)
    @handle_errors
    def fit_db(
        root: Path | None = typer.Argument(  # noqa: UP007
            None,
            help="The database: a Bosphorus folder (folder per subject, or flat) or a CSV "
            "manifest with columns subject, neutral, scan.",
        ),
        out: Path | None = typer.Option(  # noqa: UP007
            None, "--out", "-o", file_okay=False, help="Output folder (created if missing)."
        ),
        summary: Path | None = typer.Option(  # noqa: UP007
            None,
            "--summary",
            file_okay=False,
            help="Print the summary per expression code of DIR/results.parquet and exit.",
        ),
        workers: int | None = typer.Option(  # noqa: UP007
            None,
            "--workers",
            "-w",
            min=1,
            help="Worker processes of the embedded cluster (default: one per GPU, else the core "
            "count / 2, at least 1).",
        ),
        threads_per_worker: int = typer.Option(
            1, "--threads-per-worker", min=1, help="Dask threads per worker process."
        ),
        scheduler: str | None = typer.Option(  # noqa: UP007
            None,
            "--scheduler",
            metavar="tcp://HOST:PORT",
            help="Use a running Dask scheduler instead of the embedded cluster.",
        ),
        gpus: str = typer.Option(
            "auto",
            "--gpus",
            help="GPUs of the embedded cluster, one worker process each: auto (CUDA_VISIBLE_DEVICES "
            "or nvidia-smi), none, or ids such as 0,1.",
        ),
        resume: bool | None = typer.Option(  # noqa: UP007
            None,
            "--resume/--no-resume",
            help="Skip the scans that are done: outputs complete, or failed before (default "
            "when DIR exists); --no-resume fits every scan again.",
        ),
        retry_failed: bool = typer.Option(
            False,
            "--retry-failed",
            help="With resume, also fit the scans that failed before (default: a failed scan "
            "is done; its row keeps the error).",
        ),
        retries: int = typer.Option(
            1,
            "--retries",
            min=0,
            help="Runs of a subject again after its worker process died; then its scans are "
            "failed rows.",
        ),
        template: Path | None = options.template(),  # noqa: UP007
        template_landmarks: Path | None = options.template_landmarks(),  # noqa: UP007
        backend: str = options.backend(),
        landmarks: str = options.landmarks_mode(),
        ict: Path | None = options.ict(),  # noqa: UP007
        no_arkit: bool = options.no_arkit(),
        pictures: bool = typer.Option(False, "--pictures", help="Also write a picture per scan."),
        points: int = typer.Option(1000, "--points", min=100, help="Scan points per fit."),
        motion_fraction: float = typer.Option(
            0.5, "--motion-fraction", min=0.0, max=1.0, help="As jaxface fit."
        ),
        outer_iterations: int = typer.Option(
            6, "--outer-iterations", min=1, help="As jaxface fit."
        ),
        extra_iterations: int = typer.Option(
            6, "--extra-iterations", min=0, help="As jaxface fit."
        ),
        max_steps: int = typer.Option(40, "--max-steps", min=1, help="As jaxface fit."),
        exact_steps: int = typer.Option(0, "--exact-steps", min=0, help="As jaxface fit."),
        restart_iterations: int = typer.Option(
            2, "--restart-iterations", min=0, help="As jaxface fit."
        ),
        restart_when: RestartWhen = typer.Option(
            RestartWhen.unconverged, "--restart-when", help="As jaxface fit."
        ),
        au_sparse_weight: float = typer.Option(
            0.02, "--au-sparse-weight", min=0.0, help="As jaxface fit."
        ),
        au_min_motion: float = typer.Option(
            0.05, "--au-min-motion", min=0.0, help="As jaxface fit."
        ),
        levels: int = typer.Option(4, "--levels", min=1, help="As jaxface fit."),
        pitch_knots: int = typer.Option(12, "--pitch-knots", min=3, help="As jaxface fit."),
        batch_size: int | None = typer.Option(  # noqa: UP007
            None, "--batch-size", min=1, help="As jaxface fit (default: a subject's scans)."
        ),
        subject_cache: str = typer.Option(
            "default",
            "--subject-cache",
            envvar="JAXFACE_SUBJECT_CACHE",
            metavar="DIR|default|off",
            help="As jaxface fit: a resumed run loads the subjects it built.",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Fit every expression scan of a database, one Dask task per subject (its rig built
        once, its scans fitted as one batch, as `jaxface fit` does), into DIR/<subject>/ and
        one table DIR/results.parquet. Resumable; a failed scan is a row with its error.

        The fit options are jaxface fit's (see `jaxface fit --help`), with its defaults.

        \b
        Examples:
          jaxface fit-db BosphorusDB --out fits
          jaxface fit-db BosphorusDB --out fits --workers 4 --points 600
          jaxface fit-db scans.csv --out fits --scheduler tcp://10.0.0.5:8786
          jaxface fit-db --summary fits
        """
        from ..errors import JaxfaceError

        if summary is not None:
            if root is not None or out is not None:
                raise JaxfaceError("--summary DIR prints a finished table: give no ROOT or --out.")
            _print_summary(console, summary)
            return
        if root is None or out is None:
            raise JaxfaceError(
                "give the database and the output folder: jaxface fit-db ROOT --out DIR "
                "(or jaxface fit-db --summary DIR)."
            )
        if out.exists() and not out.is_dir():
            raise JaxfaceError(f"--out {out} exists and is not a folder.")
        if backend not in ("pbd", "ltw"):
            raise JaxfaceError(f"--backend {backend!r}: use 'pbd' or 'ltw'.")

        import jax
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        from ..fit.options import FitOptions
        from ..fit.pipeline import SubjectOptions
        from ..fitdb.discover import discover_database
        from ..fitdb.runner import ClusterSpec, run_database
        from ..fitdb.task import FitSettings

        do_resume = out.is_dir() if resume is None else resume
        if landmarks not in ("file", "auto"):
            from ..errors import LandmarkError

            raise LandmarkError(f"--landmarks {landmarks!r}: use 'file' or 'auto'.")
        if ict is not None and not no_arkit and not ict.is_file():
            from ..errors import DataNotFoundError

            raise DataNotFoundError(f"--ict {ict}: no such file (ICT-FaceKit ict_face.npz).")
        settings = FitSettings(
            options=FitOptions(
                n_points=points,
                motion_fraction=motion_fraction,
                outer_iterations=outer_iterations,
                extra_iterations=extra_iterations,
                max_steps=max_steps,
                exact_steps=exact_steps,
                restart_iterations=restart_iterations,
                restart_when=RestartWhen(restart_when).value,
                au_sparse_weight=au_sparse_weight,
                au_min_motion_mm=au_min_motion,
            ),
            subject_options=SubjectOptions(backend=backend, levels=levels, pitch_knots=pitch_knots),
            template=template,
            template_landmarks=template_landmarks,
            pictures=pictures,
            batch_size=batch_size,
            landmarks=landmarks,
            arkit=None if no_arkit else (ict if ict is not None else "auto"),
            subject_cache=subject_cache,
        )
        # the workers use the compile cache this process was given (--compile-cache)
        cache = getattr(jax.config, "jax_compilation_cache_dir", None)
        spec = ClusterSpec(
            scheduler=scheduler,
            workers=workers,
            threads_per_worker=threads_per_worker,
            gpus=() if scheduler else _gpus(gpus),
            compile_cache=str(cache) if cache else "off",
            retries=retries,
        )
        jobs = discover_database(root)
        t0 = time.perf_counter()
        prog = Progress(
            TextColumn("[bold]jaxface fit-db"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("[green]{task.fields[ok]} fitted[/] [red]{task.fields[bad]} failed[/]"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            console=console,
            disable=quiet,
        )
        state = {"task": None, "ok": 0, "bad": 0}

        def on_start(report, n):
            if not quiet:
                where = scheduler or f"LocalCluster, {len(report.workers)} worker process(es)"
                console.print(
                    f"{report.scans} scan(s) of {len(jobs)} subject(s); {report.skipped} done "
                    f"already, {n} to fit on {where}"
                    + (f"; dashboard {report.dashboard}" if report.dashboard else "")
                )
            state["task"] = prog.add_task("fit", total=n, ok=0, bad=0)

        def on_scan(subject, stem, status):
            state["ok" if status == "fitted" else "bad"] += 1
            if state["task"] is not None:
                prog.update(state["task"], advance=1, ok=state["ok"], bad=state["bad"])

        with prog:
            report = run_database(
                jobs,
                out,
                settings,
                spec,
                resume=do_resume,
                retry_failed=retry_failed,
                on_start=on_start,
                on_scan=on_scan,
            )
        if quiet:
            return
        console.print(
            f"fitted {report.fitted}, failed {report.failed}, skipped {report.skipped} (done before), "
            f"pending {report.pending} of {report.scans} scan(s) in {time.perf_counter() - t0:.1f} s; "
            f"table {report.table}"
        )
        if report.failed:
            console.print(
                f"[yellow]warning:[/] {report.failed} scan(s) failed: see the error column "
                f"(jaxface fit-db --summary {out}); --retry-failed fits them again.",
                markup=True,
            )
