"""Fitting RBF morphs: the saddle-point system in the normalised frame, solved in JAX
(:func:`fit`, jit-able and differentiable) or NumPy/SciPy (:func:`fit_numpy`)."""

from __future__ import annotations

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import RBFError
from .checks import (
    _check_geometry,
    _check_inputs,
    _check_params,
    _is_concrete,
    _merge_matrix,
    find_duplicates,
)
from .kernels import (
    _RIDGE_SIGN,
    KERNELS,
    KernelName,
    _kernel_np,
    _sqdist,
    _sqdist_np,
    kernel_values,
)
from .morph import Morph

__all__ = ["fit", "fit_numpy"]


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
