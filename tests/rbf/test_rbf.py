"""Tests of jaxface.rbf: exact interpolation, affine precision, gradients vs finite
differences, chunking, NumPy path, and every RBFError case."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxface import rbf
from jaxface.errors import JaxfaceError, RBFError

KERNELS = ("tps", "biharmonic", "multiquadric")


def _cloud(n=40, seed=0, scale=40.0):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * scale + np.array([0.0, 10.0, 80.0])
    dst = src + rng.normal(size=(n, 3)) * 3.0
    return src, dst


@pytest.mark.parametrize("kernel", KERNELS)
def test_exact_interpolation_at_centres(kernel):
    src, dst = _cloud()
    m = rbf.fit(src, dst, kernel)
    np.testing.assert_allclose(np.asarray(m(src)), dst, atol=1e-9)
    mn = rbf.fit_numpy(src, dst, kernel)
    np.testing.assert_allclose(mn.apply_np(src), dst, atol=1e-9)


@pytest.mark.parametrize("kernel", KERNELS)
def test_ridge_smooths_and_vanishes(kernel):
    src, dst = _cloud()
    res = []
    for reg in (1e-1, 1e-3, 1e-6):
        m = rbf.fit(src, dst, kernel, reg=reg)
        res.append(float(np.abs(np.asarray(m(src)) - dst).max()))
    assert res[0] > 1e-3  # ridge really relaxes interpolation
    assert res[0] > res[1] > res[2]
    assert res[2] < 1e-3


@pytest.mark.parametrize("kernel", KERNELS)
def test_affine_map_reproduced(kernel):
    rng = np.random.default_rng(1)
    src, _ = _cloud(30, seed=2)
    A = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
    t = np.array([5.0, -3.0, 12.0])
    dst = src @ A.T + t
    m = rbf.fit(src, dst, kernel)
    x = rng.normal(size=(500, 3)) * 80.0
    np.testing.assert_allclose(np.asarray(m(x)), x @ A.T + t, atol=1e-8)
    assert np.abs(np.asarray(m.weights)).max() < 1e-9
    M, tt = m.affine_part()
    np.testing.assert_allclose(np.asarray(M), A, atol=1e-10)
    np.testing.assert_allclose(np.asarray(tt), t, atol=1e-8)


def test_tps_matches_direct_unnormalised_formula():
    """Reference: the plain Erdoğdu (4.11-4.19) system in raw mm coordinates."""
    src, dst = _cloud(25, seed=3)
    n = len(src)
    d = np.linalg.norm(src[:, None] - src[None], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        K = np.where(d > 0, d**2 * np.log(d**2), 0.0)
    P = np.hstack([np.ones((n, 1)), src])
    L = np.block([[K, P], [P.T, np.zeros((4, 4))]])
    sol = np.linalg.solve(L, np.vstack([dst, np.zeros((4, 3))]))
    rng = np.random.default_rng(4)
    x = src.mean(0) + rng.normal(size=(200, 3)) * 50
    dx = np.linalg.norm(x[:, None] - src[None], axis=-1)
    ref = np.hstack([np.ones((200, 1)), x]) @ sol[n:] + (dx**2 * np.log(dx**2)) @ sol[:n]
    np.testing.assert_allclose(np.asarray(rbf.fit(src, dst, "tps")(x)), ref, atol=1e-7)


def test_multiquadric_radii_are_nearest_neighbour_distances():
    src, dst = _cloud(30, seed=5)
    m = rbf.fit(src, dst, "multiquadric")
    nn = cKDTree(src).query(src, k=2)[0][:, 1]
    np.testing.assert_allclose(np.sqrt(np.asarray(m.radii2)) * float(m.scale), nn, rtol=1e-10)
    # the Hardy function of eq. 3.29 in raw coordinates, directly
    n = len(src)
    R = np.sqrt(np.linalg.norm(src[:, None] - src[None], axis=-1) ** 2 + nn[None] ** 2)
    P = np.hstack([np.ones((n, 1)), src])
    L = np.block([[R, P], [P.T, np.zeros((4, 4))]])
    sol = np.linalg.solve(L, np.vstack([dst, np.zeros((4, 3))]))
    x = src[:7] + 3.0
    Rx = np.sqrt(np.linalg.norm(x[:, None] - src[None], axis=-1) ** 2 + nn[None] ** 2)
    ref = Rx @ sol[:n] + np.hstack([np.ones((7, 1)), x]) @ sol[n:]
    np.testing.assert_allclose(np.asarray(m(x)), ref, atol=1e-8)


@pytest.mark.parametrize("kernel", KERNELS)
def test_numpy_path_matches_jax(kernel):
    src, dst = _cloud(35, seed=6)
    x = np.random.default_rng(7).normal(size=(300, 3)) * 60
    a = np.asarray(rbf.fit(src, dst, kernel)(x))
    mn = rbf.fit_numpy(src, dst, kernel)
    np.testing.assert_allclose(mn.apply_np(x), a, atol=1e-8)
    np.testing.assert_allclose(np.asarray(mn(x)), a, atol=1e-8)  # JAX call on a NumPy morph


@pytest.mark.parametrize("kernel", KERNELS)
def test_numpy_path_in_parallel_blocks_matches_jax(kernel):
    # 40 centres x 40,000 points: above rbf._PARALLEL_MIN_ELEMENTS, evaluated in blocks on threads
    src, dst = _cloud(40, seed=8)
    x = np.random.default_rng(9).normal(size=(40_000, 3)) * 60
    assert x.shape[0] * 40 >= rbf._PARALLEL_MIN_ELEMENTS
    mn = rbf.fit_numpy(src, dst, kernel)
    ref = np.asarray(rbf.fit(src, dst, kernel)(x))
    np.testing.assert_allclose(mn.apply_np(x, chunk_size=1000), ref, atol=1e-8)
    np.testing.assert_allclose(mn.apply_np(x[:20]), ref[:20], atol=1e-8)  # one block, no threads


def _fd_jacobian(f, x, eps=1e-5):
    """Central finite differences of f: (k, 3) -> (m, 3), shape (m, 3, k, 3)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.asarray(f(x))
    J = np.zeros(out.shape + x.shape)
    for idx in np.ndindex(*x.shape):
        xp, xm = x.copy(), x.copy()
        xp[idx] += eps
        xm[idx] -= eps
        J[(...,) + idx] = (np.asarray(f(xp)) - np.asarray(f(xm))) / (2 * eps)
    return J


@pytest.mark.parametrize("kernel", KERNELS)
def test_gradients_match_finite_differences(kernel):
    """Reverse-mode Jacobians (JAX) w.r.t. points, src and dst vs central differences of the
    NumPy implementation; one evaluation point sits exactly on a centre (r = 0)."""
    src, dst = _cloud(12, seed=8, scale=20.0)
    rng = np.random.default_rng(9)
    pts = np.vstack([src[:1], src[1:4] + rng.normal(size=(3, 3)) * 5.0])
    t = rng.normal(size=src.shape)

    def f(p, s, d):
        return rbf.fit(s, d, kernel)(p)

    @jax.jit
    def derivs(p, s, d):
        jac = jax.jacrev(f, argnums=(0, 1, 2))(p, s, d)
        _, jvp = jax.jvp(lambda ss: f(p, ss, d), (s,), (t,))
        tied = jax.grad(lambda ss: jnp.sum(f(ss[:3], ss, d)))(s)  # points on the centres
        return jac, jvp, tied

    (jp, js, jd), jvp, tied = derivs(pts, src, dst)
    fd_p = _fd_jacobian(lambda p: rbf.fit_numpy(src, dst, kernel).apply_np(p), pts)
    fd_s = _fd_jacobian(lambda s: rbf.fit_numpy(s, dst, kernel).apply_np(pts), src)
    fd_d = _fd_jacobian(lambda d: rbf.fit_numpy(src, d, kernel).apply_np(pts), dst)
    for j, fd in ((jp, fd_p), (js, fd_s), (jd, fd_d)):
        assert np.all(np.isfinite(np.asarray(j)))
        np.testing.assert_allclose(np.asarray(j), fd, atol=2e-6 * (1 + np.abs(fd).max()))
    np.testing.assert_allclose(
        np.asarray(jvp), np.einsum("mikj,kj->mi", np.asarray(js), t), atol=1e-8
    )
    assert np.all(np.isfinite(np.asarray(tied)))


def test_chunked_equals_unchunked_and_jit():
    src, dst = _cloud(30, seed=11)
    x = np.random.default_rng(12).normal(size=(50_003, 3)) * 50
    m = rbf.fit(src, dst, "tps")
    full = np.asarray(m(x, chunk_size=10**9))
    chunked = np.asarray(m(x, chunk_size=997))  # odd size: last chunk is padded
    np.testing.assert_allclose(chunked, full, rtol=0, atol=1e-10)
    jitted = np.asarray(jax.jit(lambda mm, p: mm(p, chunk_size=4096))(m, x))
    np.testing.assert_allclose(jitted, full, atol=1e-10)
    # leading batch dimensions
    np.testing.assert_allclose(np.asarray(m(x[:60].reshape(3, 20, 3))).reshape(60, 3), full[:60])


def test_fit_under_jit_and_vmap():
    src, dst = _cloud(15, seed=13)
    x = src[:5] + 1.0
    f = jax.jit(lambda s, d: rbf.fit(s, d, "biharmonic")(x))
    np.testing.assert_allclose(
        np.asarray(f(src, dst)), np.asarray(rbf.fit(src, dst, "biharmonic")(x))
    )
    dsts = np.stack([dst, dst + 1.0])
    out = jax.vmap(lambda d: rbf.fit(src, d, "tps")(x))(jnp.asarray(dsts))
    np.testing.assert_allclose(np.asarray(out[1] - out[0]), np.ones((5, 3)), atol=1e-9)


def test_float32_follows_input():
    src, dst = _cloud(20, seed=14)
    m = rbf.fit(src.astype(np.float32), dst.astype(np.float32), "tps")
    y = m(src.astype(np.float32))
    assert y.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(y), dst, atol=2e-3)


def test_lstsq_solver_matches_solve():
    src, dst = _cloud(20, seed=15)
    a = np.asarray(rbf.fit(src, dst, "tps", solver="lstsq")(src + 1))
    b = np.asarray(rbf.fit(src, dst, "tps")(src + 1))
    np.testing.assert_allclose(a, b, atol=1e-6)


# ------------------------------------------------------------------------ errors
@pytest.mark.parametrize("fitter", [rbf.fit, rbf.fit_numpy])
def test_too_few_centres(fitter):
    src, dst = _cloud(3)
    with pytest.raises(RBFError, match="too few centres"):
        fitter(src, dst)


@pytest.mark.parametrize("fitter", [rbf.fit, rbf.fit_numpy])
def test_coplanar_and_collinear_centres(fitter):
    rng = np.random.default_rng(16)
    xy = rng.normal(size=(20, 2)) * 30
    src = np.c_[xy, np.full(20, 5.0)]
    # a tilted plane, tiny noise far below the tolerance, big offset from the origin
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    src = src @ R.T + 1000.0 + rng.normal(size=src.shape) * 1e-12
    with pytest.raises(RBFError, match="coplanar"):
        fitter(src, src + 1)
    line = np.outer(np.linspace(0, 50, 10), [1.0, 2.0, 3.0])
    with pytest.raises(RBFError, match="collinear"):
        fitter(line, line)
    # slightly off-plane (0.5 mm over a 60 mm cloud) is fine
    ok = src + np.outer(rng.normal(size=20), R[:, 2]) * 0.5
    fitter(ok, ok + 1)


@pytest.mark.parametrize("fitter", [rbf.fit, rbf.fit_numpy])
def test_duplicate_centres_named_and_merged(fitter):
    src, dst = _cloud(10, seed=17)
    src = np.vstack([src, src[3], src[7]])
    dst = np.vstack([dst, dst[3] + 2.0, dst[7] - 4.0])
    with pytest.raises(RBFError, match=r"\[3, 10\].*\[7, 11\]"):
        fitter(src, dst)
    m = fitter(src, dst, merge_duplicates=True)
    assert m.centres.shape == (10, 3)
    y = np.asarray(m(src[[3, 7]]))
    np.testing.assert_allclose(y, [dst[3] + 1.0, dst[7] - 2.0], atol=1e-9)


@pytest.mark.parametrize("fitter", [rbf.fit, rbf.fit_numpy])
def test_shape_nan_kernel_errors(fitter):
    src, dst = _cloud(10)
    with pytest.raises(RBFError, match="same number"):
        fitter(src, dst[:-1])
    with pytest.raises(RBFError, match=r"\(n, 3\)"):
        fitter(src[:, :2], dst[:, :2])
    bad = dst.copy()
    bad[4, 1] = np.nan
    with pytest.raises(RBFError, match=r"NaN/inf.*\[4\]"):
        fitter(src, bad)
    with pytest.raises(RBFError, match="unknown RBF kernel"):
        fitter(src, dst, kernel="gaussian")
    assert issubclass(RBFError, JaxfaceError) and issubclass(RBFError, ValueError)


def test_find_duplicates_groups():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0], [2, 2, 2.0]])
    groups = rbf.find_duplicates(p)
    assert sorted(g.tolist() for g in groups) == [[0, 2, 4], [1, 3]]


def test_warp_mesh():
    mesh_mod = pytest.importorskip("jaxface.mesh")
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0]])
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    mesh = mesh_mod.TriMesh(v, tris)
    src, dst = _cloud(12, seed=18)
    m = rbf.fit_numpy(src, dst)
    out = rbf.warp_mesh(m, mesh)
    np.testing.assert_allclose(out.vertices, m.apply_np(v))
    np.testing.assert_array_equal(out.triangles, tris)
