"""Headless pictures: the z-buffer rasteriser against analytic answers, figures and heat maps."""

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402
from matplotlib.image import imread  # noqa: E402

from jaxface.render import (  # noqa: E402
    VIEWS,
    Layer,
    as_layers,
    camera,
    eye_colors,
    figure_views,
    head_layers,
    rasterize,
    save_views,
    vertex_normals,
)


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    return np.asarray(s.vertices) + np.array([10.0, -5.0, 20.0]), np.asarray(s.faces)


def test_sphere_silhouette_area_and_depth(sphere):
    """An orthographic sphere is a disk: area pi r^2 (in pixels) and nearest depth c.z + r."""
    V, F = sphere
    r = rasterize((V, F), "front", 300, 300, supersample=1)
    scale = r.camera.scale
    covered = (r.image[..., 3] > 0.5).sum()
    expected = np.pi * (50.0 * scale) ** 2
    assert abs(covered - expected) / expected < 0.02  # polygonal sphere, pixel edges
    # the centre pixel sees the front pole
    col, row, depth = r.project(np.array([[10.0, -5.0, 70.0]]))[0]
    assert abs(r.depth[int(row), int(col)] - 70.0) < 0.1
    assert np.isinf(r.depth[0, 0]) and r.depth[0, 0] < 0  # background
    np.testing.assert_allclose(r.image[0, 0, :3], 1.0)  # white background


def test_shading_follows_the_light(sphere):
    V, F = sphere
    r = rasterize((V, F), "front", 200, 200)
    lum = r.image[..., :3].mean(axis=2)
    inside = r.image[..., 3] > 0.99
    # lit from the camera, slightly from the upper left: the upper-left quadrant is brighter
    # than the lower-right one, and the rim is darker than the centre
    h, w = lum.shape
    ul = lum[: h // 2, : w // 2][inside[: h // 2, : w // 2]].mean()
    lr = lum[h // 2 :, w // 2 :][inside[h // 2 :, w // 2 :]].mean()
    assert ul > lr
    c = r.project(np.array([[10.0, -5.0, 70.0]]))[0]
    assert lum[int(c[1]), int(c[0])] > np.percentile(lum[inside], 20)


def test_zbuffer_occlusion_and_visibility(sphere):
    V, F = sphere
    small = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    near = np.asarray(small.vertices) + np.array([10.0, -5.0, 100.0])  # in front of the big one
    far = np.asarray(small.vertices) + np.array([10.0, -5.0, -100.0])  # hidden behind it
    layers = [
        Layer(V, F),
        Layer(near, small.faces, color=(1.0, 0.0, 0.0)),
        Layer(far, small.faces, color=(0.0, 0.0, 1.0)),
    ]
    r = rasterize(layers, "front", 200, 200, supersample=1)
    col, row, _ = r.project(np.array([[10.0, -5.0, 110.0]]))[0]
    px = r.image[int(row), int(col), :3]
    assert px[0] > 0.5 and px[2] < 0.2  # red sphere in front, blue one hidden
    assert not (r.image[..., 2] > 0.5 + r.image[..., 0]).any()
    # from the back the blue one is in front
    rb = rasterize(layers, "back", 200, 200, supersample=1)
    col, row, _ = rb.project(np.array([[10.0, -5.0, -110.0]]))[0]
    px = rb.image[int(row), int(col), :3]
    assert px[2] > 0.5 and px[0] < 0.2
    # visibility of points: the big sphere's front pole is visible, its back pole is not
    vis = r.visible(np.array([[10.0, -5.0, 70.0], [10.0, -5.0, -30.0], [10.0, -5.0, 110.0]]))
    assert vis.tolist() == [False, False, True]  # the front pole is behind the red sphere
    vis = rasterize((V, F), "front", 200, 200).visible(
        np.array([[10.0, -5.0, 70.0], [10.0, -5.0, -30.0]])
    )
    assert vis.tolist() == [True, False]


def test_camera_views_and_projection():
    pts = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]) * 50
    cam = camera("front", pts, 100, 100, margin=0.0)
    p = cam.project(np.array([[50.0, 0.0, 0.0], [0.0, 50.0, 0.0], [0.0, 0.0, 50.0]]))
    # +x to the right, +y up (rows grow downwards), depth = z
    assert p[0, 0] == pytest.approx(100.0) and p[1, 1] == pytest.approx(0.0)
    assert p[2, 2] == pytest.approx(50.0)
    side = camera("side", pts, 100, 100, margin=0.0)  # camera on the subject's left (+x)
    q = side.project(np.array([[50.0, 0.0, 0.0], [0.0, 0.0, 50.0]]))
    assert q[0, 2] == pytest.approx(50.0)  # +x is toward the camera
    assert q[1, 0] < 50.0  # the face (+z) looks to the left
    assert set(VIEWS) >= {"front", "side", "left", "right", "back", "top"}
    with pytest.raises(ValueError, match="unknown view"):
        camera("diagonal", pts)


def test_head_front_and_side_differ_and_are_not_empty():
    from jaxface.head import generic_head

    head = generic_head()
    layers = head_layers(head)
    assert [L.label for L in layers] == [
        "skin",
        "eye_left",
        "eye_right",
        "upper_teeth",
        "lower_teeth",
    ]
    front = rasterize(layers, "front", 160, 160)
    side = rasterize(layers, "side", 160, 160)
    for r in (front, side):
        cover = r.image[..., 3] > 0.5
        assert 0.2 < cover.mean() < 0.9
        assert np.abs(r.image[..., :3] - 1.0).max() > 0.3  # pixels differ from background
    assert np.abs(front.image - side.image).mean() > 0.05
    # the front view is (nearly) mirror symmetric, the side view is not
    sym_front = np.abs(front.image[..., 3] - front.image[:, ::-1, 3]).mean()
    sym_side = np.abs(side.image[..., 3] - side.image[:, ::-1, 3]).mean()
    assert sym_front < 0.02 < sym_side
    # the eyes show dark pupils in the front view
    for k in range(2):
        c = head.eye_centers[k] + [0.0, 0.0, 14.0]
        col, row, _ = front.project(c[None])[0]
        assert front.image[int(row), int(col), :3].mean() < 0.35


def test_heat_map_figure_has_a_colour_bar(tmp_path, sphere):
    V, F = sphere
    err = np.abs(V[:, 0] - 10.0) / 10.0  # a scalar field in mm
    fig = figure_views(
        (V, F),
        ("front", "side"),
        scalars=err,
        cmap="magma",
        colorbar_label="error (mm)",
        title="heat",
        panel_px=160,
    )
    assert len(fig.axes) == 3  # two panels + the colour bar
    cbar_ax = fig.axes[-1]
    assert cbar_ax.get_ylabel() == "error (mm)"
    lo, hi = cbar_ax.get_ylim()
    assert lo == pytest.approx(err.min()) and hi == pytest.approx(err.max())
    path = save_views(
        tmp_path / "heat.png",
        (V, F),
        ("front", "side"),
        scalars=err,
        colorbar_label="error (mm)",
        panel_px=160,
    )
    img = imread(path)
    assert img.shape[1] > 2 * 160
    # colour-mapped (not grey) pixels are present: the viridis default is far from grey
    rgb = img[..., :3]
    assert (rgb.max(axis=2) - rgb.min(axis=2) > 0.3).mean() > 0.05
    # without scalars: no colour bar
    fig2 = figure_views((V, F), ("front",), panel_px=120)
    assert len(fig2.axes) == 1


def test_landmarks_and_polylines_are_drawn(tmp_path, sphere):
    V, F = sphere
    import matplotlib.pyplot as plt

    from jaxface.render import draw

    fig, ax = plt.subplots()
    pts = {"front pole": [10.0, -5.0, 70.0], "back pole": [10.0, -5.0, -30.0]}
    line = np.array([[-30.0, -5.0, 60.0], [50.0, -5.0, 60.0]])
    draw(
        ax,
        (V, F),
        "front",
        width=120,
        height=120,
        landmarks=pts,
        labels=True,
        polylines=[line],
        polyline_colors="tab:green",
    )
    # one visible point (the back pole is hidden), one label
    offsets = ax.collections[0].get_offsets()
    assert len(offsets) == 1
    assert [t.get_text() for t in ax.texts] == ["front pole"]
    assert len(ax.lines) == 2  # hidden (dashed) and visible parts of the polyline
    plt.close(fig)


def test_inputs_and_helpers(sphere):
    V, F = sphere
    tm = trimesh.Trimesh(V, F, process=False)
    assert len(as_layers(tm)) == 1 and len(as_layers([(V, F), tm])) == 2
    with pytest.raises(TypeError):
        as_layers(42)
    with pytest.raises(ValueError):
        rasterize([], "front")
    with pytest.raises(ValueError, match="scalars"):
        Layer(V, F, scalars=np.zeros(3)).vertex_colors()
    n = vertex_normals(V, F)
    radial = (V - V.mean(axis=0)) / 50.0
    assert np.abs((n * radial).sum(axis=1) - 1.0).max() < 2e-3  # sphere normals are radial
    c = eye_colors(V, V.mean(axis=0))
    front = np.argmax(V[:, 2])
    back = np.argmin(V[:, 2])
    assert c[front].mean() < 0.1 and c[back].mean() > 0.8  # pupil vs sclera
    # a degenerate (zero-area) triangle is skipped, not a crash
    Vd = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    r = rasterize((Vd, np.array([[0, 1, 2], [0, 1, 3]])), "front", 40, 40)
    assert r.image[..., 3].max() > 0
