"""Closest points on a polyline (:func:`jaxface.contours.closest_on_polyline`) against the
analytic answer on an L-shaped path."""

import numpy as np

from jaxface.contours import closest_on_polyline


def test_closest_points_and_tangents_on_an_l_shape():
    L = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0]])
    q = np.array([[3.0, 2.0, 1.0], [12.0, 6.0, 0.0], [-4.0, -1.0, 0.0], [11.0, -3.0, 0.0]])
    c, t = closest_on_polyline(q, L, tangents=True)
    np.testing.assert_allclose(c, [[3, 0, 0], [10, 6, 0], [0, 0, 0], [10, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(t[:3], [[1, 0, 0], [0, 1, 0], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0)
    np.testing.assert_array_equal(closest_on_polyline(q, L), c)
    one, t1 = closest_on_polyline(q, L[:1], tangents=True)
    np.testing.assert_array_equal(one, np.zeros((4, 3)))
    np.testing.assert_array_equal(t1, 0.0)
