"""PBD solver: every constraint kind alone, momentum, volume inflation, collisions, XPBD,
robustness, colouring, the sequential reference and input errors.

Independent references: analytic geometry (rest lengths, angles, areas, volumes, hull faces),
the plain sequential Gauss-Seidel of :mod:`jaxface.reference`, ``jax.grad`` of the dihedral
angle, the analytic equilibrium of a hanging XPBD chain.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from jaxface import pbd
from jaxface import reference as ref
from jaxface.coloring import balanced_coloring, greedy_coloring, padded_layout
from jaxface.errors import MeshError

TOL = 1e-4  # mm (mm^2, mm^3, rad) residual required by the issue


# ----------------------------------------------------------------------------------------
# small test geometry (mm)
# ----------------------------------------------------------------------------------------


def grid(nx=5, ny=5, h=2.0):
    """Planar grid in z = 0: (nx*ny, 3) vertices, triangles counter-clockwise seen from +z."""
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    v = np.stack([ii.ravel() * h, jj.ravel() * h, np.zeros(nx * ny)], 1)
    tris = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            a, b, c, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
            tris += [[a, b, c], [a, c, d]]
    return v, np.asarray(tris)


def grid_topology(v, t):
    from jaxface.mesh import TriMesh

    m = TriMesh(v, t)
    return m.edges, m.edge_pairs


def dodecahedron(radius=10.0):
    """Closed dodecahedron (pentagons split into triangles), outward oriented."""
    phi = (1 + 5**0.5) / 2
    pts = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    for a in (-1, 1):
        for b in (-1, 1):
            pts += [(0, a / phi, b * phi), (a / phi, b * phi, 0), (a * phi, 0, b / phi)]
    v = np.asarray(pts, float)
    v *= radius / np.linalg.norm(v[0])
    h = ConvexHull(v)
    t = h.simplices.copy()
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    flip = np.einsum("ij,ij->i", n, v[t].mean(1)) < 0
    t[flip] = t[flip][:, ::-1]
    return v, t


def hinge(theta=0.0):
    """Two unit triangles (a, b, c), (b, a, d) about the x axis with dihedral angle theta."""
    a, b = np.array([0.0, 0, 0]), np.array([2.0, 0, 0])
    c = np.array([1.0, 1.5, 0])
    d = np.array([1.0, -1.5 * np.cos(theta), 1.5 * np.sin(theta)])
    return np.stack([a, b, c, d])


def volume(v, t):
    return np.einsum("ij,ij->", np.cross(v[t[:, 0]], v[t[:, 1]]), v[t[:, 2]]) / 6.0


# ----------------------------------------------------------------------------------------
# each kind alone reaches satisfaction
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("scheme,iters", [("gs", 60), ("jacobi", 300)])
def test_distance_alone_satisfied_and_center_of_mass_kept(scheme, iters):
    v, t = dodecahedron()
    e, p = grid_topology(v, t)
    rng = np.random.default_rng(0)
    x0 = v + rng.normal(size=v.shape) * 0.3
    S = pbd.build_system({"d": pbd.distance_constraints(np.concatenate([e, p[:, 2:]]), v)}, len(v))
    x = pbd.relax(S, jnp.asarray(x0), iterations=iters, scheme=scheme)
    assert float(S.max_violation(x)["d"]) < TOL
    # rest lengths measured independently
    d = np.concatenate([e, p[:, 2:]])
    L = np.linalg.norm(np.asarray(x)[d[:, 0]] - np.asarray(x)[d[:, 1]], axis=1)
    np.testing.assert_allclose(L, np.linalg.norm(v[d[:, 0]] - v[d[:, 1]], axis=1), atol=TOL)
    if scheme == "gs":  # equal masses, internal constraints: linear momentum (centroid) kept
        np.testing.assert_allclose(np.asarray(x).mean(0), x0.mean(0), atol=1e-12)


def test_bending_alone_reaches_rest_angle():
    rest = 0.7
    S = pbd.build_system({"b": pbd.bending_constraints([[0, 1, 2, 3]], rest=[rest])}, 4)
    for start in (0.0, -2.5, 3.0):  # flat, strongly bent the other way, nearly folded
        x = pbd.relax(S, jnp.asarray(hinge(start)), iterations=60)
        got = float(pbd.dihedral_angle(*x))
        assert abs(got - rest) < TOL, (start, got)


def _check_hinge_inert_then_active(x, y, rest, active_angle):
    """The hinge ``[0, 1, 2, 3]`` at float32 positions ``x`` is inert (C = 0; the projection's
    reverse pass finite and equal to that of the identity, d sum(x^2) / dx = 2 x); at ``y``
    it is active (|C| > ``active_angle`` rad) with a finite reverse pass."""
    S = pbd.build_system({"b": pbd.bending_constraints([[0, 1, 2, 3]], rest=[rest])}, 4)
    c = lambda p: float(  # noqa: E731
        pbd.bending_constraints([[0, 1, 2, 3]], rest=[rest]).terms(
            [jnp.asarray(p[k][:, None]) for k in range(4)]
        )[0][0]
    )
    f = lambda p: jnp.sum(pbd.project(S, p, iterations=2) ** 2)  # noqa: E731
    assert c(x) == 0.0
    g = np.asarray(jax.grad(f)(jnp.asarray(x)))
    assert g.dtype == np.float32 and np.all(np.isfinite(g))
    np.testing.assert_allclose(g, 2 * x, rtol=1e-6, atol=1e-6)
    assert abs(c(y)) > active_angle
    g1 = np.asarray(jax.grad(f)(jnp.asarray(y)))
    assert np.all(np.isfinite(g1)) and not np.allclose(g1, 2 * y)


def test_a_collapsed_hinge_is_inert_and_its_reverse_pass_stays_finite_in_float32():
    """A hinge whose shared edge has collapsed to 4e-7 mm between 5 mm wings (seen in the
    orbicularis oris of the default head, where two ring particles sit on one surface point)
    is degenerate at float32 precision: its constraint must be inert, and the reverse pass of
    its projection finite (with the old absolute eps^2 threshold it was active, folded at
    2.9 rad against a rest of 0, and its squared gradients of ~2e7 / mm overflowed into NaN).
    The same wings about a 1 mm edge: an active constraint with a finite reverse pass."""
    x = np.array(
        [
            [-2.7e-7, -40.896, 103.086],
            [1.7e-7, -40.896, 103.086],
            [-4.945, -40.389, 102.477],
            [6.821, -40.298, 101.865],
        ],
        np.float32,
    )
    y = x.copy()
    y[0, 0], y[1, 0] = -0.5, 0.5
    _check_hinge_inert_then_active(x, y, 0.0, 1.0)


def test_a_hinge_with_a_collapsed_wing_is_inert_and_its_reverse_pass_stays_finite_in_float32():
    """A wing collapsed onto the edge's end (1e-7 mm from it, beside a 5 mm edge: two
    particles placed on one surface point, as four pairs are in the default head's orbicularis
    oris and depressor labii inferioris) has no dihedral angle at float32 precision: its normal points
    wherever the rounding does. The hinge must be inert, and the reverse pass of its projection
    finite. Judged by the edge and the normals alone it was active, and the default head's
    float32 reverse pass through the rig at rest came out NaN once the modiolus moved to the
    mouth corner. The wing 1 mm out: active, finite."""
    x = np.array(
        [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [6e-8, -8e-8, 3e-8], [2.5, 3.0, 1.0]], np.float32
    )
    y = x.copy()
    y[2] = [0.3, -0.8, 0.5]
    _check_hinge_inert_then_active(x, y, 0.4, 0.1)


def test_a_hinge_degenerate_at_rest_gets_no_stiffness():
    """Built from rest positions, a hinge that is degenerate there (coincident edge ends, or
    a wing along the edge's line) has no rest angle and is kept inert (stiffness 0); the
    others keep the given stiffness."""
    v = hinge(0.7)
    v = np.vstack([v, v[0] + [1e-9, 0, 0], v[0] + [1.0, 0, 0]])  # 4: on a; 5: on the edge line
    rows = [[0, 1, 2, 3], [0, 4, 2, 3], [0, 1, 2, 5]]
    g = pbd.bending_constraints(rows, v, stiffness=0.6)
    np.testing.assert_array_equal(np.asarray(g.stiffness), [0.6, 0.0, 0.0])
    assert abs(float(g.rest[0])) == pytest.approx(0.7, abs=1e-12)


def test_dihedral_angle_and_bending_gradient_match_autodiff():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(8, 4, 3))
    # analytic value against the arccos formula of eq. 3.20 (unsigned)
    for q in P:
        n1 = np.cross(q[1] - q[0], q[2] - q[0])
        n2 = np.cross(q[0] - q[1], q[3] - q[1])
        cos = n1 @ n2 / np.linalg.norm(n1) / np.linalg.norm(n2)
        assert abs(abs(float(pbd.dihedral_angle(*q))) - np.arccos(cos)) < 1e-12
    g = pbd.bending_constraints(np.arange(4)[None].repeat(8, 0), rest=np.zeros(8))
    Pt = [jnp.asarray(P[:, k].T) for k in range(4)]
    _, grads, _ = g.terms(Pt)
    auto = jax.vmap(jax.grad(lambda q: pbd.dihedral_angle(*q)))(jnp.asarray(P))
    for k in range(4):
        np.testing.assert_allclose(np.asarray(grads[k]).T, np.asarray(auto[:, k]), atol=1e-10)


def test_area_alone_reaches_rest_area():
    v, t = grid(4, 4)
    rng = np.random.default_rng(2)
    rest = rng.uniform(1.0, 3.0, len(t))  # mm^2, rest area 2 mm^2 perturbed
    S = pbd.build_system({"a": pbd.area_constraints(t, rest=rest)}, len(v))
    x = pbd.relax(S, jnp.asarray(v + rng.normal(size=v.shape) * 0.1), iterations=300)
    xn = np.asarray(x)
    A = 0.5 * np.linalg.norm(np.cross(xn[t[:, 1]] - xn[t[:, 0]], xn[t[:, 2]] - xn[t[:, 0]]), axis=1)
    np.testing.assert_allclose(A, rest, atol=TOL)


def test_volume_inflates_dodecahedron_to_target():
    v, t = dodecahedron()
    V0 = volume(v, t)
    vol = pbd.volume_constraint(t, v)
    assert abs(float(vol.rest[0]) - V0) < 1e-9 * V0  # origin-independent for a closed mesh
    # the volume constraint alone, growing target (thesis fig. 3.7); centroid kept
    Sv = pbd.build_system({"volume": vol}, len(v))
    x = jnp.asarray(v)
    for target in (1.5 * V0, 2.0 * V0, 3.0 * V0):
        Sv = Sv.set("volume", rest=target)
        x = pbd.relax(Sv, x, iterations=10)
        assert abs(volume(np.asarray(x), t) - target) < TOL, target
    np.testing.assert_allclose(np.asarray(x).mean(0), v.mean(0), atol=1e-12)
    # with a compliant (XPBD) stretch network holding the shape, the hard volume still reaches
    # its target exactly (its multiplier converges to C = 0)
    e = grid_topology(v, t)[0]
    groups = {
        "stretch": pbd.distance_constraints(e, v, compliance=1e-4),
        "volume": pbd.volume_constraint(t, v, compliance=0.0),
    }
    S = pbd.build_system(groups, len(v))
    x = jnp.asarray(v)
    for target in (1.5 * V0, 2.0 * V0):
        S = S.set("volume", rest=target)
        x = pbd.relax(S, x, iterations=150)
        assert abs(volume(np.asarray(x), t) - target) < TOL, target
    # and the stretch network did resist: edges are longer, the shape stayed convex-ish
    assert float(S.max_violation(x)["stretch"]) > 0.1


def test_anchor_follows_moving_targets():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(6, 3))
    S = pbd.build_system({"a": pbd.anchor_constraints([1, 4], v[[1, 4]], stiffness=0.2)}, 6)
    for shift in (np.array([1.0, 0, 0]), np.array([0, -3.0, 2.0])):
        targets = v[[1, 4]] + shift
        S = S.set("a", target=targets)
        x = np.asarray(pbd.relax(S, jnp.asarray(v), iterations=80))
        np.testing.assert_allclose(x[[1, 4]], targets, atol=TOL)
        np.testing.assert_allclose(x[[0, 2, 3, 5]], v[[0, 2, 3, 5]], atol=0)
        # thesis eq. 3.23 form: dp = -k (p - t) per projection
        x1 = np.asarray(pbd.relax(S, jnp.asarray(v), iterations=1))
        np.testing.assert_allclose(x1[[1, 4]], v[[1, 4]] - 0.2 * (v[[1, 4]] - targets), atol=1e-12)


def test_particle_inside_convex_hull_ends_on_face_of_least_penetration():
    cube = np.array([[x, y, z] for x in (-5, 5) for y in (-5, 5) for z in (-5, 5)], float)
    N, d = pbd.hull_planes(cube)
    assert N.shape == (6, 3)
    pts = np.array(
        [
            [4.0, 0.5, -1.0],  # nearest face +x (1 mm deep)
            [0.2, -0.3, -4.5],  # nearest face -z
            [7.0, 0.0, 0.0],
        ]
    )  # outside: untouched
    S = pbd.build_system({"teeth": pbd.hull_constraints([0, 1, 2], N, d)}, 3)
    x = np.asarray(pbd.relax(S, jnp.asarray(pts), iterations=1))
    np.testing.assert_allclose(x[0], [5.0, 0.5, -1.0], atol=1e-12)
    np.testing.assert_allclose(x[1], [0.2, -0.3, -5.0], atol=1e-12)
    np.testing.assert_allclose(x[2], pts[2], atol=0)
    # the hull moves with the jaw: planes are a run-time input. Box 10 x 4 x 6 mm rotated by
    # 90 deg about z and lifted 1 mm: (1.5, 0.3, 1) is now 0.5 mm inside the +x face (it was
    # nearest the +y face before the motion)
    box = np.array([[x, y, z] for x in (-5, 5) for y in (-2, 2) for z in (-3, 3)], float)
    Nb, db = pbd.hull_planes(box)
    Sb = pbd.build_system({"teeth": pbd.hull_constraints([0], Nb, db)}, 1)
    q = jnp.asarray([[1.5, 0.3, 1.0]])
    np.testing.assert_allclose(
        np.asarray(pbd.relax(Sb, q, iterations=1)), [[1.5, 2.0, 1.0]], atol=1e-12
    )
    R = np.array([[0.0, -1.0, 0], [1.0, 0.0, 0], [0, 0, 1.0]])
    N2, d2 = pbd.transform_planes(Nb, db, R, np.array([0.0, 0.0, 1.0]))
    S2 = Sb.set("teeth", normals=N2, offsets=d2)
    x2 = np.asarray(pbd.relax(S2, q, iterations=1))
    np.testing.assert_allclose(x2, [[2.0, 0.3, 1.0]], atol=1e-12)
    assert float(S2.max_violation(x2)["teeth"]) < 1e-12


def test_halfspace_pushes_out_only_violating_particles():
    S = pbd.build_system({"floor": pbd.halfspace_constraints([0, 1], [0, 2.0, 0], [-1.0, -1.0])}, 2)
    x = np.asarray(pbd.relax(S, jnp.asarray([[0.3, -3.0, 1.0], [0.0, 2.0, 0.0]]), iterations=1))
    np.testing.assert_allclose(x, [[0.3, -1.0, 1.0], [0.0, 2.0, 0.0]], atol=1e-12)


# ----------------------------------------------------------------------------------------
# momentum (thesis sec. 3.2.1: the correction along grad C conserves linear and angular
# momentum for internal constraints and equal masses)
# ----------------------------------------------------------------------------------------


def _single(kind, x):
    if kind == "distance":
        return pbd.distance_constraints([[0, 1]], rest=[1.0])
    if kind == "bending":
        return pbd.bending_constraints([[0, 1, 2, 3]], rest=[0.4])
    if kind == "area":
        return pbd.area_constraints([[0, 1, 2]], rest=[0.2])
    v, t = dodecahedron(1.0)
    return pbd.volume_constraint(t, rest=2 * volume(v, t), origin=[0.3, -0.2, 0.1])


@pytest.mark.parametrize("kind", ["distance", "bending", "area", "volume"])
def test_single_projection_conserves_linear_and_angular_momentum(kind):
    rng = np.random.default_rng(4)
    if kind == "volume":
        x0 = dodecahedron(1.0)[0] + rng.normal(size=(20, 3)) * 0.05
    else:
        x0 = rng.normal(size=(4, 3))
    S = pbd.build_system({"c": _single(kind, x0)}, len(x0))
    dx = np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=1)) - x0
    assert np.abs(dx).max() > 1e-3  # something happened
    np.testing.assert_allclose(dx.sum(0), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(x0, dx).sum(0), 0.0, atol=1e-12)


def test_time_stepping_conserves_linear_momentum_and_rigid_damping():
    v, t = dodecahedron(5.0)
    g = pbd.skin_constraints(v, t)
    S = pbd.build_system(g, len(v))
    rng = np.random.default_rng(5)
    p = pbd.Particles(x=jnp.asarray(v), v=jnp.asarray(rng.normal(size=v.shape) * 50.0))
    P0 = np.asarray(p.v).sum(0)
    out = pbd.simulate(S, p, steps=10, iterations=5, damping=0.0)
    np.testing.assert_allclose(np.asarray(out.v).sum(0), P0, atol=1e-8)
    # Mueller's damping removes only the non-rigid part: momenta unchanged, energy down
    x, vel = jnp.asarray(v), jnp.asarray(rng.normal(size=v.shape))
    w = jnp.ones(len(v))
    vd = np.asarray(pbd._damp_rigid(x, vel, w, 0.2))
    np.testing.assert_allclose(vd.sum(0), np.asarray(vel).sum(0), atol=1e-12)
    L = lambda u: np.cross(v, u).sum(0)  # noqa: E731
    np.testing.assert_allclose(L(vd), L(np.asarray(vel)), atol=1e-10)
    assert (vd**2).sum() < (np.asarray(vel) ** 2).sum()


# ----------------------------------------------------------------------------------------
# XPBD: equilibrium independent of the iteration count
# ----------------------------------------------------------------------------------------


def _chain(n=4, compliance=None, stiffness=1.0):
    x = np.zeros((n + 1, 3))
    x[:, 1] = -np.arange(n + 1) * 10.0  # hanging along -y from particle 0 (kinematic)
    pairs = np.stack([np.arange(n), np.arange(1, n + 1)], 1)
    S = pbd.build_system(
        {"springs": pbd.distance_constraints(pairs, x, stiffness=stiffness, compliance=compliance)},
        np.r_[0.0, np.ones(n)],
    )
    return S, x


def test_xpbd_equilibrium_independent_of_iterations_and_matches_analytic():
    alpha, g = 2e-4, 9810.0  # s^2/g (mm / (g mm/s^2)), mm/s^2
    S, x = _chain(compliance=alpha)
    p = pbd.Particles.at_rest(jnp.asarray(x))
    res = {}
    for it in (20, 200):
        out = pbd.simulate(S, p, steps=400, iterations=it, gravity=jnp.array([0, -g, 0]))
        res[it] = np.asarray(out.x)
    np.testing.assert_allclose(res[20], res[200], atol=1e-6)
    # spring j carries the weight of the n - j particles below it: extension alpha * T_j
    ext = -np.diff(res[200][:, 1]) - 10.0
    np.testing.assert_allclose(ext, alpha * g * np.arange(4, 0, -1), rtol=1e-6)
    # plain PBD with k < 1: the sag depends on the iteration count (what XPBD fixes)
    Sk, _ = _chain(stiffness=0.01)
    sag = [
        np.asarray(pbd.simulate(Sk, p, steps=400, iterations=it, gravity=jnp.array([0, -g, 0])).x)[
            -1, 1
        ]
        for it in (20, 200)
    ]
    assert abs(sag[0] - sag[1]) > 0.01


# ----------------------------------------------------------------------------------------
# parallel schemes vs the sequential reference
# ----------------------------------------------------------------------------------------


def _mixed_system():
    v, t = dodecahedron(8.0)
    e, p = grid_topology(v, t)
    rng = np.random.default_rng(6)
    sel = np.array([0, 3, 7, 11])
    N, d = pbd.hull_planes(v * 0.45)
    groups = {
        "stretch": pbd.distance_constraints(e, v, stiffness=0.8),
        "cross": pbd.distance_constraints(p[:, 2:], v, compliance=1e-7),
        "bend": pbd.bending_constraints(p, v, stiffness=0.6),
        "area": pbd.area_constraints(t, v, stiffness=0.9, compliance=1e-6),
        "volume": pbd.volume_constraint(t, v, rest=1.2 * volume(v, t)),
        "anchors": pbd.anchor_constraints(
            sel, v[sel] + rng.normal(size=(4, 3)), stiffness=0.3, compliance=1e-8
        ),
        "hull": pbd.hull_constraints(np.arange(len(v)), N, d),
        "floor": pbd.halfspace_constraints(np.arange(len(v)), [0, 1, 0], -6.0),
    }
    w = rng.uniform(0.5, 2.0, len(v))
    w[5] = 0.0  # one kinematic particle
    x0 = v + rng.normal(size=v.shape) * 0.8
    x0[2] *= 0.2  # deep inside the hull
    return pbd.build_system(groups, w), x0


def test_coloured_gauss_seidel_is_the_sequential_sweep_in_colour_order():
    S, x0 = _mixed_system()
    xj = np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=4))
    xr = ref.solve(S, x0, iterations=4, order="color")
    np.testing.assert_allclose(xj, xr, atol=1e-10)
    # the user's order is a different (valid) sweep: results differ, so the test can fail
    assert np.abs(ref.solve(S, x0, iterations=4, order="user") - xr).max() > 1e-3
    # both time-step the same way
    vj = pbd.step(
        S,
        pbd.Particles.at_rest(jnp.asarray(x0)),
        iterations=3,
        gravity=jnp.array([0.0, -9810.0, 0.0]),
    )
    xs, vs = ref.step(
        S, x0, np.zeros_like(x0), iterations=3, gravity=[0, -9810.0, 0], order="color"
    )
    np.testing.assert_allclose(np.asarray(vj.x), xs, atol=1e-10)
    np.testing.assert_allclose(np.asarray(vj.v), vs, atol=1e-6)
    # constraint values: JAX kernels vs the scalar formulas of the reference
    for name in S.names:
        np.testing.assert_allclose(
            np.asarray(S[name].values(jnp.asarray(x0))),
            ref.constraint_values(S[name], x0),
            atol=1e-9,
        )


def test_schemes_and_reference_reach_the_same_equilibrium():
    """Compatible constraints (rest configuration moved rigidly, anchors on it): the unique
    equilibrium is the moved rest shape, whatever the order or the scheme."""
    v, t = grid(6, 6)
    v[:, 2] = 0.05 * (v[:, 0] - 5) ** 2  # a curved sheet
    e, p = grid_topology(v, t)
    th = 0.2
    R = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
    goal = v @ R.T + [1.0, 2.0, -0.5]
    sel = np.array([0, 5, 14, 21, 30, 35])
    groups = {
        "stretch": pbd.distance_constraints(np.concatenate([e, p[:, 2:]]), v),
        "bend": pbd.bending_constraints(p, v, stiffness=0.5),
        "area": pbd.area_constraints(t, v, stiffness=0.5),
        "anchors": pbd.anchor_constraints(sel, goal[sel]),
    }
    S = pbd.build_system(groups, len(v))
    rng = np.random.default_rng(7)
    x0 = goal + rng.normal(size=v.shape) * 0.3
    out = {
        "gs": np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=300)),
        "jacobi": np.asarray(pbd.relax(S, jnp.asarray(x0), iterations=3000, scheme="jacobi")),
        "reference": ref.solve(S, x0, iterations=300),
    }
    for name, x in out.items():
        assert np.abs(x - goal).max() < 1e-3, (name, np.abs(x - goal).max())


# ----------------------------------------------------------------------------------------
# robustness: no NaN in values or gradients
# ----------------------------------------------------------------------------------------


def _degenerate_system():
    x = np.array(
        [
            [0.0, 0, 0],
            [0.0, 0, 0],  # 0, 1 coincident (zero-length edge)
            [1.0, 0, 0],
            [2.0, 0, 0],  # 0-2-3 collinear: zero-area triangle
            [1.0, 1.0, 0],
            [1.0, -1.0, 0],  # flat hinge about 0-2 with 4 and 5
            [1.0, 1.0, 0],  # 6 == 4: hinge 0-2 folded flat onto itself (pi)
        ]
    )
    groups = {
        "d": pbd.distance_constraints([[0, 1], [0, 2], [2, 3]], rest=[1.0, 1.0, 1.0]),
        "a": pbd.area_constraints([[0, 2, 3], [0, 1, 4], [0, 2, 4]], rest=[0.5, 0.5, 0.5]),
        "b": pbd.bending_constraints(
            [[0, 2, 4, 5], [0, 2, 4, 6], [0, 1, 4, 5], [0, 2, 3, 4]], rest=[0.3, 0.3, 0.3, 0.3]
        ),
        "v": pbd.volume_constraint([[0, 1, 2], [0, 2, 4]], rest=1.0, origin=[0, 0, 0]),
        "an": pbd.anchor_constraints([1], [[0.0, 0, 0]], compliance=1e-6),
    }
    return pbd.build_system(groups, len(x)), x


@pytest.mark.parametrize("scheme", ["gs", "jacobi"])
def test_degenerate_geometry_gives_no_nan_in_values_or_gradients(scheme):
    S, x = _degenerate_system()
    xj = jnp.asarray(x)
    for name, r in S.residuals(xj).items():
        assert np.all(np.isfinite(np.asarray(r))), name
    out = pbd.relax(S, xj, iterations=5, scheme=scheme)
    assert np.all(np.isfinite(np.asarray(out)))

    def loss(x, rest, k):
        s = S.set("d", rest=rest).set("b", stiffness=k)
        return jnp.sum(pbd.relax(s, x, iterations=5, scheme=scheme) ** 2)

    grads = jax.grad(loss, argnums=(0, 1, 2))(xj, jnp.ones(3), jnp.full(4, 0.5))
    for gr in grads:
        assert np.all(np.isfinite(np.asarray(gr)))
    tang = jax.jvp(
        lambda x: pbd.relax(S, x, iterations=5, scheme=scheme), (xj,), (jnp.ones_like(xj),)
    )[1]
    assert np.all(np.isfinite(np.asarray(tang)))


def test_dihedral_angle_flat_and_folded_values_and_gradients():
    a = jnp.asarray(hinge(0.0))
    assert float(pbd.dihedral_angle(*a)) == 0.0
    folded = jnp.asarray(hinge(np.pi))
    assert abs(abs(float(pbd.dihedral_angle(*folded))) - np.pi) < 1e-12
    for q in (a, folded, jnp.zeros((4, 3)), jnp.asarray(hinge(0.3)).at[3].set(hinge(0.3)[0])):
        g = jax.grad(lambda q: pbd.dihedral_angle(*q))(q)
        assert np.all(np.isfinite(np.asarray(g)))


# ----------------------------------------------------------------------------------------
# colouring and errors
# ----------------------------------------------------------------------------------------


def test_balanced_coloring_is_valid_and_even():
    rng = np.random.default_rng(8)
    idx = rng.integers(0, 300, size=(2000, 3))
    idx = idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 1] != idx[:, 2]) & (idx[:, 0] != idx[:, 2])]
    first = greedy_coloring(idx, 300)
    col = balanced_coloring(idx, 300)
    assert col.max() == first.max()  # no extra colour
    for c in range(col.max() + 1):
        r = idx[col == c].ravel()
        assert len(np.unique(r)) == len(r)
    sizes = np.bincount(col)
    assert sizes.max() < np.bincount(first).max()
    assert sizes.max() <= -(-len(idx) // len(sizes)) + 2
    slot, K, Sz = padded_layout(col)
    assert K * Sz >= len(idx) and len(np.unique(slot)) == len(idx)


def test_bad_input_raises_typed_errors():
    with pytest.raises(MeshError, match="stiffness"):
        pbd.distance_constraints([[0, 1]], rest=[1.0], stiffness=1.5)
    with pytest.raises(MeshError, match="compliance"):
        pbd.distance_constraints([[0, 1]], rest=[1.0], compliance=-1.0)
    with pytest.raises(MeshError, match="particles >= N"):
        pbd.build_system({"d": pbd.distance_constraints([[0, 7]], rest=[1.0])}, 3)
    with pytest.raises(MeshError, match="inverse masses"):
        pbd.build_system({"d": pbd.distance_constraints([[0, 1]], rest=[1.0])}, [1.0, -1.0])
    S = pbd.build_system({"d": pbd.distance_constraints([[0, 1]], rest=[1.0])}, 2)
    with pytest.raises(MeshError, match="shape"):
        pbd.relax(S, jnp.zeros((3, 3)), iterations=1)
    with pytest.raises(MeshError, match="no constraint group named"):
        S.set("nope", rest=1.0)
    with pytest.raises(MeshError, match="settable"):
        S.set("d", target=1.0)
    with pytest.raises(MeshError, match="scheme"):
        pbd.relax(S, jnp.zeros((2, 3)), iterations=1, scheme="sor")
    with pytest.raises(MeshError, match="coplanar|degenerate"):
        pbd.hull_planes(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))
    with pytest.raises(MeshError, match="NaN"):
        pbd.anchor_constraints([0], [[np.nan, 0, 0]])


def test_float32_input_stays_float32_and_matches_float64():
    v, t = grid(4, 4)
    g = pbd.skin_constraints(v, t, volume=None)
    g["anchors"] = pbd.anchor_constraints([0, 15], v[[0, 15]] + 1.0, stiffness=0.5)
    S = pbd.build_system(g, len(v))
    x64 = pbd.relax(S, jnp.asarray(v), iterations=20)
    x32 = pbd.relax(S, jnp.asarray(v, jnp.float32), iterations=20)
    assert x32.dtype == jnp.float32 and x64.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(x32), np.asarray(x64), atol=1e-4)
