"""Graph colouring of constraints for parallel Gauss-Seidel (NumPy, build time only).

Two constraints *conflict* when they share a particle. A colouring assigns every constraint a
colour such that no two constraints of the same colour conflict; the constraints of one colour
can then be projected simultaneously (one vectorised gather / project / scatter) and the
result is exactly that of projecting them one after the other in any order. Projecting the
colours one after the other is therefore a sequential Gauss-Seidel sweep over the constraints
sorted by colour (see :func:`jaxface.reference.solve` with ``order=``), which is what
:mod:`jaxface.pbd` does.

The colouring is greedy (first-fit, in the given order): constraint ``j`` takes the smallest
colour not yet used by any constraint that shares a particle with it. With ``P`` the largest
number of constraints touching one particle, it needs at most ``P * (arity - 1) + 1`` colours
and in practice close to ``P``: on the ICT-FaceKit face skin (9,409 particles) the 55,383
stretch + cross-edge constraints take 20 colours, the 27,511 bending constraints 22 and the
18,461 area constraints 11.

First-fit colours are very unequal (4,601 constraints in the first stretch colour, 2 in the
last). :func:`balance_coloring` then moves constraints out of over-full colours into the
smallest compatible colour, without adding colours, until every colour holds ``ceil(M / K)``
constraints or fewer (on the face: 2,767-2,770 per stretch colour). Equal colours let the
solver store a group as a padded ``(K, S)`` block and ``lax.scan`` over the colours: one
compiled body per group instead of one per colour (compile time independent of the mesh) with
almost no padding. :func:`color_blocks` builds that layout (:class:`ColorBlocks`) for the
Gauss-Seidel scheme of :mod:`jaxface.pbd`; the Jacobi scheme needs no colouring.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .errors import MeshError

__all__ = [
    "ColorBlocks",
    "color_blocks",
    "greedy_coloring",
    "balance_coloring",
    "balanced_coloring",
    "padded_layout",
    "color_slices",
    "particle_counts",
]


def greedy_coloring(indices, n_particles: int | None = None) -> np.ndarray:
    """First-fit colouring of constraints that share particles.

    Args:
        indices: ``(M, k)`` int particle ids of each constraint (``k`` = arity).
        n_particles: number of particles ``N`` (default ``indices.max() + 1``).

    Returns:
        ``(M,)`` int64 colours in ``0 .. n_colors - 1``; constraints with the same colour share
        no particle.

    Raises:
        MeshError: ``indices`` is not a 2-D integer array or holds ids outside ``[0, N)``.
    """
    idx = np.asarray(indices)
    if idx.ndim != 2 or not np.issubdtype(idx.dtype, np.integer):
        raise MeshError(
            f"constraint indices must be an (M, k) integer array, got shape {idx.shape} "
            f"dtype {idx.dtype}; pass particle ids, one row per constraint.",
            problem="shape",
        )
    m = idx.shape[0]
    if m == 0:
        return np.zeros(0, np.int64)
    n = int(idx.max()) + 1 if n_particles is None else int(n_particles)
    bad = np.flatnonzero((idx < 0).any(1) | (idx >= n).any(1))
    if bad.size:
        raise MeshError(
            f"constraints {bad[:10].tolist()} refer to particle ids outside [0, {n}); "
            "check the index arrays against the number of particles.",
            problem="index_out_of_range",
            elements=bad[:100],
        )
    # Bit masks of the colours already used at each particle (Python ints: unbounded width).
    masks = [0] * n
    colors = np.empty(m, np.int64)
    for j, row in enumerate(idx.tolist()):
        used = 0
        for p in row:
            used |= masks[p]
        c = ((~used) & (used + 1)).bit_length() - 1  # lowest zero bit
        colors[j] = c
        bit = 1 << c
        for p in row:
            masks[p] |= bit
    return colors


def color_slices(colors) -> tuple[np.ndarray, tuple[int, ...]]:
    """Stable permutation that sorts constraints by colour, and the colour boundaries.

    Args:
        colors: ``(M,)`` int colours from :func:`greedy_coloring`.

    Returns:
        ``(perm, bounds)``: ``perm`` ``(M,)`` int64 such that ``colors[perm]`` is sorted (stable,
        so the original order is kept inside a colour); ``bounds`` a tuple of ``n_colors + 1``
        Python ints, colour ``c`` occupying ``perm[bounds[c]:bounds[c + 1]]``.
    """
    colors = np.asarray(colors, np.int64)
    if colors.size == 0:
        return np.zeros(0, np.int64), (0,)
    perm = np.argsort(colors, kind="stable")
    counts = np.bincount(colors)
    bounds = (0,) + tuple(int(b) for b in np.cumsum(counts))
    return perm, bounds


def particle_counts(indices, n_particles: int) -> np.ndarray:
    """Number of constraints touching each particle (a particle repeated in one constraint is
    counted once).

    Args:
        indices: ``(M, k)`` int particle ids.
        n_particles: ``N``.

    Returns:
        ``(N,)`` int64 counts (the Jacobi averaging denominators).
    """
    idx = np.asarray(indices, np.int64)
    if idx.size == 0:
        return np.zeros(n_particles, np.int64)
    s = np.sort(idx, axis=1)
    keep = np.ones_like(s, bool)
    keep[:, 1:] = s[:, 1:] != s[:, :-1]
    return np.bincount(s[keep], minlength=n_particles).astype(np.int64)


def balance_coloring(
    indices, colors, n_particles: int | None = None, n_colors: int | None = None
) -> np.ndarray:
    """Even out the colour sizes of a valid colouring without creating conflicts.

    Every constraint in a colour larger than ``ceil(M / K)`` is moved, if it can be, to the
    smallest colour (below that size) that none of its particles uses.

    Args:
        indices: ``(M, k)`` int particle ids.
        colors: ``(M,)`` a valid colouring (e.g. :func:`greedy_coloring`).
        n_particles: ``N`` (default ``indices.max() + 1``).
        n_colors: number of colours ``K`` to spread over (default: the colours in use).

    Returns:
        ``(M,)`` int64 balanced colours (still valid).
    """
    idx = np.asarray(indices, np.int64)
    col = np.asarray(colors, np.int64).copy()
    m = idx.shape[0]
    if m == 0:
        return col
    n = int(idx.max()) + 1 if n_particles is None else int(n_particles)
    K = max(int(col.max()) + 1, int(n_colors or 0))
    sizes = np.bincount(col, minlength=K).tolist()
    target = -(-m // K)
    rows = idx.tolist()
    masks = [0] * n
    for j, row in enumerate(rows):
        b = 1 << int(col[j])
        for p in row:
            masks[p] |= b
    for j in np.argsort(-np.asarray(sizes)[col], kind="stable").tolist():
        a = int(col[j])
        if sizes[a] <= target:
            continue
        used = 0
        for p in rows[j]:
            used |= masks[p]
        best, best_size = -1, target
        for c in range(K):
            if sizes[c] < best_size and not (used >> c) & 1:
                best, best_size = c, sizes[c]
        if best < 0:
            continue
        clear, setb = ~(1 << a), 1 << best
        for p in rows[j]:
            masks[p] = (masks[p] & clear) | setb
        col[j] = best
        sizes[a] -= 1
        sizes[best] += 1
    return col


def balanced_coloring(indices, n_particles: int | None = None) -> np.ndarray:
    """:func:`greedy_coloring` followed by :func:`balance_coloring` (same number of colours).

    Args:
        indices: ``(M, k)`` int particle ids.
        n_particles: ``N``.

    Returns:
        ``(M,)`` int64 colours.
    """
    col = greedy_coloring(indices, n_particles)
    return balance_coloring(indices, col, n_particles)


def padded_layout(colors) -> tuple[np.ndarray, int, int]:
    """Slots of a ``(K, S)`` colour-major block layout.

    Args:
        colors: ``(M,)`` int colours ``0 .. K-1`` (every colour non-empty or not).

    Returns:
        ``(slot, K, S)``: ``slot`` ``(M,)`` int64 position of each constraint in the flattened
        ``K * S`` block (colour ``c`` occupies ``c * S .. c * S + size_c - 1``, original order
        kept inside a colour), ``K`` colours, ``S`` the largest colour size. Slots not used are
        padding.
    """
    col = np.asarray(colors, np.int64)
    if col.size == 0:
        return np.zeros(0, np.int64), 1, 1
    K = int(col.max()) + 1
    counts = np.bincount(col, minlength=K)
    S = int(counts.max())
    order = np.argsort(col, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.empty(col.size, np.int64)
    rank[order] = np.arange(col.size) - np.repeat(starts, counts)
    return col * S + rank, K, S


class ColorBlocks(eqx.Module):
    """The ``(K, S)`` colour-block layout of one constraint group (Gauss-Seidel scheme).

    Attributes:
        perm: ``(K * S,)`` int32, slot ``s`` holds the user's constraint ``perm[s]``
            (-1: padding).
        idx: ``(K, arity, S)`` int32 particle ids per slot; padding slots point at dummy
            particles ``N, N + 1, ...`` (unique inside a colour, inverse mass 0: inert).
        layout: static ``(K, S)``.
        n_dummy: static number of dummy particles the padding needs.
    """

    perm: jax.Array
    idx: jax.Array
    layout: tuple[int, int] = eqx.field(static=True)
    n_dummy: int = eqx.field(static=True)

    def gather(self, a):
        """Per-constraint array ``(M, ...)`` (user order) as ``(K, S, ...)`` colour blocks
        (padding slots repeat constraint 0; differentiable)."""
        K, S = self.layout
        return a[jnp.maximum(self.perm, 0)].reshape((K, S) + a.shape[1:])

    def order(self) -> np.ndarray:
        """The user's constraint ids in the order a Gauss-Seidel sweep projects them."""
        perm = np.asarray(self.perm)
        return perm[perm >= 0]


def color_blocks(indices, n_particles: int) -> ColorBlocks:
    """Balanced colouring (:func:`balanced_coloring`) of ``(M, arity)`` constraints on ``N``
    particles, laid out in ``(K, S)`` blocks (NumPy, build time)."""
    idx = np.asarray(indices, np.int64)
    slot, K, S = padded_layout(balanced_coloring(idx, n_particles))
    perm = np.full(K * S, -1, np.int64)
    perm[slot] = np.arange(slot.size)
    pad = perm < 0
    rank = (np.cumsum(pad.reshape(K, S), axis=1) - 1).reshape(-1)
    ids = idx[np.maximum(perm, 0)] if idx.size else np.zeros((K * S, idx.shape[1]), np.int64)
    ids[pad] = (n_particles + rank[pad])[:, None]
    n_dummy = int(pad.reshape(K, S).sum(1).max()) if pad.size else 0
    return ColorBlocks(
        perm=jnp.asarray(perm, jnp.int32),
        idx=jnp.asarray(ids.reshape(K, S, -1).transpose(0, 2, 1), jnp.int32),
        layout=(K, S),
        n_dummy=n_dummy,
    )
