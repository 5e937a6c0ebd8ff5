"""Correspondences of scan points on the simulated skin (jaxface.fit.correspond): signed
point-to-plane distances, rejection, robust weights; the scan data the fit takes."""

import numpy as np
import pytest

from jaxface.errors import FitError
from jaxface.fit.correspond import ScanTargets, find_correspondences


def _plane(n=21, spacing=1.0):
    xs = np.arange(n) * spacing - (n - 1) * spacing / 2
    X, Y = np.meshgrid(xs, xs)
    v = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        ids[:-1, :-1].ravel(),
        ids[:-1, 1:].ravel(),
        ids[1:, 1:].ravel(),
        ids[1:, :-1].ravel(),
    )
    t = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, t


def test_correspondences_on_a_plane_signed_distance_rejection_and_weights():
    v, t = _plane()
    # face region: the central 10 x 10 mm (triangles whose vertices all lie inside)
    inside = (np.abs(v[:, 0]) <= 5) & (np.abs(v[:, 1]) <= 5)
    face_tri = inside[t].all(axis=1)
    local = np.arange(len(v))
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(-4, 4, 40), rng.uniform(-4, 4, 40), rng.uniform(0.1, 1.0, 40)])
    q = np.vstack(
        [
            q,
            [[0.0, 0.0, 30.0]],  # too far
            [[8.0, 0.0, 0.2]],  # beyond the face region's border
            [[1.0, 1.0, 2.5]],
        ]
    )  # an outlier for the robust weights
    valid = np.ones(len(q), bool)
    nrm = np.tile([0.0, 0.0, 1.0], (len(q), 1))
    c = find_correspondences(
        v, t, face_tri, local, q, nrm, valid, max_distance=5.0, robust_floor=0.5
    )
    np.testing.assert_allclose(c.distance[:40], -q[:40, 2], atol=1e-12)  # n . (S - q), n = +z
    assert c.weight[40] == 0 and c.weight[41] == 0
    assert c.weight[42] == 0  # |r| = 2.5 mm beyond the Tukey cut-off (MAD scale, floor 0.5)
    assert np.all(c.weight[:40] > 0)
    np.testing.assert_allclose(c.weight.sum(), 1.0)
    # the surface points reproduce the footprints of the queries
    pts = np.einsum("kc,kcd->kd", c.bary[:40], v[t[c.tri[:40]]])
    np.testing.assert_allclose(pts[:, :2], q[:40, :2], atol=1e-12)
    with pytest.raises(FitError, match="no scan point"):
        find_correspondences(
            v,
            t,
            face_tri,
            local,
            q[:40] + [0, 0, 50],
            nrm[:40],
            valid[:40],
            max_distance=5.0,
            robust_floor=0.5,
        )


def test_scan_targets_from_a_mapping_and_a_missing_key():
    d = {
        "points": np.zeros((4, 3)),
        "valid": np.ones(4, bool),
        "landmarks": np.zeros((2, 3)),
        "landmark_valid": np.ones(2, bool),
    }
    t = ScanTargets.of(d)
    assert t.points is d["points"] and t.normals is None and ScanTargets.of(t) is t
    del d["landmarks"]
    with pytest.raises(FitError, match="landmarks"):
        ScanTargets.of(d)
