"""Validation of RBF inputs (concrete values only): parameters, shapes, NaN/inf, duplicated
centres (:func:`find_duplicates`, merged by :func:`_merge_matrix`) and coplanar centres."""

from __future__ import annotations

import math

import jax
import numpy as np
from jax.core import Tracer

from ..errors import RBFError
from .kernels import KERNELS

__all__ = ["find_duplicates"]

# relative tolerances (fractions of the centre cloud's size)
_DUPLICATE_RTOL = 1e-9
_PLANAR_RTOL = 1e-6


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
