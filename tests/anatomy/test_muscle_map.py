"""The muscle map: JSON loading and validation, L/R expansion, placement on a face."""

import json

import numpy as np
import pytest

from jaxface.anatomy.muscle_geometry import grid_topology, jax_sample_polyline, sample_polyline
from jaxface.anatomy.muscle_map import default_muscle_map_path, load_muscle_map, place_muscles
from jaxface.anatomy.skull import estimate_skull
from jaxface.errors import DataNotFoundError, RigError
from jaxface.head import generic_head

REQUIRED = [
    "frontalis_medial",
    "frontalis_lateral",
    "corrugator",
    "levator_labii_superioris_alaeque_nasi",
    "levator_labii_superioris",
    "zygomaticus_major",
    "zygomaticus_minor",
    "levator_anguli_oris",
    "risorius",
    "buccinator",
    "depressor_anguli_oris",
    "depressor_labii_inferioris",
    "mentalis",
    "platysma",
    "masseter",
    "cheek_fat",
]


def test_default_map_has_every_muscle_on_both_sides():
    specs = load_muscle_map()
    names = {s.name for s in specs}
    for m in REQUIRED:
        assert {m + "_L", m + "_R"} <= names, m
    assert {"procerus", "orbicularis_oris"} <= names
    kinds = {s.name: s.kind for s in specs}
    assert kinds["orbicularis_oris"] == "sphincter" and kinds["masseter_L"] == "passive"
    assert kinds["cheek_fat_R"] == "passive"
    # right = mirror of left
    L = next(s for s in specs if s.name == "zygomaticus_major_L")
    R = next(s for s in specs if s.name == "zygomaticus_major_R")
    assert R.insertion["offset"][0] == -L.insertion["offset"][0]
    assert list(R.insertion["at"]) == ["Right mouth corner"]


def _entry(d, name):
    return next(m for m in d["muscles"] if m["name"] == name)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d["muscles"][0].update(kind="spring"), "unknown kind"),
        (lambda d: d["muscles"][1].update(origin={"at": {}}), "origin"),
        (lambda d: d["muscles"][2].update(lies_on=["nonexistent"]), "unknown muscle"),
        (lambda d: d["muscles"][3].update(max_contraction=1.5), "max_contraction"),
        (lambda d: d["muscles"].append(dict(d["muscles"][4])), "duplicate"),
        (lambda d: _entry(d, "orbicularis_oris").update(n_around=32), "same n_around"),
        (lambda d: d["defaults"]["sphincter"].update(n_around=4), "n_around must be"),
        (lambda d: d["defaults"]["sphincter"].update(n_around=16.5), "n_around must be"),
    ],
)
def test_bad_maps_are_reported(tmp_path, mutate, match):
    d = json.loads(default_muscle_map_path().read_text())
    mutate(d)
    p = tmp_path / "map.json"
    p.write_text(json.dumps(d))
    with pytest.raises(RigError, match=match):
        load_muscle_map(p)


def test_sphincters_with_another_number_of_samples_around_build_and_contract(tmp_path):
    """``n_around`` other than 16, on every sphincter: the rig builds with that many ring samples
    (the modiolus weights included) and the mouth's sphincter (AU23) narrows the mouth."""
    import jax
    import jax.numpy as jnp

    from jaxface import facs
    from jaxface.anatomy.rig import build_rig, synthesize

    d = json.loads(default_muscle_map_path().read_text())
    d["defaults"]["sphincter"]["n_around"] = 24
    p = tmp_path / "map.json"
    p.write_text(json.dumps(d))
    rig = build_rig(generic_head(), muscle_map=p)
    assert rig.muscles.sph_ids.shape[2] == 24 and rig.muscles.mod_w.shape[2] == 24
    a, _, _ = facs.aus_to_controls({"AU23": 1.0}, rig.muscle_names)
    x = np.asarray(jax.jit(lambda a: synthesize(rig, a))(jnp.asarray(a)))
    rest = np.asarray(rig.rest)
    corners = [
        int(np.argmin(np.linalg.norm(rest - rig.info.landmarks[f"{s} mouth corner"], axis=1)))
        for s in ("Left", "Right")
    ]
    width = lambda v: v[corners[0], 0] - v[corners[1], 0]  # noqa: E731
    assert np.isfinite(x).all() and width(x) < width(rest) - 0.6


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(DataNotFoundError):
        load_muscle_map(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(RigError, match="not valid JSON"):
        load_muscle_map(tmp_path / "bad.json")


def test_sampling_eqs_4_1_to_4_5_and_contraction():
    pts = np.array([[0.0, 0, 0], [3.0, 0, 0], [3.0, 4.0, 0]])  # length 7
    s = sample_polyline(pts, 8)
    np.testing.assert_allclose(s[0], pts[0]) and np.testing.assert_allclose(s[-1], pts[-1])
    np.testing.assert_allclose(np.linalg.norm(np.diff(s, axis=0), axis=1)[:3], 1.0)
    sc = sample_polyline(pts, 8, contraction=0.5)  # step * (1 - c)
    np.testing.assert_allclose(sc[-1], [3.0, 0.5, 0.0])
    np.testing.assert_allclose(np.asarray(jax_sample_polyline(pts, 8, 0.5)), sc, atol=1e-12)


def test_grid_topology_is_closed():
    import trimesh

    for w, h, per in ((2, 8, False), (3, 6, False), (16, 3, True)):
        g = grid_topology(w, h, per)
        v = np.random.default_rng(0).normal(size=(g.n_vertices, 3))
        tm = trimesh.Trimesh(v, g.triangles, process=False)
        assert tm.is_watertight and tm.is_winding_consistent


@pytest.fixture(scope="module")
def placed():
    h = generic_head()
    sk = estimate_skull(h.mesh, h.landmarks)
    return h, place_muscles(h.mesh, h.landmarks, sk)


def test_placement_on_the_default_head(placed):
    h, pms = placed
    by = {p.name: p for p in pms}
    for p in pms:
        if p.mesh is None:
            continue
        mt = p.mesh.to_trimesh()
        assert mt.is_watertight and mt.volume > 0, p.name
        bottom = p.rest_vertices[: len(p.rest_vertices) // 2]
        sp_, dist = h.mesh.closest_points(bottom)
        tri = np.asarray(sp_.tri)
        q = np.einsum("kj,kjd->kd", np.asarray(sp_.bary), h.mesh.vertices[h.mesh.triangles[tri]])
        inward = np.einsum("kd,kd->k", bottom - q, h.mesh.face_normals[tri]) < 0
        assert inward.mean() > 0.9, p.name  # muscles lie under the skin
    lm = h.landmarks
    z = by["zygomaticus_major_L"]
    assert np.linalg.norm(z.insertion_skin[0] - lm["Left mouth corner"]) < 15
    assert z.origin.shape == (1, 3)
    f = by["frontalis_medial_R"]
    assert np.linalg.norm(f.insertion_skin.mean(0) - lm["Inner right eyebrow"]) < 15
    # left/right placements mirror each other on the (symmetric) default head
    for base in ("zygomaticus_major", "risorius", "frontalis_lateral", "depressor_anguli_oris"):
        L, R = by[base + "_L"], by[base + "_R"]
        np.testing.assert_allclose(
            L.origin_skin.mean(0) * [-1, 1, 1], R.origin_skin.mean(0), atol=3.0
        )
        np.testing.assert_allclose(L.insertion.mean(0) * [-1, 1, 1], R.insertion.mean(0), atol=3.0)
    oo = by["orbicularis_oris"]
    assert oo.semi_axes.min() > 5 and oo.normal[2] > 0.5
    lid = by["levator_palpebrae_L"]
    assert lid.centre[2] < lm["Outer left eye corner"][2]
