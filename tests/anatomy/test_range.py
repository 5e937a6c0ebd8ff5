"""The anatomy's expressive range (issue 44), pinned qualitatively on the default head: the
frontalis lifts every part of the brows by more than 10 mm (the default map); with the range
variant of the muscle map (:data:`jaxface.anatomy.muscle_map.RANGE_EDITS`, opt-in) the mouth
ring lies on the teeth behind the red lip and the red lip on the ring, so pursed lips move
the mouth corners toward the mid-line and forward and the lips themselves forward, the cheeks
hollow as the lips protrude, and the protrusion is smooth at rest. Units mm."""

import json
from importlib.resources import files

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface import facs
from jaxface.anatomy.muscle_map import RANGE_EDITS, load_muscle_map, skull_registry
from jaxface.anatomy.muscles import moved_skull_points, sample_targets
from jaxface.anatomy.rig import build_rig, synthesize
from jaxface.errors import RigError
from jaxface.head import generic_head
from jaxface.normals import vertex_normals


@pytest.fixture(scope="module")
def head():
    return generic_head()


@pytest.fixture(scope="module")
def range_rig(head):
    return build_rig(head, muscle_map=load_muscle_map(edits=RANGE_EDITS))


@pytest.fixture(scope="module")
def rest(range_rig):
    return np.asarray(synthesize(range_rig, range_rig.activations({})))


def _aus(rig, aus):
    a, jaw, puff = facs.aus_to_controls(aus, rig.muscle_names)
    return np.asarray(synthesize(rig, a, jaw, puff))


def _vertex(rest, head, label):
    return int(np.argmin(np.linalg.norm(rest - np.asarray(head.landmarks[label]), axis=1)))


@pytest.fixture(scope="module")
def pucker(range_rig, rest):
    a = range_rig.activations({"orbicularis_oris": 1.0})
    return np.asarray(synthesize(range_rig, a)) - rest


def test_pucker_moves_the_corners_medially_and_forward(head, rest, pucker):
    for label, medial in (("Left mouth corner", -1.0), ("Right mouth corner", 1.0)):
        d = pucker[_vertex(rest, head, label)]
        assert medial * d[0] >= 6.0, (label, d)  # toward the mid-line (x = 0)
        assert d[2] >= 6.0, (label, d)  # forward (+z)
    # symmetric: the two corners mirror each other
    dl = pucker[_vertex(rest, head, "Left mouth corner")]
    dr = pucker[_vertex(rest, head, "Right mouth corner")]
    np.testing.assert_allclose(dl * [-1, 1, 1], dr, atol=0.3)


def test_pucker_moves_the_lips_forward(head, rest, pucker):
    """The red lip is bound to the ring, so the protruding ring carries the lips off the
    teeth (ICT-FaceKit's ``mouthPucker``: 6-9 mm at the lip mid-line)."""
    for label in ("Upper lip outer middle", "Upper lip inner middle", "Lower lip inner middle"):
        d = pucker[_vertex(rest, head, label)]
        assert d[2] >= 3.0, (label, d)
        assert abs(d[0]) < 0.1, (label, d)  # on the mid-line, by symmetry


def _red_lip(rig, head):
    """Skin vertices of the red lip: between the mouth corners, from the outer middle of the
    upper lip to that of the lower, in front of the corners."""
    x = np.asarray(rig.info.skin.vertices)
    lm = {k: np.asarray(head.landmarks[k]) for k in head.landmarks.names}
    lc, rc = lm["Left mouth corner"], lm["Right mouth corner"]
    top, bottom = lm["Upper lip outer middle"][1], lm["Lower lip outer middle"][1]
    return np.flatnonzero(
        (x[:, 0] < lc[0] - 3)
        & (x[:, 0] > rc[0] + 3)
        & (x[:, 1] < top - 1)
        & (x[:, 1] > bottom + 1)
        & (x[:, 2] > lc[2])
    )


def test_the_red_lip_lies_on_the_orbicularis_oris(range_rig, head):
    """Nearly all of the red lip is bound to the ring (before the ring lay on the teeth, a
    third of the upper red lip missed it and fell back to the cranium above the teeth), and
    no skin vertex is bound to a tooth."""
    info = range_rig.info
    ring = info.registry.index("orbicularis_oris")
    lip = _red_lip(range_rig, head)
    assert lip.size > 80
    on_ring = np.mean(info.binding.surface[lip] == ring)
    assert on_ring > 0.85, on_ring
    for k in (0, 1):
        on = info.binding.surface == k
        assert np.all(info.binding.tri[on] < info.registry.bones[k].n_triangles)


def test_the_mouth_ring_lies_on_the_teeth_behind_the_lips(range_rig, head):
    """``project: "backward"``: the ring's inner samples lie straight behind their skin points
    (on the teeth), below the middle ring above the slit and above it below, not folded over
    the red lip as along the lips' normals (which turn into the mouth slit)."""
    pm = {p.name: p for p in range_rig.info.placed}["orbicularis_oris"]
    inner, middle = pm.fibres[0].positions, pm.fibres[1].positions
    skin_inner = pm.insertion_skin
    fwd = range_rig.info.frame.axes[2]
    back = skin_inner - inner
    along = back @ fwd
    assert np.all(along > 0)
    sideways = np.linalg.norm(back - np.outer(along, fwd), axis=1)
    assert np.all(sideways < 0.05 * along + 1e-6), sideways
    st = range_rig.info.frame.to_local(range_rig.info.frame.stomion)[1]
    yi = range_rig.info.frame.to_local(inner)[:, 1]
    ym = range_rig.info.frame.to_local(middle)[:, 1]
    up = ym > st
    assert np.all(yi[up] < ym[up]) and np.all(yi[~up] > ym[~up])
    reg = skull_registry(range_rig.info.skull)
    teeth = [k for k in (0, 1) if reg.meshes[k].n_triangles > reg.bones[k].n_triangles]
    assert teeth == [0, 1]
    f = pm.fibres[0]
    upper_teeth = (f.surface == 0) & (f.tri >= reg.bones[0].n_triangles)
    assert np.sum(upper_teeth[up]) >= 2  # the upper teeth carry the ring's middle
    assert not np.any(f.surface[~up] == 0)  # below the slit it rides the jaw, never the cranium


def test_the_cheeks_hollow_when_the_lips_protrude(range_rig, head, rest, pucker):
    n = np.asarray(vertex_normals(rest, np.asarray(range_rig.triangles)))
    for label, side in (("Left mouth corner", 1.0), ("Right mouth corner", -1.0)):
        c = np.asarray(head.landmarks[label])
        dx = side * (rest[:, 0] - c[0])
        # the lower lateral cheek: 12-35 mm lateral of the mouth corner, 20 mm below to 10 above
        region = (dx > 12) & (dx < 35) & (rest[:, 1] > c[1] - 20) & (rest[:, 1] < c[1] + 10)
        region &= rest[:, 2] > c[2] - 40
        assert region.sum() > 50
        inward = -np.sum(pucker[region] * n[region], axis=1)
        assert inward.mean() > 0.3, inward.mean()
        assert np.mean(inward > 0) > 0.75


def test_the_frontalis_lifts_the_brows_more_than_10_mm(default_rig, head):
    """AU1+2 at 1 on the default rig: every brow landmark rises at least 10 mm (real brow
    raises reach 13-15 mm), and the inner brows at least as far as the middle and outer."""
    rest = np.asarray(synthesize(default_rig, default_rig.activations({})))
    d = _aus(default_rig, {"AU1": 1.0, "AU2": 1.0}) - rest
    for side in ("left", "right"):
        rise = {
            part: d[_vertex(rest, head, f"{part} {side} eyebrow"), 1]
            for part in ("Inner", "Middle", "Outer")
        }
        assert min(rise.values()) >= 10.0, rise
        assert rise["Inner"] >= max(rise["Middle"], rise["Outer"]), rise


def test_protrusion_is_smooth_at_rest_and_moves_the_ring_forward(range_rig):
    """The ring's targets (:func:`~jaxface.anatomy.muscles.sample_targets` on the rest
    support): the forward term scales the radial contraction's length, which is linear in the
    activation, so the derivative at activation 0 is finite and matches a one-sided finite
    difference; at the ring's lateral ends (the mouth corners, where the radial motion is
    medial) the forward motion is ``protrusion`` times the in-plane motion."""
    system = range_rig.muscles
    spec = {s.name: s for s in range_rig.info.specs}["orbicularis_oris"]
    skull = moved_skull_points(system, jnp.eye(3), jnp.zeros(3))
    G = system.support(skull, system.rest)
    i = range_rig.index("orbicularis_oris")
    a0 = range_rig.activations({})
    e = jnp.zeros_like(a0).at[i].set(1.0)

    def f(t):
        return sample_targets(system, G, a0 + t * e)[1]

    jv = jax.jvp(f, (jnp.asarray(0.0),), (jnp.asarray(1.0),))[1]
    assert bool(jnp.all(jnp.isfinite(jv)))
    h = 1e-6
    fd = (f(jnp.asarray(h)) - f(jnp.asarray(0.0))) / h
    np.testing.assert_allclose(np.asarray(fd), np.asarray(jv), atol=1e-5 * float(jnp.abs(jv).max()))
    ids = np.asarray(sample_targets(system, G, a0)[0])
    d = np.asarray(f(jnp.asarray(1.0)) - f(jnp.asarray(0.0)))
    k = list(np.asarray(system.sph_ctrl)).index(i)
    ring = np.asarray(system.sph_bottom)[k, 0]  # the inner ring's particles
    row = {int(p): j for j, p in enumerate(ids)}
    dr = d[[row[int(p)] for p in ring]]
    ends = np.argsort(np.abs(np.asarray(system.rest)[ring, 0]))[-2:]  # the lateral ends
    for j in ends:
        ratio = dr[j, 2] / np.linalg.norm(dr[j, :2])
        assert 0.8 * spec.protrusion < ratio < 1.25 * spec.protrusion, (j, dr[j])


def _write_map(tmp_path, edit):
    m = json.loads((files("jaxface") / "data" / "muscle_map.json").read_text())
    for x in m["muscles"]:
        if x["name"] in edit:
            x.update(edit[x["name"]])
    p = tmp_path / "map.json"
    p.write_text(json.dumps(m))
    return p


def test_muscle_map_checks_protrusion(tmp_path):
    specs = {s.name: s for s in load_muscle_map(edits=RANGE_EDITS)}
    assert specs["orbicularis_oris"].protrusion == 1.2
    assert specs["orbicularis_oris"].modiolus_drag == 1.0
    assert specs["orbicularis_oris"].project == "backward"
    default = {s.name: s for s in load_muscle_map()}
    ring = default["orbicularis_oris"]
    assert (ring.protrusion, ring.modiolus_drag, ring.project) == (0, 0, "normal")
    assert default["orbicularis_oculi_L"].project == "normal"
    with pytest.raises(RigError, match="sphincters only"):
        load_muscle_map(_write_map(tmp_path, {"zygomaticus_major": {"protrusion": 0.5}}))
    for bad in (-0.1, "1", 5.0, True):
        with pytest.raises(RigError, match="protrusion"):
            load_muscle_map(_write_map(tmp_path, {"orbicularis_oris": {"protrusion": bad}}))
        with pytest.raises(RigError, match="modiolus_drag"):
            load_muscle_map(_write_map(tmp_path, {"orbicularis_oris": {"modiolus_drag": bad}}))
    with pytest.raises(RigError, match="sphincters only"):
        load_muscle_map(_write_map(tmp_path, {"risorius": {"modiolus_drag": 1.0}}))
    with pytest.raises(RigError, match="not a muscle of the map"):
        load_muscle_map(edits={"orbicularis_orbis": {"protrusion": 1.0}})
    for bad in ("back", 1, None):
        with pytest.raises(RigError, match="project must be"):
            load_muscle_map(_write_map(tmp_path, {"orbicularis_oris": {"project": bad}}))
    with pytest.raises(RigError, match="project applies to sphincters only"):
        load_muscle_map(_write_map(tmp_path, {"risorius": {"project": "backward"}}))


def test_the_default_ring_lies_on_the_bones_and_no_skin_on_a_tooth(default_rig):
    """Only a ring projected ``"backward"`` lies on the teeth: the default map's muscles lie
    on the bare bones, as before the teeth were part of the skull's surfaces, and the skin
    binds to the bones, never through the lips onto a tooth."""
    info = default_rig.info
    for pm in info.placed:
        for f in pm.fibres:
            on_skull = f.surface <= 1
            bone = np.asarray([info.registry.bones[k].n_triangles for k in f.surface[on_skull]])
            assert np.all(f.tri[on_skull] < bone), pm.name
    for k in (0, 1):
        on = info.binding.surface == k
        assert np.all(info.binding.tri[on] < info.registry.bones[k].n_triangles)
