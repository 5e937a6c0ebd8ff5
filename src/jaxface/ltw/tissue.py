"""Layered prism tissue of Lee, Terzopoulos & Waters (SIGGRAPH 95), built from any skin mesh.

Units: millimetres for every length and position; forces are in the paper's (unit-less)
"model force" units, so that a stiffness ``c`` is force per mm. Frame: +y up, the face looks
along +z, the subject's left is +x.

Geometry (paper sec. 3.1, Fig. 6a)
----------------------------------
Every skin triangle becomes one 9-node element: epidermal nodes 1-3 (the skin vertices),
fascia nodes 4-6 and skull nodes 7-9 below them. Nodes are shared between neighbouring
elements, so the node set is three layers of ``V`` nodes each, stored layer after layer::

    node id  = layer * V + vertex,    layer 0 = epidermis, 1 = fascia, 2 = skull

The skull surface is the skin offset inward along (smoothed) vertex normals by a per-vertex
soft-tissue depth (paper sec. 3.7: "the skull is computed as an offset surface"), or given
explicitly (``skull_points``, e.g. from a user skull). The fascia node of a vertex lies on the
segment from the skin vertex to its skull node, at ``fascia_fraction`` (0.5) of the depth but
at most ``fascia_max_depth`` (3 mm) below the skin and at most ``self_clearance`` (0.3) of the
distance to where the inward ray meets the skin again (paper: uniform layer thickness, value
not given). Deep offsets of a real face fold (lips, eyelids, nostrils: ~10 % of the ICT
face's elements have an inverted rest volume); the skull layer is kinematic, so folds there
are harmless, and the shallow fascia layer keeps the free nodes well shaped. Fascia springs
of edges that still collapse (< ``collapse_ratio`` of the epidermal edge) are left out.

Springs (paper sec. 3.3, 3.10): four families, stiffness per spring (not per length)

====================  ===========================================  ==========
family                connects                                     stiffness
====================  ===========================================  ==========
0 epidermal           skin-triangle edges in the epidermis         60
1 dermal-fatty        epidermis -> fascia (biphasic)               30 / 70
2 fascia              triangle edges in the fascia layer           80
3 muscle layer        fascia -> skull                              10
====================  ===========================================  ==========

The paper does not say whether the prism has cross (shear) springs; a prism with only
vertical springs has no shear stiffness at rest, so with ``diagonals=True`` (default) the
dermal-fatty and muscle layers also get, for every mesh edge (a, b), the two diagonals
a(top)-b(bottom) and b(top)-a(bottom) with the same family stiffness [our choice].

Kinematic nodes: the skull layer (moved rigidly with the jaw where ``mandible`` is set) and
every node of a vertex used by no triangle.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import MeshError, RigError
from ..mesh import TriMesh

__all__ = [
    "EPIDERMAL",
    "DERMAL_FATTY",
    "FASCIA",
    "MUSCLE_LAYER",
    "LTWParams",
    "LTWTissue",
    "build_tissue",
    "mesh_edges",
    "offset_normals",
]

EPIDERMAL, DERMAL_FATTY, FASCIA, MUSCLE_LAYER = 0, 1, 2, 3


def _scalar(x) -> jax.Array:
    """A JAX scalar: floating arrays keep their dtype, Python numbers get JAX's default float."""
    if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.asarray(x)
    return jnp.asarray(x, dtype=jnp.result_type(float))


class LTWParams(eqx.Module):
    """Material and integration constants (JAX scalars, all differentiable).

    Paper values (sec. 3.10) are the defaults for the springs and the integrator; the other
    constants are not given in the paper and are documented here.

    Attributes:
        c_epidermis: epidermal spring stiffness, force/mm (paper 60).
        c_dermal_low: dermal-fatty stiffness below the threshold strain, force/mm (paper 30).
        c_dermal_high: dermal-fatty stiffness above the threshold strain, force/mm (paper 70).
        biphasic_strain: threshold strain ``eps_c`` of the biphasic law (not in the paper; 0.15).
            The force is continuous (C0) there: ``F = c_lo*min(e, e_c) + c_hi*max(e - e_c, 0)``
            with extension ``e = l - l0`` and ``e_c = eps_c * l0``. 0.15 sits in the low-stiffness
            "toe" region of soft-tissue stress-strain curves (collagen un-crimping, roughly 10-30 %
            strain), and full expressions stretch dermal-fatty springs by 5-30 %, so both phases
            are used. Compression always uses ``c_dermal_low``.
        c_fascia: fascia spring stiffness, force/mm (paper 80).
        c_muscle_layer: fascia-to-skull spring stiffness, force/mm (paper 10).
        k_volume: volume constant (not in the paper; 300), force/mm^2 (a bulk modulus). The
            paper's ``q_i = k1 (V - V0) n_i`` on the epidermal nodes, with ``V = A t`` (rest
            area x epidermis-to-skull thickness along the normal) and
            ``k1 = k_volume A / (3 Vref)``, ``Vref`` = area x mean depth: a uniform thickness
            change ``dh`` gives ``-k_volume A dh / (3 D)`` per epidermal node (about ``-30 dh``
            for 3 mm^2 triangles over 10 mm of tissue, comparable with the springs) and the
            constant does not depend on the mesh resolution. See
            :func:`jaxface.ltw.forces.volume_forces` for why the exact prism volume is not used.
        k_shape: shape constant ``k2`` (not in the paper; 5), force/mm: each node is pulled back to
            its rest offset from the element's centre of mass (rest offsets rotate with the jaw on
            mandible elements).
        k_restore: stiffness of the "nodal restoration force" ``h`` of the paper's equation of
            motion (undefined there; we use a zero-length spring from each free node to its rest
            position moved with the jaw), force/mm; default 1. It anchors the few nodes whose
            springs are nearly collinear where the inward offsets fold (lip corners, eyelids,
            nostrils), which otherwise have almost no stiffness and stall the quasi-static solve;
            at 1 it is ~1/100 of a node's spring stiffness and changes expressions by a few %.
        muscle_force: force on a fascia node at full activation and unit fall-off weights
            (not in the paper; 600), force units. Tuned on the ICT face so that single muscles
            at activation 1 move the skin by amounts comparable with the PBD rig (zygomaticus
            major ~9 mm, medial frontalis ~8 mm peak displacement).
        skull_contact: fascia nodes closer to the skull than this fraction of their rest
            muscle-layer thickness have the inward force (and velocity) component removed (0.2).
        skull_band: width of the smooth transition above the contact height, as a fraction of
            the rest muscle-layer thickness (0.3).
        mass: nodal mass (paper 0.5).
        dt: time step (paper 0.01).
        damping: damping coefficient gamma (paper 30).
    """

    c_epidermis: jax.Array = eqx.field(default=60.0, converter=_scalar)
    c_dermal_low: jax.Array = eqx.field(default=30.0, converter=_scalar)
    c_dermal_high: jax.Array = eqx.field(default=70.0, converter=_scalar)
    biphasic_strain: jax.Array = eqx.field(default=0.15, converter=_scalar)
    c_fascia: jax.Array = eqx.field(default=80.0, converter=_scalar)
    c_muscle_layer: jax.Array = eqx.field(default=10.0, converter=_scalar)
    k_volume: jax.Array = eqx.field(default=300.0, converter=_scalar)
    k_shape: jax.Array = eqx.field(default=5.0, converter=_scalar)
    k_restore: jax.Array = eqx.field(default=1.0, converter=_scalar)
    muscle_force: jax.Array = eqx.field(default=600.0, converter=_scalar)
    skull_contact: jax.Array = eqx.field(default=0.2, converter=_scalar)
    skull_band: jax.Array = eqx.field(default=0.3, converter=_scalar)
    mass: jax.Array = eqx.field(default=0.5, converter=_scalar)
    dt: jax.Array = eqx.field(default=0.01, converter=_scalar)
    damping: jax.Array = eqx.field(default=30.0, converter=_scalar)

    def family_stiffness(self) -> tuple[jax.Array, jax.Array]:
        """``(c_low (4,), c_high (4,))`` per spring family (force/mm); equal except dermal-fatty."""
        lo = jnp.stack([self.c_epidermis, self.c_dermal_low, self.c_fascia, self.c_muscle_layer])
        hi = jnp.stack([self.c_epidermis, self.c_dermal_high, self.c_fascia, self.c_muscle_layer])
        return lo, hi


class LTWTissue(eqx.Module):
    """Topology and rest state of the layered tissue (constants; JAX arrays).

    ``N = 3 V`` nodes (layers epidermis, fascia, skull), ``S`` springs, ``F`` elements.

    Attributes:
        n_vertices: ``V`` (static).
        rest: ``(N, 3)`` rest node positions, mm.
        spring_i, spring_j: ``(S,)`` int32 head/tail node ids.
        spring_rest: ``(S,)`` rest lengths, mm.
        spring_family: ``(S,)`` int32 family (0 epidermal, 1 dermal-fatty, 2 fascia, 3 muscle layer).
        elements: ``(F, 9)`` int32 node ids [epi a,b,c, fascia a,b,c, skull a,b,c].
        elem_rest_volume: ``(F,)`` rest element volume (both prisms), mm^3.
        elem_ref_volume: ``(F,)`` reference volume of the bulk energy, mm^3: the rest epidermal
            triangle area (floored at 0.2 x its squared longest edge) x the mean skin-to-skull
            depth of its vertices; > 0 even for folded elements.
        elem_rest_area: ``(F,)`` rest epidermal triangle area, mm^2.
        elem_rest_normal: ``(F, 3)`` rest unit epidermal normal (zero for degenerate triangles).
        elem_rest_thickness: ``(F,)`` rest epidermis-to-skull centroid height along it, mm.
        elem_rest_offsets: ``(F, 9, 3)`` rest node offsets from the element centre of mass, mm.
        elem_jaw: ``(F,)`` fraction of the element's skull nodes on the mandible.
        skull_normals: ``(V, 3)`` unit outward skull normals at rest (column directions).
        muscle_layer_rest: ``(V,)`` rest fascia-to-skull distance along the skull normal, mm.
        free: ``(N,)`` 1 for simulated nodes, 0 for kinematic ones.
        jaw_weight: ``(N,)`` 1 where a kinematic node moves with the mandible, else 0.
        init_weight: ``(N,)`` smooth jaw weight in [0, 1] used only for the initial guess.
        incidence: ``(N, 4)`` number of springs of each family at a node.
        elem_count: ``(N,)`` number of elements containing the node.
        diag_spring: ``(N, 4, 3, 3)`` per family, the sum of ``s s^T`` over the node's springs
            (rest directions): the node's 3x3 stiffness block per unit stiffness.
        diag_volume: ``(N, 3, 3)`` the node's 3x3 block of the volume term per unit
            ``k_volume``: ``sum_e (A_e / 3)^2 n_e n_e^T / Vref_e`` on epidermal nodes (mm).
    """

    n_vertices: int = eqx.field(static=True)
    rest: jax.Array
    spring_i: jax.Array
    spring_j: jax.Array
    spring_rest: jax.Array
    spring_family: jax.Array
    elements: jax.Array
    elem_rest_volume: jax.Array
    elem_ref_volume: jax.Array
    elem_rest_area: jax.Array
    elem_rest_normal: jax.Array
    elem_rest_thickness: jax.Array
    elem_rest_offsets: jax.Array
    elem_jaw: jax.Array
    skull_normals: jax.Array
    muscle_layer_rest: jax.Array
    free: jax.Array
    jaw_weight: jax.Array
    init_weight: jax.Array
    incidence: jax.Array
    elem_count: jax.Array
    diag_spring: jax.Array
    diag_volume: jax.Array

    @property
    def n_nodes(self) -> int:
        return 3 * self.n_vertices

    def layer(self, x: jax.Array, k: int) -> jax.Array:
        """Rows of layer ``k`` (0 epidermis, 1 fascia, 2 skull) of an ``(N, ...)`` array."""
        V = self.n_vertices
        return x[k * V : (k + 1) * V]


# ----------------------------------------------------------------------------- numpy helpers


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` int64 (``i < j``) of a triangle list ``(F, 3)``.

    Degenerate triangles with repeated vertex ids contribute no self-edges."""
    t = np.asarray(triangles, dtype=np.int64)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=0)
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0) if len(e) else np.zeros((0, 2), np.int64)


def offset_normals(vertices: np.ndarray, triangles: np.ndarray, smoothing: int = 2) -> np.ndarray:
    """Unit area-weighted vertex normals ``(V, 3)``, averaged over one-rings ``smoothing`` times.

    Smoothing reduces fold-overs of the deep inward offsets in concave regions (nose wings,
    lip corners). Vertices without a usable normal get ``+z`` (the view direction)."""
    v = np.asarray(vertices, float)
    t = np.asarray(triangles, np.int64)
    V = len(v)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros((V, 3))
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    e = mesh_edges(t)
    for _ in range(int(smoothing)):
        m = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        acc = m.copy()
        np.add.at(acc, e[:, 0], m[e[:, 1]])
        np.add.at(acc, e[:, 1], m[e[:, 0]])
        n = acc
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.where(ln > 1e-12, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return out


def _tet_volume_grad(p, q, r, u):
    """Signed volume ``det[q-p, r-p, u-p] / 6`` of tetrahedra ``(...)`` and its gradients
    with respect to p, q, r, u (each ``(..., 3)``); mm^3 and mm^2. Works on NumPy or JAX arrays."""
    xp = jnp if isinstance(p, jax.Array) else np
    gu = xp.cross(q - p, r - p) / 6.0
    gq = xp.cross(r - p, u - p) / 6.0
    gr = xp.cross(u - p, q - p) / 6.0
    vol = xp.sum(gu * (u - p), axis=-1)
    return vol, (-(gq + gr + gu), gq, gr, gu)


def element_volume_grad(ex):
    """Volume of 9-node elements and its gradient (NumPy or JAX).

    Args:
        ex: ``(F, 9, 3)`` node positions, mm, ordered [epidermis a,b,c, fascia a,b,c, skull a,b,c].

    Returns:
        ``(vol (F,) mm^3, grad (F, 9, 3) mm^2)``. The volume is the sum of the
        epidermis-fascia and fascia-skull prisms, each split into the tetrahedra
        (a,b,c,d), (b,c,d,e), (c,d,e,f) (top a,b,c over bottom d,e,f); it is positive when the
        epidermal triangle is counter-clockwise seen from outside, exact for planar side faces.
    """
    xp = jnp if isinstance(ex, jax.Array) else np
    vol = 0.0
    grads: list[Any] = [0.0] * 9
    for off in (0, 3):
        a, b, c, d, e, f = (ex[:, off + k] for k in range(6))
        ids = [off + k for k in range(6)]
        for tet in ((0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5)):
            pts = [(a, b, c, d, e, f)[k] for k in tet]
            v, gs = _tet_volume_grad(*pts)
            vol = vol - v
            for k, g in zip(tet, gs):
                grads[ids[k]] = grads[ids[k]] - g
    return vol, xp.stack(grads, axis=1)


def _smooth_weight(w: np.ndarray, edges: np.ndarray, iters: int) -> np.ndarray:
    w = np.asarray(w, float).copy()
    deg = np.ones(len(w))
    np.add.at(deg, edges[:, 0], 1.0)
    np.add.at(deg, edges[:, 1], 1.0)
    for _ in range(iters):
        acc = w.copy()
        np.add.at(acc, edges[:, 0], w[edges[:, 1]])
        np.add.at(acc, edges[:, 1], w[edges[:, 0]])
        w = acc / deg
    return w


def build_tissue(
    vertices,
    triangles,
    depth=None,
    *,
    skull_points=None,
    fascia_fraction: float = 0.5,
    mandible=None,
    diagonals: bool = True,
    normal_smoothing: int = 10,
    normals=None,
    fascia_max_depth: float = 3.0,
    self_clearance: float = 0.3,
    collapse_ratio: float = 0.3,
    dtype=None,
) -> LTWTissue:
    """Build the layered prism tissue under a skin mesh (NumPy, build time).

    Args:
        vertices: ``(V, 3)`` skin vertex positions, mm (the epidermis).
        triangles: ``(F, 3)`` int vertex ids, counter-clockwise seen from outside.
        depth: ``(V,)`` soft-tissue depth skin-to-skull, mm, > 0 (e.g.
            ``jaxface.anatomy.skull.tissue_depth``); used when ``skull_points`` is None.
        skull_points: optional ``(V, 3)`` skull node positions, mm (e.g. where the inward ray
            from each skin vertex meets a given skull). Overrides ``depth``.
        fascia_fraction: position of the fascia node between skin (0) and skull (1).
        mandible: optional ``(V,)`` bool, columns whose skull node moves with the jaw.
        diagonals: add cross springs in the dermal-fatty and muscle layers (see module doc).
        normal_smoothing: one-ring smoothing passes of the offset directions.
        normals: optional ``(V, 3)`` offset directions (outward); default smoothed vertex normals.
        fascia_max_depth: cap of the fascia depth below the skin, mm (the paper gives no
            thickness; skin plus subcutaneous fat over the SMAS is a few mm). Shallow fascia
            keeps the free fascia layer from folding where deep offsets cross.
        self_clearance: the fascia depth is also at most this fraction of the distance at
            which the inward ray from the vertex meets the skin again (lips, eyelids, nose
            wings, ears), so that the two sides of a thin feature do not cross. 0 disables.
        collapse_ratio: fascia springs whose rest length is below this fraction of the same
            edge in the epidermis (a folded fascia triangle) are left out: near-zero rest
            lengths make mass-spring layers buckle (negative transverse stiffness).
        dtype: float dtype of the JAX arrays (default: JAX's default float).

    Returns:
        The :class:`LTWTissue`.

    Raises:
        MeshError: non-finite vertices, bad triangle indices, or no triangles.
        RigError: bad depth / skull points / fascia fraction / mandible mask shapes or values.
    """
    v = np.asarray(vertices, dtype=float)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(
            f"skin vertices must have shape (V, 3), got {v.shape}.", problem="bad_shape"
        )
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad):
        raise MeshError(
            f"skin vertices {bad[:10].tolist()} have NaN/inf coordinates; fix or drop them before "
            "building the LTW tissue.",
            problem="non_finite_vertices",
            elements=bad,
        )
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise MeshError(
            f"skin triangles must have shape (F, 3) with F > 0, got {t.shape}.", problem="bad_shape"
        )
    t = t.astype(np.int64)
    V = len(v)
    badt = np.flatnonzero((t < 0).any(axis=1) | (t >= V).any(axis=1))
    if len(badt):
        raise MeshError(
            f"triangles {badt[:10].tolist()} index vertices outside 0..{V - 1}.",
            problem="bad_indices",
            elements=badt,
        )
    if not (0.0 < float(fascia_fraction) < 1.0):
        raise RigError(f"fascia_fraction must lie strictly between 0 and 1, got {fascia_fraction}.")

    if normals is None:
        nrm = offset_normals(v, t, normal_smoothing)
    else:
        nrm = np.asarray(normals, float)
        if nrm.shape != (V, 3) or not np.isfinite(nrm).all():
            raise RigError(f"normals must be a finite (V, 3) = ({V}, 3) array, got {nrm.shape}.")
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)

    if skull_points is not None:
        skull = np.asarray(skull_points, float)
        if skull.shape != (V, 3) or not np.isfinite(skull).all():
            raise RigError(
                f"skull_points must be a finite (V, 3) = ({V}, 3) array of mm positions, got "
                f"{skull.shape}."
            )
        col = v - skull
        dep = np.linalg.norm(col, axis=1)
        tooshallow = np.flatnonzero(dep < 1e-6)
        if len(tooshallow):
            raise RigError(
                f"skull points coincide with skin vertices {tooshallow[:10].tolist()}: the tissue "
                "needs a positive depth everywhere; offset the skull or pass depth=."
            )
        snorm = col / dep[:, None]
    else:
        if depth is None:
            raise RigError("build_tissue needs either depth (V,) in mm or skull_points (V, 3).")
        dep = np.broadcast_to(np.asarray(depth, float), (V,)).copy()
        badd = np.flatnonzero(~np.isfinite(dep) | (dep <= 0))
        if len(badd):
            raise RigError(
                f"tissue depth must be finite and > 0 mm; vertices {badd[:10].tolist()} have "
                f"{dep[badd[:5]].tolist()}. Check the depth estimate or pass skull_points."
            )
        skull = v - dep[:, None] * nrm
        snorm = nrm
    col = skull - v
    clen = np.linalg.norm(col, axis=1)
    fdep = np.minimum(float(fascia_fraction) * clen, float(fascia_max_depth))
    if self_clearance > 0:
        dirs = col / np.maximum(clen, 1e-300)[:, None]
        hits = TriMesh(v, t, validate=False).ray_cast(
            v,
            dirs,
            min_distance=1e-3 * float(np.median(clen)),
            max_distance=float(clen.max()) * 2.0,
        )
        dh = np.full(V, np.inf)
        dh[np.asarray(hits.hit)] = np.asarray(hits.distances)
        fdep = np.minimum(fdep, float(self_clearance) * dh)
    fdep = np.maximum(fdep, 1e-3 * clen)
    fascia = v + (fdep / np.maximum(clen, 1e-300))[:, None] * col

    if mandible is None:
        mand = np.zeros(V, bool)
    else:
        mand = np.asarray(mandible).astype(bool).reshape(-1)
        if mand.shape != (V,):
            raise RigError(f"mandible mask must have shape (V,) = ({V},), got {mand.shape}.")

    rest = np.concatenate([v, fascia, skull], axis=0)
    e = mesh_edges(t)
    a, b = e[:, 0], e[:, 1]
    vid = np.arange(V)
    used = np.zeros(V, bool)
    used[t.reshape(-1)] = True
    uv = vid[used]

    si: Any
    sj: Any
    fam: Any
    si, sj, fam = [], [], []

    def add(i, j, f):
        si.append(np.asarray(i, np.int64))
        sj.append(np.asarray(j, np.int64))
        fam.append(np.full(len(np.atleast_1d(i)), f, np.int64))

    add(a, b, EPIDERMAL)
    add(V + a, V + b, FASCIA)
    add(uv, V + uv, DERMAL_FATTY)
    add(V + uv, 2 * V + uv, MUSCLE_LAYER)
    if diagonals:
        add(np.concatenate([a, b]), V + np.concatenate([b, a]), DERMAL_FATTY)
        add(V + np.concatenate([a, b]), 2 * V + np.concatenate([b, a]), MUSCLE_LAYER)
    si = np.concatenate(si)
    sj = np.concatenate(sj)
    fam = np.concatenate(fam)
    srest = np.linalg.norm(rest[sj] - rest[si], axis=1)
    # drop fascia springs of folded fascia edges (see collapse_ratio)
    epi_len = np.linalg.norm(v[b] - v[a], axis=1)
    keep = np.ones(len(si), bool)
    fas = np.flatnonzero(fam == FASCIA)  # in the order of the edges (a, b)
    keep[fas] = srest[fas] >= float(collapse_ratio) * epi_len
    si, sj, fam, srest = si[keep], sj[keep], fam[keep], srest[keep]

    elements = np.concatenate([t, V + t, 2 * V + t], axis=1)
    ex = rest[elements]  # (F, 9, 3)
    vol, vgrad = element_volume_grad(ex)
    cr = np.cross(ex[:, 1] - ex[:, 0], ex[:, 2] - ex[:, 0])
    area_true = 0.5 * np.linalg.norm(cr, axis=1)
    nrm_e = np.where(area_true[:, None] > 0, cr / np.maximum(2.0 * area_true, 1e-300)[:, None], 0.0)
    thick0 = np.einsum("fk,fk->f", ex[:, 0:3].mean(axis=1) - ex[:, 6:9].mean(axis=1), nrm_e)
    emax2 = np.max(
        np.stack([np.sum((ex[:, i] - ex[:, (i + 1) % 3]) ** 2, axis=1) for i in range(3)], 1),
        axis=1,
    )
    # reference volume of the bulk energy: (area floored at a fifth of the squared longest
    # edge, for slivers) x (mean skin-to-skull depth); always > 0, also for folded elements
    area = np.maximum(area_true, 0.2 * emax2)
    pos_area = area[area > 0]
    area = np.maximum(area, 1e-6 * (np.median(pos_area) if len(pos_area) else 1.0))
    vref = area * np.maximum(clen[t].mean(axis=1), 1e-6)
    offsets = ex - ex.mean(axis=1, keepdims=True)
    elem_jaw = mand[t].mean(axis=1)

    muscle_layer_rest = np.einsum("ij,ij->i", fascia - skull, snorm)

    N = 3 * V
    free = np.zeros(N)
    free[uv] = 1.0
    free[V + uv] = 1.0
    jaw_w = np.tile(mand.astype(float), 3)
    init_w = np.tile(_smooth_weight(mand.astype(float), e, 8), 3)
    init_w[2 * V :] = mand
    init_w[np.tile(~used, 3)] = np.tile(mand.astype(float), 3)[np.tile(~used, 3)]
    incidence = np.zeros((N, 4))
    np.add.at(incidence, (si, fam), 1.0)
    np.add.at(incidence, (sj, fam), 1.0)
    elem_count = np.bincount(elements.reshape(-1), minlength=N).astype(float)
    # per-node 3x3 diagonal blocks of the rest stiffness, per unit constant (preconditioner)
    dspring = np.zeros((N, 4, 3, 3))
    ss = np.zeros((len(si), 3, 3))
    okl = srest > 1e-12
    sd = (rest[sj] - rest[si])[okl] / srest[okl, None]
    ss[okl] = sd[:, :, None] * sd[:, None, :]
    np.add.at(dspring, (si, fam), ss)
    np.add.at(dspring, (sj, fam), ss)
    gv = np.zeros_like(ex)
    gv[:, 0:3] = (area_true / 3.0)[:, None, None] * nrm_e[:, None, :]
    gg = gv[:, :, :, None] * gv[:, :, None, :] / vref[:, None, None, None]
    dvol = np.zeros((N, 3, 3))
    np.add.at(dvol, elements.reshape(-1), gg.reshape(-1, 3, 3))

    fdt = jnp.result_type(float) if dtype is None else dtype

    def f(x):
        return jnp.asarray(x, dtype=fdt)

    def i32(x):
        return jnp.asarray(x, dtype=jnp.int32)

    return LTWTissue(
        n_vertices=V,
        rest=f(rest),
        spring_i=i32(si),
        spring_j=i32(sj),
        spring_rest=f(srest),
        spring_family=i32(fam),
        elements=i32(elements),
        elem_rest_volume=f(vol),
        elem_ref_volume=f(vref),
        elem_rest_area=f(area_true),
        elem_rest_normal=f(nrm_e),
        elem_rest_thickness=f(thick0),
        elem_rest_offsets=f(offsets),
        elem_jaw=f(elem_jaw),
        skull_normals=f(snorm),
        muscle_layer_rest=f(muscle_layer_rest),
        free=f(free),
        jaw_weight=f(jaw_w),
        init_weight=f(init_w),
        incidence=f(incidence),
        elem_count=f(elem_count),
        diag_spring=f(dspring),
        diag_volume=f(dvol),
    )
