"""Tests of jaxface.landmarks: labels, variants, container, MPEG-4 table, mirror check, .lm3."""

from __future__ import annotations

import glob

import numpy as np
import pytest
import trimesh

from jaxface.errors import DataNotFoundError, JaxfaceError, LandmarkError, ScanFormatError
from jaxface.landmarks import (
    BOSPHORUS_LABELS,
    FACE_LABELS,
    MIRROR_PAIRS,
    MPEG4_FDP,
    STABLE_LABELS,
    Landmarks,
    attach_to_mesh,
    canonical_label,
    check_side,
    read_lm3,
    write_lm3,
)
from jaxface.mesh import TriMesh


def face_landmarks() -> Landmarks:
    """A plausible 24-landmark set in mm (left at +x), mirror-symmetric by construction."""
    half = {
        "Outer left eyebrow": (58, 51, 79),
        "Middle left eyebrow": (38, 61, 98),
        "Inner left eyebrow": (12, 58, 107),
        "Outer left eye corner": (44, 35, 87),
        "Inner left eye corner": (18, 33, 92),
        "Nose saddle left": (8.5, 27, 106),
        "Left nose peak": (18, 4, 102),
        "Left mouth corner": (33, -24, 92),
        "Left ear lobe": (75, -10, 0),
    }
    mid = {
        "Nose tip": (0, 3, 130),
        "Upper lip outer middle": (0, -21, 114),
        "Upper lip inner middle": (0, -29, 110),
        "Lower lip inner middle": (0, -31, 111),
        "Lower lip outer middle": (0, -40, 113),
        "Chin middle": (0, -57, 111),
    }
    d = {}
    for left, right in MIRROR_PAIRS:
        x, y, z = half[left]
        d[left] = (x, y, z)
        d[right] = (-x, y, z)
    d.update(mid)
    return Landmarks.from_dict({k: d[k] for k in BOSPHORUS_LABELS})


def test_label_tables():
    assert len(BOSPHORUS_LABELS) == 24 and len(set(BOSPHORUS_LABELS)) == 24
    assert BOSPHORUS_LABELS[-2:] == ("Left ear lobe", "Right ear lobe")
    assert FACE_LABELS == BOSPHORUS_LABELS[:22]
    assert set(STABLE_LABELS) == {
        "Outer left eye corner",
        "Inner left eye corner",
        "Inner right eye corner",
        "Outer right eye corner",
        "Nose saddle left",
        "Nose saddle right",
        "Nose tip",
    }
    # the exact label text of the Bosphorus notes
    for lbl in (
        "Outer left eyebrow",
        "Nose saddle left",
        "Left nose peak",
        "Upper lip outer middle",
        "Lower lip inner middle",
        "Chin middle",
    ):
        assert lbl in BOSPHORUS_LABELS
    # every pair is a left/right pair of canonical labels
    for left, right in MIRROR_PAIRS:
        assert "left" in left.lower() and "right" in right.lower()
        assert left.lower().replace("left", "right") == right.lower()


def test_mpeg4_fdp_table():
    assert set(MPEG4_FDP) <= set(BOSPHORUS_LABELS)
    assert len(set(MPEG4_FDP.values())) == len(MPEG4_FDP)  # one FDP per label
    expected = {
        "Nose tip": "9.3",
        "Left mouth corner": "8.3",
        "Right mouth corner": "8.4",
        "Outer left eye corner": "3.7",
        "Inner right eye corner": "3.8",
        "Inner left eye corner": "3.11",
        "Outer right eye corner": "3.12",
        "Chin middle": "2.10",
        "Upper lip outer middle": "8.1",
        "Lower lip outer middle": "8.2",
        "Upper lip inner middle": "2.2",
        "Lower lip inner middle": "2.3",
        "Inner left eyebrow": "4.1",
        "Inner right eyebrow": "4.2",
        "Middle left eyebrow": "4.3",
        "Middle right eyebrow": "4.4",
        "Outer left eyebrow": "4.5",
        "Outer right eyebrow": "4.6",
    }
    for k, v in expected.items():
        assert MPEG4_FDP[k] == v
    assert MPEG4_FDP["Left ear lobe"].startswith("10.")
    assert MPEG4_FDP["Nose saddle left"].startswith("9.")
    # MPEG-4 numbering: odd FDP ids are on the subject's left for the symmetric groups
    for left, right in MIRROR_PAIRS:
        if left in MPEG4_FDP and right in MPEG4_FDP:
            g_l, n_l = map(int, MPEG4_FDP[left].split("."))
            g_r, n_r = map(int, MPEG4_FDP[right].split("."))
            assert g_l == g_r
            assert n_l % 2 == 1 and n_r % 2 == 0


@pytest.mark.parametrize(
    "text,canon",
    [
        ("Nose tip", "Nose tip"),
        ("NOSE TIP", "Nose tip"),
        ("nose_tip", "Nose tip"),
        ("  nose   tip ", "Nose tip"),
        ("NoseTip", "Nose tip"),
        ("Left ear lobe", "Left ear lobe"),
        ("Left earlobe", "Left ear lobe"),
        ("left ear-lobe", "Left ear lobe"),
        ("Ear lobe left", "Left ear lobe"),
        ("Lobe of the right ear", "Right ear lobe"),
        ("R ear lobe", "Right ear lobe"),
        ("Left eye brow outer", "Outer left eyebrow"),
        ("outer-left-eye-corner", "Outer left eye corner"),
        ("Mouth corner (right)", "Right mouth corner"),
        ("9.3", "Nose tip"),
        ("2.10", "Chin middle"),
        ("mouth corner", None),
        ("ear lobe", None),
        ("forehead", None),
    ],
)
def test_canonical_label_variants(text, canon):
    assert canonical_label(text) == canon


def test_all_canonical_labels_map_to_themselves():
    for lbl in BOSPHORUS_LABELS:
        assert canonical_label(lbl) == lbl
        assert canonical_label(lbl.upper()) == lbl
        assert canonical_label(lbl.lower().replace(" ", "_")) == lbl


def test_container_lookup_and_copies():
    lm = face_landmarks()
    assert len(lm) == 24 and lm.names == BOSPHORUS_LABELS
    np.testing.assert_array_equal(lm["nose_TIP"], [0, 3, 130])
    np.testing.assert_array_equal(lm["left earlobe"], [75, -10, 0])
    assert "LEFT EARLOBE" in lm and "forehead" not in lm
    with pytest.raises(LandmarkError) as info:
        lm["Nose tipp"]
    assert "Nose tip" in str(info.value)  # a suggestion
    assert isinstance(info.value, KeyError) and isinstance(info.value, JaxfaceError)
    with pytest.raises(ValueError):
        lm.positions[0, 0] = 1.0
    d = lm.to_dict()
    d["Nose tip"][0] = 99  # copies
    assert lm["Nose tip"][0] == 0
    assert Landmarks.from_dict(lm.to_dict()) == lm
    # names given as variants are stored canonically
    lm2 = Landmarks(["nose tip", "left EARLOBE"], [[0, 0, 1], [1, 2, 3]])
    assert lm2.names == ("Nose tip", "Left ear lobe")
    # custom labels are allowed and found case-insensitively
    lm3 = Landmarks(["Glabella"], [[0, 40, 110]])
    np.testing.assert_array_equal(lm3["glabella"], [0, 40, 110])


def test_require_lists_every_missing_name():
    lm = face_landmarks().subset(FACE_LABELS)  # no ear lobes
    assert len(lm) == 22
    req = lm.require(["nose tip", "Chin middle"])
    assert req.names == ("Nose tip", "Chin middle")
    with pytest.raises(LandmarkError) as info:
        lm.require(["Nose tip", "left earlobe", "Right ear lobe", "Forehead centre"])
    err = info.value
    assert err.missing == ("Left ear lobe", "Right ear lobe", "Forehead centre")
    for name in err.missing:
        assert name in str(err)
    assert lm.missing(BOSPHORUS_LABELS) == ("Left ear lobe", "Right ear lobe")
    sub = lm.subset(["Right ear lobe", "Nose tip", "Outer left eye corner"])
    assert sub.names == ("Nose tip", "Outer left eye corner")
    np.testing.assert_array_equal(lm.array(["Nose tip"]), [[0, 3, 130]])


def test_container_rejects_bad_input():
    with pytest.raises(LandmarkError, match="duplicated"):
        Landmarks(["Nose tip", "NOSE TIP"], np.zeros((2, 3)))
    with pytest.raises(LandmarkError, match="NaN"):
        Landmarks(["Nose tip"], [[np.nan, 0, 0]])
    with pytest.raises(LandmarkError):
        Landmarks(["Nose tip", "Chin middle"], np.zeros((3, 3)))


def test_check_side_detects_mirrored_input():
    lm = face_landmarks()
    check_side(lm)  # left at +x: fine
    flipped = lm.mirrored(swap_labels=False)  # x negated, labels kept: a mirrored scan
    with pytest.raises(LandmarkError) as info:
        check_side(flipped)
    msg = str(info.value)
    assert "mirrored" in msg and "+x" in msg
    # mirroring and relabelling gives a valid set again (the face is symmetric: same set)
    again = lm.mirrored(swap_labels=True)
    check_side(again)
    np.testing.assert_allclose(again.subset(BOSPHORUS_LABELS).positions, lm.positions)
    # a face turned to look along -z (rotated 180 deg about y) also reads as mirrored
    rot = np.diag([-1.0, 1.0, -1.0])
    with pytest.raises(LandmarkError):
        check_side(lm.transformed(rotation=rot))
    # without eye corners the other pairs decide
    no_eyes = lm.subset([n for n in lm.names if "eye corner" not in n])
    check_side(no_eyes)
    with pytest.raises(LandmarkError, match="mirrored"):
        check_side(no_eyes.mirrored(swap_labels=False))
    # one eye pair swapped, the other not: inconsistent
    d = lm.to_dict()
    d["Inner left eye corner"], d["Inner right eye corner"] = (
        d["Inner right eye corner"],
        d["Inner left eye corner"],
    )
    with pytest.raises(LandmarkError, match="inconsistent"):
        check_side(Landmarks.from_dict(d))
    with pytest.raises(LandmarkError, match="cannot check"):
        check_side(lm.subset(["Nose tip", "Chin middle"]))


def test_lm3_round_trip(tmp_path):
    lm = face_landmarks().transformed(translation=[0.123456, -7.654321, 1e-3])
    p = tmp_path / "x.lm3"
    write_lm3(p, lm, comment="test file\nsecond line")
    text = p.read_text().splitlines()
    assert text[0] == "# test file" and text[1] == "# second line" and text[2] == ""
    assert text[3] == "24 landmarks:"
    back = read_lm3(p)
    assert back.names == lm.names
    np.testing.assert_allclose(back.positions, lm.positions, atol=5e-7)


def test_lm3_variants_and_missing_landmarks(tmp_path):
    p = tmp_path / "v.lm3"
    p.write_text(
        "# comment\n#\n\n3 landmarks:\nNOSE TIP\n1 2 3\n\nleft earlobe\n4 5 6\n"
        "Chin middle\n7 8 9.5\n"
    )
    lm = read_lm3(p)
    assert lm.names == ("Nose tip", "Left ear lobe", "Chin middle")
    np.testing.assert_array_equal(lm["chin middle"], [7, 8, 9.5])


@pytest.mark.parametrize(
    "body,line,what",
    [
        ("3 landmarks:\nNose tip\n1 2 3\nChin middle\n4 5 6\nLeft mouth corner\n", 8, "truncated"),
        ("3 landmarks:\nNose tip\n1 2 3\nChin middle\n4 5 6\n", None, "truncated"),
        ("2 landmarks:\nNose tip\n1 2 x\nChin middle\n4 5 6\n", 5, "bad coordinates"),
        ("2 landmarks:\nNose tip\n1 2\nChin middle\n4 5 6\n", 5, "bad coordinates"),
        ("2 landmarks:\nNose tip\n1 2 nan\nChin middle\n4 5 6\n", 5, "bad coordinates"),
        ("2 landmarks:\nNose tip\n1 2 3\nnose tip\n4 5 6\n", 6, "twice"),
        ("Nose tip\n1 2 3\n", 3, "landmarks:"),
        ("", None, "no 'N landmarks:'"),
    ],
)
def test_lm3_errors_name_file_and_line(tmp_path, body, line, what):
    p = tmp_path / "bad.lm3"
    # a comment line and a blank line, so the body starts on line 3
    p.write_text("# synthetic\n\n" + body if body else "# only\n")
    with pytest.raises(ScanFormatError) as info:
        read_lm3(p)
    msg = str(info.value)
    assert "bad.lm3" in msg and what in msg
    if line is not None:
        assert f"line {line}" in msg


def test_lm3_missing_file(tmp_path):
    with pytest.raises(DataNotFoundError):
        read_lm3(tmp_path / "nope.lm3")


@pytest.mark.data
def test_read_real_shared_lm3_files(shared):
    folder = shared("data", "bosphorus_style")
    files = sorted(glob.glob(str(folder / "*.lm3")))
    assert len(files) >= 20
    import json

    truth = json.loads((folder / "truth.json").read_text())
    for f in files:
        lm = read_lm3(f)
        assert set(lm.names) == set(FACE_LABELS)  # the 22 face landmarks, canonical
        check_side(lm)
        assert np.all(np.isfinite(lm.positions))
        # plausible face geometry in mm: eye corners ~60-110 mm apart, nose tip in front
        w = np.linalg.norm(lm["Outer left eye corner"] - lm["Outer right eye corner"])
        assert 60 < w < 110
        assert lm["Nose tip"][2] > lm["Inner left eye corner"][2]
    assert isinstance(truth, dict)


@pytest.mark.data
def test_real_landmarks_attach_to_truth_mesh(shared):
    from jaxface.mesh import load_mesh

    folder = shared("data", "bosphorus_style")
    lm = read_lm3(folder / "bs900_N_N_0.lm3")
    mesh = load_mesh(folder / "bs900_N_N_0.truth.ply")
    sp, dist = attach_to_mesh(lm, mesh, max_distance=1.0)
    assert dist.max() < 0.01  # the landmarks are mesh vertices of the scanned truth mesh
    pos = np.asarray(sp.positions(mesh.vertices, mesh.triangles))
    np.testing.assert_allclose(pos, lm.positions, atol=0.01)


def test_attach_to_mesh_and_far_landmarks():
    s = trimesh.creation.icosphere(subdivisions=3, radius=100.0)
    mesh = TriMesh(s.vertices, s.faces)
    lm = Landmarks(
        ["Nose tip", "Chin middle", "Left ear lobe"], [[0, 0, 101.0], [0, -99.0, 0], [150.0, 0, 0]]
    )
    sp, dist = lm.on_mesh(mesh)
    assert len(sp) == 3
    np.testing.assert_allclose(dist[:2], [1.0, 1.0], atol=0.3)
    pos = np.asarray(sp.positions(mesh.vertices, mesh.triangles))
    np.testing.assert_allclose(np.linalg.norm(pos - lm.positions, axis=1), dist, atol=1e-9)
    with pytest.raises(LandmarkError) as info:
        attach_to_mesh(lm, mesh, max_distance=5.0)
    assert info.value.missing == ("Left ear lobe",) and "Left ear lobe" in str(info.value)
