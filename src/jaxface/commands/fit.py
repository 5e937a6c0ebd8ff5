"""``jaxface fit``: muscle activations, jaw pose and FACS AU intensities from 3D scans.

Contract (other tools call it; keep it stable)::

    jaxface fit --neutral N.bnt --scan S.bnt [--scan S2.bnt ...]
                [--neutral-landmarks N.lm3] [--scan-landmarks S.lm3 ...]
                [--template FACE.ply --template-landmarks FACE.lm3] [--backend pbd|ltw]
                --out DIR [--pictures]

Landmark files default to the scan path with suffix ``.lm3``; a scan without one gets
detected landmarks (:mod:`jaxface.detect`, with a note), and ``--landmarks auto`` detects for
every scan without an explicit file. Several ``--scan`` options fit a
batch (solved together in one compiled call) with a progress bar. Per scan it writes
``DIR/<scan-stem>.json`` (keys: ``activations``, ``au_intensities`` (the fewest AUs that reproduce the fit's skin motion,
calibrated; ``au_intensity_letters`` their FACS letters A-E), ``au_from_activations``,
``au_motion_mm``, ``au_readout``, ``jaw``, ``rigid``,
``metrics``, ``baselines``, ``solver``, ``frame``, ``quality``: coverage, identity, noise
floor and warnings, :mod:`jaxface.fit.quality`; ``arkit``, ``arkit_detail``: the ARKit-52
readout, :mod:`jaxface.interop.arkit`; see :class:`jaxface.fit.pipeline.ExpressionFit`)
and ``DIR/<scan-stem>.fitted.ply`` (the fitted skin in the scan's own frame, mm); with
``--pictures`` also ``DIR/<scan-stem>.fit.png`` (scan, before, fit, error heat map).

Library functions used: :func:`jaxface.fit.pipeline.prepare_subject`,
:func:`jaxface.fit.pipeline.fit_expressions`. Units: mm, degrees.
"""

from __future__ import annotations

import time
import warnings
from enum import Enum
from pathlib import Path
from typing import List  # noqa: UP035 (typer options keep List[str], see UP006 below)

import typer

__all__ = ["register", "run_fit", "load_fit_scan", "prepare_fit_subject", "fit_and_write"]


def load_fit_scan(
    path: Path,
    landmarks: Path | None = None,
    what: str = "scan",
    auto: bool = False,
    notice=None,
):
    """Load a scan with its landmarks as ``jaxface fit`` does: the explicit ``.lm3``, or the
    one beside the scan; without either, or with ``auto`` and no explicit file, the landmarks
    are detected (:mod:`jaxface.detect`; ``notice(text)`` says so). A missing or unreadable
    input is a :class:`~jaxface.errors.InputPathError` / :class:`~jaxface.errors.DataNotFoundError`."""
    from ..io import load_scan
    from ..mesh import check_input_file
    from .landmarks import detect_for

    check_input_file(path, f"{what} file")
    if landmarks is not None:
        check_input_file(landmarks, f"landmark file of the {what}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scan = load_scan(path, landmarks=False if auto and landmarks is None else landmarks)
    _show_label_warnings(caught)
    if scan.landmarks is None:
        det = detect_for(scan, f"{what} {path.name}", notice)
        scan = scan.with_landmarks(det.landmarks, detected=True)
    return scan


def _show_label_warnings(caught) -> None:
    """Print the landmark-label warnings of a load (misspelled or unknown labels) on stderr;
    the other load warnings (missing ear lobes and the like) stay quiet."""
    from ..cli import console
    from ..landmarks import LandmarkLabelWarning

    for w in caught:
        if issubclass(w.category, LandmarkLabelWarning):
            console.print(f"[yellow]warning:[/] {w.message}", markup=True, soft_wrap=True)


def _template(template: Path | None, template_landmarks: Path | None):
    from ..errors import LandmarkError
    from ..landmarks import read_lm3
    from ..mesh import check_input_file, load_mesh

    if template is None:
        if template_landmarks is not None:
            raise LandmarkError("--template-landmarks needs --template (the mesh they belong to).")
        return None, None
    check_input_file(template, "template mesh")
    lm = template_landmarks if template_landmarks is not None else template.with_suffix(".lm3")
    if not lm.is_file():
        raise LandmarkError(
            f"the template {template} needs its landmarks: give --template-landmarks FACE.lm3 (no "
            f"{template.with_suffix('.lm3')} beside it)."
        )
    return load_mesh(template, validate=False), read_lm3(lm)


def run_fit(
    neutral: Path,
    scans: list[Path],
    out: Path,
    *,
    neutral_landmarks: Path | None = None,
    scan_landmarks: list[Path] | None = None,
    template: Path | None = None,
    template_landmarks: Path | None = None,
    backend: str = "pbd",
    pictures: bool = False,
    options=None,
    subject_options=None,
    batch_size: int | None = None,
    progress=None,
    on_step=None,
    on_written=None,
    arkit: object = "auto",
    landmarks: str = "file",
    notice=None,
    subject_cache: object = None,
) -> list:
    """The library behind ``jaxface fit``: fit ``scans`` of the subject of ``neutral`` and
    write the results into ``out``. Returns the :class:`~jaxface.fit.pipeline.ExpressionFit`
    list (in the order of ``scans``).

    Arguments:
        progress: optional ``(text) -> None`` for fine-grained messages.
        on_step: optional ``(text) -> None`` called before each major step.
        on_written: optional ``(ExpressionFit, files) -> None`` called after each scan's files
            are written.
        arkit: ICT data of the ARKit readout (``"auto"``, a path, None = off; see
            :func:`jaxface.fit.pipeline.fit_expressions`).
        landmarks: ``"file"`` (default): the given or beside-the-scan ``.lm3``, detected
            (:mod:`jaxface.detect`) for a scan that has none; ``"auto"``: detect for every scan
            without an explicitly given ``.lm3``.
        notice: optional ``(text) -> None`` told when landmarks are detected (default: a
            warning).
        subject_cache: the subject cache of :func:`jaxface.fit.subject.prepare_subject`
            (None: ``$JAXFACE_SUBJECT_CACHE``; ``"default"``; ``"off"``; a folder).
    """
    from ..atomic import ensure_out_dir
    from ..errors import FitError, LandmarkError
    from ..fit.pipeline import scan_stem

    if backend not in ("pbd", "ltw"):
        raise FitError(f"--backend {backend!r}: use 'pbd' or 'ltw'.")
    if not scans:
        raise FitError("give at least one --scan.")
    if scan_landmarks and len(scan_landmarks) != len(scans):
        raise LandmarkError(
            f"{len(scan_landmarks)} --scan-landmarks for {len(scans)} --scan: give one per scan, in the "
            "same order (or none, to use the .lm3 files beside the scans)."
        )
    ensure_out_dir(out)  # before the minute-long build: a bad --out fails at once
    if isinstance(arkit, (str, Path)) and arkit != "auto" and not Path(arkit).is_file():
        from ..errors import DataNotFoundError

        raise DataNotFoundError(f"--ict {arkit}: no such file (ICT-FaceKit ict_face.npz).")
    step = on_step or (lambda s: None)
    step("reading the scans")
    auto = landmarks == "auto"
    if landmarks not in ("file", "auto"):
        raise LandmarkError(f"--landmarks {landmarks!r}: use 'file' or 'auto'.")
    say = notice or (lambda s: warnings.warn(s, stacklevel=2))
    n_scan = load_fit_scan(neutral, neutral_landmarks, "neutral scan", auto, say)
    loaded = [
        load_fit_scan(p, scan_landmarks[i] if scan_landmarks else None, "scan", auto, say)
        for i, p in enumerate(scans)
    ]
    stems = [scan_stem(s) for s in loaded]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise FitError(
            f"several --scan files share the stem(s) {dup}; their outputs would overwrite each other."
        )
    step("building the subject's rig (registration, skull, muscles, reduced model)")
    subject = prepare_fit_subject(
        n_scan,
        template=template,
        template_landmarks=template_landmarks,
        backend=backend,
        subject_options=subject_options,
        progress=progress,
        cache=subject_cache,
    )
    step(f"fitting {len(loaded)} scan(s)")
    return fit_and_write(
        subject,
        loaded,
        out,
        options=options,
        pictures=pictures,
        batch_size=batch_size,
        progress=progress,
        on_written=on_written,
        arkit=arkit,
    )


def prepare_fit_subject(
    neutral,
    *,
    template: Path | None = None,
    template_landmarks: Path | None = None,
    backend: str = "pbd",
    subject_options=None,
    progress=None,
    cache: object = None,
):
    """The subject of ``jaxface fit``: its rig built once from the loaded ``neutral`` scan
    (:func:`load_fit_scan`) on ``template`` (default: the built-in head); returns the
    :class:`~jaxface.fit.pipeline.Subject` that :func:`fit_and_write` fits scans with.
    ``cache``: the subject cache (:func:`jaxface.fit.subject.prepare_subject`)."""
    from ..fit.pipeline import SubjectOptions, prepare_subject

    tmesh, tlm = _template(template, template_landmarks)
    sopt = subject_options or SubjectOptions(backend=backend)
    if sopt.backend != backend:
        from dataclasses import replace

        sopt = replace(sopt, backend=backend)
    return prepare_subject(
        neutral,
        template=tmesh,
        template_landmarks=tlm,
        options=sopt,
        progress=progress,
        cache=cache,
    )


def fit_and_write(
    subject,
    loaded: list,
    out: Path,
    *,
    options=None,
    pictures: bool = False,
    batch_size: int | None = None,
    progress=None,
    on_written=None,
    arkit: object = "auto",
) -> list:
    """Fit the loaded scans of ``subject`` (:func:`prepare_fit_subject`) as ``jaxface fit``
    does (one batch, or ``batch_size`` at a time) and write each scan's ``<stem>.json`` and
    ``<stem>.fitted.ply`` into ``out``; ``on_written(ExpressionFit, files)`` after each.
    ``arkit``: the ARKit readout's ICT data (:func:`jaxface.fit.pipeline.fit_expressions`).
    Every call also fits the neutral to itself once, for the AU readout's noise floor.
    Returns the :class:`~jaxface.fit.pipeline.ExpressionFit` list in the order of ``loaded``."""
    from ..atomic import ensure_out_dir
    from ..fit.options import FitOptions
    from ..fit.pipeline import fit_expressions

    ensure_out_dir(out)
    results = fit_expressions(
        subject,
        loaded,
        options=options or FitOptions(),
        progress=progress,
        batch_size=batch_size,
        on_result=lambda r: _write(r, out, pictures, on_written),
        noise_floor=True,  # one self-fit of the neutral: the AU readout's noise floor
        arkit=arkit,
    )
    return results


def _write(result, out: Path, pictures: bool, on_written) -> None:
    files = result.write(out, pictures=pictures)
    if on_written is not None:
        on_written(result, files)


class RestartWhen(str, Enum):
    """``--restart-when``: which fits with activations at 1 restart (``FitOptions.restart_when``)."""

    unconverged = "unconverged"
    saturated = "saturated"


def register(app: typer.Typer) -> None:
    """Add ``jaxface fit`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors
    from . import options

    @app.command(epilog=_EPILOG)
    @handle_errors
    def fit(
        neutral: Path = typer.Option(
            ..., "--neutral", "-n", help="The subject's neutral scan (.bnt, .ply, .obj)."
        ),
        scan: List[Path] = typer.Option(  # noqa: UP006
            ..., "--scan", "-s", help="Expression scan(s) of the same subject; repeat for a batch."
        ),
        out: Path = options.out_dir(),
        neutral_landmarks: Path | None = typer.Option(  # noqa: UP007
            None, "--neutral-landmarks", help="Neutral .lm3 (default: beside the neutral scan)."
        ),
        scan_landmarks: List[Path] | None = typer.Option(  # noqa: UP006, UP007
            None,
            "--scan-landmarks",
            help="Scan .lm3, one per --scan in the same order (default: beside each scan).",
        ),
        template: Path | None = options.template(),  # noqa: UP007
        template_landmarks: Path | None = options.template_landmarks(),  # noqa: UP007
        backend: str = options.backend(),
        landmarks: str = options.landmarks_mode(),
        pictures: bool = typer.Option(
            False, "--pictures", help="Also write a before/after picture per scan."
        ),
        points: int = typer.Option(1000, "--points", min=100, help="Scan points per fit."),
        motion_fraction: float = typer.Option(
            0.5,
            "--motion-fraction",
            min=0.0,
            max=1.0,
            help="Share of the scan points drawn from where the expression moves the skin (farther "
            "than FitOptions.motion_threshold_mm, 0.3 mm, from the registered neutral); the rest "
            "evenly. 0 = all evenly.",
        ),
        outer_iterations: int = typer.Option(
            6,
            "--outer-iterations",
            min=1,
            help="Correspondence refreshes (one exact rig synthesis and one "
            "reverse pass through the rig each).",
        ),
        extra_iterations: int = typer.Option(
            6,
            "--extra-iterations",
            min=0,
            help="At most this many more outer iterations for a scan still converging: its cost still "
            "falls by more than 1 % per iteration while its activations or jaw still move (each "
            "scan stops on its own; one still converging after them is reported as "
            "outer_not_converged).",
        ),
        max_steps: int = typer.Option(
            40, "--max-steps", min=1, help="Levenberg-Marquardt steps per inner solve."
        ),
        exact_steps: int = typer.Option(
            0,
            "--exact-steps",
            min=0,
            help="Final LM steps through the exact rig (slow: a rig Jacobian each).",
        ),
        restart_iterations: int = typer.Option(
            2,
            "--restart-iterations",
            min=0,
            help="Bound-flip restart: a fit with activations at 1 (see --restart-when) is fitted again "
            "for this many outer iterations with them back near 0; the lower cost wins (0 = off).",
        ),
        restart_when: RestartWhen = typer.Option(
            RestartWhen.unconverged,
            "--restart-when",
            help="Which fits with activations at 1 restart: 'unconverged' (only those that did not "
            "converge, the trap's signature) or 'saturated' (all of them; slower).",
        ),
        au_sparse_weight: float = typer.Option(
            0.02,
            "--au-sparse-weight",
            min=0.0,
            help="L1 weight of the AU readout (au_intensities in the JSON: the fewest AUs that "
            "reproduce the fit's skin motion; mm^2 of mean squared motion per unit intensity; "
            "0 = plain least squares). It reads the fit and does not change it.",
        ),
        au_min_motion: float = typer.Option(
            0.05,
            "--au-min-motion",
            min=0.0,
            help="An AU whose removal moves the readout's skin motion by less than this (mm, RMS) "
            "is not reported. It reads the fit and does not change it.",
        ),
        levels: int = typer.Option(
            4, "--levels", min=1, help="Activation knots of the rig's reduced model."
        ),
        pitch_knots: int = typer.Option(
            12, "--pitch-knots", min=3, help="Jaw pitch knots of the reduced model."
        ),
        batch_size: int | None = typer.Option(  # noqa: UP007
            None,
            "--batch-size",
            min=1,
            help="Scans fitted together (one after the other on the CPU, one vmap on a GPU); default all.",
        ),
        ict: Path | None = options.ict(),  # noqa: UP007
        no_arkit: bool = options.no_arkit(),
        subject_cache: str = typer.Option(
            "default",
            "--subject-cache",
            envvar="JAXFACE_SUBJECT_CACHE",
            metavar="DIR|default|off",
            help="Folder that keeps each neutral's registration, rig and reduced model for the "
            "next run on the same neutral (default ~/.cache/jaxface/subjects, at most 4 GiB); "
            "'off' builds without it.",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Fit muscle activations, jaw pose and a rigid correction to expression scans of one
        subject; report FACS AU intensities, fit metrics (mm) and the B0/B1 baselines.

        Writes OUT/<scan-stem>.json and OUT/<scan-stem>.fitted.ply (the fitted skin in the
        scan's own frame, mm) per scan, plus OUT/<scan-stem>.fit.png with --pictures.

        \b
        Examples:
          jaxface fit --neutral bs000_N_N_0.bnt --scan bs000_LFAU_12_0.bnt --out fits
          jaxface fit -n N.bnt -s A.bnt -s B.bnt -s C.bnt -o fits --pictures
          jaxface fit -n N.ply --neutral-landmarks N.lm3 -s S.ply --scan-landmarks S.lm3 -o fits
        """
        import jax
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )
        from rich.table import Table

        # the fit runs in float64: Levenberg-Marquardt tolerances, second differences of the
        # reduced model and sub-0.1 mm residuals need it (the library follows the dtype)
        jax.config.update("jax_enable_x64", True)

        from ..facs import intensity_letter
        from ..fit.options import FitOptions
        from ..fit.pipeline import SubjectOptions

        opts = FitOptions(
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
        )
        sopts = SubjectOptions(backend=backend, levels=levels, pitch_knots=pitch_knots)
        t0 = time.perf_counter()
        prog = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("{task.fields[info]}"),
            console=console,
            disable=quiet,
            transient=False,
        )
        # the batches' annealed outer iterations and the neutral's self-fit (noise floor)
        n_batches = (len(scan) + (batch_size or len(scan)) - 1) // (batch_size or len(scan))
        n_fit = outer_iterations * (n_batches + 1)
        written = [0]
        with prog:
            t_main = prog.add_task("jaxface fit", total=4 + n_fit + len(scan), info="")

            def on_step(text):
                prog.update(t_main, advance=1, info=text)

            def on_progress(text):
                task = prog.tasks[t_main]
                # extra iterations of unconverged scans are not counted ahead: the bar keeps
                # room for the writes and never runs past its total
                room = (task.total or 0) - (len(scan) - written[0]) - task.completed
                if text.startswith("outer iteration") and room > 0:
                    prog.update(t_main, advance=1, info=text)
                else:
                    prog.update(t_main, info=text)

            def done(r, files):
                written[0] += 1
                prog.update(t_main, advance=1, info=f"wrote {Path(files['json']).name}")

            results = run_fit(
                neutral,
                list(scan),
                out,
                neutral_landmarks=neutral_landmarks,
                scan_landmarks=list(scan_landmarks) if scan_landmarks else None,
                template=template,
                template_landmarks=template_landmarks,
                backend=backend,
                pictures=pictures,
                options=opts,
                subject_options=sopts,
                batch_size=batch_size,
                progress=on_progress,
                on_step=on_step,
                on_written=done,
                arkit=None if no_arkit else (ict if ict is not None else "auto"),
                landmarks=landmarks,
                notice=lambda text: console.print(f"[cyan]note:[/] {text}", markup=True),
                subject_cache=subject_cache,
            )
        for r in results:  # shown even with --quiet: the result may be meaningless
            q = getattr(r, "quality", None)
            for w in q.warnings if q is not None else ():
                console.print(f"[yellow]warning:[/] {r.stem}: {w}", markup=True, soft_wrap=True)
        if quiet:
            return
        table = Table(
            title=f"jaxface fit: {len(results)} scan(s) -> {out} ({time.perf_counter() - t0:.1f} s)"
        )
        table.add_column("scan", no_wrap=True)
        for col in ("status", "scan->fit mm", "B0 mm", "B1 mm", "pitch deg"):
            table.add_column(col, justify="right")
        table.add_column("AUs (intensity, FACS letter)")
        table.add_column("most visible AUs (skin motion, mm)")
        for r in results:
            aus = ", ".join(
                f"{k} {v:.2f} {intensity_letter(v) or '-'}"
                for k, v in r.strongest_aus(3, sided=True)
            )
            vis = ", ".join(f"{k} {v:.2f}" for k, v in r.strongest_aus(3, by="motion", sided=True))
            table.add_row(
                r.stem,
                r.status if r.status == "successful" else f"[yellow]{r.status}[/]",
                f"{r.metrics.scan_to_fit['all'].mean:.3f}",
                f"{r.baselines['B0'].scan_to_fit['all'].mean:.3f}",
                f"{r.baselines['B1'].scan_to_fit['all'].mean:.3f}",
                f"{r.jaw['pitch_deg']:.1f}",
                aus or "none",
                vis,
            )
        console.print(table)
        bad = [r.stem for r in results if r.status != "successful"]
        if bad:
            console.print(
                f"[yellow]warning:[/] the last inner solve did not meet its tolerance for {', '.join(bad)} "
                "(see solver.status / solver.outer_iterations in the JSON).",
                markup=True,
            )
