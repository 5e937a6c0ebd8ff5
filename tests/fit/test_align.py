"""Tests of jaxface.fit.align: Kabsch/Umeyama, robust ICP, and the expression-scan to neutral
alignment on synthetic face-like surfaces (known rigid motions, with noise, holes, outliers
and a moving mouth) and on the shared Bosphorus-style scans against truth.json."""

import numpy as np
import pytest

from jaxface.errors import FitError, LandmarkError
from jaxface.fit.align import (
    MOUTH_CHIN_LABELS,
    AlignmentResult,
    RigidTransform,
    align_scans,
    mouth_chin_mask,
    robust_icp,
    rotation_from_euler,
    stable_mask,
    umeyama,
)
from jaxface.fit.metrics import SurfaceIndex
from jaxface.landmarks import STABLE_LABELS


def _g(x, y, cx, cy, sx, sy):
    return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2))


def face_height(x, y):
    """A face-like height field z(x, y), mm: a rounded head, nose, eye sockets, brows, cheeks,
    lips and chin (features in every direction, so all six rigid DOF are determined)."""
    z = 100.0 - 0.012 * x**2 - 0.006 * y**2
    z += 28.0 * _g(x, y, 0.0, 8.0, 7.0, 18.0)  # nose
    z -= 9.0 * (_g(x, y, 31.0, 33.0, 11.0, 7.0) + _g(x, y, -31.0, 33.0, 11.0, 7.0))  # eye sockets
    z += 5.0 * (_g(x, y, 28.0, 50.0, 16.0, 5.0) + _g(x, y, -28.0, 50.0, 16.0, 5.0))  # brows
    z += 6.0 * (_g(x, y, 40.0, 5.0, 12.0, 12.0) + _g(x, y, -40.0, 5.0, 12.0, 12.0))  # cheeks
    z += 6.0 * _g(x, y, 0.0, -36.0, 20.0, 5.0) + 7.0 * _g(x, y, 0.0, -64.0, 14.0, 9.0)  # lips, chin
    return z


LANDMARK_XY = {
    "Outer left eye corner": (45.0, 34.0),
    "Inner left eye corner": (17.0, 33.0),
    "Inner right eye corner": (-17.0, 33.0),
    "Outer right eye corner": (-45.0, 34.0),
    "Nose saddle left": (8.0, 30.0),
    "Nose saddle right": (-8.0, 30.0),
    "Nose tip": (0.0, 6.0),
    "Left mouth corner": (25.0, -36.0),
    "Right mouth corner": (-25.0, -36.0),
    "Upper lip outer middle": (0.0, -30.0),
    "Lower lip outer middle": (0.0, -43.0),
    "Chin middle": (0.0, -64.0),
}


def face_mesh(step=1.5, offset=0.0, half=(70.0, 90.0)):
    xs = np.arange(-half[0], half[0] + 1e-9, step) + offset
    ys = np.arange(-half[1], half[1] + 1e-9, step) + offset
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), face_height(X.ravel(), Y.ravel())], 1)
    n, m = X.shape
    idx = np.arange(n * m).reshape(n, m)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return V, F


def face_landmarks():
    return {k: np.array([x, y, face_height(x, y)]) for k, (x, y) in LANDMARK_XY.items()}


def random_rigid(rng, angle_deg=6.0, shift=8.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    th = np.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    return RigidTransform(R, rng.uniform(-shift, shift, 3))


def transform_error(T, T_true, pts):
    dR = T.rotation @ T_true.rotation.T
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    disp = np.linalg.norm(T.apply(pts) - T_true.apply(pts), axis=1).max()
    return ang, np.linalg.norm(T.translation - T_true.translation), disp


# ------------------------------------------------------------------------- basics
def test_umeyama_recovers_rigid_and_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(12, 3)) * 40.0
    T = random_rigid(rng, 25.0, 30.0)
    est = umeyama(src, T.apply(src))
    np.testing.assert_allclose(est.rotation, T.rotation, atol=1e-12)
    np.testing.assert_allclose(est.translation, T.translation, atol=1e-10)
    S = RigidTransform(T.rotation, T.translation, 1.07)
    est = umeyama(src, S.apply(src), scale=True)
    assert est.scale == pytest.approx(1.07, abs=1e-12)
    np.testing.assert_allclose(est.apply(src), S.apply(src), atol=1e-10)
    # a reflection is never returned
    refl = src * [-1, 1, 1]
    assert np.linalg.det(umeyama(src, refl).rotation) == pytest.approx(1.0)
    with pytest.raises(FitError):
        umeyama(src[:2], src[:2])


def test_rotation_from_euler_convention():
    # Rx(90) Ry(90) applied to +x: Ry(90) sends +x to -z, Rx(90) sends -z to +y
    R = rotation_from_euler(pitch_deg=90.0, yaw_deg=90.0)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        rotation_from_euler(0.0, 30.0) @ [0, 0, 1.0], [0.5, 0, np.sqrt(3) / 2], atol=1e-12
    )
    np.testing.assert_allclose(
        rotation_from_euler(30.0, 0.0) @ [0, 1.0, 0], [0, np.sqrt(3) / 2, 0.5], atol=1e-12
    )


def test_regions_never_touch_mouth_and_chin():
    V, _ = face_mesh(step=3.0)
    lm = face_landmarks()
    st = stable_mask(V, lm)
    mc = mouth_chin_mask(V, lm)
    assert st.sum() > 200 and mc.sum() > 200
    assert not np.any(st & mc)
    # nothing of the stable region lies below the nose tip by more than 5 mm (along the
    # face's up direction: outer-eye-corner midpoint minus mouth-corner midpoint)
    up = 0.5 * (lm["Outer left eye corner"] + lm["Outer right eye corner"])
    up = up - 0.5 * (lm["Left mouth corner"] + lm["Right mouth corner"])
    up /= np.linalg.norm(up)
    assert ((V[st] - lm["Nose tip"]) @ up).min() >= -5.0 - 1e-9
    assert ((V[~st] - lm["Nose tip"]) @ up).min() < -20.0
    with pytest.raises(LandmarkError, match="mouth or chin"):
        align_scans((V, _), (V, _), lm, lm, labels=STABLE_LABELS + ("Chin middle",), icp=False)
    assert set(MOUTH_CHIN_LABELS).isdisjoint(STABLE_LABELS)


# ------------------------------------------------------------------------- synthetic recovery
def test_icp_recovers_known_motion_exactly_on_clean_data():
    rng = np.random.default_rng(1)
    Vf, Ff = face_mesh(step=1.5)
    Vm, Fm = face_mesh(step=1.7, offset=0.37)  # a different sampling of the same surface
    lm = face_landmarks()
    T_true = random_rigid(rng, 5.0, 6.0)  # moving -> fixed
    Vm_moved = T_true.inverse().apply(Vm)
    lm_m = {k: T_true.inverse().apply(v[None])[0] for k, v in lm.items()}
    res = align_scans((Vm_moved, Fm), (Vf, Ff), lm_m, lm, region="stable")
    ang, dt, disp = transform_error(res.transform, T_true, Vm_moved)
    assert ang < 0.01 and disp < 0.02, (ang, dt, disp)
    assert res.converged and res.landmark_rms < 0.02
    assert res.residual.mean < 0.01


def test_point_cloud_icp_recovers_known_motion_and_shares_the_result_type():
    """The preprocessing ICP (nearest samples of a PointCloud, jaxface.io.preprocess.icp)
    runs on the same robust_icp: on a dense sampling of the surface it recovers a known
    motion to the sampling's accuracy and reports in the same ICPStage."""
    from jaxface.alignment import AlignmentResult as StackResult
    from jaxface.alignment import ICPStage, PointCloud
    from jaxface.io.preprocess import AlignmentResult as IOResult
    from jaxface.io.preprocess import icp

    assert IOResult is StackResult and StackResult is AlignmentResult
    rng = np.random.default_rng(4)
    Vf, Ff = face_mesh(step=0.5, half=(40.0, 50.0))
    Vm, _ = face_mesh(step=1.7, offset=0.37, half=(35.0, 45.0))
    normals = SurfaceIndex(Vf, Ff).vertex_normals
    T_true = random_rigid(rng, 2.0, 2.0)
    moving = T_true.inverse().apply(Vm)
    T, info = icp(moving, Vf, normals, iterations=40)
    assert isinstance(info, ICPStage) and info.converged
    ang, _, disp = transform_error(T, T_true, moving)
    assert ang < 0.01 and disp < 0.01, (ang, disp)  # nearest samples of a 0.5 mm grid
    assert info.rms < 0.01 and info.median < 0.01
    with pytest.raises(FitError, match="PointCloud"):
        PointCloud(Vf, normals[:-1])


def test_alignment_tolerates_noise_holes_outliers_and_a_moving_mouth():
    rng = np.random.default_rng(2)
    Vf, Ff = face_mesh(step=1.5)
    Vm, Fm = face_mesh(step=1.6, offset=0.21)
    lm = face_landmarks()
    # expression: the mouth and chin move by up to 6 mm (must not bias the alignment)
    mouth = 6.0 * _g(Vm[:, 0], Vm[:, 1], 0.0, -45.0, 22.0, 14.0)
    Vm = Vm + np.stack([0 * mouth, -0.6 * mouth, 0.8 * mouth], 1)
    lm_m = dict(lm)
    for k in MOUTH_CHIN_LABELS:
        if k in lm_m:
            lm_m[k] = lm_m[k] + [0.0, -6.0, 5.0]
    # noise, outliers, holes (in both scans)
    Vm = Vm + rng.normal(scale=0.1, size=Vm.shape)
    spikes = rng.choice(len(Vm), len(Vm) // 50, replace=False)
    Vm[spikes, 2] += rng.choice([-1, 1], len(spikes)) * rng.uniform(3, 10, len(spikes))
    cm = Vm[Fm].mean(1)
    Fm = Fm[np.linalg.norm(cm[:, :2] - [22.0, 10.0], axis=1) > 8.0]  # hole on the left cheek
    cf = Vf[Ff].mean(1)
    Ff = Ff[np.linalg.norm(cf[:, :2] - [-5.0, 45.0], axis=1) > 7.0]  # hole on the forehead
    # landmark noise of 1 mm
    lm_m = {k: v + rng.normal(scale=1.0, size=3) for k, v in lm_m.items()}
    T_true = random_rigid(rng, 4.0, 5.0)
    Vm = T_true.inverse().apply(Vm)
    lm_m = {k: T_true.inverse().apply(v[None])[0] for k, v in lm_m.items()}
    res = align_scans((Vm, Fm), (Vf, Ff), lm_m, lm)
    ang, dt, disp = transform_error(res.transform, T_true, Vm)
    ang0, _, disp0 = transform_error(res.landmark_transform, T_true, Vm)
    assert disp0 > 0.5  # the landmark fit alone is not good enough ...
    assert ang < 0.05 and disp < 0.15, (ang, dt, disp)  # ... the robust ICP is
    assert [s.name for s in res.stages] == ["stable", "face"]
    assert res.residual.median < 0.1
    d = res.to_dict()
    assert d["transform"]["scale"] == 1.0 and len(d["stages"]) == 2


def test_similarity_alignment_recovers_scale():
    rng = np.random.default_rng(4)
    Vf, Ff = face_mesh(step=1.5)
    Vm, Fm = face_mesh(step=1.6, offset=0.3)
    lm = face_landmarks()
    T_true = RigidTransform(random_rigid(rng, 3.0, 4.0).rotation, np.array([1.0, -2.0, 3.0]), 0.97)
    inv = T_true.inverse()
    res = align_scans(
        (inv.apply(Vm), Fm),
        (Vf, Ff),
        {k: inv.apply(v[None])[0] for k, v in lm.items()},
        lm,
        similarity=True,
        region="stable",
    )
    assert res.transform.scale == pytest.approx(0.97, abs=2e-4)
    assert np.abs(res.transform.apply(inv.apply(Vm)) - Vm).max() < 0.05


def test_robust_icp_huber_and_failure():
    rng = np.random.default_rng(5)
    Vf, Ff = face_mesh(step=2.0)
    idx = SurfaceIndex(Vf, Ff)
    T_true = random_rigid(rng, 1.0, 1.0)
    pts = T_true.inverse().apply(Vf[::7])
    T, st = robust_icp(pts, idx, loss="huber", iterations=40)
    assert transform_error(T, T_true, pts)[2] < 0.01
    assert st.converged and st.n_inliers > 0.8 * len(pts)
    with pytest.raises(FitError, match="not roughly aligned"):
        robust_icp(pts + [0.0, 0.0, 200.0], idx)
    with pytest.raises(FitError, match="robust loss"):
        robust_icp(pts, idx, loss="cauchy")  # pyright: ignore[reportArgumentType]


def test_alignment_needs_stable_landmarks():
    V, F = face_mesh(step=3.0)
    lm = face_landmarks()
    few = {
        k: lm[k]
        for k in ("Nose tip", "Left mouth corner", "Right mouth corner", "Inner left eye corner")
    }
    with pytest.raises(LandmarkError, match="at least 3 stable landmarks") as e:
        align_scans((V, F), (V, F), few, lm)
    assert "Outer left eye corner" in e.value.missing


# ------------------------------------------------------------------------- shared data
@pytest.mark.data
def test_bs900_scans_align_to_identity(shared):
    from jaxface.fit.evaluation import load_truth

    ts = load_truth(shared("data", "bosphorus_style"))
    ns = ts.neutral_stem("bs900")
    for code in ("LFAU_20",):
        stem = f"bs900_{code}_0"
        res = align_scans(ts.scan(stem), ts.scan(ns), fixed_index=ts.scan_index(ns))
        ang, dt, disp = transform_error(
            res.transform, RigidTransform(), ts.truth_vertices(stem)[:9409]
        )
        assert ang < 0.1 and dt < 0.2, (stem, ang, dt, disp)


# A sample of the scans whose expression leaves part of the face still, so that the rigid
# motion is observable (E_HAPPY and E_SURPRISE move every visible face vertex by more than
# 0.3 mm in the ICT model: see the align module doc; all scans: benchmarks/bench_register.py)
@pytest.mark.data
@pytest.mark.parametrize("code", ["UFAU_4", "LFAU_9", "LFAU_12L", "LFAU_20"])
def test_bs901_alignment_matches_truth_json(shared, code):
    from jaxface.fit.evaluation import load_truth

    ts = load_truth(shared("data", "bosphorus_style"))
    ns = ts.neutral_stem("bs901")
    stem = f"bs901_{code}_0"
    res = align_scans(ts.scan(stem), ts.scan(ns), fixed_index=ts.scan_index(ns))
    T_true = ts.relative_transform(stem, ns)
    ang, dt, disp = transform_error(res.transform, T_true, ts.truth_vertices(stem)[:9409])
    ang0, dt0, _ = transform_error(res.landmark_transform, T_true, ts.truth_vertices(stem)[:9409])
    assert ang < 0.2 and dt < 0.2, (stem, ang, dt, disp)
    assert ang <= ang0 + 0.02
