"""The LTW backend as a face rig: same controls as the PBD rig, jaw, eyelids, gradients.

Built on the face region of the generic head (about 4.9k vertices) with a reduced number of
relaxation steps so that the module stays fast.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface.anatomy.jaw import JawPose
from jaxface.anatomy.muscle_map import load_muscle_map
from jaxface.errors import RigError
from jaxface.head import generic_head
from jaxface.ltw.rig import LTWRig, build_ltw_rig, synthesize_ltw


@pytest.fixture(scope="module")
def face():
    h = generic_head()
    keep = h.face_mask[h.mesh.triangles].all(axis=1)
    skin, _ = h.mesh.submesh(keep)
    return skin, h.landmarks


@pytest.fixture(scope="module")
def rig(face):
    skin, lm = face
    return build_ltw_rig(skin, lm, n_steps=150)


def nearest(rig, point):
    return int(np.argmin(np.linalg.norm(np.asarray(rig.rest) - np.asarray(point), axis=1)))


def test_controls_are_the_pbd_controls(rig):
    specs = load_muscle_map()
    assert rig.muscle_names == tuple(s.name for s in specs if s.active)
    counts = dict(zip(rig.muscle_names, rig.model.muscles.influence_counts()))
    kinds = {s.name: s.kind for s in specs}
    for name, k in counts.items():
        if kinds[name] in ("linear", "sheet", "sphincter"):
            assert k > 0, name  # every force muscle acts on some fascia nodes
        else:
            assert k == 0, name  # eyelids are kinematic
    assert int(rig.lid_nodes.shape[0]) > 0


def test_neutral_synthesis_is_the_rest_face(rig):
    x = synthesize_ltw(rig, jnp.zeros(rig.n_controls), JawPose())
    np.testing.assert_allclose(x, rig.rest, atol=1e-9)


def test_zygomaticus_major_raises_its_own_mouth_corner(rig):
    lm = rig.info.landmarks
    left, right = nearest(rig, lm["Left mouth corner"]), nearest(rig, lm["Right mouth corner"])
    a = rig.activations(zygomaticus_major_L=1.0)
    d = np.asarray(synthesize_ltw(rig, a) - rig.rest)
    assert d[left, 1] > 1.0 and d[left, 0] > 0.5  # up and toward the subject's left (+x)
    assert np.linalg.norm(d[right]) < 0.3 * np.linalg.norm(d[left])


def test_jaw_opening_and_eyelids(rig):
    lm = rig.info.landmarks
    chin, brow = nearest(rig, lm["Chin middle"]), nearest(rig, lm["Inner left eyebrow"])
    d = np.asarray(synthesize_ltw(rig, jnp.zeros(rig.n_controls), JawPose(12.0)) - rig.rest)
    assert d[chin, 1] < -5.0  # the chin drops with the mandible
    assert np.linalg.norm(d[brow]) < 0.5
    # closing the eyes moves the upper lids down; the lid nodes follow the PBD rig's rotation
    a = rig.activations(orbicularis_oculi_palpebral_L=1.0, orbicularis_oculi_palpebral_R=1.0)
    d = np.asarray(synthesize_ltw(rig, a) - rig.rest)
    V = rig.n_vertices
    lids = np.asarray(rig.lid_nodes)
    upper = lids[np.asarray(rig.lid_upper) & (lids < V)]
    assert d[upper, 1].min() < -2.0


def test_directional_derivatives_wrt_jaw_and_activations_match_finite_differences(rig):
    # forward mode (jax.jvp) through the full face rig; reverse-mode gradients of the LTW
    # integrator are checked against finite differences on the small patches in test_ltw.py,
    # where they are affordable (on the 4.9k-vertex face the reverse pass is too slow for CI)
    r = rig.with_iterations(30)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(r.n_vertices, 3)))

    def loss(a, pitch):
        return jnp.sum(w * synthesize_ltw(r, a, JawPose(pitch, 0.0, 0.0)))

    f = jax.jit(loss)
    a0 = r.activations(zygomaticus_major_L=0.5, frontalis_medial_R=0.3)
    p0 = jnp.asarray(5.0)
    k = r.index("zygomaticus_major_L")
    ea = jnp.zeros_like(a0).at[k].set(1.0)
    _, da = jax.jit(lambda a, p: jax.jvp(lambda t: loss(t, p), (a,), (ea,)))(a0, p0)
    _, dp = jax.jit(lambda a, p: jax.jvp(lambda t: loss(a, t), (p,), (jnp.ones_like(p),)))(a0, p0)
    # the biphasic law is only C0: among ~10^5 springs a few cross their threshold within any
    # finite-difference step, so the agreement is limited to ~1e-4 here
    h = 1e-6
    fd_a = (float(f(a0.at[k].add(h), p0)) - float(f(a0.at[k].add(-h), p0))) / (2 * h)
    fd_p = (float(f(a0, p0 + h)) - float(f(a0, p0 - h))) / (2 * h)
    assert float(da) == pytest.approx(fd_a, rel=5e-4)
    assert float(dp) == pytest.approx(fd_p, rel=5e-4)
    assert np.isfinite(float(da)) and abs(float(da)) > 0


def test_vmap_over_a_batch(rig):
    A = jnp.stack([rig.activations(), rig.activations(corrugator_L=1.0)])
    xs = jax.vmap(lambda a: synthesize_ltw(rig, a))(A)
    np.testing.assert_allclose(xs[1], synthesize_ltw(rig, A[1]), atol=1e-9)


def test_bad_inputs(rig, face):
    with pytest.raises(RigError, match="activations"):
        synthesize_ltw(rig, jnp.zeros(3))
    with pytest.raises(RigError, match="JawPose"):
        synthesize_ltw(rig, jnp.zeros(rig.n_controls), 12.0)
    with pytest.raises(RigError, match="unknown"):
        rig.activations(not_a_muscle=1.0)
    with pytest.raises(RigError, match="landmarks"):
        build_ltw_rig(face[0], None)


def test_build_rig_dispatches_to_the_ltw_backend(face):
    from jaxface.anatomy.rig import build_rig, synthesize

    r = build_rig(face[0], face[1], backend="ltw").with_iterations(20)
    assert isinstance(r, LTWRig) and r.backend == "ltw"
    # the backend-independent entry point runs the layered-tissue solver for an LTW rig
    a = r.activations(zygomaticus_major_L=1.0)
    np.testing.assert_allclose(synthesize(r, a), synthesize_ltw(r, a), atol=1e-12)
    assert float(jnp.abs(synthesize(r, a) - r.rest).max()) > 0.1
