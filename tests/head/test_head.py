"""The embedded default head: topology, landmarks, openings, teeth, proportions (all mm)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxface.head import EYE_RADIUS, RAY_ORIGIN, Head, build_head, generic_head
from jaxface.landmarks import BOSPHORUS_LABELS, check_side
from jaxface.mesh import TriMesh


@pytest.fixture(scope="module")
def head() -> Head:
    return generic_head()


def _angles(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]

    def ang(p, q, r):
        u, v = q - p, r - p
        cos = (u * v).sum(1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        return np.degrees(np.arccos(np.clip(cos, -1, 1)))

    return np.stack([ang(a, b, c), ang(b, c, a), ang(c, a, b)], axis=1)


def _segments_hit_mesh(mesh: TriMesh, p, q) -> np.ndarray:
    """(K,) bool: segment p_k -> q_k crosses the mesh surface (exact ray casting)."""
    d = q - p
    length = np.linalg.norm(d, axis=1)
    hits = mesh.ray_cast(p, d, all_hits=True, max_distance=float(length.max()))
    out = np.zeros(len(p), dtype=bool)
    ok = hits.distances <= length[hits.ray_index]
    out[hits.ray_index[ok]] = True
    return out


# ----------------------------------------------------------------------------- determinism
def test_deterministic_and_cached(head):
    again = build_head()
    np.testing.assert_array_equal(again.mesh.vertices, head.mesh.vertices)
    np.testing.assert_array_equal(again.mesh.triangles, head.mesh.triangles)
    np.testing.assert_array_equal(again.landmarks.positions, head.landmarks.positions)
    np.testing.assert_array_equal(again.upper_teeth.vertices, head.upper_teeth.vertices)
    assert generic_head() is head  # cached


# ----------------------------------------------------------------------------- mesh quality
def test_size_and_validation(head):
    m = head.mesh
    assert 8_000 <= m.n_vertices <= 13_000
    TriMesh(m.vertices, m.triangles).validate(orientation=True)  # raises on any defect
    assert m.vertices.dtype == np.float64 and m.triangles.dtype == np.int64
    # no unused vertex
    assert np.array_equal(np.unique(m.triangles), np.arange(m.n_vertices))


def test_triangle_quality(head):
    ang = _angles(head.mesh.vertices, head.mesh.triangles).min(axis=1)
    assert ang.min() > 10.0
    assert np.percentile(ang, 1) > 18.0
    e = head.mesh.edge_lengths
    assert e.min() > 0.4 and e.max() < 12.0


def test_orientation_outward(head):
    """Triangles face away from the head's interior: seen from the ray origin inside the head,
    the sum of signed solid angles of a closed-ish outward surface is ~ +4 pi."""
    V, F = head.mesh.vertices - RAY_ORIGIN, head.mesh.triangles
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + (a * b).sum(1) * lc + (a * c).sum(1) * lb + (b * c).sum(1) * la
    omega = 2.0 * np.arctan2(num, den).sum()
    # the neck opening, the eyes and the mouth miss a few percent of the full sphere
    assert 0.85 * 4 * np.pi < omega < 4 * np.pi


def test_face_is_a_height_field_without_folds(head):
    """Front triangles project onto the xy plane counter-clockwise (seen from +z): the relief
    never folds over (lip roll, nose underside, lids included)."""
    V, F = head.mesh.vertices, head.mesh.triangles
    front = head.face_mask[F].all(axis=1) & (head.mesh.face_normals[:, 2] > -0.5)
    front &= (V[F][:, :, 2] > 60.0).all(axis=1)
    a, b, c = (V[F[front, k], :2] for k in range(3))
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    assert front.sum() > 3000
    assert (area2 > 0).all()


def test_mirror_symmetry(head):
    V = head.mesh.vertices
    np.testing.assert_allclose(V[head.mirror], V * np.array([-1.0, 1.0, 1.0]), atol=1e-9)
    assert np.array_equal(head.mirror[head.mirror], np.arange(len(V)))

    # the triangulation is mirrored too (orientation reversed by the reflection)
    def canonical(F):  # rotate each triangle so that its smallest id comes first
        k = np.argmin(F, axis=1)[:, None]
        G = np.take_along_axis(F, (k + np.arange(3)) % 3, axis=1)
        return G[np.lexsort(G.T[::-1])]

    F = head.mesh.triangles
    np.testing.assert_array_equal(canonical(head.mirror[F][:, ::-1]), canonical(F))


# ----------------------------------------------------------------------------- openings
def test_boundaries_are_exactly_eyes_mouth_and_neck(head):
    loops = head.mesh.boundary_loops
    assert len(loops) == 4
    as_sets = sorted((frozenset(map(int, lp)) for lp in loops), key=len)
    expected = {
        "mouth": frozenset(
            map(int, np.concatenate([head.edges["upper_lip_edge"], head.edges["lower_lip_edge"]]))
        ),
        "eye_left": frozenset(
            map(int, np.concatenate([head.edges["upper_lid_left"], head.edges["lower_lid_left"]]))
        ),
        "eye_right": frozenset(
            map(int, np.concatenate([head.edges["upper_lid_right"], head.edges["lower_lid_right"]]))
        ),
        "neck": frozenset(map(int, head.edges["neck"])),
    }
    assert set(as_sets) == set(expected.values())
    # the neck cut is horizontal, below the chin
    neck_y = head.mesh.vertices[head.edges["neck"], 1]
    assert np.ptp(neck_y) < 1e-6 and neck_y[0] < head.landmarks["Chin middle"][1] - 40


@pytest.mark.parametrize(
    "upper,lower,corners",
    [
        ("upper_lip_edge", "lower_lip_edge", ("Right mouth corner", "Left mouth corner")),
        ("upper_lid_left", "lower_lid_left", ("Inner left eye corner", "Outer left eye corner")),
        (
            "upper_lid_right",
            "lower_lid_right",
            ("Inner right eye corner", "Outer right eye corner"),
        ),
    ],
)
def test_slits_have_distinct_edges_meeting_at_the_corners(head, upper, lower, corners):
    up, lo = head.edges[upper], head.edges[lower]
    V = head.mesh.vertices
    # shared corner vertices, distinct interior vertices
    assert up[0] == lo[0] and up[-1] == lo[-1]
    assert set(up[1:-1].tolist()).isdisjoint(lo[1:-1].tolist())
    assert len(up) == len(lo) >= 8
    for name, vid in zip(corners, (up[0], up[-1])):
        np.testing.assert_allclose(head.landmarks[name], V[vid], atol=1e-12)
        assert head.landmark_vertex[name] == vid
    if "lid" in upper:  # the lid hinge axis: inner -> outer corner
        inner, outer = head.eye_axis(upper.rsplit("_", 1)[1])
        np.testing.assert_allclose([inner, outer], V[[up[0], up[-1]]], atol=1e-12)
    # the upper edge lies above the lower one at every column
    assert np.all(V[up[1:-1], 1] > V[lo[1:-1], 1])
    np.testing.assert_allclose(V[up[1:-1], 0], V[lo[1:-1], 0], atol=0.25)  # same columns
    # each edge is a path of mesh edges
    E = {tuple(e) for e in head.mesh.edges.tolist()}
    for path in (up, lo):
        for a, b in zip(path[:-1], path[1:]):
            assert (min(a, b), max(a, b)) in E


def test_closed_mouth_and_open_eyes(head):
    V, lm = head.mesh.vertices, head.landmarks
    gap = lm["Upper lip inner middle"][1] - lm["Lower lip inner middle"][1]
    assert 0.3 < gap < 1.5  # the lips touch (closed mouth), distinct edges
    for side in ("left", "right"):
        up, lo = V[head.edges[f"upper_lid_{side}"]], V[head.edges[f"lower_lid_{side}"]]
        height = up[:, 1].max() - lo[:, 1].min()
        assert 8.0 < height < 12.5  # palpebral fissure height (adults ~ 9-11 mm)
        # lid margins lie in front of the eyeball, close to it
        c = head.eye_centers[0 if side == "left" else 1]
        r = np.linalg.norm(np.concatenate([up[1:-1], lo[1:-1]]) - c, axis=1)
        assert np.all(r > EYE_RADIUS + 0.5)
        assert EYE_RADIUS + 1.0 < np.median(r) < EYE_RADIUS + 2.5


# ----------------------------------------------------------------------------- landmarks
def test_landmarks_complete_on_surface_and_sided(head):
    lm = head.landmarks.require(BOSPHORUS_LABELS)
    assert tuple(lm.names) == tuple(BOSPHORUS_LABELS)
    _, dist = head.mesh.closest_points(head.landmarks.positions)
    assert dist.max() < 0.5
    check_side(head.landmarks)  # raises if mirrored
    for name in BOSPHORUS_LABELS:
        if "left" in name.lower():
            assert head.landmarks[name][0] > 0, name
        if "right" in name.lower():
            assert head.landmarks[name][0] < 0, name
    # mirror pairs are exact mirrors
    for name in BOSPHORUS_LABELS:
        if "left" in name.lower() or "Left" in name:
            other = name.replace("left", "right").replace("Left", "Right")
            np.testing.assert_allclose(
                head.landmarks[other], head.landmarks[name] * [-1, 1, 1], atol=1e-6
            )


def test_landmark_anatomy(head):
    lm = head.landmarks
    tip = lm["Nose tip"]
    V = head.mesh.vertices
    # the nose tip is the most anterior point of the face
    assert tip[2] >= V[head.regions["face"], 2].max() - 0.01
    # vertical order along the midline
    ys = [
        lm[n][1]
        for n in (
            "Inner left eyebrow",
            "Nose saddle left",
            "Nose tip",
            "Upper lip outer middle",
            "Upper lip inner middle",
            "Lower lip inner middle",
            "Lower lip outer middle",
            "Chin middle",
        )
    ]
    assert all(a > b for a, b in zip(ys[:-1], ys[1:]))
    # eyebrows above the eyes, the eye corners inside the brow span
    assert lm["Middle left eyebrow"][1] > lm["Outer left eye corner"][1] + 15
    assert (
        lm["Inner left eye corner"][0]
        < lm["Outer left eye corner"][0]
        < lm["Outer left eyebrow"][0]
    )
    # ear lobes at the sides, behind the face
    assert (
        lm["Left ear lobe"][0] > 60 and lm["Left ear lobe"][2] < lm["Outer left eye corner"][2] - 60
    )


def test_proportions_are_adult_human(head):
    """Ranges from adult anthropometry (Farkas' norms, both sexes, rounded outward)."""
    lm, V = head.landmarks, head.mesh.vertices
    d = lambda a, b: float(np.linalg.norm(lm[a] - lm[b]))  # noqa: E731
    assert 28 < d("Inner left eye corner", "Inner right eye corner") < 40  # en-en
    assert 80 < d("Outer left eye corner", "Outer right eye corner") < 100  # ex-ex
    assert 24 < d("Inner left eye corner", "Outer left eye corner") < 36  # eye fissure length
    assert 42 < d("Left mouth corner", "Right mouth corner") < 60  # ch-ch
    assert 30 < d("Left nose peak", "Right nose peak") < 46  # al-al
    nasion_y = lm["Nose saddle left"][1] + 10.0
    menton_y = V[head.regions["face"] & (np.abs(V[:, 0]) < 3), 1].min()
    assert 105 < nasion_y - menton_y < 135  # n-gn face height
    assert 140 < np.ptp(V[:, 0][np.abs(V[:, 1] - 50) < 5]) < 170  # head breadth eu-eu
    glabella_z = V[(np.abs(V[:, 0]) < 2) & (V[:, 1] > 35) & (V[:, 1] < 70), 2].max()
    assert 175 < glabella_z - V[:, 2].min() < 210  # head length g-op
    assert 210 < V[:, 1].max() - menton_y < 245  # vertex to menton
    # nose projection: tip ahead of the alar base / cheek by 20-35 mm
    assert 20 < lm["Nose tip"][2] - lm["Left nose peak"][2] < 35


# ----------------------------------------------------------------------------- regions
def test_regions(head):
    n = head.mesh.n_vertices
    for name, mask in head.regions.items():
        assert mask.shape == (n,) and mask.dtype == bool and mask.any(), name
    r = head.regions
    np.testing.assert_array_equal(head.face_mask, r["face"])
    assert not (r["upper_lip"] & r["lower_lip"]).any()
    assert not (r["upper_lip"] & r["jaw"]).any()
    assert (r["lips"] <= r["face"]).all()
    # the lower lip edge and the chin ride on the jaw; the upper lip edge does not
    lower_edge = head.edges["lower_lip_edge"][1:-1]
    upper_edge = head.edges["upper_lip_edge"][1:-1]
    assert r["jaw"][lower_edge].all() and not r["jaw"][upper_edge].any()
    assert r["lower_lip"][lower_edge].all() and r["upper_lip"][upper_edge].all()
    chin = np.argmin(np.linalg.norm(head.mesh.vertices - head.landmarks["Chin middle"], axis=1))
    assert r["jaw"][chin]
    # lids: left at +x, the margins belong to their lids
    V = head.mesh.vertices
    for side, sign in (("left", 1), ("right", -1)):
        assert (np.sign(V[r[f"eye_{side}"], 0]) == sign).all()
        assert r[f"upper_lid_{side}"][head.edges[f"upper_lid_{side}"][1:-1]].all()
        assert r[f"lower_lid_{side}"][head.edges[f"lower_lid_{side}"][1:-1]].all()
        assert not (r[f"upper_lid_{side}"] & r[f"lower_lid_{side}"]).any()
    # regions are mirror images of each other
    np.testing.assert_array_equal(r["eye_left"][head.mirror], r["eye_right"])
    np.testing.assert_array_equal(r["jaw"][head.mirror], r["jaw"])


# ----------------------------------------------------------------------------- teeth and eyes
def test_teeth_are_closed_and_behind_the_lips(head):
    lm = head.landmarks
    for teeth in (head.upper_teeth, head.lower_teeth):
        TriMesh(teeth.vertices, teeth.triangles).validate()
        assert teeth.boundary_loops == [] and teeth.signed_volume() > 500.0  # closed, outward
        # arch shape: widest at the back, front on the midline
        v = teeth.vertices
        assert v[:, 2].max() < lm["Upper lip inner middle"][2] - 5.0
        assert np.ptp(v[:, 0]) > 45.0
        # inside the head and clear of the skin
        _, dist = head.mesh.closest_points(v)
        assert dist.min() > 1.5
    # occlusion: upper incisal edge below the lower one (overbite), no interpenetration
    up, lo = head.upper_teeth.vertices, head.lower_teeth.vertices
    assert up[:, 1].min() < lo[:, 1].max()
    F = head.upper_teeth.triangles
    for a, b in ((head.upper_teeth, head.lower_teeth), (head.lower_teeth, head.upper_teeth)):
        e = a.edges
        assert not _segments_hit_mesh(b, a.vertices[e[:, 0]], a.vertices[e[:, 1]]).any()
    del F


def test_teeth_and_eyes_do_not_cross_the_skin(head):
    for part in (head.upper_teeth, head.lower_teeth, *head.eyes):
        e = part.edges
        assert not _segments_hit_mesh(
            head.mesh, part.vertices[e[:, 0]], part.vertices[e[:, 1]]
        ).any()
    # the eyeballs sit in their sockets, seen through the fissures
    for k, eye in enumerate(head.eyes):
        TriMesh(eye.vertices, eye.triangles).validate()
        assert eye.boundary_loops == []
        c = head.eye_centers[k]
        np.testing.assert_allclose(eye.vertices.mean(axis=0)[:2], c[:2], atol=0.5)
        assert np.sign(c[0]) == (1 if k == 0 else -1)
        side = "left" if k == 0 else "right"
        fissure = head.mesh.vertices[
            np.concatenate([head.edges[f"upper_lid_{side}"], head.edges[f"lower_lid_{side}"]])
        ]
        mid = fissure.mean(axis=0)
        # a ray from in front of the fissure centre hits the eyeball before anything else
        hit = eye.ray_cast(mid + [0, 0, 30.0], np.array([0.0, 0.0, -1.0]))
        skin = head.mesh.ray_cast(mid + [0, 0, 30.0], np.array([0.0, 0.0, -1.0]))
        assert hit.hit[0] and (not skin.hit[0] or skin.first_distance[0] > hit.first_distance[0])


def test_head_is_readonly(head):
    with pytest.raises((ValueError, AttributeError, TypeError)):
        head.face_mask[0] = not head.face_mask[0]
    with pytest.raises(dataclasses_frozen_error()):
        head.mesh = None


def dataclasses_frozen_error():
    import dataclasses

    return dataclasses.FrozenInstanceError


def test_spatial_index_sanity(head):
    """Vertices are unique (no accidental duplicates other than none: the slits have a gap)."""
    d, _ = cKDTree(head.mesh.vertices).query(head.mesh.vertices, k=2)
    assert d[:, 1].min() > 0.05
