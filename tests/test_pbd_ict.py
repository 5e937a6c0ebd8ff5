"""PBD on the ICT-FaceKit face skin (shared data): the parallel solver against the plain
sequential reference (thesis algorithm), with random anchors."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxface import pbd
from jaxface import reference as ref
from jaxface.mesh import TriMesh

pytestmark = pytest.mark.data

N_FACE = 9409  # face region = ICT vertices 0..9408


@pytest.fixture(scope="module")
def face(request):
    from jaxface.testing import shared_path

    d = np.load(shared_path("data", "ict", "ict_face.npz"))
    tri = d["triangles"][d["triangle_group"] == 0].astype(np.int64)
    tri = tri[(tri < N_FACE).all(1)]
    return TriMesh(d["neutral"][:N_FACE].astype(np.float64), tri)


def test_parallel_gauss_seidel_equals_sequential_reference_on_face(face):
    """Full face skin (thesis constraint set and stiffness, volume capped at a point behind
    the face) with 10% of the particles anchored (k = 0.2) to randomly displaced targets: the
    coloured parallel sweep is the sequential Gauss-Seidel sweep in colour order."""
    rng = np.random.default_rng(0)
    x = face.vertices
    groups = pbd.skin_constraints(face, origin=x.mean(0) - [0.0, 0.0, 60.0])
    sel = rng.choice(face.n_vertices, face.n_vertices // 10, replace=False)
    groups["anchors"] = pbd.anchor_constraints(
        sel, x[sel] + rng.normal(size=(len(sel), 3)), stiffness=0.2
    )
    S = pbd.build_system(groups, face.n_vertices)
    assert sum(S[n].size for n in ("stretch", "cross")) > 55_000
    xj = np.asarray(pbd.relax(S, jnp.asarray(x), iterations=2))
    xr = ref.solve(S, x, iterations=2, order="color")
    assert np.abs(xr - x).max() > 0.1  # the anchors did pull
    np.testing.assert_allclose(xj, xr, atol=1e-9)
    x32 = np.asarray(pbd.relax(S, jnp.asarray(x, jnp.float32), iterations=2))
    assert np.abs(x32 - xr).max() < 1e-3


def test_schemes_and_reference_reach_same_equilibrium_on_face_region(face):
    """A region around the mouth (about 300 particles, 3,000 constraints), stretch + cross +
    bending + area at k = 1, 30% of the particles anchored at random to the rest shape moved
    rigidly, start perturbed by 0.2 mm noise. The equilibrium is unique (the moved rest shape):
    coloured Gauss-Seidel, Jacobi and the sequential reference in the user's (thesis) order
    all reach it within 1e-3 mm."""
    x = face.vertices
    mouth = x[np.argmin(np.abs(x[:, 0]) + np.abs(x[:, 1] + 40.0))]
    keep = np.linalg.norm(x[face.triangles].mean(1) - mouth, axis=1) < 12.0
    m, _ = face.submesh(keep)
    assert 200 < m.n_vertices < 600
    th = np.radians(3.0)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    c = m.vertices.mean(0)
    goal = (m.vertices - c) @ R.T + c + [1.0, -0.5, 0.7]
    rng = np.random.default_rng(1)
    sel = rng.choice(m.n_vertices, int(0.3 * m.n_vertices), replace=False)
    groups = pbd.skin_constraints(m, stretch=1.0, bend=1.0, area=1.0, volume=None)
    groups["anchors"] = pbd.anchor_constraints(sel, goal[sel])
    S = pbd.build_system(groups, m.n_vertices)
    x0 = goal + rng.normal(size=goal.shape) * 0.2
    out = {
        "gs": np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=220)),
        "jacobi": np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=3200, scheme="jacobi")),
        "reference": ref.solve(S, x0, iterations=220, order="user"),
    }
    for name, xs in out.items():
        assert np.abs(xs - goal).max() < 1e-3, (name, np.abs(xs - goal).max())
    assert np.abs(out["gs"] - out["reference"]).max() < 1e-3
