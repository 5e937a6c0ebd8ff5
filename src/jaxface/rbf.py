"""Radial-basis-function volume morphs: Hardy multiquadric and thin-plate splines.

A morph is a smooth map ``G: R^3 -> R^3`` (millimetres in, millimetres out) that sends each
source centre ``P_i`` onto its target ``Q_i`` (thesis sec. 3.4, eqs. 3.26-3.35; Erdoğdu 2010,
eqs. 4.11-4.19)::

    G(p) = sum_i w_i U_i(|p - P_i|) + A^T [1, p]        w_i in R^3, A in R^{4x3}

with the linear-precision side conditions ``sum_i w_i = 0`` and ``sum_i w_i P_i^T = 0`` that
make the affine part absorb every affine component of the correspondence. Fitting solves the
one ``(n+4) x (n+4)`` saddle-point system

    [[K + reg I, P], [P^T, 0]] [W; A] = [Q; 0].

Kernels (``r`` = distance to the centre):

* ``"multiquadric"``: Hardy, ``U_i(r) = sqrt(r^2 + r_i^2)`` with the stiffness radius ``r_i``
  the distance from ``P_i`` to its nearest other centre (eq. 3.30), times ``radius_scale``;
* ``"tps"``: ``U(r) = r^2 log r^2`` (the kernel Erdoğdu uses in 3D);
* ``"biharmonic"``: ``U(r) = r``, the fundamental solution of the biharmonic operator in 3D.

Every kernel is NaN-safe at ``r = 0`` in value and gradient (double ``where``).

Numerics: centres and evaluation points are mapped to a normalised frame (centred on the
centroid of the centres, divided by their RMS radius) before the kernel is applied; this makes
the system well scaled whatever the unit. The interpolant is the same function as in the raw
frame for all three kernels (for TPS the ``log`` of the scale adds a multiple of ``r^2``, which
the side conditions turn into an affine term). ``reg`` is measured in that normalised frame
(a kernel of a unit-radius cloud is O(1)), so it means the same for a nose and for a head.

:func:`fit` validates its inputs when they are concrete (too few centres, coplanar centres,
duplicated centres, shape mismatch, NaN/inf) and raises :class:`~jaxface.errors.RBFError`;
under ``jax.jit``/``jax.grad`` tracing the checks that need values are skipped. The returned
:class:`Morph` is an ``eqx.Module`` whose ``__call__`` is jit-able and differentiable with
respect to the evaluated points and (through :func:`fit`) the centres and their targets; it
evaluates in fixed-size chunks with ``lax.map`` so that a million points fit in memory.

NumPy-side helpers (:func:`fit_numpy`, :meth:`Morph.apply_np`, :func:`warp_points`,
:func:`warp_mesh`) run the same algebra with NumPy/SciPy, without tracing or compilation, for
build-time code (mesh fitting, motion cloning) that solves many differently-sized systems.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ._parallel import thread_map
from .errors import RBFError
from .mesh import TriMesh

__all__ = [
    "KERNELS",
    "Morph",
    "fit",
    "fit_numpy",
    "find_duplicates",
    "warp_points",
    "warp_mesh",
    "kernel_values",
]

KernelName = Literal["tps", "biharmonic", "multiquadric"]
KERNELS: tuple[str, ...] = ("tps", "biharmonic", "multiquadric")

# Sign of the ridge term per kernel. r^2 log r^2 is conditionally positive definite (order 2)
# while r and the multiquadric are conditionally *negative* definite (order 1): the ridge must
# push the kernel matrix away from singularity, so it is added with the kernel's sign (adding it
# with the wrong sign can make K + reg I singular for some reg and blow the morph up).
_RIDGE_SIGN = {"tps": 1.0, "biharmonic": -1.0, "multiquadric": -1.0}

# relative tolerances (fractions of the centre cloud's size)
_DUPLICATE_RTOL = 1e-9
_PLANAR_RTOL = 1e-6
# the largest (points x centres) block evaluated at once
_MAX_BLOCK_ELEMENTS = 1 << 21
_PARALLEL_MIN_ELEMENTS = 1 << 20  # Morph.apply_np: below this, threads cost more than they save


# --------------------------------------------------------------------------------------
# kernels (JAX), NaN-safe at r = 0 in value and gradient
# --------------------------------------------------------------------------------------
def kernel_values(kernel: str, d2, c2=None):
    """Kernel ``U`` as a function of the squared distance.

    Arguments:
        kernel: ``"tps"``, ``"biharmonic"`` or ``"multiquadric"``.
        d2: ``(..., n)`` squared distances to the centres (any unit; the caller's frame).
        c2: ``(n,)`` squared stiffness radii, multiquadric only (same unit as ``d2``).

    Returns:
        ``(..., n)`` kernel values; 0 (with zero gradient) where the argument of the root or
        the logarithm is 0.
    """
    if kernel == "tps":
        pos = d2 > 0
        safe = jnp.where(pos, d2, 1.0)
        return jnp.where(pos, safe * jnp.log(safe), 0.0)
    if kernel == "biharmonic":
        pos = d2 > 0
        safe = jnp.where(pos, d2, 1.0)
        return jnp.where(pos, jnp.sqrt(safe), 0.0)
    if kernel == "multiquadric":
        s = d2 + c2
        pos = s > 0
        safe = jnp.where(pos, s, 1.0)
        return jnp.where(pos, jnp.sqrt(safe), 0.0)
    raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")


def _kernel_np(kernel: str, d2: np.ndarray, c2: np.ndarray | None) -> np.ndarray:
    if kernel == "tps":
        return d2 * np.log(np.where(d2 > 0, d2, 1.0))
    if kernel == "biharmonic":
        return np.sqrt(np.maximum(d2, 0.0))
    if kernel == "multiquadric":
        return np.sqrt(np.maximum(d2 + c2, 0.0))
    raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")


def _sqdist(a, b):
    """(m, 3), (n, 3) -> (m, n) squared distances by differences (exact 0 at coincidence)."""
    diff = a[:, None, :] - b[None, :, :]
    return jnp.sum(diff * diff, axis=-1)


def _sqdist_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances by coordinate differences (exactly 0 at coincident points)."""
    d2 = np.zeros((a.shape[0], b.shape[0]))
    for k in range(3):
        diff = np.subtract.outer(a[:, k], b[:, k])
        diff *= diff
        d2 += diff
    return d2


# --------------------------------------------------------------------------------------
# the morph
# --------------------------------------------------------------------------------------
class Morph(eqx.Module):
    """A fitted RBF morph ``G: R^3 -> R^3`` (mm -> mm). Build it with :func:`fit`.

    Attributes:
        centres: ``(n, 3)`` source centres ``P_i``, mm (after duplicate merging).
        targets: ``(n, 3)`` their images ``Q_i``, mm.
        weights: ``(n, 3)`` kernel coefficients ``w_i`` (mm per kernel unit).
        affine: ``(4, 3)`` affine coefficients acting on ``[1, (p - shift) / scale]``.
        shift: ``(3,)`` centroid of the centres, mm.
        scale: ``()`` RMS radius of the centres about ``shift``, mm.
        radii2: ``(n,)`` squared stiffness radii in the normalised frame (multiquadric;
            zeros otherwise).
        kernel: kernel name (static).

    Arrays are JAX from :func:`fit`, NumPy from :func:`fit_numpy`.
    """

    centres: jax.Array | np.ndarray
    targets: jax.Array | np.ndarray
    weights: jax.Array | np.ndarray
    affine: jax.Array | np.ndarray
    shift: jax.Array | np.ndarray
    scale: jax.Array | np.ndarray
    radii2: jax.Array | np.ndarray
    kernel: str = eqx.field(static=True)

    @property
    def n_centres(self) -> int:
        return int(self.centres.shape[0])

    def _normalised_centres(self):
        return (self.centres - self.shift) / self.scale

    def _eval_block(self, x, cn):
        """x: (m, 3) mm -> (m, 3) mm."""
        xn = (x - self.shift) / self.scale
        kx = kernel_values(self.kernel, _sqdist(xn, cn), self.radii2)
        return kx @ self.weights + self.affine[0] + xn @ self.affine[1:]

    def __call__(self, points, chunk_size: int = 65536):
        """Evaluate the morph.

        Arguments:
            points: ``(..., 3)`` points, mm.
            chunk_size: the most points evaluated at once (static). It is further capped so
                that one chunk's ``(points x centres)`` kernel block holds at most 2M entries.

        Returns:
            ``(..., 3)`` morphed points, mm. Jit-able; differentiable with respect to
            ``points`` and to the morph's arrays (hence to ``fit``'s ``src``/``dst``).
        """
        points = jnp.asarray(points)
        if points.shape[-1] != 3:
            raise RBFError(f"points must have shape (..., 3) in mm, got {points.shape}.")
        n = max(self.n_centres, 1)
        chunk = int(max(1, min(int(chunk_size), max(256, _MAX_BLOCK_ELEMENTS // n))))
        return _evaluate(self, points, chunk)

    def displacement(self, points, chunk_size: int = 65536):
        """``G(p) - p`` for ``(..., 3)`` points, mm."""
        return self(points, chunk_size=chunk_size) - jnp.asarray(points)

    def apply_np(self, points, chunk_size: int = 65536) -> np.ndarray:
        """NumPy evaluation (no tracing, no compilation) of ``(..., 3)`` points, mm -> mm.

        Same function as :meth:`__call__`; for build-time code on concrete arrays.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1] != 3:
            raise RBFError(f"points must have shape (..., 3) in mm, got {pts.shape}.")
        lead = pts.shape[:-1]
        x = pts.reshape(-1, 3)
        shift = np.asarray(self.shift, np.float64)
        scale = float(self.scale)
        cn = (np.asarray(self.centres, np.float64) - shift) / scale
        W = np.asarray(self.weights, np.float64)
        A = np.asarray(self.affine, np.float64)
        c2 = np.asarray(self.radii2, np.float64)
        n = max(cn.shape[0], 1)
        # blocks of about 1 M kernel values stay in cache (2x faster than 4x larger blocks)
        chunk = int(max(1, min(int(chunk_size), max(256, (_MAX_BLOCK_ELEMENTS // 2) // n))))
        out = np.empty_like(x)
        smooth = self.kernel == "multiquadric"  # r_i > 0: no precision loss near r = 0
        cc = np.einsum("ij,ij->i", cn, cn)
        cnT = np.ascontiguousarray(cn.T)

        def block(s):
            xn = (x[s : s + chunk] - shift) / scale
            if smooth:  # sqrt(max(|x|^2 + |c|^2 - 2 x.c, 0) + r_i^2), in place
                kx = xn @ cnT
                kx *= -2.0
                kx += np.einsum("ij,ij->i", xn, xn)[:, None]
                kx += cc[None, :]
                np.maximum(kx, 0.0, out=kx)
                kx += c2[None, :]
                np.sqrt(kx, out=kx)
            else:
                kx = _kernel_np(self.kernel, _sqdist_np(xn, cn), c2)
            out[s : s + chunk] = kx @ W + A[0] + xn @ A[1:]

        starts = range(0, x.shape[0], chunk)
        if x.shape[0] * n >= _PARALLEL_MIN_ELEMENTS:
            thread_map(block, starts)  # NumPy releases the GIL in these kernels
        else:
            for s in starts:
                block(s)
        return out.reshape(*lead, 3)

    def affine_part(self):
        """The affine part ``p -> M p + t`` in mm: returns ``(M (3, 3), t (3,))``."""
        M = (self.affine[1:] / self.scale).T
        t = self.affine[0] - M @ self.shift
        return M, t


@eqx.filter_jit
def _evaluate(morph: Morph, points, chunk: int):
    lead = points.shape[:-1]
    dtype = jnp.result_type(points.dtype, morph.weights.dtype)
    x = points.reshape(-1, 3).astype(dtype)
    m = x.shape[0]
    cn = morph._normalised_centres()
    if m <= chunk:
        out = morph._eval_block(x, cn)
    else:
        n_chunks = -(-m // chunk)
        pad = n_chunks * chunk - m
        xp = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, 3))], axis=0) if pad else x
        out = jax.lax.map(lambda xc: morph._eval_block(xc, cn), xp.reshape(n_chunks, chunk, 3))
        out = out.reshape(n_chunks * chunk, 3)[:m]
    return out.reshape(*lead, 3)


# --------------------------------------------------------------------------------------
# validation (concrete inputs only)
# --------------------------------------------------------------------------------------
def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, Tracer) for x in xs)


def find_duplicates(src, rtol: float = _DUPLICATE_RTOL) -> list[np.ndarray]:
    """Groups of (numerically) coincident centres.

    Arguments:
        src: ``(n, 3)`` centres, mm.
        rtol: two centres coincide when closer than ``rtol`` times the cloud's bounding-box
            diagonal (or an absolute 1e-12 mm for a degenerate cloud).

    Returns:
        a list of index arrays (ascending), one per group of two or more coincident centres.
    """
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    p = np.asarray(src, dtype=np.float64)
    if p.shape[0] < 2:
        return []
    diag = float(np.linalg.norm(p.max(0) - p.min(0)))
    tol = max(rtol * diag, 1e-12)
    pairs = cKDTree(p).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = p.shape[0]
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    groups = []
    for lab in np.unique(labels[np.unique(pairs)]):
        idx = np.flatnonzero(labels == lab)
        if idx.size > 1:
            groups.append(idx)
    return groups


def _check_params(reg, radius_scale) -> None:
    """Refuse a negative or non-finite ridge ``reg`` and a non-positive ``radius_scale``
    (concrete values; a traced ``reg`` is left alone)."""
    for name, v, lo_ok in (("reg", reg, True), ("radius_scale", radius_scale, False)):
        try:
            x = float(v)
        except (TypeError, jax.errors.ConcretizationTypeError):
            continue
        if not math.isfinite(x) or x < 0.0 or (x == 0.0 and not lo_ok):
            need = ">= 0 (0 = interpolate exactly)" if lo_ok else "> 0"
            raise RBFError(
                f"{name} = {v!r}: must be a finite number {need}; a negative ridge makes the "
                "kernel system indefinite or singular."
                if lo_ok
                else f"{name} = {v!r}: must be a finite number {need}."
            )


def _check_inputs(src_np: np.ndarray, dst_np: np.ndarray, kernel: str) -> None:
    if kernel not in KERNELS:
        raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")
    for name, a in (("src", src_np), ("dst", dst_np)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise RBFError(f"{name} must be an (n, 3) array of points in mm, got shape {a.shape}.")
    if src_np.shape != dst_np.shape:
        raise RBFError(
            f"src and dst must hold the same number of points: src {src_np.shape}, "
            f"dst {dst_np.shape}. Pass one target per centre."
        )
    for name, a in (("src", src_np), ("dst", dst_np)):
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if bad.size:
            raise RBFError(
                f"{name} has NaN/inf coordinates at rows {bad[:20].tolist()}"
                f"{' ...' if bad.size > 20 else ''}; remove or fix those correspondences."
            )


def _check_geometry(src_np: np.ndarray) -> None:
    n = src_np.shape[0]
    if n < 4:
        raise RBFError(
            f"too few centres: got {n}, an RBF morph with an affine part needs at least 4 "
            "non-coplanar centres. Add correspondences."
        )
    c = src_np - src_np.mean(0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[0] <= 0 or sv[-1] <= _PLANAR_RTOL * sv[0]:
        what = "collinear" if sv[0] > 0 and sv[1] <= _PLANAR_RTOL * sv[0] else "coplanar"
        if sv[0] <= 0:
            what = "all at one point"
        spread = sv / np.sqrt(n)
        raise RBFError(
            f"the {n} centres are {what} (RMS spread along principal axes "
            f"{np.array2string(spread, precision=4)} mm): the affine part of the morph is "
            "undetermined. Add at least one centre off that plane (e.g. a landmark at a "
            "different depth)."
        )


def _merge_matrix(n: int, groups: list[np.ndarray]) -> np.ndarray:
    """(n_unique, n) row-stochastic matrix averaging each duplicate group into one row."""
    keep = np.ones(n, bool)
    rep = {}
    for g in groups:
        keep[g[1:]] = False
        rep[int(g[0])] = g
    rows = np.flatnonzero(keep)
    M = np.zeros((rows.size, n))
    for r, i in enumerate(rows):
        g = rep.get(int(i))
        if g is None:
            M[r, i] = 1.0
        else:
            M[r, g] = 1.0 / g.size
    return M


# --------------------------------------------------------------------------------------
# fitting
# --------------------------------------------------------------------------------------
def _system(src, dst, kernel: str, reg, radius_scale):
    """Build the normalised saddle-point system (JAX). Returns (L, Y, shift, scale, c2)."""
    n = src.shape[0]
    shift = jnp.mean(src, axis=0)
    c = src - shift
    scale = jnp.sqrt(jnp.mean(jnp.sum(c * c, axis=1)))
    scale = jnp.where(scale > 0, scale, 1.0)
    cn = c / scale
    d2 = _sqdist(cn, cn)
    if kernel == "multiquadric":
        big = jnp.max(d2) + 1.0
        c2 = jnp.min(d2 + big * jnp.eye(n, dtype=d2.dtype), axis=1) * radius_scale**2
    else:
        c2 = jnp.zeros((n,), d2.dtype)
    K = kernel_values(kernel, d2, c2)
    K = K + (_RIDGE_SIGN[kernel] * reg) * jnp.eye(n, dtype=K.dtype)
    P = jnp.concatenate([jnp.ones((n, 1), cn.dtype), cn], axis=1)
    L = jnp.block([[K, P], [P.T, jnp.zeros((4, 4), cn.dtype)]])
    Y = jnp.concatenate([dst, jnp.zeros((4, 3), dst.dtype)], axis=0)
    return L, Y, shift, scale, c2


@functools.partial(jax.jit, static_argnames=("kernel", "solver"))
def _solve(src, dst, reg, radius_scale, kernel: str, solver: str):
    L, Y, shift, scale, c2 = _system(src, dst, kernel, reg, radius_scale)
    if solver == "solve":
        sol = jnp.linalg.solve(L, Y)
    else:
        sol = jnp.linalg.pinv(L, hermitian=False) @ Y
    return sol, shift, scale, c2


def fit(
    src,
    dst,
    kernel: KernelName = "tps",
    reg: float = 0.0,
    *,
    merge_duplicates: bool = False,
    solver: Literal["solve", "lstsq"] = "solve",
    radius_scale: float = 1.0,
    validate: bool = True,
) -> Morph:
    """Fit an RBF morph sending ``src[i]`` to ``dst[i]``.

    Arguments:
        src: ``(n, 3)`` source centres ``P_i``, mm.
        dst: ``(n, 3)`` their targets ``Q_i``, mm.
        kernel: ``"tps"`` (``r^2 log r^2``), ``"biharmonic"`` (``r``) or ``"multiquadric"``
            (Hardy, with the thesis's nearest-centre stiffness radii).
        reg: ridge (smoothing) parameter, >= 0: ``reg`` times the kernel's definiteness sign
            (+1 for TPS, -1 for the biharmonic and multiquadric kernels, which are
            conditionally negative definite) is added to the kernel matrix diagonal, in the
            normalised units of the module doc; 0 reproduces exact interpolation, larger values
            smooth noisy correspondences.
        merge_duplicates: if True, coincident centres are merged into one whose target is
            the average of theirs; if False (default) they raise :class:`RBFError`.
        solver: ``"solve"`` (LU of the full system) or ``"lstsq"`` (pseudo-inverse: a
            least-squares/minimum-norm solution for near-singular systems).
        radius_scale: multiplier of the multiquadric stiffness radii (1 = thesis eq. 3.30).
        validate: run the value checks (only possible on concrete, untraced inputs).

    Returns:
        the :class:`Morph`; dtype follows the inputs.

    Raises:
        RBFError: shape mismatch, NaN/inf, fewer than 4 or coplanar centres, duplicated
            centres (their indices are listed), unknown kernel, or a singular system.
    """
    if kernel not in KERNELS:
        raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")
    _check_params(reg, radius_scale)
    if solver not in ("solve", "lstsq"):
        raise RBFError(f"unknown solver {solver!r}; choose 'solve' or 'lstsq'.")
    src = jnp.asarray(src)
    dst = jnp.asarray(dst)
    dtype = jnp.result_type(src.dtype, dst.dtype, jnp.float32)
    src = src.astype(dtype)
    dst = dst.astype(dtype)
    concrete = _is_concrete(src, dst)
    if not concrete or not validate:
        if src.ndim != 2 or src.shape[-1] != 3 or src.shape != dst.shape:
            raise RBFError(
                f"src and dst must both be (n, 3) arrays of points in mm; got {src.shape} and "
                f"{dst.shape}."
            )
    if concrete:
        src_np = np.asarray(src, dtype=np.float64)
        if validate:
            _check_inputs(src_np, np.asarray(dst, dtype=np.float64), kernel)
        groups = find_duplicates(src_np) if (validate or merge_duplicates) else []
        if groups:
            if not merge_duplicates:
                shown = "; ".join(str(g.tolist()) for g in groups[:10])
                raise RBFError(
                    f"duplicate centres (coincident source points) at indices {shown}"
                    f"{' ...' if len(groups) > 10 else ''}: the system is singular. Remove "
                    "them, or pass merge_duplicates=True to average their targets."
                )
            M = jnp.asarray(_merge_matrix(src_np.shape[0], groups), dtype)
            src = M @ src
            dst = M @ dst
            src_np = np.asarray(src, dtype=np.float64)
        if validate:
            _check_geometry(src_np)
    elif merge_duplicates:
        raise RBFError(
            "merge_duplicates=True needs concrete src (not a jit/grad tracer): merge the "
            "duplicates before tracing, e.g. with rbf.find_duplicates."
        )
    n = src.shape[0]
    sol, shift, scale, c2 = _solve(src, dst, jnp.asarray(reg, dtype), radius_scale, kernel, solver)
    if concrete and validate and not bool(jnp.all(jnp.isfinite(sol))):
        raise RBFError(
            f"the RBF system ({n} centres, kernel {kernel!r}) is singular or too ill-"
            "conditioned: the solution has NaN/inf. Check for (near-)duplicate or coplanar "
            "centres, add reg > 0, or use solver='lstsq'."
        )
    return Morph(
        centres=src,
        targets=dst,
        weights=sol[:n],
        affine=sol[n:],
        shift=shift,
        scale=scale,
        radii2=c2,
        kernel=kernel,
    )


def fit_numpy(
    src,
    dst,
    kernel: KernelName = "tps",
    reg: float = 0.0,
    *,
    merge_duplicates: bool = False,
    radius_scale: float = 1.0,
    validate: bool = True,
) -> Morph:
    """:func:`fit` computed with NumPy/SciPy (float64, no tracing or compilation).

    Same arguments, checks and result as :func:`fit` (``solver="solve"``), with NumPy arrays
    in the returned :class:`Morph`; evaluate it with :meth:`Morph.apply_np` for speed, or
    call it (JAX). Meant for build-time loops that refit systems of changing size.
    """
    import scipy.linalg

    _check_params(reg, radius_scale)
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if validate:
        _check_inputs(src, dst, kernel)
    elif kernel not in KERNELS:
        raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")
    groups = find_duplicates(src) if (validate or merge_duplicates) else []
    if groups:
        if not merge_duplicates:
            shown = "; ".join(str(g.tolist()) for g in groups[:10])
            raise RBFError(
                f"duplicate centres (coincident source points) at indices {shown}"
                f"{' ...' if len(groups) > 10 else ''}: the system is singular. Remove them, "
                "or pass merge_duplicates=True to average their targets."
            )
        M = _merge_matrix(src.shape[0], groups)
        src = M @ src
        dst = M @ dst
    if validate:
        _check_geometry(src)
    n = src.shape[0]
    shift = src.mean(0)
    c = src - shift
    scale = float(np.sqrt(np.mean(np.sum(c * c, axis=1))))
    scale = scale if scale > 0 else 1.0
    cn = c / scale
    d2 = _sqdist_np(cn, cn)
    np.fill_diagonal(d2, 0.0)
    if kernel == "multiquadric":
        dd = d2.copy()
        np.fill_diagonal(dd, np.inf)
        c2 = dd.min(axis=1) * radius_scale**2
    else:
        c2 = np.zeros(n)
    K = _kernel_np(kernel, d2, c2)
    K[np.diag_indices(n)] += _RIDGE_SIGN[kernel] * reg
    L = np.zeros((n + 4, n + 4))
    L[:n, :n] = K
    L[:n, n] = 1.0
    L[:n, n + 1 :] = cn
    L[n, :n] = 1.0
    L[n + 1 :, :n] = cn.T
    Y = np.zeros((n + 4, 3))
    Y[:n] = dst
    try:
        # the Hardy matrix is not symmetric (per-centre radii): general LU for every kernel
        # (LAPACK gesv through NumPy: twice as fast as scipy.linalg.solve here, which also
        # checks the matrix structure and estimates the condition number)
        sol = np.linalg.solve(L, Y)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as e:
        raise RBFError(
            f"the RBF system ({n} centres, kernel {kernel!r}) is singular ({e}). Check for "
            "(near-)duplicate or coplanar centres, or add reg > 0."
        ) from None
    if not np.all(np.isfinite(sol)):
        raise RBFError(
            f"the RBF system ({n} centres, kernel {kernel!r}) is too ill-conditioned: the "
            "solution has NaN/inf. Check for near-duplicate centres or add reg > 0."
        )
    return Morph(
        centres=src,
        targets=dst,
        weights=sol[:n],
        affine=sol[n:],
        shift=shift,
        scale=np.asarray(scale),
        radii2=c2,
        kernel=kernel,
    )


# --------------------------------------------------------------------------------------
# NumPy helpers
# --------------------------------------------------------------------------------------
def warp_points(morph: Morph, points) -> np.ndarray:
    """Apply ``morph`` to ``(..., 3)`` points (mm) with NumPy; returns float64 mm."""
    return morph.apply_np(points)


def warp_mesh(morph: Morph, mesh):
    """Return a new :class:`jaxface.mesh.TriMesh` whose vertices are ``morph(mesh.vertices)``
    (mm) with the same triangles. Accepts a ``TriMesh`` or a ``trimesh.Trimesh``."""
    tris = mesh.triangles if hasattr(mesh, "triangles") else mesh.faces
    return TriMesh(morph.apply_np(np.asarray(mesh.vertices)), np.asarray(tris), validate=False)
