"""``jaxface clone``: facial motion cloning (thesis chapter 6) from files.

Library functions used (:mod:`jaxface.clone`): :func:`~jaxface.clone.fit_source_to_target`
(landmark RBF, contours, correspondence refinement), :func:`~jaxface.clone.map_onto_surface`
(target vertices on the deformed source) and :func:`~jaxface.clone.apply_clone` (one morph
target at a time, so that a progress bar runs over the targets). Together they do exactly
what :func:`jaxface.clone.clone_motion` does.

Inputs are meshes (``.ply``/``.obj``; the target may also be a ``.bnt`` range scan, meshed on
reading) with ``.lm3`` landmarks beside them (same stem) or given explicitly, in the units
given by ``--source-units`` / ``--target-units`` (converted to mm inside). Every source morph
target must have the source neutral's vertex count and order.

Outputs, in ``--out``: one mesh per source morph target (``<name>.<format>``, the target's
topology, in ``--out-units``) and ``clone.json`` (the correspondences, iterations, timings and
per-target displacement statistics, in mm).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import List  # noqa: UP035 (typer options keep List[str], see UP006 below)

import numpy as np
import typer

from . import Units

__all__ = ["register", "load_face", "collect_targets"]

_MESHES = (".ply", ".obj")


def load_face(
    path: Path,
    units: str,
    landmarks: Path | None,
    what: str,
    *,
    allow_scan: bool = False,
    clean: bool = False,
):
    """A face mesh (mm) and its landmarks (mm) from files.

    Args:
        path: ``.ply``/``.obj`` (or ``.bnt`` with ``allow_scan``).
        units: unit of the mesh and landmark coordinates.
        landmarks: ``.lm3`` path, or ``None`` for the one beside ``path``.
        what: name used in error messages ("source neutral", "target").
        clean: weld duplicate vertices, drop degenerate/repeated triangles, refuse meshes
            above :data:`jaxface.hygiene.MAX_RIG_VERTICES` (:func:`jaxface.hygiene.clean_mesh`;
            a warning on stderr says what changed). For a face a rig is built on; not for
            morph-target sources, whose vertex ids must stay.

    Returns:
        ``(TriMesh, Landmarks)``.
    """
    from ..errors import LandmarkError, ScanFormatError
    from ..landmarks import read_lm3
    from ..mesh import check_input_file, load_mesh, unit_scale

    path = Path(path)
    check_input_file(path, f"{what} file")
    ext = path.suffix.lower()
    if ext == ".bnt" and allow_scan:
        from ..io import load_scan

        scan = load_scan(path, landmarks=False, units=units)
        mesh = scan.to_mesh(validate=False)
    elif ext in _MESHES:
        mesh = load_mesh(path, units=units, validate=False)
    else:
        allowed = ".ply, .obj" + (" or .bnt" if allow_scan else "")
        raise ScanFormatError(
            f"{what} {path}: unsupported format {ext or '(no suffix)'!r}; use {allowed}."
        )
    if clean:
        from ..cli import console
        from ..hygiene import clean_mesh

        mesh, report = clean_mesh(mesh, source=f"{what} {path}")
        if report.changed:
            console.print(f"[yellow]warning:[/] {what} {path}: {report.describe()}.", markup=True)
    lm_path = Path(landmarks) if landmarks is not None else path.with_suffix(".lm3")
    if landmarks is not None:
        check_input_file(lm_path, f"{what} landmark file")
    if not lm_path.is_file():
        opt = "--source-landmarks" if what.startswith("source") else "--target-landmarks"
        raise LandmarkError(
            f"the {what} {path} has no landmarks: {lm_path} does not exist. Give a "
            f".lm3 file with {opt} (Bosphorus labels, the same names on both faces)."
        )
    lm = read_lm3(lm_path).transformed(scale=unit_scale(units))
    return mesh, lm


def collect_targets(items: list[Path], exclude: tuple[Path, ...] = ()) -> list[Path]:
    """Morph-target files from folders (their ``.ply``/``.obj`` files, sorted by name) and
    files; ``exclude`` (e.g. the source neutral) is skipped.

    Raises:
        DataNotFoundError: a path does not exist. ScanFormatError: no mesh found, an
        unsupported file, or two targets with the same name.
    """
    from ..errors import DataNotFoundError, ScanFormatError

    skip = {Path(p).resolve() for p in exclude}
    out: list[Path] = []
    for item in items:
        item = Path(item)
        if item.is_dir():
            found = sorted(
                p
                for p in item.iterdir()
                if p.is_file() and p.suffix.lower() in _MESHES and p.resolve() not in skip
            )
            if not found:
                raise ScanFormatError(f"source-targets folder {item} holds no .ply or .obj mesh.")
            out += found
        elif item.is_file():
            if item.suffix.lower() not in _MESHES:
                raise ScanFormatError(
                    f"source target {item}: unsupported format {item.suffix!r}; use .ply or .obj."
                )
            if item.resolve() not in skip:
                out.append(item)
        else:
            raise DataNotFoundError(f"source target not found: {item}")
    if not out:
        raise ScanFormatError(
            "no source morph targets given (the only mesh is the source neutral)."
        )
    stems = [p.stem for p in out]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ScanFormatError(
            f"several source targets share the name(s) {dup}; the outputs are named "
            f"after the input stems, so rename them."
        )
    return out


def register(app: typer.Typer) -> None:
    """Add ``jaxface clone`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors, status_steps
    from . import options

    @app.command(epilog=_EPILOG)
    @handle_errors
    def clone(
        source_neutral: Path = typer.Option(
            ..., "--source-neutral", "-s", help="Source neutral mesh (.ply/.obj)."
        ),
        source_targets: List[Path] = typer.Option(  # noqa: UP006
            ...,
            "--source-targets",
            "-t",
            metavar="PATH",
            help="Source morph targets: a folder of .ply/.obj meshes or files (repeat the "
            "option); same vertex order as the source neutral.",
        ),
        target: Path = typer.Option(
            ..., "--target", "-T", help="Target neutral face (.ply/.obj, or a .bnt range scan)."
        ),
        out: Path = options.out_dir(),
        source_landmarks: Path | None = typer.Option(  # noqa: UP007
            None, "--source-landmarks", help="Source .lm3 (default: beside the source neutral)."
        ),
        target_landmarks: Path | None = typer.Option(  # noqa: UP007
            None, "--target-landmarks", help="Target .lm3 (default: beside the target)."
        ),
        landmarks: str | None = typer.Option(  # noqa: UP007
            None,
            "--landmarks",
            help="Comma-separated landmark names to use as correspondences "
            "(default: every name common to both .lm3 files; at least 4).",
        ),
        source_units: Units = typer.Option(
            Units.mm, "--source-units", help="Units of the source files."
        ),
        target_units: Units = typer.Option(
            Units.mm, "--target-units", help="Units of the target files."
        ),
        out_units: Units = typer.Option(
            Units.mm, "--out-units", help="Units of the written meshes."
        ),
        fmt: str | None = typer.Option(  # noqa: UP007
            None,
            "--format",
            help="Output mesh format: ply or obj (default: the target's, ply for a .bnt target).",
        ),
        mode: str = typer.Option(
            "displacement", "--mode", help="displacement (default) or thesis (see jaxface.clone)."
        ),
        max_iterations: int = typer.Option(
            100, "--max-iterations", min=0, help="Cap on correspondence-refinement iterations."
        ),
        contours: bool = typer.Option(
            True,
            "--contours/--no-contours",
            help="Enrich the correspondences with eye/lip contours.",
        ),
        ens0: float | None = typer.Option(  # noqa: UP007
            None,
            "--ens0",
            min=0.0,
            help="Target eye-nose separation in mm (default: from its "
            "landmarks; needed when the eye corners or nose tip are not labelled).",
        ),
        move_tol: float = typer.Option(
            0.01,
            "--move-tol",
            min=0.0,
            help="A source vertex moves if displaced more than this, mm.",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Clone a source face's morph targets (expressions) onto a target face (facial
        motion cloning, thesis chapter 6: landmark RBF fit, contour and ray-cast
        correspondence refinement, barycentric mapping).

        Writes OUT/<target name>.ply (or .obj) per source morph target, on the target's mesh,
        and OUT/clone.json (correspondences, iterations, timings, displacement statistics).

        \b
        Examples:
          jaxface clone -s ict.ply -t expressions/ -T face.ply -o cloned
          jaxface clone -s a.ply -t smile.ply -t blink.ply -T scan.bnt -o out --no-contours
          jaxface clone -s a.obj -t shapes/ -T b.obj --source-units m --target-units m --out-units m -o out
        """
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        from .. import clone as cl
        from ..atomic import ensure_out_dir, write_json_atomic
        from ..errors import LandmarkError, MeshError, ScanFormatError
        from ..mesh import load_mesh, save_mesh, unit_scale

        if mode not in ("displacement", "thesis"):
            raise MeshError(
                f"--mode {mode!r}: use 'displacement' or 'thesis'.", problem="bad_arguments"
            )
        if fmt is None:
            fmt = target.suffix.lower().lstrip(".") if target.suffix.lower() in _MESHES else "ply"
        fmt = fmt.lower().lstrip(".")
        if fmt not in ("ply", "obj"):
            raise ScanFormatError(f"--format {fmt!r}: use ply or obj.")
        t_start = time.perf_counter()
        s_units = source_units.value
        with status_steps("jaxface clone", quiet=quiet) as step:
            step("reading the source and target faces")
            src, slm = load_face(source_neutral, s_units, source_landmarks, "source neutral")
            tgt, tlm = load_face(
                target, target_units.value, target_landmarks, "target", allow_scan=True
            )
            if landmarks:
                names = [n.strip() for n in landmarks.split(",") if n.strip()]
                for lm, who in ((slm, "source"), (tlm, "target")):
                    miss = lm.missing(names)
                    if miss:
                        raise LandmarkError(
                            f"--landmarks: {len(miss)} name(s) missing from the {who} "
                            f"landmarks: {list(miss)}. The {who} has {list(lm.names)}.",
                            missing=miss,
                        )
                slm, tlm = slm.require(names), tlm.require(names)
            files = collect_targets(source_targets, exclude=(source_neutral,))
        deltas = np.zeros((len(files), src.n_vertices, 3))

        def new_progress():
            return Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[item]}"),
                TimeElapsedColumn(),
                console=console,
                disable=quiet,
            )

        with new_progress() as progress:
            task = progress.add_task("reading source targets", total=len(files), item="")
            for j, f in enumerate(files):
                progress.update(task, item=f.name)
                m = load_mesh(f, units=s_units, validate=False, check_size=False)
                if m.n_vertices != src.n_vertices:
                    raise MeshError(
                        f"source target {f} has {m.n_vertices} vertices but the source "
                        f"neutral {source_neutral} has {src.n_vertices}; morph targets "
                        f"must share the neutral's vertices (same count and order).",
                        problem="shape",
                    )
                deltas[j] = m.vertices - src.vertices
                progress.advance(task)
        bad = np.flatnonzero(~np.isfinite(deltas).all(axis=(1, 2)))
        if bad.size:
            raise MeshError(
                f"source target(s) {[files[i].name for i in bad]} hold NaN/inf coordinates.",
                problem="nonfinite",
            )
        moving = np.linalg.norm(deltas, axis=2) > move_tol
        with status_steps("jaxface clone", quiet=quiet) as step:
            step(
                f"fitting the source into the target ({len(slm.names)} source landmarks, "
                f"{src.n_vertices} -> {tgt.n_vertices} vertices)"
            )
            t0 = time.perf_counter()
            fit = cl.fit_source_to_target(
                src,
                tgt,
                slm,
                tlm,
                movable=moving.any(axis=0),
                use_contours=contours,
                max_iterations=max_iterations,
                ens0=ens0,
            )
            t1 = time.perf_counter()
            step("mapping the target onto the deformed source")
            mapping = cl.map_onto_surface(
                tgt.vertices, tgt.vertex_normals, fit.ray_length, fit.deformed, src.triangles
            )
            t2 = time.perf_counter()
        ensure_out_dir(out)
        stats = []
        with new_progress() as progress:
            task = progress.add_task("cloning targets", total=len(files), item="")
            for j, f in enumerate(files):
                progress.update(task, item=f.stem)
                pos = cl.apply_clone(
                    fit,
                    mapping,
                    src.triangles,
                    tgt.vertices,
                    deltas[j : j + 1],
                    moving[j : j + 1],
                    mode=mode,
                )[0]
                path = out / f"{f.stem}.{fmt}"
                save_mesh(path, pos, tgt.triangles, units=out_units.value)
                d = np.linalg.norm(pos - tgt.vertices, axis=1)
                ds = np.linalg.norm(deltas[j], axis=1)
                stats.append(
                    dict(
                        name=f.stem,
                        file=str(path),
                        source_moving_vertices=int(moving[j].sum()),
                        source_max_mm=float(ds.max()),
                        max_mm=float(d.max()),
                        mean_moving_mm=float(d[d > move_tol].mean())
                        if (d > move_tol).any()
                        else 0.0,
                        moving_vertices=int((d > move_tol).sum()),
                    )
                )
                progress.advance(task)
        t3 = time.perf_counter()
        report = dict(
            source_neutral=str(source_neutral),
            target=str(target),
            units_written=out_units.value,
            source_vertices=src.n_vertices,
            target_vertices=tgt.n_vertices,
            mode=mode,
            landmarks=list(fit.landmark_names),
            ens0_mm=fit.ens0,
            ray_length_mm=fit.ray_length,
            pairs=dict(
                landmark=fit.n_landmark_pairs,
                contour=fit.n_contour_pairs,
                refined=fit.n_refined_pairs,
            ),
            contours_used=list(fit.contours_used),
            contours_skipped=dict(fit.contours_skipped),
            iterations=fit.iterations,
            converged=bool(fit.converged),
            mapped_by_ray=float(np.mean(mapping.by_ray)),
            seconds=dict(
                fit=t1 - t0, mapping=t2 - t1, cloning_and_writing=t3 - t2, total=t3 - t_start
            ),
            targets=stats,
        )
        write_json_atomic(out / "clone.json", report, default=float)
        if quiet:
            return
        from rich.table import Table

        table = Table(title=f"jaxface clone: {len(files)} morph targets -> {out}")
        for col, just in (
            ("target", "left"),
            ("source max (mm)", "right"),
            ("clone max (mm)", "right"),
            ("moving vertices", "right"),
            ("file", "left"),
        ):
            table.add_column(col, justify="right" if just == "right" else "left")
        scale = unit_scale(out_units.value)
        for s in stats:
            table.add_row(
                s["name"],
                f"{s['source_max_mm']:.2f}",
                f"{s['max_mm']:.2f}",
                str(s["moving_vertices"]),
                Path(s["file"]).name,
            )
        console.print(table)
        console.print(
            f"correspondences: {fit.n_landmark_pairs} landmarks + {fit.n_contour_pairs} contour + "
            f"{fit.n_refined_pairs} refined pairs; {fit.iterations} refinement iterations"
            f"{' (converged)' if fit.converged else ' (stopped at --max-iterations)'}; "
            f"fit {t1 - t0:.2f} s, total {t3 - t_start:.2f} s. Meshes in {out_units.value}"
            f"{'' if scale == 1.0 else ' (statistics in mm)'}; details in {out / 'clone.json'}."
        )
