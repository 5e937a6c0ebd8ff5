"""The sweep of the PBD engine: constraint groups, the two schemes, Chebyshev iteration.

A sweep projects the constraint groups one after the other, in the order given (Gauss-Seidel
across groups). Inside a group one of two static schemes applies the correction of
:meth:`jaxface.constraints.Constraints.correction` (the one projection of every kind):

* ``"jacobi"`` (fused Jacobi, what the rig runs): every constraint of the group is projected
  from the same positions as *one* vectorised block; the corrections are summed per particle
  with one ``segment_sum``, divided by the number of the group's constraints on the particle
  (``inv_count``) and scaled by the group's over-relaxation ``omega``. On a 2-core CPU, where
  XLA's per-operation overhead dominates, this is the fastest sweep per synthesis;
* ``"gs"`` (graph-coloured Gauss-Seidel): the group is split into colours of constraints that
  share no particle (:func:`jaxface.coloring.color_blocks`); colour after colour is projected
  and applied (one gather / project / scatter each, a ``lax.scan`` over the colours). A sweep is
  exactly the sequential Gauss-Seidel sweep over the constraints in colour order
  (:func:`jaxface.reference.solve` with ``order="color"``).

Volume groups are projected globally in both schemes (one exact-to-first-order correction per
body). :func:`iterate` runs a static number of sweeps, plain or with Chebyshev semi-iterative
acceleration (Wang 2015), with optional ``jax.checkpoint`` blocks for reverse mode.

Everything is pure JAX: jit-able, vmap-able, differentiable in positions and every float leaf
of the groups (targets, planes, rest values, stiffness, compliance). Units: mm, 1/g, s.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import to_jax
from .coloring import ColorBlocks, color_blocks
from .constraints import Constraints, VolumeConstraint
from .errors import MeshError, RigError

__all__ = ["Group", "Scheme", "make_group", "sweep", "solve", "iterate", "check_rho"]

Scheme = Literal["gs", "jacobi"]


class Group(eqx.Module):
    """One constraint group of the engine (a pytree).

    Attributes:
        c: the constraint kind (:mod:`jaxface.constraints`), user order.
        inv_count: ``(N,)`` 1 / (number of the group's constraint corners on each particle),
            0 where none (the Jacobi averaging).
        blocks: :class:`~jaxface.coloring.ColorBlocks` for the Gauss-Seidel scheme, or
            ``None`` (Jacobi only, and for volumes).
        omega: static Jacobi over-relaxation (1 = plain averaging).
        name: static label.
        scatter_hints: static ``(sorted, unique)`` of the corners' particle ids (hints for the
            Jacobi scatter, e.g. the rig's anchors on every skin vertex; no effect on values).
    """

    c: Constraints
    inv_count: jax.Array
    blocks: ColorBlocks | None = None
    omega: float = eqx.field(static=True, default=1.0)
    name: str = eqx.field(static=True, default="")
    scatter_hints: tuple[bool, bool] = eqx.field(static=True, default=(False, False))

    def set(self, **fields) -> Group:
        """Copy with fields of the constraints replaced (:meth:`Constraints.set`; traced
        values allowed)."""
        return eqx.tree_at(lambda g: g.c, self, self.c.set(**fields))


def make_group(
    c: Constraints, n: int, *, omega: float = 1.0, name: str = "", color: bool = False
) -> Group:
    """Prepare a constraint group for the engine (NumPy, build time).

    Args:
        c: the constraints (built by :mod:`jaxface.constraints.build`).
        n: number of particles ``N``.
        omega: Jacobi over-relaxation of the averaged update.
        name: label.
        color: also build the Gauss-Seidel colour blocks (volumes never need them).

    Raises:
        MeshError: ``c`` is not a constraint group or refers to particles ``>= N``.
    """
    if not isinstance(c, Constraints):
        raise MeshError(
            f"group {name!r} is a {type(c).__name__}, not a constraint group; build it with "
            "jaxface.pbd.*_constraints().",
            problem="bad_group",
        )
    idx = np.asarray(c.idx)
    if idx.size and int(idx.max()) >= n:
        rows = np.flatnonzero((idx >= n).any(1))
        raise MeshError(
            f"group {name!r}: constraints {rows[:10].tolist()} refer to particles >= N = {n}; "
            f"the system has {n} particles.",
            problem="index_out_of_range",
            elements=rows[:100],
        )
    cnt = np.bincount(idx.ravel(), minlength=n).astype(np.float64)
    inv = np.where(cnt > 0, 1.0 / np.maximum(cnt, 1.0), 0.0)
    blocks = None
    if color and not isinstance(c, VolumeConstraint):
        blocks = color_blocks(idx, n)
    flat = idx.T.ravel()
    hints = (bool(np.all(np.diff(flat) >= 0)), bool(cnt.max(initial=0.0) <= 1.0))
    return Group(
        c=c,
        inv_count=to_jax(inv),
        blocks=blocks,
        omega=float(omega),
        name=name,
        scatter_hints=hints,
    )


def _cast(tree, dtype):
    """Floating leaves of ``tree`` in ``dtype`` (integers untouched)."""

    def f(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(dtype)
        return a

    return jax.tree.map(f, tree)


def _alpha(c: Constraints, dt: float):
    return None if c.compliance is None else c.compliance / (dt * dt)


def _jacobi_group(g: Group, x, w, lam, dt):
    c = g.c
    if isinstance(c, VolumeConstraint):
        x, dlam = c.correct(x, w, _alpha(c, dt), lam)
        return x, (None if dlam is None else lam + dlam)
    xt = x.T
    P = tuple(xt[:, c.idx[:, k]] for k in range(c.arity))
    W = [w[c.idx[:, k]] for k in range(c.arity)]
    dps, dlam = c.correction(P, W, _alpha(c, dt), lam)
    # one scatter over all corners (one segment_sum per corner was slower on the CPU)
    contrib = jnp.concatenate([dp.T for dp in dps])
    acc = jax.ops.segment_sum(
        contrib,
        c.idx.T.reshape(-1),
        num_segments=x.shape[0],
        indices_are_sorted=g.scatter_hints[0],
        unique_indices=g.scatter_hints[1],
    )
    x = x + g.omega * acc * g.inv_count[:, None]
    return x, (None if dlam is None else lam + dlam)


def _gs_group(g: Group, x, w, lam, dt):
    c, b = g.c, g.blocks
    if isinstance(c, VolumeConstraint):
        return _jacobi_group(g, x, w, lam, dt)
    if b is None:
        raise MeshError(
            f"group {g.name!r} has no colour blocks; build the system with color=True for "
            "scheme='gs'.",
            problem="bad_option",
        )
    fields = {f: b.gather(getattr(c, f)) for f in c.per_constraint if getattr(c, f) is not None}
    ids = b.idx  # (K, arity, S)

    def body(x, inp):
        fl, idc, lamc = inp
        gc = dataclasses.replace(c, **fl)
        P = [x[idc[k]].T for k in range(c.arity)]
        W = [w[idc[k]] for k in range(c.arity)]
        dps, dlam = gc.correction(P, W, _alpha(gc, dt), lamc)
        for k in range(c.arity):
            x = x.at[idc[k]].add(dps[k].T, unique_indices=True, mode="promise_in_bounds")
        return x, (None if dlam is None else lamc + dlam)

    return jax.lax.scan(body, x, (fields, ids, lam))


def sweep(groups: Sequence[Group], x, inv_mass, *, scheme: Scheme = "jacobi") -> jax.Array:
    """One sweep of plain-PBD groups: every group projected in order (XPBD: :func:`solve`).

    Args:
        groups: the :class:`Group` s (their floats are cast to ``x``'s dtype).
        x: ``(N, 3)`` mm positions (for ``"gs"`` extended by the dummy particles).
        inv_mass: ``(N,)`` inverse masses, 1/g (0 = kinematic: never moved).
        scheme: static ``"jacobi"`` or ``"gs"``.

    Returns:
        ``(N, 3)`` mm.
    """
    return _sweep(groups, x, inv_mass, scheme, [None] * len(groups), 1.0)[0]


def _sweep(groups, x, inv_mass, scheme, lams, dt):
    """One sweep with the XPBD multipliers ``lams`` (one entry per group, ``None`` for PBD);
    returns ``(x, lams)``."""
    groups = _cast(tuple(groups), x.dtype)
    inv_mass = inv_mass.astype(x.dtype)
    one = _gs_group if scheme == "gs" else _jacobi_group
    out = list(lams)
    for i, g in enumerate(groups):
        x, out[i] = one(g, x, inv_mass, out[i], dt)
    return x, tuple(out)


def _zero_lambdas(groups, scheme, dtype):
    out = []
    for g in groups:
        c = g.c
        if c.compliance is None:
            out.append(None)
        elif scheme == "gs" and g.blocks is not None and not isinstance(c, VolumeConstraint):
            K, S = g.blocks.layout
            shape = (K, S) if len(c.lambda_shape()) == 1 else (K, 3, S)
            out.append(jnp.zeros(shape, dtype))
        else:
            out.append(jnp.zeros(c.lambda_shape(), dtype))
    return tuple(out)


def solve(
    groups: Sequence[Group],
    x,
    inv_mass,
    *,
    iterations: int,
    scheme: Scheme = "jacobi",
    rho: float = 0.0,
    dt: float = 1.0,
    checkpoint_every: int | None = 1,
):
    """``iterations`` sweeps from ``x``, XPBD multipliers starting at zero.

    Args:
        groups: the :class:`Group` s, projected in this order.
        x: ``(N, 3)`` mm start positions (their dtype is the solve's).
        inv_mass: ``(N,)`` 1/g.
        iterations: static number of sweeps.
        scheme: static ``"jacobi"`` (fused) or ``"gs"`` (coloured Gauss-Seidel).
        rho: static Chebyshev spectral-radius estimate (:func:`iterate`; 0 = plain).
        dt: s, XPBD time step.
        checkpoint_every: static sweeps per ``jax.checkpoint`` block, or ``None``.

    Returns:
        ``(N, 3)`` mm, same dtype as ``x``.

    Raises:
        MeshError: an unknown scheme or a negative sweep count.
    """
    if scheme not in ("gs", "jacobi"):
        raise MeshError(f"unknown scheme {scheme!r}; use 'gs' or 'jacobi'.", problem="bad_option")
    if int(iterations) < 0:
        raise MeshError(f"iterations must be >= 0, got {iterations}.", problem="bad_option")
    dtype = x.dtype
    groups = _cast(tuple(groups), dtype)
    w = inv_mass.astype(dtype)
    n = x.shape[0]
    D = 0
    if scheme == "gs":
        D = max([g.blocks.n_dummy for g in groups if g.blocks is not None], default=0)
    if D:
        x = jnp.concatenate([x, jnp.zeros((D, 3), dtype)])
        w = jnp.concatenate([w, jnp.zeros((D,), dtype)])
    lams = _zero_lambdas(groups, scheme, dtype)
    x, _ = iterate(
        lambda c: _sweep(groups, c[0], w, scheme, c[1], dt),
        (x, lams),
        iterations,
        rho,
        checkpoint_every=checkpoint_every,
    )
    return x[:n]


def check_rho(rho, what: str = "the Chebyshev spectral-radius estimate") -> float:
    """``rho`` as a float in ``[0, 1)``, else :class:`~jaxface.errors.RigError` naming ``what``."""
    rho = float(rho)
    if not 0.0 <= rho < 1.0:
        raise RigError(
            f"{what} must be in [0, 1), got {rho} (0.95-0.97 suits the skin solve; "
            "0 = plain sweeps)."
        )
    return rho


def _blocks(step, x, iterations: int, every: int | None):
    """``iterations`` plain steps; with ``every`` = B, blocks of B steps in ``jax.checkpoint``
    (reverse mode then stores one state per block and recomputes inside it)."""
    if every is None:
        return jax.lax.fori_loop(0, iterations, lambda _, c: step(c), x)
    B = min(int(every), iterations)
    nb, rem = divmod(iterations, B)

    def run(c, m):
        return step(c) if m == 1 else jax.lax.fori_loop(0, m, lambda _, cc: step(cc), c)

    blk = jax.checkpoint(lambda c: run(c, B), prevent_cse=False)
    x = jax.lax.fori_loop(0, nb, lambda _, c: blk(c), x) if nb > 1 else blk(x)
    if rem:
        x = jax.checkpoint(lambda c: run(c, rem), prevent_cse=False)(x)
    return x


def iterate(
    step: Callable,
    x,
    iterations: int,
    rho: float = 0.0,
    delay: int = 4,
    *,
    checkpoint_every: int | None = 1,
):
    """Run ``iterations`` applications of ``step`` (a pytree ``x -> x``), optionally with
    Chebyshev semi-iterative acceleration (Wang 2015, "A Chebyshev semi-iterative approach for
    accelerating projective and position-based dynamics").

    With ``rho > 0`` the iterate after step ``k`` is
    ``x_{k+1} = w_{k+1} (step(x_k) - x_{k-1}) + x_{k-1}`` with ``w = 1`` for the first
    ``delay`` steps, then ``w = 2 / (2 - rho^2)`` and ``w_{k+1} = 4 / (4 - rho^2 w_k)``
    (tending to ``2 / (1 + sqrt(1 - rho^2))``). ``rho`` estimates the spectral radius of the
    plain iteration near its fixed point: too small loses speed, too large overshoots. The
    *last* step is always a plain ``step(x)``, so whatever ``step`` enforces last (collisions,
    volume) holds exactly in the result; the fixed points are those of ``step``.

    Args:
        step: pure function of a pytree of arrays (``(N, 3)`` mm positions, ...).
        x: the start.
        iterations: static number of ``step`` calls.
        rho: static spectral-radius estimate in ``[0, 1)``; 0 = plain iteration.
        delay: static number of plain steps before the acceleration starts.
        checkpoint_every: static; wrap blocks of this many steps in ``jax.checkpoint`` (with
            ``rho > 0``: every step), or ``None``. Reverse mode then stores one state per
            block and recomputes a step's intermediates on the way back; values, derivatives
            and the forward pass's cost are unchanged.

    Returns:
        The iterate after ``iterations`` steps. Pure, jit-able, differentiable, vmap-able.

    Raises:
        RigError: ``rho`` outside ``[0, 1)``; MeshError: ``checkpoint_every`` below 1.
    """
    iterations = int(iterations)
    rho = check_rho(rho)
    if checkpoint_every is not None and int(checkpoint_every) < 1:
        raise MeshError(
            f"checkpoint_every must be >= 1 or None, got {checkpoint_every}.", problem="bad_option"
        )
    if iterations <= 0:
        return x
    if rho == 0.0 or iterations <= delay + 1:
        return _blocks(step, x, iterations, checkpoint_every)
    if checkpoint_every is not None:
        step = jax.checkpoint(step, prevent_cse=False)
    r2 = rho * rho

    def body(k, carry):
        x, prev, w = carry
        y = step(x)
        w_new = jnp.where(
            k < delay, 1.0, jnp.where(k == delay, 2.0 / (2.0 - r2), 4.0 / (4.0 - r2 * w))
        )
        new = jax.tree.map(lambda a, p: w_new.astype(a.dtype) * (a - p) + p, y, prev)
        return new, x, w_new

    w0 = jnp.asarray(1.0, jax.tree.leaves(x)[0].dtype)
    x, _, _ = jax.lax.fori_loop(0, iterations - 1, body, (x, x, w0))
    return step(x)
