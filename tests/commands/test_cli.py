"""The ``jaxface`` command line, run as a user would (subprocess), plus the error mapping."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from jaxface import __version__
from jaxface.cli import EXIT_ERROR, EXIT_MISSING, EXIT_USAGE, handle_errors


def run_cli(*args, cwd=None, timeout=300):
    env = dict(os.environ, MPLBACKEND="Agg")
    return subprocess.run(
        [sys.executable, "-m", "jaxface.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    proc = run_cli("demo", "--out", out, "--size", 200, timeout=1200)
    return out, proc


def test_demo_writes_its_files(demo_dir):
    out, proc = demo_dir
    assert proc.returncode == 0, proc.stderr
    names = {
        "head.ply",
        "head.lm3",
        "head.png",
        "upper_teeth.ply",
        "lower_teeth.ply",
        "eye_left.ply",
        "eye_right.ply",
    }
    assert names <= {p.name for p in out.iterdir()}
    assert "report.md" in proc.stderr  # the summary names the report


def test_demo_showcase_report(demo_dir):
    """The showcase: emotions and AU pictures, Bosphorus-style scans of synthetic expressions
    that load back, and their fits recovering the known jaw pose and the skin."""
    import json

    from jaxface.io import load_scan
    from jaxface.showcase import SYNTHETIC_SCANS

    out, _ = demo_dir
    rep = json.loads((out / "report.json").read_text())
    for name in ["emotions.png", "aus.png", "muscle_map.png", "jaw.png", "report.md"] + [
        f"emotion_{e}.png" for e in ("happiness", "sadness", "surprise", "fear", "anger", "disgust")
    ]:
        assert (out / name).stat().st_size > 1000, name
    assert [f["stem"] for f in rep["fits"]] == list(SYNTHETIC_SCANS)
    for f in rep["fits"]:
        scan = load_scan(out / "scans" / f"{f['stem']}.bnt")
        assert len(scan.landmarks.names) >= 22
        assert (out / f["files"]["json"]).is_file() and (out / f["files"]["picture"]).is_file()
        # synthetic scans of the rig itself: the fit reproduces the skin and the jaw
        assert f["skin_error_mm"]["mean"] < 0.1, f
        assert abs(f["jaw_fit"]["pitch_deg"] - f["jaw_true"]["pitch_deg"]) < 0.5, f
    md = (out / "report.md").read_text()
    assert "emotions.png" in md and "demo_E_HAPPY_0" in md


def test_demo_files_load_back(demo_dir):
    from matplotlib.image import imread

    from jaxface.head import generic_head
    from jaxface.landmarks import BOSPHORUS_LABELS, read_lm3
    from jaxface.mesh import load_mesh

    out, _ = demo_dir
    head = generic_head()
    mesh = load_mesh(out / "head.ply", units="mm")
    assert mesh.n_vertices == head.mesh.n_vertices
    np.testing.assert_array_equal(mesh.triangles, head.mesh.triangles)
    np.testing.assert_allclose(mesh.vertices, head.mesh.vertices, atol=1e-3)  # float32 PLY
    lm = read_lm3(out / "head.lm3")
    assert tuple(lm.names) == tuple(BOSPHORUS_LABELS)
    np.testing.assert_allclose(lm.positions, head.landmarks.positions, atol=1e-5)
    for name, part in (("upper_teeth", head.upper_teeth), ("eye_left", head.eyes[0])):
        m = load_mesh(out / f"{name}.ply", check_size=False)  # small parts (25-55 mm)
        assert m.n_vertices == part.n_vertices
    img = imread(out / "head.png")
    assert img.ndim == 3 and img.shape[1] > img.shape[0]  # two panels side by side
    assert (img[..., :3].mean(axis=2) < 0.9).mean() > 0.05  # not a blank picture


def test_help_and_version(capsys):
    from jaxface.cli import main

    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "demo" in out and "Examples" in out and "Exit codes" in out
    assert main(["demo", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--out" in out and "jaxface demo --out" in out
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxface {__version__}"


def test_bad_usage_exits_2_with_a_helpful_message(tmp_path, capsys):
    from jaxface.cli import main

    # through the real entry point in a subprocess
    a_file = tmp_path / "not_a_folder.txt"
    a_file.write_text("x")
    proc = run_cli("demo", "--out", a_file)
    assert proc.returncode == EXIT_USAGE
    assert "--out" in proc.stderr and "is a file" in proc.stderr
    assert not any(p.suffix == ".ply" for p in tmp_path.iterdir())
    # and in process
    assert main(["demo"]) == EXIT_USAGE
    assert "Missing option '--out'" in capsys.readouterr().err
    assert main(["demo", "--out", str(tmp_path / "x"), "--size", "5"]) == EXIT_USAGE
    assert "--size" in capsys.readouterr().err
    assert main(["no-such-command"]) == EXIT_USAGE
    assert "No such command" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_error_mapping_to_exit_codes():
    """Library errors map to the documented exit codes, with the message, without traceback."""
    from jaxface.errors import DataNotFoundError, MeshError

    app = typer.Typer()

    @app.command()
    @handle_errors
    def boom(kind: str):
        if kind == "mesh":
            raise MeshError(
                "3 degenerate triangle(s): triangle ids 4, 5, 6", problem="degenerate_triangles"
            )
        if kind == "data":
            raise DataNotFoundError("shared data not found: /nowhere")
        if kind == "file":
            raise FileNotFoundError("no such file: scan.bnt")
        raise RuntimeError("unexpected")

    runner = CliRunner()
    res = runner.invoke(app, ["mesh"])
    assert res.exit_code == EXIT_USAGE and "degenerate triangle" in res.output
    res = runner.invoke(app, ["data"])
    assert res.exit_code == EXIT_MISSING and "/nowhere" in res.output
    res = runner.invoke(app, ["file"])
    assert res.exit_code == EXIT_MISSING and "scan.bnt" in res.output
    res = runner.invoke(app, ["other"])
    assert (
        res.exit_code == EXIT_ERROR and "internal error" in res.output and "--debug" in res.output
    )
    assert "Traceback" not in res.output


def test_fit_command_defaults_are_the_librarys():
    """``jaxface fit`` spells its defaults out for ``--help`` (the CLI imports the library
    lazily); they must stay those of FitOptions and SubjectOptions."""
    from jaxface.commands import fit
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions

    app = typer.Typer()
    fit.register(app)
    cmd = typer.main.get_command(app)
    defaults = {p.name: p.default for p in cmd.params}
    fo, so = FitOptions(), SubjectOptions()
    assert defaults["points"] == fo.n_points
    assert defaults["motion_fraction"] == fo.motion_fraction
    assert defaults["au_sparse_weight"] == fo.au_sparse_weight
    assert defaults["au_min_motion"] == fo.au_min_motion_mm
    assert defaults["outer_iterations"] == fo.outer_iterations
    assert defaults["extra_iterations"] == fo.extra_iterations
    assert defaults["max_steps"] == fo.max_steps
    assert defaults["exact_steps"] == fo.exact_steps
    assert defaults["restart_iterations"] == fo.restart_iterations
    assert defaults["restart_when"] == fo.restart_when
    assert defaults["levels"] == so.levels
    assert defaults["pitch_knots"] == so.pitch_knots
    assert defaults["backend"] == so.backend


def test_fit_command_refuses_an_unknown_restart_trigger(tmp_path):
    """``--restart-when`` takes FitOptions' values only; anything else is a usage error (exit
    2) naming the option and the values, before any file is read."""
    from jaxface.commands import fit
    from jaxface.fit.options import RESTART_WHEN

    assert tuple(w.value for w in fit.RestartWhen) == RESTART_WHEN
    app = typer.Typer()
    fit.register(app)
    res = CliRunner().invoke(
        app,
        [
            "--neutral",
            str(tmp_path / "N.bnt"),
            "--scan",
            str(tmp_path / "S.bnt"),
            "--restart-when",
            "always",
            "--out",
            str(tmp_path / "out"),
        ],
    )
    assert res.exit_code == EXIT_USAGE, res.output
    assert (
        "--restart-when" in res.output and "unconverged" in res.output and "saturated" in res.output
    )
    assert not (tmp_path / "out").exists()


def test_compile_cache_is_written_where_asked_and_not_when_off(tmp_path):
    """The CLI keeps XLA's compiled programs in ``--compile-cache`` / ``JAXFACE_COMPILE_CACHE``
    (default under ``$XDG_CACHE_HOME``), and writes nothing with ``off``."""
    env = dict(
        os.environ,
        MPLBACKEND="Agg",
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        XDG_CACHE_HOME=str(tmp_path / "xdg"),
    )
    # the cold path, with no folder inherited from the suite's shared cache (tests/conftest.py)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    cache = tmp_path / "cache"
    args = [sys.executable, "-m", "jaxface.cli", "synth", "--au", "AU12=0.5", "-q"]
    on = subprocess.run(
        args + ["--out", str(tmp_path / "a")],
        capture_output=True,
        text=True,
        env=dict(env, JAXFACE_COMPILE_CACHE=str(cache)),
        timeout=600,
    )
    assert on.returncode == 0, on.stderr[-2000:]
    assert any(p.name.endswith("-cache") for p in cache.iterdir())
    assert not (tmp_path / "xdg" / "jaxface").exists()  # (matplotlib may cache there)
    noenv = {k: v for k, v in env.items() if k != "JAXFACE_COMPILE_CACHE"}
    # the default folder and ``off``: a command that builds the rig (its eager operations are
    # compiled programs too, cached with the minimum compile time at 0) and synthesises nothing
    args = [*args[:4], "--list-controls"]
    default = subprocess.run(
        args + ["--out", str(tmp_path / "c")],
        capture_output=True,
        text=True,
        env=noenv,
        timeout=600,
    )
    assert default.returncode == 0, default.stderr[-2000:]
    assert any(p.name.endswith("-cache") for p in (tmp_path / "xdg" / "jaxface" / "xla").iterdir())
    shutil.rmtree(tmp_path / "xdg" / "jaxface")
    off = subprocess.run(
        [
            args[0],
            "-m",
            "jaxface.cli",
            "--compile-cache",
            "off",
            *args[3:],
            "--out",
            str(tmp_path / "b"),
        ],
        capture_output=True,
        text=True,
        env=noenv,
        timeout=600,
    )
    assert off.returncode == 0, off.stderr[-2000:]
    assert "zygomaticus_major_L" in off.stdout + off.stderr  # it did build the rig
    assert not (tmp_path / "xdg" / "jaxface").exists()


def test_compile_cache_default_folder_and_unwritable_folder(tmp_path, monkeypatch):
    from jaxface.compile_cache import default_cache_dir, enable_compile_cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "jaxface" / "xla"
    for off in ("off", "OFF", "0", "none", ""):
        assert enable_compile_cache(off) is None
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.warns(UserWarning, match="compilation cache stays off"):
        assert enable_compile_cache(blocker / "xla") is None
