"""The ``jaxface`` command line (typer + rich).

The CLI is thin: every command parses its arguments, calls library functions, shows progress
and maps errors to exit codes. Scripts can rely on the exit codes:

====  ==========================================================================
code  meaning
====  ==========================================================================
0     success
1     unexpected internal error (a bug: rerun with ``--debug`` for the traceback)
2     bad usage or invalid input (unknown option, bad value, malformed mesh,
      landmark or scan file: any :class:`jaxface.errors.JaxfaceError`; an output
      folder that cannot be created; a folder given where a file is expected;
      an input too large for the memory)
3     a required file or data folder does not exist
130   interrupted (Ctrl-C)
====  ==========================================================================

Adding a sub-command from another module: write ``register(app: typer.Typer) -> None`` in
your module (it calls ``app.command(...)`` on a thin function that calls your library code,
and wraps its body in :func:`handle_errors`), and add the module name to
:data:`COMMAND_MODULES`. Modules can also be registered by installed plugins through the
``jaxface.commands`` entry-point group (value: ``module:register`` function).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import os
import sys
import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from . import __version__
from .commands.options import check_out_dir_option

__all__ = [
    "app",
    "main",
    "handle_errors",
    "console",
    "EXIT_OK",
    "EXIT_ERROR",
    "EXIT_USAGE",
    "EXIT_MISSING",
    "COMMAND_MODULES",
    "status_steps",
]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_MISSING = 3
EXIT_INTERRUPTED = 130

#: modules that add sub-commands: each defines ``register(app)``. A listed module that is not
#: installed yet is skipped; any other import error is reported.
COMMAND_MODULES: tuple[str, ...] = (
    "jaxface.commands.synth",
    "jaxface.commands.fit",
    "jaxface.commands.fitdb",
    "jaxface.commands.clone",
    "jaxface.commands.convert",
    "jaxface.commands.bench",
    "jaxface.commands.export",
    "jaxface.commands.landmarks",
)

#: status and progress go to stderr so that stdout stays clean for data
console = Console(stderr=True, highlight=False)

_EPILOG = (
    "Exit codes: 0 success, 1 internal error, 2 bad usage or invalid input, 3 missing file "
    "or data, 130 interrupted. Units: millimetres; +y up, the face looks along +z, the "
    "subject's left is +x."
)

app = typer.Typer(
    name="jaxface",
    help=(
        "jaxface: a differentiable, physically based simulator of the human face in JAX.\n\n"
        "Muscles and jaw in, face mesh out (forward); muscle activations fitted back from 3D "
        "scans (inverse).\n\n"
        "\b\nExamples:\n"
        "  jaxface demo --out demo     # default head: mesh, landmarks, picture\n"
        "  jaxface demo --help         # the options of a command\n"
        "  jaxface --version"
    ),
    epilog=_EPILOG,
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
    pretty_exceptions_enable=False,
)


# ----------------------------------------------------------------------------- error handling
_DEBUG = False


def _fail(code: int, message: str, hint: str | None = None) -> typer.Exit:
    console.print(f"[bold red]error:[/] {message}", markup=True, soft_wrap=True)
    if hint:
        console.print(f"[dim]{hint}[/]", markup=True, soft_wrap=True)
    return typer.Exit(code)


def _nonfinite_option(kwargs: dict) -> tuple[str, float] | None:
    """The first ``(name, value)`` of a command's parsed options that is a NaN/inf float
    (click's number ranges let ``nan`` through: every comparison with it is false)."""
    import math

    for name, value in kwargs.items():
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                return name, v
    return None


def handle_errors(fn):
    """Decorator for command functions: map exceptions to messages and exit codes.

    :class:`jaxface.errors.DataNotFoundError` / ``FileNotFoundError`` -> 3, any other
    :class:`jaxface.errors.JaxfaceError` -> 2, ``KeyboardInterrupt`` -> 130, anything else
    -> 1 with a hint to rerun with ``--debug`` (which shows the traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from .errors import DataNotFoundError, JaxfaceError

        bad = _nonfinite_option(kwargs)
        if bad is not None:
            raise _fail(
                EXIT_USAGE,
                f"--{bad[0].replace('_', '-')} {bad[1]}: not a finite number; give a number.",
            )
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt:
            raise _fail(EXIT_INTERRUPTED, "interrupted") from None
        except (DataNotFoundError, FileNotFoundError) as e:
            if _DEBUG:
                console.print_exception()
            raise _fail(EXIT_MISSING, str(e)) from None
        except JaxfaceError as e:
            if _DEBUG:
                console.print_exception()
            raise _fail(EXIT_USAGE, str(e)) from None
        except PermissionError as e:
            raise _fail(EXIT_USAGE, f"permission denied: {e}") from None
        except (IsADirectoryError, NotADirectoryError, FileExistsError) as e:
            # a path that is a folder where a file is expected, or the other way round
            raise _fail(
                EXIT_USAGE,
                f"{e.strerror or e}: {e.filename}",
                "Check the input and output paths (a folder where a file is expected, or a "
                "file where a folder is expected).",
            ) from None
        except MemoryError:
            raise _fail(
                EXIT_USAGE,
                "out of memory: the input is too large for this machine.",
                "Decimate the mesh or give fewer scans/points (see docs/input-checks.md).",
            ) from None
        except Exception as e:  # noqa: BLE001 - the CLI's last line of defence
            if _DEBUG:
                console.print_exception()
                raise _fail(EXIT_ERROR, f"internal error: {type(e).__name__}: {e}") from None
            raise _fail(
                EXIT_ERROR,
                f"internal error: {type(e).__name__}: {e}",
                "This is a bug in jaxface. Rerun with `jaxface --debug ...` for the "
                "traceback and report it.",
            ) from None

    return wrapper


@contextlib.contextmanager
def status_steps(title: str, *, quiet: bool = False):
    """Show numbered steps with a spinner (rich); yields ``step(text)`` to start the next one.

    Each finished step is printed with its duration."""
    state: dict = {"text": None, "t0": None, "n": 0}
    st = None if quiet else console.status(title, spinner="dots")

    def finish():
        if state["text"] is not None and not quiet:
            console.print(
                f"  [green]done[/] {state['text']} [dim]({time.perf_counter() - state['t0']:.2f} s)[/]",
                markup=True,
            )

    def step(text: str):
        finish()
        state["n"] += 1
        state["text"], state["t0"] = text, time.perf_counter()
        if st is not None:
            st.update(f"[bold]{title}[/]: {text}")

    if st is not None:
        st.start()
    try:
        yield step
        finish()
    finally:
        if st is not None:
            st.stop()


# ----------------------------------------------------------------------------- root
def _version_callback(value: bool):
    if value:
        typer.echo(f"jaxface {__version__}")
        raise typer.Exit(EXIT_OK)


@app.callback()
def _root(
    version: bool | None = typer.Option(  # noqa: UP007 - typer needs Optional here
        None,
        "--version",
        "-V",
        callback=_version_callback,
        is_eager=True,
        help="Print the version and exit.",
    ),
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks on errors."),
    compile_cache: str | None = typer.Option(  # noqa: UP007
        None,
        "--compile-cache",
        envvar="JAXFACE_COMPILE_CACHE",
        metavar="DIR|off",
        help="Folder of the persistent XLA compilation cache (default ~/.cache/jaxface/xla): a later "
        "run on the same subject loads what this one compiled (a one-scan fit: 54 s -> 32 s). "
        "'off' turns it off.",
    ),
):
    """jaxface command line."""
    global _DEBUG
    _DEBUG = debug
    from .compile_cache import enable_compile_cache

    enable_compile_cache(compile_cache)


# ----------------------------------------------------------------------------- demo
@app.command(epilog=_EPILOG)
@handle_errors
def demo(
    out: Path = typer.Option(
        ...,
        "--out",
        "-o",
        help="Output folder (created if missing).",
        callback=check_out_dir_option,
        file_okay=False,
        dir_okay=True,
        writable=True,
        resolve_path=False,
    ),
    size: int = typer.Option(
        600, "--size", min=128, max=4000, help="Picture panel size in pixels (128-4000)."
    ),
    labels: bool = typer.Option(
        False, "--labels/--no-labels", help="Write the landmark names on the picture."
    ),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Render the head PNG."),
    showcase: bool = typer.Option(
        True,
        "--showcase/--head-only",
        help="Also build the rig, synthesise emotions and AUs, scan and fit "
        "them back, and write report.md/report.json (about 2-4 min on 2 CPU cores).",
    ),
    fit: bool = typer.Option(
        True, "--fit/--no-fit", help="Showcase: scan and fit back synthetic expressions."
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
):
    """The showcase on the embedded default head: forward synthesis and inverse fitting.

    Writes OUT/head.ply (skin, mm), OUT/head.lm3 (24 Bosphorus landmarks, mm), teeth and eye
    meshes and OUT/head.png; then (unless --head-only) builds the rig, draws the muscle map
    (OUT/muscle_map.png) and the jaw model (OUT/jaw.png) and writes the six
    emotions (OUT/emotions.png, OUT/emotion_<name>.png) and single action units (OUT/aus.png),
    Bosphorus-style scans of synthetic expressions (OUT/scans/*.bnt, *.lm3), their fits
    (OUT/fits/<stem>.json, .fitted.ply, .fit.png: scan, neutral, fit, error in mm) and
    OUT/report.json + OUT/report.md.

    \b
    Examples:
      jaxface demo --out demo
      jaxface demo --out demo --no-fit          # forward part only
      jaxface demo --out /tmp/head --head-only --size 900 --labels
    """
    from .head import generic_head, save_head

    report = None
    with status_steps("jaxface demo", quiet=quiet) as step:
        if showcase and not labels:
            from .showcase import run_showcase

            if fit:
                import jax

                # as `jaxface fit`: the fits run in float64 (in float32 the Levenberg-Marquardt
                # solves crept on to their step limit, and the surprise scan's activations came
                # back 0.094 off instead of 0.011)
                jax.config.update("jax_enable_x64", True)

            report = run_showcase(out, fit=fit, panel_px=size, progress=step)
            files = {"report": out / "report.md", "report_json": out / "report.json"}
        else:
            step("building the default head")
            head = generic_head()
            step("writing meshes and landmarks" + (" and rendering the picture" if picture else ""))
            files = save_head(head, out, picture=picture, panel_px=size, labels=labels)
    if quiet:
        return
    if report is not None:
        table = Table(title=f"jaxface demo: report in {out / 'report.md'}")
        for col in (
            "scan",
            "status",
            "scan->fit mm",
            "skin error mm",
            "jaw pitch true/fit",
            "strongest AUs",
        ):
            table.add_column(col, overflow="fold")  # a narrow terminal wraps, never cuts, a name
        for f in report.get("fits", []):
            table.add_row(
                f["stem"],
                f["status"],
                f"{f['scan_to_fit_mean_mm']:.3f}",
                f"{f['skin_error_mm']['mean']:.3f}",
                f"{f['jaw_true']['pitch_deg']:.1f} / {f['jaw_fit']['pitch_deg']:.2f}",
                ", ".join(f"{k} {v:.2f}" for k, v in f["strongest_aus"][:3]),
            )
        console.print(table)
        console.print(
            f"pictures: {out / 'emotions.png'}, {out / 'aus.png'}, {out / 'fits'}/*.fit.png; "
            f"total {report['timings']['total_s']:.0f} s"
        )
        return
    table = Table(title=f"jaxface demo: files written to {out}", show_lines=False)
    table.add_column("file")
    table.add_column("content")
    table.add_column("size", justify="right")
    desc = {
        "skin": f"skin mesh, {head.mesh.n_vertices} vertices, {head.mesh.n_triangles} triangles (mm)",
        "landmarks": f"{len(head.landmarks.names)} Bosphorus landmarks (mm)",
        "upper_teeth": f"upper teeth, {head.upper_teeth.n_vertices} vertices",
        "lower_teeth": f"lower teeth, {head.lower_teeth.n_vertices} vertices",
        "eye_left": "left eyeball",
        "eye_right": "right eyeball",
        "picture": "front + side view with landmarks",
    }
    for key, path in files.items():
        table.add_row(
            Path(path).name, desc.get(key, key), f"{os.path.getsize(path) / 1024:.0f} KiB"
        )
    console.print(table)


# ----------------------------------------------------------------------------- extensions
def _load_extensions() -> None:
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            # only skip modules that do not exist (yet); report broken imports inside them
            if e.name is not None and (name == e.name or name.startswith(e.name + ".")):
                continue
            raise
        mod.register(app)
    try:
        from importlib.metadata import entry_points

        for ep in entry_points(group="jaxface.commands"):
            ep.load()(app)
    except Exception as e:  # noqa: BLE001 - a broken plugin must not break the CLI
        console.print(
            f"[yellow]warning:[/] a jaxface.commands plugin failed to load: {e}", markup=True
        )


_loaded = False


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxface`` console script; returns the exit code."""
    global _loaded
    os.environ.setdefault("MPLBACKEND", "Agg")
    if not _loaded:
        _load_extensions()
        _loaded = True
    try:
        app(args=argv, prog_name="jaxface", standalone_mode=True)
    except SystemExit as e:  # typer/click exit with the command's code
        code = e.code
        if code is None:
            return EXIT_OK
        return code if isinstance(code, int) else EXIT_ERROR
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
