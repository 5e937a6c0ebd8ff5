"""Differentiable position-based dynamics (PBD / XPBD) in JAX: the solver of jaxface.

Implements thesis sec. 3.2 (Mueller et al. 2006 as summarised there, eqs. 3.11-3.23) with two
parallel projection schemes, XPBD compliance (Macklin et al. 2016) as an option, time stepping
with damping, and a quasi-static mode. Units: positions mm, velocities mm/s, time s, inverse
masses 1/g (the thesis sets every mass to 1), angles rad.

Model / state split
-------------------
* Constraints are built once in NumPy (:func:`distance_constraints`, :func:`bending_constraints`,
  :func:`area_constraints`, :func:`volume_constraint`, :func:`anchor_constraints`,
  :func:`halfspace_constraints`, :func:`hull_constraints`, or :func:`skin_constraints` for the
  thesis's skin set) and assembled with :func:`build_system`, which colours them (greedy graph
  colouring, :mod:`jaxface.coloring`) and returns a :class:`System` pytree.
* Everything that changes at run time is a leaf: anchor targets, collision planes, rest
  values, stiffness, compliance, inverse masses (``system.set("anchors", target=t)``). All of
  them can be differentiated.
* The solvers (:func:`project`, :func:`relax`, :func:`step`, :func:`simulate`) are pure,
  ``eqx.filter_jit``-compiled functions with static Python-int iteration counts
  (``lax.fori_loop`` with a static trip count), so ``jax.grad``, ``jax.jvp``, ``jax.jacfwd``
  and ``jax.vmap`` all go through a solve. ``checkpoint_every=B`` wraps blocks of ``B``
  iterations in ``jax.checkpoint``: reverse mode then stores one state per block instead of
  every intermediate of every iteration.

Projection schemes
------------------
``scheme="gs"`` (graph-coloured Gauss-Seidel): the constraints of a kind are coloured so that no
two of one colour share a particle; a sweep projects colour after colour, each colour one
vectorised gather / project / scatter (``unique_indices``). A sweep is *exactly* the thesis's
sequential Gauss-Seidel sweep over the constraints in colour order
(:func:`jaxface.reference.solve` with ``order="color"`` reproduces it to rounding).

``scheme="jacobi"``: every constraint is projected from the same positions; the corrections are
summed per particle, divided by the number of constraints acting on it (static count of
bilateral constraints + active unilateral ones) and scaled by the over-relaxation ``omega``.
Summation uses the same colour blocks (conflict-free scatters are several times faster on CPU
than one scatter with repeated indices). Jacobi does not conserve momentum exactly (the
per-particle averaging breaks the symmetry of the corrections); Gauss-Seidel does, per
projection, for internal constraints with equal masses.

Default: ``"gs"`` (:data:`DEFAULT_SCHEME`): per iteration the two cost the same, but coloured
Gauss-Seidel reaches a converged configuration about 16x sooner. Measured with
``python benchmarks/bench_pbd.py`` on the 2-core CPU, float32 throughput / float64
convergence, ICT-FaceKit face skin (9,409 particles; 55,383 stretch + cross-edge, 27,511
bending, 18,461 area constraints and the capped volume; 10% of the particles anchored, k = 0.2,
to targets displaced by N(0, 1 mm)):

==============================================  ============  ============
                                                ``gs``        ``jacobi``
==============================================  ============  ============
distance projections / s (distance-only system) 61.4 M        57.0 M
ms per iteration, full skin system              4.74          5.12
iterations to 1e-3 mm of its own fixed point    1,200         19,175
wall time to 1e-3 mm                            5.7 s         98 s
==============================================  ============  ============

(With plain-PBD stiffness k < 1 the fixed point depends on the scheme: the two converged
configurations differ by 0.30 mm here. On a 1.1k-vertex patch: 1,450 vs 19,475 iterations.)

Stiffness and XPBD
------------------
Plain PBD (thesis): the correction of constraint ``j`` is multiplied by ``k_j`` in ``[0, 1]``;
the effective stiffness then depends on the iteration count (and conflicting constraints
settle where the sweep order puts them). With ``compliance=alpha`` (XPBD) each group carries a
Lagrange multiplier per constraint, reset at the start of each step (or each ``relax`` pass);
``alpha / dt^2`` enters the projection and the equilibrium of a time-stepped simulation is the
force balance ``sum_j grad C_j C_j / alpha_j = f_ext``, independent of ``dt`` and of the
iteration count once each step's solve has converged (tested: 20 vs 200 iterations).

Time integration (thesis loop, lines 1-15, with damping as in Mueller et al. 2006)
---------------------------------------------------------------------------------
damping (``"linear"``: ``v *= 1 - damping``; ``"rigid"``: damp only the non-rigid part of the
motion, conserving linear and angular momentum); ``v += dt w f_ext + dt g``; ``p = x + dt v``;
project; ``v = (p - x) / dt``; ``x = p``. Fixed ``dt`` 16.6 ms and damping 0.2 by default.
Damping is applied *before* the external forces (Mueller et al. 2006 damp after them): damping
after the forces would scale a constant load such as gravity by ``1 - damping`` at rest, and
the steady state would no longer be the force balance.

Quasi-static mode (:func:`relax`, what fitting uses): projections from the given positions
without prediction or velocity. For XPBD groups each of the ``passes`` is one implicit step
from rest (multipliers reset per pass); repeating passes converges to the minimum of
``sum_j C_j^2 / (2 alpha_j)`` subject to the hard constraints.

Robustness: see :mod:`jaxface.constraints` (degenerate constraints are skipped; no NaN in
values or derivatives).

Measured (``python benchmarks/bench_pbd.py``, 2-core CPU, float32)
-------------------------------------------------------------------
* Reverse-mode gradient through 100 iterations of the full ICT face system (w.r.t. start
  positions and anchor targets): with the default ``checkpoint_every=1`` XLA's peak buffer
  memory is 47 MB and it takes 3.3 s; ``checkpoint_every=10``: 263 MB, 3.6 s; no
  checkpointing: 2,227 MB, 4.4 s.
* Against the sequential NumPy reference (:mod:`jaxface.reference`, thesis loop): 361x
  (quiet machine, 2.25 s vs 6.2 ms per iteration) to 848x faster per iteration on the ICT face;
  1,865x on the 1.1k patch.
* Other sizes, distance projections / s (gs / jacobi): 53 M / 52 M on the 1.1k-vertex patch
  (0.56 ms per full iteration); 24 M / 16 M on a 100k-vertex sheet (177 ms per full
  iteration; measured while other jobs shared the 2 cores, and past the CPU caches).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import to_jax
from .coloring import balanced_coloring, particle_counts
from .constraints import (
    AnchorConstraints,
    AreaConstraints,
    BendingConstraints,
    Constraints,
    DistanceConstraints,
    HalfSpaceConstraints,
    HullConstraints,
    VolumeConstraint,
    dihedral_angle,
    safe_norm,
)
from .errors import MeshError

__all__ = [
    "DEFAULT_DT",
    "DEFAULT_DAMPING",
    "DEFAULT_OMEGA",
    "DEFAULT_SCHEME",
    "System",
    "Particles",
    "build_system",
    "distance_constraints",
    "bending_constraints",
    "area_constraints",
    "volume_constraint",
    "anchor_constraints",
    "halfspace_constraints",
    "hull_constraints",
    "skin_constraints",
    "hull_planes",
    "transform_planes",
    "project",
    "relax",
    "step",
    "simulate",
    "Constraints",
    "DistanceConstraints",
    "BendingConstraints",
    "AreaConstraints",
    "VolumeConstraint",
    "AnchorConstraints",
    "HalfSpaceConstraints",
    "HullConstraints",
    "dihedral_angle",
    "safe_norm",
]

DEFAULT_DT = 0.0166
"""Fixed time step, s (thesis sec. 5.7: 16.6 ms)."""
DEFAULT_DAMPING = 0.2
"""Velocity damping per step (thesis sec. 5.5, skin)."""
DEFAULT_OMEGA = 1.5
"""Jacobi over-relaxation factor."""
DEFAULT_SCHEME = "gs"
"""Default projection scheme (see the module docstring for the measurements)."""

Scheme = Literal["gs", "jacobi"]

# ----------------------------------------------------------------------------------------
# builders (thin wrappers, NumPy in)
# ----------------------------------------------------------------------------------------


def distance_constraints(pairs, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
    """Stretch constraints (eq. 3.15). See :meth:`DistanceConstraints.build`.

    Args:
        pairs: ``(M, 2)`` int particle ids.
        x_rest: ``(N, 3)`` mm rest positions (rest lengths measured there).
        rest: ``(M,)`` mm rest lengths, instead of ``x_rest``.
        stiffness: ``k`` in ``[0, 1]`` (scalar or ``(M,)``).
        compliance: XPBD compliance, ``None`` for PBD.
    """
    return DistanceConstraints.build(
        pairs, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def bending_constraints(edge_pairs, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
    """Dihedral bending constraints (eq. 3.20) on ``(M, 4)`` rows ``[a, b, c, d]``
    (:attr:`jaxface.mesh.TriMesh.edge_pairs`); rest angles (rad) measured on ``x_rest`` (mm)."""
    return BendingConstraints.build(
        edge_pairs, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def area_constraints(triangles, x_rest=None, *, rest=None, stiffness=1.0, compliance=None):
    """Triangle area constraints (eq. 3.21); rest areas (mm^2) measured on ``x_rest`` (mm)."""
    return AreaConstraints.build(
        triangles, x_rest, rest=rest, stiffness=stiffness, compliance=compliance
    )


def volume_constraint(
    triangles, x_rest=None, *, rest=None, origin=None, stiffness=1.0, compliance=None
):
    """Global volume constraint (eq. 3.22) of a closed or capped surface; ``rest`` mm^3
    (default: measured on ``x_rest``), ``origin`` mm cap point. See :class:`VolumeConstraint`."""
    return VolumeConstraint.build(
        triangles, x_rest, rest=rest, origin=origin, stiffness=stiffness, compliance=compliance
    )


def anchor_constraints(indices, targets, *, stiffness=1.0, compliance=None):
    """Position constraints (eq. 3.23) of particles ``(M,)`` to targets ``(M, 3)`` mm; move
    the targets at run time with ``system.set(name, target=...)``."""
    return AnchorConstraints.build(indices, targets, stiffness=stiffness, compliance=compliance)


def halfspace_constraints(indices, normals, offsets, *, stiffness=1.0, compliance=None):
    """Unilateral plane constraints ``n . p >= d`` (mm) for particles ``(M,)``."""
    return HalfSpaceConstraints.build(
        indices, normals, offsets, stiffness=stiffness, compliance=compliance
    )


def hull_constraints(indices, normals, offsets, *, clearance=0.0, stiffness=1.0, compliance=None):
    """Convex-hull collision for particles ``(M,)`` against the planes ``(H, 3)``, ``(H,)`` mm
    of one convex hull (:func:`hull_planes`); run-time planes via ``system.set(name,
    normals=..., offsets=...)`` (:func:`transform_planes` for a hull moving with the jaw)."""
    return HullConstraints.build(
        indices, normals, offsets, clearance=clearance, stiffness=stiffness, compliance=compliance
    )


def hull_planes(points) -> tuple[np.ndarray, np.ndarray]:
    """Planes of the convex hull of a point set (NumPy, build time).

    Args:
        points: ``(K, 3)`` mm, at least 4 points not all coplanar (e.g. teeth vertices).

    Returns:
        ``(normals (H, 3), offsets (H,))``: outward unit normals and offsets in mm; the hull is
        ``{q : normals @ q <= offsets}``. Coplanar facets are merged.

    Raises:
        MeshError: fewer than 4 points, or all coplanar.
    """
    from scipy.spatial import ConvexHull, QhullError

    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 4:
        raise MeshError(
            f"hull_planes needs (K, 3) points with K >= 4, got {p.shape}.", problem="shape"
        )
    try:
        h = ConvexHull(p)
    except QhullError as err:  # flat or degenerate input
        raise MeshError(
            f"cannot build a convex hull of {p.shape[0]} points (coplanar or degenerate): "
            f"{str(err).splitlines()[0]}",
            problem="degenerate_hull",
        ) from err
    eq = h.equations  # n . x + c <= 0 inside
    scale = float(np.ptp(p, axis=0).max())
    key = np.round(np.concatenate([eq[:, :3], eq[:, 3:] / scale], 1) * 1e9).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    eq = eq[np.sort(first)]
    return eq[:, :3].copy(), -eq[:, 3].copy()


def transform_planes(normals, offsets, rotation, translation):
    """Planes after the rigid motion ``q' = R q + t`` (JAX, differentiable).

    Args:
        normals: ``(H, 3)`` unit normals; offsets: ``(H,)`` mm.
        rotation: ``(3, 3)`` rotation matrix; translation: ``(3,)`` mm.

    Returns:
        ``(normals' (H, 3), offsets' (H,) mm)`` of the moved hull.
    """
    n = jnp.asarray(normals) @ jnp.asarray(rotation).T
    return n, jnp.asarray(offsets) + n @ jnp.asarray(translation)


def skin_constraints(
    mesh,
    triangles=None,
    *,
    stretch=0.15,
    cross=None,
    bend=0.95,
    area=0.95,
    volume=1.0,
    origin=None,
    compliance=None,
) -> dict[str, Constraints]:
    """The thesis's skin constraint set (sec. 5.5): stretch along every edge, stretch between
    the opposite vertices of adjacent triangles, bending on every interior edge, area on every
    triangle and one volume constraint, rest values measured on the mesh.

    Args:
        mesh: a :class:`jaxface.mesh.TriMesh`, or ``(V, 3)`` mm vertices with ``triangles``.
        triangles: ``(F, 3)`` int when ``mesh`` is a vertex array.
        stretch, cross, bend, area, volume: stiffness of each kind (thesis values 0.15, 0.15,
            0.95, 0.95, 1.0; ``cross`` defaults to ``stretch``); ``None`` or 0 leaves the kind
            out.
        origin: ``(3,)`` mm cap point of the volume (see :class:`VolumeConstraint`).
        compliance: optional dict kind -> XPBD compliance (e.g. ``{"stretch": 1e-6}``).

    Returns:
        dict with keys ``"stretch"``, ``"cross"``, ``"bend"``, ``"area"``, ``"volume"`` (those
        enabled), ready for :func:`build_system`.
    """
    from .mesh import TriMesh

    if not isinstance(mesh, TriMesh):
        mesh = TriMesh(mesh, triangles)
    x = mesh.vertices
    comp = dict(compliance or {})
    cross = stretch if cross is None else cross
    out: dict[str, Constraints] = {}
    if stretch:
        out["stretch"] = distance_constraints(
            mesh.edges, x, stiffness=stretch, compliance=comp.get("stretch")
        )
    pairs = mesh.edge_pairs
    if cross and len(pairs):
        out["cross"] = distance_constraints(
            pairs[:, 2:], x, stiffness=cross, compliance=comp.get("cross")
        )
    if bend and len(pairs):
        out["bend"] = bending_constraints(pairs, x, stiffness=bend, compliance=comp.get("bend"))
    if area:
        out["area"] = area_constraints(
            mesh.triangles, x, stiffness=area, compliance=comp.get("area")
        )
    if volume:
        out["volume"] = volume_constraint(
            mesh.triangles, x, origin=origin, stiffness=volume, compliance=comp.get("volume")
        )
    return out


# ----------------------------------------------------------------------------------------
# the system
# ----------------------------------------------------------------------------------------


class System(eqx.Module):
    """All constraints of a particle system plus the inverse masses (a JAX pytree).

    Build with :func:`build_system`. Groups are projected in the order given there (thesis:
    in the order the constraints were defined), each group colour by colour.

    Attributes:
        groups: tuple of constraint groups (:class:`jaxface.constraints.Constraints`),
            arranged in balanced colour blocks.
        inv_mass: ``(N,)`` inverse masses, 1/g (0 = kinematic: never moved by constraints).
        counts: ``(N,)`` number of bilateral constraints acting on each particle (Jacobi).
        names: static tuple of group names.
        n_dummy: static number of inert dummy particles the colour padding points at.
    """

    groups: tuple
    inv_mass: jax.Array
    counts: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)
    n_dummy: int = eqx.field(static=True)

    @property
    def n_particles(self) -> int:
        """Number of particles ``N``."""
        return int(self.inv_mass.shape[0])

    def __getitem__(self, name: str) -> Constraints:
        return self.groups[self._index(name)]

    def _index(self, name):
        try:
            return self.names.index(name)
        except ValueError:
            raise MeshError(
                f"no constraint group named {name!r}; groups: {list(self.names)}.",
                problem="unknown_group",
            ) from None

    def set(self, name: str, **fields) -> System:
        """Copy with fields of group ``name`` replaced (user order, differentiable), e.g.
        ``system.set("anchors", target=t)`` or ``system.set("teeth", normals=n, offsets=d)``."""
        i = self._index(name)
        g = self.groups[i].set(**fields)
        return eqx.tree_at(lambda s: s.groups[i], self, g)

    def with_inv_mass(self, inv_mass) -> System:
        """Copy with new inverse masses ``(N,)`` 1/g."""
        w = jnp.asarray(inv_mass, self.inv_mass.dtype)
        if w.shape != self.inv_mass.shape:
            raise MeshError(
                f"inv_mass must have shape {self.inv_mass.shape}, got {w.shape}.",
                problem="shape",
            )
        return eqx.tree_at(lambda s: s.inv_mass, self, w)

    def residuals(self, x) -> dict[str, jax.Array]:
        """Per-group violations at ``x`` ``(N, 3)`` mm, user order: ``|C|`` (bilateral) or
        ``max(-C, 0)`` (unilateral), in the unit of each kind (mm, rad, mm^2, mm^3)."""
        return {n: g.violation(x) for n, g in zip(self.names, self.groups)}

    def max_violation(self, x) -> dict[str, jax.Array]:
        """Largest violation of each group at ``x`` (scalars, units as in :meth:`residuals`)."""
        return {n: jnp.max(r) if r.size else jnp.zeros(()) for n, r in self.residuals(x).items()}


def build_system(constraints, inv_mass) -> System:
    """Assemble constraint groups into a :class:`System` (NumPy, build time).

    Colours every group (greedy + balancing, :func:`jaxface.coloring.balanced_coloring`) and
    arranges it in ``(K, S)`` colour blocks; the volume constraint's triangles are coloured
    for conflict-free gradient summation.

    Args:
        constraints: mapping name -> group (or a sequence of ``(name, group)``), projected in
            this order.
        inv_mass: ``(N,)`` inverse masses 1/g (0 = kinematic), or an int ``N`` for unit masses.

    Raises:
        MeshError: inverse masses not finite / negative, a group referring to particles
            ``>= N``, duplicate or non-string names, or an object that is not a constraint group.
    """
    if isinstance(inv_mass, (int, np.integer)):
        w = np.ones(int(inv_mass))
    else:
        w = np.asarray(inv_mass, np.float64)
    if w.ndim != 1 or w.size == 0:
        raise MeshError(
            f"inv_mass must be a non-empty (N,) array, got shape {w.shape}.", problem="shape"
        )
    bad = np.flatnonzero(~np.isfinite(w) | (w < 0))
    if bad.size:
        raise MeshError(
            f"inverse masses of particles {bad[:10].tolist()} are negative or not finite; "
            "use 0 for kinematic particles.",
            problem="bad_inverse_mass",
            elements=bad[:100],
        )
    n = w.size
    items = list(constraints.items()) if isinstance(constraints, Mapping) else list(constraints)
    names, groups = [], []
    counts = np.zeros(n, np.int64)
    for name, g in items:
        if not isinstance(name, str) or name in names:
            raise MeshError(
                f"constraint group names must be unique strings, got {name!r}.", problem="bad_name"
            )
        if not isinstance(g, Constraints):
            raise MeshError(
                f"group {name!r} is a {type(g).__name__}, not a constraint group; build it "
                "with jaxface.pbd.*_constraints().",
                problem="bad_group",
            )
        g = g.user_order()
        idx = np.asarray(g.idx)
        if idx.size and int(idx.max()) >= n:
            rows = np.flatnonzero((idx >= n).any(1))
            raise MeshError(
                f"group {name!r}: constraints {rows[:10].tolist()} refer to particles >= N = "
                f"{n}; the system has {n} particles.",
                problem="index_out_of_range",
                elements=rows[:100],
            )
        g = g.arrange(balanced_coloring(idx, n), n)
        if isinstance(g, VolumeConstraint):
            counts += np.bincount(np.unique(idx), minlength=n)
        elif not g.unilateral:
            counts += particle_counts(idx, n)
        names.append(name)
        groups.append(g)
    return System(
        groups=tuple(groups),
        inv_mass=to_jax(w),
        counts=to_jax(counts.astype(np.float64)),
        names=tuple(names),
        n_dummy=max([g.n_dummy for g in groups], default=0),
    )


# ----------------------------------------------------------------------------------------
# solver core
# ----------------------------------------------------------------------------------------


def _cast(tree, dtype):
    def f(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(dtype)
        return a

    return jax.tree.map(f, tree)


def _gather(xs, ids, unique=True):
    """Positions of particles ``ids`` as a ``(3, m)`` array from the 3 coordinate arrays."""
    return jnp.stack([q.at[ids].get(unique_indices=unique, mode="promise_in_bounds") for q in xs])


def _scatter_add(xs, ids, dp):
    """Add ``dp`` ``(3, m)`` to particles ``ids`` (unique within a colour)."""
    return tuple(
        q.at[ids].add(dp[i], unique_indices=True, mode="promise_in_bounds")
        for i, q in enumerate(xs)
    )


def _scatter_add_all(xs, ids, dps):
    """Add the corrections ``dps`` (one ``(3, m)`` per endpoint) to the particles ``ids`` (one
    ``(m,)`` per endpoint), coordinate by coordinate (independent chains per coordinate)."""
    out = []
    for c, q in enumerate(xs):
        for i, dp in zip(ids, dps):
            q = q.at[i].add(dp[c], unique_indices=True, mode="promise_in_bounds")
        out.append(q)
    return tuple(out)


def _extend(a, n):
    return a if n == 0 else jnp.concatenate([a, jnp.zeros((n,) + a.shape[1:], a.dtype)])


def _project_block(g, P, W, A, lam):
    """Corrections of one colour block of group ``g`` (a block view).

    Args: P gathered positions (arity x (3, S)); W (arity, S) inverse masses; A alpha/dt^2 (S,)
    or None; lam the block's multipliers or None.

    Returns: (list of dp (3, S) per endpoint, dlam or None, active mask (S,) or None).
    """
    if isinstance(g, AnchorConstraints):
        dp, dlam = g.project(P[0], W[0], A, lam)
        return [dp], dlam, None
    if A is None and isinstance(g, DistanceConstraints):
        return g.project_pbd(P, W), None, None
    C, grads, g2 = g.terms(P)
    denom = W[0] * g2[0]
    for k in range(1, len(P)):
        denom = denom + W[k] * g2[k]
    kk = g.stiffness
    if A is None:
        ok = denom > 0
        dlam = jnp.where(ok, -kk * C / jnp.where(ok, denom, 1.0), 0.0)
        if g.unilateral:
            dlam = jnp.where(C < 0, dlam, 0.0)
        new = None
    else:
        den = denom + A
        ok = den > 0
        dlam = jnp.where(ok, kk * (-C - A * lam) / jnp.where(ok, den, 1.0), 0.0)
        if g.unilateral:
            dlam = jnp.maximum(lam + dlam, 0.0) - lam
        new = dlam
    dps = [(W[k] * dlam) * grads[k] for k in range(len(P))]
    active = (dlam != 0) if g.unilateral else None
    return dps, new, active


def _volume_correction(g, xs, w_ext, dt, lam):
    """Dense correction (3 arrays) of a volume constraint, and its multiplier increment."""
    K, S = g.layout
    P = [_gather(xs, g.idx[:, k], unique=False) for k in range(3)]
    V, gt = g.volume_terms(P)
    ids = g.idx.reshape(K, S, 3)
    gtb = tuple(q.reshape(3, K, S).transpose(1, 0, 2) for q in gt)

    def body(G, inp):
        idc, gc = inp
        for k in range(3):
            G = _scatter_add(G, idc[:, k], gc[k])
        return G, None

    z = jnp.zeros_like(xs[0])
    G, _ = jax.lax.scan(body, (z, z, z), (ids, gtb))
    denom = jnp.sum(w_ext * (G[0] ** 2 + G[1] ** 2 + G[2] ** 2))
    C = V - g.rest[0]
    kk = g.stiffness[0]
    if g.compliance is None:
        ok = denom > 0
        dlam = jnp.where(ok, -kk * C / jnp.where(ok, denom, 1.0), 0.0)
        new = None
    else:
        A = g.compliance[0] / (dt * dt)
        den = denom + A
        ok = den > 0
        dlam = jnp.where(ok, kk * (-C - A * lam[0]) / jnp.where(ok, den, 1.0), 0.0)
        new = dlam[None]
    return tuple(w_ext * dlam * Gk for Gk in G), new


def _block_inputs(g, w_ext):
    """Loop-invariant scan inputs of a group: the per-constraint fields as ``(K, S, ...)``
    blocks, the particle ids per endpoint ``(K, arity, S)`` and their inverse masses
    ``(K, arity, S)``."""
    if isinstance(g, VolumeConstraint):
        return None
    blocks = g.blocks()
    idx = blocks.pop("idx")  # (K, S, arity)
    # one (K, S) array per endpoint: slicing a middle axis inside the scan body keeps XLA CPU
    # from vectorising the fused kernels (measured 2x slower)
    ids = tuple(idx[:, :, k] for k in range(g.arity))
    return blocks, ids, tuple(w_ext[i] for i in ids)


def _gs_group(g, inputs, xs, lam, dt):
    blocks, IDS, W = inputs

    def body(xs, inp):
        flds, ids, Wc, lamc = inp
        gc = g.block_view(flds)
        P = [_gather(xs, i) for i in ids]
        A = None if gc.compliance is None else gc.compliance / (dt * dt)
        dps, dlam, _ = _project_block(gc, P, Wc, A, lamc)
        xs = _scatter_add_all(xs, ids, dps)
        return xs, (None if dlam is None else lamc + dlam)

    return jax.lax.scan(body, xs, (blocks, IDS, W, lam))


def _jacobi_group(g, inputs, xs, acc, dyn, lam, dt):
    blocks, IDS, W = inputs

    def body(carry, inp):
        acc, dyn = carry
        flds, ids, Wc, lamc = inp
        gc = g.block_view(flds)
        P = [_gather(xs, i) for i in ids]
        A = None if gc.compliance is None else gc.compliance / (dt * dt)
        dps, dlam, active = _project_block(gc, P, Wc, A, lamc)
        acc = _scatter_add_all(acc, ids, dps)
        if active is not None:
            dyn = dyn.at[ids[0]].add(
                active.astype(dyn.dtype), unique_indices=True, mode="promise_in_bounds"
            )
        return (acc, dyn), (None if dlam is None else lamc + dlam)

    (acc, dyn), lam = jax.lax.scan(body, (acc, dyn), (blocks, IDS, W, lam))
    return acc, dyn, lam


def _sweep(system, inputs, w_ext, cnt_ext, scheme, omega, dt, xs, lams):
    lams = list(lams)
    if scheme == "gs":
        for gi, g in enumerate(system.groups):
            if isinstance(g, VolumeConstraint):
                dp, dl = _volume_correction(g, xs, w_ext, dt, lams[gi])
                xs = tuple(q + d for q, d in zip(xs, dp))
                if dl is not None:
                    lams[gi] = lams[gi] + dl
            else:
                xs, lams[gi] = _gs_group(g, inputs[gi], xs, lams[gi], dt)
        return xs, tuple(lams)
    z = jnp.zeros_like(xs[0])
    acc, dyn = (z, z, z), z
    for gi, g in enumerate(system.groups):
        if isinstance(g, VolumeConstraint):
            dp, dl = _volume_correction(g, xs, w_ext, dt, lams[gi])
            acc = tuple(q + d for q, d in zip(acc, dp))
            if dl is not None:
                lams[gi] = lams[gi] + dl
        else:
            acc, dyn, lams[gi] = _jacobi_group(g, inputs[gi], xs, acc, dyn, lams[gi], dt)
    scale = omega / jnp.maximum(cnt_ext + dyn, 1.0)
    return tuple(q + scale * a for q, a in zip(xs, acc)), tuple(lams)


def _zero_lambdas(system, dtype):
    return tuple(
        None if g.compliance is None else jnp.zeros(g.lambda_shape(), dtype) for g in system.groups
    )


def _iterate(system, xs, *, iterations, scheme, omega, dt, checkpoint_every):
    """``iterations`` sweeps from positions ``xs`` (3 arrays (N,)), multipliers from zero."""
    if scheme not in ("gs", "jacobi"):
        raise MeshError(f"unknown scheme {scheme!r}; use 'gs' or 'jacobi'.", problem="bad_option")
    if iterations < 0:
        raise MeshError(f"iterations must be >= 0, got {iterations}.", problem="bad_option")
    if checkpoint_every is not None and int(checkpoint_every) < 1:
        raise MeshError(
            f"checkpoint_every must be >= 1 or None, got {checkpoint_every}.", problem="bad_option"
        )
    if iterations == 0:
        return xs
    D = system.n_dummy
    dtype = xs[0].dtype
    w_ext = _extend(system.inv_mass, D)
    cnt_ext = _extend(system.counts, D)
    xs = tuple(_extend(q, D) for q in xs)
    lams = _zero_lambdas(system, dtype)
    inputs = [_block_inputs(g, w_ext) for g in system.groups]

    def sweep(c):
        return _sweep(system, inputs, w_ext, cnt_ext, scheme, omega, dt, *c)

    def run(c, n):
        if n == 1:
            return sweep(c)
        return jax.lax.fori_loop(0, n, lambda i, cc: sweep(cc), c)

    carry = (xs, lams)
    if checkpoint_every is None:
        carry = run(carry, iterations)
    else:
        B = min(int(checkpoint_every), iterations)
        nb, rem = divmod(iterations, B)
        blk = jax.checkpoint(lambda c: run(c, B), prevent_cse=False)
        carry = jax.lax.fori_loop(0, nb, lambda i, c: blk(c), carry) if nb > 1 else blk(carry)
        if rem:
            carry = jax.checkpoint(lambda c: run(c, rem), prevent_cse=False)(carry)
    n = system.n_particles
    return tuple(q[:n] for q in carry[0])


def _check_x(system, x, what="x"):
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    if x.ndim != 2 or x.shape != (system.n_particles, 3):
        raise MeshError(
            f"{what} must have shape ({system.n_particles}, 3) mm (one row per particle), got "
            f"{tuple(x.shape)}.",
            problem="shape",
        )
    return x


@eqx.filter_jit
def project(
    system: System,
    x,
    *,
    iterations: int,
    scheme: Scheme = DEFAULT_SCHEME,
    omega: float = DEFAULT_OMEGA,
    dt: float = DEFAULT_DT,
    checkpoint_every: int | None = 1,
):
    """Run ``iterations`` projection sweeps over all constraints from positions ``x``
    (thesis loop lines 8-10), XPBD multipliers starting at zero.

    Args:
        system: the :class:`System`.
        x: ``(N, 3)`` mm predicted positions.
        iterations: static number of sweeps.
        scheme: ``"gs"`` (graph-coloured Gauss-Seidel) or ``"jacobi"``.
        omega: Jacobi over-relaxation (ignored by ``"gs"``).
        dt: s, time step for XPBD ``alpha / dt^2``.
        checkpoint_every: iterations per ``jax.checkpoint`` block (``None``: no
            checkpointing). Only affects reverse-mode memory and time.

    Returns:
        ``(N, 3)`` mm projected positions, same dtype as ``x``.
    """
    x = _check_x(system, x)
    sysd = _cast(system, x.dtype)
    xs = (x[:, 0], x[:, 1], x[:, 2])
    xs = _iterate(
        sysd,
        xs,
        iterations=iterations,
        scheme=scheme,
        omega=omega,
        dt=dt,
        checkpoint_every=checkpoint_every,
    )
    return jnp.stack(xs, axis=1)


@eqx.filter_jit
def relax(
    system: System,
    x,
    *,
    iterations: int,
    passes: int = 1,
    scheme: Scheme = DEFAULT_SCHEME,
    omega: float = DEFAULT_OMEGA,
    dt: float = DEFAULT_DT,
    checkpoint_every: int | None = 1,
):
    """Quasi-static solve: projections from ``x`` without inertia (no prediction, no velocity).

    ``passes`` blocks of ``iterations`` sweeps; XPBD multipliers are reset at the start of
    every pass (each pass is one implicit step from rest, so more passes approach the
    minimum of ``sum C^2 / 2 alpha``); for plain PBD groups this is simply
    ``passes * iterations`` sweeps.

    Args:
        system: the :class:`System` (anchor targets, planes, ... already set).
        x: ``(N, 3)`` mm start positions (kinematic particles stay where they are).
        iterations, passes: static ints.
        scheme, omega, dt, checkpoint_every: as in :func:`project`.

    Returns:
        ``(N, 3)`` mm relaxed positions.
    """
    x = _check_x(system, x)
    sysd = _cast(system, x.dtype)
    xs = (x[:, 0], x[:, 1], x[:, 2])

    def one(xs):
        return _iterate(
            sysd,
            xs,
            iterations=iterations,
            scheme=scheme,
            omega=omega,
            dt=dt,
            checkpoint_every=checkpoint_every,
        )

    if passes == 1:
        xs = one(xs)
    elif passes > 1:
        xs = jax.lax.fori_loop(0, passes, lambda i, c: one(c), xs)
    return jnp.stack(xs, axis=1)


class Particles(eqx.Module):
    """Dynamic state of the particles (the inverse masses live in the :class:`System`).

    Attributes:
        x: ``(N, 3)`` mm positions.
        v: ``(N, 3)`` mm/s velocities.
    """

    x: jax.Array
    v: jax.Array

    @classmethod
    def at_rest(cls, x) -> Particles:
        """Particles at ``x`` ``(N, 3)`` mm with zero velocity."""
        x = jnp.asarray(x)
        return cls(x=x, v=jnp.zeros_like(x))


def _damp_rigid(x, v, w, k):
    """Mueller et al. 2006 sec. 3.5: damp the velocity deviation from the rigid motion of the
    dynamic particles (conserves linear and angular momentum)."""
    dyn = w > 0
    m = jnp.where(dyn, 1.0 / jnp.where(dyn, w, 1.0), 0.0)
    M = jnp.maximum(jnp.sum(m), jnp.finfo(x.dtype).tiny)
    xcm = jnp.sum(m[:, None] * x, 0) / M
    vcm = jnp.sum(m[:, None] * v, 0) / M
    r = x - xcm
    L = jnp.sum(m[:, None] * jnp.cross(r, v), 0)
    r2 = jnp.sum(r * r, 1)
    eye = jnp.eye(3, dtype=x.dtype)
    inertia = jnp.einsum("i,ijk->jk", m, r2[:, None, None] * eye - r[:, :, None] * r[:, None, :])
    reg = 1e-9 * jnp.trace(inertia) + jnp.finfo(x.dtype).tiny
    omega = jnp.linalg.solve(inertia + reg * eye, L)
    dv = vcm + jnp.cross(omega, r) - v
    return v + jnp.where(dyn[:, None], k * dv, 0.0)


def _advance(
    system,
    particles,
    *,
    iterations,
    dt,
    damping,
    damping_mode,
    gravity,
    external_force,
    scheme,
    omega,
    checkpoint_every,
):
    x = _check_x(system, particles.x, "particles.x")
    v = jnp.asarray(particles.v, x.dtype)
    sysd = _cast(system, x.dtype)
    w = sysd.inv_mass
    dyn = (w > 0)[:, None]
    # damping first, then the external forces: damping applied after the forces (the order of
    # Mueller et al. 2006) would scale the steady-state load by (1 - damping)
    if damping:
        if damping_mode == "linear":
            v = jnp.where(dyn, (1.0 - damping) * v, v)
        elif damping_mode == "rigid":
            v = _damp_rigid(x, v, w, damping)
        else:
            raise MeshError(
                f"unknown damping_mode {damping_mode!r}; use 'linear' or 'rigid'.",
                problem="bad_option",
            )
    if external_force is not None:
        v = v + dt * w[:, None] * jnp.asarray(external_force, x.dtype)
    if gravity is not None:
        v = v + jnp.where(dyn, dt * jnp.asarray(gravity, x.dtype), 0.0)
    p = x + dt * v
    ps = (p[:, 0], p[:, 1], p[:, 2])
    ps = _iterate(
        sysd,
        ps,
        iterations=iterations,
        scheme=scheme,
        omega=omega,
        dt=dt,
        checkpoint_every=checkpoint_every,
    )
    p = jnp.stack(ps, axis=1)
    return Particles(x=p, v=(p - x) / dt)


@eqx.filter_jit
def step(
    system: System,
    particles: Particles,
    *,
    iterations: int,
    dt: float = DEFAULT_DT,
    damping: float = DEFAULT_DAMPING,
    damping_mode: Literal["linear", "rigid"] = "linear",
    gravity=None,
    external_force=None,
    scheme: Scheme = DEFAULT_SCHEME,
    omega: float = DEFAULT_OMEGA,
    checkpoint_every: int | None = 1,
) -> Particles:
    """One PBD time step (thesis sec. 3.2 loop, lines 5-14).

    Args:
        system: the :class:`System`.
        particles: state at time t (``x`` mm, ``v`` mm/s).
        iterations: static number of projection sweeps.
        dt: s, fixed time step (16.6 ms).
        damping: in ``[0, 1]`` (thesis 0.2); ``damping_mode`` ``"linear"`` (``v *= 1 - k`` for
            dynamic particles) or ``"rigid"`` (Mueller et al. 2006, momentum conserving).
        gravity: ``(3,)`` mm/s^2 acceleration of the dynamic particles, or ``None``.
        external_force: ``(N, 3)`` forces (g mm / s^2), or ``None``.
        scheme, omega, checkpoint_every: as in :func:`project`.

    Returns:
        :class:`Particles` at ``t + dt``.
    """
    return _advance(
        system,
        particles,
        iterations=iterations,
        dt=dt,
        damping=damping,
        damping_mode=damping_mode,
        gravity=gravity,
        external_force=external_force,
        scheme=scheme,
        omega=omega,
        checkpoint_every=checkpoint_every,
    )


@eqx.filter_jit
def simulate(
    system: System,
    particles: Particles,
    *,
    steps: int,
    iterations: int,
    dt: float = DEFAULT_DT,
    damping: float = DEFAULT_DAMPING,
    damping_mode: Literal["linear", "rigid"] = "linear",
    gravity=None,
    external_force=None,
    scheme: Scheme = DEFAULT_SCHEME,
    omega: float = DEFAULT_OMEGA,
    checkpoint_every: int | None = 1,
    record: bool = False,
):
    """``steps`` time steps of :func:`step` (``lax.scan``).

    Returns:
        the final :class:`Particles`; with ``record=True`` also the positions after every step,
        ``(steps, N, 3)`` mm.
    """

    def body(ps, _):
        new = _advance(
            system,
            ps,
            iterations=iterations,
            dt=dt,
            damping=damping,
            damping_mode=damping_mode,
            gravity=gravity,
            external_force=external_force,
            scheme=scheme,
            omega=omega,
            checkpoint_every=checkpoint_every,
        )
        return new, (new.x if record else None)

    x = _check_x(system, particles.x, "particles.x")
    particles = Particles(x=x, v=jnp.asarray(particles.v, x.dtype))
    final, xs = jax.lax.scan(body, particles, None, length=steps)
    return (final, xs) if record else final
