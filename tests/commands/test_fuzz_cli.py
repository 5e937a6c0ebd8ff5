"""Every ``jaxface`` command with bad inputs and bad option values (issue 49): each must end
with a usage error (exit 2) or a missing-file error (exit 3) and a message, never an internal
error (exit 1, a traceback), never a hang (a 60 s alarm guards each case) and never a
silent result. Runs the CLI in-process (:func:`jaxface.cli.main`); every case fails before
any rig is built."""

from __future__ import annotations

import shutil
import signal

import numpy as np
import pytest

from jaxface.cli import main
from jaxface.mesh import TriMesh, save_mesh

HANG_S = 60


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Bad and good input files in one folder; ``f(name)`` gives their paths."""
    from jaxface.testing import shared_path

    d = tmp_path_factory.mktemp("cli")
    n = 10
    x, y = np.meshgrid(np.linspace(-60, 60, n), np.linspace(-60, 60, n))
    v = np.stack([x.ravel(), y.ravel(), 5 * np.cos(x.ravel() / 30)], 1)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, e = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    t = np.concatenate(
        [np.stack([a, b, e], -1).reshape(-1, 3), np.stack([a, e, c], -1).reshape(-1, 3)]
    )
    save_mesh(d / "ok.ply", TriMesh(v, t))
    vn = v.copy()
    vn[[3, 4, 9]] = np.nan
    import trimesh

    tm = trimesh.Trimesh(vn, t, process=False, validate=False)
    (d / "nan.ply").write_bytes(trimesh.exchange.ply.export_ply(tm, encoding="binary"))
    (d / "face.stl").write_text("solid x\nendsolid x\n")
    for name in ("x.bnt", "dir.ply", "dir.lm3"):
        (d / name).mkdir()
    (d / "a_file.txt").write_text("not a folder")
    root = shared_path("data", "bosphorus_style")
    for stem in ("bs900_N_N_0", "bs900_E_HAPPY_0"):
        shutil.copy(root / f"{stem}.bnt", d / f"{stem}.bnt")
        shutil.copy(root / f"{stem}.lm3", d / f"{stem}.lm3")
    data = (root / "bs900_N_N_0.bnt").read_bytes()
    (d / "cut.bnt").write_bytes(data[: len(data) // 3])
    shutil.copy(root / "bs900_N_N_0.lm3", d / "cut.lm3")
    (d / "badhead.bnt").write_bytes(data)
    text = (root / "bs900_N_N_0.lm3").read_text()
    (d / "badhead.lm3").write_text(text.replace("22 landmarks", "5 landmarks"))
    return lambda name: str(d / name)


def _run(capsys, argv):
    def alarm(*_):
        raise TimeoutError(f"jaxface {' '.join(argv)} ran longer than {HANG_S} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(HANG_S)
    try:
        code = main(list(argv))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    out = capsys.readouterr()
    return code, out.out + out.err


def _cases(f, d):
    """``(argv, expected exit code, text the message must contain)``."""
    nb, hb = f("bs900_N_N_0.bnt"), f("bs900_E_HAPPY_0.bnt")
    under_file = f("a_file.txt") + "/sub"
    fit = ["fit", "--neutral", nb, "--scan", hb, "--out", d]
    syn = ["synth", "--out", d]
    return [
        # ---- root
        (["no-such-command"], 2, "No such command"),
        # ---- synth
        (["synth", "--out", under_file, "--emotion", "happiness"], 2, "is a file"),
        ([*syn, "--emotion", "bogus"], 2, "unknown preset"),
        ([*syn, "--au", "AU999=0.5"], 2, "AU"),
        ([*syn, "--au", "AU12=2"], 2, "[0, 1]"),
        ([*syn, "--au", "AU12=nan"], 2, "[0, 1]"),
        ([*syn, "--au", "AU12=abc"], 2, "AU"),
        ([*syn, "--muscle", "zygomaticus_major_L=5"], 2, "[0, 1]"),
        ([*syn, "--muscle", "zygomaticus_major_L=nan"], 2, "[0, 1]"),
        ([*syn, "--muscle", "zygomaticus_major_L=lots"], 2, "number"),
        ([*syn, "--jaw-pitch", "nan"], 2, "finite"),
        ([*syn, "--jaw-yaw", "inf"], 2, "finite"),
        ([*syn, "--jaw-protrusion", "-inf"], 2, "finite"),
        ([*syn, "--emotion", "happiness", "--intensity", "2"], 2, "intensity"),
        ([*syn, "--emotion", "happiness", "--intensity", "nan"], 2, "--intensity"),
        ([*syn, "--emotion", "happiness", "--sweeps", "0/0"], 2, "at least 1"),
        ([*syn, "--emotion", "happiness", "--sweeps", "many"], 2, "sweeps"),
        ([*syn, "--emotion", "happiness", "--sweeps", "32/8/1.5"], 2, "sweeps"),
        ([*syn, "--emotion", "happiness", "--backend", "ltw", "--sweeps", "32/8"], 2, "ltw"),
        ([*syn, "--emotion", "happiness", "--backend", "foo"], 2, "backend"),
        ([*syn, "--emotion", "happiness", "--units", "parsec"], 2, "parsec"),
        ([*syn, "--emotion", "happiness", "--out-units", "inch"], 2, "inch"),
        (syn, 2, "nothing to synthesise"),
        ([*syn, "-e", "happiness", "--mesh", f("missing.ply")], 3, "not found"),
        ([*syn, "-e", "happiness", "--mesh", f("dir.ply")], 2, "is a folder"),
        ([*syn, "-e", "happiness", "--mesh", f("nan.ply")], 2, "NaN"),
        ([*syn, "-e", "happiness", "--mesh", f("face.stl")], 2, "unsupported"),
        # no .lm3 beside a mesh that is not a face: detection says there is no face
        ([*syn, "-e", "happiness", "--mesh", f("ok.ply")], 2, "no face found"),
        (
            [*syn, "-e", "happiness", "--mesh", f("ok.ply"), "--landmarks", f("dir.lm3")],
            2,
            "folder",
        ),
        # ---- fit
        (["fit", "--neutral", nb, "--scan", hb, "--out", under_file], 2, "is a file"),
        (["fit", "--neutral", f("missing.bnt"), "--scan", hb, "--out", d], 3, "not found"),
        (["fit", "--neutral", f("x.bnt"), "--scan", hb, "--out", d], 2, "is a folder"),
        (["fit", "--neutral", nb, "--scan", f("x.bnt"), "--out", d], 2, "is a folder"),
        (["fit", "--neutral", f("cut.bnt"), "--scan", hb, "--out", d], 2, "cut.bnt"),
        (["fit", "--neutral", f("badhead.bnt"), "--scan", hb, "--out", d], 2, "5 landmarks"),
        ([*fit, "--backend", "foo"], 2, "backend"),
        ([*fit, "--points", "5"], 2, "points"),
        ([*fit, "--motion-fraction", "nan"], 2, "--motion-fraction"),
        ([*fit, "--motion-fraction", "1.5"], 2, "motion-fraction"),
        ([*fit, "--au-sparse-weight", "inf"], 2, "finite"),
        ([*fit, "--outer-iterations", "0"], 2, "outer-iterations"),
        ([*fit, "--restart-when", "sometimes"], 2, "restart-when"),
        ([*fit, "--scan-landmarks", nb, "--scan-landmarks", nb], 2, "--scan-landmarks"),
        ([*fit, "--neutral-landmarks", f("dir.lm3")], 2, "is a folder"),
        ([*fit, "--template", f("dir.ply")], 2, "is a folder"),
        ([*fit, "--template-landmarks", f("badhead.lm3")], 2, "--template"),
        # ---- convert
        (["convert", f("x.bnt"), f("o.ply")], 2, "is a folder"),
        (["convert", f("missing.bnt"), f("o.ply")], 3, "not found"),
        (["convert", f("nan.ply"), f("nan_out.obj")], 2, "NaN"),
        (["convert", f("ok.ply"), f("o.stl")], 2, "stl"),
        (["convert", f("ok.ply"), under_file + "/o.ply"], 2, "is a file"),
        (["convert", f("ok.ply"), f("ok.ply")], 2, "input"),
        (["convert", f("ok.ply"), f("o.bnt"), "--resolution", "nan"], 2, "--resolution"),
        (["convert", f("ok.ply"), f("o.bnt"), "--resolution", "0"], 2, "resolution"),
        (["convert", f("ok.ply"), f("o.bnt"), "--bounds=1,2,3"], 2, "bounds"),
        (["convert", f("ok.ply"), f("o.bnt"), "--noise", "inf"], 2, "finite"),
        (["convert", f("ok.ply"), f("o.ply"), "--in-units", "parsec"], 2, "parsec"),
        (["convert", f("cut.bnt"), f("o.ply")], 2, "cut.bnt"),
        # ---- clone
        (
            ["clone", "-s", f("missing.ply"), "-t", f("ok.ply"), "-T", f("ok.ply"), "-o", d],
            3,
            "not found",
        ),
        (
            ["clone", "-s", f("dir.ply"), "-t", f("ok.ply"), "-T", f("ok.ply"), "-o", d],
            2,
            "is a folder",
        ),
        (
            ["clone", "-s", f("ok.ply"), "-t", f("ok.ply"), "-T", f("ok.ply"), "-o", under_file],
            2,
            "is a file",
        ),
        (
            ["clone", "-s", f("ok.ply"), "-t", f("ok.ply"), "-T", f("ok.ply"), "-o", d]
            + ["--move-tol", "nan"],
            2,
            "--move-tol",
        ),
        # ---- demo
        (["demo", "--out", under_file], 2, "is a file"),
        (["demo", "--out", d, "--size", "5"], 2, "size"),
        # ---- bench
        (["bench", "--timeout", "nan", "--list"], 2, "--timeout"),
    ]


def test_every_command_with_bad_input(files, capsys, tmp_path):
    d = str(tmp_path / "out")
    failures = []
    for argv, code, text in _cases(files, d):
        got, out = _run(capsys, argv)
        if got != code or text.lower() not in out.lower() or "internal error" in out:
            failures.append(f"jaxface {' '.join(argv)} -> {got} (want {code}, {text!r}): {out}")
    assert not failures, "\n\n".join(failures)
    assert not (tmp_path / "nan_out.obj").exists()


def test_nan_mesh_not_converted(files, capsys):
    code, out = _run(capsys, ["convert", files("nan.ply"), files("nan2.obj")])
    assert code == 2 and "3 of 100 vertices" in out and "vertex 3" in out
    assert not __import__("pathlib").Path(files("nan2.obj")).exists()


def test_soup_mesh_welded_for_the_rig(files, capsys):
    """The unwelded triangle soup of the issue: ``synth --mesh`` welds it back (a warning
    says so) so the rig is built on the real mesh; ``build_rig`` refuses a soup at once."""
    import trimesh

    from jaxface.anatomy.rig import build_rig
    from jaxface.commands.clone import load_face
    from jaxface.errors import MeshError
    from jaxface.head import generic_head
    from jaxface.landmarks import write_lm3

    head = generic_head()
    m = head.mesh
    sv = m.vertices[m.triangles].reshape(-1, 3)
    st = np.arange(len(sv)).reshape(-1, 3)
    soup = files("soup.ply")
    tm = trimesh.Trimesh(sv, st, process=False, validate=False)
    with open(soup, "wb") as fh:
        fh.write(trimesh.exchange.ply.export_ply(tm, encoding="binary"))
    write_lm3(files("soup.lm3"), head.landmarks)
    mesh, lm = load_face(soup, "mm", None, "face mesh", clean=True)
    err = capsys.readouterr().err
    assert "welded" in err
    used = np.unique(m.triangles)
    assert mesh.n_vertices == len(used) and mesh.n_triangles == m.n_triangles
    mesh.validate()
    with pytest.raises(MeshError, match="unwelded"):
        build_rig(TriMesh(sv, st, validate=False), head.landmarks)


def test_huge_mesh_refused_with_the_limit(capsys):
    from jaxface.anatomy.rig import build_rig
    from jaxface.errors import MeshError
    from jaxface.head import generic_head
    from jaxface.hygiene import MAX_RIG_VERTICES

    head = generic_head()
    n = MAX_RIG_VERTICES + 1
    v = np.random.default_rng(0).normal(0.0, 50.0, (n, 3))
    t = np.arange(3 * (n // 3)).reshape(-1, 3)
    with pytest.raises(MeshError, match=f"{MAX_RIG_VERTICES}") as ei:
        build_rig(TriMesh(v, t, validate=False), head.landmarks)
    assert ei.value.problem == "too_large"
