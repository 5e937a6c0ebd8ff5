"""The ARKit -> rig map (:mod:`jaxface.interop.inverse`) against an oracle: ARKit shapes made
of the rig's own unit responses must map back to the inputs that made them, with no misfit,
and drive the rig to those inputs."""

import json

import numpy as np
import pytest

from jaxface.errors import FitError
from jaxface.interop.arkit import ARKIT_NAMES, ArkitBasis
from jaxface.interop.inverse import JAW_UNITS, InverseMap, _unit_responses, fit_inverse_map

# ARKit shape -> {rig input: fraction}: the shape is that mix of the inputs' exact responses
RECIPES = {
    "jawOpen": {"jaw_pitch": 1.0},
    "mouthSmileLeft": {"zygomaticus_major_L": 0.6, "levator_anguli_oris_L": 0.3},
    "browInnerUp": {"frontalis_medial_L": 1.0, "frontalis_medial_R": 1.0},
    "cheekPuff": {"cheek_puff": 0.5},
}


@pytest.fixture(scope="module")
def rig_and_map(default_rig):
    rig = default_rig
    inputs, R = _unit_responses(rig)
    assert inputs == tuple(rig.muscle_names) + tuple(JAW_UNITS)
    D = np.zeros((len(ARKIT_NAMES), *R.shape[1:]))
    avail = np.zeros(len(ARKIT_NAMES), bool)
    for name, mix in RECIPES.items():
        k = ARKIT_NAMES.index(name)
        D[k] = sum(w * R[inputs.index(i)] for i, w in mix.items())
        avail[k] = True
    basis = ArkitBasis(D, avail, np.ones(len(R[0]), bool), "unit responses")
    return rig, fit_inverse_map(rig, basis, key="oracle")


def test_shapes_made_of_unit_responses_map_back(rig_and_map):
    rig, imap = rig_and_map
    for name, mix in RECIPES.items():
        k = ARKIT_NAMES.index(name)
        want = np.zeros(len(imap.inputs))
        for i, w in mix.items():
            want[imap.inputs.index(i)] = w
        np.testing.assert_allclose(imap.matrix[k], want, atol=2e-3, err_msg=name)
        assert imap.misfit_mm[k] < 0.01 * imap.shape_rms_mm[k], name
    # shapes without a source map to nothing
    assert not imap.matrix[ARKIT_NAMES.index("tongueOut")].any()


def test_controls_drive_the_rig_with_the_mix(rig_and_map):
    rig, imap = rig_and_map
    a, (pitch, yaw, prot), puff = imap.controls(
        {"mouthSmileLeft": 1.0, "jawOpen": 0.5, "cheekPuff": 1.0}, rig.muscle_names
    )
    names = list(rig.muscle_names)
    assert a[names.index("zygomaticus_major_L")] == pytest.approx(0.6, abs=2e-3)
    assert a[names.index("levator_anguli_oris_L")] == pytest.approx(0.3, abs=2e-3)
    assert pitch == pytest.approx(9.0, abs=0.05) and abs(yaw) < 0.05 and abs(prot) < 0.05
    assert puff == pytest.approx(0.5, abs=2e-3)


def test_map_round_trips_through_json(rig_and_map):
    _, imap = rig_and_map
    back = InverseMap.from_json(json.loads(json.dumps(imap.to_json())))
    assert back.inputs == imap.inputs and back.key == "oracle"
    np.testing.assert_array_equal(back.matrix, imap.matrix)
    bad = imap.to_json() | {"arkit": list(ARKIT_NAMES[:-1])}
    with pytest.raises(FitError, match="other ARKit names"):
        InverseMap.from_json(bad)
