"""glTF export: structure checks on a small mesh (accessors, views, min/max, targets, normals,
animation), the round trip through pygltflib and trimesh, a malformed document caught, and on
the default head's rig the exported per-control targets (exact physics shapes) and the
animation of fits whose exact targets reproduce the fitted skin within 1e-4 m."""

import json

import numpy as np
import pygltflib
import pytest
import trimesh

from jaxface.errors import FitError, MeshError
from jaxface.interop.gltf import (
    GltfPart,
    build_gltf,
    check_gltf,
    load_glb,
    morph_targets_of,
    write_glb,
)
from jaxface.render import vertex_normals


def _small():
    s = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    V = np.asarray(s.vertices) + [0.0, 20.0, 60.0]
    F = np.asarray(s.faces)
    rng = np.random.default_rng(0)
    targets = [(f"t{k}", rng.normal(scale=2.0, size=V.shape)) for k in range(3)]
    return V, F, targets


def test_small_round_trip_structure_normals_and_animation(tmp_path):
    V, F, targets = _small()
    eye = trimesh.creation.icosphere(subdivisions=1, radius=12.0)
    W = np.array([[1.0, 0.0, 0.0], [0.2, 0.5, 1.0]])
    g = build_gltf(
        V,
        F,
        targets,
        parts=[GltfPart("eye_left", np.asarray(eye.vertices) + 30.0, np.asarray(eye.faces))],
        animation=(np.array([0.0, 1.0]), W),
    )
    assert check_gltf(g) == []
    p = write_glb(tmp_path / "a.glb", g)
    g2 = load_glb(str(p))
    assert check_gltf(g2) == []
    # accessors: POSITION float VEC3 with exact min/max in metres
    mesh = g2.meshes[0]
    prim = mesh.primitives[0]
    acc = g2.accessors[int(prim.attributes.POSITION or 0)]
    assert acc.type == "VEC3" and acc.componentType == pygltflib.FLOAT and acc.count == len(V)
    np.testing.assert_allclose(acc.min or [], (V / 1000).min(0), atol=1e-7)
    np.testing.assert_allclose(acc.max or [], (V / 1000).max(0), atol=1e-7)
    assert (mesh.extras or {})["targetNames"] == ["t0", "t1", "t2"]
    assert len(prim.targets or []) == 3 and mesh.weights == [0.0, 0.0, 0.0]
    r = morph_targets_of(g2)
    np.testing.assert_allclose(r["rest"], V / 1000, atol=1e-7)
    np.testing.assert_array_equal(r["triangles"], F)
    for k, (_, d) in enumerate(targets):
        np.testing.assert_allclose(r["deltas"][k], d / 1000, atol=1e-7)
    # normals: the rest's area-weighted normals; a target's NORMAL delta moves them to the
    # deformed skin's normals
    np.testing.assert_allclose(r["normals"], vertex_normals(V, F), atol=1e-6)
    np.testing.assert_allclose(
        r["normals"] + r["normal_deltas"][1], vertex_normals(V + targets[1][1], F), atol=1e-5
    )
    # the animation: one keyframe per row, LINEAR, on the skin node's weights
    np.testing.assert_allclose(r["times"], [0.0, 1.0])
    np.testing.assert_allclose(r["weights"], W)
    an = g2.animations[0]
    assert an.channels[0].target.path == "weights" and an.channels[0].target.node == 0
    # trimesh reads the same file: the skin and the part, in metres
    scene = trimesh.load_scene(str(p))
    assert set(scene.geometry) == {"skin", "eye_left"}
    np.testing.assert_allclose(scene.geometry["skin"].vertices, V / 1000, atol=1e-7)


def test_check_catches_a_malformed_document():
    V, F, targets = _small()
    g = build_gltf(V, F, targets)
    g.accessors[0].count += 10  # POSITION now overruns its view
    assert any("overruns" in p for p in check_gltf(g))
    g = build_gltf(V, F, targets)
    g.meshes[0].extras = {"targetNames": ["t0"]}
    assert any("targetNames" in p for p in check_gltf(g))
    g = build_gltf(V, F, targets)
    g.accessors[0].max = [9.0, 9.0, 9.0]
    assert any("min/max" in p for p in check_gltf(g))
    with pytest.raises(MeshError):
        write_glb("/nonexistent/never.glb", g)  # refused before anything is written
    with pytest.raises(MeshError, match="duplicate"):
        build_gltf(V, F, [("a", targets[0][1]), ("a", targets[1][1])])
    with pytest.raises(MeshError, match="NaN"):
        build_gltf(V, F, [("a", np.full(V.shape, np.nan))])


# ------------------------------------------------------------------------------ rig export
@pytest.fixture(scope="module")
def head_export(tmp_path_factory):
    """The default head's rig exported with three controls (two muscles, the left cheek's
    pressure), one AU and two fits (a JSON +
    fitted PLY each, in a scan frame rotated and shifted from the rig's) as exact targets."""
    import jax.numpy as jnp

    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import synthesize
    from jaxface.commands.export import load_export_subject, run_export
    from jaxface.fit.align import rotation_from_euler
    from jaxface.mesh import save_mesh

    tmp = tmp_path_factory.mktemp("export")
    subj = load_export_subject("default")
    rig = subj.rig
    names = list(rig.muscle_names)
    controls = [n for n in names if n.startswith("zygomaticus_major")][:2] + ["cheek_puff_L"]
    fits = []
    skins = {}
    for k, (stem, acts, pitch, puff) in enumerate(
        [("s_smile", {controls[0]: 0.8}, 0.0, 0.0), ("s_open", {controls[1]: 0.3}, 9.0, 0.5)]
    ):
        a = np.zeros(len(names))
        for n, v in acts.items():
            a[names.index(n)] = v
        p = jnp.array([puff, 0.0], rig.rest.dtype)  # the fit's cheek pressures, left and right
        x = np.asarray(synthesize(rig, jnp.asarray(a, rig.rest.dtype), JawPose(pitch, 0.0, 0.0), p))
        R = rotation_from_euler(4.0 + k, -3.0)
        t = np.array([1.5, -2.0, 3.0 * k])
        save_mesh(tmp / f"{stem}.fitted.ply", x @ R.T + t, rig.triangles, units="mm")
        (tmp / f"{stem}.json").write_text(
            json.dumps(
                {
                    "scan": stem,
                    "activations": {n: float(v) for n, v in zip(names, a)}
                    | {"cheek_puff_L": puff, "cheek_puff_R": 0.0},
                    "jaw": {"pitch_deg": pitch},
                    "rigid": {"rig_to_scan": {"rotation": R.tolist(), "translation": t.tolist()}},
                }
            )
        )
        fits.append(tmp / f"{stem}.json")
        skins[stem] = x
    out = tmp / "head.glb"
    res = run_export(subj, out, fits=fits, exact=True, controls=controls, au_names=["AU12"])
    return subj, out, res, skins, controls, fits, tmp


def test_head_export_targets_names_and_parts(head_export):
    import jax.numpy as jnp

    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import synthesize

    subj, out, res, skins, controls, _, _ = head_export
    g = load_glb(str(out))
    assert check_gltf(g) == []
    want = [f"muscle.{c}" for c in controls] + ["AU12", "fit.s_smile", "fit.s_open"]
    assert res["targets"] == want
    r = morph_targets_of(g)
    assert r["names"] == want
    np.testing.assert_allclose(r["rest"], subj.rest / 1000, atol=1e-7)
    # a control's target is the exact synthesis at activation 1 minus rest
    a = np.zeros(len(subj.rig.muscle_names))
    a[list(subj.rig.muscle_names).index(controls[0])] = 1.0
    x = np.asarray(
        synthesize(subj.rig, jnp.asarray(a, subj.rig.rest.dtype), JawPose(0.0, 0.0, 0.0), 0.0)
    )
    np.testing.assert_allclose(r["deltas"][0], (x - subj.rest) / 1000, atol=1e-7)
    assert np.abs(r["deltas"][0]).max() > 1e-3  # the smile moves the skin by millimetres
    # the left cheek's pressure at 1, as the fit's control cheek_puff_L
    p = jnp.array([1.0, 0.0], subj.rig.rest.dtype)
    x = np.asarray(synthesize(subj.rig, jnp.zeros_like(jnp.asarray(a)), JawPose(0.0, 0.0, 0.0), p))
    np.testing.assert_allclose(r["deltas"][2], (x - subj.rest) / 1000, atol=1e-7)
    assert np.abs(r["deltas"][2]).max() > 1e-3
    scene = trimesh.load_scene(str(out))
    assert {"skin", "eye_left", "eye_right", "upper_teeth", "lower_teeth"} <= set(scene.geometry)


def test_exact_keyframes_reproduce_the_fits(head_export):
    subj, out, res, skins, _, _, _ = head_export
    r = morph_targets_of(load_glb(str(out)))
    assert res["keyframes"] == ["s_smile", "s_open"]
    np.testing.assert_allclose(r["times"], [0.0, 1.0])
    for i, stem in enumerate(res["keyframes"]):
        w = r["weights"][i]
        assert w[r["names"].index(f"fit.{stem}")] == 1.0 and w.sum() == 1.0
        x = r["rest"] + np.einsum("k,kvd->vd", w, r["deltas"])
        assert np.abs(x - skins[stem] / 1000).max() < 1e-4


def test_activation_keyframes(head_export, tmp_path):
    from jaxface.commands.export import run_export

    subj, _, _, _, controls, fits, _ = head_export
    res = run_export(subj, tmp_path / "b.glb", fits=fits, exact=False, controls=controls, aus=False)
    r = morph_targets_of(load_glb(str(tmp_path / "b.glb")))
    assert r["names"] == [f"muscle.{c}" for c in controls]
    np.testing.assert_allclose(r["weights"], [[0.8, 0.0, 0.0], [0.0, 0.3, 0.5]], atol=1e-7)
    assert any("--exact" in n for n in res["notes"])


def test_read_fit_undoes_rig_to_scan_and_refuses_foreign_fits(tmp_path):
    from jaxface.fit.align import rotation_from_euler
    from jaxface.interop.targets import read_fit
    from jaxface.mesh import save_mesh

    V, F, _ = _small()
    R = rotation_from_euler(7.0, -4.0)
    t = np.array([3.0, -1.0, 2.5])
    save_mesh(tmp_path / "s.fitted.ply", V @ R.T + t, F, units="mm")
    doc = {
        "scan": "s",
        "activations": {"m": 0.25},
        "jaw": {"pitch_deg": 1.0},
        "rigid": {"rig_to_scan": {"rotation": R.tolist(), "translation": t.tolist()}},
        "arkit": {"jawOpen": 0.1},
    }
    (tmp_path / "s.json").write_text(json.dumps(doc))
    f = read_fit(tmp_path / "s.json", len(V))
    assert f.stem == "s" and f.activations == {"m": 0.25} and f.arkit == {"jawOpen": 0.1}
    np.testing.assert_allclose(f.skin, V, atol=1e-4)  # PLY float precision
    with pytest.raises(FitError, match="another subject"):
        read_fit(tmp_path / "s.json", len(V) + 1)
    (tmp_path / "bad.json").write_text(json.dumps({"scan": "bad"}))
    save_mesh(tmp_path / "bad.fitted.ply", V, F, units="mm")
    with pytest.raises(FitError, match="not a jaxface fit JSON"):
        read_fit(tmp_path / "bad.json")
