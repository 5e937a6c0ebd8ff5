"""``jaxface convert``: scans and meshes between ``.bnt``, PLY and OBJ, with unit conversion.

Library functions used: :func:`jaxface.io.read_bnt` / :func:`jaxface.io.write_bnt` and
:meth:`jaxface.io.Scan.to_mesh` (range-grid meshing), :func:`jaxface.io.scanner.scan_mesh`
(mesh -> range grid by casting rays along -z), :func:`jaxface.mesh.load_mesh` /
:func:`jaxface.mesh.save_mesh` (OBJ/PLY with units), :func:`jaxface.landmarks.read_lm3` /
:func:`jaxface.landmarks.write_lm3`.

Landmarks: an ``.lm3`` file beside the input (same stem) or given with ``--landmarks`` is
carried to ``OUT`` with suffix ``.lm3``, in the output units (the convention of
:func:`jaxface.io.load_scan`: a scan's ``.lm3`` is in the scan's units).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import typer

from . import Units

__all__ = ["register", "convert_file", "MESH_SUFFIXES", "SCAN_SUFFIXES"]

MESH_SUFFIXES = (".ply", ".obj")
SCAN_SUFFIXES = (".bnt",)


def _kind(path: Path, what: str) -> str:
    from ..errors import ScanFormatError

    ext = path.suffix.lower()
    if ext in MESH_SUFFIXES:
        return "mesh"
    if ext in SCAN_SUFFIXES:
        return "bnt"
    raise ScanFormatError(
        f"{path}: unsupported {what} format {ext or '(no suffix)'!r}; use .bnt, .ply or .obj."
    )


def _parse_bounds(text: str | None):
    from ..errors import ScanFormatError

    if text is None:
        return None
    try:
        vals = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        vals = []
    if len(vals) != 4 or not np.all(np.isfinite(vals)) or vals[2] <= vals[0] or vals[3] <= vals[1]:
        raise ScanFormatError(
            f"--bounds {text!r}: give four numbers XMIN,YMIN,XMAX,YMAX in the input "
            f"units with XMAX > XMIN and YMAX > YMIN, e.g. --bounds=-80,-110,80,90."
        )
    return np.array(vals).reshape(2, 2)


def _lm3_beside(path: Path) -> Path | None:
    cands = [path.with_suffix(".lm3")]
    if path.name.lower().endswith(".truth.ply"):
        cands.append(path.with_name(path.name[: -len(".truth.ply")] + ".lm3"))
    return next((c for c in cands if c.is_file()), None)


def convert_file(
    src: Path,
    dst: Path,
    *,
    in_units: str = "mm",
    out_units: str = "mm",
    resolution: float | None = None,
    bounds=None,
    max_angle_deg: float | None = None,
    noise_mm: float = 0.0,
    seed: int = 0,
    landmarks: Path | None | bool = None,
    max_edge_factor: float | None = None,
    check_size: bool = True,
) -> dict:
    """Convert one file; the library behind ``jaxface convert``.

    Args:
        src, dst: input and output paths (``.bnt``, ``.ply``, ``.obj``).
        in_units, out_units: units of the input and output coordinates ("mm", "cm", "m").
        resolution: grid spacing for mesh -> ``.bnt``, in mm (default
            :data:`jaxface.io.scanner.DEFAULT_RESOLUTION_MM`).
        bounds: ``(2, 2)`` ``((xmin, ymin), (xmax, ymax))`` scanned window in the input
            units (mesh -> ``.bnt``; default the mesh's x/y extent).
        max_angle_deg, noise_mm, seed: virtual-scanner options (see
            :func:`jaxface.io.scanner.scan_mesh`; ``noise_mm`` in mm).
        landmarks: ``.lm3`` path (input units), ``None`` (or ``True``) = the ``.lm3`` beside
            the input if any, ``False`` = none.
        max_edge_factor: long-edge threshold (grid steps) for ``.bnt`` -> mesh.
        check_size: check that the input is face-sized in mm after unit conversion.

    Returns:
        a summary dict (kinds, counts, grid shape, files written).
    """
    from ..atomic import ensure_out_dir
    from ..errors import ScanFormatError
    from ..io.bosphorus import DEFAULT_MAX_EDGE_FACTOR, read_bnt, write_bnt
    from ..landmarks import read_lm3, write_lm3
    from ..mesh import check_input_file, load_mesh, save_mesh, unit_scale

    src, dst = Path(src), Path(dst)
    s_in, s_out = unit_scale(in_units), unit_scale(out_units)
    check_input_file(src, "input file")
    k_in, k_out = _kind(src, "input"), _kind(dst, "output")
    if dst.resolve() == src.resolve():
        raise ScanFormatError(f"output {dst} is the input file; choose another output path.")
    if max_edge_factor is None:
        max_edge_factor = DEFAULT_MAX_EDGE_FACTOR
    info: dict = {
        "input": str(src),
        "output": str(dst),
        "from": k_in,
        "to": k_out,
        "in_units": in_units,
        "out_units": out_units,
        "notes": [],
    }

    lm_path = None
    if landmarks is None or landmarks is True:
        lm_path = _lm3_beside(src)
    elif landmarks is not False:
        lm_path = Path(landmarks)
        check_input_file(lm_path, "landmark file")
    lm = read_lm3(lm_path).transformed(scale=s_in) if lm_path is not None else None  # mm

    lm_out = dst.with_suffix(".lm3")
    shared_lm3 = lm_path is not None and lm_out.resolve() == lm_path.resolve()
    if shared_lm3 and s_in != s_out:
        raise ScanFormatError(
            f"the output landmarks {lm_out} would overwrite the input landmarks "
            f"{lm_path} in other units; write the output to another folder or stem."
        )
    ensure_out_dir(dst.parent, "OUT's folder")
    if k_in == "bnt":
        scan = read_bnt(src, units=in_units, check_size=check_size)
        assert scan.shape is not None  # a .bnt is a grid scan
        info["grid"] = list(scan.shape)
        info["points"] = scan.n_points
        if k_out == "mesh":
            mesh = scan.to_mesh(max_edge_factor, validate=False)
            save_mesh(dst, mesh, units=out_units)
            info.update(vertices=mesh.n_vertices, triangles=mesh.n_triangles)
        else:
            write_bnt(dst, dataclasses.replace(scan, points=scan.points / s_out))
    else:
        mesh = load_mesh(src, units=in_units, check_size=check_size, validate=False)
        info.update(vertices=mesh.n_vertices, triangles=mesh.n_triangles)
        if k_out == "mesh":
            save_mesh(dst, mesh, units=out_units)
        else:
            from ..io.scanner import DEFAULT_RESOLUTION_MM, scan_mesh

            res = DEFAULT_RESOLUTION_MM if resolution is None else float(resolution)
            b = None if bounds is None else np.asarray(bounds, dtype=np.float64) * s_in
            scan = scan_mesh(
                mesh,
                res,
                bounds=b,
                max_angle_deg=max_angle_deg,
                noise_mm=noise_mm,
                seed=seed,
                image_name=dst.stem + ".png",
            )
            write_bnt(dst, dataclasses.replace(scan, points=scan.points / s_out))
            assert scan.shape is not None  # scan_mesh makes a grid scan
            info.update(grid=list(scan.shape), points=scan.n_points, resolution_mm=res)
    if resolution is not None and not (k_in == "mesh" and k_out == "bnt"):
        info["notes"].append("--resolution is only used when scanning a mesh into a .bnt grid")
    info["files"] = [str(dst)]
    if lm is not None and shared_lm3:  # same stem, same folder, same units: already there
        info["files"].append(f"{lm_out} (kept: the input's landmarks, same units)")
        info["landmarks"] = len(lm)
    elif lm is not None:
        assert lm_path is not None  # lm was read from it
        write_lm3(
            lm_out,
            lm.transformed(scale=1.0 / s_out),
            comment=f"landmarks converted by jaxface from {lm_path.name} ({out_units})",
        )
        info["files"].append(str(lm_out))
        info["landmarks"] = len(lm)
    return info


def register(app: typer.Typer) -> None:
    """Add ``jaxface convert`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors, status_steps

    @app.command(epilog=_EPILOG)
    @handle_errors
    def convert(
        src: Path = typer.Argument(..., metavar="IN", help="Input file: .bnt, .ply or .obj."),
        dst: Path = typer.Argument(
            ..., metavar="OUT", help="Output file: .bnt, .ply or .obj (folders are created)."
        ),
        in_units: Units = typer.Option(
            Units.mm,
            "--in-units",
            help="Units of IN's coordinates (and of its .lm3 and of --bounds).",
        ),
        out_units: Units = typer.Option(
            Units.mm, "--out-units", help="Units to write OUT (and its .lm3) in."
        ),
        resolution: float | None = typer.Option(  # noqa: UP007
            None,
            "--resolution",
            "-r",
            min=1e-3,
            help="Mesh -> .bnt: grid spacing in mm (default 0.5).",
        ),
        bounds: str | None = typer.Option(  # noqa: UP007
            None,
            "--bounds",
            help="Mesh -> .bnt: scanned window XMIN,YMIN,XMAX,YMAX in the input "
            "units (default the mesh's x/y extent). Write it as --bounds=-80,-110,80,90.",
        ),
        max_angle: float | None = typer.Option(  # noqa: UP007
            None,
            "--max-angle",
            min=0.0,
            max=90.0,
            help="Mesh -> .bnt: drop samples on surfaces steeper than this (degrees from the "
            "view axis), like a real scanner.",
        ),
        noise: float = typer.Option(
            0.0, "--noise", min=0.0, help="Mesh -> .bnt: Gaussian depth noise, mm."
        ),
        seed: int = typer.Option(0, "--seed", help="Seed of the depth noise."),
        landmarks: Path | None = typer.Option(  # noqa: UP007
            None,
            "--landmarks",
            "-l",
            help=".lm3 landmarks of IN (default: IN's stem + .lm3 if "
            "it exists); written beside OUT.",
        ),
        no_landmarks: bool = typer.Option(False, "--no-landmarks", help="Do not carry landmarks."),
        max_edge: float | None = typer.Option(  # noqa: UP007
            None,
            "--max-edge",
            min=0.0,
            help=".bnt -> mesh: drop triangles with an edge longer than this many grid steps "
            "(default 6; depth discontinuities).",
        ),
        check_size: bool = typer.Option(
            True,
            "--check-size/--no-check-size",
            help="Check that IN is face-sized after unit conversion.",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Convert scans and meshes: .bnt -> PLY/OBJ (meshing the range grid), PLY/OBJ -> .bnt
        (a virtual range scan along -z on a regular x/y grid), OBJ <-> PLY; with units.

        Landmarks in IN's .lm3 (or --landmarks) are written to OUT's stem + .lm3, in the
        output units. A mesh scanned into a .bnt grid must look along +z (+y up).

        \b
        Examples:
          jaxface convert bs000_N_N_0.bnt bs000_N_N_0.ply
          jaxface convert head.ply head.bnt --resolution 0.5
          jaxface convert face.ply face_scan.bnt -r 1 --max-angle 80 --noise 0.1
          jaxface convert skull.obj skull_mm.ply --in-units m --out-units mm
        """
        from ..errors import UnitsError

        b = _parse_bounds(bounds)
        with status_steps("jaxface convert", quiet=quiet) as step:
            step(f"converting {src.name} -> {dst.name}")
            try:
                info = convert_file(
                    src,
                    dst,
                    in_units=in_units.value,
                    out_units=out_units.value,
                    resolution=resolution,
                    bounds=b,
                    max_angle_deg=max_angle,
                    noise_mm=noise,
                    seed=seed,
                    landmarks=False if no_landmarks else landmarks,
                    max_edge_factor=max_edge,
                    check_size=check_size,
                )
            except UnitsError as e:
                raise UnitsError(
                    f"{e} On the command line: set --in-units to the file's unit, "
                    f"or pass --no-check-size."
                ) from e
        if quiet:
            return
        from rich.table import Table

        table = Table(title=f"jaxface convert: {src} -> {dst}")
        table.add_column("item")
        table.add_column("value")
        table.add_row(
            "conversion",
            f"{info['from']} ({info['in_units']}) -> {info['to']} ({info['out_units']})",
        )
        if "grid" in info:
            table.add_row(
                "range grid",
                f"{info['grid'][0]} rows x {info['grid'][1]} columns, "
                f"{info['points']} valid points",
            )
        if "resolution_mm" in info:
            table.add_row("grid spacing", f"{info['resolution_mm']:g} mm")
        if "vertices" in info:
            table.add_row("mesh", f"{info['vertices']} vertices, {info['triangles']} triangles")
        table.add_row("landmarks", str(info.get("landmarks", "none")))
        table.add_row("written", "\n".join(info["files"]))
        console.print(table)
        for note in info["notes"]:
            console.print(f"[yellow]note:[/] {note}", markup=True)
