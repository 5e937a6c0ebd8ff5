"""Skull: tissue-depth table and interpolation, estimated skull, mandible split, user skulls
(ArtiSynth), template fitting by landmark RBF."""

import numpy as np
import pytest

from jaxface.anatomy.frame import face_frame
from jaxface.anatomy.skull import (
    TISSUE_DEPTH_MM,
    depth_sites,
    enrich_correspondences,
    estimate_skull,
    fit_skull,
    load_artisynth_skull,
    load_skull,
    mandible_mask,
    tissue_depth,
)
from jaxface.errors import DataNotFoundError
from jaxface.head import generic_head
from jaxface.landmarks import Landmarks


@pytest.fixture(scope="module")
def head():
    return generic_head()


@pytest.fixture(scope="module")
def skull(head):
    return estimate_skull(head.mesh, head.landmarks)


def test_depth_sites_carry_the_table(head):
    names, pos, depth = depth_sites(head.mesh, head.landmarks)
    assert {"glabella", "chin", "upper lip", "mid-masseter left", "gonion right"} <= set(names)
    for n, d in zip(names, depth):
        key = n.replace(" left", "").replace(" right", "")
        if key in TISSUE_DEPTH_MM:
            assert d == TISSUE_DEPTH_MM[key]
    # sites lie on the skin
    _, dist = head.mesh.closest_points(pos)
    assert dist.max() < 1e-6


def test_tissue_depth_interpolates_the_sites(head):
    names, pos, depth = depth_sites(head.mesh, head.landmarks)
    d = tissue_depth(head.mesh, head.landmarks)
    assert d.shape == (head.mesh.n_vertices,) and d.min() >= 2.0 and d.max() <= 25.0
    near = np.argmin(np.linalg.norm(head.mesh.vertices[None] - pos[:, None], axis=2), axis=1)
    # nearest vertex to each site (within ~1-2 mm) carries about the table value
    assert np.abs(d[near] - depth).max() < 1.5
    fr = face_frame(head.landmarks)
    loc = fr.to_local(head.mesh.vertices)
    forehead = (loc[:, 1] > 40) & (loc[:, 1] < 70) & (np.abs(loc[:, 0]) < 25) & (loc[:, 2] > 0)
    cheek = (np.abs(loc[:, 0] - 50) < 8) & (np.abs(loc[:, 1] + 62) < 8)
    assert d[forehead].mean() < 7.0 and d[cheek].mean() > 13.0


def below_skin(mesh, pts):
    """Signed distance (mm, negative = inside) of points to the skin, by closest point."""
    sp_, dist = mesh.closest_points(pts)
    tri = np.asarray(sp_.tri)
    n = mesh.face_normals[tri]
    q = np.einsum("kj,kjd->kd", np.asarray(sp_.bary), mesh.vertices[mesh.triangles[tri]])
    return np.sign(np.einsum("kd,kd->k", pts - q, n)) * dist


def test_estimated_skull_is_inside_and_split(head, skull):
    for part in (skull.cranium, skull.mandible):
        sd = below_skin(head.mesh, part.vertices)
        assert (sd < -1.0).mean() > 0.95
    # the offset follows the depth (smoothing moves it a little)
    off = skull.extras["offset_mesh"].vertices
    gap = np.linalg.norm(head.mesh.vertices - off, axis=1)
    assert np.median(np.abs(gap - skull.extras["depth"])) < 1.5
    fr = face_frame(head.landmarks)
    m = mandible_mask(
        np.stack(
            [
                fr.points["Chin middle"],
                fr.points["Lower lip outer middle"],
                fr.points["Nose tip"],
                fr.points["Inner left eyebrow"],
                fr.points["Upper lip outer middle"],
            ]
        ),
        fr,
    )
    assert m.tolist() == [True, True, False, False, False]
    assert skull.source == "estimated" and skull.mandible.n_triangles > 100


def test_fit_skull_reproduces_a_similarity(head, skull):
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    # a small rotation keeps "face along +z"
    ang = np.radians(8.0)
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    s, t = 1.1, np.array([3.0, -2.0, 5.0])
    f = lambda p: s * p @ R.T + t  # noqa: E731
    skin2 = head.mesh.with_vertices(f(head.mesh.vertices))
    lm2 = Landmarks(head.landmarks.names, f(head.landmarks.positions))
    fitted = fit_skull(skull, head.mesh, head.landmarks, skin2, lm2)
    np.testing.assert_allclose(fitted.cranium.vertices, f(skull.cranium.vertices), atol=1e-4)
    np.testing.assert_allclose(fitted.mandible.vertices, f(skull.mandible.vertices), atol=1e-4)
    assert fitted.thickness_scale == pytest.approx(1.1, rel=0.02)  # bounding-box diagonals
    extra = enrich_correspondences(head.mesh, head.landmarks)
    _, dist = head.mesh.closest_points(extra)
    assert extra.shape == (16, 3) and dist.max() < 1e-6


def test_artisynth_skull_in_mm_and_jaxface_axes(shared):
    sk = load_artisynth_skull(shared("data", "artisynth"))
    ext = np.ptp(sk.cranium.vertices, axis=0)
    assert 100 < ext.max() < 300  # metres -> mm
    c, m = sk.cranium.vertices, sk.mandible.vertices
    assert m[:, 1].mean() < c[:, 1].mean()  # the jaw is below
    assert m[:, 2].max() > c[:, 2].mean()  # the chin is in front (+z)
    assert abs(c[:, 0].mean()) < 5.0  # symmetric about x = 0


def test_user_skull_errors(tmp_path):
    with pytest.raises(DataNotFoundError):
        load_skull(tmp_path / "nope.obj", tmp_path / "nope2.obj")
    with pytest.raises(DataNotFoundError):
        load_artisynth_skull(tmp_path)
