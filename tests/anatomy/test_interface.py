"""The rig interface (jaxface.anatomy.interface): both backends are FaceRigs with the same
controls and a working ``synthesize``; backend options live in their own config objects, and
an option the chosen backend does not take is refused with a typed error instead of dropped.

Both rigs are built once, on the face region of the default head (about 4.9k vertices), with
the fewest sweeps / relaxation steps, and each synthesis compiles once."""

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface.anatomy.interface import FaceRig, RigConfig, configure, rig_backend
from jaxface.anatomy.jaw import PITCH_LIMITS_DEG, PROTRUSION_LIMITS_MM, JawPose
from jaxface.anatomy.muscles import SHELL_STIFFNESS
from jaxface.anatomy.rig import Rig, RigInfo, build_rig, synthesize
from jaxface.anatomy.rig_common import BuildInfo, RigBase
from jaxface.anatomy.rig_config import (
    FAT_VOLUME,
    FOOTPRINT_CLUSTER_MM,
    FOOTPRINT_MM,
    JAW_FOLLOW_MM,
    PBDRigConfig,
)
from jaxface.errors import RigError, RigOptionError
from jaxface.head import generic_head
from jaxface.ltw.rig import LTWInfo, LTWRig, LTWRigConfig, build_ltw_rig, synthesize_ltw


@pytest.fixture(scope="module")
def face():
    h = generic_head()
    keep = h.face_mask[h.mesh.triangles].all(axis=1)
    skin, _ = h.mesh.submesh(keep)
    return skin, h.landmarks


@pytest.fixture(scope="module")
def pbd_rig(face):
    # a config with 3 muscle sweeps, overridden by the keyword: the keyword wins
    cfg = PBDRigConfig(muscle_iterations=3, skin_iterations=2)
    return build_rig(*face, config=cfg, muscle_iterations=2)


@pytest.fixture(scope="module")
def ltw_rig(face):
    return build_rig(*face, backend="ltw", config=LTWRigConfig(n_steps=10))


def test_both_backends_are_face_rigs_with_the_same_controls(face, pbd_rig, ltw_rig):
    skin, _ = face
    assert isinstance(pbd_rig, Rig) and isinstance(ltw_rig, LTWRig)
    for rig, name in ((pbd_rig, "pbd"), (ltw_rig, "ltw")):
        assert isinstance(rig, FaceRig)
        assert rig.backend == name
        assert rig.n_controls == len(rig.muscle_names) == len(rig.muscle_aus)
        assert rig.n_vertices == skin.n_vertices
        assert rig.rest.shape == (skin.n_vertices, 3)
        np.testing.assert_array_equal(rig.triangles, skin.triangles)
        np.testing.assert_allclose(rig.rest, skin.vertices, atol=1e-9)
        assert rig.info.landmarks is face[1]
    assert pbd_rig.muscle_names == ltw_rig.muscle_names
    # what is not a rig is not taken for one
    assert not isinstance(skin, FaceRig)
    assert not isinstance(pbd_rig.info, FaceRig)


def test_both_backends_share_the_control_accessors_and_checks(pbd_rig, ltw_rig):
    names = pbd_rig.muscle_names
    for rig in (pbd_rig, ltw_rig):
        assert issubclass(type(rig), RigBase) and isinstance(rig.info, BuildInfo)
        # the activation vector, against one laid out by hand from muscle_names
        want = np.zeros(len(names))
        want[names.index("zygomaticus_major_L")] = 0.25  # the keyword wins over the dict
        want[names.index(names[-1])] = 1.0
        got = rig.activations({"zygomaticus_major_L": 0.5, names[-1]: 1}, zygomaticus_major_L=0.25)
        np.testing.assert_array_equal(got, want)
        assert [rig.index(n) for n in names] == list(range(len(names)))
        with pytest.raises(RigError, match="unknown muscle 'nope'.*zygomaticus_major_L"):
            rig.activations(nope=1.0)
        # the same input checks, with the same messages, on both backends
        with pytest.raises(RigError, match=rf"shape \({rig.n_controls},\) ordered as"):
            rig.synthesize(jnp.zeros(rig.n_controls + 1))
        with pytest.raises(RigError, match="jaw must be a JawPose, got float"):
            rig.synthesize(jnp.zeros(rig.n_controls), 4.0)


def test_both_backends_puff_each_cheek_on_its_own(pbd_rig, ltw_rig):
    """``cheek_puff=[left, right]``: ``[p, p]`` is the scalar ``p`` to the digit, ``[p, 0]``
    moves the left cheek (+x) as the bilateral puff does and leaves the right one, and a
    pressure of another shape is refused."""
    for rig in (pbd_rig, ltw_rig):
        a = jnp.zeros(rig.n_controls)

        def puff(*p):  # one compiled synthesis per pressure shape
            return np.asarray(rig.synthesize(a, None, jnp.array(p if len(p) > 1 else p[0])))

        x0, both, left = puff(0.0, 0.0), puff(0.6, 0.6), puff(0.6, 0.0)
        np.testing.assert_array_equal(puff(0.6), both)
        d_both = np.linalg.norm(both - x0, axis=1)
        d_left = np.linalg.norm(left - x0, axis=1)
        on_left = np.asarray(rig.rest)[:, 0] > 0
        assert d_both[on_left].max() > 1e-3 and d_both[~on_left].max() > 1e-3, rig.backend
        # the puffed cheek moves as in the bilateral puff, the other one barely moves
        assert d_left[on_left].max() > 0.9 * d_both[on_left].max(), rig.backend
        assert d_left[~on_left].max() < 0.1 * d_both[~on_left].max(), rig.backend
        with pytest.raises(RigError, match=r"\[left, right\]"):
            rig.synthesize(a, None, jnp.zeros(3))


def test_rig_field_layouts_and_build_records(pbd_rig, ltw_rig):
    # the shared base adds no field: each rig's pytree layout is its own (rigs cross jit/vmap)
    def layout(rig):
        return [(f.name, bool(f.metadata.get("static"))) for f in dataclasses.fields(rig)]

    tail = [("muscle_names", True), ("muscle_aus", True), ("info", True)]
    assert layout(pbd_rig) == [("jaw", False), ("muscles", False), ("skin", False)] + tail
    lids = ["lid_nodes", "lid_fall", "lid_upper", "lid_side", "lid_pivot", "lid_axis"]
    ltw_fields = ["model", "jaw", *lids, "lid_angles", "puff_field", "puff_left", "puff_force"]
    assert layout(ltw_rig) == [(n, False) for n in ltw_fields] + [("n_steps", True)] + tail
    # build records: compared by identity, so a copy with the same record keeps the jit cache
    # key and one with an equal but new record does not
    for rig, cls in ((pbd_rig, RigInfo), (ltw_rig, LTWInfo)):
        assert type(rig.info) is cls
        again = cls(**vars(rig.info))
        assert again != rig.info and rig.info == rig.info and hash(rig.info) == id(rig.info)
        same = dataclasses.replace(rig)
        other = dataclasses.replace(rig, info=again)
        assert jax.tree_util.tree_structure(same) == jax.tree_util.tree_structure(rig)
        assert jax.tree_util.tree_structure(other) != jax.tree_util.tree_structure(rig)


def test_config_and_keywords_reach_the_pbd_rig(pbd_rig):
    assert pbd_rig.muscles.iterations == 2  # the keyword over the config's 3
    assert pbd_rig.skin.iterations == 2  # the config's


def test_synthesize_method_is_the_backend_synthesis(pbd_rig, ltw_rig):
    for rig, direct in ((pbd_rig, synthesize), (ltw_rig, synthesize_ltw)):
        zero = jnp.zeros(rig.n_controls)
        a = rig.activations(zygomaticus_major_L=1.0)
        x = rig.synthesize(a, JawPose(0.0))
        np.testing.assert_array_equal(x, direct(rig, a, JawPose(0.0)))
        assert x.shape == (rig.n_vertices, 3) and bool(jnp.all(jnp.isfinite(x)))
        d = np.asarray(x - rig.rest)
        k = int(np.argmax(np.linalg.norm(d, axis=1)))
        # the left smile muscle moves the subject's left side (+x) of the face, upward
        assert rig.rest[k, 0] > 0 and d[k, 1] > 0.5, (rig.backend, k, d[k])
        # an opened jaw lowers the chin
        chin = int(np.argmin(np.linalg.norm(rig.rest - rig.info.landmarks["Chin middle"], axis=1)))
        xj = rig.synthesize(zero, JawPose(4.0))
        assert float(xj[chin, 1] - rig.rest[chin, 1]) < -0.5, rig.backend
        np.testing.assert_allclose(rig.synthesize(zero, JawPose(0.0)), rig.rest, atol=1e-6)


def test_ltw_refuses_the_options_it_would_drop(face):
    skin, lm = face
    with pytest.raises(RigOptionError, match="muscle_iterations") as e:
        build_rig(skin, lm, backend="ltw", muscle_iterations=4, footprint_mm=7.0)
    assert e.value.backend == "ltw"
    assert e.value.options == ("footprint_mm", "muscle_iterations")
    assert isinstance(e.value, RigError) and isinstance(e.value, ValueError)
    with pytest.raises(RigOptionError, match="upper_teeth"):
        build_rig(skin, lm, backend="ltw", upper_teeth=skin)
    with pytest.raises(RigOptionError, match="LTWRigConfig"):
        build_rig(skin, lm, backend="ltw", config=PBDRigConfig())
    with pytest.raises(RigOptionError, match="PBDRigConfig"):
        build_rig(skin, lm, config=LTWRigConfig())
    with pytest.raises(RigError, match="unknown backend"):
        build_rig(skin, lm, backend="fem")


def test_an_option_both_backends_have_reaches_the_ltw_config():
    ltw = rig_backend("ltw")
    cfg = configure(ltw, None, {"eyelid_threshold": 0.05, "muscle_iterations": None})
    assert cfg == LTWRigConfig(eyelid_threshold=0.05)
    base = LTWRigConfig(n_steps=7)
    assert configure(ltw, base, {}) is base
    assert configure(ltw, base, {"eyelid_threshold": 0.05}) == LTWRigConfig(
        n_steps=7, eyelid_threshold=0.05
    )


def test_configs_round_trip_their_defaults():
    # the PBD defaults are build_rig's keyword defaults before the configs existed
    assert PBDRigConfig().options() == {
        "upper_teeth": None,
        "lower_teeth": None,
        "muscle_iterations": 32,
        "skin_iterations": 8,
        "footprint_mm": FOOTPRINT_MM,
        "footprint_cluster_mm": FOOTPRINT_CLUSTER_MM,
        "influence_radius": 0.15,
        "eyelid_threshold": 0.04,
        "bending": False,
        "jaw_follow_mm": JAW_FOLLOW_MM,
        "jaw_membrane": False,
        "skin_chebyshev_rho": 0.0,
        "muscle_shell_stiffness": SHELL_STIFFNESS,
        "fat_volume": FAT_VOLUME,
        "jaw_pitch_limits_deg": PITCH_LIMITS_DEG,  # JawModel's default before the option
        "jaw_protrusion_limits_mm": PROTRUSION_LIMITS_MM,
    }
    assert FOOTPRINT_MM == (10.0, 10.0) and FOOTPRINT_CLUSTER_MM == 5.0
    assert JAW_FOLLOW_MM == (30.0, 100.0) and FAT_VOLUME == (0.5, 0.0)
    # the LTW defaults are build_ltw_rig's
    sig = inspect.signature(build_ltw_rig).parameters
    assert LTWRigConfig().options() == {k: sig[k].default for k in LTWRigConfig().options()}
    for cls in (PBDRigConfig, LTWRigConfig):
        cfg = cls()
        assert isinstance(cfg, RigConfig) and cls(**cfg.options()) == cfg
        assert rig_backend(cls.backend).config_type is cls
        assert configure(rig_backend(cls.backend), None, {}) == cfg
        with pytest.raises(dataclasses.FrozenInstanceError):
            cfg.eyelid_threshold = 0.1  # type: ignore[misc]
