"""The detector's landmark definitions (:mod:`jaxface.detect.definitions`) and their
calibration (:mod:`jaxface.detect.calibrate`): recovered exactly on a face whose labels are
known points of the head, the packaged calibration on the head's surface, typed errors for bad
files."""

import json

import numpy as np
import pytest

from jaxface.closest import SurfaceIndex
from jaxface.detect.calibrate import calibrate_definitions, mapped_points
from jaxface.detect.definitions import (
    CALIBRATED_LABELS,
    LandmarkDefinitions,
    load_definitions,
    save_definitions,
)
from jaxface.detect.features import FEATURE_LABELS, NOSE_PEAK_LABELS, feature_extrema
from jaxface.detect.transfer import build_face_template, face_template
from jaxface.errors import DataNotFoundError
from jaxface.fit.align import rotation_from_euler
from jaxface.io.preprocess import RigidTransform
from jaxface.landmarks import Landmarks


def _surface_point(tpl, p):
    """The closest point of the template's face to ``p`` (mm)."""
    idx = SurfaceIndex(np.asarray(tpl.mesh.vertices), np.asarray(tpl.mesh.triangles))
    return idx.query(np.asarray(p, float)[None]).points[0]


def test_calibration_recovers_the_labels_of_a_moved_copy_of_the_head():
    """Independent reference: the "faces" are the head's own face, turned and moved, labelled
    at known points of the head: each calibrated label 4 mm up and 3 mm toward the midline of
    the head's own landmark (moved onto the surface), each other feature label (brows, nose
    tip) 3 mm above its relief extremum on the head; the nose peaks' offsets are from the
    alare found from their calibrated points. The registration of a face onto itself is exact,
    so the calibration must return those points (head frame) and offsets."""
    tpl = build_face_template(None)
    v0, f0 = np.asarray(tpl.mesh.vertices), np.asarray(tpl.mesh.triangles)
    known = {}
    for n in CALIBRATED_LABELS:
        p = np.array(tpl.landmarks[n], float)
        p += [-3.0 * np.sign(p[0]), 4.0, 0.0]
        known[n] = _surface_point(tpl, p)
    # a feature label with a point too (the nose peaks) is searched from its point, as the
    # calibration and the detector search it
    ext = feature_extrema(
        SurfaceIndex(v0, f0),
        {n: known.get(n, tpl.landmarks[n]) for n in FEATURE_LABELS},
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 1.0, 0.0]),
        np.array([0.0, 0.0, 1.0]),
    )
    # the head has a nose tip and ridges under its inner and middle brows (its outer brows'
    # profile falls away without a maximum: those features are not found on this face)
    assert {"Nose tip", "Inner left eyebrow", "Middle right eyebrow"} <= set(ext)
    assert set(NOSE_PEAK_LABELS) <= set(ext)
    for n, e in ext.items():
        if n not in CALIBRATED_LABELS:
            known[n] = _surface_point(tpl, e + [0.0, 3.0, 0.0])
    names = list(known)
    truth_rest = np.stack(list(known.values()))
    faces = []
    for pitch, yaw, shift in ((12.0, -20.0, (4.0, -7.0, 30.0)), (-8.0, 25.0, (-2.0, 5.0, 60.0))):
        T = RigidTransform(rotation_from_euler(pitch, yaw), np.array(shift))
        faces.append((T.apply(v0), f0, Landmarks(names, T.apply(truth_rest))))
    defs = calibrate_definitions(faces, source="test")
    assert defs.faces == 2
    assert set(defs.points) == set(CALIBRATED_LABELS)
    assert set(defs.offsets_mm) == set(ext)
    err = {n: float(np.linalg.norm(defs.points[n] - known[n])) for n in CALIBRATED_LABELS}
    assert max(err.values()) < 0.5, err
    off = {n: float(np.linalg.norm(defs.offsets_mm[n] - (known[n] - ext[n]))) for n in ext}
    assert max(off.values()) < 0.5, off
    assert max(defs.spread_mm.values()) < 0.5, defs.spread_mm
    points, offsets = mapped_points(*faces[0], template=tpl)
    assert set(points) == set(CALIBRATED_LABELS) and set(offsets) == set(ext)


def test_a_moved_definition_moves_the_detected_landmark():
    """The template carries the definitions: a face that is the head itself, detected with
    the chin's definition moved 5 mm down and the inner left brow's offset 4 mm up, returns
    the chin 5 mm lower and that brow 4 mm above its ridge (on the face)."""
    from jaxface.detect import detect_landmarks

    own = build_face_template(None)
    chin = _surface_point(own, own.landmarks["Chin middle"] + [0.0, -5.0, 0.0])
    n = "Inner left eyebrow"
    tpl = build_face_template(
        LandmarkDefinitions({"Chin middle": chin}, offsets_mm={n: np.array([0.0, 4.0, 0.0])})
    )
    assert np.linalg.norm(tpl.landmarks["Chin middle"] - chin) < 1e-9
    v, f = np.asarray(own.mesh.vertices), np.asarray(own.mesh.triangles)
    det = detect_landmarks((v, f), template=tpl)
    assert np.linalg.norm(det.landmarks["Chin middle"] - chin) < 0.5
    saddle = "Nose saddle left"  # not redefined: the head's own
    assert np.linalg.norm(det.landmarks[saddle] - own.landmarks[saddle]) < 0.5
    axes = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    ridge = feature_extrema(SurfaceIndex(v, f), {n: own.landmarks[n]}, *axes)[n]
    want = _surface_point(own, ridge + [0.0, 4.0, 0.0])
    assert np.linalg.norm(det.landmarks[n] - want) < 0.5
    plain = detect_landmarks((v, f), template=tpl, refine=False)  # the transferred point
    assert np.linalg.norm(plain.landmarks[n] - own.landmarks[n]) < 0.5


def test_the_packaged_definitions_lie_on_the_default_head():
    """A change of the default head's face would leave the stored points off its surface:
    re-run ``benchmarks/calibrate_landmarks.py --write``."""
    defs = load_definitions()
    assert set(defs.points) == set(CALIBRATED_LABELS)
    assert defs.faces >= 10 and "calibrate_landmarks.py" in defs.source
    own = build_face_template(None)
    for n, p in defs.points.items():
        assert np.linalg.norm(_surface_point(own, p) - p) < 0.05, n
        assert np.linalg.norm(p - own.landmarks[n]) < 15.0, n  # the same anatomical place
    assert set(defs.offsets_mm) == set(FEATURE_LABELS)
    # the nose peaks lie on the cheek 10-12 mm beside the alare and 7-9 mm behind it
    far = {n: 16.0 if n in NOSE_PEAK_LABELS else 10.0 for n in defs.offsets_mm}
    assert all(np.linalg.norm(o) < far[n] for n, o in defs.offsets_mm.items()), defs.offsets_mm
    tpl = face_template()
    for n in CALIBRATED_LABELS:
        assert np.linalg.norm(tpl.landmarks[n] - defs.points[n]) < 0.05, n


def test_definitions_files_fail_clearly(tmp_path):
    with pytest.raises(DataNotFoundError):
        load_definitions(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"labels": {"Nose wing": {"point_mm": [0, 0, 0]}}}))
    with pytest.raises(ValueError, match="unknown labels"):
        load_definitions(bad)
    bad.write_text(json.dumps({"labels": {"Chin middle": {"point_mm": [0, float("nan"), 0]}}}))
    with pytest.raises(ValueError, match="finite"):
        load_definitions(bad)
    bad.write_text(json.dumps({"faces": 3}))
    with pytest.raises(ValueError, match="not a landmark definitions file"):
        load_definitions(bad)
    d = LandmarkDefinitions({"Chin middle": np.array([0.0, -60.0, 100.0])}, {"Chin middle": 1.0})
    back = load_definitions(save_definitions(d, tmp_path / "d.json"))
    assert np.allclose(back.points["Chin middle"], [0.0, -60.0, 100.0])
    assert back.spread_mm == {"Chin middle": 1.0}
    bad.write_text(json.dumps({"labels": {}, "offsets": {"Chin middle": {"offset_mm": [0, 1, 0]}}}))
    with pytest.raises(ValueError, match="not relief features"):
        load_definitions(bad)


def _ridge_grid(depth, step=0.7, half=30.0):
    """A range-scan-like grid (mm) of the surface ``z = depth(x, y)``: vertices, triangles."""
    g = np.arange(-half, half + 1e-9, step)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), depth(x, y).ravel()], axis=1)
    n = len(g)
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    i = i.ravel()
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    return v, f


def test_the_brow_ridge_is_the_profile_maximum():
    """Analytic reference: a ridge ``z = 50 - (y - 5)^2 / 40`` (mm) across the face, seen
    along a tilted frame, is found at ``y = 5`` from a guess 7 mm below it, on a fine grid
    and on a coarse one (3 mm, a decimated mesh); a slope with no interior maximum and a
    profile with a hole over half its length give no ridge."""
    from jaxface.detect.features import brow_extremum

    left, up, fwd = np.eye(3)
    R = rotation_from_euler(15.0, -25.0)
    guess = R @ np.array([10.0, -2.0, 50.0 - 49.0 / 40.0 + 0.2])
    for step in (0.7, 3.0):
        v, f = _ridge_grid(lambda x, y: 50.0 - (y - 5.0) ** 2 / 40.0 + 0.02 * x, step)
        idx = SurfaceIndex(v @ R.T, f)
        p = brow_extremum(idx, guess, R @ left, R @ up, R @ fwd)
        assert p is not None
        y = (R.T @ p)[1]
        assert abs(y - 5.0) < 0.5, (step, y)
    v, f = _ridge_grid(lambda x, y: 50.0 - 0.3 * y)
    assert brow_extremum(SurfaceIndex(v, f), np.array([0.0, 0.0, 50.0]), left, up, fwd) is None
    v, f = _ridge_grid(lambda x, y: 50.0 - (y - 5.0) ** 2 / 40.0)
    keep = ~((v[f][:, :, 1] > -8.0) & (v[f][:, :, 1] < 6.0)).any(axis=1)
    g = np.array([0.0, -2.0, 49.0])
    assert brow_extremum(SurfaceIndex(v, f[keep]), g, left, up, fwd) is None


def test_the_alar_edge_is_the_steepest_outward_drop():
    """Analytic reference: a wing ``z = 50 + 8 / (1 + exp((|x| - w(y)) / 0.6))`` (mm; 8 mm
    in front of the cheek medial of its edge ``w(y) = 12 - 0.1 y^2``, falling over about
    2 mm) on a cheek sloping back 0.2 mm per mm, seen along a tilted frame, has its most
    lateral edge (the alare) found at ``x = 12``, ``y = 0`` from guesses 3 mm above it and
    6 mm medial to 8 mm lateral of it, for the left side (outward +x) and mirrored for the
    right (outward -x); a smooth slope gives no edge."""
    from jaxface.detect.features import alar_edge

    left, up, fwd = np.eye(3)
    R = rotation_from_euler(-10.0, 20.0)

    def wing(x, y):
        edge = 12.0 - 0.1 * y**2
        return 50.0 + 8.0 / (1.0 + np.exp((np.abs(x) - edge) / 0.6)) - 0.2 * np.abs(x)

    v, f = _ridge_grid(wing, step=0.7)
    idx = SurfaceIndex(v @ R.T, f)
    for side in (1.0, -1.0):
        for dx in (-6.0, 0.0, 8.0):
            x0 = side * (12.0 + dx)
            guess = R @ np.array([x0, 3.0, wing(x0, 3.0)])
            p = alar_edge(idx, guess, side * (R @ left), R @ up, R @ fwd)
            assert p is not None, (side, dx)
            x, y = (R.T @ p)[:2]
            assert abs(x - side * 12.0) < 0.8 and abs(y) < 1.01, (side, dx, x, y)
    v, f = _ridge_grid(lambda x, y: 50.0 - 0.3 * x)
    assert alar_edge(SurfaceIndex(v, f), np.array([10.0, 0.0, 47.0]), left, up, fwd) is None
