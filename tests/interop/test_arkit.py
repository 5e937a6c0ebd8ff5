"""ARKit-52 readout: the name mapping and sides, the bounded QP against an independent solver,
exact recovery of known coefficients from motions built from a basis (rig-free and ICP), the
unavailable-data path, and on shared data the side of the one-sided smile scan (LFAU_12L)."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from scipy.optimize import minimize

from jaxface.interop.arkit import (
    ARKIT_MISSING_IN_ICT,
    ARKIT_NAMES,
    ICT_TO_ARKIT,
    ICT_UNUSED,
    ArkitBasis,
    ArkitReadout,
    arkit_deltas_from_ict,
    arkit_from_ict_name,
    arkit_weights_from_ict,
    box_qp,
    eye_rim_motion,
    fit_arkit_to_scan,
    ict_transfer_error,
    landmark_motion,
    readout_for_subject,
    solve_arkit,
)


# ------------------------------------------------------------------------------ names
def test_arkit_names_are_apples_52():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52
    assert ARKIT_NAMES[0] == "browDownLeft" and ARKIT_NAMES[-1] == "tongueOut"
    for n in ("eyeBlinkLeft", "jawOpen", "mouthSmileRight", "cheekPuff", "browInnerUp"):
        assert n in ARKIT_NAMES


def test_ict_to_arkit_sides_and_merges():
    assert arkit_from_ict_name("eyeBlink_L") == "eyeBlinkLeft"
    assert arkit_from_ict_name("eyeBlink_R") == "eyeBlinkRight"
    assert arkit_from_ict_name("mouthSmile_L") == "mouthSmileLeft"
    assert (
        arkit_from_ict_name("browInnerUp_L")
        == arkit_from_ict_name("browInnerUp_R")
        == "browInnerUp"
    )
    assert arkit_from_ict_name("cheekPuff_R") == "cheekPuff"
    assert arkit_from_ict_name("jawOpen") == "jawOpen"
    for n in ICT_UNUSED:
        assert arkit_from_ict_name(n) is None
    # every ARKit name but tongueOut has an ICT source, and only the merged ones have two
    covered = set(ICT_TO_ARKIT.values())
    assert covered == set(ARKIT_NAMES) - set(ARKIT_MISSING_IN_ICT)
    assert len(ICT_TO_ARKIT) == 53
    two = {a for a in covered if list(ICT_TO_ARKIT.values()).count(a) == 2}
    assert two == {"browInnerUp", "cheekPuff"}


def test_recipe_weights_and_deltas_follow_the_mapping():
    w = arkit_weights_from_ict({"browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "mouthSmile_L": 0.7})
    assert w["browInnerUp"] == 1.0 and w["mouthSmileLeft"] == 0.7 and w["mouthSmileRight"] == 0.0
    assert set(w) == set(ARKIT_NAMES)
    names = sorted(ICT_TO_ARKIT) + list(ICT_UNUSED)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(len(names), 5, 3))
    out, avail = arkit_deltas_from_ict(names, d)
    k = ARKIT_NAMES.index("browInnerUp")
    np.testing.assert_allclose(
        out[k], d[names.index("browInnerUp_L")] + d[names.index("browInnerUp_R")]
    )
    np.testing.assert_allclose(out[ARKIT_NAMES.index("eyeBlinkLeft")], d[names.index("eyeBlink_L")])
    assert not avail[ARKIT_NAMES.index("tongueOut")]
    assert np.all(out[ARKIT_NAMES.index("tongueOut")] == 0)


# ------------------------------------------------------------------------------ solver
def test_box_qp_matches_an_independent_bounded_solver():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 8))
    G = A.T @ A
    g = A.T @ rng.normal(size=40) * 3.0
    c = box_qp(G, g)

    def f(x):
        return 0.5 * x @ G @ x - g @ x, G @ x - g

    ref = minimize(
        f,
        np.full(8, 0.5),
        jac=True,
        method="L-BFGS-B",
        bounds=[(0, 1)] * 8,
        options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 5000},
    )
    assert f(c)[0] <= ref.fun + 1e-9
    np.testing.assert_allclose(c, ref.x, atol=1e-5)
    assert np.any(c == 0.0) or np.any(c == 1.0)  # the bounds are active in this case


def _sphere_basis(seed=0, subdiv=3):
    """A sphere (radius 50 mm) with 52 smooth random displacement fields (unit RMS, mm)."""
    s = trimesh.creation.icosphere(subdivisions=subdiv, radius=50.0)
    V = np.asarray(s.vertices)
    F = np.asarray(s.faces)
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(52, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True) / 50.0
    dirs = rng.normal(size=(52, 3))
    D = (
        np.exp(-np.sum((V[None] - centres[:, None]) ** 2, -1) / (2 * 15.0**2))[..., None]
        * dirs[:, None]
    )
    D[ARKIT_NAMES.index("tongueOut")] = 0.0
    D *= 3.0
    avail = np.ones(52, bool)
    avail[ARKIT_NAMES.index("tongueOut")] = False
    return V, F, ArkitBasis(D, avail, np.ones(len(V), bool), "synthetic")


def test_solve_recovers_known_coefficients_exactly():
    V, F, basis = _sphere_basis()
    truth = dict.fromkeys(ARKIT_NAMES, 0.0)
    truth.update(jawOpen=0.5, mouthSmileLeft=1.0, browInnerUp=0.3, eyeBlinkRight=0.8)
    motion = np.einsum("k,kvd->vd", np.array([truth[n] for n in ARKIT_NAMES]), basis.deltas)
    sol = solve_arkit(basis, motion, l1=0.0)
    for n in ARKIT_NAMES:
        assert sol.coefficients[n] == pytest.approx(truth[n], abs=1e-6), n
    assert sol.residual_mm < 1e-5
    assert sol.unavailable == ("tongueOut",)
    # contributions are the RMS of each shape's share of the motion
    k = ARKIT_NAMES.index("jawOpen")
    want = np.sqrt(np.mean(np.sum((0.5 * basis.deltas[k]) ** 2, -1)))
    assert sol.contribution_mm["jawOpen"] == pytest.approx(want, rel=1e-6)
    # robust weights: gross outliers on a few vertices do not move the answer
    bad = motion.copy()
    bad[:6] += 40.0
    sol2 = solve_arkit(basis, bad, l1=0.0)
    got = np.array([sol2.coefficients[n] for n in ARKIT_NAMES])
    np.testing.assert_allclose(got, [truth[n] for n in ARKIT_NAMES], atol=0.02)


def test_l1_penalises_each_shapes_motion_not_its_coefficient():
    """Shapes on disjoint vertex blocks (orthogonal): without robust weights the optimum is
    analytic, ``c_k = c_true - l1 / (2 s_k)`` with ``s_k`` the shape's RMS motion (mm), so a
    0.25 mm shape loses 0.04 and a 10 mm shape 0.001 of the same true coefficient (a plain
    ``l1 * c_k`` would take 0.16 from the small one)."""
    n_per = 10
    K = len(ARKIT_NAMES)
    rng = np.random.default_rng(3)
    D = np.zeros((K, K * n_per, 3))
    for k in range(K):
        u = rng.normal(size=(n_per, 3))
        D[k, k * n_per : (k + 1) * n_per] = u
    avail = np.ones(K, bool)
    avail[ARKIT_NAMES.index("tongueOut")] = False
    D[~avail] = 0.0
    small, large = ARKIT_NAMES.index("eyeWideLeft"), ARKIT_NAMES.index("jawOpen")
    mask = np.ones(K * n_per, bool)
    rms = np.sqrt(np.mean(np.sum(D**2, -1), -1))
    D[small] *= 0.25 / rms[small]
    D[large] *= 10.0 / rms[large]
    basis = ArkitBasis(D, avail, mask, "synthetic")
    np.testing.assert_allclose(basis.scale_mm[[small, large]], [0.25, 10.0], rtol=1e-12)
    c = np.zeros(K)
    c[[small, large]] = 0.6
    motion = np.einsum("k,kvd->vd", c, D)
    l1 = 0.02
    sol = solve_arkit(basis, motion, l1=l1, robust=False)
    assert sol.coefficients["eyeWideLeft"] == pytest.approx(0.6 - l1 / (2 * 0.25), abs=1e-7)
    assert sol.coefficients["jawOpen"] == pytest.approx(0.6 - l1 / (2 * 10.0), abs=1e-7)
    others = [sol.coefficients[n] for i, n in enumerate(ARKIT_NAMES) if i not in (small, large)]
    assert max(others) == 0.0


def test_scan_icp_recovers_known_coefficients():
    V, F, basis = _sphere_basis(seed=1)
    c = np.zeros(52)
    c[[ARKIT_NAMES.index(n) for n in ("mouthSmileLeft", "noseSneerRight", "jawOpen")]] = [
        1.0,
        0.6,
        0.4,
    ]
    scan = V + np.einsum("k,kvd->vd", c, basis.deltas)
    lm_ids = np.arange(0, len(V), 37)
    tri = np.array([np.flatnonzero((F == i).any(1))[0] for i in lm_ids])
    bary = (F[tri] == lm_ids[:, None]).astype(float)  # each landmark on a triangle corner
    lmot = np.einsum("k,kld->ld", c, basis.deltas[:, lm_ids])
    sol = fit_arkit_to_scan(basis, V, F, scan, F, landmarks=(tri, bary, lmot), l1=0.0, iterations=8)
    got = np.array([sol.coefficients[n] for n in ARKIT_NAMES])
    np.testing.assert_allclose(got, c, atol=0.03)


def _plane_with_eyes(step, holes):
    """A flat face (z = 0, mm) sampled every ``step`` mm, without the triangles whose
    centroid lies inside any of ``holes`` (each a predicate on ``(n, 2)`` points)."""
    xs = np.arange(-60.0, 60.0 + 1e-9, step)
    ys = np.arange(0.0, 60.0 + 1e-9, step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    n = len(ys)
    F = []
    for i in range(len(xs) - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            F += [(a, b, c), (a, c, d)]
    F = np.asarray(F)
    cen = V[F].mean(1)[:, :2]
    inside = np.zeros(len(F), bool)
    for h in holes:
        inside |= h(cen)
    return V, F[~inside]


def _ellipse(cx, cy, a, b_up, b_down):
    def inside(p):
        dy = p[:, 1] - cy
        b = np.where(dy > 0, b_up, b_down)
        return ((p[:, 0] - cx) / a) ** 2 + (dy / b) ** 2 < 1.0

    return inside


def test_eye_rims_see_a_lid_sliding_across_the_eye():
    """A flat face with two eye openings: ``eyeWideLeft`` stretches the left opening's upper
    half upward by 40 % (2.4 mm at the top) *within* the plane, which point-to-plane matching
    cannot see. The scans' holes (a finer grid, shifted 0.3 / -0.4 mm from the skin's
    openings) follow; the expression's right eye is closed (no hole). With the rim term the
    readout recovers the coefficient (1); without it, nothing."""
    cx, cy, a, b, k = 30.0, 30.0, 14.0, 6.0, 1.4
    skin_holes = [_ellipse(cx, cy, a, b, b), _ellipse(-cx, cy, a, b, b)]
    V, F = _plane_with_eyes(2.0, skin_holes)
    sx, sy = 0.3, -0.4
    neutral_holes = [_ellipse(cx + sx, cy + sy, a, b, b), _ellipse(-cx + sx, cy + sy, a, b, b)]
    expr_holes = [_ellipse(cx + sx, cy + sy, a, k * b, b)]
    nv, nf = _plane_with_eyes(1.0, neutral_holes)
    ev, ef = _plane_with_eyes(1.0, expr_holes)
    names = [f"{w} {s} eye corner" for s in ("left", "right") for w in ("Inner", "Outer")]
    pos = np.array([[cx - a, cy, 0], [cx + a, cy, 0], [-cx + a, cy, 0], [-cx - a, cy, 0]])
    lms = SimpleNamespace(names=names, positions=pos)
    neutral = SimpleNamespace(landmarks=lms, mesh_arrays=lambda: (nv, nf, None))
    scan = SimpleNamespace(landmarks=lms, mesh_arrays=lambda: (ev, ef, None))
    ident = SimpleNamespace(apply=lambda p: np.asarray(p, float))

    rims = eye_rim_motion(V, F, neutral, scan, ident)
    assert rims.sides == ("left",)  # the right eye is closed in the expression
    assert np.all(np.linalg.norm(V[rims.vertices, :2] - [cx, cy], axis=1) < a + 3)
    y = V[rims.vertices, 1]
    m0, _ = rims.motion()
    assert m0[y > cy + 0.5 * b, 1].max() > 1.5  # the upper lid rose (2.4 mm at most)
    assert np.abs(m0[y < cy - 0.5 * b]).max() < 0.3  # the lower one stayed

    # the basis: eyeWideLeft as above (in the plane); every other shape a smooth bump in z
    r = np.sqrt(((V[:, 0] - cx) / a) ** 2 + ((V[:, 1] - cy) / b) ** 2)
    D = np.zeros((52, len(V), 3))
    up = V[:, 1] > cy
    D[ARKIT_NAMES.index("eyeWideLeft"), :, 1] = np.where(
        up, (V[:, 1] - cy) * (k - 1) * np.clip(2.0 - r, 0.0, 1.0), 0.0
    )
    rng = np.random.default_rng(5)
    for i in range(52):
        if ARKIT_NAMES[i] not in ("eyeWideLeft", "tongueOut"):
            c0 = rng.uniform([-50, 5], [50, 55])
            D[i, :, 2] = 2.0 * np.exp(-np.sum((V[:, :2] - c0) ** 2, 1) / (2 * 12.0**2))
    avail = np.ones(52, bool)
    avail[ARKIT_NAMES.index("tongueOut")] = False
    basis = ArkitBasis(D, avail, np.ones(len(V), bool), "synthetic")
    with_rims = fit_arkit_to_scan(basis, V, F, ev, ef, rims=rims, l1=0.001)
    without = fit_arkit_to_scan(basis, V, F, ev, ef, l1=0.001)
    assert with_rims.coefficients["eyeWideLeft"] == pytest.approx(1.0, abs=0.15)
    assert without.coefficients["eyeWideLeft"] < 0.05
    assert max(v for n, v in with_rims.coefficients.items() if n != "eyeWideLeft") < 0.05

    # the fit's readout reads the scan the same way, and the fitted skin beside it
    ro = ArkitReadout(V, basis, l1=0.001)
    coeffs, detail = ro.from_scan(
        scan, neutral, ident, F, (), np.zeros(0, int), np.zeros((0, 3)), V
    )
    assert coeffs is not None and coeffs["eyeWideLeft"] == pytest.approx(
        with_rims.coefficients["eyeWideLeft"], abs=1e-9
    )
    assert "left" in detail["method"] and detail["fitted_skin"]["coefficients"]["eyeWideLeft"] == 0
    assert ArkitReadout(V, reason="no data").from_scan(scan, neutral, ident, F, (), [], []) == (
        None,
        {"available": False, "reason": "no data"},
    )

    # the neutral against itself: no motion at all
    still = eye_rim_motion(V, F, neutral, neutral, ident)
    assert still.sides == ("left", "right")
    np.testing.assert_allclose(still.motion()[0], 0.0, atol=1e-12)


def test_readout_without_ict_data_says_why(monkeypatch, tmp_path):
    V, F, _ = _sphere_basis()

    class Subject:  # the attributes readout_for_subject reads from a fit Subject
        forward = SimpleNamespace(rest=V)
        triangles = F
        face_mask = np.ones(len(V), bool)

        def landmarks_on(self, x):
            return None

    subject = Subject()
    monkeypatch.setenv("JAXFACE_ICT", str(tmp_path / "missing.npz"))
    ro = readout_for_subject(subject, "auto")
    coeffs, detail = ro(V + 1.0)
    assert coeffs is None and detail["available"] is False
    assert "JAXFACE_ICT" in detail["reason"]
    coeffs, detail = readout_for_subject(subject, None)(V)
    assert coeffs is None and "not requested" in detail["reason"]


# ------------------------------------------------------------------------------ shared data
@pytest.fixture(scope="module")
def bs900_basis():
    from jaxface.fit.register import register_template
    from jaxface.interop.arkit import transfer_ict_basis
    from jaxface.io import load_scan
    from jaxface.testing import shared_path

    root = shared_path("data", "bosphorus_style")
    shared_path("data", "ict", "ict_face.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        neutral = load_scan(root / "bs900_N_N_0.bnt")
    reg = register_template(neutral)
    basis = transfer_ict_basis(
        reg.vertices,
        reg.mesh.triangles,
        reg.landmarks,
        reg.face_mask,
        ict_path=shared_path("data", "ict", "ict_face.npz"),
    )
    return root, neutral, reg, basis


@pytest.mark.data
def test_ict_left_shapes_act_on_the_subjects_left(shared):
    d = np.load(shared("data", "ict", "ict_face.npz"))
    names = [str(n) for n in d["expression_names"]]
    X = d["neutral"]
    for n in ("mouthSmile_L", "eyeBlink_L", "browDown_L"):
        m = np.linalg.norm(d["expression_deltas"][names.index(n)], axis=1)
        w = m / m.sum()
        assert float(w @ X[:, 0]) > 10.0, n  # +x: the subject's left


@pytest.mark.data
def test_one_sided_smile_reads_as_mouth_smile_left(bs900_basis):
    from jaxface.fit.align import align_scans
    from jaxface.io import load_scan

    root, neutral, reg, basis = bs900_basis
    assert basis.available.sum() == 51
    # the transferred left smile moves the subject's left (+x) side of the registered skin
    k = ARKIT_NAMES.index("mouthSmileLeft")
    m = np.linalg.norm(basis.deltas[k], axis=1)
    assert float((m / m.sum()) @ reg.vertices[:, 0]) > 10.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scan = load_scan(root / "bs900_LFAU_12L_0.bnt")
    al = align_scans(scan, neutral)
    v, tr, _ = scan.mesh_arrays()
    lmk = landmark_motion(reg, neutral, scan, al.transform)
    sol = fit_arkit_to_scan(
        basis, reg.vertices, reg.mesh.triangles, al.transform.apply(v), tr, landmarks=lmk
    )
    top = sol.strongest(3)
    assert top[0][0] == "mouthSmileLeft", top
    assert sol.coefficients["mouthSmileLeft"] > 3 * sol.coefficients["mouthSmileRight"] + 0.2


@pytest.mark.data
def test_basis_on_the_ict_identity_matches_the_ict_shapes(bs900_basis):
    """bs900 is the ICT neutral scanned as is, so the true transfer is ICT's own shapes at
    each registered vertex's closest point (0.01 mm away). Measured: median relative error
    0.10 over the 51 shapes (0.21 with an exactly interpolating cloning morph, 0.41 when
    Multi-PIE's menton stood in for Bosphorus's chin and the eye/mouth contours were
    dropped), eyeWide 0.06 (0.22-0.35), eyeBlink 0.10-0.11 (0.34-0.45), jawOpen 0.12."""
    _, _, reg, basis = bs900_basis
    assert "Chin middle" not in basis.info["landmarks"]
    assert not basis.info["contours_skipped"], basis.info["contours_skipped"]
    err = ict_transfer_error(basis, reg.vertices)
    assert len(err) == 51
    assert float(np.median(list(err.values()))) < 0.15, sorted(err.items(), key=lambda kv: -kv[1])
    assert err["jawOpen"] < 0.2 and err["mouthSmileLeft"] < 0.15
    assert max(err["eyeWideLeft"], err["eyeWideRight"]) < 0.15
    assert max(err["eyeBlinkLeft"], err["eyeBlinkRight"]) < 0.2


@pytest.mark.data
def test_transfer_error_follows_the_subjects_frame(bs900_basis):
    """The oracle in another frame: rotating and shifting the skin, the basis and the true
    neutral together (``truth_neutral``, ``rotation``) leaves every error unchanged, and a
    wrong rotation does not."""
    import dataclasses

    from jaxface.anatomy.ict import FACE_VERTEX_COUNT, load_ict_face
    from jaxface.errors import FitError
    from jaxface.rigid import RigidTransform, rotation_from_euler
    from jaxface.testing import shared_path

    _, _, reg, basis = bs900_basis
    ict_path = shared_path("data", "ict", "ict_face.npz")
    ict = load_ict_face(ict_path)
    T = RigidTransform(
        rotation=rotation_from_euler(7.0, -12.0), translation=np.array([3.0, -5.0, 9.0])
    )
    moved = dataclasses.replace(basis, deltas=basis.deltas @ T.rotation.T)
    ref = ict_transfer_error(basis, reg.vertices, ict_path)
    got = ict_transfer_error(
        moved,
        T.apply(np.asarray(reg.vertices)),
        ict_path,
        truth_neutral=T.apply(np.asarray(ict.skin.vertices)[:FACE_VERTEX_COUNT]),
        rotation=T.rotation,
    )
    assert got.keys() == ref.keys()
    np.testing.assert_allclose([got[k] for k in ref], [ref[k] for k in ref], rtol=1e-6, atol=1e-9)
    wrong = ict_transfer_error(
        moved,
        T.apply(np.asarray(reg.vertices)),
        ict_path,
        truth_neutral=T.apply(np.asarray(ict.skin.vertices)[:FACE_VERTEX_COUNT]),
    )
    assert wrong["jawOpen"] > ref["jawOpen"] + 0.05
    with pytest.raises(FitError, match="ICT face topology"):
        ict_transfer_error(basis, reg.vertices, ict_path, truth_neutral=np.zeros((10, 3)))


# ------------------------------------------------------------------------------ synth --arkit
def test_parse_arkit_and_inverse_map_controls():
    from jaxface.errors import FitError
    from jaxface.interop.inverse import JAW_UNITS, InverseMap, parse_arkit

    assert parse_arkit(["browInnerUp=0.8,jawOpen=0.3", "eyeBlinkLeft"]) == {
        "browInnerUp": 0.8,
        "jawOpen": 0.3,
        "eyeBlinkLeft": 1.0,
    }
    with pytest.raises(FitError, match="unknown ARKit shape"):
        parse_arkit(["eyeBlink_L=1"])  # the ICT name, not ARKit's
    with pytest.raises(FitError, match=r"\[0, 1\]"):
        parse_arkit(["jawOpen=1.5"])
    muscles = ("m0", "m1")
    inputs = muscles + tuple(JAW_UNITS)
    M = np.zeros((52, len(inputs)))
    M[ARKIT_NAMES.index("jawOpen"), inputs.index("jaw_pitch")] = 0.5
    M[ARKIT_NAMES.index("jawLeft"), inputs.index("jaw_yaw_left")] = 1.0
    M[ARKIT_NAMES.index("mouthSmileLeft"), 1] = 0.7
    M[ARKIT_NAMES.index("cheekPuff"), inputs.index("cheek_puff")] = 1.0
    imap = InverseMap(inputs, M, np.zeros(52), np.zeros(52), "k")
    a, (pitch, yaw, prot), puff = imap.controls(
        {"jawOpen": 1.0, "jawLeft": 0.4, "mouthSmileLeft": 1.0, "cheekPuff": 0.5}, ["m1", "m0"]
    )
    np.testing.assert_allclose(a, [0.7, 0.0])  # in the order asked for
    assert pitch == pytest.approx(9.0) and yaw == pytest.approx(2.0) and prot == 0.0
    assert puff == pytest.approx(0.5)
    # a JSON round trip keeps the map
    back = InverseMap.from_json(imap.to_json())
    np.testing.assert_array_equal(back.matrix, M)
    assert back.inputs == inputs
