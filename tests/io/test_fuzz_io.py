"""Fuzzing the file readers and writers (issue 49): truncated files at every section of
``.bnt`` / ``.lm3`` / ``.ply`` / ``.obj``, random bytes, absurd headers, huge values, NaN,
missing / duplicated / misspelled labels, folders given as files, atomic and NaN-free writes,
and mesh hygiene. Every bad input must raise a :class:`jaxface.errors.JaxfaceError` (never
another exception, never a silent result)."""

from __future__ import annotations

import json
import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxface.atomic import ensure_out_dir, write_json_atomic, write_text_atomic
from jaxface.errors import (
    DataNotFoundError,
    InputPathError,
    JaxfaceError,
    LandmarkError,
    MeshError,
    OutputError,
    RBFError,
    ScanFormatError,
)
from jaxface.hygiene import HygieneReport, clean_mesh, weld_vertices
from jaxface.io.bosphorus import read_bnt, write_bnt
from jaxface.landmarks import (
    BOSPHORUS_LABELS,
    LandmarkLabelWarning,
    Landmarks,
    fuzzy_label,
    read_lm3,
    write_lm3,
)
from jaxface.mesh import TriMesh, load_mesh, save_mesh

FUZZ = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


# ------------------------------------------------------------------------- small fixtures
def _grid_mesh(n: int = 12, size: float = 120.0) -> TriMesh:
    """A bumpy ``n`` x ``n`` grid, ``size`` mm wide (face-sized, +z up), counter-clockwise."""
    x, y = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n))
    z = 10.0 * np.cos(x / 40.0) * np.cos(y / 40.0)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    t = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    return TriMesh(v, t)


def _landmarks(n: int = 22) -> Landmarks:
    rng = np.random.default_rng(1)
    return Landmarks(BOSPHORUS_LABELS[:n], rng.normal(0.0, 40.0, (n, 3)))


def _bnt_bytes(tmp_path) -> bytes:
    from jaxface.io.bosphorus import Scan

    rng = np.random.default_rng(0)
    nr, nc = 6, 5
    x, y = np.meshgrid(np.linspace(-60, 60, nc), np.linspace(60, -60, nr))
    xyz = np.stack([x, y, 50 + rng.normal(0, 1, x.shape)], -1)
    scan = Scan.from_grid(xyz, image_name="face.png")
    p = tmp_path / "ok.bnt"
    write_bnt(p, scan)
    return p.read_bytes()


def _expect_clean_error(fn, *errors):
    """``fn()`` raises one of ``errors`` (default any JaxfaceError) with a message."""
    errors = errors or (JaxfaceError,)
    with pytest.raises(errors) as ei:
        fn()
    assert str(ei.value).strip(), "an error without a message"
    return ei.value


# ------------------------------------------------------------------------- .bnt
def test_bnt_truncated_at_every_section(tmp_path):
    data = _bnt_bytes(tmp_path)
    name_len = struct.unpack_from("<H", data, 12)[0]
    sections = {
        "empty": 0,
        "in the header": 7,
        "after the header": 12,
        "in the name length": 13,
        "in the image name": 14 + name_len // 2,
        "after the name": 14 + name_len,
        "in the plane count": 16 + name_len,
        "after the plane count": 18 + name_len,
        "in the x plane": 18 + name_len + 40,
        "one byte short": len(data) - 1,
    }
    assert read_bnt(tmp_path / "ok.bnt").n_points == 30
    for what, cut in sections.items():
        p = tmp_path / "cut.bnt"
        p.write_bytes(data[:cut])
        err = _expect_clean_error(lambda: read_bnt(p), ScanFormatError)
        assert str(p) in str(err), what


def test_bnt_absurd_headers_do_not_allocate(tmp_path):
    data = bytearray(_bnt_bytes(tmp_path))
    cases = {
        "65535 x 65535 grid": struct.pack("<HHd", 65535, 65535, -1e9),
        "zero rows": struct.pack("<HHd", 0, 5, -1e9),
        "NaN zmin": struct.pack("<HHd", 6, 5, float("nan")),
    }
    for what, header in cases.items():
        p = tmp_path / "bad.bnt"
        p.write_bytes(bytes(header) + bytes(data[12:]))
        err = _expect_clean_error(lambda: read_bnt(p), ScanFormatError)
        assert str(p) in str(err), what
    # a plane count that disagrees with the grid
    bad = bytearray(data)
    n = struct.unpack_from("<H", bad, 12)[0]
    struct.pack_into("<I", bad, 14 + n, 0xFFFFFFFF)
    p = tmp_path / "count.bnt"
    p.write_bytes(bytes(bad))
    _expect_clean_error(lambda: read_bnt(p), ScanFormatError)


def test_bnt_huge_and_nan_values_refused(tmp_path):
    data = bytearray(_bnt_bytes(tmp_path))
    n = struct.unpack_from("<H", data, 12)[0]
    off = 18 + n
    for val in (1e300, float("nan"), float("inf")):
        bad = bytearray(data)
        struct.pack_into("<d", bad, off + 8 * 3, val)  # x of the 4th pixel
        p = tmp_path / "v.bnt"
        p.write_bytes(bytes(bad))
        _expect_clean_error(lambda: read_bnt(p), JaxfaceError)


@FUZZ
@given(st.binary(min_size=0, max_size=400))
def test_random_bytes_as_any_format(tmp_path_factory, blob):
    d = tmp_path_factory.mktemp("rnd")
    for suffix, reader in (
        (".bnt", read_bnt),
        (".lm3", read_lm3),
        (".ply", load_mesh),
        (".obj", load_mesh),
    ):
        p = d / f"x{suffix}"
        p.write_bytes(blob)
        try:
            reader(p)
        except JaxfaceError as e:
            assert str(e)
        # success is allowed only for a readable file: then it holds finite data
    with pytest.raises(JaxfaceError):
        read_bnt(d / "missing.bnt")


def test_folder_named_like_a_file(tmp_path):
    for name, reader in (
        ("x.bnt", read_bnt),
        ("x.lm3", read_lm3),
        ("x.ply", load_mesh),
        ("x.obj", load_mesh),
    ):
        (tmp_path / name).mkdir()
        err = _expect_clean_error(lambda: reader(tmp_path / name), InputPathError)
        assert "is a folder" in str(err)
    err = _expect_clean_error(lambda: read_bnt(tmp_path / "nope.bnt"), DataNotFoundError)
    assert "not found" in str(err)


def test_write_bnt_refuses_nan(tmp_path):
    from jaxface.io.bosphorus import Scan

    data = _bnt_bytes(tmp_path)
    scan = read_bnt(tmp_path / "ok.bnt")
    pts = scan.points.copy()
    pts[3, 1] = np.nan
    bad = Scan(**{**scan.__dict__, "points": pts})
    p = tmp_path / "out.bnt"
    _expect_clean_error(lambda: write_bnt(p, bad), ScanFormatError)
    assert not p.exists()
    assert (tmp_path / "ok.bnt").read_bytes() == data


# ------------------------------------------------------------------------- .lm3
def _lm3_text(lm: Landmarks) -> str:
    out = ["# test", "", f"{len(lm)} landmarks:"]
    for n, p in zip(lm.names, lm.positions):
        out += [n, f"{p[0]:.4f} {p[1]:.4f} {p[2]:.4f}"]
    return "\n".join(out) + "\n"


def test_lm3_truncated_at_every_line(tmp_path):
    text = _lm3_text(_landmarks(5))
    lines = text.splitlines()
    p = tmp_path / "a.lm3"
    for k in range(len(lines)):
        p.write_text("\n".join(lines[:k]) + "\n")
        _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    # a coordinate line cut in the middle of its numbers
    p.write_text("\n".join(lines[:-1] + [lines[-1].rsplit(" ", 1)[0]]) + "\n")
    _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    p.write_text(text)
    assert len(read_lm3(p)) == 5


def test_lm3_header_count_disagrees(tmp_path):
    lm = _landmarks(22)
    text = _lm3_text(lm)
    p = tmp_path / "a.lm3"
    p.write_text(text.replace("22 landmarks:", "5 landmarks:"))
    err = _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    assert "5 landmarks" in str(err) and "more" in str(err)
    p.write_text(text.replace("22 landmarks:", "40 landmarks:"))
    _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    p.write_text(text.replace("22 landmarks:", "99999999999999 landmarks:"))
    _expect_clean_error(lambda: read_lm3(p), ScanFormatError)


def test_lm3_misspelled_labels_matched_with_warning(tmp_path):
    lm = _landmarks(22)
    text = _lm3_text(lm).replace("Nose tip\n", "Nose tipp\n").replace("Chin middle", "Chin centre")
    p = tmp_path / "a.lm3"
    p.write_text(text)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        got = read_lm3(p)
    assert "Nose tip" in got.names and "Chin middle" in got.names
    np.testing.assert_allclose(got["Nose tip"], lm["Nose tip"], atol=1e-4)
    msgs = [str(x.message) for x in w if issubclass(x.category, LandmarkLabelWarning)]
    assert any("'Nose tipp' -> 'Nose tip'" in m for m in msgs)


def test_lm3_unknown_labels_listed(tmp_path):
    lm = _landmarks(6)
    text = _lm3_text(lm).replace("Outer left eyebrow", "Glabella thing")
    p = tmp_path / "a.lm3"
    p.write_text(text)
    with pytest.warns(LandmarkLabelWarning, match="Glabella thing"):
        got = read_lm3(p)
    err = _expect_clean_error(lambda: got.require(["Outer left eyebrow"]), LandmarkError)
    assert "Outer left eyebrow" in str(err)


def test_lm3_duplicate_and_nonfinite(tmp_path):
    lm = _landmarks(4)
    text = _lm3_text(lm)
    p = tmp_path / "a.lm3"
    p.write_text(text.replace("Middle left eyebrow", "Outer left eyebrow"))
    err = _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    assert "twice" in str(err)
    # a misspelling that lands on a label already present is a duplicate too
    p.write_text(text.replace("Middle left eyebrow", "Outer left eyebrw"))
    _expect_clean_error(lambda: read_lm3(p), ScanFormatError)
    first = f"{lm.positions[0][0]:.4f}"
    for bad in ("nan", "inf", "1e400", "x"):
        p.write_text(text.replace(first, bad, 1))
        _expect_clean_error(lambda: read_lm3(p), ScanFormatError)


@pytest.mark.parametrize(
    "text,expect",
    [
        ("Nose tipp", "Nose tip"),
        ("Left nose peek", "Left nose peak"),
        ("Outer left eyebow", "Outer left eyebrow"),
        ("Inner right eye coner", "Inner right eye corner"),
        ("Chin centre", "Chin middle"),
        ("Nose", None),  # too far from any label
        ("Lft mouth corner", None),  # side word misspelled: never guess a side
        ("banana", None),
    ],
)
def test_fuzzy_label(text, expect):
    got = fuzzy_label(text)
    assert (got[0] if got else None) == expect


def test_fuzzy_label_never_swaps_sides():
    for lbl in BOSPHORUS_LABELS:
        typo = lbl[:-1]  # drop the last letter
        got = fuzzy_label(typo)
        if got is not None:
            assert ("left" in got[0].lower()) == ("left" in lbl.lower())
            assert ("right" in got[0].lower()) == ("right" in lbl.lower())


# ------------------------------------------------------------------------- .ply / .obj
def _ply_ascii(mesh: TriMesh) -> str:
    v, t = mesh.vertices, mesh.triangles
    head = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(t)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [f"{a:.5f} {b:.5f} {c:.5f}" for a, b, c in v] + [f"3 {a} {b} {c}" for a, b, c in t]
    return "\n".join(head + body) + "\n"


def test_ply_truncated_at_every_section(tmp_path):
    mesh = _grid_mesh()
    p = tmp_path / "m.ply"
    save_mesh(p, mesh)
    data = p.read_bytes()
    hdr = data.index(b"end_header") + len(b"end_header\n")
    nv = mesh.n_vertices
    cuts = {
        "empty": 0,
        "in the magic": 2,
        "in the header": hdr // 2,
        "after the header": hdr,
        "in the vertices": hdr + 12 * nv // 2,
        "after the vertices": hdr + 12 * nv,
        "in the faces": (hdr + 12 * nv + len(data)) // 2,
        "one byte short": len(data) - 1,
    }
    for what, cut in cuts.items():
        q = tmp_path / "cut.ply"
        q.write_bytes(data[:cut])
        err = _expect_clean_error(lambda: load_mesh(q), MeshError)
        assert str(q) in str(err), what
    text = _ply_ascii(mesh)
    lines = text.splitlines()
    for k in (0, 3, 9, 9 + nv // 2, 9 + nv, len(lines) - 1):
        q = tmp_path / "cut_ascii.ply"
        q.write_text("\n".join(lines[:k]) + "\n")
        _expect_clean_error(lambda: load_mesh(q), MeshError)


def test_ply_absurd_header_and_huge_values(tmp_path):
    mesh = _grid_mesh()
    text = _ply_ascii(mesh)
    p = tmp_path / "a.ply"
    p.write_text(text.replace(f"element vertex {mesh.n_vertices}", "element vertex 99999999999"))
    _expect_clean_error(lambda: load_mesh(p), MeshError)
    p.write_text(text.replace(f"element vertex {mesh.n_vertices}", "element vertex -5"))
    _expect_clean_error(lambda: load_mesh(p), MeshError)
    p.write_text(text.replace(f"element face {mesh.n_triangles}", "element face lots"))
    _expect_clean_error(lambda: load_mesh(p), MeshError)
    huge = mesh.with_vertices(mesh.vertices * 1e30)
    q = tmp_path / "huge.ply"
    save_mesh(q, huge, encoding="ascii")
    _expect_clean_error(lambda: load_mesh(q), JaxfaceError)  # implausible size (units)


def test_nan_vertices_refused_on_read_with_count_and_first(tmp_path):
    mesh = _grid_mesh()
    v = mesh.vertices.copy()
    v[[7, 20, 21]] = np.nan
    text = _ply_ascii(TriMesh(mesh.vertices, mesh.triangles)).splitlines()
    for i in (7, 20, 21):
        text[9 + i] = "nan nan nan"
    p = tmp_path / "nan.ply"
    p.write_text("\n".join(text) + "\n")
    for validate in (True, False):
        err = _expect_clean_error(lambda: load_mesh(p, validate=validate), MeshError)
        assert err.problem == "nonfinite_vertices"
        assert "3 of" in str(err) and "vertex 7" in str(err)
    # the binary case of the issue: a binary PLY with NaN vertices
    import trimesh

    tm = trimesh.Trimesh(v, mesh.triangles, process=False, validate=False)
    b = tmp_path / "nan_bin.ply"
    b.write_bytes(trimesh.exchange.ply.export_ply(tm, encoding="binary"))
    err = _expect_clean_error(lambda: load_mesh(b, validate=False), MeshError)
    assert err.elements[0] == 7


def test_save_mesh_refuses_nan_and_keeps_old_file(tmp_path):
    mesh = _grid_mesh()
    for suffix in (".ply", ".obj"):
        p = tmp_path / f"m{suffix}"
        save_mesh(p, mesh)
        before = p.read_bytes()
        v = mesh.vertices.copy()
        v[3, 2] = np.inf
        err = _expect_clean_error(lambda: save_mesh(p, v, mesh.triangles), MeshError)
        assert "vertex 3" in str(err)
        assert p.read_bytes() == before
    assert not [q for q in tmp_path.iterdir() if ".tmp" in q.name]


def test_obj_truncated_and_garbage(tmp_path):
    mesh = _grid_mesh()
    p = tmp_path / "m.obj"
    save_mesh(p, mesh)
    text = p.read_text()
    for cut in (0, 10, len(text) // 3, len(text) - 3):
        q = tmp_path / "cut.obj"
        q.write_text(text[:cut])
        try:
            got = load_mesh(q)
        except JaxfaceError:
            continue
        # a cut exactly between lines leaves a smaller but whole mesh; it must be finite
        assert np.all(np.isfinite(got.vertices))
    q.write_text(text.replace("v ", "v nan ", 1))
    _expect_clean_error(lambda: load_mesh(q), MeshError)
    q.write_text(text + "f 1 2 999999\n")
    _expect_clean_error(lambda: load_mesh(q), MeshError)


# ------------------------------------------------------------------------- hygiene
def test_triangle_soup_welded_back_to_the_mesh():
    mesh = _grid_mesh()
    soup_v = mesh.vertices[mesh.triangles].reshape(-1, 3)
    soup_t = np.arange(len(soup_v)).reshape(-1, 3)
    clean, rep = clean_mesh(TriMesh(soup_v, soup_t, validate=False))
    assert rep.welded_vertices == len(soup_v) - mesh.n_vertices
    assert clean.n_vertices == mesh.n_vertices and clean.n_triangles == mesh.n_triangles
    clean.validate()  # manifold and consistently oriented again
    # same triangles, as sets of positions
    key = lambda v, t: sorted(map(tuple, np.round(np.sort(v[t], axis=1), 6).reshape(len(t), -1)))  # noqa: E731
    assert key(clean.vertices, clean.triangles) == key(mesh.vertices, mesh.triangles)


def test_hygiene_drops_degenerate_and_repeated_and_unused():
    mesh = _grid_mesh()
    mid = 0.5 * (mesh.vertices[0] + mesh.vertices[1])
    n = mesh.n_vertices
    v = np.concatenate([mesh.vertices, [[0.0, 0.0, 500.0], mid]])  # n: unused, n + 1: midpoint
    t = np.concatenate([mesh.triangles, mesh.triangles[:3], [[0, 0, 1], [0, n + 1, 1]]])
    clean, rep = clean_mesh(TriMesh(v, t, validate=False))
    # a repeated id and a zero-area sliver; 3 repeated triangles; the far vertex and the
    # sliver's midpoint are left unused
    assert rep == HygieneReport(0, 2, 3, 2)
    assert "degenerate" in rep.describe()
    assert clean.n_triangles == mesh.n_triangles and clean.n_vertices == mesh.n_vertices


def test_hygiene_refuses_nan_and_huge():
    mesh = _grid_mesh()
    v = mesh.vertices.copy()
    v[5] = np.nan
    err = _expect_clean_error(lambda: clean_mesh(TriMesh(v, mesh.triangles, validate=False)))
    assert err.problem == "nonfinite_vertices" and "vertex 5" in str(err)
    err = _expect_clean_error(lambda: clean_mesh(mesh, max_vertices=100), MeshError)
    assert err.problem == "too_large" and "100" in str(err)


def test_weld_keeps_first_vertex_order():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 1, 0]], float)
    nv, nt, n = weld_vertices(v, np.array([[0, 1, 3], [2, 3, 1]]))
    assert n == 1
    np.testing.assert_array_equal(nv, v[[0, 1, 3]])
    np.testing.assert_array_equal(nt, [[0, 1, 2], [0, 2, 1]])


# ------------------------------------------------------------------------- outputs
def test_out_dir_under_a_file(tmp_path):
    f = tmp_path / "a_file.txt"
    f.write_text("x")
    err = _expect_clean_error(lambda: ensure_out_dir(f / "sub"), OutputError)
    assert "is a file" in str(err)
    err = _expect_clean_error(lambda: ensure_out_dir(f), OutputError)
    assert ensure_out_dir(tmp_path / "new" / "deep").is_dir()


def test_json_writer_refuses_nan_with_key_path(tmp_path):
    p = tmp_path / "a.json"
    write_json_atomic(p, {"a": 1.0})
    err = _expect_clean_error(
        lambda: write_json_atomic(p, {"a": {"b": [1.0, float("nan")]}}), OutputError
    )
    assert "a.b[1]" in str(err)
    assert json.loads(p.read_text()) == {"a": 1.0}
    err = _expect_clean_error(
        lambda: write_json_atomic(p, {"x": np.array([1.0, np.inf])}), OutputError
    )


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    from jaxface.atomic import atomic_path

    p = tmp_path / "a.txt"
    write_text_atomic(p, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert p.read_text() == "old"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.txt"]
    _expect_clean_error(lambda: write_text_atomic(tmp_path, "x"), OutputError)
    _expect_clean_error(lambda: write_text_atomic(tmp_path / "no" / "a.txt", "x"), OutputError)


def test_write_lm3_round_trip_atomic(tmp_path):
    lm = _landmarks(22)
    p = tmp_path / "a.lm3"
    write_lm3(p, lm)
    got = read_lm3(p)
    np.testing.assert_allclose(got.positions, lm.positions, atol=1e-6)
    with pytest.raises(LandmarkError):
        Landmarks(["Nose tip"], [[np.nan, 0, 0]])


# ------------------------------------------------------------------------- rbf
@pytest.mark.parametrize("reg", [-1.0, -1e-12, float("nan"), float("inf")])
def test_rbf_bad_reg_refused(reg):
    from jaxface import rbf

    src = np.random.default_rng(0).normal(0, 30, (12, 3))
    for fit in (rbf.fit, rbf.fit_numpy):
        err = _expect_clean_error(lambda: fit(src, src, reg=reg), RBFError)
        assert "reg" in str(err)
    _expect_clean_error(lambda: rbf.fit(src, src, radius_scale=0.0), RBFError)
