"""AU motion readout: how much of a fitted expression's skin motion each action unit accounts
for, in mm.

:func:`jaxface.facs.au_intensities` reads AU intensities out of the fitted activations: how hard
the muscles of each AU work, in [0, 1]. That is not how strongly an AU shows. A small muscle
(mentalis, depressor labii inferioris, buccinator) reaches activation 1 while it moves the skin
a millimetre, and a large one (zygomaticus major) at 0.6 moves the mouth corner 10 mm. On the
Bosphorus-style smiles the fit saturates several small muscles at 1 while most of the motion is
the zygomaticus major's, so AU12 ranks 6th-8th by intensity. FACS coders score intensity by the
visible change, and this readout follows them:

* the activations are split into AU shares by :func:`jaxface.facs.au_decomposition` (the same
  non-negative least squares the intensities come from): AU ``k``'s share is
  ``intensity_k * row_k``;
* the jaw pose is split like the intensities: the opening up to AU26's 10 degrees is AU26, the
  rest AU27; positive protrusion is AU29; yaw is AU30L (toward the subject's left, +) or
  AU30R;
* each share is applied *alone* to the subject's reduced model
  (:class:`jaxface.fit.reduced.ResponseModel`, the model the fit solves with) and the RMS skin
  displacement over its points (the face region, mm) is that AU's motion. A bilateral AU
  (``AU12``) is both sides' shares together, its sides (``AU12L``, ``AU12R``) each alone.

The numbers do not add up to the whole motion (the reduced model is additive in the muscles
and the jaw, but the RMS of a sum is not the sum of the RMSs): they rank the AUs by their
visible effect; they are not a decomposition of the motion's variance.

:func:`au_sparse` reads intensities out of the motion instead of the activations: the
sparsest AU intensities whose table activations reproduce the fit's skin motion. Many
activation vectors give nearly the same skin (an antagonist pair both at 1 cancels on the
eyelid), so the fit's own activations are one arbitrary choice among them, and the table's
inverse of that choice (:func:`jaxface.facs.au_intensities`) inherits it. Asking which few AUs
explain the *motion* removes that freedom, as FACS coders code the fewest AUs that account for
what they see.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize

from ..anatomy.jaw import JawPose
from ..facs import AU_JAW, au_decomposition, au_dict, sort_aus
from .options import AU_SPARSE_WEIGHT
from .reduced import ResponseModel, hermite_basis

__all__ = ["au_skin_motion", "au_sparse", "motion_gram", "AU_SPARSE_WEIGHT"]


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
    """Gram matrix of a reduced model's coefficient fields, for :func:`au_sparse`.

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


@jax.jit
def _sparse_cost(G, knots, i, rows, phi_a, weight):
    """Cost of :func:`au_sparse` at intensities ``i`` ``(K,)``: ``(cost, mean squared misfit
    mm^2, d cost / d i)``. ``rows`` ``(K, M)`` the AU table rows, ``phi_a`` the spline
    weights of the fitted activations (the rest state's weights cancel in the difference)."""

    def f(i):
        act = jnp.clip(i @ rows, 0.0, 1.0)
        d = _spline_weights(act, knots) - phi_a
        mis = d @ (G @ d)
        return mis + weight * jnp.sum(i), mis

    (c, mis), g = jax.value_and_grad(f, has_aux=True)(i)
    return c, mis, g


def au_sparse(
    response,
    activations,
    jaw,
    muscle_names: Sequence[str],
    *,
    weight: float = AU_SPARSE_WEIGHT,
    gram=None,
) -> tuple[dict[str, float], float]:
    """AU intensities of the sparsest AU combination that reproduces a fit's skin motion.

    Solves, over the unilateral AU intensities ``i`` of the table (:func:`jaxface.facs.au_decomposition`'s
    AUs and rows ``A``),

    ``min_{0 <= i <= 1}  mean_p |D(A^T i)_p - D(a)_p|^2 + weight * sum_k i_k``

    where ``D(a)`` ``(P, 3)`` is the reduced model's skin displacement (mm, muscles only, jaw at
    rest) over its points and ``a`` the fitted activations (L-BFGS-B from the table's
    non-negative least-squares intensities). The L1 term keeps an AU only where it accounts for
    more than ``weight`` mm^2 of the mean squared motion per unit intensity: an antagonist pair
    the fit holds at 1 against each other, whose net motion is small, drops out, and where two
    AUs move the same skin the one that does it with less intensity stays. The jaw AUs (26,
    27, 29, 30) come from the jaw pose as in :func:`jaxface.facs.au_intensities`.

    Args:
        response: the subject's :class:`~jaxface.fit.reduced.ResponseModel` (mm).
        activations: ``(M,)`` fitted activations in [0, 1], ordered as ``muscle_names``.
        jaw: ``(3,)`` effective jaw pose ``[pitch_deg, yaw_deg, protrusion_mm]``.
        muscle_names: the rig's control names.
        weight: the L1 weight (mm^2 per unit intensity, >= 0; 0 gives the plain bounded least
            squares in motion space).
        gram: :func:`motion_gram` of ``response`` (computed here if not given; pass it to
            read many fits of one subject: 0.24 s on bs901's 4,887-point model, a readout then
            0.08 s on the 2-core CPU).

    Returns:
        ``({AU: intensity}, misfit_mm)``: the intensities in [0, 1] (bilateral AUs the mean of
        their sides, the sides as ``AUxxL`` / ``AUxxR``, sorted by AU number) and the RMS
        distance (mm) between the motion they produce and the fit's.

    Raises:
        RigError: ``activations`` and ``muscle_names`` differ in length.
        ValueError: a negative or non-finite ``weight``.
    """
    w = float(weight)
    if not (np.isfinite(w) and w >= 0.0):
        raise ValueError(
            f"au_sparse: weight must be a finite number >= 0 (mm^2 per unit intensity), got {weight!r}."
        )
    a = np.asarray(activations, np.float64).ravel()
    aus, inten, rows = au_decomposition(a, muscle_names)
    dt = response.rest.dtype
    G = jnp.asarray(motion_gram(response) if gram is None else gram, dt)
    knots = jnp.asarray(response.levels, dt)
    phi_a = _spline_weights(jnp.asarray(a, dt), knots)
    R = jnp.asarray(rows, dt)
    wj = jnp.asarray(w, dt)

    def fun(x):
        c, _, g = _sparse_cost(G, knots, jnp.asarray(x, dt), R, phi_a, wj)
        return float(c), np.asarray(g, np.float64)

    if len(inten):
        sol = minimize(
            fun,
            np.asarray(inten, np.float64),
            jac=True,
            method="L-BFGS-B",
            bounds=[(0.0, 1.0)] * len(inten),
            options={"maxiter": 500},
        )
        x = np.clip(sol.x, 0.0, 1.0)
    else:
        x = np.zeros(0)
    _, mis, _ = _sparse_cost(G, knots, jnp.asarray(x, dt), R, phi_a, wj)
    je = np.asarray(jaw, np.float64).ravel()
    out = au_dict(aus, x, JawPose(float(je[0]), float(je[1]), float(je[2])))
    return out, float(np.sqrt(max(float(mis), 0.0)))
