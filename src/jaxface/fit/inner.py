"""The inner solves: Levenberg-Marquardt on the residuals of :mod:`jaxface.fit.residuals`
with fixed correspondences, batched over scans, and the optional refinement through the exact
rig.

Each inner solve minimises ``sum r^2`` (mm^2) over :class:`~jaxface.fit.params.Params` with
optimistix's Levenberg-Marquardt (forward-mode Jacobian through the residuals' custom rule,
``throw=False``); the damped Gauss-Newton steps solve the normal equations by Cholesky in
float64 (QR in float32). A batch runs as one compiled single-scan solve per scan on the CPU
(``"map"``), or as one ``jax.vmap`` padded to a power of two on accelerators (``"vmap"``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._arrays import to_jax
from .._parallel import thread_map
from ..errors import FitError
from .forward import ForwardModel
from .options import SolverOptions
from .params import Params, activations_from_z, apply_rigid
from .residuals import (
    PointSet,
    Priors,
    cost,
    cost_of_activations,
    effective_z,
    point_residuals,
    points_from_vertices,
    residuals,
)

__all__ = [
    "InnerResult",
    "InnerReport",
    "linear_solver",
    "batch_mode",
    "padded_batch_size",
    "solve_inner",
    "result_name",
    "result_names",
    "stack_trees",
    "index_tree",
    "exact_refine",
]

#: The ``optimistix.RESULTS`` entries :func:`result_names` looks up (public attributes,
#: compared with ``==``); a result matching none is ``"unknown"``.
RESULT_NAMES = (
    "successful",
    "max_steps_reached",
    "singular",
    "breakdown",
    "stagnation",
    "conlim",
    "nonfinite_input",
    "nonlinear_max_steps_reached",
    "nonlinear_divergence",
    "nonfinite",
)


class InnerResult(NamedTuple):
    """A batch of inner solves (leading axis ``B``: one member per run).

    Attributes:
        y: the solutions (:class:`~jaxface.fit.params.Params`, leaves ``(B, ...)``).
        result: ``B`` optimistix result names (``"successful"``, ``"nonlinear_max_steps_reached"``,
            ...; :func:`result_names`).
        steps: ``(B,)`` Levenberg-Marquardt steps.
        cost: ``(B,)`` final cost (mm^2); cost0: ``(B,)`` the cost at the start (mm^2).
        activations: ``(B, M)`` the activations at the solution (held ones at their bound).
        grad_activations: ``(B, M)`` gradient of the cost with respect to the activations at
            the solution (mm^2 per unit activation): the KKT test of the bounds.
    """

    y: Params
    result: tuple[str, ...]
    steps: np.ndarray
    cost: np.ndarray
    cost0: np.ndarray
    activations: np.ndarray
    grad_activations: np.ndarray


@dataclass(frozen=True)
class InnerReport:
    """One inner solve of one scan, as reported in the fit's JSON.

    Attributes:
        outer: outer iteration; result: optimistix result name; steps: LM steps.
        cost0, cost: cost before / after (mm^2).
        n_accepted: accepted correspondences; scale_mm: Tukey cut-off (mm).
        active_set_changes: active-set changes after the solve; n_at_bounds: activations held
            at a bound; seconds: wall time of the whole batched call.
    """

    outer: int
    result: str
    steps: int
    cost0: float
    cost: float
    n_accepted: int
    scale_mm: float
    active_set_changes: int
    n_at_bounds: int
    seconds: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def result_names(result) -> tuple[str, ...]:
    """Names of the members of a batched ``optimistix.RESULTS`` item ``(B,)``."""
    out = np.full(np.shape(np.asarray(result == optx.RESULTS.successful)), "unknown", object)
    for name in RESULT_NAMES:
        item = getattr(optx.RESULTS, name, None)
        if item is not None:
            out[np.asarray(result == item) & (out == "unknown")] = name
    return tuple(str(v) for v in np.ravel(out))


def result_name(result) -> str:
    """Name of one ``optimistix.RESULTS`` item (``"successful"``, ``"max_steps_reached"``,
    ``"nonlinear_max_steps_reached"``, ...)."""
    return result_names(result)[0]


def linear_solver(dtype) -> lx.AbstractLinearSolver:
    """The damped Gauss-Newton steps' linear solver: the normal equations by Cholesky in
    float64, QR otherwise.

    Each step solves the tall system ``[J; sqrt(lambda) D] dy = [-r; 0]``; with the damping the
    normal matrix is positive definite and its condition number the square of the Jacobian's
    (at most about 1e6 on the shared data, harmless in float64, and faster than QR). In float32
    the squared conditioning would cost digits, so QR stays.
    """
    return lx.Normal(lx.Cholesky()) if jnp.dtype(dtype) == jnp.float64 else lx.QR()


def _solve_one(y0: Params, pts: PointSet, pri: Priors, *, max_steps, rtol, atol):
    """One inner solve (traced): ``(y, optimistix result, steps, cost, cost0, a, grad_a)``."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=linear_solver(y0.z.dtype))
    sol = optx.least_squares(
        residuals, solver, y0, args=(pts, pri), max_steps=max_steps, throw=False
    )
    y = sol.value
    a = activations_from_z(effective_z(y, pts))
    g = jax.grad(cost_of_activations)(a, y, pts, pri)
    return (
        y,
        sol.result,
        sol.stats["num_steps"],
        cost(y, (pts, pri)),
        cost(y0, (pts, pri)),
        a,
        g,
    )


def batch_mode() -> str:
    """How :func:`solve_inner` runs a batch: ``"map"`` (one compiled single-scan solve called
    per scan, each stopping at its own convergence) on the CPU, ``"vmap"`` (parallel) on
    accelerators."""
    return "map" if jax.default_backend() == "cpu" else "vmap"


@functools.lru_cache(maxsize=16)
def _batched_solver(max_steps: int, rtol: float, atol: float, mode: str = "vmap"):
    fn = functools.partial(_solve_one, max_steps=max_steps, rtol=rtol, atol=atol)
    if mode == "map":
        return eqx.filter_jit(fn)
    return eqx.filter_jit(jax.vmap(fn, in_axes=(0, 0, None)))


def padded_batch_size(n: int) -> int:
    """The batch size a ``"vmap"`` inner solve of ``n`` members is compiled for: the next
    power of two (1, 2, 4, 8, 16, ...), so the shrinking subsets of a fit and batches of other
    sizes reuse a few compiled solves instead of compiling one per size."""
    n = int(n)
    if n < 1:
        raise FitError(f"padded_batch_size needs a batch of at least one member; got {n}.")
    return 1 << (n - 1).bit_length()


def _pad_leading(tree, n: int, size: int):
    """Every array leaf of ``tree`` padded from ``n`` to ``size`` rows along its leading axis
    by repeating its last row (padding members repeat a real member's solve, so they cannot
    fail where it does not and never take more steps than the batch's slowest member)."""
    if size == n:
        return tree

    def pad(x):
        if not eqx.is_array(x):
            return x
        x = np.asarray(x)
        return to_jax(np.concatenate([x, np.repeat(x[n - 1 : n], size - n, axis=0)], axis=0))

    return jax.tree_util.tree_map(pad, tree)


def solve_inner(
    y0: Params,
    points: PointSet,
    priors: Priors,
    options: SolverOptions,
    *,
    mode: str | None = None,
    pad_to: int | None = None,
) -> InnerResult:
    """Batched Levenberg-Marquardt solves over the leading axis of ``y0`` and ``points``,
    ``throw=False``.

    In ``"map"`` mode (the CPU default) each scan is solved by the same compiled single-scan
    solve, the scans on the outer thread pool (:func:`jaxface._parallel.thread_map`): a batch
    of any size, and the subsets that :func:`jaxface.fit.solve.fit_points` goes on with, cost
    no new compilation. ``"vmap"`` (accelerators) pads the batch to a power of two
    (:func:`padded_batch_size`) and compiles one parallel solve per padded size.

    Args:
        y0, points: batched parameters and residual data; priors: shared.
        options: ``max_steps``, ``rtol``, ``atol`` (a :class:`~jaxface.fit.options.FitOptions`).
        mode: ``"map"`` or ``"vmap"``; default :func:`batch_mode`.
        pad_to: ``"vmap"`` only: pad the batch to at least this many members, rounded up by
            :func:`padded_batch_size` (default: ``padded_batch_size`` of the batch). The
            padding repeats the last member and is cut from the results, so one compiled
            solve serves every batch size up to it. ``"map"`` ignores it.

    Raises:
        FitError: an unknown ``mode``.
    """
    mode = batch_mode() if mode is None else mode
    if mode not in ("map", "vmap"):
        raise FitError(f"solve_inner mode {mode!r}: use 'map' or 'vmap'.")
    fn = _batched_solver(int(options.max_steps), float(options.rtol), float(options.atol), mode)
    n = int(np.shape(jax.tree_util.tree_leaves(y0)[0])[0])
    if mode == "map":
        # one solve per thread of the pool: a solve's small kernels keep one core busy
        outs = thread_map(
            lambda b: jax.block_until_ready(fn(index_tree(y0, b), index_tree(points, b), priors)),
            range(n),
            outer=True,
        )
        return InnerResult(
            stack_trees([o[0] for o in outs]),
            tuple(result_name(o[1]) for o in outs),
            *(np.stack([np.asarray(o[k]) for o in outs]) for k in range(2, 7)),
        )
    size = padded_batch_size(max(n, int(pad_to or 0)))
    y, res, steps, cost_, cost0, a, g = fn(
        _pad_leading(y0, n, size), _pad_leading(points, n, size), priors
    )
    if size != n:
        y = index_tree(y, slice(0, n))
    return InnerResult(
        y, result_names(res)[:n], *(np.asarray(v)[:n] for v in (steps, cost_, cost0, a, g))
    )


def stack_trees(trees):
    """The pytrees ``trees`` stacked along a new leading axis, on the host (the same bits as
    ``jnp.stack``, without an eager XLA dispatch, and a compilation per new shape, per leaf)."""
    return jax.tree_util.tree_map(lambda *xs: to_jax(np.stack([np.asarray(x) for x in xs])), *trees)


def index_tree(tree, i):
    """Entry (or slice) ``i`` of the leading axis of every array leaf of ``tree`` (on the
    host, see :func:`stack_trees`)."""
    return jax.tree_util.tree_map(
        lambda x: to_jax(np.asarray(x)[i]) if eqx.is_array(x) else x, tree
    )


def exact_refine(
    forward: ForwardModel,
    fit_ids,
    y: Params,
    pts: PointSet,
    priors: Priors,
    opt: SolverOptions,
    outer: int,
) -> tuple[Params, InnerReport]:
    """Levenberg-Marquardt through the exact rig (forward-mode Jacobian of the synthesis,
    ``opt.exact_steps`` steps) with the last correspondences ``pts`` and active set.

    Returns:
        the refined parameters and the report of the solve (``outer``: its iteration number;
        result ``"exact:<name>"``).
    """
    t0 = time.perf_counter()
    fn = forward.fn
    fit_ids_j = to_jax(fit_ids)

    def resid(yy, args):
        pts_, pri = args
        a = activations_from_z(effective_z(yy, pts_))
        x = points_from_vertices(fn(a, yy.jaw)[fit_ids_j], pts_)
        if pri.use_rigid:
            x = apply_rigid(yy.rigid, pts_.centre, x)
        out = residuals(yy, args)
        r_pt, r_lm = point_residuals(x, pts_)
        return eqx.tree_at(lambda r: (r.points, r.landmarks), out, (r_pt, r_lm))

    total_cost = jax.jit(
        lambda yy, args: sum(jnp.sum(v * v) for v in jax.tree_util.tree_leaves(resid(yy, args)))
    )
    solver = optx.LevenbergMarquardt(rtol=opt.rtol, atol=opt.atol)
    c0 = float(total_cost(y, (pts, priors)))

    def run(y0, args):
        sol = optx.least_squares(
            resid, solver, y0, args=args, max_steps=int(opt.exact_steps), throw=False
        )
        return sol.value, sol.result, sol.stats["num_steps"]

    yv, result, n_steps = jax.jit(run)(y, (pts, priors))
    c1 = float(total_cost(yv, (pts, priors)))
    report = InnerReport(
        outer,
        "exact:" + result_name(result),
        int(n_steps),
        c0,
        c1,
        int(np.sum(np.asarray(pts.w_point) > 0)),
        float("nan"),
        0,
        int(np.sum(np.asarray(pts.free) == 0)),
        time.perf_counter() - t0,
    )
    return yv, report
