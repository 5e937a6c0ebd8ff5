"""Jaw kinematics (thesis sec. 5.2): axes from landmarks, smooth limits, differentiability."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxface.anatomy import build_rig
from jaxface.anatomy.frame import face_frame, mirror_label
from jaxface.anatomy.jaw import (
    PITCH_LIMITS_DEG,
    PROTRUSION_LIMITS_MM,
    YAW_LIMITS_DEG,
    JawModel,
    JawPose,
    rotation_matrix,
    smooth_clamp,
)
from jaxface.errors import LandmarkError, RigError
from jaxface.head import generic_head
from jaxface.landmarks import Landmarks


def synthetic_landmarks(scale=1.0, shift=(0.0, 0.0, 0.0)):
    """A plausible adult face (mm), written for these tests (left = +x)."""
    half = {
        "Outer {s} eyebrow": (56.0, 20.0, -8.0),
        "Middle {s} eyebrow": (36.0, 29.0, 9.0),
        "Inner {s} eyebrow": (12.0, 26.0, 18.0),
        "Outer {s} eye corner": (44.0, 1.0, -3.0),
        "Inner {s} eye corner": (18.0, -1.0, 3.0),
        "Nose saddle {s}": (8.0, -6.0, 17.0),
        "{S} nose peak": (17.0, -36.0, 20.0),
        "{S} mouth corner": (25.0, -68.0, 13.0),
    }
    mid = {
        "Nose tip": (0.0, -29.0, 42.0),
        "Upper lip outer middle": (0.0, -58.0, 29.0),
        "Upper lip inner middle": (0.0, -66.5, 24.0),
        "Lower lip inner middle": (0.0, -67.5, 23.5),
        "Lower lip outer middle": (0.0, -77.0, 26.5),
        "Chin middle": (0.0, -94.0, 21.5),
    }
    names, pos = [], []
    for k, v in half.items():
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            names.append(k.format(s=side, S=side.capitalize()))
            pos.append((sgn * v[0], v[1], v[2]))
    for k, v in mid.items():
        names.append(k)
        pos.append(v)
    p = np.asarray(pos) * scale + np.asarray(shift) + np.array([0.0, 33.0, 89.0])
    return Landmarks(names, p)


@pytest.fixture(scope="module")
def jaw():
    return JawModel.from_landmarks(synthetic_landmarks())


def test_frame_axes_and_scale():
    fr = face_frame(synthetic_landmarks())
    np.testing.assert_allclose(fr.axes @ fr.axes.T, np.eye(3), atol=1e-12)
    assert fr.axes[0] @ [1, 0, 0] > 0.99 and fr.axes[2] @ [0, 0, 1] > 0.95
    fr2 = face_frame(synthetic_landmarks(scale=1.2))
    np.testing.assert_allclose(fr2.scale / fr.scale, 1.2, rtol=1e-9)
    # estimated condyles: symmetric, behind and below the eyes
    c = fr.condyles
    np.testing.assert_allclose(c[0] * [-1, 1, 1], c[1], atol=1e-9)
    assert c[0, 2] < fr.origin[2] - 50 and c[0, 1] < fr.origin[1]


def test_frame_errors():
    lm = synthetic_landmarks()
    with pytest.raises(LandmarkError, match="Chin middle"):
        face_frame(lm.subset([n for n in lm.names if n != "Chin middle"]))
    mirrored = Landmarks([mirror_label(n) for n in lm.names], lm.positions)
    with pytest.raises(LandmarkError, match="mirror"):
        face_frame(mirrored)


def test_rotation_matrix_matches_scipy():
    rng = np.random.default_rng(0)
    for _ in range(5):
        ax = rng.normal(size=3)
        ax /= np.linalg.norm(ax)
        ang = rng.uniform(-2, 2)
        np.testing.assert_allclose(
            rotation_matrix(jnp.asarray(ax), ang),
            Rotation.from_rotvec(ax * ang).as_matrix(),
            atol=1e-12,
        )


def test_neutral_is_identity(jaw):
    R, t = jaw.transform(JawPose())
    # the smooth clamp moves 0 by e^(-range/softness): ~1e-8 degrees, ~1e-10 mm
    np.testing.assert_allclose(R, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(t, 0.0, atol=1e-7)


def test_pitch_opens_about_the_condyles(jaw):
    chin = np.array([0.0, -61.0, 110.0])
    cond = np.stack([jaw.pivot + 50 * jaw.pitch_axis, jaw.pivot - 50 * jaw.pitch_axis])
    pose = JawPose(12.0)
    moved = np.asarray(jaw.apply(pose, np.vstack([chin, cond])))
    np.testing.assert_allclose(moved[1:], cond, atol=1e-9)  # the axis stays put
    assert moved[0, 1] < chin[1] - 10 and moved[0, 2] < chin[2]  # chin down and back
    R, _ = jaw.transform(pose)
    ang = np.degrees(np.arccos((np.trace(np.asarray(R)) - 1) / 2))
    assert ang == pytest.approx(12.0, abs=1e-6)
    np.testing.assert_allclose(np.asarray(R) @ np.asarray(R).T, np.eye(3), atol=1e-12)


def test_yaw_and_protrusion_directions(jaw):
    chin = jnp.array([[0.0, -61.0, 110.0]])
    assert float(jaw.apply(JawPose(0.0, 4.0), chin)[0, 0]) > 3.0  # to the subject's left
    assert float(jaw.apply(JawPose(0.0, -4.0), chin)[0, 0]) < -3.0
    d = np.asarray(jaw.apply(JawPose(0.0, 0.0, 3.0), chin) - chin)[0]
    np.testing.assert_allclose(d, 3.0 * np.asarray(jaw.protrusion_dir), atol=1e-6)
    assert d[2] > 2.0  # mostly forward


@pytest.mark.parametrize(
    "field,limits",
    [
        ("pitch_deg", PITCH_LIMITS_DEG),
        ("yaw_deg", YAW_LIMITS_DEG),
        ("protrusion_mm", PROTRUSION_LIMITS_MM),
    ],
)
def test_limits_hold(jaw, field, limits):
    lo, hi = limits
    clamp = jax.vmap(lambda v: getattr(jaw.clamp(JawPose(**{field: v})), field))
    far = np.asarray(clamp(jnp.linspace(lo - 1000.0, hi + 1000.0, 401)))
    assert far.min() >= lo and far.max() <= hi  # never beyond
    near = np.asarray(clamp(jnp.linspace(lo - 2.0, hi + 2.0, 401)))
    assert near.min() > lo and near.max() < hi  # strictly inside
    assert np.all(np.diff(near) > 0)  # strictly monotone
    mid = 0.5 * (lo + hi)
    assert float(getattr(jaw.clamp(JawPose(**{field: mid})), field)) == pytest.approx(mid, abs=1e-6)


def test_smooth_clamp_derivative_in_unit_interval():
    dfn = jax.jit(jax.vmap(jax.grad(lambda x: smooth_clamp(x, -4.0, 18.0, 0.25))))
    g = np.asarray(dfn(jnp.linspace(-30.0, 40.0, 141)))
    assert np.all(g >= 0) and np.all(g <= 1.0 + 1e-12)
    gin = np.asarray(dfn(jnp.linspace(-6.0, 20.0, 53)))
    assert np.all(gin > 1e-5)  # no dead zone near the limits
    assert float(dfn(jnp.array([7.0]))[0]) == pytest.approx(1.0, abs=1e-9)


def test_gradients_match_finite_differences(jaw):
    pts = jnp.array([[0.0, -61.0, 110.0], [40.0, -50.0, 70.0]])

    @jax.jit
    def f(p):
        return jnp.sum(jnp.sin(jaw.apply(JawPose.from_array(p), pts)))

    p0 = jnp.array([6.0, 1.5, 2.0])
    g = jax.jit(jax.grad(f))(p0)
    eps = 1e-6
    fd = [(f(p0.at[i].add(eps)) - f(p0.at[i].add(-eps))) / (2 * eps) for i in range(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    # forward mode too
    _, jv = jax.jvp(f, (p0,), (jnp.array([1.0, 0.0, 0.0]),))
    assert float(jv) == pytest.approx(float(fd[0]), rel=1e-6)


def test_vmap_over_poses(jaw):
    poses = JawPose(
        jnp.array([0.0, 5.0, 15.0]), jnp.array([0.0, -2.0, 3.0]), jnp.array([0.0, 1.0, -1.0])
    )
    pts = jnp.array([[0.0, -61.0, 110.0]])
    one = jax.jit(lambda p: jaw.apply(p, pts))
    batch = jax.vmap(one)(poses)
    for i in range(3):
        single = one(JawPose(poses.pitch_deg[i], poses.yaw_deg[i], poses.protrusion_mm[i]))
        np.testing.assert_allclose(batch[i], single, atol=1e-12)


@pytest.mark.parametrize("limits", [(5.0, 20.0), (-4.0, -1.0), (-4.0, 60.0), (-4.0, float("nan"))])
def test_build_rig_refuses_impossible_jaw_pitch_limits(limits):
    with pytest.raises(RigError, match="jaw_pitch_limits_deg"):
        build_rig(generic_head(), jaw_pitch_limits_deg=limits)


@pytest.mark.parametrize("limits", [(1.0, 8.0), (-2.0, 0.0), (-2.0, 25.0), (float("nan"), 8.0)])
def test_build_rig_refuses_impossible_jaw_protrusion_limits(limits):
    with pytest.raises(RigError, match="jaw_protrusion_limits_mm"):
        build_rig(generic_head(), jaw_protrusion_limits_mm=limits)


def test_the_protrusion_limit_stops_the_incisors_at_the_set_translation():
    head = generic_head()
    chin = jnp.asarray(head.landmarks["Chin middle"])
    for hi in (6.0, 10.0):
        jaw = JawModel.from_landmarks(head.landmarks, protrusion_limits=(-2.0, hi))
        R, t = jaw.transform(JawPose(protrusion_mm=jnp.asarray(40.0)))  # saturates at the limit
        np.testing.assert_allclose(float(jnp.linalg.norm(R @ chin + t - chin)), hi, atol=1e-6)
        R, t = jaw.transform(JawPose(protrusion_mm=jnp.asarray(-40.0)))
        np.testing.assert_allclose(float(jnp.linalg.norm(R @ chin + t - chin)), 2.0, atol=1e-6)


def test_the_full_anatomical_range_drops_the_chin_as_far_as_a_wide_open_mouth():
    # a wide-open mouth drops the chin 40-50 mm (ICT-FaceKit's jawOpen: 42 mm); the default
    # 18 degree limit stops short of it, jaw_pitch_limits_deg=(-4, 28) reaches it
    head = generic_head()
    chin = jnp.asarray(head.landmarks["Chin middle"])
    drops = {}
    for hi in (18.0, 28.0):
        jaw = JawModel.from_landmarks(head.landmarks, pitch_limits=(-4.0, hi))
        R, t = jaw.transform(JawPose(jnp.asarray(90.0)))  # saturates at the opening limit
        drops[hi] = float(jnp.linalg.norm(R @ chin + t - chin))
    assert drops[18.0] < 40.0 <= drops[28.0] <= 60.0, drops
