"""Tissue forces of the Lee-Terzopoulos-Waters model (pure JAX, jit/vmap/grad/jvp-able).

Units: positions in mm; forces in the paper's model units (stiffness = force per mm).
Sign convention: every function returns the force *acting on* the nodes (what enters
``m a = f``), i.e. the paper's left-hand-side terms of its equation of motion already negated
(the notes' sign fix for the spring term, sec. 2.4 of the notes).

All gathers/scatters are vectorised (``jax.ops.segment_sum``); lengths and normals are
guarded so that zero-length springs and zero-area triangles give finite values and gradients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .tissue import LTWParams, LTWTissue

__all__ = [
    "safe_length",
    "smoothstep",
    "kinematic_positions",
    "spring_forces",
    "prism_volume",
    "element_volumes",
    "volume_forces",
    "restoration_forces",
    "skull_frame",
    "skull_gate",
    "remove_inward",
    "internal_forces",
    "preconditioner",
]


def safe_length(d: jax.Array) -> jax.Array:
    """``|d|`` over the last axis with a zero (not NaN) gradient at ``d = 0``; mm."""
    n2 = jnp.sum(d * d, axis=-1)
    ok = n2 > jnp.finfo(d.dtype).tiny
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def smoothstep(t: jax.Array) -> jax.Array:
    """C1 step: 0 for t <= 0, ``3t^2 - 2t^3`` on [0, 1], 1 for t >= 1 (dimensionless)."""
    t = jnp.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _rigid(points: jax.Array, weight: jax.Array, R: jax.Array, t: jax.Array) -> jax.Array:
    """``p + w (R p + t - p)``: the jaw motion applied with per-point weight ``w``."""
    moved = points @ R.T + t
    return points + weight[:, None] * (moved - points)


def kinematic_positions(tissue: LTWTissue, R: jax.Array, t: jax.Array, *, smooth: bool = False):
    """Rest node positions moved by the jaw, ``(N, 3)`` mm.

    Args:
        tissue: the tissue.
        R: ``(3, 3)`` mandible rotation; t: ``(3,)`` mandible translation, mm.
        smooth: use the smooth initial-guess weights instead of the rigid mandible mask.
    """
    w = tissue.init_weight if smooth else tissue.jaw_weight
    return _rigid(tissue.rest, w.astype(tissue.rest.dtype), R, t)


def spring_forces(x: jax.Array, tissue: LTWTissue, params: LTWParams) -> jax.Array:
    """Spring forces on all nodes, ``(N, 3)``.

    The force of spring (i, j) on node i is ``F(l) s``, ``s = (x_j - x_i)/l``, on node j ``-F s``
    (paper eq. in sec. 3.3 with the sign fixed). ``F = c (l - l0)``; for the biphasic
    dermal-fatty family ``F = c_lo min(e, e_c) + c_hi max(e - e_c, 0)``, ``e = l - l0``,
    ``e_c = eps_c l0`` (continuous at the threshold, see :class:`LTWParams`).
    """
    d = x[tissue.spring_j] - x[tissue.spring_i]
    length = safe_length(d)
    ok = length > 0
    s = d / jnp.where(ok, length, 1.0)[:, None] * ok[:, None]
    lo, hi = params.family_stiffness()
    c_lo = lo[tissue.spring_family]
    c_hi = hi[tissue.spring_family]
    ext = length - tissue.spring_rest
    ext_c = params.biphasic_strain * tissue.spring_rest
    F = c_lo * jnp.minimum(ext, ext_c) + c_hi * jnp.maximum(ext - ext_c, 0.0)
    fs = F[:, None] * s
    ids = jnp.concatenate([tissue.spring_i, tissue.spring_j])
    vals = jnp.concatenate([fs, -fs], axis=0)
    return jax.ops.segment_sum(vals, ids, num_segments=x.shape[0])


def prism_volume(top: jax.Array, bot: jax.Array) -> jax.Array:
    """Volume of prisms (top triangle ``(..., 3, 3)`` over bottom triangle), mm^3.

    Split into the tetrahedra (a,b,c,d), (b,c,d,e), (c,d,e,f); positive when the top triangle
    is counter-clockwise seen from outside (away from the bottom). Exact for planar side faces."""
    a, b, c = top[..., 0, :], top[..., 1, :], top[..., 2, :]
    d, e, f = bot[..., 0, :], bot[..., 1, :], bot[..., 2, :]

    def tet(p, q, r, u):
        return jnp.sum(jnp.cross(q - p, r - p) * (u - p), axis=-1) / 6.0

    return -(tet(a, b, c, d) + tet(b, c, d, e) + tet(c, d, e, f))


def element_volumes(x: jax.Array, tissue: LTWTissue) -> jax.Array:
    """Current element volumes (epidermis-fascia prism + fascia-skull prism), ``(F,)`` mm^3."""
    ex = x[tissue.elements]
    return prism_volume(ex[:, 0:3], ex[:, 3:6]) + prism_volume(ex[:, 3:6], ex[:, 6:9])


def volume_forces(
    x: jax.Array, tissue: LTWTissue, params: LTWParams, R: jax.Array | None = None
) -> jax.Array:
    """Volume-preservation forces (paper sec. 3.6), ``(N, 3)``.

    Per element e (``n`` its rest epidermal unit normal, rotated by ``R_e``, the jaw rotation
    blended by the element's mandible fraction; identity when ``R`` is None):

    * volume term: the element volume measured as ``V = A t``, ``A`` the rest epidermal area
      and ``t`` the thickness, the height of the epidermal triangle's centroid above the skull
      triangle's centroid along ``n`` (exact for an epidermis moving along its normal). With
      the energy ``k_volume (V - V0)^2 / (2 Vref)`` the force on each epidermal node is
      ``-k_volume (V - V0) / Vref (A / 3) n`` - the paper's ``-k1 (V - V0) n_i`` with
      ``k1 = k_volume A / (3 Vref)``; the reaction acts on the (kinematic) skull nodes.
      Convex and linear for a fixed jaw pose: the exact prism volume's Hessian has an
      indefinite part (strain x column depth) that made the quasi-static solve diverge on the
      ICT face at full muscle forces.
    * shape term: ``-k_shape (p_i - R_e p0_i)`` with ``p`` the offsets from the element's
      centre of mass (paper's ``k2`` term; sums to zero over the element).
    """
    ex = x[tissue.elements]  # (F, 9, 3)
    p = ex - jnp.mean(ex, axis=1, keepdims=True)
    p0 = tissue.elem_rest_offsets
    n = tissue.elem_rest_normal
    if R is not None:
        w = tissue.elem_jaw[:, None, None]
        p0 = p0 + w * (p0 @ R.T - p0)
        n = n + w[:, 0] * (n @ R.T - n)
    dp = p - p0
    thick = jnp.sum((jnp.mean(ex[:, 0:3], axis=1) - jnp.mean(ex[:, 6:9], axis=1)) * n, axis=-1)
    A = tissue.elem_rest_area
    dV = A * (thick - tissue.elem_rest_thickness)
    mag = -params.k_volume * dV / tissue.elem_ref_volume * A / 3.0  # (F,)
    fv = mag[:, None, None] * jnp.concatenate(
        [
            jnp.broadcast_to(n[:, None, :], (ex.shape[0], 3, 3)),
            jnp.zeros_like(ex[:, 3:6]),
            -jnp.broadcast_to(n[:, None, :], (ex.shape[0], 3, 3)),
        ],
        axis=1,
    )
    f = fv - params.k_shape * dp
    return jax.ops.segment_sum(
        f.reshape(-1, 3), tissue.elements.reshape(-1), num_segments=x.shape[0]
    )


def restoration_forces(x: jax.Array, x_target: jax.Array, params: LTWParams) -> jax.Array:
    """Nodal restoration ``-k_restore (x - x_target)``, ``(N, 3)`` (paper's ``h``, our definition)."""
    return -params.k_restore * (x - x_target)


def skull_frame(tissue: LTWTissue, R: jax.Array, t: jax.Array):
    """Skull node positions ``(V, 3)`` mm and outward unit normals ``(V, 3)`` under the jaw pose."""
    V = tissue.n_vertices
    w = tissue.jaw_weight[2 * V :].astype(tissue.rest.dtype)
    pts = _rigid(tissue.rest[2 * V :], w, R, t)
    nrm = tissue.skull_normals
    nrm = nrm + w[:, None] * (nrm @ R.T - nrm)
    return pts, nrm


def skull_gate(
    x: jax.Array, tissue: LTWTissue, params: LTWParams, skull_pts: jax.Array, skull_nrm: jax.Array
) -> jax.Array:
    """Contact weight in [0, 1] of every fascia node, ``(V,)``.

    With ``h`` the height of the fascia node above the skull tangent plane of its column (mm)
    and ``T`` the rest muscle-layer thickness: 1 for ``h <= skull_contact T``, 0 for
    ``h >= (skull_contact + skull_band) T``, C1 smoothstep in between.
    """
    V = tissue.n_vertices
    h = jnp.sum((x[V : 2 * V] - skull_pts) * skull_nrm, axis=-1)
    T = tissue.muscle_layer_rest
    return 1.0 - smoothstep((h - params.skull_contact * T) / (params.skull_band * T))


def remove_inward(vec: jax.Array, normals: jax.Array, gate: jax.Array) -> jax.Array:
    """Skull non-penetration (paper sec. 3.7, sign fixed): ``vec - g min(vec . n, 0) n``.

    Args:
        vec: ``(V, 3)`` forces or velocities of the fascia nodes.
        normals: ``(V, 3)`` outward unit skull normals.
        gate: ``(V,)`` contact weights.
    """
    vn = jnp.sum(vec * normals, axis=-1)
    return vec - (gate * jnp.minimum(vn, 0.0))[:, None] * normals


def internal_forces(
    x: jax.Array,
    tissue: LTWTissue,
    params: LTWParams,
    R: jax.Array,
    t: jax.Array,
) -> jax.Array:
    """Springs + volume preservation + restoration, ``(N, 3)`` (no muscles, no skull projection)."""
    f = spring_forces(x, tissue, params) + volume_forces(x, tissue, params, R)
    target = kinematic_positions(tissue, R, t)
    return f + restoration_forces(x, target, params)


def preconditioner(tissue: LTWTissue, params: LTWParams, x: jax.Array | None = None) -> jax.Array:
    """Per-node 3x3 stiffness blocks ``B (N, 3, 3)`` (force/mm): the block diagonal of the
    stiffness matrix, used as the (anisotropic) fictitious mass of the quasi-static relaxation.

    Springs contribute ``c' s s^T + max(F, 0)/l (I - s s^T)`` (``c'`` the slope of the force
    law at the current length: the high branch of a stretched biphasic spring; the tension
    term is the geometric stiffness, compression is left out so that the mass never drops),
    evaluated at ``x`` (``(N, 3)`` mm) or at rest when ``x`` is None; plus the volume term's
    Gauss-Newton block at rest, the shape and restoration terms and ``1e-6 tr(B)/3``.
    Kinematic nodes get the identity."""
    lo, hi = params.family_stiffness()
    eye = jnp.eye(3, dtype=tissue.rest.dtype)
    if x is None:
        Bs = jnp.einsum("f,nfij->nij", lo, tissue.diag_spring)
    else:
        d = x[tissue.spring_j] - x[tissue.spring_i]
        length = safe_length(d)
        ok = length > 0
        safe_l = jnp.where(ok, length, 1.0)
        s = d / safe_l[:, None] * ok[:, None]
        ext = length - tissue.spring_rest
        ext_c = params.biphasic_strain * tissue.spring_rest
        c_lo = lo[tissue.spring_family]
        c_hi = hi[tissue.spring_family]
        F = c_lo * jnp.minimum(ext, ext_c) + c_hi * jnp.maximum(ext - ext_c, 0.0)
        slope = jnp.where(ext > ext_c, c_hi, c_lo)
        geo = jnp.where(ok, jnp.maximum(F, 0.0) / safe_l, 0.0)
        ss = s[:, :, None] * s[:, None, :]
        blk = (slope - geo)[:, None, None] * ss + geo[:, None, None] * eye
        ids = jnp.concatenate([tissue.spring_i, tissue.spring_j])
        Bs = jax.ops.segment_sum(jnp.concatenate([blk, blk]), ids, num_segments=x.shape[0])
    B = (
        Bs
        + params.k_volume * tissue.diag_volume
        + (params.k_shape * (8.0 / 9.0) * tissue.elem_count + params.k_restore)[:, None, None] * eye
    )
    tr = jnp.trace(B, axis1=1, axis2=2) / 3.0
    B = B + (1e-6 * tr)[:, None, None] * eye
    free = tissue.free[:, None, None]
    return free * B + (1.0 - free) * eye
