"""The forward model on the default head and the ICT face: AU regions and directions, rest
state, muscle volume and bulge, lips vs teeth, jaw limits, vmap, gradients vs finite
differences, dynamic animation.

Compilations are shared: one vmapped synthesis evaluates every case (including the
finite-difference points), one function computes a forward and a reverse derivative."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface import facs
from jaxface.anatomy.jaw import JawPose
from jaxface.anatomy.muscles import muscle_volumes
from jaxface.anatomy.rig import build_rig, simulate, synthesize, synthesize_state
from jaxface.errors import RigError
from jaxface.head import generic_head

EPS = 1e-4  # finite-difference step (activations / degrees)


@pytest.fixture(scope="module")
def rig(default_rig):
    return default_rig


def _case_list(rig):
    n = rig.n_controls
    cases = {"rest": (np.zeros(n), 0.0)}
    for au in (
        "AU1",
        "AU2",
        "AU4",
        "AU7",
        "AU9",
        "AU12",
        "AU12L",
        "AU14",
        "AU15",
        "AU20",
        "AU43",
        "AU23",
    ):
        a, _, _ = facs.aus_to_controls({au: 1.0}, rig.muscle_names)
        cases[au] = (a, 0.0)
    for emo in facs.EMOTIONS:
        a, j, _ = facs.emotion_controls(emo, rig.muscle_names)
        cases[emo] = (a, float(j.pitch_deg))
    cases["AU26"] = (np.zeros(n), 10.0)
    cases["pitch14"] = (np.zeros(n), 14.0)
    cases["pitch30"] = (np.zeros(n), 30.0)
    cases["pitch60"] = (np.zeros(n), 60.0)
    a, j, _ = facs.aus_to_controls(
        {"AU20": 1.0, "AU23": 1.0, "AU12": 1.0, "AU14": 1.0}, rig.muscle_names
    )
    cases["lips_stretched_open"] = (a, 16.0)
    rng = np.random.default_rng(0)
    a0 = np.clip(rng.uniform(0.0, 0.4, n), 0, 1)
    da = rng.normal(size=n)
    cases["fd0"] = (a0, 6.0)
    cases["fd+a"] = (a0 + EPS * da, 6.0)
    cases["fd-a"] = (a0 - EPS * da, 6.0)
    cases["fd+p"] = (a0, 6.0 + EPS)
    cases["fd-p"] = (a0, 6.0 - EPS)
    return cases, (a0, da)


@pytest.fixture(scope="module")
def results(rig):
    cases, fd = _case_list(rig)
    names = list(cases)
    A = jnp.asarray(np.stack([cases[k][0] for k in names]))
    P = jnp.asarray(np.array([cases[k][1] for k in names]))

    @jax.jit
    def batch(A, P):
        st = jax.vmap(lambda a, p: synthesize_state(rig, a, JawPose(p)))(A, P)
        return st.skin, st.muscles, st.R, st.t

    skin, mus, R, t = batch(A, P)
    out = {
        k: (np.asarray(skin[i]), np.asarray(mus[i]), np.asarray(R[i]), np.asarray(t[i]))
        for i, k in enumerate(names)
    }
    return out, fd


def _lm(rig, name):
    """Index of the skin vertex nearest a landmark."""
    p = rig.info.landmarks[name]
    return int(np.argmin(np.linalg.norm(np.asarray(rig.rest) - p, axis=1)))


def _disp(results, rig, case, name):
    i = _lm(rig, name)
    return results[0][case][0][i] - np.asarray(rig.rest)[i]


def test_rest_state_is_a_fixed_point(rig, results):
    np.testing.assert_allclose(results[0]["rest"][0], np.asarray(rig.rest), atol=1e-5)


def test_au12_moves_mouth_corners_up_and_out(rig, results):
    for side, sgn in (("Left", 1), ("Right", -1)):
        d = _disp(results, rig, "AU12", f"{side} mouth corner")
        assert d[1] > 1.0 and sgn * d[0] > 0.5, (side, d)
        # and back along the dental arch nearly as far as out (ICT's smile on the Bosphorus-style
        # scans: 7.1 out, 9.1 back): measured 5.6 out, 4.7 back (7.2 and 7.2 with a 5 mm tissue
        # footprint); 6.1 out, 3.7 back (7.6 and 5.8) while the zygomaticus major lay on the
        # cheek fat
        assert -d[2] > 0.75 * sgn * d[0], (side, d)
    # the one-sided variant moves only the left corner
    dl = _disp(results, rig, "AU12L", "Left mouth corner")
    dr = _disp(results, rig, "AU12L", "Right mouth corner")
    assert np.linalg.norm(dl) > 1.0 and np.linalg.norm(dr) < 0.25 * np.linalg.norm(dl)


def test_brow_aus(rig, results):
    for side, sgn in (("left", 1), ("right", -1)):
        d1 = _disp(results, rig, "AU1", f"Inner {side} eyebrow")
        assert d1[1] > 1.0, d1  # AU1 raises the inner brow
        d2 = _disp(results, rig, "AU2", f"Outer {side} eyebrow")
        assert d2[1] > 1.0, d2  # AU2 raises the outer brow
        d4 = _disp(results, rig, "AU4", f"Inner {side} eyebrow")
        assert d4[1] < -0.3 and sgn * d4[0] < -0.3, d4  # AU4: down and inward


def test_lower_face_aus(rig, results):
    for side, sgn in (("Left", 1), ("Right", -1)):
        d15 = _disp(results, rig, "AU15", f"{side} mouth corner")
        assert d15[1] < -0.5, d15  # AU15 pulls the corners down
        d20 = _disp(results, rig, "AU20", f"{side} mouth corner")
        assert sgn * d20[0] > 0.5, d20  # AU20 stretches outward
        d9 = _disp(results, rig, "AU9", f"{side} nose peak")
        assert d9[1] > 0.3, d9  # AU9 lifts the nose wings
    d23 = _disp(results, rig, "AU23", "Left mouth corner")
    assert d23[0] < -0.3  # AU23 narrows the mouth


def test_the_modiolus_carries_the_corner_muscles_pull_into_the_lips(rig):
    """The buccinator (AU14) reaches the lips only through the modiolus: with the ring's
    modiolus weights zeroed the corners move under 1.5 mm and the lips' mid-line not at all;
    with them the corners go back several mm and the upper lip's mid-line follows. The modiolus
    sits at the mouth corners, so the lower lip's mid-point goes back less than half as far as
    the corners (the truth's lip stretcher: 0.9 mm against 7.0 mm; with the modiolus at the
    corner muscles' insertion ends, inside the lips and below their line, it went 3.7 mm where
    the corners went 6.1 mm; README, Known limits, the lip stretcher)."""
    import equinox as eqx

    a, _, _ = facs.aus_to_controls({"AU14": 1.0}, rig.muscle_names)
    off = eqx.tree_at(lambda r: r.muscles.mod_w, rig, jnp.zeros_like(rig.muscles.mod_w))
    synth = jax.jit(lambda r, a: synthesize_state(r, a, JawPose(0.0)).skin)
    rest = np.asarray(rig.rest)
    on_x, off_x = (np.asarray(synth(r, jnp.asarray(a))) - rest for r in (rig, off))
    corners_z = []
    for side, sgn in (("Left", 1), ("Right", -1)):
        i = _lm(rig, f"{side} mouth corner")
        assert np.linalg.norm(off_x[i]) < 1.5, off_x[i]
        assert on_x[i][2] < -3.0 and sgn * on_x[i][0] > 2.0, on_x[i]  # back along the teeth, out
        corners_z.append(on_x[i][2])
    lower, upper = _lm(rig, "Lower lip inner middle"), _lm(rig, "Upper lip inner middle")
    assert np.linalg.norm(off_x[lower]) < 0.1 and np.linalg.norm(off_x[upper]) < 0.1
    assert on_x[upper][2] < -1.0, on_x[upper]
    assert 0.5 * max(corners_z) < on_x[lower][2] <= 0.0, (on_x[lower], corners_z)


def test_only_the_mouth_ring_has_a_modiolus(rig):
    """The modiolus weights (the share of the corner muscles' pull each ring sample takes) are
    zero on the eyes' rings, and on the mouth's ring they peak at its lateral ends: each side's
    strongest sample is nearer that side's mouth corner than any sample of the other half."""
    ms = rig.muscles
    w = np.asarray(ms.mod_w)  # (rings, 3, n, 2)
    ring_of = {rig.muscle_names[int(c)]: k for k, c in enumerate(np.asarray(ms.sph_ctrl))}
    assert set(ring_of) == {"orbicularis_oculi_L", "orbicularis_oculi_R", "orbicularis_oris"}, (
        ring_of
    )
    bottom = np.asarray(ms.sph_bottom)
    rest = np.asarray(ms.rest)
    for name, k in ring_of.items():
        if name != "orbicularis_oris":
            assert np.all(w[k] == 0.0), name
            continue
        pos = rest[bottom[k]]  # (3, n, 3)
        for s_, side in ((0, "Left"), (1, "Right")):
            c = rig.info.landmarks[f"{side} mouth corner"]
            best = np.unravel_index(np.argmax(w[k, ..., s_]), w[k, ..., s_].shape)
            d = np.linalg.norm(pos - c, axis=-1)
            lateral = (pos[..., 0] - rig.info.landmarks["Lower lip inner middle"][0]) * (
                1 if s_ == 0 else -1
            )
            assert lateral[best] > 0 and d[best] <= d[lateral < 0].min(), (side, best)
            assert w[k, ..., s_].max() > 0.3


def test_au26_opens_the_mouth(rig, results):
    up = _disp(results, rig, "AU26", "Upper lip inner middle")
    lo = _disp(results, rig, "AU26", "Lower lip inner middle")
    chin = _disp(results, rig, "AU26", "Chin middle")
    assert lo[1] - up[1] < -5.0 and chin[1] < -8.0, (up, lo, chin)
    assert abs(up[1]) < 0.5 * abs(lo[1])


def test_au43_closes_the_upper_lid(rig, results):
    skin = results[0]["AU43"][0]
    rest = np.asarray(rig.rest)
    lids = np.asarray(rig.skin.lid_ids)[np.asarray(rig.skin.lid_upper)]
    assert (skin[lids, 1] - rest[lids, 1]).min() < -2.0


@pytest.mark.parametrize(
    "case,far",
    [
        ("AU12", "upper"),
        ("AU15", "upper"),
        ("AU20", "upper"),
        ("AU1", "lower"),
        ("AU2", "lower"),
        ("AU4", "lower"),
        ("AU43", "lower"),
    ],
)
def test_nothing_far_away_moves(rig, results, case, far):
    fr = rig.info.frame
    loc = fr.to_local(np.asarray(rig.rest))
    d = np.linalg.norm(results[0][case][0] - np.asarray(rig.rest), axis=1)
    assert d.max() > 1.0
    back = loc[:, 2] < -90.0  # back of the head (behind the ears)
    assert d[back].max() < 0.05
    region = loc[:, 1] > 45.0 if far == "upper" else loc[:, 1] < -45.0  # forehead / mouth-chin
    assert d[region].max() < 0.1 * d.max() + 0.05, (case, d[region].max(), d.max())


def test_jaw_limits_hold(rig, results):
    # beyond the limit the pose saturates: 30 and 60 degrees give the same face
    a = results[0]["pitch30"][0]
    b = results[0]["pitch60"][0]
    np.testing.assert_allclose(a, b, atol=1e-6)
    for R in (results[0]["pitch30"][2], results[0]["pitch60"][2]):
        ang = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
        assert ang <= 18.0 + 1e-9


def _inverted_triangles(rig, x):
    """Rest centroids ``(K, 3)`` of the triangles whose normal turned against its rest direction
    (the skin folded over)."""
    F = np.asarray(rig.triangles)
    X0 = np.asarray(rig.rest)
    n0 = np.cross(X0[F[:, 1]] - X0[F[:, 0]], X0[F[:, 2]] - X0[F[:, 0]])
    n = np.cross(x[F[:, 1]] - x[F[:, 0]], x[F[:, 2]] - x[F[:, 0]])
    return X0[F[np.einsum("ij,ij->i", n, n0) < 0]].mean(axis=1).reshape(-1, 3)


def test_opening_the_jaw_folds_skin_only_in_the_crease_under_the_chin(rig, results):
    # carrying the tissue over the mandible rigidly (the thesis's split) folded the skin all
    # along the jaw line: 28 / 152 / 258 triangles at 10 / 14 / 18 degrees; the follow weights
    # leave 2 / 24 / 78, all in the submental crease; the fat layer (FAT_VOLUME), whose
    # bunched tissue bulges there, 10 / 62 / 102, still all in the crease
    fr = rig.info.frame
    chin_y = fr.to_local(fr.points["Chin middle"])[1]
    for case, most in (("AU26", 12), ("pitch14", 70), ("pitch30", 115)):
        c = _inverted_triangles(rig, results[0][case][0])
        assert len(c) <= most, (case, len(c))
        if len(c):
            assert fr.to_local(c)[:, 1].max() < chin_y - 15.0, case


def test_expressions_do_not_fold_the_skin(rig, results):
    # the smile folded the skin over itself below the mouth corners with a 5 mm tissue
    # footprint (40 inverted triangles for AU12 and happiness, 36 for AU14); with FOOTPRINT_MM
    # none fold. The jaw-opening emotions may only crease under the chin (test above)
    fr = rig.info.frame
    chin_y = fr.to_local(fr.points["Chin middle"])[1]
    for case in ("AU7", "AU12", "AU12L", "AU14", "AU43", "lips_stretched_open", *facs.EMOTIONS):
        c = _inverted_triangles(rig, results[0][case][0])
        assert len(c) == 0 or fr.to_local(c)[:, 1].max() < chin_y - 15.0, (case, len(c), c[:3])


def test_eyelids_hinge_at_the_eye_corners(rig, results):
    # the lids rotate about the eyeball centre, 12 mm behind the corners; the rotation tapers to
    # 0 at the corners (LID_CORNER_TAPER), so the corners stay while the lid closes
    skin = results[0]["AU43"][0]
    rest = np.asarray(rig.rest)
    for side in ("left", "right"):
        for corner in ("Inner", "Outer"):
            i = _lm(rig, f"{corner} {side} eye corner")
            assert np.linalg.norm(skin[i] - rest[i]) < 0.3, (side, corner, skin[i] - rest[i])


def test_jaw_membrane_removes_the_crease_folds():
    rig = build_rig(generic_head(), jaw_membrane=True)
    assert rig.skin.mem_ids.shape[0] > 50
    fr = rig.info.frame
    chin_y = fr.to_local(fr.points["Chin middle"])[1]
    zero = jnp.zeros(rig.n_controls)
    a, _, _ = facs.aus_to_controls(
        {"AU20": 1.0, "AU23": 1.0, "AU12": 1.0, "AU14": 1.0}, rig.muscle_names
    )
    A = jnp.stack([zero, zero, zero, jnp.asarray(a)])
    P = jnp.asarray([0.0, 14.0, 18.0, 16.0])
    X = np.asarray(jax.jit(jax.vmap(lambda a, p: synthesize(rig, a, JawPose(p))))(A, P))
    np.testing.assert_allclose(X[0], np.asarray(rig.rest), atol=1e-5)  # rest stays rest
    for x in X[1:3]:
        assert len(_inverted_triangles(rig, x)) == 0
    # lips stretched with the jaw open: nothing folds under the chin (the mouth corners crease)
    c = _inverted_triangles(rig, X[3])
    assert len(c) == 0 or fr.to_local(c)[:, 1].min() > chin_y


def test_jaw_follow_weights():
    from jaxface.anatomy.frame import face_frame
    from jaxface.anatomy.rig import jaw_follow_weights

    frame = face_frame(generic_head().landmarks)
    chin = frame.points["Chin middle"]
    down = -frame.axes[1]
    fwd = frame.axes[2]
    # points on the mandible going back from the chin, and cranium points above / below the slit
    pts = chin + np.outer(np.linspace(0.0, 120.0, 13), -fwd) + 5.0 * down
    w = jaw_follow_weights(pts, np.ones(13, bool), frame)
    assert w[0] == 1.0 and w[2] == 1.0 and 0.2 < w[6] < 0.8 and w[-1] == 0.0
    assert np.all(np.diff(w) <= 0)
    above = frame.stomion + 20.0 * frame.axes[1] - 10.0 * fwd
    below = chin + 15.0 * down - 20.0 * fwd
    wc = jaw_follow_weights(np.stack([above, below]), np.zeros(2, bool), frame)
    assert wc[0] == 0.0 and wc[1] > 0.9
    rigid = jaw_follow_weights(np.stack([pts[-1], above]), np.array([True, False]), frame, 0.0, 0.0)
    np.testing.assert_array_equal(rigid, [1.0, 0.0])
    with pytest.raises(RigError, match="full < reach"):
        jaw_follow_weights(pts, np.ones(13, bool), frame, 50.0, 40.0)


def test_lips_never_penetrate_the_teeth(rig, results):
    sk = rig.skin
    for case in ("lips_stretched_open", "AU23", "AU20", "AU26", "rest"):
        x, _, R, t = results[0][case]
        for g, planes in ((sk.upper_hull, None), (sk.lower_hull, sk.lower_planes)):
            if g is None:
                continue
            ids = np.asarray(g.c.idx[:, 0])
            N = np.asarray(g.c.normals) if planes is None else np.asarray(planes[0]) @ R.T
            d = np.asarray(g.c.offsets) if planes is None else np.asarray(planes[1]) + N @ t
            sd = (x[ids] @ N.T - d).max(axis=1)
            clr = np.asarray(g.c.clearance)
            assert (sd - clr).min() > -1e-6, case


def test_contracting_muscles_bulge_and_keep_their_volume(rig, results):
    ms = rig.muscles
    v0 = np.asarray(muscle_volumes(ms, ms.rest))
    for case, mus in (
        ("AU12", "zygomaticus_major_L"),
        ("AU1", "frontalis_medial_L"),
        ("AU23", "orbicularis_oris"),
        ("AU26", "masseter_L"),
    ):
        x = results[0][case][1]
        v = np.asarray(muscle_volumes(ms, jnp.asarray(x)))
        k = ms.names.index(mus)
        assert abs(v[k] / v0[k] - 1.0) < 0.02, (case, mus, v[k] / v0[k])
    # bulge: the contracted zygomaticus gets thicker (top-to-bottom distance)
    k = ms.names.index("zygomaticus_major_L")
    s, e = ms.offsets[k], ms.offsets[k + 1]
    half = (e - s) // 2

    def thick(x):
        return np.linalg.norm(x[s + half : e] - x[s : s + half], axis=1).mean()

    assert thick(results[0]["AU12"][1]) > 1.1 * thick(np.asarray(ms.rest))


def test_gradients_match_finite_differences_and_vmap_matches_single(rig, results):
    out, (a0, da) = results
    fd_a = (out["fd+a"][0] - out["fd-a"][0]) / (2 * EPS)
    fd_p = (out["fd+p"][0] - out["fd-p"][0]) / (2 * EPS)
    w = np.random.default_rng(1).normal(size=fd_a.shape)

    @jax.jit
    def derivs(a, p, ta, tp, w):
        f = lambda a, p: synthesize(rig, a, JawPose(p))  # noqa: E731
        y, jv = jax.jvp(f, (a, p), (ta, tp))
        _, vjp = jax.vjp(f, a, p)
        ga, gp = vjp(w)
        return y, jv, ga, gp

    a0j, p0 = jnp.asarray(a0), jnp.asarray(6.0)
    y, jv_a, ga, gp = derivs(a0j, p0, jnp.asarray(da), jnp.asarray(0.0), jnp.asarray(w))
    # the un-batched call equals its member of the vmapped batch
    np.testing.assert_allclose(np.asarray(y), out["fd0"][0], atol=1e-9)
    scale = np.abs(fd_a).max()
    assert scale > 1e-2
    np.testing.assert_allclose(np.asarray(jv_a), fd_a, atol=2e-3 * scale)
    # reverse mode: <w, J da> = <J^T w, da>, and the jaw column
    assert float(np.dot(np.asarray(ga), da)) == pytest.approx(float(np.sum(w * fd_a)), rel=2e-3)
    assert float(gp) == pytest.approx(float(np.sum(w * fd_p)), rel=2e-3)
    assert np.all(np.isfinite(np.asarray(ga)))


def test_reverse_pass_is_finite_in_float32_at_rest_and_for_the_emotions():
    """float32 reverse mode through the rig, as a user without x64 runs it: finite at zero
    activations and for every emotion preset, jaw closed and at 9 degrees. At zero
    activations it was NaN before the bending constraints judged degeneracy relative to the
    hinge's size: two particles of the orbicularis oris ring sit on one surface point. The
    rig is built and run with x64 off: built under x64 (as the module's rig is), its float32
    run rounds differently and did not show the NaN."""
    with jax.enable_x64(False):
        _check_float32_reverse_pass(build_rig(generic_head()))


def _check_float32_reverse_pass(rig):
    f32 = jnp.float32
    w = jnp.asarray(np.random.default_rng(2).normal(size=(rig.n_vertices, 3)), f32)

    @jax.jit
    def grads(a, p):
        f = lambda a, p: synthesize(rig, a, JawPose(p, jnp.zeros((), f32), jnp.zeros((), f32)))  # noqa: E731
        y, vjp = jax.vjp(f, a, p)
        return y, *vjp(w)

    cases = [np.zeros(rig.n_controls)]
    for name in facs.EMOTIONS:
        cases.append(np.asarray(facs.emotion_controls(name, rig.muscle_names)[0]))
    for a in cases:
        for pitch in (0.0, 9.0):
            y, ga, gp = grads(jnp.asarray(a, f32), jnp.asarray(pitch, f32))
            assert y.dtype == f32 and ga.dtype == f32
            assert np.all(np.isfinite(np.asarray(ga))) and np.isfinite(float(gp)), (a, pitch)
            assert np.abs(np.asarray(ga)).max() > 0


def test_bad_activation_shape(rig):
    with pytest.raises(RigError, match="shape"):
        synthesize(rig, jnp.zeros(rig.n_controls + 1), JawPose())
    with pytest.raises(RigError, match="unknown muscle"):
        rig.activations({"not_a_muscle": 1.0})


# ------------------------------------------------------------------------------ ICT face
@pytest.fixture(scope="module")
def ict():
    """The ICT face (face group and teeth) with its landmarks and rig."""
    from jaxface.anatomy.ict import load_ict_face
    from jaxface.testing import shared_path

    npz = shared_path("data", "ict", "ict_face.npz")
    f = load_ict_face(npz, shared_path("data", "bosphorus_style", "truth.json"))
    rig = build_rig(f.skin, f.landmarks, upper_teeth=f.upper_teeth, lower_teeth=f.lower_teeth)
    return f, rig, npz


def test_ict_face_builds_and_animates(ict):
    f, rig, _ = ict
    assert rig.n_vertices == 9409
    n = 6
    a12, _, _ = facs.aus_to_controls({"AU12": 1.0}, rig.muscle_names)
    ramp = np.linspace(0.0, 1.0, n)
    zero = jnp.zeros(n)
    run = jax.jit(lambda A, p: simulate(rig, A, JawPose(p, zero, zero)))
    smile = np.asarray(run(jnp.asarray(ramp[:, None] * a12[None]), zero))
    jaw = np.asarray(run(jnp.zeros((n, rig.n_controls)), jnp.asarray(8.0 * ramp)))
    rest = np.asarray(rig.rest)
    np.testing.assert_allclose(smile[0], rest, atol=1e-6)  # starts at rest
    i = int(np.argmin(np.linalg.norm(rest - f.landmarks["Left mouth corner"], axis=1)))
    j = int(np.argmin(np.linalg.norm(rest - f.landmarks["Chin middle"], axis=1)))
    d = smile[-1, i] - rest[i]
    assert d[1] > 0.5 and d[0] > 0.3, d  # smile: corner up and out
    assert jaw[-1, j, 1] - rest[j, 1] < -3.0  # the jaw opened
    assert np.all(np.isfinite(smile)) and np.all(np.isfinite(jaw))


def test_ict_eyelids_fold_little(ict):
    # ICT's lids are thin strips between the eye opening and the lid crease; rotating them
    # about the eyeball centre all the way to the corners inverted 90 (AU43) and 54 (AU7)
    # triangles there; tapered toward the corners 28 and 2 (measured)
    f, rig, _ = ict
    for au, most in (("AU43", 40), ("AU7", 6)):
        a, _, _ = facs.aus_to_controls({au: 1.0}, rig.muscle_names)
        x = np.asarray(synthesize(rig, jnp.asarray(a), JawPose(jnp.asarray(0.0))))
        assert len(_inverted_triangles(rig, x)) <= most, au


def _rigid_fit(P, Q):
    """Least-squares rotation ``R`` and translation ``t`` with ``Q ~ P R^T + t`` (Kabsch)."""
    pc, qc = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - pc).T @ (Q - qc))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, qc - pc @ R.T


def test_jaw_opening_moves_the_skin_like_the_ict_jawopen_expression(ict):
    """Independent reference: ICT-FaceKit's scan-based ``jawOpen`` blendshape. Its lower teeth
    give the jaw angle; the skin our jaw model moves at that angle is compared with ICT's."""
    f, rig, npz = ict
    d = np.load(npz)
    names = [str(n) for n in d["expression_names"]]
    delta = np.asarray(d["expression_deltas"][names.index("jawOpen")], np.float64)
    X = np.asarray(d["neutral"], np.float64)
    groups = [str(g) for g in d["group_names"]]
    T = np.asarray(d["triangles"])
    teeth = np.unique(T[np.asarray(d["triangle_group"]) == groups.index("teeth")])
    moving = teeth[
        np.linalg.norm(delta[teeth], axis=1) > 0.3 * np.linalg.norm(delta[teeth], axis=1).max()
    ]
    V = rig.n_vertices
    for weight, max_mean in ((0.4, 3.2), (0.7, 4.4)):
        R, _ = _rigid_fit(X[moving], X[moving] + weight * delta[moving])
        angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
        x = np.asarray(synthesize(rig, jnp.zeros(rig.n_controls), JawPose(jnp.asarray(angle))))
        ref = weight * delta[:V]
        moved = np.linalg.norm(ref, axis=1) > 1.0
        err = np.linalg.norm(x - X[:V] - ref, axis=1)[moved]
        # 2.8 / 3.9 mm; the mandible's tissue carried rigidly gave 3.8 / 5.2 mm
        assert err.mean() < max_mean, (weight, angle, err.mean())


def test_expression_sheet_draws_the_heads_eyes(rig, tmp_path):
    from types import SimpleNamespace

    from matplotlib.image import imread

    from jaxface.anatomy.pictures import expression_sheet

    expr = [("AU26", {"AU26": 1.0})]
    with_head = expression_sheet(
        tmp_path / "head.png", rig, expr, views=("front",), px=200, head=generic_head()
    )
    skin_only = expression_sheet(tmp_path / "skin.png", rig, expr, views=("front",), px=200)

    def bluish(path):  # iris pixels: the skin is reddish, the irises blue-grey
        img = imread(path)[..., :3]
        return int(np.sum(img[..., 2] > img[..., 0] + 0.04))

    assert bluish(with_head) > 30 and bluish(skin_only) == 0
    with pytest.raises(RigError, match="skin vertices"):
        expression_sheet(
            tmp_path / "bad.png",
            rig,
            expr,
            head=SimpleNamespace(mesh=SimpleNamespace(n_vertices=3)),
        )


def _grid_mesh(n=9, jitter=0.0, seed=0):
    from jaxface.mesh import TriMesh

    ij = (
        np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1)
        .reshape(-1, 2)
        .astype(float)
    )
    rng = np.random.default_rng(seed)
    inner = (ij > 0).all(1) & (ij < n - 1).all(1)
    ij[inner] += jitter * rng.uniform(-0.3, 0.3, (inner.sum(), 2))
    X = np.column_stack([10.0 * ij, np.zeros(len(ij))])
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    T = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return TriMesh(X, T), inner


def test_membrane_interpolation_reproduces_linear_fields_and_a_jacobi_reference():
    from jaxface.anatomy.skin import membrane_interpolation

    # regular grid: the 1/length-weighted Laplacian is exact for linear fields
    mesh, inner = _grid_mesh()
    ids, border, H = membrane_interpolation(mesh, inner)
    np.testing.assert_array_equal(ids, np.flatnonzero(inner))
    f = mesh.vertices @ np.array([0.3, -1.2, 0.0]) + 4.0
    np.testing.assert_allclose(H @ f[border], f[ids], atol=1e-9)
    # jittered grid: same answer as plain Jacobi iteration of the weighted average
    mesh, inner = _grid_mesh(jitter=1.0)
    ids, border, H = membrane_interpolation(mesh, inner)
    assert np.all(H >= -1e-12) and np.allclose(H.sum(axis=1), 1.0)
    rng = np.random.default_rng(1)
    x = rng.normal(size=(mesh.n_vertices, 3))
    e = mesh.edges
    wt = 1.0 / np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1)
    y = x.copy()
    y[ids] = 0.0
    for _ in range(3000):
        acc = np.zeros_like(y)
        ws = np.zeros(len(y))
        np.add.at(acc, e[:, 0], wt[:, None] * y[e[:, 1]])
        np.add.at(acc, e[:, 1], wt[:, None] * y[e[:, 0]])
        np.add.at(ws, e[:, 0], wt)
        np.add.at(ws, e[:, 1], wt)
        y[ids] = acc[ids] / ws[ids, None]
    np.testing.assert_allclose(H @ x[border], y[ids], atol=1e-8)
    # a free region with nothing around it is left alone
    ids, border, H = membrane_interpolation(mesh, np.ones(mesh.n_vertices, bool))
    assert ids.size == 0 and H.shape == (0, 0)


def test_footprint_with_one_sigma_per_vertex_matches_the_scalar_rows_and_blends_by_height(rig):
    from jaxface.anatomy.skin import footprint_matrix, footprint_sigma

    mesh, _ = _grid_mesh(jitter=1.0)
    sig = np.where(mesh.vertices[:, 1] > np.median(mesh.vertices[:, 1]), 14.0, 6.0)
    M = footprint_matrix(mesh, sig).toarray()
    nnz = (M > 0).sum(axis=1)  # rows reach past the neighbours, wider for 14
    assert nnz[sig == 14.0].mean() > nnz[sig == 6.0].mean() > 4
    for s in (6.0, 14.0):
        ref = footprint_matrix(mesh, s).toarray()  # the scalar path, row by row
        rows = np.flatnonzero(sig == s)
        np.testing.assert_allclose(M[rows], ref[rows], atol=1e-12)
    np.testing.assert_allclose(M.sum(axis=1), 1.0)
    # the (lower, upper) pair on the default head: lower below the inner eye corners,
    # upper above the inner eyebrows, monotone in height in between
    info = rig.info
    fr = info.frame
    y = fr.to_local(info.skin.vertices)[:, 1]
    s = footprint_sigma(info.skin, fr, (5.0, 12.0)) / fr.mean_scale
    eye = np.mean([fr.to_local(fr.points[f"Inner {k} eye corner"])[1] for k in ("left", "right")])
    brow = np.mean([fr.to_local(fr.points[f"Inner {k} eyebrow"])[1] for k in ("left", "right")])
    np.testing.assert_allclose(s[y <= eye], 5.0)
    np.testing.assert_allclose(s[y >= brow], 12.0)
    o = np.argsort(y)
    assert np.all(np.diff(s[o]) >= -1e-12)
    np.testing.assert_allclose(footprint_sigma(info.skin, fr, 7.0), 7.0 * fr.mean_scale)
    for bad in ((5.0, -1.0), (1.0, 2.0, 3.0), float("nan"), 0.0):
        with pytest.raises(RigError, match="footprint"):
            footprint_sigma(info.skin, fr, bad)


def test_footprint_clusters_stay_within_their_radius_and_the_operator_matches_the_matrix():
    """The clustered footprint (wide rows weighting clusters of vertices by the mean of their
    Gaussian weights) against the exact row-normalised matrix: constants exactly, linear and
    smooth fields to a fraction of a per cent of their range, narrow rows untouched."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    from jaxface.anatomy.skin import footprint_clusters, footprint_matrix, footprint_operator

    mesh, _ = _grid_mesh(n=15, jitter=1.0)  # 10 mm grid
    X = mesh.vertices
    h = 25.0
    P = footprint_clusters(mesh, h)
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0)
    cluster = np.asarray(P.argmax(axis=1)).ravel()
    assert np.all(P.max(axis=1).toarray().ravel() == 1.0)  # no mirror: one cluster each
    C = P.shape[1]
    assert 20 < C < len(X) // 2
    e = mesh.edges
    L = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    g = sp.coo_matrix(
        (np.r_[L, L], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(len(X),) * 2
    )
    D = dijkstra(g.tocsr(), directed=False)
    # every vertex lies within h/2 of its centre along the surface: a cluster's members lie
    # within h of each other
    for c in range(C):
        m = np.flatnonzero(cluster == c)
        assert D[np.ix_(m, m)].max() <= h + 1e-9
    sig = np.where(X[:, 1] > 70.0, 40.0, 20.0)  # 40 mm rows use clusters, 20 mm rows do not
    wide = sig >= 1.5 * h
    op = footprint_operator(mesh, sig, cluster_mm=h)
    F = footprint_matrix(mesh, sig).toarray()
    W = op.dense(len(X))
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(W[~wide], F[~wide], atol=1e-12)
    for f in (X[:, 0], X[:, 1], np.sin(X[:, 0] / 30.0)):
        ref = F @ f
        assert np.abs(W @ f - ref).max() < 0.01 * np.ptp(ref)
    per_row = np.bincount(op.rows, minlength=len(X))
    assert per_row[wide].mean() < 0.5 * (F[wide] > 0).sum(axis=1).mean()
    exact = footprint_operator(mesh, sig, cluster_mm=0.0)
    assert exact.n_clusters == 0
    np.testing.assert_allclose(exact.dense(len(X)), F, atol=1e-12)
    with pytest.raises(RigError, match="cluster spacing"):
        footprint_clusters(mesh, 0.0)
    for bad in (-1.0, float("nan")):
        with pytest.raises(RigError, match="footprint_cluster_mm"):
            footprint_operator(mesh, sig, cluster_mm=bad)


def test_footprint_neighbourhoods_equal_dijkstra_on_the_whole_graph():
    """The clusters' geodesic neighbourhoods run Dijkstra on the subgraph near each chunk of
    sources; against Dijkstra on the whole edge graph (scipy, undirected) the pairs within
    the limit and the footprint's weights are the same to the last digit."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    from jaxface.anatomy.skin import footprint_matrix
    from jaxface.anatomy.skin_footprint import _geodesic_graph, _within

    mesh, _ = _grid_mesh(n=15, jitter=1.0)  # 10 mm grid
    X = mesh.vertices
    D = dijkstra(_geodesic_graph(mesh), directed=False)
    for limit in (6.0, 12.5, 31.0):
        near = _within(_geodesic_graph(mesh), X, limit, chunk=17)
        np.testing.assert_array_equal(near.toarray(), D <= limit)
    sig = np.where(X[:, 0] > 70.0, 14.0, 6.0)
    ref = np.where(D <= 2.5 * sig[:, None], np.exp(-0.5 * (D / sig[:, None]) ** 2), 0.0)
    ref /= ref.sum(axis=1, keepdims=True)
    F = footprint_matrix(mesh, sig, chunk=23)
    assert sp.issparse(F)
    np.testing.assert_allclose(F.toarray(), ref, rtol=1e-15, atol=0)


def test_clustered_footprint_synthesises_what_the_exact_one_does(rig):
    """The rig's default clustered footprint against the exact one, through the JAX path:
    the six emotions and AU12 agree within 0.15 mm on the default head."""
    from jaxface.anatomy.rig import FOOTPRINT_CLUSTER_MM

    assert FOOTPRINT_CLUSTER_MM > 0 and rig.skin.fp_count.shape[0] > 0
    exact = build_rig(generic_head(), footprint_cluster_mm=0.0)
    assert exact.skin.fp_count.shape[0] == 0
    assert rig.skin.fp_vals.shape[0] < exact.skin.fp_vals.shape[0]
    cases = [facs.emotion_controls(n, rig.muscle_names) for n in sorted(facs.EMOTIONS)]
    cases.append(facs.aus_to_controls({"AU12": 1.0}, rig.muscle_names))
    A = jnp.stack([jnp.asarray(a) for a, _, _ in cases])
    P = jnp.asarray([float(j.pitch_deg) for _, j, _ in cases])

    def run(r):
        return np.asarray(jax.jit(jax.vmap(lambda a, p: synthesize(r, a, JawPose(p))))(A, P))

    # mirror-image clusters on the symmetric head: the operator commutes with the mirror
    from jaxface.anatomy.skin import footprint_operator, footprint_sigma, mirror_vertices

    info = rig.info
    m = mirror_vertices(info.skin, info.frame)
    assert m is not None
    op = footprint_operator(
        info.skin, footprint_sigma(info.skin, info.frame, (10.0, 5.0)), cluster_mm=5.0, mirror=m
    )
    d = np.random.default_rng(0).normal(size=(len(m), 3))
    np.testing.assert_allclose(op.apply(d[m]), op.apply(d)[m], atol=1e-12)
    Xc, Xe = run(rig), run(exact)
    moved = np.linalg.norm(Xe - np.asarray(exact.rest)[None], axis=-1).max(axis=1)
    assert moved.min() > 3.0
    assert np.linalg.norm(Xc - Xe, axis=-1).max() < 0.15


def test_fat_thickness_keeps_the_layer_volume_and_stays_finite():
    import trimesh

    from jaxface.anatomy.skin import FAT_RATIO_RANGE, fat_thickness, vertex_areas

    mesh, _ = _grid_mesh(jitter=1.0)
    S0, T = mesh.vertices, mesh.triangles
    n = len(S0)
    # vertex areas against trimesh's triangle areas, summed vertex by vertex
    ref = np.zeros(n)
    for t, a in zip(T, trimesh.Trimesh(S0, T, process=False).area_faces):
        ref[t] += a
    a0 = vertex_areas(S0, T, n)
    np.testing.assert_allclose(a0, ref, rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(vertex_areas(jnp.asarray(S0), jnp.asarray(T), n, xp=jnp)), ref, rtol=1e-9
    )

    def factor(S, gain=1.0):
        return np.asarray(fat_thickness(jnp.asarray(S), jnp.asarray(T), a0, gain))

    np.testing.assert_allclose(factor(S0), 1.0, atol=1e-12)
    # squeezed to 0.7 of its width: a layer of 5 mm over the sheet thickens to 5 / 0.7, and
    # the prism (area x thickness) keeps its volume
    sq = S0 * np.array([0.7, 1.0, 1.0])
    f = factor(sq)
    np.testing.assert_allclose(f, 1.0 / 0.7, rtol=1e-9)
    area = trimesh.Trimesh(sq, T, process=False).area
    np.testing.assert_allclose(
        area * 5.0 * f.mean(), trimesh.Trimesh(S0, T, process=False).area * 5.0, rtol=1e-9
    )
    np.testing.assert_allclose(factor(sq, 0.5), np.sqrt(1.0 / 0.7), rtol=1e-9)
    np.testing.assert_allclose(factor(sq, 0.0), 1.0, rtol=1e-12)
    # stretched 3x: thins, but at most to the range's lower bound
    np.testing.assert_allclose(
        factor(S0 * np.array([3.0, 1.0, 1.0])), FAT_RATIO_RANGE[0], rtol=1e-9
    )
    # a local squeeze moves only the vertices whose triangles changed
    loc = S0.copy()
    k = np.argmin(np.linalg.norm(S0 - S0.mean(0), axis=1))
    loc[k] += np.array([4.0, 0.0, 0.0])
    f = factor(loc)
    near = np.isin(np.arange(n), T[np.any(T == k, axis=1)].ravel())
    np.testing.assert_allclose(f[~near], 1.0, atol=1e-12)
    assert np.any(np.abs(f[near] - 1.0) > 0.05)
    # a collapsed triangle (zero area) and a vertex in no triangle: finite, also the reverse
    # pass, in float32
    bad = S0.copy()
    t0 = T[0]
    bad[t0[1]] = bad[t0[0]]
    bad[t0[2]] = bad[t0[0]]
    Sx = np.vstack([bad, [[500.0, 500.0, 0.0]]])
    a0x = np.concatenate([a0, [0.0]])
    with jax.enable_x64(False):
        S32 = jnp.asarray(Sx, jnp.float32)
        fx = fat_thickness(S32, jnp.asarray(T), a0x, 0.5)
        g = jax.grad(lambda S: jnp.sum(fat_thickness(S, jnp.asarray(T), a0x, 0.5) ** 2))(S32)
    assert np.all(np.isfinite(np.asarray(fx))) and np.all(np.isfinite(np.asarray(g)))
    assert float(fx[-1]) == 1.0
    assert float(np.max(np.asarray(fx))) <= np.sqrt(FAT_RATIO_RANGE[1]) + 1e-6


def test_fat_volume_is_checked():
    for bad in (1.5, -0.1, (0.5, 0.2, 0.1), float("nan")):
        with pytest.raises(RigError, match="fat_volume"):
            build_rig(generic_head(), fat_volume=bad)


def test_a_symmetric_face_gets_a_symmetric_rig(rig, results):
    """The default head is a mirror image of itself; so must its rig be. Before the right
    side's muscle quads were split the other way, no triangle of a left muscle matched its
    right twin's, 45 skin vertices bound to other muscles than their mirror images, and a
    full AU12 moved the skin below one mouth corner 13.6 mm further than below the other."""
    from scipy.spatial import cKDTree

    info = rig.info
    fr = info.frame
    flip = np.array([-1.0, 1.0, 1.0])
    R = fr.to_local(np.asarray(rig.rest))
    d, mirror = cKDTree(R).query(R * flip)
    assert d.max() < 1e-9  # the head is symmetric
    placed = {p.spec.name: p for p in info.placed}
    n_pairs = 0
    for name, p in placed.items():
        if not name.endswith("_L") or p.mesh is None:  # eyelids have no mesh
            continue
        q = placed[name[:-2] + "_R"]
        A, B = fr.to_local(p.mesh.vertices), fr.to_local(q.mesh.vertices) * flip
        dv, jv = cKDTree(B).query(A)
        assert dv.max() < 1e-6, name
        tb = {tuple(sorted(t)) for t in q.mesh.triangles}
        assert {tuple(sorted(jv[list(t)])) for t in p.mesh.triangles} == tb, name
        n_pairs += 1
    assert n_pairs >= 15
    names = info.registry.names
    surf = info.binding.surface

    def mirrored(n):
        return n[:-2] + {"_L": "_R", "_R": "_L"}[n[-2:]] if n[-2:] in ("_L", "_R") else n

    off_mid = np.flatnonzero(np.abs(R[:, 0]) > 1e-6)  # a mid-line vertex picks a side
    assert all(mirrored(names[surf[i]]) == names[surf[mirror[i]]] for i in off_mid)
    # a symmetric expression moves the skin symmetrically. Before every sphincter ring sample
    # took both modioli's pulls (not only its nearer side's), a full AU12 moved the lip mid-line
    # 0.46 mm sideways (0.91 mm of asymmetry); before the sphincter ellipse reached the
    # farthest sample on either side of its centre, the left eye's ellipse was 20 mm wide and
    # the right eye's 33 mm, and AU6 was 0.43 mm asymmetric.
    # Muscles lying across the mid-line (procerus on both frontales) bind each mid-line
    # particle to one side: measured 0.13 mm (AU1), 0.04 mm (AU4), 0.03 mm (AU9)
    tol = dict.fromkeys(
        ("AU2", "AU12", "AU15", "AU20", "AU23", "AU43", "pitch14", "lips_stretched_open"), 1e-6
    )
    tol.update(dict.fromkeys(("AU1", "AU4", "AU9"), 0.2))
    for case, most in tol.items():
        D = fr.to_local(results[0][case][0]) - R
        assert np.linalg.norm(D - D[mirror] * flip, axis=1).max() < most, case
    ab = {p.spec.name: p.semi_axes for p in info.placed if p.semi_axes is not None}
    np.testing.assert_allclose(ab["orbicularis_oculi_L"], ab["orbicularis_oculi_R"], atol=1e-9)
    D = fr.to_local(results[0]["AU12"][0]) - R
    assert np.linalg.norm(D, axis=1).max() > 10.0
