"""The fit's quality checks (:mod:`jaxface.fit.quality`, issue 49) on the shared
Bosphorus-style data: a self-fit of the neutral (noise floor: the fit computes one itself,
and the neutral is also fitted as a scan), a cross-subject pair (bs901's
smile against bs900's neutral: identity), a mirrored scan (refused), a scan with 90 % of its
points removed (refused as unusable), and partial coverage. One subject build and one
batch of three quick fits for the whole module."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from jaxface.errors import FitError
from jaxface.fit import quality as Q

# one subject build and three fits: minutes on a loaded 2-core machine
pytestmark = pytest.mark.timeout(1800)

FAST = dict(
    n_points=600, outer_iterations=3, max_steps=20, extra_iterations=0, restart_iterations=0
)
STEMS = ("bs900_N_N_0", "bs900_E_HAPPY_0", "bs901_E_HAPPY_0")


def _load(root, stem):
    from jaxface.io import load_scan

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scan(root / f"{stem}.bnt")


def _thinned(scan, keep: float = 0.1, seed: int = 0):
    """The grid scan with a random ``1 - keep`` of its valid points removed."""
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(scan.valid.ravel())
    k = rng.random(len(idx)) < keep
    valid = np.zeros(scan.valid.size, bool)
    valid[idx[k]] = True
    return dataclasses.replace(scan, valid=valid.reshape(scan.valid.shape), points=scan.points[k])


def _mirrored(scan):
    """x -> -x of the points and the landmarks (labels kept): a mirror image."""
    flip = np.diag([-1.0, 1.0, 1.0])
    return dataclasses.replace(
        scan, points=scan.points @ flip, landmarks=scan.landmarks.transformed(flip)
    )


@pytest.fixture(scope="module")
def fitted():
    from jaxface.fit.options import FitOptions
    from jaxface.fit.pipeline import SubjectOptions, fit_expressions, prepare_subject
    from jaxface.testing import shared_path

    root = shared_path("data", "bosphorus_style")
    neutral = _load(root, "bs900_N_N_0")
    subject = prepare_subject(neutral, options=SubjectOptions(levels=2, pitch_knots=6))
    scans = [_load(root, s) for s in STEMS]
    fits = fit_expressions(
        subject,
        scans,
        options=FitOptions(**FAST),
        noise_floor=True,
        arkit=shared_path("data", "ict", "ict_face.npz"),
    )
    return root, subject, dict(zip(STEMS, fits))


def test_self_fit_is_within_noise(fitted):
    _, subject, fits = fitted
    r = fits["bs900_N_N_0"]
    q = r.quality
    print("self-fit", q.to_dict())
    # the floor is the self-fit's own readout, and the fitted neutral reproduces it
    assert q.noise_floor == subject.au_noise_floor
    np.testing.assert_allclose(
        [r.au_intensities[k] for k in q.noise_floor], list(q.noise_floor.values()), atol=0.02
    )
    assert set(q.aus_within_noise) == set(r.au_intensities)
    assert all(v == 0.0 for v in q.au_intensities_above_noise.values())
    assert any("no expression" in w for w in q.warnings)
    assert q.coverage > 0.8 and q.identity_mm == pytest.approx(0.0, abs=1e-9)


def test_same_subject_expression_passes(fitted):
    _, _, fits = fitted
    r = fits["bs900_E_HAPPY_0"]
    q = r.quality
    print("happy", q.to_dict(), r.strongest_aus(4, by="motion"))
    assert q.ok, q.warnings
    assert q.coverage >= Q.MIN_COVERAGE and q.identity_mm < Q.IDENTITY_MAX_MM
    # the smile's strongest AU stands above the noise floor and keeps its intensity
    top = r.strongest_aus(1, bilateral_only=True)[0][0]
    assert top not in q.aus_within_noise
    assert q.au_intensities_above_noise[top] == r.au_intensities[top]


def test_fit_reads_arkit_from_the_scan(fitted, tmp_path):
    """The fit's ARKit readout names the smile's recipe (ICT mouthSmile_L/R, cheekSquint_L/R)
    within the top (n + 2) = 6 of the 52, from the scan itself; the fitted skin's readout is
    beside it in the detail, and the JSON carries both."""
    from jaxface.interop.arkit import ARKIT_NAMES

    _, _, fits = fitted
    r = fits["bs900_E_HAPPY_0"]
    assert r.arkit is not None and set(r.arkit) == set(ARKIT_NAMES), r.arkit_detail
    assert all(0.0 <= v <= 1.0 for v in r.arkit.values())
    order = sorted(r.arkit, key=lambda k: -r.arkit[k])
    recipe = ("mouthSmileLeft", "mouthSmileRight", "cheekSquintLeft", "cheekSquintRight")
    ranks = {k: order.index(k) + 1 for k in recipe}
    print("arkit ranks", ranks, r.arkit_detail["fitted_skin"])
    assert max(ranks.values()) <= 6, ranks
    assert "eye holes" in r.arkit_detail["method"]
    skin = r.arkit_detail["fitted_skin"]["coefficients"]
    assert set(skin) == set(ARKIT_NAMES) and skin["mouthSmileLeft"] > 0.3
    doc = json.loads(r.write(tmp_path)["json"].read_text())
    assert doc["arkit"] == pytest.approx(r.arkit)
    assert doc["arkit_detail"]["fitted_skin"]["coefficients"] == pytest.approx(skin)


def test_cross_subject_pair_warned(fitted):
    _, _, fits = fitted
    q = fits["bs901_E_HAPPY_0"].quality
    print("cross", q.to_dict())
    assert q.identity_mm is not None and q.identity_mm > Q.IDENTITY_MAX_MM
    assert any("another person" in w for w in q.warnings)


def test_quality_in_json(fitted, tmp_path):
    _, _, fits = fitted
    files = fits["bs901_E_HAPPY_0"].write(tmp_path)
    doc = json.loads(files["json"].read_text())
    assert doc["quality"]["ok"] is False and doc["quality"]["warnings"]
    assert doc["quality"]["identity_max_mm"] == Q.IDENTITY_MAX_MM


def test_mirrored_scan_refused(fitted):
    from jaxface.fit.pipeline import fit_expressions

    root, subject, _ = fitted
    scan = _mirrored(_load(root, "bs900_E_HAPPY_0"))
    hn, hs = Q.handedness(subject.neutral.landmarks), Q.handedness(scan.landmarks)
    assert hn is not None and hs is not None and hn > 0 > hs
    with pytest.raises(FitError, match="mirror image"):
        fit_expressions(subject, [scan])


def test_thinned_scan_refused_as_unusable(fitted):
    from jaxface.fit.pipeline import fit_expressions

    root, subject, _ = fitted
    scan = _thinned(_load(root, "bs900_E_HAPPY_0"))
    with pytest.raises(FitError, match="covers only"):
        fit_expressions(subject, [scan])


def test_partial_coverage_measured(fitted):
    """Coverage of the smile's fitted skin against its whole scan, the scan's x < 0 half and
    a tenth of its triangles (isolated triangles: every closest point on a border)."""
    from jaxface.fit.metrics import SurfaceIndex

    root, subject, fits = fitted
    r = fits["bs900_E_HAPPY_0"]
    v, t = r.scan.mesh_arrays()[:2]
    fv = np.asarray(r.fitted.vertices)
    mask = subject.registration.face_mask
    full = Q.coverage(fv, mask, SurfaceIndex(v, t))
    half = Q.coverage(fv, mask, SurfaceIndex(v, t[v[t].mean(axis=1)[:, 0] < 0.0]))
    sparse_t = t[np.random.default_rng(0).random(len(t)) < 0.1]
    sparse = Q.coverage(fv, mask, SurfaceIndex(v, sparse_t))
    print("coverage full/half/tenth", full, half, sparse)
    assert full == pytest.approx(r.quality.coverage)
    assert 0.35 * full < half < 0.65 * full
    assert sparse < Q.MIN_COVERAGE


def test_identity_and_handedness_on_all_shared_landmarks(shared):
    """Every scan of a subject stays under the identity threshold against its neutral, every
    scan of the other subject above it; a mirror flips the handedness and keeps identity."""
    from jaxface.landmarks import read_lm3

    root = shared("data", "bosphorus_style")
    lm = {p.stem: read_lm3(p) for p in sorted(root.glob("bs90*_*.lm3"))}
    for subj in ("bs900", "bs901"):
        n = lm[f"{subj}_N_N_0"]
        for stem, other in lm.items():
            d = Q.identity_distance(n, other)
            assert d is not None
            assert (d < Q.IDENTITY_MAX_MM) == stem.startswith(subj), (subj, stem, d)
            assert Q.handedness(other) > 0
        m = n.transformed(np.diag([-1.0, 1.0, 1.0]))
        assert Q.handedness(m) < 0 and Q.identity_distance(n, m) == pytest.approx(0, abs=1e-9)
        with pytest.raises(FitError):
            Q.check_mirror(n, m)
