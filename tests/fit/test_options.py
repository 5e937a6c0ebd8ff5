"""The fit's settings (jaxface.fit.options): one FitOptions made of option groups, with the
field names and defaults the CLI and the JSON contract rely on, and its checks."""

import dataclasses

import pytest

from jaxface.fit.options import (
    CorrespondenceOptions,
    FitOptions,
    OuterOptions,
    PriorOptions,
    ReadoutOptions,
    SamplingOptions,
    SolverOptions,
    should_restart,
)

#: every field of FitOptions with its default, as before the split into groups
DEFAULTS = {
    "n_points": 1000,
    "motion_fraction": 0.5,
    "motion_threshold_mm": 0.3,
    "outer_iterations": 6,
    "max_steps": 40,
    "rtol": 1e-3,
    "atol": 1e-4,
    "init_activation": 0.05,
    "jaw_starts": None,
    "rigid": True,
    "landmark_weight": 0.05,
    "detected_landmark_weight": 0.0,
    "sparsity_weight": 2e-4,
    "symmetry_weight": 1e-3,
    "symmetry_scale": 0.1,
    "rigid_weight": 1e-4,
    "jaw_weight": 1e-4,
    "max_distance_mm": (10.0, 4.0),
    "robust_floor_mm": (6.0, 1.5),
    "max_normal_angle_deg": 60.0,
    "exact_steps": 0,
    "gradient_correction": True,
    "release_gradient": 5e-5,
    "active_set_rounds": 3,
    "controls": None,
    "seed": 0,
    "restart_iterations": 2,
    "restart_when": "unconverged",
    "extra_iterations": 6,
    "converge_activation": 5e-3,
    "converge_jaw": 0.05,
    "converge_cost": 0.01,
    "converge_cost_mm2": 1e-4,
    "au_sparse_weight": 0.02,
    "au_min_motion_mm": 0.05,
}


def test_fit_options_are_the_union_of_the_groups_with_the_same_fields_and_defaults():
    fo = FitOptions()
    assert {f.name: getattr(fo, f.name) for f in dataclasses.fields(fo)} == DEFAULTS
    groups = (
        SamplingOptions,
        SolverOptions,
        PriorOptions,
        CorrespondenceOptions,
        OuterOptions,
        ReadoutOptions,
    )
    names = [f.name for g in groups for f in dataclasses.fields(g)]
    assert sorted(names) == sorted(DEFAULTS) and len(names) == len(set(names))
    assert all(isinstance(fo, g) for g in groups)
    with pytest.raises(dataclasses.FrozenInstanceError):
        fo.n_points = 3  # type: ignore[misc]
    assert dataclasses.replace(fo, symmetry_scale=0.2).symmetry_scale == 0.2


def test_anneal_is_geometric_between_the_first_and_last_iteration():
    fo = FitOptions(outer_iterations=3)
    assert fo.anneal((10.0, 4.0), 0) == 10.0 and fo.anneal((10.0, 4.0), 2) == pytest.approx(4.0)
    assert fo.anneal((10.0, 4.0), 1) == pytest.approx((10.0 * 4.0) ** 0.5)
    assert fo.anneal((10.0, 4.0), 9) == pytest.approx(4.0)  # clamped after the last
    assert fo.anneal((0.0, 2.0), 1) == pytest.approx(1.0)  # linear where not positive


def test_restart_trigger_restarts_saturated_fits_that_did_not_converge():
    """``restart_when``: "unconverged" restarts a run with controls at 1 only when its fit did
    not converge, "saturated" every run with controls at 1; no run without them restarts, and
    an unknown value is refused when the options are made."""
    table = {  # (saturated, converged): (unconverged, saturated)
        (True, False): (True, True),
        (True, True): (False, True),
        (False, False): (False, False),
        (False, True): (False, False),
    }
    for (sat, conv), (want_u, want_s) in table.items():
        assert should_restart("unconverged", sat, conv) is want_u, (sat, conv)
        assert should_restart("saturated", sat, conv) is want_s, (sat, conv)
    assert FitOptions().restart_when == "unconverged" and FitOptions().restart_iterations > 0
    with pytest.raises(ValueError, match="restart_when"):
        FitOptions(restart_when="always")


def test_motion_sampling_options_are_checked():
    assert FitOptions().motion_fraction == 0.5 and FitOptions().motion_threshold_mm == 0.3
    with pytest.raises(ValueError, match="motion_fraction"):
        FitOptions(motion_fraction=1.5)
    with pytest.raises(ValueError, match="motion_threshold_mm"):
        FitOptions(motion_threshold_mm=-1.0)
    with pytest.raises(ValueError, match="motion_threshold_mm"):
        FitOptions(motion_threshold_mm=float("nan"))


def test_sparse_readout_weight_is_checked():
    assert FitOptions().au_sparse_weight == 0.02
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="au_sparse_weight"):
            FitOptions(au_sparse_weight=bad)
        with pytest.raises(ValueError, match="au_min_motion_mm"):
            FitOptions(au_min_motion_mm=bad)
