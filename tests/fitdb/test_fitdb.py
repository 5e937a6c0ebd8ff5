"""``jaxface fit-db``: database discovery, the manifest, and one real run on a LocalCluster
with 2 worker processes over a small copy of the shared bs900/bs901 scans (quick fit
settings: two controls, one outer iteration).

The one cluster run (module fixture) carries several checks: every scan has a row; the
per-scan JSON and PLY equal a plain in-process ``run_fit`` of the same scan (the reference,
not fit-db against itself); a worker process killed at the start of bs901's first attempt
(the task's test hook, ``os._exit(1)``) still ends with bs901 fitted by Dask's retry; a
truncated .bnt is a failed row with its reason while the others are fitted; the parquet
columns. Then the CLI resumes into the same folder (from the folder and from a CSV
manifest) and fits nothing, and ``--summary`` prints the table per code.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import typer.main

from jaxface.cli import main
from jaxface.commands import fit, fitdb
from jaxface.commands.fit import run_fit
from jaxface.errors import DataNotFoundError, ScanFormatError
from jaxface.fit.options import FitOptions
from jaxface.fit.pipeline import SubjectOptions
from jaxface.fitdb.discover import discover_database, read_manifest
from jaxface.fitdb.runner import ClusterSpec, pending_jobs, run_database
from jaxface.fitdb.table import read_table, summarise
from jaxface.fitdb.task import CRASH_ONCE_ENV, FitSettings
from jaxface.mesh import load_mesh
from jaxface.testing import shared_path

CONTROLS = ("zygomaticus_major_L", "zygomaticus_major_R")
FITTED = ("bs900_LFAU_12_0", "bs901_LFAU_12_0")
CORRUPT = "bs900_UFAU_1_0"


def _link_scan(src_dir, dst_dir, stem):
    for ext in (".bnt", ".lm3"):
        (dst_dir / f"{stem}{ext}").symlink_to(src_dir / f"{stem}{ext}")


def _quick_settings():

    return FitSettings(
        options=FitOptions(
            n_points=200,
            outer_iterations=1,
            extra_iterations=0,
            restart_iterations=0,
            max_steps=5,
            jaw_starts=(0.0,),
            controls=CONTROLS,
        ),
        subject_options=SubjectOptions(levels=2, pitch_knots=3, controls=CONTROLS),
    )


# ------------------------------------------------------------------------------ discovery
@pytest.mark.data
def test_flat_and_subject_folder_layouts_give_the_same_jobs(tmp_path, shared):
    root = shared("data", "bosphorus_style")
    flat, nested = tmp_path / "flat", tmp_path / "nested"
    flat.mkdir()
    stems = ["bs900_N_N_0", "bs900_LFAU_12_0", "bs900_E_HAPPY_0", "bs901_N_N_0", "bs901_UFAU_4_0"]
    for stem in stems:
        _link_scan(root, flat, stem)
        sub = nested / stem[:5]
        sub.mkdir(parents=True, exist_ok=True)
        _link_scan(root, sub, stem)
    # a scan the database marks to be ignored, a subject without neutral, an unrelated file
    (flat / "bs900_IGN_X_0.bnt").symlink_to(root / "bs900_UFAU_2_0.bnt")
    (flat / "bs902_LFAU_9_0.bnt").symlink_to(root / "bs900_LFAU_9_0.bnt")
    (flat / "notes.bnt").write_text("not a scan name")
    a, b = discover_database(flat), discover_database(nested)
    assert [j.subject for j in a] == ["bs900", "bs901", "bs902"]
    assert a[0].neutral == flat / "bs900_N_N_0.bnt"
    assert [(e.stem, e.code) for e in a[0].scans] == [
        ("bs900_E_HAPPY_0", "E_HAPPY"),
        ("bs900_LFAU_12_0", "LFAU_12"),
    ]
    assert a[2].neutral is None and [e.stem for e in a[2].scans] == ["bs902_LFAU_9_0"]

    def key(jobs):
        return [
            (j.subject, Path(j.neutral or "").name, [(e.stem, e.code) for e in j.scans])
            for j in jobs
        ]

    assert key(a[:2]) == key(b)


def test_manifest_reads_relative_paths_and_rejects_bad_ones(tmp_path):
    m = tmp_path / "db.csv"
    m.write_text(
        "subject,neutral,scan,scan_landmarks,code\n"
        "s1,meshes/s1_neutral.ply,meshes/s1_smile.truth.ply,lm/s1_smile.lm3,smile\n"
        "s1,meshes/s1_neutral.ply,/abs/s1_frown.obj,,\n"
        "s0,n0.ply,bs000_LFAU_12L_0.ply,,\n"
    )
    jobs = read_manifest(m)
    assert [j.subject for j in jobs] == ["s0", "s1"]
    s0, s1 = jobs
    assert s0.scans[0].code == "LFAU_12L"  # a Bosphorus stem gives its code
    assert s1.neutral == tmp_path / "meshes" / "s1_neutral.ply"
    frown, smile = s1.scans
    assert (frown.stem, frown.code, str(frown.path)) == (
        "s1_frown",
        "s1_frown",
        "/abs/s1_frown.obj",
    )
    assert (smile.stem, smile.code) == ("s1_smile", "smile")  # .truth.ply: as jaxface fit names it
    assert smile.landmarks == tmp_path / "lm" / "s1_smile.lm3"
    assert discover_database(m) == jobs
    bad = tmp_path / "bad.csv"
    bad.write_text("subject,scan\ns1,a.ply\n")
    with pytest.raises(ScanFormatError, match="neutral"):
        read_manifest(bad)
    bad.write_text("subject,neutral,scan\ns1,a.ply,b.ply\ns1,c.ply,d.ply\n")
    with pytest.raises(ScanFormatError, match="another neutral"):
        read_manifest(bad)
    bad.write_text("subject,neutral,scan\ns1,a.ply,b.ply\ns1,a.ply,x/b.ply\n")
    with pytest.raises(ScanFormatError, match="twice"):
        read_manifest(bad)
    with pytest.raises(DataNotFoundError):
        discover_database(tmp_path / "missing")


def test_fit_db_has_every_fit_option_of_jaxface_fit_with_its_default():

    def params(mod):
        app = typer.Typer()
        mod.register(app)
        app.command("noop")(lambda: None)  # two commands: get_command gives a group
        return typer.main.get_command(app).commands  # type: ignore[attr-defined]

    fit_cmd = params(fit)["fit"]
    fitdb_cmd = params(fitdb)["fit-db"]
    per_call = {"neutral", "scan", "out", "neutral_landmarks", "scan_landmarks", "quiet"}
    theirs = {p.name: p.default for p in fitdb_cmd.params}
    for p in fit_cmd.params:
        if p.name in per_call:
            continue
        assert p.name in theirs, p.name
        assert theirs[p.name] == p.default, (p.name, theirs[p.name], p.default)


# ------------------------------------------------------------------------------ one cluster run
@pytest.fixture(scope="module")
def db_run(tmp_path_factory):

    src = shared_path("data", "bosphorus_style")
    tmp = tmp_path_factory.mktemp("fitdb")
    db = tmp / "db"
    db.mkdir()
    for stem in ("bs900_N_N_0", "bs901_N_N_0", *FITTED):
        _link_scan(src, db, stem)
    # a truncated copy of a real scan (its landmarks intact)
    data = (src / f"{CORRUPT}.bnt").read_bytes()
    (db / f"{CORRUPT}.bnt").write_bytes(data[: len(data) // 3])
    (db / f"{CORRUPT}.lm3").symlink_to(src / f"{CORRUPT}.lm3")
    settings = _quick_settings()
    marker = tmp / "bs901-crashed"
    old = os.environ.get(CRASH_ONCE_ENV)
    os.environ[CRASH_ONCE_ENV] = f"bs901={marker}"
    events = []
    try:
        report = run_database(
            discover_database(db),
            tmp / "out",
            settings,
            ClusterSpec(workers=2, compile_cache="off", retries=1),
            on_scan=lambda *a: events.append(a),
        )
    finally:
        if old is None:
            os.environ.pop(CRASH_ONCE_ENV, None)
        else:
            os.environ[CRASH_ONCE_ENV] = old
    # the reference: the plain in-process fit of the same scan with the same settings
    ref = tmp / "ref"
    run_fit(
        db / "bs900_N_N_0.bnt",
        [db / "bs900_LFAU_12_0.bnt"],
        ref,
        options=settings.options,
        subject_options=settings.subject_options,
    )
    return {
        "db": db,
        "out": tmp / "out",
        "ref": ref,
        "report": report,
        "marker": marker,
        "events": events,
        "tmp": tmp,
    }


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_every_scan_has_a_row_and_the_corrupt_one_says_why(db_run):

    rep = db_run["report"]
    assert (rep.scans, rep.fitted, rep.failed, rep.skipped, rep.pending) == (3, 2, 1, 0, 0)
    rows = {r["scan"]: r for r in read_table(db_run["out"]).to_pylist()}
    assert sorted(rows) == sorted([*FITTED, CORRUPT])
    for stem in FITTED:
        r = rows[stem]
        assert r["status"] == "fitted" and r["error"] == "", r
        assert r["wall_s"] > 0 and r["worker"]
        assert (db_run["out"] / stem[:5] / f"{stem}.fitted.ply").is_file()
    bad = rows[CORRUPT]
    assert bad["status"] == "failed" and bad["code"] == "UFAU_1"
    assert bad["error"].startswith("ScanFormatError: "), bad["error"]
    assert f"{CORRUPT}.bnt" in bad["error"]
    assert bad["scan_to_fit_mm"] is None and bad["act_zygomaticus_major_L"] is None
    assert not (db_run["out"] / "bs900" / f"{CORRUPT}.json").exists()
    # the progress events reached the client, one per scan
    assert sorted((s, st) for _, s, st in db_run["events"]) == sorted(
        [(FITTED[0], "fitted"), (FITTED[1], "fitted"), (CORRUPT, "failed")]
    )
    # nothing temporary left behind
    assert not [p for p in db_run["out"].rglob(".*")]


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_per_scan_files_equal_the_in_process_jaxface_fit(db_run):

    stem = FITTED[0]
    got = json.loads((db_run["out"] / "bs900" / f"{stem}.json").read_text())
    want = json.loads((db_run["ref"] / f"{stem}.json").read_text())
    assert set(got) == set(want)
    assert got["activations"].keys() == want["activations"].keys()
    for k, v in want["activations"].items():
        assert abs(got["activations"][k] - v) <= 1e-6, (k, got["activations"][k], v)
    assert any(v > 1e-3 for v in want["activations"].values())  # the fit did move
    for k, v in want["au_intensities"].items():
        assert abs(got["au_intensities"][k] - v) <= 1e-6, k
    for k, v in want["jaw"].items():
        assert abs(got["jaw"][k] - v) <= 1e-6, k
    m = ("metrics", "scan_to_fit", "all", "mean")
    g, w = got, want
    for k in m:
        g, w = g[k], w[k]
    assert abs(g - w) <= 1e-6
    assert got["frame"] == want["frame"]
    for k in ("rotation", "translation"):
        np.testing.assert_allclose(
            got["rigid"]["rig_to_scan"][k], want["rigid"]["rig_to_scan"][k], atol=1e-6
        )
    a = load_mesh(db_run["out"] / "bs900" / f"{stem}.fitted.ply", validate=False)
    b = load_mesh(db_run["ref"] / f"{stem}.fitted.ply", validate=False)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6)
    np.testing.assert_array_equal(a.triangles, b.triangles)


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_a_worker_killed_mid_run_has_its_subject_retried(db_run):

    # the first attempt of bs901 ended its worker process (the hook wrote the marker first)
    assert db_run["marker"].exists()
    rows = {r["scan"]: r for r in read_table(db_run["out"]).to_pylist()}
    assert rows["bs901_LFAU_12_0"]["status"] == "fitted"
    assert rows["bs901_LFAU_12_0"]["scan_to_fit_mm"] < rows["bs901_LFAU_12_0"]["b0_mm"] + 1.0


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_parquet_columns_match_the_per_scan_json(db_run):

    tab = read_table(db_run["out"] / "results.parquet")
    cols = tab.column_names
    for c in (
        "subject",
        "code",
        "scan",
        "status",
        "error",
        "scan_to_fit_mm",
        "b0_mm",
        "b1_mm",
        "jaw_pitch_deg",
        "jaw_yaw_deg",
        "jaw_protrusion_mm",
        "wall_s",
        "worker",
    ):
        assert c in cols, c
    doc = json.loads((db_run["out"] / "bs901" / "bs901_LFAU_12_0.json").read_text())
    row = next(r for r in tab.to_pylist() if r["scan"] == "bs901_LFAU_12_0")
    assert {f"act_{k}" for k in doc["activations"]} <= set(cols)
    assert set(doc["au_intensities"]) <= set(cols) and "AU12" in cols and "AU12L" in cols
    for k, v in doc["activations"].items():
        assert row[f"act_{k}"] == v
    for k, v in doc["au_intensities"].items():
        assert row[k] == v
    assert row["b0_mm"] == doc["baselines"]["B0"]["scan_to_fit"]["all"]["mean"]
    assert row["b1_mm"] == doc["baselines"]["B1"]["scan_to_fit"]["all"]["mean"]
    assert row["jaw_pitch_deg"] == doc["jaw"]["pitch_deg"]
    assert row["subject"] == "bs901" and row["code"] == "LFAU_12"


def _cli(args, capsys):

    code = main(args)
    return code, capsys.readouterr().err


def _stamp(out):
    return {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_resume_from_the_folder_and_from_a_manifest_fits_nothing(db_run, capsys):

    out = db_run["out"]
    before = read_table(out).to_pylist()
    jobs = discover_database(db_run["db"])
    # done: the fitted scans and the recorded failure; --retry-failed would run the failure
    assert pending_jobs(jobs, out, resume=True) == ([], 3)
    todo, skipped = pending_jobs(jobs, out, resume=True, retry_failed=True)
    assert [[e.stem for e in j.scans] for j in todo] == [[CORRUPT]] and skipped == 2
    assert sum(len(j.scans) for j in pending_jobs(jobs, out, resume=False)[0]) == 3
    files = _stamp(out)
    # what a killed run leaves behind: a staging folder and a temporary file
    (out / "bs900" / ".staging-dead").mkdir()
    (out / "bs900" / ".staging-dead" / f"{FITTED[0]}.json").write_text("{")
    (out / "bs901" / ".bs901_LFAU_12_0.json.0123.tmp").write_text("{")
    orphan = out / "bs901" / "bs901_UFAU_2_0.fitted.ply"  # renamed, but no record yet
    orphan.write_text("ply")
    code, err = _cli(["fit-db", str(db_run["db"]), "--out", str(out)], capsys)
    assert code == 0, err
    assert "fitted 0, failed 0, skipped 3" in " ".join(err.split()), err
    # the same scans through a CSV manifest (the layout for PLY/OBJ databases)
    man = db_run["tmp"] / "db.csv"
    with man.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["subject", "neutral", "scan"])
        for stem in (*FITTED, CORRUPT):
            w.writerow([stem[:5], f"db/{stem[:5]}_N_N_0.bnt", f"db/{stem}.bnt"])
    code, err = _cli(["fit-db", str(man), "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    after = read_table(out).to_pylist()
    assert after == before
    # no scan file was written again (only the table)
    changed = {p for p, t in _stamp(out).items() if files.get(p) != t}
    assert changed <= {out / "results.parquet"}, changed
    assert not [p for p in out.rglob(".*")] and not orphan.exists()  # leftovers removed


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fixture: a 2-worker cluster run, minutes
def test_summary_prints_the_table_per_code(db_run, capsys):

    code, err = _cli(["fit-db", "--summary", str(db_run["out"])], capsys)
    assert code == 0, err
    assert "LFAU_12" in err and "UFAU_1" in err
    s = {x["code"]: x for x in summarise(read_table(db_run["out"]))}
    assert (s["LFAU_12"]["scans"], s["LFAU_12"]["fitted"]) == (2, 2)
    assert (s["UFAU_1"]["failed"], s["UFAU_1"]["scan_to_fit_mm"]) == (1, None)
    rows = [r for r in read_table(db_run["out"]).to_pylist() if r["code"] == "LFAU_12"]
    assert s["LFAU_12"]["scan_to_fit_mm"] == pytest.approx(
        sum(r["scan_to_fit_mm"] for r in rows) / 2
    )
    code, err = _cli(["fit-db", "--summary", str(db_run["tmp"] / "nothing")], capsys)
    assert code == 3 and "no results table" in err


def test_fit_db_without_a_database_is_a_usage_error(capsys, tmp_path):
    code, err = _cli(["fit-db", "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "fit-db ROOT --out DIR" in err
    code, err = _cli(["fit-db", str(tmp_path / "none"), "--out", str(tmp_path / "o")], capsys)
    assert code == 3 and "database not found" in err
    shutil.rmtree(tmp_path / "o", ignore_errors=True)
