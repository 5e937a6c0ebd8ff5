"""Waters muscles for the layered tissue: linear fibres and piecewise-linear (sphincter) fibres.

Units: mm for positions, widths and lengths; forces in the paper's model units.

A *fibre* is a polyline ``m^1 ... m^(N+1)`` (paper sec. 3.4-3.5, Fig. 7) ordered from the
attachment in the fascia (``m^1``, the insertion, where the force is strongest) to the fixed
bony end (``m^(N+1)``, the origin). A linear muscle is a 1-segment fibre; a sheet muscle is
several fibres sharing one activation; the orbicularis oris is four piecewise-linear arcs
(upper/lower lip x left/right), each attached at a mouth corner and fixed at the lip midline,
so that contraction draws the corners medially along the lips.

For a fascia node ``x`` whose nearest segment (fixed at build time) is ``l`` with unit direction
``m_l`` (pointing toward the origin) and unit muscle-sheet normal ``n_l``:

* length ratio ``eps = ((m^(l+1) - x) . m_l + sum_{k>l} |m^(k+1) - m^k|) / d`` (``d`` the fibre
  length): 0 at the bony end, 1 at the attachment (paper eq. for eps, sec. 3.4 / 3.5);
* width ``omega = |p - (p . n_l) n_l|`` with ``p`` the perpendicular from the segment line to
  ``x`` (the lateral distance within the muscle sheet);
* force ``f = a * F * g * Theta1(eps) * Theta2(omega / w) * m_l`` with activation ``a`` (in
  [0, 1], not clipped), ``F = params.muscle_force``, per-fibre gain ``g`` and width ``w``.

The paper shows Theta1 and Theta2 only as plots (Fig. 8). We use C1-smooth surrogates so that
forces are C1 in the node positions:

* ``Theta1(eps) = S(eps / eps_full) * (1 - S((eps - 1) / eps_tail))`` with ``S`` the cubic
  smoothstep: zero at the bone, rising to full strength at ``eps_full`` (0.8) and fading out
  over ``eps_tail`` (0.25) beyond the attachment;
* ``Theta2(r) = (1 + cos(pi r)) / 2`` for ``r < 1``, else 0. Raised-cosine windows of half-width
  ``w`` spaced ``w`` apart sum to one, so sheet fibres spaced by their width do not
  double-count the nodes between them.

The influence sets (which fascia nodes each fibre acts on, and their nearest segment) are
precomputed in NumPy at build time (paper: "in a precomputation step"): nodes with rest
``omega < w``, ``-0.02 < eps < 1 + eps_tail`` and depth ``|p . n| < depth_reach``.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import RigError
from ..surface import safe_normalize
from .forces import _rigid, smoothstep
from .tissue import LTWParams

__all__ = [
    "Fibre",
    "WatersMuscles",
    "linear_fibre",
    "sheet_fibres",
    "sphincter_fibres",
    "build_waters",
    "theta1",
    "theta2",
    "muscle_forces",
]


@dataclass(frozen=True)
class Fibre:
    """One Waters fibre (NumPy, build time).

    Attributes:
        points: ``(K, 3)`` polyline, mm, from the attachment (insertion) to the fixed origin, K >= 2.
        muscle: index of the activation that drives it.
        width: influence half-width ``w``, mm.
        jaw: True when the fibre is anchored on the mandible (moves rigidly with the jaw).
        gain: force multiplier (dimensionless).
    """

    points: np.ndarray
    muscle: int
    width: float
    jaw: bool = False
    gain: float = 1.0


def linear_fibre(origin, insertion, width, muscle, *, jaw=False, gain=1.0) -> Fibre:
    """A linear muscle: ``origin`` (3,) fixed end, ``insertion`` (3,) attachment, mm."""
    pts = np.stack([np.asarray(insertion, float), np.asarray(origin, float)])
    return Fibre(pts, int(muscle), float(width), bool(jaw), float(gain))


def sheet_fibres(origins, insertions, muscle, *, width=None, jaw=False, gain=1.0) -> list[Fibre]:
    """A sheet muscle as ``k`` linear fibres (``origins``, ``insertions``: ``(k, 3)`` mm).

    The default width is the mean spacing of neighbouring insertions (so the raised-cosine
    windows form a partition of unity across the sheet), at least 1/6 of the mean fibre length.
    """
    o = np.asarray(origins, float).reshape(-1, 3)
    ins = np.asarray(insertions, float).reshape(-1, 3)
    if o.shape != ins.shape or len(o) == 0:
        raise RigError(
            f"sheet muscle {muscle}: origins {o.shape} and insertions {ins.shape} must both be (k, 3), k >= 1."
        )
    if width is None:
        length = float(np.mean(np.linalg.norm(o - ins, axis=1)))
        if len(ins) > 1:
            spacing = float(np.mean(np.linalg.norm(np.diff(ins, axis=0), axis=1)))
        else:
            spacing = 0.0
        width = max(spacing, length / 6.0)
    return [linear_fibre(a, b, width, muscle, jaw=jaw, gain=gain) for a, b in zip(o, ins)]


def sphincter_fibres(
    centre, axis_u, axis_v, semi_u, semi_v, muscle, *, n_segments=4, width=None, gain=1.0
) -> list[Fibre]:
    """Orbicularis-oris style sphincter as four piecewise-linear arcs of an ellipse.

    Args:
        centre: ``(3,)`` ellipse centre, mm.
        axis_u: ``(3,)`` direction of the long (corner-to-corner) axis; axis_v: ``(3,)`` of the
            short axis (toward the upper lip). Both are normalised here.
        semi_u, semi_v: semi-axes, mm.
        muscle: activation index.
        n_segments: segments per quarter arc.
        width: influence half-width, mm (default ``semi_v``).

    Each quarter arc runs from a corner (attachment, ``+-axis_u``) to the lip midline (fixed end,
    ``+-axis_v``).
    """
    c = np.asarray(centre, float)
    u = np.asarray(axis_u, float)
    u = u / np.linalg.norm(u)
    v = np.asarray(axis_v, float)
    v = v - (v @ u) * u
    v = v / np.linalg.norm(v)
    if width is None:
        width = float(semi_v)
    th = np.linspace(0.0, np.pi / 2.0, int(n_segments) + 1)
    out = []
    for su in (1.0, -1.0):
        for sv in (1.0, -1.0):
            pts = c + np.outer(su * semi_u * np.cos(th), u) + np.outer(sv * semi_v * np.sin(th), v)
            out.append(Fibre(pts, int(muscle), float(width), False, float(gain)))
    return out


class WatersMuscles(eqx.Module):
    """Precomputed Waters fibres and influence sets (JAX arrays).

    ``G`` segments over all fibres, ``P`` (segment, fascia node) pairs.

    Attributes:
        n_muscles: number of activations (static).
        eps_full, eps_tail: Theta1 shape constants (static floats, dimensionless).
        seg_start, seg_end: ``(G, 3)`` rest segment end points ``m^l``, ``m^(l+1)``, mm.
        seg_normal: ``(G, 3)`` unit muscle-sheet normals.
        seg_remaining: ``(G,)`` fibre length beyond the segment toward the origin, mm.
        seg_total: ``(G,)`` total length of the segment's fibre, mm.
        seg_width: ``(G,)`` fibre half-width, mm.
        seg_gain: ``(G,)`` fibre gain.
        seg_muscle: ``(G,)`` int32 activation index.
        seg_jaw: ``(G,)`` 1 if the fibre moves with the mandible, else 0.
        pair_node: ``(P,)`` int32 node ids (global, fascia layer).
        pair_seg: ``(P,)`` int32 segment ids.
    """

    n_muscles: int = eqx.field(static=True)
    eps_full: float = eqx.field(static=True)
    eps_tail: float = eqx.field(static=True)
    seg_start: jax.Array
    seg_end: jax.Array
    seg_normal: jax.Array
    seg_remaining: jax.Array
    seg_total: jax.Array
    seg_width: jax.Array
    seg_gain: jax.Array
    seg_muscle: jax.Array
    seg_jaw: jax.Array
    pair_node: jax.Array
    pair_seg: jax.Array

    def influence_counts(self) -> np.ndarray:
        """Number of influenced fascia nodes per muscle, ``(M,)`` int (for diagnostics)."""
        m = np.asarray(self.seg_muscle)[np.asarray(self.pair_seg)]
        return np.bincount(m, minlength=self.n_muscles)


def build_waters(
    fibres: list[Fibre],
    fascia_rest,
    fascia_node_ids,
    sheet_normals,
    n_muscles: int,
    *,
    eps_full: float = 0.8,
    eps_tail: float = 0.25,
    depth_reach: float = 25.0,
    candidate_mask=None,
    dtype=None,
) -> WatersMuscles:
    """Precompute segments and influence sets (NumPy, build time).

    Args:
        fibres: the fibres (see :class:`Fibre`).
        fascia_rest: ``(V, 3)`` rest fascia node positions, mm.
        fascia_node_ids: ``(V,)`` global node id of each fascia node.
        sheet_normals: ``(V, 3)`` outward unit normals at the fascia nodes (the skin normals);
            a segment's sheet normal is the normal of the node nearest its midpoint, made
            orthogonal to the segment.
        n_muscles: number of activations ``M``.
        eps_full, eps_tail: Theta1 shape (see module doc).
        depth_reach: nodes farther than this from the muscle sheet (along its normal) are not
            influenced, mm.
        candidate_mask: optional ``(V,)`` bool, nodes that may be influenced (e.g. free nodes).
        dtype: float dtype of the arrays.

    Raises:
        RigError: a fibre with fewer than two points, a zero-length fibre, non-positive width,
            non-finite points or a muscle index outside ``0..M-1``.
    """
    X = np.asarray(fascia_rest, float)
    ids = np.asarray(fascia_node_ids, np.int64)
    nrm_nodes = np.asarray(sheet_normals, float)
    cand = np.ones(len(X), bool) if candidate_mask is None else np.asarray(candidate_mask, bool)
    S_start, S_end, S_nrm, S_rem, S_tot, S_w, S_g, S_m, S_j = ([] for _ in range(9))
    P_node, P_seg = [], []
    gseg = 0
    for fi, fb in enumerate(fibres):
        pts = np.asarray(fb.points, float)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.isfinite(pts).all():
            raise RigError(
                f"fibre {fi} (muscle {fb.muscle}) needs (K>=2, 3) finite points, got {pts.shape}."
            )
        if not (0 <= fb.muscle < n_muscles):
            raise RigError(f"fibre {fi} refers to muscle {fb.muscle}, outside 0..{n_muscles - 1}.")
        if not (fb.width > 0 and np.isfinite(fb.width)):
            raise RigError(
                f"fibre {fi} (muscle {fb.muscle}) has width {fb.width} mm; it must be > 0."
            )
        seg = np.diff(pts, axis=0)
        slen = np.linalg.norm(seg, axis=1)
        keep = slen > 1e-9
        if not keep.any():
            raise RigError(
                f"fibre {fi} (muscle {fb.muscle}) has zero length: origin equals insertion."
            )
        # drop zero-length segments
        pts = np.concatenate([pts[:1], pts[1:][keep]], axis=0)
        seg = np.diff(pts, axis=0)
        slen = np.linalg.norm(seg, axis=1)
        m = seg / slen[:, None]
        total = slen.sum()
        remaining = total - np.cumsum(slen)
        mids = 0.5 * (pts[:-1] + pts[1:])
        near = np.argmin(((X[None, :, :] - mids[:, None, :]) ** 2).sum(-1), axis=1)
        n0 = nrm_nodes[near]
        n = n0 - np.sum(n0 * m, axis=1, keepdims=True) * m
        ln = np.linalg.norm(n, axis=1)
        fallback = np.cross(m, np.array([1.0, 0.0, 0.0]))
        fallback = np.where(
            np.linalg.norm(fallback, axis=1, keepdims=True) < 1e-6,
            np.cross(m, np.array([0.0, 1.0, 0.0])),
            fallback,
        )
        n = np.where(
            ln[:, None] > 1e-6,
            n / np.maximum(ln, 1e-300)[:, None],
            fallback / np.linalg.norm(fallback, axis=1, keepdims=True),
        )
        # nearest segment of every candidate node (rest)
        rel = X[:, None, :] - pts[None, :-1, :]  # (V, L, 3)
        tpar = np.clip(np.einsum("vlk,lk->vl", rel, m) / slen[None], 0.0, 1.0)
        closest = pts[None, :-1, :] + (tpar * slen[None])[..., None] * m[None]
        dist = np.linalg.norm(X[:, None, :] - closest, axis=2)
        l_near = np.argmin(dist, axis=1)
        Ml, Nl, El = m[l_near], n[l_near], pts[1:][l_near]
        eps = (np.einsum("vk,vk->v", El - X, Ml) + remaining[l_near]) / total
        dv = X - El
        p = dv - np.einsum("vk,vk->v", dv, Ml)[:, None] * Ml
        pn = np.einsum("vk,vk->v", p, Nl)
        lat = p - pn[:, None] * Nl
        omega = np.linalg.norm(lat, axis=1)
        sel = (
            cand
            & (omega < fb.width)
            & (eps > -0.02)
            & (eps < 1.0 + eps_tail)
            & (np.abs(pn) < depth_reach)
        )
        idx = np.flatnonzero(sel)
        P_node.append(ids[idx])
        P_seg.append(gseg + l_near[idx])
        L = len(slen)
        S_start.append(pts[:-1])
        S_end.append(pts[1:])
        S_nrm.append(n)
        S_rem.append(remaining)
        S_tot.append(np.full(L, total))
        S_w.append(np.full(L, fb.width))
        S_g.append(np.full(L, fb.gain))
        S_m.append(np.full(L, fb.muscle))
        S_j.append(np.full(L, 1.0 if fb.jaw else 0.0))
        gseg += L

    fdt = jnp.result_type(float) if dtype is None else dtype

    def cat(lst, shape_tail=()):
        if lst:
            return np.concatenate(lst, axis=0)
        return np.zeros((0,) + shape_tail)

    def f(a):
        return jnp.asarray(a, dtype=fdt)

    def i32(a):
        return jnp.asarray(a, dtype=jnp.int32)

    return WatersMuscles(
        n_muscles=int(n_muscles),
        eps_full=float(eps_full),
        eps_tail=float(eps_tail),
        seg_start=f(cat(S_start, (3,))),
        seg_end=f(cat(S_end, (3,))),
        seg_normal=f(cat(S_nrm, (3,))),
        seg_remaining=f(cat(S_rem)),
        seg_total=f(cat(S_tot)),
        seg_width=f(cat(S_w)),
        seg_gain=f(cat(S_g)),
        seg_muscle=i32(cat(S_m)),
        seg_jaw=f(cat(S_j)),
        pair_node=i32(cat(P_node)),
        pair_seg=i32(cat(P_seg)),
    )


def theta1(eps: jax.Array, eps_full: float = 0.8, eps_tail: float = 0.25) -> jax.Array:
    """Length fall-off (C1): 0 at the bone (eps <= 0), 1 on [eps_full, 1], 0 beyond 1 + eps_tail."""
    return smoothstep(eps / eps_full) * (1.0 - smoothstep((eps - 1.0) / eps_tail))


def theta2(q: jax.Array) -> jax.Array:
    """Width fall-off (C1) as a function of ``q = (omega / w)^2``: ``(1 + cos(pi sqrt q)) / 2``
    for q < 1, else 0. Smooth at q = 0 (an even function of omega), NaN-free gradients."""
    ok = (q > 0) & (q < 1)
    r = jnp.sqrt(jnp.where(ok, q, 0.25))
    val = 0.5 * (1.0 + jnp.cos(jnp.pi * r))
    return jnp.where(ok, val, jnp.where(q <= 0, 1.0, 0.0))


def muscle_forces(
    x: jax.Array,
    muscles: WatersMuscles,
    activations: jax.Array,
    params: LTWParams,
    R: jax.Array,
    t: jax.Array,
) -> jax.Array:
    """Waters muscle forces on all nodes, ``(N, 3)`` (non-zero only on influenced fascia nodes).

    Args:
        x: ``(N, 3)`` node positions, mm.
        muscles: the precomputed fibres.
        activations: ``(M,)`` activations (nominally in [0, 1]).
        params: material constants (uses ``muscle_force``).
        R, t: mandible rotation ``(3, 3)`` and translation ``(3,)`` (mm), applied to jaw fibres.
    """
    if muscles.pair_node.shape[0] == 0:
        return jnp.zeros_like(x)
    w = muscles.seg_jaw.astype(x.dtype)
    start = _rigid(muscles.seg_start, w, R, t)
    end = _rigid(muscles.seg_end, w, R, t)
    nrm0 = muscles.seg_normal
    nrm = nrm0 + w[:, None] * (nrm0 @ R.T - nrm0)
    m = safe_normalize(end - start)
    seg = muscles.pair_seg
    xs = x[muscles.pair_node]
    ms, es, ns = m[seg], end[seg], nrm[seg]
    eps = (jnp.sum((es - xs) * ms, axis=-1) + muscles.seg_remaining[seg]) / muscles.seg_total[seg]
    dv = xs - es
    p = dv - jnp.sum(dv * ms, axis=-1, keepdims=True) * ms
    lat = p - jnp.sum(p * ns, axis=-1, keepdims=True) * ns
    q = jnp.sum(lat * lat, axis=-1) / muscles.seg_width[seg] ** 2
    a = jnp.asarray(activations)[muscles.seg_muscle[seg]]
    mag = (
        a
        * params.muscle_force
        * muscles.seg_gain[seg]
        * theta1(eps, muscles.eps_full, muscles.eps_tail)
        * theta2(q)
    )
    return jax.ops.segment_sum(mag[:, None] * ms, muscles.pair_node, num_segments=x.shape[0])
