"""Command-line options that several ``jaxface`` commands share, declared once.

Each function returns a fresh ``typer.Option`` (typer keeps per-parameter state on it), so a
command writes ``out: Path = options.out_dir()``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

__all__ = [
    "check_out_dir_option",
    "out_dir",
    "template",
    "template_landmarks",
    "backend",
    "landmarks_mode",
    "ict",
    "no_arkit",
]


def check_out_dir_option(out: Path) -> Path:
    """``--out`` callback: the folder exists or can be created (a usage error, exit 2, with
    the reason otherwise: a parent that is a file, no permission). Nothing is created here;
    the command creates the folder when it writes."""
    from ..atomic import check_out_dir
    from ..errors import OutputError

    try:
        return check_out_dir(out)
    except OutputError as e:
        raise typer.BadParameter(str(e), param_hint="'--out'") from None


def out_dir(help: str = "Output folder (created if missing).") -> Any:
    """``--out/-o DIR``, required, checked up front (:func:`check_out_dir_option`)."""
    return typer.Option(
        ..., "--out", "-o", file_okay=False, callback=check_out_dir_option, help=help
    )


def template() -> Any:
    """``--template MESH``: the template skin to register instead of the built-in head."""
    return typer.Option(
        None,
        "--template",
        help="Template skin to register (.ply/.obj, mm; default: the built-in head).",
    )


def template_landmarks() -> Any:
    """``--template-landmarks LM3``."""
    return typer.Option(
        None, "--template-landmarks", help="Landmarks of --template (.lm3; default: beside it)."
    )


def backend(help: str = "Simulation backend: pbd or ltw.") -> Any:
    """``--backend pbd|ltw``."""
    return typer.Option("pbd", "--backend", help=help)


def landmarks_mode() -> Any:
    """``--landmarks file|auto``: where the scans' landmarks come from."""
    return typer.Option(
        "file",
        "--landmarks",
        help="'file': the .lm3 given or beside each scan, detected when there is none; "
        "'auto': detect for every scan without an explicit landmark file.",
    )


def ict() -> Any:
    """``--ict FILE``: ICT-FaceKit's ``ict_face.npz`` for the ARKit-52 readout."""
    return typer.Option(
        None,
        "--ict",
        help="ICT-FaceKit ict_face.npz for the ARKit-52 coefficients (key 'arkit'; default "
        "$JAXFACE_ICT; without it the JSON says why 'arkit' is null).",
    )


def no_arkit() -> Any:
    """``--no-arkit``."""
    return typer.Option(False, "--no-arkit", help="Skip the ARKit readout.")
