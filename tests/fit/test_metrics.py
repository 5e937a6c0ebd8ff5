"""Tests of jaxface.fit.metrics: exact closest points, distance statistics, the face split,
landmark errors and the issue-7 metric set, against hand-computed values and an
independent closest-point implementation (trimesh)."""

import math

import numpy as np
import pytest
import trimesh

from jaxface.errors import FitError, LandmarkError, MeshError
from jaxface.fit.metrics import (
    DistanceStats,
    FacePlane,
    SurfaceIndex,
    closest_on_triangles,
    fit_metrics,
    landmark_errors,
    point_to_surface,
)


def grid_plane(n=11, size=10.0, z=0.0):
    """Square grid mesh in the plane z (mm), counter-clockwise seen from +z."""
    xs = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(xs, xs, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return V, F


# ------------------------------------------------------------------------- closest points
def test_closest_on_triangles_matches_trimesh():
    rng = np.random.default_rng(0)
    n = 4000
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    # some degenerate-ish and sliver triangles
    c[:200] = a[:200] + 1e-9 * rng.normal(size=(200, 3))
    b[200:400] = a[200:400] + 50.0 * (b[200:400] - a[200:400])
    p = 2.0 * rng.normal(size=(n, 3))
    q, bary = closest_on_triangles(p, a, b, c)
    ref = trimesh.triangles.closest_point(np.stack([a, b, c], 1), p)
    np.testing.assert_allclose(
        np.linalg.norm(p - q, axis=1), np.linalg.norm(p - ref, axis=1), atol=1e-7
    )
    assert bary.min() >= 0.0
    np.testing.assert_allclose(bary.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(q, np.einsum("kj,kjd->kd", bary, np.stack([a, b, c], 1)), atol=1e-12)


def _brute_force(points, V, F):
    tris = V[F]
    best = np.full(len(points), np.inf)
    for k in range(len(F)):
        q = trimesh.triangles.closest_point(np.repeat(tris[k : k + 1], len(points), 0), points)
        best = np.minimum(best, np.linalg.norm(points - q, axis=1))
    return best


def test_surface_index_exact_against_brute_force():
    rng = np.random.default_rng(1)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    V = np.asarray(sphere.vertices) * [1.0, 1.5, 0.6]
    F = np.asarray(sphere.faces)
    # add a far, long sliver triangle (different radius bucket)
    V = np.vstack([V, [[-60, 0, 40], [60, 0, 40], [60, 1, 40]]])
    F = np.vstack([F, [[len(V) - 3, len(V) - 2, len(V) - 1]]])
    pts = rng.normal(size=(300, 3)) * 25.0
    idx = SurfaceIndex(V, F)
    cp = idx.query(pts)
    np.testing.assert_allclose(cp.distances, _brute_force(pts, V, F), atol=1e-9)
    # the reported point, triangle and barycentrics agree
    corners = V[F[cp.triangles]]
    np.testing.assert_allclose(np.einsum("kj,kjd->kd", cp.bary, corners), cp.points, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(cp.points - pts, axis=1), cp.distances, atol=1e-9)
    # capped search: exact below the cap, "farther than the cap" above it
    capped = idx.query(pts, max_distance=5.0)
    near = cp.distances <= 5.0
    np.testing.assert_allclose(capped.distances[near], cp.distances[near], atol=1e-12)
    assert np.all(capped.distances[~near] > 5.0)
    # point_to_surface helper
    np.testing.assert_allclose(point_to_surface(pts, (V, F)), cp.distances)


def test_surface_index_boundary_flags_and_normals():
    V, F = grid_plane(n=11, size=10.0)
    # cut a hole: drop the triangles around the centre cell
    cen = V[F].mean(1)
    keep = np.max(np.abs(cen[:, :2]), axis=1) > 1.5
    idx = SurfaceIndex(V, F, triangle_mask=keep)
    pts = np.array(
        [
            [3.2, -2.7, 0.4],  # above data
            [0.0, 0.0, 0.3],  # above the hole -> projects to the hole rim
            [7.0, 0.0, 0.0],  # beyond the outer border
            [-3.3, 3.1, -0.2],  # below data
        ]
    )
    cp = idx.query(pts)
    np.testing.assert_array_equal(cp.on_boundary, [False, True, True, False])
    np.testing.assert_allclose(cp.distances[[0, 3]], [0.4, 0.2], atol=1e-12)
    np.testing.assert_allclose(cp.normals[[0, 3]], [[0, 0, 1], [0, 0, 1]], atol=1e-12)
    assert np.all(np.isin(cp.triangles, np.flatnonzero(keep)))


def test_surface_index_rejects_bad_input():
    V, F = grid_plane(5)
    idx = SurfaceIndex(V, F)
    with pytest.raises(MeshError, match="NaN"):
        idx.query([[0.0, np.nan, 0.0]])
    with pytest.raises(MeshError, match=r"\(K, 3\)"):
        idx.query(np.zeros((3, 2)))
    with pytest.raises(MeshError, match="outside"):
        SurfaceIndex(V, F + 1000)
    Vn = V.copy()
    Vn[3] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        SurfaceIndex(Vn, F)


# ------------------------------------------------------------------------- statistics
def test_distance_stats_hand_computed():
    s = DistanceStats.from_distances([1.0, 2.0, 3.0, 4.0])
    assert s.n == 4
    assert s.mean == pytest.approx(2.5)
    assert s.median == pytest.approx(2.5)
    assert s.rms == pytest.approx(math.sqrt((1 + 4 + 9 + 16) / 4))
    assert s.p95 == pytest.approx(1.0 + 0.95 * 3.0)  # linear interpolation at rank 2.85
    assert s.max == 4.0
    e = DistanceStats.from_distances([])
    assert e.n == 0 and math.isnan(e.mean) and e.to_dict()["mean"] is None
    with pytest.raises(FitError, match="NaN"):
        DistanceStats.from_distances([1.0, np.nan])


def test_plane_metrics_hand_computed():
    V, F = grid_plane(n=21, size=20.0)
    heights = np.array([0.5, -1.0, 2.0, 0.25, -0.75])
    xy = np.array([[1.0, 2.0], [-3.0, 4.5], [0.2, -6.0], [5.5, 5.5], [-2.0, -2.0]])
    scan = np.column_stack([xy, heights])
    m = fit_metrics((V, F), scan)
    s = m.scan_to_fit["all"]
    d = np.abs(heights)
    assert s.n == 5
    assert s.mean == pytest.approx(d.mean())
    assert s.median == pytest.approx(np.median(d))
    assert s.rms == pytest.approx(np.sqrt(np.mean(d**2)))
    assert s.p95 == pytest.approx(np.percentile(d, 95))
    # face mask: only the half x > 0; points beyond its border (x < 0) are outside the face
    mask = V[:, 0] >= -1e-9
    m2 = fit_metrics((V, F), scan, face_mask=mask)
    assert m2.scan_to_fit["all"].n == 3
    assert m2.scan_to_fit["all"].mean == pytest.approx(np.abs(heights[[0, 2, 3]]).mean())
    # max_distance drops outliers
    m3 = fit_metrics((V, F), scan, max_distance=1.0)
    assert m3.scan_to_fit["all"].n == 4


def test_scan_points_on_skin_outside_the_face_region_do_not_count():
    # the face region (z = 0) and skin outside it folded 10 mm beneath (z = -10), as under the
    # chin of an opened jaw: a scan point on that skin lies 10 mm from the face region, inside
    # it rather than beyond its border, but it is no fitting error
    V, F = grid_plane(n=21, size=20.0)
    V2 = V + np.array([0.0, 0.0, -10.0])
    VV = np.vstack([V, V2])
    FF = np.vstack([F, F + len(V)])
    mask = np.arange(len(VV)) < len(V)
    scan = np.array([[1.0, 2.0, 0.5], [-3.0, 4.5, -1.0], [2.0, 1.0, -10.0], [0.0, 0.0, -9.5]])
    m = fit_metrics((VV, FF), scan, face_mask=mask)
    assert m.scan_to_fit["all"].n == 2
    assert m.scan_to_fit["all"].mean == pytest.approx(0.75)
    assert fit_metrics((VV, FF), scan).scan_to_fit["all"].n == 4  # no mask: every point


def test_sphere_truth_to_fit_hand_computed():
    R = 50.0
    sph = trimesh.creation.icosphere(subdivisions=3, radius=R)
    V, F = np.asarray(sph.vertices), np.asarray(sph.faces)
    rng = np.random.default_rng(3)
    ids = rng.choice(len(V), 200, replace=False)
    delta = rng.uniform(0.0, 2.0, size=200)
    # points outside the polyhedron along vertex directions: the vertex is the closest point
    pts = V[ids] * ((R + delta) / R)[:, None]
    m = fit_metrics((V, F), truth=pts)
    s = m.truth_to_fit["all"]
    assert s.mean == pytest.approx(delta.mean(), abs=1e-9)
    assert s.max == pytest.approx(delta.max(), abs=1e-9)
    assert s.rms == pytest.approx(np.sqrt(np.mean(delta**2)), abs=1e-9)
    # truth_mask selects a subset
    tm = np.zeros(200, bool)
    tm[:50] = True
    m2 = fit_metrics((V, F), truth=pts, truth_mask=tm)
    assert m2.truth_to_fit["all"].mean == pytest.approx(delta[:50].mean(), abs=1e-9)


# ------------------------------------------------------------------------- face split, landmarks
def _face_landmarks(shift=np.zeros(3)):
    lm = {
        "Outer left eye corner": [45.0, 34.0, 90.0],
        "Inner left eye corner": [17.0, 33.0, 95.0],
        "Inner right eye corner": [-17.0, 33.0, 95.0],
        "Outer right eye corner": [-45.0, 34.0, 90.0],
        "Nose tip": [0.0, 5.0, 130.0],
        "Left mouth corner": [25.0, -36.0, 105.0],
        "Right mouth corner": [-25.0, -36.0, 105.0],
        "Upper lip outer middle": [0.0, -25.0, 122.0],
        "Chin middle": [0.0, -64.0, 115.0],
    }
    return {k: np.asarray(v) + shift for k, v in lm.items()}


def test_face_plane_from_landmarks():
    lm = _face_landmarks()
    plane = FacePlane.from_landmarks(lm)
    # up = inner-eye midpoint - mouth-corner midpoint = (0, 69, -10), made orthogonal to the
    # forward direction (across x up); across is +x so up stays in the y-z plane
    up = np.array([0.0, 69.0, -10.0])
    fwd = np.cross([34.0, 0.0, 0.0], up)
    fwd /= np.linalg.norm(fwd)
    up = up - up @ fwd * fwd
    np.testing.assert_allclose(plane.normal, up / np.linalg.norm(up), atol=1e-12)
    np.testing.assert_allclose(plane.point, lm["Nose tip"])
    h = plane.height(np.array([lm["Nose tip"] + 3 * plane.normal, lm["Chin middle"]]))
    assert h[0] == pytest.approx(3.0)
    assert h[1] < 0
    assert plane.is_upper(
        np.array([lm["Inner left eye corner"], lm["Left mouth corner"]])
    ).tolist() == [True, False]
    with pytest.raises(LandmarkError, match="Nose tip"):
        FacePlane.from_landmarks({k: v for k, v in lm.items() if k != "Nose tip"})


def test_landmark_errors():
    a = _face_landmarks()
    b = _face_landmarks(shift=np.array([0.0, 0.0, 0.0]))
    b["Nose tip"] = b["Nose tip"] + [3.0, 4.0, 0.0]
    del b["Chin middle"]
    err = landmark_errors(a, b)
    assert "Chin middle" not in err
    assert err["Nose tip"] == pytest.approx(5.0)
    assert err["Left mouth corner"] == 0.0
    # spelling variants are matched through the canonical labels
    err2 = landmark_errors({"nose tip": a["Nose tip"]}, {"Nose Tip": b["Nose tip"]})
    assert err2 == {"Nose tip": pytest.approx(5.0)}
    with pytest.raises(LandmarkError, match="Chin middle"):
        landmark_errors(a, b, names=["Nose tip", "Chin middle"])


def test_fit_metrics_upper_lower_and_landmarks():
    V, F = grid_plane(n=41, size=200.0, z=0.0)
    lm = _face_landmarks()
    # project the landmarks' x, y onto the plane; face plane split by the nose tip level
    lm = {k: np.array([v[0], v[1], 0.0]) for k, v in lm.items()}
    pts = np.array([[0.0, 40.0, 1.0], [10.0, 20.0, 2.0], [0.0, -30.0, 0.5], [30.0, -60.0, 0.25]])
    fitted_lm = {k: v + [0.0, 0.0, 1.0] for k, v in lm.items()}
    m = fit_metrics((V, F), pts, fitted_landmarks=fitted_lm, scan_landmarks=lm)
    assert m.scan_to_fit["upper"].mean == pytest.approx(1.5)
    assert m.scan_to_fit["lower"].mean == pytest.approx(0.375)
    assert m.landmark_stats["all"].mean == pytest.approx(1.0)
    assert m.landmark_stats["upper"].n + m.landmark_stats["lower"].n == len(lm)
    d = m.to_dict()
    assert d["unit"] == "mm" and d["scan_to_fit"]["upper"]["n"] == 2
    with pytest.raises(FitError, match="face_mask"):
        fit_metrics((V, F), pts, face_mask=np.ones(3, bool))
