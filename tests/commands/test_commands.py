"""The ``convert``, ``clone`` and ``bench`` sub-commands run as a user runs them (a subprocess
of ``python -m jaxface.cli``), and the virtual range scanner behind ``convert``.

References: the scanner against :meth:`jaxface.mesh.TriMesh.ray_cast` (an independent ray
caster) and an analytic plane; ``.bnt`` -> mesh -> ``.bnt`` against the original grid points;
unit conversion against the exact factors; cloning onto an affine image of the source against
the analytic answer (every cloned displacement is ``A d``); ``bench`` against small scripts
whose outcome is known.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from jaxface.cli import EXIT_ERROR, EXIT_MISSING, EXIT_USAGE


def run_cli(*args, cwd=None, timeout=300):
    env = dict(os.environ, MPLBACKEND="Agg", COLUMNS="200")
    return subprocess.run(
        [sys.executable, "-m", "jaxface.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=timeout,
    )


def run_main(capsys, *args):
    """The same command in-process (``jaxface.cli.main``): ``(exit code, stderr)``."""
    from jaxface.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def keyed(points, res=1.0):
    """{(round(x / res), round(y / res)): z} of grid points (mm)."""
    k = np.round(np.asarray(points)[:, :2] / res).astype(np.int64)
    return {(int(a), int(b)): float(z) for (a, b), z in zip(k, np.asarray(points)[:, 2])}


@pytest.fixture(scope="module")
def head():
    from jaxface.head import generic_head

    return generic_head()


@pytest.fixture(scope="module")
def head_files(head, tmp_path_factory):
    from jaxface.landmarks import write_lm3
    from jaxface.mesh import save_mesh

    d = tmp_path_factory.mktemp("head")
    save_mesh(d / "head.ply", head.mesh)
    write_lm3(d / "head.lm3", head.landmarks)
    return d


# ------------------------------------------------------------------------------- scanner
def test_scanner_matches_ray_cast(head):
    from jaxface.io.scanner import scan_mesh

    scan, hits = scan_mesh(head.mesh, 2.0, return_hits=True)
    assert scan.is_grid and scan.shape == hits.shape
    X, Y = np.meshgrid(hits.xs, hits.ys)
    np.testing.assert_allclose(hits.xs / 2.0, np.round(hits.xs / 2.0))  # nodes on multiples
    idx = np.random.default_rng(0).choice(X.size, 1500, replace=False)
    top = head.mesh.bounds[1, 2] + 10.0
    o = np.stack([X.ravel()[idx], Y.ravel()[idx], np.full(idx.size, top)], 1)
    ref = head.mesh.ray_cast(o, np.array([0.0, 0.0, -1.0]))
    assert ref.hit.sum() > 500
    np.testing.assert_array_equal(ref.hit, hits.valid.ravel()[idx])
    np.testing.assert_allclose(
        hits.xyz.reshape(-1, 3)[idx][ref.hit, 2], top - ref.first_distance[ref.hit], atol=1e-9
    )
    # the scan's points are the valid pixels in row-major order, rows bottom to top
    np.testing.assert_allclose(scan.points, hits.xyz[hits.valid])
    assert np.all(np.diff(hits.ys) > 0)
    # the same surface points re-evaluated on the undeformed vertices
    np.testing.assert_allclose(
        hits.positions(head.mesh.vertices)[hits.valid], scan.points, atol=1e-9
    )
    moved = head.mesh.vertices + np.array([1.0, -2.0, 3.0])
    np.testing.assert_allclose(hits.sample(moved), scan.points + [1.0, -2.0, 3.0], atol=1e-9)


def test_scanner_plane_layers_angle_and_errors():
    from jaxface.errors import MeshError, ScanFormatError
    from jaxface.io.scanner import scan_mesh

    # two parallel tilted squares 5 mm apart: the front one (larger z) is seen, at the
    # analytic depth z = 0.2 x - 0.1 y + c
    g = np.linspace(-20, 20, 9)
    X, Y = np.meshgrid(g, g)
    V0 = np.c_[X.ravel(), Y.ravel(), 0.2 * X.ravel() - 0.1 * Y.ravel()]
    i = np.arange(8)[:, None] * 9 + np.arange(8)[None]
    q = np.stack([i.ravel(), i.ravel() + 1, i.ravel() + 10, i.ravel() + 9], 1)
    T0 = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    V = np.concatenate([V0 + [0, 0, 30.0], V0 + [0, 0, 35.0]])
    T = np.concatenate([T0, T0 + 81])
    scan = scan_mesh((V, T), 0.5)
    p = scan.points
    assert scan.shape == (81, 81) and scan.n_points == 81 * 81
    np.testing.assert_allclose(p[:, 2], 0.2 * p[:, 0] - 0.1 * p[:, 1] + 35.0, atol=1e-9)
    # steep surfaces are dropped by the angle cut-off (this plane is 12.6 degrees from +z)
    assert scan_mesh((V, T), 1.0, max_angle_deg=13.0).n_points == 41 * 41
    with pytest.raises(ScanFormatError, match="no ray"):
        scan_mesh((V, T), 1.0, max_angle_deg=12.0)
    noisy = scan_mesh((V, T), 1.0, noise_mm=0.1, seed=1)
    assert (
        0.07
        < np.std(noisy.points[:, 2] - (0.2 * noisy.points[:, 0] - 0.1 * noisy.points[:, 1] + 35))
        < 0.13
    )
    with pytest.raises(ScanFormatError, match="resolution"):
        scan_mesh((V, T), 0.0)
    with pytest.raises(ScanFormatError, match="too large"):
        scan_mesh((V * 1000.0, T), 0.5)  # metres read as mm
    with pytest.raises(ScanFormatError, match="no ray"):
        scan_mesh((V, T), 1.0, bounds=((100, 100), (120, 120)))
    bad = V.copy()
    bad[3] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        scan_mesh((bad, T), 1.0)


# ------------------------------------------------------------------------------- convert
def test_convert_round_trip_synthetic_head(head, head_files, tmp_path):
    """default head (PLY) -> .bnt (virtual scan) -> PLY (grid meshing) -> .bnt: the second
    scan gives back every point of the meshed grid (float32 PLY precision)."""
    from jaxface.io import load_scan, read_bnt
    from jaxface.io.scanner import scan_mesh
    from jaxface.landmarks import read_lm3
    from jaxface.mesh import load_mesh

    a, b, c = tmp_path / "scan.bnt", tmp_path / "scan.ply", tmp_path / "rescan.bnt"
    p = run_cli("convert", head_files / "head.ply", a, "--resolution", 1.0)
    assert p.returncode == 0, p.stderr
    assert "range grid" in p.stderr and "scan.lm3" in p.stderr
    s1 = load_scan(a)
    ref = scan_mesh(load_mesh(head_files / "head.ply"), 1.0)
    assert s1.shape == ref.shape
    np.testing.assert_allclose(s1.points, ref.points, atol=1e-12)
    assert s1.image_name == "scan.png"
    np.testing.assert_allclose(s1.landmarks.positions, head.landmarks.positions, atol=1e-6)

    p = run_cli("convert", a, b)
    assert p.returncode == 0, p.stderr
    mesh = load_mesh(b, validate=False)
    m_ref = s1.to_mesh()
    assert (mesh.n_vertices, mesh.n_triangles) == (m_ref.n_vertices, m_ref.n_triangles)
    np.testing.assert_allclose(mesh.vertices, m_ref.vertices, atol=1e-4)
    p = run_cli("convert", b, c, "-r", 1)
    assert p.returncode == 0, p.stderr
    s2 = read_bnt(c)
    k1, k2 = keyed(mesh.vertices), keyed(s2.points)
    assert set(k1) == set(k2)
    assert max(abs(k1[k] - k2[k]) for k in k1) < 1e-4
    assert s1.n_points - s2.n_points < 0.05 * s1.n_points  # only unmeshed pixels are lost
    np.testing.assert_allclose(
        read_lm3(c.with_suffix(".lm3")).positions, head.landmarks.positions, atol=1e-5
    )


def test_convert_round_trip_shared_bnt(shared, tmp_path):
    from jaxface.io import load_scan, read_bnt
    from jaxface.landmarks import read_lm3
    from jaxface.mesh import load_mesh

    src = shared("data", "bosphorus_style", "bs900_N_N_0.bnt")
    ply, bnt = tmp_path / "n.ply", tmp_path / "n.bnt"
    p = run_cli("convert", src, ply)
    assert p.returncode == 0, p.stderr
    scan = load_scan(src)
    mesh = load_mesh(ply, validate=False)
    ref = scan.to_mesh()
    np.testing.assert_array_equal(mesh.triangles, ref.triangles)
    np.testing.assert_allclose(mesh.vertices, ref.vertices, atol=1e-4)
    p = run_cli("convert", ply, bnt, "--resolution", 1.0)
    assert p.returncode == 0, p.stderr
    back = read_bnt(bnt)
    k0, k1 = keyed(ref.vertices), keyed(back.points)
    assert set(k0) == set(k1) and len(k0) > 27000
    assert max(abs(k0[k] - k1[k]) for k in k0) < 1e-4
    np.testing.assert_allclose(back.xyz_grid()[back.valid][:, :2], np.round(back.points[:, :2]))
    np.testing.assert_allclose(
        read_lm3(bnt.with_suffix(".lm3")).positions, scan.landmarks.positions, atol=1e-6
    )


def test_convert_units(head, head_files, tmp_path, capsys):
    from jaxface.io import read_bnt
    from jaxface.landmarks import read_lm3
    from jaxface.mesh import load_mesh

    obj, ply = tmp_path / "head_cm.obj", tmp_path / "head_m.ply"
    p = run_cli("convert", head_files / "head.ply", obj, "--out-units", "cm")
    assert p.returncode == 0, p.stderr
    raw = load_mesh(obj, units="mm", check_size=False)  # the numbers in the file
    np.testing.assert_allclose(raw.vertices, head.mesh.vertices / 10.0, atol=1e-6)
    np.testing.assert_array_equal(raw.triangles, head.mesh.triangles)
    np.testing.assert_allclose(
        read_lm3(obj.with_suffix(".lm3")).positions, head.landmarks.positions / 10.0, atol=1e-6
    )
    code, err = run_main(capsys, "convert", obj, ply, "--in-units", "cm", "--out-units", "m")
    assert code == 0, err
    np.testing.assert_allclose(
        load_mesh(ply, units="mm", check_size=False).vertices,
        head.mesh.vertices / 1000.0,
        atol=1e-7,
    )
    np.testing.assert_allclose(load_mesh(ply, units="m").vertices, head.mesh.vertices, atol=1e-4)
    # a .bnt scan of a mesh given in metres, written in cm: 2 mm grid -> 0.2 apart in the file
    bnt = tmp_path / "head_cm.bnt"
    code, err = run_main(
        capsys, "convert", ply, bnt, "--in-units", "m", "--out-units", "cm", "-r", 2
    )
    assert code == 0, err
    s = read_bnt(bnt, units="cm")
    np.testing.assert_allclose(np.diff(np.unique(s.points[:, 0]))[:5], 2.0, atol=1e-9)
    raw = read_bnt(bnt, check_size=False)
    assert 15 < np.ptp(raw.points[:, 0]) < 20  # 167 mm wide head, in cm


def test_convert_bad_inputs(head_files, tmp_path, capsys):
    p = run_cli("convert", tmp_path / "missing.ply", tmp_path / "x.bnt")
    assert p.returncode == EXIT_MISSING and "not found" in p.stderr and "missing.ply" in p.stderr
    bnt = tmp_path / "truncated.bnt"
    bnt.write_bytes(b"\x10\x00\x10\x00" + b"\x00" * 20)
    p = run_cli("convert", bnt, tmp_path / "x.ply")
    assert p.returncode == EXIT_USAGE and "truncated" in p.stderr and "truncated.bnt" in p.stderr
    # the same code path in-process (cheaper than a subprocess each)
    code, err = run_main(capsys, "convert", head_files / "head.ply", tmp_path / "x.stl")
    assert code == EXIT_USAGE and "'.stl'" in err and ".bnt, .ply or .obj" in err
    # a millimetre mesh declared in metres: the size check explains which unit fits
    code, err = run_main(
        capsys, "convert", head_files / "head.ply", tmp_path / "x.obj", "--in-units", "m"
    )
    assert code == EXIT_USAGE and "units='mm'" in err and "--in-units" in err
    code, err = run_main(
        capsys, "convert", head_files / "head.ply", tmp_path / "x.obj", "--in-units", "inch"
    )
    assert code == EXIT_USAGE and "--in-units" in err
    code, err = run_main(
        capsys, "convert", head_files / "head.ply", tmp_path / "y.bnt", "--bounds=1,2,3"
    )
    assert code == EXIT_USAGE and "XMIN,YMIN,XMAX,YMAX" in err
    assert not list(tmp_path.glob("x.*")) and not (tmp_path / "y.bnt").exists()


# ------------------------------------------------------------------------------- clone
@pytest.fixture(scope="module")
def clone_case(head, tmp_path_factory):
    """Source: the face region of the default head with two bump morph targets (cheek and
    brow, away from the mouth and eye slits); target: an affine image of the source."""
    from jaxface.landmarks import write_lm3
    from jaxface.mesh import save_mesh

    d = tmp_path_factory.mktemp("clone")
    m = head.mesh
    src, _ = m.submesh(head.face_mask[m.triangles].all(1))
    V, lm = src.vertices, head.landmarks
    A = np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.0], [0.0, 0.0, 1.05]])
    t = np.array([2.0, -3.0, 4.0])
    save_mesh(d / "src.ply", src)
    write_lm3(d / "src.lm3", lm)
    save_mesh(d / "tgt.ply", V @ A.T + t, src.triangles)
    write_lm3(d / "tgt.lm3", lm.transformed(A, t))
    (d / "targets").mkdir()
    c1 = 0.5 * (lm["Left nose peak"] + lm["Outer left eye corner"]) + [8.0, 0.0, 0.0]
    w1 = np.exp(-np.sum((V - c1) ** 2, 1) / 60.0)
    w2 = np.exp(-np.sum((V - lm["Inner right eyebrow"]) ** 2, 1) / 200.0)
    deltas = {
        "brow_r": np.c_[0 * w2, 2.5 * w2, 0 * w2],
        "cheek_l": np.c_[0 * w1, 2.0 * w1, 1.5 * w1],
    }
    for name, dl in deltas.items():
        save_mesh(d / "targets" / f"{name}.ply", V + dl, src.triangles)
    return d, A, deltas


def test_clone_affine_target_is_exact(clone_case):
    from jaxface.mesh import load_mesh

    d, A, deltas = clone_case
    out = d / "out"
    p = run_cli(
        "clone",
        "--source-neutral",
        d / "src.ply",
        "--source-targets",
        d / "targets",
        "--target",
        d / "tgt.ply",
        "--out",
        out,
    )
    assert p.returncode == 0, p.stderr
    assert "cloning targets" in p.stderr and "2/2" in p.stderr
    T = load_mesh(d / "tgt.ply", validate=False).vertices
    for name, dl in deltas.items():
        got = load_mesh(out / f"{name}.ply", validate=False).vertices - T
        moving = np.linalg.norm(dl, axis=1) > 0.01  # the default --move-tol
        assert moving.sum() > 100
        np.testing.assert_allclose(got[moving], dl[moving] @ A.T, atol=1e-4)  # float32 PLY
        np.testing.assert_allclose(got[~moving], 0.0, atol=1e-4)
    rep = json.loads((out / "clone.json").read_text())
    assert [t["name"] for t in rep["targets"]] == ["brow_r", "cheek_l"]
    assert rep["converged"] and rep["pairs"]["landmark"] == 24 and rep["pairs"]["refined"] == 0
    assert rep["targets"][0]["max_mm"] == pytest.approx(
        np.linalg.norm(deltas["brow_r"] @ A.T, axis=1).max(), abs=1e-3
    )


def test_clone_bad_inputs(clone_case, tmp_path, capsys):
    from jaxface.mesh import save_mesh

    d, _, _ = clone_case
    # a target without landmarks
    tgt = tmp_path / "bare.ply"
    tgt.write_bytes((d / "tgt.ply").read_bytes())
    p = run_cli("clone", "-s", d / "src.ply", "-t", d / "targets", "-T", tgt, "-o", tmp_path / "o")
    assert (
        p.returncode == EXIT_USAGE and "--target-landmarks" in p.stderr and "bare.lm3" in p.stderr
    )
    # a morph target with another vertex count
    bad = tmp_path / "bad_targets"
    bad.mkdir()
    save_mesh(bad / "small.ply", np.array([[0, 0, 0], [100.0, 0, 0], [0, 100.0, 0]]), [[0, 1, 2]])
    code, err = run_main(
        capsys,
        "clone",
        "-s",
        d / "src.ply",
        "-t",
        bad,
        "-T",
        d / "tgt.ply",
        "-o",
        tmp_path / "o",
        "--landmarks",
        "Nose tip,Left mouth corner,Right mouth corner",
    )
    assert code == EXIT_USAGE and "small.ply has 3 vertices" in err
    code, err = run_main(
        capsys,
        "clone",
        "-s",
        d / "src.ply",
        "-t",
        d / "targets",
        "-T",
        d / "tgt.ply",
        "-o",
        tmp_path / "o",
        "--landmarks",
        "Nose tip,Left pupil",
    )
    assert code == EXIT_USAGE and "Left pupil" in err
    code, err = run_main(
        capsys,
        "clone",
        "-s",
        d / "src.ply",
        "-t",
        tmp_path / "nothing",
        "-T",
        d / "tgt.ply",
        "-o",
        tmp_path / "o",
    )
    assert code == EXIT_MISSING and "nothing" in err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------- bench
def _bench_repo(root):
    b = root / "benchmarks"
    b.mkdir(parents=True)
    (b / "bench_good.py").write_text(
        textwrap.dedent("""
        import json, sys
        from pathlib import Path
        quick = "--quick" in sys.argv
        print("| case | value |")
        print("| sum  | %d |" % sum(range(10 if quick else 100)))
        out = Path(__file__).parent / "results"
        out.mkdir(exist_ok=True)
        (out / "bench_good.json").write_text(json.dumps({"quick": quick, "sum": sum(range(10 if quick else 100))}))
    """)
    )
    (b / "bench_broken.py").write_text(
        "import sys\nprint('starting')\nraise SystemExit('no data here')\n"
    )
    (b / "helper.py").write_text("raise RuntimeError('not a benchmark')\n")
    return b


def test_bench_runs_scripts_and_summarises(tmp_path):
    b = _bench_repo(tmp_path / "repo")
    sub = tmp_path / "repo" / "deep"
    sub.mkdir()
    # found from a sub-folder of the checkout; one script fails -> exit 1
    p = run_cli("bench", "--quick", "--json", tmp_path / "summary.json", cwd=sub)
    assert p.returncode == EXIT_ERROR, p.stderr
    assert "| sum  | 45 |" in p.stderr  # the script's own table
    assert "no data here" in p.stderr and "broken" in p.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    status = {r["name"]: r["status"] for r in summary["runs"]}
    assert status == {"bench_broken": "failed", "bench_good": "ok"}
    assert json.loads((b / "results" / "bench_good.json").read_text()) == {"quick": True, "sum": 45}
    # --only, without --quick
    p = run_cli("bench", "--only", "good", "--dir", b, "--no-output", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads((b / "results" / "bench_good.json").read_text()) == {
        "quick": False,
        "sum": 4950,
    }
    assert "| sum" not in p.stderr and "bench_good.json" in p.stderr


def test_help_lists_the_commands_with_examples(capsys):
    from jaxface.cli import main

    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(c in out for c in ("convert", "clone", "bench"))
    for cmd, example in (
        ("convert", "jaxface convert head.ply head.bnt"),
        ("clone", "jaxface clone -s"),
        ("bench", "jaxface bench --quick"),
    ):
        assert main([cmd, "--help"]) == 0
        assert example in capsys.readouterr().out


def test_bench_bad_inputs(tmp_path, capsys):
    b = _bench_repo(tmp_path / "repo")
    p = run_cli("bench", "--only", "nope", "--dir", b)
    assert p.returncode == EXIT_USAGE and "available: broken, good" in p.stderr
    code, err = run_main(capsys, "bench", "--dir", tmp_path / "nowhere")
    assert code == EXIT_MISSING and "no bench_*.py" in err
