"""Checks at the rig's entry points (issue 49, :mod:`jaxface.validate`): ``build_rig`` on a
skin with NaN vertices, ``synthesize`` with NaN or out-of-range controls (concrete: a
:class:`RigError` before the compiled body runs; traced inside the caller's jit: a run-time
``equinox`` error), and the checked call equal to the unchecked one. One rig of the default
head for the module."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxface.anatomy.jaw import JawPose
from jaxface.errors import MeshError, RigError

# a rig build and several compilations: minutes on a loaded 2-core machine
pytestmark = pytest.mark.timeout(1800)


@pytest.fixture(scope="module")
def rig(default_rig):
    return default_rig


def test_build_rig_refuses_nan_skin():
    from jaxface.anatomy.rig import build_rig
    from jaxface.head import generic_head
    from jaxface.mesh import TriMesh

    head = generic_head()
    v = head.mesh.vertices.copy()
    v[[11, 500]] = np.nan
    with pytest.raises(MeshError, match="2 of .* vertices have NaN") as ei:
        build_rig(TriMesh(v, head.mesh.triangles, validate=False), head.landmarks)
    assert ei.value.problem == "nonfinite_vertices" and ei.value.elements[0] == 11


def _a(rig, **set_):
    a = np.zeros(rig.n_controls)
    for k, v in set_.items():
        a[rig.index(k)] = v
    return jnp.asarray(a)


@pytest.mark.parametrize(
    "case",
    ["nan activation", "inf activation", "above 1", "below 0", "nan pitch", "nan puff", "puff 3"],
)
def test_synthesize_refuses_bad_controls(rig, case):
    from jaxface.anatomy.rig import synthesize

    name = rig.muscle_names[0]
    a = _a(rig, **{name: 0.3})
    jaw, puff = JawPose(), 0.0
    if case == "nan activation":
        a = a.at[2].set(jnp.nan)
    elif case == "inf activation":
        a = a.at[2].set(jnp.inf)
    elif case == "above 1":
        a = a.at[0].set(5.0)
    elif case == "below 0":
        a = a.at[0].set(-1.0)
    elif case == "nan pitch":
        jaw = JawPose(float("nan"), 0.0, 0.0)
    elif case == "nan puff":
        puff = float("nan")
    elif case == "puff 3":
        puff = 3.0
    with pytest.raises(RigError) as ei:
        synthesize(rig, a, jaw, puff)
    msg = str(ei.value)
    if case in ("above 1", "below 0"):
        assert name in msg and "[0, 1]" in msg


def test_dict_activations_with_nan_refused(rig):
    from jaxface.anatomy.rig import synthesize

    a = rig.activations({rig.muscle_names[1]: float("nan")})
    with pytest.raises(RigError, match=rig.muscle_names[1]):
        synthesize(rig, a)


def test_traced_nan_raises_inside_jit(rig):
    """Traced controls inside a caller's ``eqx.filter_jit`` and ``jax.vmap``: a NaN row makes
    the compiled call raise an ``EquinoxRuntimeError`` with the message (under a plain
    ``jax.jit`` JAX wraps the same message in a ``JaxRuntimeError`` or ``ValueError``)."""
    from jaxface.anatomy.rig import synthesize

    f = eqx.filter_jit(jax.vmap(lambda a: synthesize(rig, a)))
    good = jnp.stack([_a(rig), _a(rig).at[0].set(0.5)])
    assert np.all(np.isfinite(np.asarray(f(good))))
    with pytest.raises(eqx.EquinoxRuntimeError, match="RigError"):
        jax.block_until_ready(f(good.at[1, 3].set(jnp.nan)))


def test_checked_equals_unchecked(rig):
    """The checks change no value (the same compiled body), in and out of jit."""
    from jaxface.anatomy.rig import synthesize

    a = _a(rig, **{rig.muscle_names[0]: 0.6, rig.muscle_names[4]: 0.2})
    jaw = JawPose(6.0, 1.0, 0.5)
    x = np.asarray(synthesize(rig, a, jaw, 0.2))
    y = np.asarray(synthesize.__wrapped__(rig, a, jaw, 0.2))
    np.testing.assert_array_equal(x, y)
    z = np.asarray(jax.jit(lambda q: synthesize(rig, q, jaw, 0.2))(a))
    np.testing.assert_allclose(z, x, atol=1e-9)
    # the range check allows rounding at the bounds
    synthesize(rig, a.at[0].set(1.0 + 1e-9), jaw)
