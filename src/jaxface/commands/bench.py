"""``jaxface bench``: run the repository's benchmarks and summarise them.

Benchmarks belong to the repository, not to the installed package: they are the scripts
``benchmarks/bench_*.py`` of a jaxface checkout, each a plain program that prints its tables
and writes ``benchmarks/results/<name>.json``. The folder is found (:func:`find_benchmarks`)
from ``--dir``, else from the current directory and its parents, else beside the package
source (an editable install: ``<repo>/src/jaxface`` -> ``<repo>/benchmarks``).

Each script runs in its own subprocess (``python <script> [--quick]``), from the repository
root, with the current environment (``JAXFACE_SHARED`` ...); its output is shown when it
ends, then a summary table (status, seconds, the JSON written). ``--quick`` is passed only
to scripts that accept it (their source mentions ``--quick``); the others run in full and are
marked in the table.

Exit codes: 0 every benchmark succeeded; 1 a benchmark failed or timed out; 2 bad usage
(unknown ``--only`` name); 3 no benchmarks folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import List  # noqa: UP035 (typer options keep List[str], see UP006 below)

import typer

__all__ = ["register", "find_benchmarks", "discover", "run_benchmark"]


def _has_benchmarks(folder: Path) -> bool:
    return folder.is_dir() and any(folder.glob("bench_*.py"))


def find_benchmarks(directory: Path | None = None, *, cwd: Path | None = None) -> Path:
    """The benchmarks folder.

    Args:
        directory: an explicit folder (must hold ``bench_*.py`` scripts).
        cwd: where to start looking (default the current directory): ``<cwd>/benchmarks``,
            then the same in every parent folder, then ``<package source>/../../benchmarks``.

    Raises:
        DataNotFoundError: no folder with ``bench_*.py`` scripts was found (the message says
            where it looked and what to do).
    """
    from ..errors import DataNotFoundError

    if directory is not None:
        d = Path(directory)
        if not _has_benchmarks(d):
            raise DataNotFoundError(
                f"--dir {d}: no bench_*.py scripts there "
                f"({'folder does not exist' if not d.is_dir() else 'folder has none'})."
            )
        return d.resolve()
    start = Path(cwd) if cwd is not None else Path.cwd()
    tried = []
    for folder in [start, *start.resolve().parents]:
        cand = folder / "benchmarks"
        tried.append(cand)
        if _has_benchmarks(cand):
            return cand.resolve()
    pkg = Path(__file__).resolve().parents[1]  # .../src/jaxface
    cand = pkg.parent.parent / "benchmarks"
    tried.append(cand)
    if _has_benchmarks(cand):
        return cand.resolve()
    raise DataNotFoundError(
        "no benchmarks folder found: the benchmarks are part of the jaxface repository, not of "
        f"the installed package. Looked for benchmarks/bench_*.py in {start} and its parents and "
        f"beside the package ({cand}). Run `jaxface bench` inside a jaxface checkout, or pass "
        "--dir path/to/jaxface/benchmarks."
    )


def discover(folder: Path, only: list[str] | None = None) -> list[Path]:
    """The ``bench_*.py`` scripts of ``folder`` (sorted), or those named by ``only`` (stems,
    with or without the ``bench_`` prefix and ``.py`` suffix).

    Raises:
        JaxfaceError: a name in ``only`` matches no script (the message lists them).
    """
    from ..errors import JaxfaceError

    scripts = sorted(folder.glob("bench_*.py"))
    if not only:
        return scripts
    by_name = {p.stem: p for p in scripts}
    picked, unknown = [], []
    for name in only:
        for part in name.split(","):
            key = part.strip()
            if not key:
                continue
            key = key[:-3] if key.endswith(".py") else key
            key = key if key.startswith("bench_") else f"bench_{key}"
            if key in by_name:
                if by_name[key] not in picked:
                    picked.append(by_name[key])
            else:
                unknown.append(part.strip())
    if unknown:
        names = ", ".join(p.stem.removeprefix("bench_") for p in scripts)
        raise JaxfaceError(f"--only: no benchmark named {unknown} in {folder}; available: {names}.")
    return picked


def accepts_quick(script: Path) -> bool:
    """Whether a benchmark script accepts ``--quick`` (its source mentions the flag)."""
    try:
        return "--quick" in script.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False


def run_benchmark(script: Path, *, quick: bool = False, timeout: float | None = None) -> dict:
    """Run one benchmark script in a subprocess from the repository root.

    Returns:
        dict: ``name``, ``status`` ("ok", "failed", "timeout"), ``returncode``, ``seconds``,
        ``output`` (stdout + stderr), ``quick`` (whether ``--quick`` was passed), ``result``
        (path of ``results/<name>.json`` if the run wrote or updated it, else ``None``).
    """
    root = script.parent.parent
    result = script.parent / "results" / f"{script.stem}.json"
    before = result.stat().st_mtime_ns if result.exists() else None
    quick_ok = quick and accepts_quick(script)
    cmd = [sys.executable, str(script)] + (["--quick"] if quick_ok else [])
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd, cwd=root, env=env, capture_output=True, text=True, timeout=timeout
        )
        status = "ok" if proc.returncode == 0 else "failed"
        rc, output = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as e:

        def _text(x):
            return x.decode(errors="replace") if isinstance(x, bytes) else (x or "")

        status, rc, output = "timeout", None, _text(e.stdout) + _text(e.stderr)
    seconds = time.perf_counter() - t0
    written = result.exists() and result.stat().st_mtime_ns != before
    return dict(
        name=script.stem,
        script=str(script),
        status=status,
        returncode=rc,
        seconds=seconds,
        output=output,
        quick=quick_ok,
        result=str(result) if written else None,
    )


def _last_error_line(output: str) -> str:
    lines = [ln.strip() for ln in output.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else ""


def register(app: typer.Typer) -> None:
    """Add ``jaxface bench`` to ``app``."""
    from ..cli import _EPILOG, EXIT_ERROR, console, handle_errors

    @app.command(epilog=_EPILOG)
    @handle_errors
    def bench(
        quick: bool = typer.Option(
            False, "--quick", help="Small settings (passed to each script that accepts --quick)."
        ),
        only: List[str] | None = typer.Option(  # noqa: UP006, UP007
            None,
            "--only",
            help="Run only this benchmark (name with or without 'bench_'; repeat "
            "or comma-separate for several).",
        ),
        directory: Path | None = typer.Option(  # noqa: UP007
            None,
            "--dir",
            help="The benchmarks folder (default: ./benchmarks, a parent's, or the "
            "one beside an editable install).",
        ),
        timeout: float | None = typer.Option(  # noqa: UP007
            None, "--timeout", min=1.0, help="Seconds allowed per benchmark (default: no limit)."
        ),
        list_only: bool = typer.Option(False, "--list", help="List the benchmarks and exit."),
        json_out: Path | None = typer.Option(  # noqa: UP007
            None, "--json", help="Also write the summary (status, seconds, result files) as JSON."
        ),
        show_output: bool = typer.Option(
            True, "--output/--no-output", help="Print each benchmark's own tables."
        ),
    ):
        """Run the benchmarks of a jaxface checkout (benchmarks/bench_*.py), each in a
        subprocess, and print a summary table. Each script prints its tables and writes
        benchmarks/results/<name>.json.

        Exit code 1 when a benchmark fails or times out.

        \b
        Examples:
          jaxface bench --quick
          jaxface bench --only clone
          jaxface bench --list
          jaxface bench --quick --json bench_summary.json --no-output
        """
        from rich.table import Table

        folder = find_benchmarks(directory)
        scripts = discover(folder, only)
        if list_only:
            table = Table(title=f"benchmarks in {folder}")
            table.add_column("name")
            table.add_column("--quick")
            table.add_column("script")
            for s in scripts:
                table.add_row(
                    s.stem.removeprefix("bench_"), "yes" if accepts_quick(s) else "no", s.name
                )
            console.print(table)
            return
        runs = []
        for k, script in enumerate(scripts, 1):
            label = f"[{k}/{len(scripts)}] {script.stem}" + (
                " --quick" if quick and accepts_quick(script) else ""
            )
            with console.status(f"[bold]jaxface bench[/]: running {label}", spinner="dots"):
                r = run_benchmark(script, quick=quick, timeout=timeout)
            runs.append(r)
            colour = "green" if r["status"] == "ok" else "red"
            console.print(
                f"[{colour}]{r['status']}[/] {label} [dim]({r['seconds']:.1f} s)[/]", markup=True
            )
            if show_output or r["status"] != "ok":
                text = r["output"].rstrip()
                if r["status"] != "ok" and not show_output:
                    text = "\n".join(text.splitlines()[-20:])
                if text:
                    console.print(text, markup=False, highlight=False, soft_wrap=True)
        table = Table(
            title=f"jaxface bench{' --quick' if quick else ''}: {len(runs)} benchmark(s) in {folder}"
        )
        for col, just in (
            ("benchmark", "left"),
            ("status", "left"),
            ("seconds", "right"),
            ("mode", "left"),
            ("result / error", "left"),
        ):
            table.add_column(col, justify="right" if just == "right" else "left")
        for r in runs:
            mode = "quick" if r["quick"] else ("full (no --quick)" if quick else "full")
            if r["status"] == "ok":
                info = os.path.relpath(r["result"]) if r["result"] else "(no JSON written)"
            elif r["status"] == "timeout":
                info = f"timed out after {timeout:g} s"
            else:
                info = f"exit {r['returncode']}: {_last_error_line(r['output'])}"
            table.add_row(
                r["name"].removeprefix("bench_"), r["status"], f"{r['seconds']:.1f}", mode, info
            )
        console.print(table)
        if json_out is not None:
            from ..atomic import ensure_out_dir, write_text_atomic

            ensure_out_dir(json_out.parent, "--json's folder")
            write_text_atomic(
                json_out,
                json.dumps(
                    dict(
                        folder=str(folder),
                        quick=quick,
                        runs=[{k: v for k, v in r.items() if k != "output"} for r in runs],
                    ),
                    indent=1,
                ),
            )
        failed = [r["name"] for r in runs if r["status"] != "ok"]
        if failed:
            console.print(
                f"[bold red]error:[/] {len(failed)} benchmark(s) did not succeed: "
                f"{', '.join(failed)}",
                markup=True,
            )
            raise typer.Exit(EXIT_ERROR)
