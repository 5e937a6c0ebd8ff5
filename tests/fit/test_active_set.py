"""The active set of the activation bounds (jaxface.fit.active_set)."""

import numpy as np
import pytest

from jaxface.errors import FitError
from jaxface.fit.active_set import ActiveSet, locked_controls, update_active_set
from jaxface.fit.params import activations_from_z


def test_active_set_holds_and_releases_bounds_by_the_gradient_sign():
    a = np.array([0.0005, 0.9995, 0.5, 0.0, 1.0, 0.0, 0.004])
    g = np.array([0.3, -0.2, 1.0, -0.5, -0.1, 0.2, 1e-6])
    free = np.array([1, 1, 1, 0, 0, 0, 1], float)
    zf = np.array([0, 0, 0, 0, 1, 0, 0], float)
    f2, z2, zs, n = update_active_set(
        a, g, free, zf, tol_g=1e-4, locked=[False] * 5 + [True, False]
    )
    # 0: pushed below 0 -> held at 0; 1: pushed above 1 -> held at 1; 2: interior stays free;
    # 3: held at 0 but the gradient points inside -> released; 4: held at 1, gradient pushes
    # further out -> stays; 5: locked at 0 whatever the gradient; 6: near 0 but inside the
    # gradient dead band (its optimum lies just above 0) -> stays free
    np.testing.assert_array_equal(f2, [0, 0, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(z2[[0, 1, 4, 5]], [0, 1, 1, 0])
    assert n == 3 and np.isfinite(zs[3]) and np.isnan(zs[[0, 1, 2, 4, 5, 6]]).all()
    assert 0.0 < float(activations_from_z(zs[3])) < 0.05
    # anti-cycling: a held activation marked `keep` is not released whatever its gradient
    f3, _, zs3, n3 = update_active_set(
        a,
        g,
        free,
        zf,
        tol_g=1e-4,
        locked=[False] * 5 + [True, False],
        keep=[False, False, False, True, False, False, False],
    )
    assert f3[3] == 0 and np.isnan(zs3[3]) and n3 == 2


def test_active_set_state_keeps_an_activation_released_then_held_again():
    """Anti-cycling in the per-run state: held at 0, released (restarting 0.02 inside), then
    pushed out again -> held, and from then on kept at 0 whatever its gradient."""
    locked = np.array([False, True])
    s = ActiveSet.start(locked)
    np.testing.assert_array_equal(s.free, [1.0, 0.0])
    z = np.array([0.0, 0.0])
    z, n = s.update([0.001, 0.0], [0.5, 0.0], z, locked=locked, tol_g=1e-4)  # held
    assert n == 1 and s.free[0] == 0 and z[0] == 0.0
    z, n = s.update([0.0, 0.0], [-0.5, 0.0], z, locked=locked, tol_g=1e-4)  # released
    assert n == 1 and s.free[0] == 1 and s.released[0]
    np.testing.assert_allclose(float(activations_from_z(z[0])), 0.02, rtol=1e-9)
    z, n = s.update([0.005, 0.0], [0.5, 0.0], z, locked=locked, tol_g=1e-4)  # held again
    assert n == 1 and s.cycled[0]
    z, n = s.update([0.0, 0.0], [-0.5, 0.0], z, locked=locked, tol_g=1e-4)  # kept
    assert n == 0 and s.free[0] == 0
    assert s.at_bounds(locked) == {0: 0.0} and s.n_held(locked) == 1
    np.testing.assert_array_equal(s.effective_z(np.array([0.3, 0.4])), [0.0, 0.0])


def test_locked_controls():
    names = ["a_L", "a_R", "b"]
    np.testing.assert_array_equal(locked_controls(names, (), None), [False] * 3)
    np.testing.assert_array_equal(locked_controls(names, (True, True, False), None), [0, 0, 1])
    np.testing.assert_array_equal(locked_controls(names, (), ("b",)), [1, 1, 0])
    with pytest.raises(FitError, match="unknown controls"):
        locked_controls(names, (), ("c",))
    with pytest.raises(FitError, match="did not sample"):
        locked_controls(names, (True, True, False), ("b",))
