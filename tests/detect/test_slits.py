"""The eye and mouth refinement (:mod:`jaxface.detect.slits`) on synthetic range grids with a
known slit: a smile's mouth valley broken into pieces is grown to its true corners, a steep
crease beside it is not joined, and one arc of an open mouth's rim places only the lip it
belongs to and reports the open mouth."""

import numpy as np
import pytest

from jaxface.detect.slits import refine_slits, scan_rim_vertices
from jaxface.fit.metrics import SurfaceIndex

LEFT = np.array([1.0, 0.0, 0.0])
UP = np.array([0.0, 1.0, 0.0])


def _grid(depth, keep=None, step=1.0, half=(50.0, 35.0)):
    """A range grid ``z = -depth(x, y)`` (mm) on ``|x| <= half[0]``, ``|y| <= half[1]``, its
    triangles dropped where ``keep(x, y)`` is False at any corner (a hole)."""
    xs = np.arange(-half[0], half[0] + 1e-9, step)
    ys = np.arange(-half[1], half[1] + 1e-9, step)
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), -depth(X.ravel(), Y.ravel())], 1)
    nx = len(xs)
    i = np.arange(len(ys) - 1)[:, None] * nx + np.arange(nx - 1)[None]
    i = i.ravel()
    F = np.concatenate([np.stack([i, i + 1, i + nx], 1), np.stack([i + 1, i + nx + 1, i + nx], 1)])
    if keep is not None:
        ok = keep(V[:, 0], V[:, 1])
        F = F[ok[F].all(1)]
    return SurfaceIndex(V, F)


def _smile_curve(x):
    return 0.012 * x**2  # the slit rises toward the corners: 12 mm at |x| = 32 mm


def _groove(x, y, breaks=True):
    """A 1.5 mm deep valley along the smile curve from x = -32 to 32, shallow (0.1 mm, below
    the refinement's 0.3 mm concavity) on 19.5 <= |x| <= 21.5 when ``breaks``."""
    d = 1.5 * np.exp(-(((y - _smile_curve(x)) / 1.0) ** 2))
    d = np.where(np.abs(x) <= 32.0, d, 0.0)
    if breaks:
        d = np.where((np.abs(x) >= 19.5) & (np.abs(x) <= 21.5), 0.1 * d, d)
    return d


def _mouth_guesses(y0=-2.0, half_width=24.0):
    return {
        "Left mouth corner": np.array([half_width, y0, 0.0]),
        "Right mouth corner": np.array([-half_width, y0, 0.0]),
        "Upper lip inner middle": np.array([0.0, y0 + 1.0, 0.0]),
        "Lower lip inner middle": np.array([0.0, y0 - 1.0, 0.0]),
    }


def test_a_broken_smile_valley_is_grown_to_its_corners():
    index = _grid(_groove)
    findings = {}
    out = refine_slits(index, _mouth_guesses(), LEFT, UP, scan_rim_vertices(index), findings)
    assert findings == {}  # a closed mouth
    for label, sign in (("Left mouth corner", 1.0), ("Right mouth corner", -1.0)):
        want = np.array([sign * 32.0, _smile_curve(32.0), 0.0])
        assert label in out, out.keys()
        np.testing.assert_allclose(out[label][:2], want[:2], atol=1.5)
    # the midpoints come from the central valley, at the curve's bottom
    assert abs(out["Upper lip inner middle"][1]) <= 1.0
    # without the breaks the same corners come out (the growth changes nothing there)
    whole = _grid(lambda x, y: _groove(x, y, breaks=False))
    out2 = refine_slits(whole, _mouth_guesses(), LEFT, UP, scan_rim_vertices(whole))
    np.testing.assert_allclose(out2["Left mouth corner"], out["Left mouth corner"], atol=1.0)


def test_a_steep_crease_past_the_slit_is_not_joined():
    """A nasolabial-like crease starts 4 mm beyond the valley's left end and runs steeply
    down: the corner stays at the valley's end."""

    def depth(x, y):
        crease = 1.5 * np.exp(-(((x - (36.0 - (y - 12.0) / 4.0)) / 1.0) ** 2))
        crease = np.where((y <= 11.0) & (y >= -15.0), crease, 0.0)
        return np.maximum(_groove(x, y), crease)

    index = _grid(depth)
    out = refine_slits(index, _mouth_guesses(), LEFT, UP, scan_rim_vertices(index))
    assert out["Left mouth corner"][0] == pytest.approx(32.0, abs=1.5)
    assert out["Left mouth corner"][1] == pytest.approx(_smile_curve(32.0), abs=1.5)


def test_one_arc_of_an_open_mouth_places_only_its_own_lip():
    """An open mouth (a hole from y = -30 to 0) whose lower rim lies outside the search box,
    with the transferred lower-lip midpoint drawn up next to the upper lip (as when the
    template closes over the mouth): the rim found is the upper lip's, so only the upper
    midpoint is placed."""

    def keep(x, y):
        return ~((np.abs(x) < 25.0) & (y < 0.0) & (y > -30.0))

    index = _grid(lambda x, y: np.zeros_like(x), keep=keep)
    g = _mouth_guesses(y0=-2.0, half_width=25.0)
    g["Upper lip inner middle"] = np.array([0.0, 0.5, 0.0])
    g["Lower lip inner middle"] = np.array([0.0, -4.0, 0.0])
    findings = {}
    out = refine_slits(index, g, LEFT, UP, scan_rim_vertices(index), findings)
    assert "Upper lip inner middle" in out
    assert abs(out["Upper lip inner middle"][1]) <= 1.0
    assert "Lower lip inner middle" not in out
    # the detector then leaves the jaw's labels out (detect.JAW_FOLLOWERS)
    assert "open" in findings["open_mouth"]
