"""``jaxface synth`` as a user runs it (a subprocess on the default head), its outputs checked
against the library call, and bad inputs (clear message, exit code 2, nothing written)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_commands import run_cli, run_main

from jaxface.cli import EXIT_USAGE


@pytest.fixture(scope="module")
def synth_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    proc = run_cli(
        "synth",
        "--au",
        "AU26=0.5",
        "--muscle",
        "zygomaticus_major_L=0.8",
        "--name",
        "custom",
        "--emotion",
        "surprise",
        "--sweeps",
        "48/6",
        "--out",
        out,
        timeout=600,
    )
    return out, proc


def test_synth_writes_meshes_landmarks_json_and_pictures(synth_run):
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, synthesize
    from jaxface.facs import aus_to_controls
    from jaxface.head import generic_head
    from jaxface.landmarks import read_lm3
    from jaxface.mesh import load_mesh

    out, proc = synth_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("custom", "surprise"):
        for ext in ("ply", "lm3", "json", "png"):
            assert (out / f"{name}.{ext}").stat().st_size > 0, (name, ext)
    doc = json.loads((out / "custom.json").read_text())
    assert doc["activations"]["zygomaticus_major_L"] == pytest.approx(0.8)
    assert doc["activations"]["zygomaticus_major_R"] == 0.0
    # AU26 at 0.5 opens the jaw (the AU table's pitch, half of it) and reads back as AU26
    assert doc["jaw"]["pitch_deg"] > 2.0 and doc["au_intensities"]["AU26"] > 0.3
    assert doc["units"] == "mm" and doc["backend"] == "pbd"

    # the written mesh is the library's synthesis of the same controls (independent call), in
    # the CLI's precision (float32; other tests in this process may have enabled float64)
    import jax

    with jax.enable_x64(False):
        head = generic_head()
        rig = build_rig(head).with_iterations(muscles=48, skin=6)  # --sweeps 48/6
        a, jaw, puff = aus_to_controls({"AU26": 0.5}, rig.muscle_names)
        a[list(rig.muscle_names).index("zygomaticus_major_L")] = 0.8
        x = np.asarray(
            synthesize(rig, a, JawPose(jaw.pitch_deg, jaw.yaw_deg, jaw.protrusion_mm), puff)
        )
    m = load_mesh(out / "custom.ply", validate=False)
    np.testing.assert_array_equal(m.triangles, np.asarray(rig.triangles))
    np.testing.assert_allclose(m.vertices, x, atol=1e-3)  # PLY stores float32
    # the left zygomaticus pulls the left mouth corner (subject's left = +x) outward and up
    # against the jaw opening that lowers both corners alike
    lm = read_lm3(out / "custom.lm3")
    d = {n: np.asarray(v) for n, v in doc["landmark_displacement_mm"].items()}
    left, right = d["Left mouth corner"], d["Right mouth corner"]
    assert left[0] > 1.0 and left[0] > 2 * abs(right[0])
    assert left[1] - right[1] > 1.0
    assert len(lm.names) == len(d)
    # the chin went down with the open jaw
    assert d["Chin middle"][1] < -2.0


def test_synth_bad_inputs(tmp_path, capsys):
    code, err = run_main(capsys, "synth", "--emotion", "glee", "--out", tmp_path / "a")
    assert code == EXIT_USAGE and "unknown preset" in err and "happiness" in err
    code, err = run_main(capsys, "synth", "--out", tmp_path / "b")
    assert code == EXIT_USAGE and "nothing to synthesise" in err
    code, err = run_main(capsys, "synth", "--au", "AU12=3", "--out", tmp_path / "c")
    assert code == EXIT_USAGE and "[0, 1]" in err
    code, err = run_main(
        capsys, "synth", "--au", "AU12", "--backend", "fem", "--out", tmp_path / "d"
    )
    assert code == EXIT_USAGE and "pbd" in err
    code, err = run_main(capsys, "synth", "--au", "AU12", "--sweeps", "64", "--out", tmp_path / "e")
    assert code == EXIT_USAGE and "MUSCLE/SKIN" in err
    code, err = run_main(
        capsys, "synth", "--au", "AU12", "--sweeps", "0/8", "--out", tmp_path / "f"
    )
    assert code == EXIT_USAGE and "at least 1" in err
    code, err = run_main(
        capsys,
        "synth",
        "--au",
        "AU12",
        "--sweeps",
        "64/8",
        "--backend",
        "ltw",
        "--out",
        tmp_path / "g",
    )
    assert code == EXIT_USAGE and "ltw" in err
    code, err = run_main(
        capsys, "synth", "--au", "AU12", "--sweeps", "64/8/1.5", "--out", tmp_path / "h"
    )
    assert code == EXIT_USAGE and "[0, 1)" in err
    assert not any((tmp_path / s).exists() for s in "abcdefgh")


def test_parse_sweeps_reads_the_optional_skin_acceleration():
    from jaxface.commands.synth import parse_sweeps
    from jaxface.errors import RigError

    assert parse_sweeps("384/16") == (384, 16, 0.0)
    assert parse_sweeps(" 128 / 32 / 0.97 ") == (128, 32, 0.97)
    assert parse_sweeps("Converged") == (32, 56, 0.995)
    assert parse_sweeps("reference") == (48, 96, 0.99)
    assert parse_sweeps("fast") == (32, 8, 0.0)
    for bad in ("1/2/3/4", "a/8", "8/8/x", "convergd"):
        with pytest.raises(RigError, match="MUSCLE/SKIN"):
            parse_sweeps(bad)


def test_parse_muscles_names_the_controls():
    from jaxface.commands.synth import parse_muscles
    from jaxface.errors import RigError

    names = ("zygomaticus_major_L", "zygomaticus_major_R")
    assert parse_muscles(["zygomaticus_major_L=0.25", "zygomaticus_major_R"], names) == {
        "zygomaticus_major_L": 0.25,
        "zygomaticus_major_R": 1.0,
    }
    with pytest.raises(RigError, match="unknown control 'smile'.*zygomaticus_major_L"):
        parse_muscles(["smile=0.5"], names)
    with pytest.raises(RigError, match=r"\[0, 1\]"):
        parse_muscles(["zygomaticus_major_L=1.5"], names)
    with pytest.raises(RigError, match="number"):
        parse_muscles(["zygomaticus_major_L=lots"], names)


def test_synth_ltw_backend(tmp_path):
    """The same command drives the Lee-Terzopoulos-Waters backend (issue 6)."""
    out = tmp_path / "ltw"
    proc = run_cli(
        "synth",
        "--backend",
        "ltw",
        "--au",
        "AU12=0.8",
        "--name",
        "smile",
        "--no-pictures",
        "--compare-backends",
        "--out",
        out,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads((out / "smile.json").read_text())
    assert doc["backend"] == "ltw" and not (out / "smile.png").exists()
    # AU12 pulls both mouth corners outward (subject's left = +x) and up
    left = np.asarray(doc["landmark_displacement_mm"]["Left mouth corner"])
    right = np.asarray(doc["landmark_displacement_mm"]["Right mouth corner"])
    assert left[0] > 0.5 and right[0] < -0.5 and left[1] > 0.5 and right[1] > 0.5
    # the six emotions, PBD next to LTW with their difference: 7 rows x 3 panels
    from matplotlib.image import imread

    img = imread(out / "backends_emotions.png")
    assert img.shape[0] > 2 * img.shape[1]
    assert (img[..., :3].mean(axis=2) < 0.9).mean() > 0.05


@pytest.mark.data
def test_synth_arkit_drives_the_rig_through_the_inverse_map(tmp_path, monkeypatch):
    """``jaxface synth --arkit``: a left smile with the jaw half open drives the left smile
    muscles more than the right ones and opens the jaw; the inverse map is cached as JSON
    (``$XDG_CACHE_HOME/jaxface/arkit``, keyed as ``inverse_map_cached`` says)."""
    from jaxface.cli import main
    from jaxface.testing import shared_path

    shared_path("data", "ict", "ict_face.npz")  # skip (or fail in CI) without the ICT data
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    args = ["synth", "--arkit", "mouthSmileLeft=1,jawOpen=0.5", "--no-pictures", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    cached = list((tmp_path / "cache" / "jaxface" / "arkit").glob("inverse_*.json"))
    assert len(cached) == 1
    (doc_path,) = (tmp_path / "a").glob("*.json")
    doc = json.loads(doc_path.read_text())
    act = doc["activations"]
    left = act["zygomaticus_major_L"] + act["levator_anguli_oris_L"] + act["risorius_L"]
    right = act["zygomaticus_major_R"] + act["levator_anguli_oris_R"] + act["risorius_R"]
    assert left > 0.2 and left > 2 * right, act
    assert doc["jaw"]["pitch_deg"] > 2.0
    # the cached map is whole and says how far each shape is from what the rig can make
    from jaxface.interop.arkit import ARKIT_NAMES
    from jaxface.interop.inverse import InverseMap

    imap = InverseMap.from_json(json.loads(cached[0].read_text()))
    assert cached[0].name == f"inverse_{imap.key}.json"
    k = ARKIT_NAMES.index("mouthSmileLeft")
    assert 0 < imap.misfit_mm[k] < imap.shape_rms_mm[k]
