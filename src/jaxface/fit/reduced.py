"""The reduced response model of a rig: cubic Hermite tables of its syntheses, mm.

``x(a, jaw) = rest + J(jaw) + sum_i H_i(a_i)``: per muscle ``i`` the displacement field at
activation knots ``0, 1/L, ..., 1`` (jaw closed), interpolated by a cubic Hermite spline
``H_i`` in the activation; for the jaw, fields at pitch knots over the whole range with first
and second derivatives in yaw and protrusion, interpolated in pitch. The contributions add.
An evaluation costs microseconds instead of a synthesis, and its forward-mode Jacobian has a
custom rule (:func:`hermite_sum`): about one evaluation plus a small matrix product.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._arrays import to_jax
from ..anatomy.jaw import JawPose, smooth_clamp
from ..errors import FitError
from .forward import ForwardModel

__all__ = [
    "hermite_basis",
    "hermite_parts",
    "hermite_sum",
    "hermite_slopes",
    "ResponseModel",
    "build_response_model",
    "gather_jit",
    "evaluate_jit",
    "landmark_pitch",
]


def hermite_basis(x, knots):
    """Segment ``s`` ``(M,)`` of every abscissa ``x`` ``(M,)`` among the ``knots`` ``(N,)``,
    and the weights ``w`` / their ``x``-derivatives ``dw`` ``(M, 4)`` of the values at knots
    ``s`` and ``s + 1`` and the slopes there (cubic Hermite; linear continuation with the end
    slope beyond the knot range)."""
    t = knots
    n = t.shape[0]
    xc = jnp.clip(x, t[0], t[-1])
    s = jnp.clip(jnp.searchsorted(t, xc, side="right") - 1, 0, n - 2)  # (M,)
    h = t[s + 1] - t[s]
    u = (xc - t[s]) / h
    u2, u3 = u * u, u * u * u
    below = (x < t[0]).astype(x.dtype)
    above = (x > t[-1]).astype(x.dtype)
    inside = 1.0 - below - above
    e = x - xc  # linear continuation beyond the ends
    w = jnp.stack(
        [
            2 * u3 - 3 * u2 + 1,
            -2 * u3 + 3 * u2,
            (u3 - 2 * u2 + u) * h + e * below,
            (u3 - u2) * h + e * above,
        ],
        axis=1,
    )
    dw = jnp.stack(
        [
            (6 * u2 - 6 * u) / h * inside,
            (-6 * u2 + 6 * u) / h * inside,
            (3 * u2 - 4 * u + 1) * inside + below,
            (3 * u2 - 2 * u) * inside + above,
        ],
        axis=1,
    )
    return s, w, dw


def hermite_parts(x, knots, values, slopes):
    """Value ``(K, 3)`` of ``sum_m H_m(x_m)`` and the derivative fields ``dH_m/dx_m``
    ``(M, K, 3)`` (see :func:`hermite_sum`)."""
    s, w, dw = hermite_basis(x, knots)
    idx = s[:, None, None, None]
    Y0 = jnp.take_along_axis(values, idx, axis=1)[:, 0]
    Y1 = jnp.take_along_axis(values, idx + 1, axis=1)[:, 0]
    m0 = jnp.take_along_axis(slopes, idx, axis=1)[:, 0]
    m1 = jnp.take_along_axis(slopes, idx + 1, axis=1)[:, 0]
    val = (
        jnp.einsum("m,mkd->kd", w[:, 0], Y0)
        + jnp.einsum("m,mkd->kd", w[:, 1], Y1)
        + jnp.einsum("m,mkd->kd", w[:, 2], m0)
        + jnp.einsum("m,mkd->kd", w[:, 3], m1)
    )
    D = (
        dw[:, 0, None, None] * Y0
        + dw[:, 1, None, None] * Y1
        + dw[:, 2, None, None] * m0
        + dw[:, 3, None, None] * m1
    )
    return val, D


@jax.custom_jvp
def hermite_sum(x, knots, values, slopes):
    """``sum_m H_m(x_m)``: cubic Hermite splines, one per row, summed.

    Arguments:
        x: ``(M,)`` abscissae (one per spline).
        knots: ``(N,)`` increasing knots shared by the splines.
        values, slopes: ``(M, N, K, 3)`` values and slopes at the knots.

    Returns:
        ``(K, 3)``. Beyond the knot range each spline continues linearly with its end slope.

    The forward-mode derivative has a custom rule: with respect to ``x`` it is
    ``sum_m dx_m dH_m/dx_m``, whose fields are computed once per evaluation, so a
    ``jax.jacfwd`` over ``T`` tangents costs one evaluation plus a ``(T, M) x (M, 3K)``
    product instead of ``T`` evaluations (the fitter's Jacobian). Tangents of the tables
    fall back to plain autodiff.
    """
    return hermite_parts(x, knots, values, slopes)[0]


def _hermite_sum_jvp(primals, tangents):
    x, knots, values, slopes = primals
    dx, dk, dv, ds = tangents
    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    if not (zero(dk) and zero(dv) and zero(ds)):
        inst = [jnp.zeros_like(p) if zero(t) else t for p, t in zip(primals, tangents)]
        return jax.jvp(lambda *a: hermite_parts(*a)[0], primals, tuple(inst))
    val, D = hermite_parts(x, knots, values, slopes)
    if zero(dx):
        return val, jnp.zeros_like(val)
    return val, jnp.einsum("m,mkd->kd", dx, D)


hermite_sum.defjvp(_hermite_sum_jvp, symbolic_zeros=True)


def hermite_slopes(knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Three-point slopes of ``values`` ``(N, ...)`` at non-uniform ``knots`` ``(N,)``."""
    t = np.asarray(knots, np.float64)
    y = np.asarray(values, np.float64)
    n = len(t)
    m = np.zeros_like(y)
    h = np.diff(t)
    d = np.diff(y, axis=0) / h.reshape((-1,) + (1,) * (y.ndim - 1))
    if n == 2:
        m[:] = d[0]
        return m
    for k in range(1, n - 1):
        a, b = h[k - 1], h[k]
        m[k] = (b * d[k - 1] + a * d[k]) / (a + b)
    m[0] = 2 * d[0] - m[1]
    m[-1] = 2 * d[-1] - m[-2]
    return m


class ResponseModel(eqx.Module):
    """Reduced model of a rig over ``P`` points (vertices, or surface points after
    :meth:`gather`), mm.

    ``x(a, jaw) = rest + J(jaw) + sum_i H_i(a_i)`` with ``H_i`` the Hermite interpolant of
    muscle ``i``'s displacement at the activation knots (jaw closed) and
    ``J = X(p) + y Dy(p) + y^2/2 Dyy(p) + q Dq(p) + q^2/2 Dqq(p)`` for the clamped pitch
    ``p`` (deg), yaw ``y`` (deg) and protrusion ``q`` (mm), each field interpolated in ``p``.

    Attributes:
        rest: ``(P, 3)`` mm.
        levels: ``(NL,)`` activation knots (``levels[0] = 0``).
        mus, mus_slope: ``(M, NL, P, 3)`` displacements (mm) and their activation slopes.
        pitch: ``(NJ,)`` pitch knots (deg, effective = after the jaw's smooth clamp).
        jaw_tab, jaw_slope: ``(NJ, 5, P, 3)`` fields ``[X, Dy, Dyy, Dq, Dqq]`` (mm, mm/deg,
            mm/deg^2, mm/mm, mm/mm^2) and their pitch slopes.
        jaw: the rig's :class:`~jaxface.anatomy.jaw.JawModel` (for the smooth clamp).
        sampled: static ``(M,)`` bools: controls whose tables were sampled (the others are
            zero and must stay at activation 0).
    """

    rest: jax.Array
    levels: jax.Array
    mus: jax.Array
    mus_slope: jax.Array
    pitch: jax.Array
    jaw_tab: jax.Array
    jaw_slope: jax.Array
    jaw: Any
    sampled: tuple = eqx.field(static=True, default=())

    @property
    def n_points(self) -> int:
        return int(self.rest.shape[0])

    def clamp_jaw(self, jaw):
        """Effective ``(3,)`` jaw pose after the rig's smooth limits."""
        p = self.jaw.clamp(JawPose.from_array(jaw))
        return jnp.stack([p.pitch_deg, p.yaw_deg, p.protrusion_mm])

    def displacement(self, a, jaw):
        """``(P, 3)`` displacement from rest, mm, for ``a`` ``(M,)`` in [0, 1] and ``jaw``
        ``(3,)`` (forward-mode derivatives through :func:`hermite_sum`'s custom rule)."""
        return hermite_sum(a, self.levels, self.mus, self.mus_slope) + self.jaw_displacement(jaw)

    def jaw_displacement(self, jaw):
        """``(P, 3)`` the jaw's part of :meth:`displacement`, mm (``jaw`` ``(3,)``: pitch
        deg, yaw deg, protrusion mm, before the smooth clamp)."""
        j = self.clamp_jaw(jaw)
        nj, nf, P = self.jaw_tab.shape[:3]
        F = hermite_sum(
            j[:1],
            self.pitch,
            self.jaw_tab.reshape(1, nj, nf * P, 3),
            self.jaw_slope.reshape(1, nj, nf * P, 3),
        ).reshape(nf, P, 3)
        y, q = j[1], j[2]
        return F[0] + y * F[1] + (0.5 * y * y) * F[2] + q * F[3] + (0.5 * q * q) * F[4]

    def __call__(self, a, jaw):
        """``(P, 3)`` positions, mm."""
        return self.rest + self.displacement(a, jaw)

    def muscle_terms(self, muscles, values):
        """``(T, P, 3)``: term ``t`` is muscle ``muscles[t]``'s own displacement at activation
        ``values[t]`` less its displacement at activation 0, mm (the model is additive, so a
        displacement is a sum of such terms; :func:`jaxface.fit.au_motion.au_skin_motion` evaluates
        only the few terms each AU has instead of every muscle's).

        Arguments:
            muscles: ``(T,)`` control indices; values: ``(T,)`` activations.
        """
        s, w, _ = hermite_basis(values, self.levels)
        s0, w0, _ = hermite_basis(jnp.zeros_like(values), self.levels)

        def spline(seg, wt):
            return (
                wt[:, 0, None, None] * self.mus[muscles, seg]
                + wt[:, 1, None, None] * self.mus[muscles, seg + 1]
                + wt[:, 2, None, None] * self.mus_slope[muscles, seg]
                + wt[:, 3, None, None] * self.mus_slope[muscles, seg + 1]
            )

        return spline(s, w) - spline(s0, w0)

    def gather(self, ids, bary) -> ResponseModel:
        """The model at surface points: ``ids`` ``(K, 3)`` local point ids of triangle
        corners, ``bary`` ``(K, 3)`` barycentrics. Returns a :class:`ResponseModel` over
        the ``K`` points."""
        ids = to_jax(ids)
        b = jnp.asarray(bary, self.rest.dtype)

        def g(arr, axis):
            taken = jnp.take(arr, ids, axis=axis)  # (..., K, 3, 3)
            return jnp.einsum("...kcd,kc->...kd", taken, b)

        return ResponseModel(
            rest=g(self.rest, 0),
            levels=self.levels,
            mus=g(self.mus, 2),
            mus_slope=g(self.mus_slope, 2),
            pitch=self.pitch,
            jaw_tab=g(self.jaw_tab, 2),
            jaw_slope=g(self.jaw_slope, 2),
            jaw=self.jaw,
            sampled=self.sampled,
        )


#: :meth:`ResponseModel.gather`, compiled (once per point count).
gather_jit = eqx.filter_jit(lambda m, ids, bary: m.gather(ids, bary))
#: :meth:`ResponseModel.__call__`, compiled.
evaluate_jit = eqx.filter_jit(lambda m, a, j: m(a, j))


def build_response_model(
    forward: ForwardModel,
    point_ids=None,
    *,
    levels: int = 4,
    pitch_knots: int = 12,
    yaw_step_deg: float = 2.5,
    protrusion_step_mm: float = 2.0,
    controls: Sequence[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ResponseModel:
    """Sample the rig and build its :class:`ResponseModel` over ``point_ids`` (vertex ids,
    default all vertices).

    Syntheses: ``M * levels`` (each muscle alone at ``1/levels, ..., 1``, jaw closed) plus
    ``5 * pitch_knots`` (pitch knots over the jaw's limits; at each, yaw ``+-h`` and
    protrusion ``h, 2h``).

    Arguments:
        forward: the :class:`ForwardModel` of the rig.
        point_ids: ``(P,)`` vertex ids to keep (default all).
        levels: activation knots above 0.
        pitch_knots: number of pitch knots (over the jaw's pitch limits).
        yaw_step_deg, protrusion_step_mm: finite-difference steps.
        controls: only sample these controls (names; default all); the others get zero
            tables and must stay at 0 (:attr:`ResponseModel.sampled`, ``FitOptions.controls``).
        progress: called as ``progress(done, total)`` after each batch of syntheses.

    Raises:
        FitError: a synthesis produced NaN/inf.
    """
    rig = forward.rig
    M = forward.n_controls
    rest_all = forward.rest
    ids = np.arange(len(rest_all)) if point_ids is None else np.asarray(point_ids, np.int64)
    lv = np.linspace(0.0, 1.0, int(levels) + 1)
    jm = rig.jaw
    plo, phi = jm.pitch_limits
    raw_p = np.linspace(plo - 1.0, phi + 1.0, int(pitch_knots))  # clamped: just inside the limits
    eff_p = np.asarray(smooth_clamp(to_jax(raw_p), plo, phi, jm.softness_deg))
    hy, hq = float(yaw_step_deg), float(protrusion_step_mm)
    names = list(forward.muscle_names)
    if controls is None:
        sampled = list(range(M))
    else:
        unknown = [c for c in controls if c not in names]
        if unknown:
            raise FitError(f"unknown controls {unknown}; the rig's controls are {names}.")
        sampled = sorted(names.index(c) for c in controls)
    A, J = [], []
    for i in sampled:
        for v in lv[1:]:
            a = np.zeros(M)
            a[i] = v
            A.append(a)
            J.append(np.zeros(3))
    jaw_offsets = [(0.0, 0.0), (hy, 0.0), (-hy, 0.0), (0.0, hq), (0.0, 2 * hq)]
    for p in raw_p:
        for y, q in jaw_offsets:
            A.append(np.zeros(M))
            J.append(np.array([p, y, q]))
    A = np.stack(A)
    J = np.stack(J)
    total = len(A)
    out = np.zeros((total, len(ids), 3))
    step = max(forward.chunk, 1)
    for s in range(0, total, step):
        x = forward.many(A[s : s + step], J[s : s + step])
        out[s : s + len(x)] = x[:, ids]
        if progress is not None:
            progress(min(s + step, total), total)
    if not np.all(np.isfinite(out)):
        bad = np.flatnonzero(~np.isfinite(out).all(axis=(1, 2)))
        raise FitError(
            f"the rig produced NaN/inf in {bad.size} of {total} syntheses (first rows "
            f"{bad[:5].tolist()}); the reduced model cannot be built."
        )
    rest = rest_all[ids]
    nl = len(lv)
    mus = np.zeros((M, nl, len(ids), 3))
    ns = len(sampled)
    mus[sampled, 1:] = out[: ns * levels].reshape(ns, levels, len(ids), 3) - rest
    mus_slope = np.stack([hermite_slopes(lv, mus[i]) for i in range(M)])
    jt = out[ns * levels :].reshape(len(raw_p), len(jaw_offsets), len(ids), 3)
    f0, fyp, fym, fq1, fq2 = (jt[:, k] for k in range(5))
    tab = np.stack(
        [
            f0 - rest,
            (fyp - fym) / (2 * hy),
            (fyp - 2 * f0 + fym) / hy**2,
            (-3 * f0 + 4 * fq1 - fq2) / (2 * hq),
            (f0 - 2 * fq1 + fq2) / hq**2,
        ],
        axis=1,
    )
    tab_slope = hermite_slopes(eff_p, tab)
    return ResponseModel(
        rest=to_jax(rest),
        levels=to_jax(lv),
        mus=to_jax(mus),
        mus_slope=to_jax(mus_slope),
        pitch=to_jax(eff_p),
        jaw_tab=to_jax(tab),
        jaw_slope=to_jax(tab_slope),
        jaw=jm,
        sampled=tuple(bool(i in set(sampled)) for i in range(M)),
    )


def landmark_pitch(response: ResponseModel, lm_loc, lm_bary, landmarks, landmark_valid) -> float:
    """Jaw pitch (deg, 1-degree grid over the limits) whose reduced-model landmarks at
    activations 0 best match the scan's landmark targets (least squares).

    Arguments:
        response: the reduced model over the fit vertices.
        lm_loc, lm_bary: ``(L, 3)`` local corner ids and barycentrics of the landmarks.
        landmarks: ``(L, 3)`` targets (mm); landmark_valid: ``(L,)`` bools.

    Returns 0 with fewer than 3 valid landmarks."""
    valid = np.asarray(landmark_valid, bool)
    if valid.sum() < 3:
        return 0.0
    gm = gather_jit(response, to_jax(lm_loc), to_jax(lm_bary))
    lo, hi = response.jaw.pitch_limits
    grid = np.arange(np.ceil(lo), np.floor(hi) + 1.0, 1.0)
    M = response.mus.shape[0]
    X = np.asarray(_pitch_sweep(gm, to_jax(grid), M))  # (G, L, 3)
    tgt = np.asarray(landmarks, np.float64)
    err = np.sum(((X - tgt[None]) ** 2).sum(-1)[:, valid], axis=1)
    return float(grid[int(np.argmin(err))])


@eqx.filter_jit
def _pitch_sweep(model: ResponseModel, pitches, M: int):
    z = jnp.zeros(M, pitches.dtype)
    return jax.vmap(lambda p: model(z, jnp.stack([p, 0.0 * p, 0.0 * p])))(pitches)
