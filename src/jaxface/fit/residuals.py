"""Residuals of the inner least-squares problem and the exact-gradient correction.

For ``K`` scan points and ``L`` landmarks, with simulated surface points ``S(y)`` (mm, the
reduced model plus the defect ``d``, then the rigid correction):

* point-to-plane ``sqrt(w_k) n_k . (S_k(y) - q_k)`` (mm; ``w_k`` robust weights summing to 1,
  so the term is a weighted mean in mm^2);
* landmarks ``sqrt(lambda_lm / L) (S_l(y) - q_l)`` (mm);
* sparsity ``sqrt(lambda_s) sin(pi z_i / 2)`` (its square is the L1 prior ``lambda_s a_i``);
* symmetry ``sqrt(lambda_sym) tau tanh((a_L - a_R) / tau)`` (quadratic for small differences,
  at most ``lambda_sym tau^2``);
* ridges on jaw yaw / protrusion and on the rigid correction.

The defect ``d = x_exact(y_k) - x_reduced(y_k)`` makes the residuals those of the exact rig at
the outer iterate ``y_k``; :func:`gradient_correction` adds a rank-one term so that their
gradient there is the exact rig's too.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._arrays import to_jax
from ..errors import FitError
from .options import FitOptions
from .params import Params, activations_from_z, apply_rigid, rotation_from_rotvec_deg
from .reduced import ResponseModel, hermite_parts

__all__ = [
    "PointSet",
    "Priors",
    "Residuals",
    "make_priors",
    "effective_z",
    "point_residuals",
    "data_vector",
    "data_vector_plain",
    "data_residuals",
    "points_from_vertices",
    "gradient_correction",
    "gradient_correction_from_vjp",
    "gradient_correction_from_vjp_jit",
    "model_points",
    "residuals",
    "cost",
    "cost_of_activations",
]


class PointSet(eqx.Module):
    """The data of one inner solve (one scan, fixed correspondences), mm.

    Attributes:
        model: :class:`ResponseModel` gathered at the ``K + L`` surface points (scan
            correspondences first, then landmarks).
        defect: ``(K + L, 3)`` exact-minus-reduced model at those points (mm).
        target: ``(K + L, 3)`` scan points, then landmark targets (mm).
        normal: ``(K, 3)`` unit skin normals at the correspondences.
        w_point: ``(K,)`` weights (sum 1; 0 for padding / rejected).
        w_landmark: ``(L,)`` weights (``lambda_lm / L``; 0 for missing landmarks).
        centre: ``(3,)`` centre of the rigid correction (mm).
        ids, bary: ``(K + L, 3)`` local fit-vertex ids and barycentrics of the points (for
            evaluating the exact rig at them).
        free: ``(M,)`` 1 for a free activation, 0 for one held at a bound (active set).
        z_fixed: ``(M,)`` the parameter of a held activation (0 -> a = 0, 1 -> a = 1).
        grad_u, grad_p: ``(M + 3,)`` the gradient correction (:func:`gradient_correction`):
            the data residuals get ``r_k (grad_u . ([a, jaw] - grad_p))``; None = none.
        grad_r: ``(K + 3 L,)`` ``r_k``, the data residuals at ``grad_p`` (points, then the
            landmarks' x, y, z).
    """

    model: ResponseModel
    defect: jax.Array
    target: jax.Array
    normal: jax.Array
    w_point: jax.Array
    w_landmark: jax.Array
    centre: jax.Array
    ids: jax.Array
    bary: jax.Array
    free: jax.Array
    z_fixed: jax.Array
    grad_u: jax.Array | None = None
    grad_p: jax.Array | None = None
    grad_r: jax.Array | None = None


class Residuals(eqx.Module):
    """The residuals of one inner problem (mm, or sqrt(mm^2) for the priors). The fields are
    in alphabetical order, so the leaves flatten in one fixed order.

    Attributes:
        jaw: ``(2,)`` ridge on jaw yaw and protrusion.
        landmarks: ``(L, 3)`` landmark residuals.
        points: ``(K,)`` point-to-plane residuals.
        rigid: ``(6,)`` ridge on the rigid correction; ``None`` without one.
        sparsity: ``(M,)`` ``sqrt(lambda_s) sin(pi z / 2)``.
        symmetry: ``(S,)`` saturated left/right differences times ``sqrt(lambda_sym)``.
    """

    jaw: jax.Array
    landmarks: jax.Array
    points: jax.Array
    rigid: jax.Array | None
    sparsity: jax.Array
    symmetry: jax.Array


class Priors(eqx.Module):
    """Prior terms (shared by every scan of a batch).

    Attributes:
        left, right: ``(S,)`` indices of the paired ``_L`` / ``_R`` controls.
        sparsity, symmetry, rigid, jaw: weights (mm^2 per unit, see :class:`FitOptions`).
        symmetry_scale: ``tau`` of the saturating symmetry prior (unit activation).
        use_rigid: static, whether ``y`` has a ``"rigid"`` entry.
    """

    left: jax.Array
    right: jax.Array
    sparsity: jax.Array
    symmetry: jax.Array
    rigid: jax.Array
    jaw: jax.Array
    symmetry_scale: jax.Array
    use_rigid: bool = eqx.field(static=True, default=True)


def make_priors(muscle_names: Sequence[str], options: FitOptions) -> Priors:
    """:class:`Priors` for a rig's control names (``name_L`` pairs with ``name_R``)."""
    names = list(muscle_names)
    tau = float(options.symmetry_scale)
    if not (np.isfinite(tau) and tau > 0.0):
        raise ValueError(
            f"FitOptions.symmetry_scale must be a positive number (unit activation), got "
            f"{options.symmetry_scale!r}; use a large value (e.g. 1e3) for the plain "
            "quadratic symmetry prior"
        )
    left, right = [], []
    for i, n in enumerate(names):
        if n.endswith("_L") and n[:-2] + "_R" in names:
            left.append(i)
            right.append(names.index(n[:-2] + "_R"))
    f = lambda v: jnp.asarray(float(v))  # noqa: E731
    return Priors(
        left=to_jax(np.array(left, np.int64)),
        right=to_jax(np.array(right, np.int64)),
        sparsity=f(options.sparsity_weight),
        symmetry=f(options.symmetry_weight),
        rigid=f(options.rigid_weight),
        jaw=f(options.jaw_weight),
        symmetry_scale=f(tau),
        use_rigid=bool(options.rigid),
    )


def effective_z(y: Params, pts: PointSet):
    """``(M,)`` activation parameters with the held ones replaced by their bound."""
    return jnp.where(pts.free > 0, y.z, pts.z_fixed)


def point_residuals(x, pts: PointSet):
    """Weighted point-to-plane ``(K,)`` and landmark ``(L, 3)`` residuals (mm) of the simulated
    surface points ``x`` ``(K + L, 3)`` (rigid correction already applied)."""
    K = pts.normal.shape[0]
    r_pt = jnp.sqrt(pts.w_point) * jnp.sum(pts.normal * (x[:K] - pts.target[:K]), axis=-1)
    r_lm = jnp.sqrt(pts.w_landmark)[:, None] * (x[K:] - pts.target[K:])
    return r_pt, r_lm


def data_vector_plain(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """The data residuals ``(K + 3 L,)`` (points, then the landmarks' x, y, z), mm."""
    x = pts.model(a, jaw) + pts.defect
    if use_rigid:
        x = apply_rigid(rigid, pts.centre, x)
    r_pt, r_lm = point_residuals(x, pts)
    r = jnp.concatenate([r_pt, r_lm.ravel()])
    gu, gp, gr = pts.grad_u, pts.grad_p, pts.grad_r
    if gu is not None and gp is not None and gr is not None:
        r = r + jnp.dot(gu, jnp.concatenate([a, jaw]) - gp) * gr
    return r


def _data_jacobian(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """The data residuals ``r`` ``(K + 3 L,)`` and their Jacobian ``(K + 3 L, M + 3 [+ 6])``
    with respect to ``[a, jaw (, rigid)]``, assembled from the reduced model's own derivative
    fields: the muscles' (:func:`hermite_parts`, one evaluation), the jaw's (3 tangents) and
    the rigid correction's (6 tangents), then projected on the normals once. Pushing every
    tangent through the whole residual instead (plain forward mode) takes 1.4-2.2x as long
    (2.9 ms against 1.3-2.0 ms per Jacobian on the shared subjects' rigs, ``bench_fit.py``'s
    ``timing.jacobian``)."""
    model = pts.model
    val, D = hermite_parts(a, model.levels, model.mus, model.mus_slope)  # (P, 3), (M, P, 3)
    xj = model.jaw_displacement(jaw)
    Jj = jax.jacfwd(model.jaw_displacement)(jaw)  # (P, 3, 3)
    x = model.rest + val + xj + pts.defect
    dx = jnp.concatenate([jnp.moveaxis(D, 0, 2), Jj], axis=2)  # (P, 3, M + 3)
    if use_rigid:
        R = rotation_from_rotvec_deg(rigid[:3])
        Jr = jax.jacfwd(lambda w: apply_rigid(w, pts.centre, x))(rigid)  # (P, 3, 6)
        x = apply_rigid(rigid, pts.centre, x)
        dx = jnp.concatenate([jnp.einsum("ij,pjn->pin", R, dx), Jr], axis=2)
    K = pts.normal.shape[0]
    r_pt, r_lm = point_residuals(x, pts)
    J_pt = jnp.sqrt(pts.w_point)[:, None] * jnp.einsum("kd,kdn->kn", pts.normal, dx[:K])
    J_lm = (jnp.sqrt(pts.w_landmark)[:, None, None] * dx[K:]).reshape(-1, dx.shape[2])
    r = jnp.concatenate([r_pt, r_lm.ravel()])
    J = jnp.concatenate([J_pt, J_lm])
    gu, gp, gr = pts.grad_u, pts.grad_p, pts.grad_r
    if gu is not None and gp is not None and gr is not None:
        M3 = gu.shape[0]
        r = r + jnp.dot(gu, jnp.concatenate([a, jaw]) - gp) * gr
        J = J.at[:, :M3].add(gr[:, None] * gu[None, :])
    return r, J


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def data_vector(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """:func:`data_vector_plain` with a forward-mode rule that applies the Jacobian of
    :func:`_data_jacobian` (the inner solves' Levenberg-Marquardt Jacobians and the KKT
    gradients go through it; derivatives with respect to ``pts`` fall back to plain autodiff)."""
    return data_vector_plain(a, jaw, rigid, pts, use_rigid)


def _data_vector_jvp(use_rigid, primals, tangents):
    a, jaw, rigid, pts = primals
    da, djaw, drigid, dpts = tangents
    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    inst = lambda p, t: jnp.zeros_like(p) if zero(t) else t  # noqa: E731
    if not all(zero(t) for t in jax.tree_util.tree_leaves(dpts, is_leaf=zero)):
        # plain forward mode in the perturbed leaves only: the others stay constants (a zero
        # tangent pushed through sqrt(w) at a zero weight would give NaN)
        leaves, tree = jax.tree_util.tree_flatten(primals)
        tans = tree.flatten_up_to(tangents)
        moving = [i for i, t in enumerate(tans) if not zero(t)]

        def plain(*sub):
            full = list(leaves)
            for i, v in zip(moving, sub):
                full[i] = v
            a_, jaw_, rigid_, pts_ = jax.tree_util.tree_unflatten(tree, full)
            return data_vector_plain(a_, jaw_, rigid_, pts_, use_rigid)

        return jax.jvp(plain, [leaves[i] for i in moving], [tans[i] for i in moving])
    r, J = _data_jacobian(a, jaw, rigid, pts, use_rigid)
    parts = [inst(a, da), inst(jaw, djaw)] + ([inst(rigid, drigid)] if use_rigid else [])
    return r, J @ jnp.concatenate(parts)


data_vector.defjvp(_data_vector_jvp, symbolic_zeros=True)


def data_residuals(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """Point-to-plane ``(K,)`` and landmark ``(L, 3)`` residuals (mm) of the reduced model with
    the defect and gradient corrections, after the rigid correction."""
    r = data_vector(a, jaw, rigid, pts, use_rigid)
    K = pts.normal.shape[0]
    return r[:K], r[K:].reshape(-1, 3)


def gradient_correction(exact_fn, fit_ids, y, pts: PointSet, use_rigid: bool):
    """Rank-one correction that gives the inner problem the exact rig's gradient at ``y``.

    Defect correction makes the inner residuals those of the exact rig at the current
    iterate, but their Jacobian stays the reduced model's. Where the reduced model is not
    additive enough (muscles interacting with each other and with the jaw: up to several mm
    on the default head), the outer loop can settle where the *reduced* gradient of the exact
    residuals vanishes while the exact gradient does not: a spurious fit. With
    ``g = J^T r`` over the data residuals ``r_k`` at ``p_k = [a, jaw]`` for the exact rig
    (one reverse-mode pass through it) and the reduced model, the data residuals get
    ``r_k (u . (p - p_k))`` with ``u = (g_exact - g_reduced) / |r_k|^2``: the corrected
    Jacobian ``J + r_k u^T`` has ``(J + r_k u^T)^T r_k = g_exact``. At a fixed point of the
    outer loop the exact gradient of the data term then vanishes.

    Args:
        exact_fn: the exact rig, ``(a (M,), jaw (3,)) -> (V, 3)`` mm.
        fit_ids: ``(P,)`` fit vertices of the rig skin.
        y: parameters at which to correct; pts: its :class:`PointSet` (with the defect
            of ``y``); use_rigid: whether ``y`` has a rigid correction.

    Returns:
        ``(u (M + 3,), p_k (M + 3,), r_k (K + 3 L,))``; ``u = 0`` (no correction) where the
        reverse pass is not finite.
    """
    a = activations_from_z(effective_z(y, pts))
    skin, skin_vjp = jax.vjp(exact_fn, a, y.jaw)
    return gradient_correction_from_vjp(skin, skin_vjp, fit_ids, y, pts, use_rigid)


def gradient_correction_from_vjp(skin, skin_vjp, fit_ids, y, pts: PointSet, use_rigid: bool):
    """:func:`gradient_correction` from a forward pass already made
    (:func:`jaxface.fit.forward.exact_skin_and_vjp` at ``y``'s effective activations and jaw): ``skin`` ``(V, 3)``
    mm and its VJP. Same returns."""
    a = activations_from_z(effective_z(y, pts))
    p0 = jnp.concatenate([a, y.jaw])

    def data_of_points(x):
        if use_rigid:
            x = apply_rigid(y.rigid, pts.centre, x)
        r_pt, r_lm = point_residuals(x, pts)
        return jnp.concatenate([r_pt, r_lm.ravel()])

    def reduced(p):
        return data_of_points(pts.model(p[: a.shape[0]], p[a.shape[0] :]) + pts.defect)

    r, vjp_x = jax.vjp(lambda xv: data_of_points(points_from_vertices(xv[fit_ids], pts)), skin)
    _, vjp_r = jax.vjp(reduced, p0)
    (ct,) = vjp_x(r)
    g_a, g_j = skin_vjp(ct)
    g_e = jnp.concatenate([g_a, g_j])
    (g_r,) = vjp_r(r)
    rr = jnp.sum(r * r)
    # no correction where the reverse pass through the rig is not finite (seen once, in
    # float32 at a wide jaw opening): the inner solve then has the reduced gradient
    ok = (rr > 1e-20) & jnp.all(jnp.isfinite(g_e)) & jnp.all(jnp.isfinite(r))
    u = jnp.where(ok, (g_e - g_r) / jnp.where(ok, rr, 1.0), 0.0)
    return u, p0, jnp.where(ok, r, 0.0)


#: :func:`gradient_correction_from_vjp`, compiled.
gradient_correction_from_vjp_jit = eqx.filter_jit(gradient_correction_from_vjp)


def model_points(y, pts: PointSet, use_rigid: bool):
    """``(K + L, 3)`` simulated points (mm, neutral-scan frame) for parameters ``y``."""
    a = activations_from_z(effective_z(y, pts))
    x = pts.model(a, y.jaw) + pts.defect
    if use_rigid:
        x = apply_rigid(y.rigid, pts.centre, x)
    return x


def _symmetry_gap(a, pri: Priors):
    """``(S,)`` saturated left/right differences ``tau tanh((a_L - a_R) / tau)`` (unit
    activation): ``a_L - a_R`` while small, at most ``tau`` in size."""
    tau = pri.symmetry_scale
    return tau * jnp.tanh((a[pri.left] - a[pri.right]) / tau)


def residuals(y: Params, args) -> Residuals:
    """The residuals of the inner problem (see the module doc); ``args = (PointSet,
    Priors)``. All terms in mm (or sqrt(mm^2) for the priors)."""
    pts, pri = args
    z = effective_z(y, pts)
    a = activations_from_z(z)
    r_pt, r_lm = data_residuals(a, y.jaw, y.rigid, pts, pri.use_rigid)
    r_sp = jnp.sqrt(pri.sparsity) * jnp.sin(0.5 * jnp.pi * z)  # r^2 = lambda a
    r_sym = jnp.sqrt(pri.symmetry) * _symmetry_gap(a, pri)
    r_jaw = jnp.sqrt(pri.jaw) * y.jaw[1:]
    r_rigid = None
    if pri.use_rigid:
        if y.rigid is None:
            raise FitError(
                "the priors include the rigid correction (FitOptions.rigid) but the parameters "
                "have none; make both with the same options."
            )
        r_rigid = jnp.sqrt(pri.rigid) * y.rigid
    return Residuals(
        jaw=r_jaw,
        landmarks=r_lm,
        points=r_pt,
        rigid=r_rigid,
        sparsity=r_sp,
        symmetry=r_sym,
    )


def cost(y: Params, args):
    """The inner cost ``sum r^2`` over every residual (mm^2); ``args`` as :func:`residuals`."""
    r = residuals(y, args)
    return sum(jnp.sum(v * v) for v in jax.tree_util.tree_leaves(r))


def cost_of_activations(a, y, pts: PointSet, pri: Priors):
    """The inner cost as a function of the activations themselves (mm^2); its gradient
    is the KKT test of the bounds."""
    r_pt, r_lm = data_residuals(a, y.jaw, y.rigid, pts, pri.use_rigid)
    c = jnp.sum(r_pt**2) + jnp.sum(r_lm**2)
    c = c + pri.sparsity * jnp.sum(a) + pri.symmetry * jnp.sum(_symmetry_gap(a, pri) ** 2)
    return c


def points_from_vertices(xv, pts: PointSet):
    """``(K + L, 3)`` surface points (mm) of fit-vertex positions ``xv`` ``(P, 3)``."""
    return jnp.einsum("kc,kcd->kd", pts.bary, xv[pts.ids])
