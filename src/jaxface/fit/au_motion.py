"""AU readouts of a fitted expression: which action units it shows, and how strongly.

* :func:`read_aus` gives the fit's AU intensities (``ExpressionFit.au_intensities``, the
  headline output): the fewest AUs whose table activations reproduce the fit's *skin motion*,
  calibrated (each kept AU gets its L1 shrinkage back, so a rig driven by the table at
  intensities ``i`` reads ``i`` back), and pruned of AUs whose removal moves the skin by less
  than :data:`AU_MIN_MOTION_MM`. Many activation vectors give nearly the same skin (two
  antagonists held at 1 cancel on the eyelid; a small muscle at 1 moves the skin a
  millimetre), so the table's inverse of the fit's own activations
  (:func:`jaxface.facs.au_intensities`, kept as ``ExpressionFit.au_from_activations``) reports
  controls the motion does not need; reading the motion removes that freedom, as FACS coders
  code the fewest AUs that account for what they see.
* :func:`au_skin_motion` says how much of the motion each AU's share of the fit's activations
  accounts for, in mm (``ExpressionFit.au_motion_mm``):

  * the activations are split into AU shares by :func:`jaxface.facs.au_decomposition`
    (AU ``k``'s share is ``intensity_k * row_k``);
  * the jaw pose is split like the intensities: the opening up to AU26's 10 degrees is AU26,
    the rest AU27; positive protrusion is AU29; yaw is AU30L (toward the subject's left, +)
    or AU30R;
  * each share is applied *alone* to the subject's reduced model
    (:class:`jaxface.fit.reduced.ResponseModel`, the model the fit solves with) and the RMS
    skin displacement over its points (the face region, mm) is that AU's motion. A bilateral
    AU (``AU12``) is both sides' shares together, its sides (``AU12L``, ``AU12R``) each alone.

  The numbers do not add up to the whole motion (the RMS of a sum is not the sum of the
  RMSs): they rank the AUs by their visible effect.

Both work on the reduced model alone (no synthesis): a readout takes a fraction of a second.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize

from ..anatomy.jaw import JawPose
from ..facs import AU_JAW, au_decomposition, au_dict, sort_aus
from .options import AU_MIN_MOTION_MM, AU_SPARSE_WEIGHT
from .reduced import ResponseModel, hermite_basis

__all__ = [
    "au_skin_motion",
    "read_aus",
    "AuReadout",
    "motion_gram",
    "AU_SPARSE_WEIGHT",
    "AU_MIN_MOTION_MM",
]


@eqx.filter_jit
def _rms_motion(model, rows, muscles, values, J, n_rows: int):
    """RMS displacement (mm) of ``n_rows`` shares of the activations, then of ``Q`` jaw poses.

    The reduced model is additive in the muscles, so a share's displacement is the sum of its
    muscles' own terms (:meth:`~jaxface.fit.reduced.ResponseModel.muscle_terms`): the triples
    ``(rows, muscles, values)`` ``(T,)`` list the activations of every share (the table's
    non-zero pattern, so ``T`` is fixed per rig and this compiles once per subject).
    ``J`` ``(Q, 3)``: jaw poses, muscles at rest. Returns ``(n_rows + Q,)``."""
    D = jax.ops.segment_sum(model.muscle_terms(muscles, values), rows, num_segments=n_rows)
    z = jnp.zeros(model.mus.shape[0], J.dtype)
    base = model.displacement(z, jnp.zeros(3, J.dtype))
    DJ = jax.vmap(lambda j: model.displacement(z, j))(J) - base[None]
    D = jnp.concatenate([D, DJ])
    return jnp.sqrt(jnp.mean(jnp.sum(D * D, axis=-1), axis=-1))


def au_skin_motion(
    response: ResponseModel, activations, jaw, muscle_names: Sequence[str]
) -> dict[str, float]:
    """RMS skin motion (mm) each action unit accounts for in a fitted expression.

    Args:
        response: the subject's :class:`~jaxface.fit.reduced.ResponseModel` (mm).
        activations: ``(M,)`` fitted activations in [0, 1], ordered as ``muscle_names``.
        jaw: ``(3,)`` effective jaw pose ``[pitch_deg, yaw_deg, protrusion_mm]`` (after the
            rig's limits, e.g. ``PointFit.jaw_effective``).
        muscle_names: the rig's control names.

    Returns:
        ``{AU: mm}`` for every AU of the table present on the rig (bilateral AUs and their
        ``L``/``R`` sides) and the jaw AUs 26, 27, 29, 30 (``AU30L``/``AU30R``), sorted by AU
        number.

    Raises:
        RigError: ``activations`` and ``muscle_names`` differ in length.
    """
    aus, inten, rows = au_decomposition(activations, muscle_names)
    M = rows.shape[1]
    own = inten[:, None] * rows  # (K, M) each AU variant's share
    sided = [au for au in aus if au[-1] in "LR"]
    bases = list(dict.fromkeys(au[:-1] for au in sided))
    labels = list(aus) + bases  # bilateral AUs: both sides together
    shares = list(own) + [sum(own[aus.index(au)] for au in sided if au[:-1] == b) for b in bases]
    je = np.asarray(jaw, np.float64).ravel()
    p, y, q = max(float(je[0]), 0.0), float(je[1]), max(float(je[2]), 0.0)
    p26 = AU_JAW["AU26"][0]
    jaw_rows = [
        ("AU26", (min(p, p26), 0.0, 0.0)),
        ("AU29", (0.0, 0.0, q)),
        ("AU30L", (0.0, max(y, 0.0), 0.0)),
        ("AU30R", (0.0, min(y, 0.0), 0.0)),
        ("_open", (p, 0.0, 0.0)),
    ]
    dt = response.rest.dtype
    S = np.asarray(shares).reshape(-1, M)
    # every share's activations lie on its table rows' non-zero pattern (fixed per rig)
    pattern = np.vstack(
        [rows] + [sum(rows[aus.index(au)] for au in sided if au[:-1] == b) for b in bases]
    )
    r, m = np.nonzero(pattern)
    J = np.asarray([j for _, j in jaw_rows], np.float64)
    rms = np.asarray(
        _rms_motion(
            response,
            jnp.asarray(r),
            jnp.asarray(m),
            jnp.asarray(S[r, m], dt),
            jnp.asarray(J, dt),
            len(S),
        ),
        np.float64,
    )
    out = {lab: float(v) for lab, v in zip(labels, rms[: len(labels)])}
    jaw_rms = {lab: float(v) for (lab, _), v in zip(jaw_rows, rms[len(labels) :])}
    out["AU26"] = jaw_rms["AU26"]
    # the opening beyond AU26's range: the extra motion of the whole opening over AU26's part
    out["AU27"] = max(jaw_rms["_open"] - jaw_rms["AU26"], 0.0) if p > p26 else 0.0
    out["AU29"] = jaw_rms["AU29"]
    out["AU30L"], out["AU30R"] = jaw_rms["AU30L"], jaw_rms["AU30R"]
    out["AU30"] = max(out["AU30L"], out["AU30R"])
    return sort_aus(out)


def motion_gram(response) -> np.ndarray:
    """Gram matrix of a reduced model's coefficient fields, for :func:`read_aus`.

    The model is additive in the muscles and each muscle's displacement is a cubic Hermite
    spline in its activation: ``D(a) = sum_m psi(a_m) . F_m`` with ``psi`` ``(2N,)`` the spline
    weights of the ``N`` knot values and slopes and ``F_m`` ``(2N, P, 3)`` those fields
    (:class:`~jaxface.fit.reduced.ResponseModel`). So the mean squared distance of two motions
    over the ``P`` points is the quadratic form ``d^T G d`` of their weight differences, with
    ``G = F F^T / P``: the readout's cost without touching the points again.

    Args:
        response: the subject's :class:`~jaxface.fit.reduced.ResponseModel` (mm).

    Returns:
        ``(M 2N, M 2N)`` float64, mm^2.
    """
    mus = np.asarray(response.mus, np.float64)
    sl = np.asarray(response.mus_slope, np.float64)
    M, N, P = mus.shape[:3]
    F = np.concatenate([mus, sl], axis=1).reshape(M * 2 * N, P * 3)
    return (F @ F.T) / max(P, 1)


def _spline_weights(x, knots):
    """``(M 2N,)``: the Hermite weights of every muscle's ``N`` knot values, then its ``N``
    slopes, at activations ``x`` ``(M,)`` (the layout of :func:`motion_gram`)."""
    s, w, _ = hermite_basis(x, knots)
    M, N = x.shape[0], knots.shape[0]
    m = jnp.arange(M)
    W = jnp.zeros((M, 2 * N), x.dtype)
    W = (
        W.at[m, s]
        .add(w[:, 0])
        .at[m, s + 1]
        .add(w[:, 1])
        .at[m, N + s]
        .add(w[:, 2])
        .at[m, N + s + 1]
        .add(w[:, 3])
    )
    return W.reshape(-1)


def _au_weights(i, rows, knots):
    """Spline weights (the layout of :func:`motion_gram`) of the table activations
    ``clip(A^T i, 0, 1)`` of unilateral-AU intensities ``i`` ``(K,)``, rows ``(K, M)``."""
    return _spline_weights(jnp.clip(i @ rows, 0.0, 1.0), knots)


@jax.jit
def _sparse_cost(G, knots, i, rows, phi_a, weight):
    """Cost of :func:`read_aus` at intensities ``i`` ``(K,)``: ``(cost, mean squared misfit
    mm^2, d cost / d i)``. ``rows`` ``(K, M)`` the AU table rows, ``phi_a`` the spline
    weights of the fitted activations (the rest state's weights cancel in the difference)."""

    def f(i):
        d = _au_weights(i, rows, knots) - phi_a
        mis = d @ (G @ d)
        return mis + weight * jnp.sum(i), mis

    (c, mis), g = jax.value_and_grad(f, has_aux=True)(i)
    return c, mis, g


@jax.jit
def _motion_distance(G, knots, rows, i1, i2):
    """RMS distance (mm) between the skin motions of two unilateral-AU intensity vectors
    ``i1``, ``i2`` ``(K,)`` on the reduced model (the quadratic form of :func:`motion_gram`)."""

    d = _au_weights(i1, rows, knots) - _au_weights(i2, rows, knots)
    return jnp.sqrt(jnp.maximum(d @ (G @ d), 0.0))


@jax.jit
def _unit_motion(G, knots, rows, x):
    """``u_k = |dD/di_k|`` ``(K,)``: each AU's RMS skin motion per unit intensity at
    unilateral-AU intensities ``x`` ``(K,)`` (mm), from the Jacobian of the spline weights and
    the Gram matrix."""

    J = jax.jacfwd(_au_weights)(x, rows, knots)  # (M 2N, K)
    return jnp.sqrt(jnp.maximum(jnp.einsum("ak,ab,bk->k", J, G, J), 0.0))


@dataclass(frozen=True)
class AuReadout:
    """The AU readout of one fit (:func:`read_aus`).

    Attributes:
        intensities: ``{AU: intensity}`` in [0, 1], the calibrated sparse intensities (bilateral
            AUs the mean of their sides, the sides as ``AUxxL`` / ``AUxxR``, the jaw AUs from
            the jaw pose), sorted by AU number. This is ``ExpressionFit.au_intensities``.
        misfit_mm: RMS distance (mm) over the reduced model's points between the skin motion
            the intensities produce and the fit's.
        removal_mm: ``{AU: mm}`` for every muscle AU the readout keeps (each side, and a
            bilateral AU with both sides together): how far (RMS, mm) the readout's skin
            motion moves when that AU is removed (the others unchanged). Each side is at
            least ``min_motion_mm``.
        lasso: ``{AU: intensity}`` of the L1 step alone (shrunk toward 0 by the penalty).
        weight: the L1 weight (mm^2 per unit intensity); min_motion_mm: the removal threshold.
    """

    intensities: dict
    misfit_mm: float
    removal_mm: dict
    lasso: dict
    weight: float
    min_motion_mm: float

    def to_dict(self) -> dict:
        """The ``au_readout`` block of the fit JSON (mm)."""
        return {
            "method": "L1 selection in motion space, per-AU Newton calibration, pruning",
            "l1_weight_mm2": self.weight,
            "min_motion_mm": self.min_motion_mm,
            "misfit_mm": self.misfit_mm,
            "removal_mm": {k: float(v) for k, v in self.removal_mm.items()},
            "lasso": {k: float(v) for k, v in self.lasso.items()},
        }


def read_aus(
    response,
    activations,
    jaw,
    muscle_names: Sequence[str],
    *,
    weight: float = AU_SPARSE_WEIGHT,
    min_motion_mm: float = AU_MIN_MOTION_MM,
    gram=None,
    cheek_puff: float = 0.0,
) -> AuReadout:
    """FACS AU intensities that account for a fit's skin motion with the fewest AUs.

    Many activation vectors give nearly the same skin (an antagonist pair both at 1 cancels on
    the eyelid), so the table's inverse of the fit's own activations
    (:func:`jaxface.facs.au_intensities`) reports controls the motion does not need. This
    readout asks which AUs *the motion* needs, as a FACS coder codes the fewest AUs that
    account for what is seen. Over the unilateral AU intensities ``i`` ``(K,)`` of the table
    (:func:`jaxface.facs.au_decomposition`'s AUs, rows ``A`` ``(K, M)``), with ``D(a)``
    ``(P, 3)`` the reduced model's skin displacement (mm, muscles only, jaw at rest), ``a`` the
    fitted activations and ``m(i) = mean_p |D(clip(A^T i))_p - D(a)_p|^2`` (mm^2):

    1. **Selection** (L1): ``i_1 = argmin_{0 <= i <= 1} m(i) + weight * sum_k i_k``
       (L-BFGS-B from the table's non-negative least squares). An AU stays only where it
       accounts for more than ``weight`` mm^2 of mean squared motion per unit intensity: an
       antagonist pair whose net motion is small drops out, and of two AUs that move the same
       skin the one that does it with less intensity stays.
    2. **Calibration**: the penalty shrinks each kept intensity by about
       ``weight / (2 u_k^2)``, where ``u_k = |dD/di_k|`` is the AU's RMS skin motion per unit
       intensity at ``i_1`` (mm): weak AUs the most. Each kept AU gets that back,
       ``i_k = clip(i_1k + weight / (2 u_k^2), 0, 1)``: one Newton step per AU on ``m`` (the
       Gauss-Newton curvature ``2 u_k^2``) from the L1 optimum, where ``dm/di_k = -weight``.
       For AUs that move different skin this is the unpenalised optimum on the support, so
       table activations at intensities ``i`` read ``i`` back; unlike a joint refit it does
       not re-open the directions in which overlapping AUs trade against each other (which
       sends antagonist pairs back to 1).
    3. **Pruning**: an AU whose removal moves the readout's skin motion by less than
       ``min_motion_mm`` (RMS over the points, the other AUs unchanged) is dropped, the least
       visible first, until every AU reported moves the skin by at least that much.

    The jaw AUs (26, 27, 29, 30) come from the jaw pose as in
    :func:`jaxface.facs.au_intensities`; the cheek puff is AU34.

    Args:
        response: the subject's :class:`~jaxface.fit.reduced.ResponseModel` (mm).
        activations: ``(M,)`` fitted activations in [0, 1], ordered as ``muscle_names``.
        jaw: ``(3,)`` effective jaw pose ``[pitch_deg, yaw_deg, protrusion_mm]``.
        muscle_names: the rig's control names.
        weight: the L1 weight (mm^2 per unit intensity, >= 0; 0 selects every AU that lowers
            the misfit).
        min_motion_mm: the pruning threshold (mm, >= 0; 0 prunes nothing).
        gram: :func:`motion_gram` of ``response`` (computed here if not given; pass it to
            read many fits of one subject).
        cheek_puff: the fitted cheek puff (reported as AU34).

    Returns:
        :class:`AuReadout`.

    Raises:
        RigError: ``activations`` and ``muscle_names`` differ in length.
        ValueError: a negative or non-finite ``weight`` or ``min_motion_mm``.
    """
    w = float(weight)
    tau = float(min_motion_mm)
    for name, v in (("weight", w), ("min_motion_mm", tau)):
        if not (np.isfinite(v) and v >= 0.0):
            raise ValueError(
                f"read_aus: {name} must be a finite number >= 0 (weight in mm^2 per unit "
                f"intensity, min_motion_mm in mm), got {v!r}."
            )
    a = np.asarray(activations, np.float64).ravel()
    aus, inten, rows = au_decomposition(a, muscle_names)
    dt = response.rest.dtype
    G = jnp.asarray(motion_gram(response) if gram is None else gram, dt)
    knots = jnp.asarray(response.levels, dt)
    phi_a = _spline_weights(jnp.asarray(a, dt), knots)
    R = jnp.asarray(rows, dt)
    K = len(aus)
    wj = jnp.asarray(w, dt)

    def fun(x):
        c, _, g = _sparse_cost(G, knots, jnp.asarray(x, dt), R, phi_a, wj)
        return float(c), np.asarray(g, np.float64)

    if K:
        sol = minimize(
            fun,
            np.clip(np.asarray(inten, np.float64), 0.0, 1.0),
            jac=True,
            method="L-BFGS-B",
            bounds=[(0.0, 1.0)] * K,
            # the misfit is mm^2 and small near a good readout: tolerances far below its scale
            options={"maxiter": 1000, "ftol": 1e-14, "gtol": 1e-10},
        )
        lasso = np.clip(sol.x, 0.0, 1.0)
        unit = _unit_motion(G, knots, R, jnp.asarray(lasso, dt))
        u2 = np.maximum(np.asarray(unit, np.float64) ** 2, 1e-30)
        x = np.where(lasso > 1e-4, np.clip(lasso + w / (2.0 * u2), 0.0, 1.0), 0.0)
    else:
        lasso = x = np.zeros(0)

    def dist(x1, x2) -> float:
        return float(_motion_distance(G, knots, R, jnp.asarray(x1, dt), jnp.asarray(x2, dt)))

    def without(x, ks):
        y = x.copy()
        y[ks] = 0.0
        return y

    removal: dict[str, float] = {}
    while np.any(x > 0.0):
        removal = {aus[k]: dist(x, without(x, [k])) for k in np.flatnonzero(x > 0.0)}
        least = min(removal, key=lambda au: removal[au])
        if removal[least] >= tau:
            break
        x = without(x, [aus.index(least)])
        removal = {}
    for base in dict.fromkeys(au[:-1] for au in aus if au[-1] in "LR"):
        sides = [k for k, au in enumerate(aus) if au[:-1] == base and x[k] > 0.0]
        if len(sides) == 2:
            removal[base] = dist(x, without(x, sides))
    _, mis, _ = _sparse_cost(G, knots, jnp.asarray(x, dt), R, phi_a, jnp.asarray(0.0, dt))
    je = np.asarray(jaw, np.float64).ravel()
    pose = JawPose(float(je[0]), float(je[1]), float(je[2]))
    return AuReadout(
        intensities=au_dict(aus, x, pose, cheek_puff),
        misfit_mm=float(np.sqrt(max(float(mis), 0.0))),
        removal_mm=sort_aus(removal),
        lasso=au_dict(aus, lasso, pose, cheek_puff),
        weight=w,
        min_motion_mm=tau,
    )
