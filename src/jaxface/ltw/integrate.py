"""Time integration and quasi-static solve of the layered tissue (pure JAX).

Units: positions mm; velocities mm per model time unit; forces in model units.

Both solvers share one damped update on the free nodes (``u`` the position increment of a step)::

    f   = springs + volume + restoration + muscles         (forces acting on the nodes)
    f   = f - g min(f . n, 0) n        on fascia nodes      (skull non-penetration, gate g)
    u   = beta * u + alpha * f
    u   = u - g min(u . n, 0) n        on fascia nodes      (no inward velocity in contact)
    x   = x + u

* :func:`simulate` is the paper's semi-implicit ("explicit" in the paper, but the position
  update uses the new velocity) Euler scheme: ``a = (f - gamma v)/m``, ``v += dt a``,
  ``x += dt v``, i.e. ``u = dt v``, ``beta = 1 - gamma dt / m``, ``alpha = dt^2 / m`` with the
  paper's ``m = 0.5``, ``dt = 0.01``, ``gamma = 30``.
* :func:`relax` is the quasi-static solve: the same update used as *dynamic relaxation*
  (a fictitious mass equal to the node's 3x3 stiffness block ``B``, refreshed from the current
  state every ``block`` steps so that it follows biphasic and geometric stiffening (:func:`forces.preconditioner`),
  i.e. block-Jacobi-preconditioned heavy-ball / Polyak momentum). ``alpha = alpha0 B^-1`` and
  ``beta`` are the optimal heavy-ball constants ``alpha0 = 4 / (sqrt(L) + sqrt(mu))^2``,
  ``beta = ((sqrt(L) - sqrt(mu)) / (sqrt(L) + sqrt(mu)))^2`` for the spectrum ``[mu, L]`` of
  ``B^-1 K`` (``K`` the rest stiffness matrix of springs, shape term, Gauss-Newton part of
  the volume term and restoration), estimated once at build time with SciPy
  (:func:`quasi_static_constants`; ``L`` is inflated by a safety factor for the biphasic
  stiffening and geometric stiffness). The error contracts by about ``1 - 2 sqrt(mu / L)`` per
  step, against ``~ mu_abs dt / gamma`` per step for the paper's dynamics.

Both run a static number of steps with ``lax.scan``, checkpointed in blocks
(``jax.checkpoint``) so that reverse-mode memory is O(n_steps / block + block) states; both are
differentiable (grad and jvp) with respect to activations, the jaw transform and every field of
:class:`LTWParams`.
"""

from __future__ import annotations

import math
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import RigError
from .forces import (
    internal_forces,
    kinematic_positions,
    preconditioner,
    remove_inward,
    safe_length,
    skull_frame,
    skull_gate,
)
from .tissue import LTWParams, LTWTissue
from .waters import WatersMuscles, muscle_forces

__all__ = [
    "LTWModel",
    "LTWState",
    "total_forces",
    "simulate",
    "relax",
    "residual",
    "quasi_static_constants",
    "make_model",
    "rest_state",
]


class LTWModel(eqx.Module):
    """Tissue + muscles + constants: everything a solve needs (a JAX pytree).

    Attributes:
        tissue: :class:`LTWTissue`.
        muscles: :class:`WatersMuscles`.
        params: :class:`LTWParams` (differentiable material constants).
        qs_alpha0, qs_beta: quasi-static relaxation constants (static floats; see module doc).
    """

    tissue: LTWTissue
    muscles: WatersMuscles
    params: LTWParams
    qs_alpha0: float = eqx.field(static=True)
    qs_beta: float = eqx.field(static=True)


class LTWState(eqx.Module):
    """Dynamic state: node positions ``x (N, 3)`` mm and velocities ``v (N, 3)`` mm/time."""

    x: jax.Array
    v: jax.Array


def _eye_zero(dtype):
    return jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype=dtype)


def _jaw_or_rest(R, t, dtype) -> tuple[jax.Array, jax.Array]:
    """The jaw motion ``(R (3, 3), t (3,) mm)``; the identity when both are None."""
    if R is None and t is None:
        return _eye_zero(dtype)
    if R is None or t is None:
        raise RigError("give the jaw motion as both R (3, 3) and t (3,) mm, or neither.")
    return R, t


def total_forces(model: LTWModel, x, activations, R, t, skull=None, external=None):
    """Net force on every node after the skull projection, ``(N, 3)`` (zero on kinematic nodes).

    Args:
        model: the model.
        x: ``(N, 3)`` node positions, mm.
        activations: ``(M,)`` muscle activations.
        R, t: mandible rotation ``(3, 3)`` and translation ``(3,)`` mm.
        skull: optional precomputed ``skull_frame(model.tissue, R, t)``.
        external: optional ``(N, 3)`` extra applied forces (model units), e.g. cheek puff.
    """
    tis, prm = model.tissue, model.params
    V = tis.n_vertices
    pts, nrm = skull_frame(tis, R, t) if skull is None else skull
    f = internal_forces(x, tis, prm, R, t) + muscle_forces(x, model.muscles, activations, prm, R, t)
    if external is not None:
        f = f + external
    g = skull_gate(x, tis, prm, pts, nrm)
    f = f.at[V : 2 * V].set(remove_inward(f[V : 2 * V], nrm, g))
    return f * tis.free[:, None]


def _step(model, activations, R, t, skull, alpha, beta, external, max_step, carry):
    x, u = carry
    tis = model.tissue
    V = tis.n_vertices
    f = total_forces(model, x, activations, R, t, skull, external)
    if alpha.ndim == 3:  # anisotropic fictitious mass (quasi-static)
        u = beta * u + jnp.einsum("nij,nj->ni", alpha, f)
    else:
        u = beta * u + alpha * f
    pts, nrm = skull
    g = skull_gate(x, tis, model.params, pts, nrm)
    u = u.at[V : 2 * V].set(remove_inward(u[V : 2 * V], nrm, g))
    u = u * tis.free[:, None]
    if max_step is not None:  # trust region: no node moves more than max_step mm per step
        un = safe_length(u)
        u = u * (max_step / jnp.maximum(un, max_step))[:, None]
    return x + u, u


def _run(step, carry, n_steps: int, block: int, prepare=None):
    """``n_steps`` applications of ``step(carry, aux)`` with lax.scan, checkpointed every
    ``block`` steps; ``aux = prepare(carry)`` is recomputed at the start of every block."""
    n_steps = int(n_steps)
    if n_steps < 0:
        raise RigError(f"n_steps must be >= 0, got {n_steps}.")
    block = max(1, min(int(block), max(n_steps, 1)))

    def run(c, length):
        aux = prepare(c) if prepare is not None else None

        def one(c, _):
            return step(c, aux), None

        c, _ = jax.lax.scan(one, c, None, length=length)
        return c

    def blk(c, _):
        return run(c, block), None

    n_blocks, rem = divmod(n_steps, block)
    if n_blocks:
        carry, _ = jax.lax.scan(jax.checkpoint(blk), carry, None, length=n_blocks)
    if rem:
        carry = run(carry, rem)
    return carry


def rest_state(model: LTWModel, R=None, t=None, *, smooth: bool = True) -> LTWState:
    """Initial state: rest positions moved with the jaw (smooth blend on free nodes, rigid on
    the skull), zero velocity."""
    tis = model.tissue
    R, t = _jaw_or_rest(R, t, tis.rest.dtype)
    kin = kinematic_positions(tis, R, t)
    x0 = kinematic_positions(tis, R, t, smooth=smooth) if smooth else kin
    free = tis.free[:, None]
    x0 = free * x0 + (1.0 - free) * kin
    return LTWState(x0, jnp.zeros_like(x0))


def simulate(
    model: LTWModel,
    activations,
    R=None,
    t=None,
    n_steps: int = 1000,
    state: LTWState | None = None,
    *,
    block: int = 50,
    external=None,
    kinematic=None,
) -> LTWState:
    """Integrate the paper's equations of motion for ``n_steps`` steps (static int).

    Semi-implicit Euler with the params' ``mass``, ``dt`` and ``damping`` (paper 0.5, 0.01, 30).

    Args:
        model: the model.
        activations: ``(M,)`` muscle activations, held constant.
        R, t: mandible rotation ``(3, 3)`` and translation ``(3,)`` mm (default identity).
        n_steps: number of time steps (static).
        state: initial :class:`LTWState` (default :func:`rest_state` with ``smooth=False``).
        block: checkpoint block length (static).
        external: optional ``(N, 3)`` extra applied forces, model units.
        kinematic: optional ``(N, 3)`` positions of the kinematic nodes, mm (default: rest
            moved with the jaw); rows of free nodes are ignored.

    Returns:
        The final :class:`LTWState` (``x (N, 3)`` mm, ``v (N, 3)`` mm/time).
    """
    tis, prm = model.tissue, model.params
    R, t = _jaw_or_rest(R, t, tis.rest.dtype)
    if state is None:
        state = rest_state(model, R, t, smooth=False)
    skull = skull_frame(tis, R, t)
    # kinematic nodes follow the jaw exactly
    kin = kinematic_positions(tis, R, t) if kinematic is None else kinematic
    free = tis.free[:, None]
    x0 = free * state.x + (1.0 - free) * kin
    beta = 1.0 - prm.damping * prm.dt / prm.mass
    alpha = prm.dt**2 / prm.mass
    a = jnp.asarray(activations)

    def step(c, _):
        return _step(model, a, R, t, skull, alpha, beta, external, None, c)

    x, u = _run(step, (x0, state.v * prm.dt * free), n_steps, block)
    return LTWState(x, u / prm.dt)


def relax(
    model: LTWModel,
    activations,
    R=None,
    t=None,
    n_steps: int = 400,
    x0=None,
    *,
    block: int = 25,
    external=None,
    kinematic=None,
    max_step: float | None = 0.5,
) -> jax.Array:
    """Quasi-static solve (dynamic relaxation, see module doc) for ``n_steps`` steps (static).

    Args:
        model: the model.
        activations: ``(M,)`` muscle activations.
        R, t: mandible rotation ``(3, 3)`` and translation ``(3,)`` mm (default identity).
        n_steps: relaxation steps (static).
        x0: optional ``(N, 3)`` initial positions, mm (default: rest moved smoothly with the jaw).
        block: checkpoint block length (static); the fictitious mass is also refreshed
            from the current state at the start of every block.
        external: optional ``(N, 3)`` extra applied forces, model units.
        kinematic: optional ``(N, 3)`` positions of the kinematic nodes, mm (default: rest
            moved with the jaw); rows of free nodes are ignored.
        max_step: trust region, mm: a node's increment per step is scaled down to at most
            this length (static; None = off). Inactive near convergence; it keeps very large
            forces (far from the rest state, where the stiffness exceeds the build-time
            estimate) from blowing up.

    Returns:
        ``(N, 3)`` node positions, mm.
    """
    tis, prm = model.tissue, model.params
    R, t = _jaw_or_rest(R, t, tis.rest.dtype)
    kin = kinematic_positions(tis, R, t) if kinematic is None else kinematic
    free = tis.free[:, None]
    if x0 is None:
        x0 = rest_state(model, R, t, smooth=True).x
    x0 = free * x0 + (1.0 - free) * kin
    skull = skull_frame(tis, R, t)
    beta = model.qs_beta
    a = jnp.asarray(activations)

    def prepare(c):  # the fictitious mass follows the current stiffness (every block)
        return model.qs_alpha0 * jnp.linalg.inv(preconditioner(tis, prm, c[0]))

    def step(c, alpha):
        return _step(model, a, R, t, skull, alpha, beta, external, max_step, c)

    x, _ = _run(step, (x0, jnp.zeros_like(x0)), n_steps, block, prepare)
    return x


def residual(model: LTWModel, x, activations, R=None, t=None, external=None) -> jax.Array:
    """Equilibrium residual per node, ``(N,)`` mm: ``|B_i^-1 f_i|`` (the block-Jacobi
    displacement that would cancel the net force; 0 on kinematic nodes)."""
    tis = model.tissue
    R, t = _jaw_or_rest(R, t, tis.rest.dtype)
    f = total_forces(model, x, jnp.asarray(activations), R, t, external=external)
    B = preconditioner(tis, model.params, x)
    return jnp.linalg.norm(jnp.linalg.solve(B, f[..., None])[..., 0], axis=-1)


# ----------------------------------------------------------------------------- build time


def _rest_stiffness(tissue: LTWTissue, params: LTWParams) -> sp.csr_matrix:
    """Sparse rest stiffness matrix ``K (3N, 3N)`` (SciPy CSR) of springs, shape, volume
    (exact: linear in the positions) and restoration."""

    rest = np.asarray(tissue.rest, float)
    N = len(rest)
    si = np.asarray(tissue.spring_i)
    sj = np.asarray(tissue.spring_j)
    fam = np.asarray(tissue.spring_family)
    lo, _ = params.family_stiffness()
    c = np.asarray(lo, float)[fam]
    d = rest[sj] - rest[si]
    ln = np.linalg.norm(d, axis=1)
    s = d / np.maximum(ln, 1e-300)[:, None]
    s[ln < 1e-12] = 0.0
    B = c[:, None, None] * s[:, :, None] * s[:, None, :]  # (S, 3, 3)
    rows, cols, vals = [], [], []

    def add_blocks(I, J, blocks):
        k = np.arange(3)
        rows.append((3 * I[:, None, None] + k[None, :, None]).repeat(3, 2).reshape(-1))
        cols.append((3 * J[:, None, None] + k[None, None, :]).repeat(3, 1).reshape(-1))
        vals.append(blocks.reshape(-1))

    add_blocks(si, si, B)
    add_blocks(sj, sj, B)
    add_blocks(si, sj, -B)
    add_blocks(sj, si, -B)
    el = np.asarray(tissue.elements)
    F = len(el)
    k2 = float(params.k_shape)
    if k2 != 0.0:
        M9 = k2 * (np.eye(9) - np.full((9, 9), 1.0 / 9.0))
        I = np.repeat(el, 9, axis=1).reshape(-1)
        J = np.tile(el, (1, 9)).reshape(-1)
        blocks = np.broadcast_to(M9.reshape(1, 81, 1, 1) * np.eye(3), (F, 81, 3, 3)).reshape(
            -1, 3, 3
        )
        add_blocks(I, J, blocks)
    k1 = float(params.k_volume)
    if k1 != 0.0:
        A = np.asarray(tissue.elem_rest_area, float)
        n = np.asarray(tissue.elem_rest_normal, float)
        w = k1 * (A / 3.0) ** 2 / np.asarray(tissue.elem_ref_volume, float)
        blk = w[:, None, None] * n[:, :, None] * n[:, None, :]
        top = el[:, :3]
        I = np.repeat(top, 3, axis=1).reshape(-1)
        J = np.tile(top, (1, 3)).reshape(-1)
        add_blocks(I, J, np.repeat(blk, 9, axis=0))
    K = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * N, 3 * N)
    ).tocsr()
    kr = float(params.k_restore)
    if kr != 0.0:
        K = K + kr * sp.identity(3 * N, format="csr")
    return cast(sp.csr_matrix, K)


def quasi_static_constants(tissue: LTWTissue, params: LTWParams, *, safety: float = 1.6):
    """Heavy-ball constants ``(alpha0, beta)`` of :func:`relax` from the rest spectrum.

    ``L`` and ``mu`` are the largest and smallest eigenvalues of ``B^-1/2 K B^-1/2`` over the
    free nodes (``B`` the 3x3 block diagonal, :func:`forces.preconditioner`) (SciPy ``eigsh``; ``mu`` by shift-invert at 0). ``L`` is multiplied by
    ``safety`` (biphasic stiffening up to 70/30 on dermal springs, tension-induced geometric
    stiffness), ``mu`` is used as is.

    Raises:
        RigError: the free nodes have a floating (zero-stiffness) mode: enable diagonals,
            ``k_shape > 0`` or ``k_restore > 0``.
    """
    K = _rest_stiffness(tissue, params)
    free = np.asarray(tissue.free) > 0.5
    dof = np.flatnonzero(np.repeat(free, 3))
    if len(dof) == 0:
        return 1.0, 0.0
    B = np.asarray(preconditioner(tissue, params), float)[free]  # (n, 3, 3)
    w, Q = np.linalg.eigh(B)
    Bmh = np.einsum("nij,nj,nkj->nik", Q, 1.0 / np.sqrt(np.maximum(w, 1e-300)), Q)
    nf = len(B)
    rr = (3 * np.arange(nf)[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2).reshape(-1)
    cc = (3 * np.arange(nf)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1).reshape(-1)
    Dh = sp.csr_matrix((Bmh.reshape(-1), (rr, cc)), shape=(3 * nf, 3 * nf))
    Kf = K[dof][:, dof]
    A = (Dh @ Kf @ Dh).tocsc()
    A = 0.5 * (A + A.T)
    n = A.shape[0]
    if n <= 600:
        w = np.linalg.eigvalsh(A.toarray())
        lam_min, lam_max = float(w[0]), float(w[-1])
    else:
        # a fixed start vector: ARPACK's default is random, and the constants (static fields
        # of the rig) would differ between two builds of the same face in the 6th digit
        v0 = np.random.default_rng(0).standard_normal(A.shape[0])
        lam_max = float(
            spla.eigsh(A, k=1, which="LA", return_eigenvectors=False, tol=1e-3, v0=v0)[0]  # pyright: ignore[reportArgumentType] (SciPy's stub types tol as int)
        )
        try:
            lam_min = float(
                spla.eigsh(
                    A,
                    k=1,
                    sigma=0.0,
                    which="LM",
                    return_eigenvectors=False,
                    tol=1e-3,  # pyright: ignore[reportArgumentType] (SciPy's stub types tol as int)
                    v0=v0,
                )[0]
            )
        except RuntimeError:  # exactly singular factorisation
            lam_min = 0.0
    if not (lam_min > 1e-9 * lam_max):
        raise RigError(
            "the LTW tissue has a floating mode (zero stiffness at rest, smallest eigenvalue "
            f"{lam_min:.3g}): enable diagonals=True, or set k_shape > 0 or k_restore > 0."
        )
    L = safety * lam_max
    sL, sm = math.sqrt(L), math.sqrt(lam_min)
    alpha0 = 4.0 / (sL + sm) ** 2
    beta = ((sL - sm) / (sL + sm)) ** 2
    return alpha0, beta


def make_model(
    tissue: LTWTissue,
    muscles: WatersMuscles,
    params: LTWParams | None = None,
    *,
    safety: float = 1.6,
) -> LTWModel:
    """Assemble an :class:`LTWModel`, estimating the quasi-static constants (build time)."""
    params = LTWParams() if params is None else params
    a0, b = quasi_static_constants(tissue, params, safety=safety)
    return LTWModel(
        tissue=tissue, muscles=muscles, params=params, qs_alpha0=float(a0), qs_beta=float(b)
    )
