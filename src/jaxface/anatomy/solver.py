"""A fused Jacobi sweep over :mod:`jaxface.pbd` constraint groups, for the rig's inner loops.

The rig runs thousands of small solves (one per synthesis, dozens per Jacobian) on a CPU
where XLA's per-operation overhead dominates: a graph-coloured Gauss-Seidel sweep issues one
gather/scatter per colour and kind (about 65 blocks on the ICT skin), which measured about
50 ms per sweep on the shared 2-core machine, and the colour-blocked Jacobi of
:func:`jaxface.pbd.relax` took minutes to compile. This module projects each constraint group
as *one* vectorised block instead:

* the constraint values and gradients come from the group's own kernel
  (``Constraints.terms`` of :mod:`jaxface.constraints`: the thesis's formulas, NaN-safe);
* the PBD correction ``dp_i = -k w_i C grad_i C / sum_j w_j |grad_j C|^2`` (eqs. 3.13-3.14)
  of every constraint is computed at the same positions and summed per particle with one
  ``segment_sum``, divided by the number of constraints of the group acting on the particle
  and scaled by the over-relaxation ``omega`` (Jacobi with averaging);
* groups are applied one after the other (Gauss-Seidel across kinds, in the order given):
  anchors first, elastic kinds, then the global volume constraint (its single correction is
  exact to first order) and last the collisions, so that the result of a sweep always
  satisfies the volume and the unilateral constraints closely.

:func:`iterate` runs a fixed number of sweeps, plain or with Chebyshev semi-iterative
acceleration (the skin solve's option ``SkinSystem.chebyshev_rho``). Convergence is measured by
the equilibrium gap (:func:`jaxface.anatomy.rig.equilibrium_gap`: how far 1,000 more plain
sweeps still move the result), because where compressed skin buckles (under the brows in a
smile, in the crease under the chin) or lips touch the teeth the problem has several
equilibria: an accelerated solve of happiness on the ICT face settles 1.4 mm from where plain
sweeps from rest end, under the left brow, and stays there (its gap is 0.02 mm). Measured on
the ICT face (``benchmarks/bench_synth.py --sweeps converged,reference --expressions``,
2-core CPU, float32): 32 muscle / 56 skin sweeps with rho 0.995 (``--sweeps converged``) take
172 ms, 3.7x the default, and leave at most 0.022 mm to go on the benchmark smile and 0.02 mm
on each of the six emotions and a jaw opening; with every control at 1 and the jaw at 18
degrees a buckle under the brow still creeps, 0.34 mm in the next 1,000 sweeps (it takes
about 1,500 to settle). The default 32 / 8 plain sweeps (47 ms) leave up to 1.6 mm.

Everything is pure JAX: jit-able, vmap-able, differentiable in positions, anchor targets,
stiffness and rest values. Units: mm (positions), inverse masses 1/g.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import to_jax
from ..constraints import AnchorConstraints, Constraints, HullConstraints, VolumeConstraint

__all__ = ["FusedGroup", "fused_group", "sweep", "anchor_sweep", "iterate", "check_rho"]


class FusedGroup(eqx.Module):
    """One constraint group prepared for fused Jacobi projection.

    Attributes:
        c: the :mod:`jaxface.constraints` group, in the user's order (one block).
        inv_count: ``(N,)`` 1 / (number of this group's constraints on each particle), 0
            for particles it does not touch.
        omega: static over-relaxation factor.
        name: static label.
    """

    c: Constraints
    inv_count: jax.Array
    omega: float = eqx.field(static=True, default=1.0)
    name: str = eqx.field(static=True, default="")


def fused_group(c: Constraints, n: int, *, omega: float = 1.0, name: str = "") -> FusedGroup:
    """Wrap a constraint group built by ``jaxface.pbd.*_constraints`` (NumPy build time).

    Args:
        c: the group (user order, as returned by the pbd builders).
        n: number of particles ``N`` of the system.
        omega: over-relaxation of the averaged Jacobi update (1 = plain averaging).
        name: label (for messages).
    """
    if not isinstance(c, VolumeConstraint) and c.arranged:
        c = c.user_order()  # a group taken from a coloured System: back to one block
    idx = np.asarray(c.idx)
    cnt = np.bincount(idx.ravel(), minlength=n).astype(np.float64)
    inv = np.where(cnt > 0, 1.0 / np.maximum(cnt, 1.0), 0.0)
    return FusedGroup(c=c, inv_count=to_jax(inv), omega=float(omega), name=name)


def _f(a, dtype):
    return a.astype(dtype) if a is not None else None


def _project_group(g: FusedGroup, x, inv_mass):
    c = g.c
    dt = x.dtype
    n = x.shape[0]
    if isinstance(c, VolumeConstraint):
        idx = c.idx
        xt = x.T
        P = tuple(xt[:, idx[:, k]] for k in range(3))
        c_ = eqx.tree_at(lambda q: (q.origin, q.rest), c, (c.origin.astype(dt), c.rest.astype(dt)))
        V, gt = c_.volume_terms(P)
        G = jax.ops.segment_sum(
            jnp.concatenate([gt[k].T for k in range(3)]), idx.T.reshape(-1), num_segments=n
        )
        denom = jnp.sum(inv_mass * jnp.sum(G * G, axis=1))
        C = V - c_.rest[0]
        ok = denom > 0
        dlam = jnp.where(ok, -c.stiffness[0].astype(dt) * C / jnp.where(ok, denom, 1.0), 0.0)
        return x + (inv_mass * dlam)[:, None] * G
    if isinstance(c, AnchorConstraints):
        i = c.idx[:, 0]
        w = inv_mass[i]
        dp = jnp.where(
            (w > 0)[:, None], c.stiffness.astype(dt)[:, None] * (c.target.astype(dt) - x[i]), 0.0
        )
        return x + jax.ops.segment_sum(dp, i, num_segments=n) * g.inv_count.astype(dt)[:, None]
    # generic kind: values and gradients from the pbd kernel, one block
    cc = c
    for fld in ("rest", "normals", "offsets", "clearance"):
        if hasattr(cc, fld) and getattr(cc, fld) is not None:
            cc = eqx.tree_at(lambda q, f=fld: getattr(q, f), cc, getattr(cc, fld).astype(dt))
    xt = x.T
    ar = c.arity
    P = tuple(xt[:, c.idx[:, k]] for k in range(ar))
    C, grads, g2 = cc.terms(P)
    W = [inv_mass[c.idx[:, k]] for k in range(ar)]
    denom = sum(W[k] * g2[k] for k in range(ar))
    ok = denom > 0
    dlam = jnp.where(ok, -c.stiffness.astype(dt) * C / jnp.where(ok, denom, 1.0), 0.0)
    if c.unilateral:
        dlam = jnp.where(C < 0, dlam, 0.0)
    # one scatter over all corners (one segment_sum per corner was slower on the CPU)
    contrib = jnp.concatenate([(W[k] * dlam * grads[k]).T for k in range(ar)])
    acc = jax.ops.segment_sum(contrib, c.idx.T.reshape(-1), num_segments=n)
    if isinstance(c, HullConstraints):
        # collisions are resolved fully (each particle has one hull constraint per group)
        return x + acc
    return x + g.omega * acc * g.inv_count.astype(dt)[:, None]


def sweep(groups, x, inv_mass):
    """One sweep: every group projected in order (Jacobi within a group, Gauss-Seidel across).

    Args:
        groups: sequence of :class:`FusedGroup`.
        x: ``(N, 3)`` mm positions.
        inv_mass: ``(N,)`` inverse masses (0 = kinematic; those particles never move).

    Returns:
        ``(N, 3)`` mm.
    """
    inv_mass = inv_mass.astype(x.dtype)
    for g in groups:
        x = _project_group(g, x, inv_mass)
    return x


def anchor_sweep(x, idx, target, stiffness, inv_count, inv_mass):
    """Anchor projection with run-time targets, without building a constraint group.

    Args:
        x: ``(N, 3)`` mm; idx: ``(M,)`` particle ids; target: ``(M, 3)`` mm;
        stiffness: ``(M,)``; inv_count: ``(N,)`` 1/(anchors per particle); inv_mass: ``(N,)``.

    Returns:
        ``(N, 3)`` mm.
    """
    dt = x.dtype
    w = inv_mass.astype(dt)[idx]
    dp = jnp.where(
        (w > 0)[:, None], stiffness.astype(dt)[:, None] * (target.astype(dt) - x[idx]), 0.0
    )
    return x + jax.ops.segment_sum(dp, idx, num_segments=x.shape[0]) * inv_count.astype(dt)[:, None]


def check_rho(rho, what: str = "the Chebyshev spectral-radius estimate") -> float:
    """``rho`` as a float in ``[0, 1)``, else :class:`~jaxface.errors.RigError` naming ``what``."""
    from ..errors import RigError

    rho = float(rho)
    if not 0.0 <= rho < 1.0:
        raise RigError(
            f"{what} must be in [0, 1), got {rho} (0.95-0.97 suits the skin solve; "
            "0 = plain sweeps)."
        )
    return rho


def iterate(step, x, iterations: int, rho: float = 0.0, delay: int = 4, *, checkpoint: bool = True):
    """Run ``iterations`` applications of ``step`` (``x -> x``), optionally with Chebyshev
    semi-iterative acceleration (Wang 2015, "A Chebyshev semi-iterative approach for
    accelerating projective and position-based dynamics").

    With ``rho > 0`` the iterate after step ``k`` is
    ``x_{k+1} = w_{k+1} (step(x_k) - x_{k-1}) + x_{k-1}`` with ``w = 1`` for the first
    ``delay`` steps, then ``w = 2 / (2 - rho^2)`` and ``w_{k+1} = 4 / (4 - rho^2 w_k)``
    (tending to ``2 / (1 + sqrt(1 - rho^2))``). ``rho`` is an estimate of the spectral
    radius of the plain iteration near its fixed point: too small loses speed, too large
    overshoots. The *last* step is always a plain ``step(x)``, so whatever ``step`` enforces
    last (collisions, volume) holds exactly in the result. Particles that ``step`` never moves
    (kinematic ones) stay where they are. The fixed points are those of ``step``.

    Args:
        step: pure function ``(N, 3) -> (N, 3)`` (mm).
        x: ``(N, 3)`` start, mm.
        iterations: static number of ``step`` calls.
        rho: static spectral-radius estimate in ``[0, 1)``; 0 = plain iteration.
        delay: static number of plain steps before the acceleration starts.
        checkpoint: static; wrap every ``step`` in ``jax.checkpoint``. Reverse mode then
            stores one ``(N, 3)`` state per sweep and recomputes the sweep's intermediates
            (per-constraint gathers, corrections, scatter-adds) on the way back, instead of
            storing them all. It changes no value and no derivative, nor the forward pass's
            cost. On bs900's rig (12,140 skin vertices, float64, 2-core CPU) the reverse
            pass of a synthesis took 0.47 s with the skin's sweeps checkpointed against 0.60
            s without, and half the time when another job shared the cores
            (``benchmarks/bench_synth.py``, ``reverse_*``).

    Returns:
        ``(N, 3)`` mm. Pure, jit-able, differentiable, vmap-able.

    Raises:
        RigError: ``rho`` outside ``[0, 1)``.
    """
    iterations = int(iterations)
    rho = check_rho(rho)
    if checkpoint:
        step = jax.checkpoint(step, prevent_cse=False)
    if rho == 0.0 or iterations <= delay + 1:
        return jax.lax.fori_loop(0, iterations, lambda _, x: step(x), x)
    r2 = rho * rho
    dt = x.dtype

    def body(k, carry):
        x, prev, w = carry
        y = step(x)
        w_new = jnp.where(
            k < delay, 1.0, jnp.where(k == delay, 2.0 / (2.0 - r2), 4.0 / (4.0 - r2 * w))
        )
        w_new = w_new.astype(dt)
        return w_new * (y - prev) + prev, x, w_new

    x, _, _ = jax.lax.fori_loop(0, iterations - 1, body, (x, x, jnp.asarray(1.0, dt)))
    return step(x)
