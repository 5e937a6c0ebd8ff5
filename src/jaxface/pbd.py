"""Differentiable position-based dynamics (PBD / XPBD) in JAX: the engine of jaxface.

Implements thesis sec. 3.2 (Mueller et al. 2006 as summarised there, eqs. 3.11-3.23): one
projection per constraint kind (:mod:`jaxface.constraints`), one sweep with two static
schemes and Chebyshev acceleration (:mod:`jaxface.sweep`), XPBD compliance (Macklin et al.
2016) as an option, time stepping with damping, and a quasi-static mode. The face rig
(:mod:`jaxface.anatomy`) runs its muscles and skin on the same groups, sweep and time step.
Units: positions mm, velocities mm/s, time s, inverse masses 1/g, angles rad.

Model / state split
-------------------
* The model is built once in NumPy: constraint kinds (:func:`distance_constraints`, ...,
  :func:`skin_constraints`) assembled by :func:`build_system` into a :class:`System` pytree
  (groups with their Jacobi counts and, for Gauss-Seidel, colour blocks; inverse masses).
* What changes at run time is a float leaf: anchor targets, collision planes, rest values,
  stiffness, compliance, inverse masses (``system.set("anchors", target=t)``, also on traced
  values inside ``jax.jit``); the dynamic state is :class:`Particles`. All differentiable.
* The solvers (:func:`project`, :func:`relax`, :func:`step`, :func:`simulate`) are pure,
  ``eqx.filter_jit``-compiled, with static iteration counts, so ``jax.grad``, ``jax.jvp``,
  ``jax.jacfwd`` and ``jax.vmap`` go through a solve. ``checkpoint_every=B`` wraps blocks of
  ``B`` sweeps in ``jax.checkpoint`` (reverse mode stores one state per block).

Schemes (:mod:`jaxface.sweep`)
------------------------------
``scheme="jacobi"``: fused Jacobi, each group one vectorised block averaged per particle and
over-relaxed by the group's ``omega`` (groups in order): the rig's scheme, fastest per sweep on
a CPU. ``scheme="gs"`` (default of :class:`System`): graph-coloured Gauss-Seidel, exactly the
thesis's sequential sweep in colour order (:func:`jaxface.reference.solve`,
``order="color"``); fewer sweeps to converge. With plain-PBD stiffness ``k < 1`` the fixed
point depends on the scheme.

Time integration (thesis loop, lines 1-15, damping as in Mueller et al. 2006)
-----------------------------------------------------------------------------
:func:`time_step`: damping (``"linear"``: ``v *= 1 - damping``; ``"rigid"``: only the
non-rigid part of the motion, conserving linear and angular momentum); ``v += dt w f_ext +
dt g``; ``p = x + dt v``; project; ``v = (p - x) / dt``; ``x = p``. Damping comes *before*
the external forces so that the steady state under a constant load is the force balance.
Fixed ``dt`` 16.6 ms and damping 0.2 by default. With XPBD the equilibrium of a time-stepped
simulation is ``sum_j grad C_j C_j / alpha_j = f_ext``, independent of ``dt`` and of the
iteration count once each step's solve has converged.

Quasi-static mode (:func:`relax`): projections from the given positions without prediction or
velocity; for XPBD groups each of the ``passes`` is one implicit step from rest (multipliers
reset per pass), converging to the minimum of ``sum_j C_j^2 / (2 alpha_j)`` subject to the hard
constraints.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import to_jax
from .constraints import (
    AnchorConstraints,
    AreaConstraints,
    BendingConstraints,
    Constraints,
    DistanceConstraints,
    HalfSpaceConstraints,
    HullConstraints,
    VolumeConstraint,
    anchor_constraints,
    area_constraints,
    bending_constraints,
    dihedral_angle,
    distance_constraints,
    halfspace_constraints,
    hull_constraints,
    hull_planes,
    safe_norm,
    skin_constraints,
    transform_planes,
    volume_constraint,
)
from .errors import MeshError
from .sweep import Group, Scheme, check_rho, iterate, make_group, solve, sweep

__all__ = [
    "DEFAULT_DT",
    "DEFAULT_DAMPING",
    "DEFAULT_OMEGA",
    "DEFAULT_SCHEME",
    "System",
    "Group",
    "Scheme",
    "Particles",
    "build_system",
    "make_group",
    "sweep",
    "solve",
    "iterate",
    "check_rho",
    "time_step",
    "project",
    "relax",
    "step",
    "simulate",
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
DEFAULT_OMEGA = 1.0
"""Jacobi over-relaxation of a group of :func:`build_system` (the rig sets its own)."""
DEFAULT_SCHEME = "gs"
"""Default scheme of the :class:`System` solvers (the rig runs ``"jacobi"``)."""


class System(eqx.Module):
    """The model of a particle system: constraint groups plus inverse masses (a pytree).

    Build with :func:`build_system`. Groups are projected in the order given there.

    Attributes:
        groups: tuple of :class:`~jaxface.sweep.Group` (constraints in user order, Jacobi
            counts, colour blocks).
        inv_mass: ``(N,)`` inverse masses, 1/g (0 = kinematic: never moved by constraints).
        names: static tuple of group names.
    """

    groups: tuple[Group, ...]
    inv_mass: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def n_particles(self) -> int:
        """Number of particles ``N``."""
        return int(self.inv_mass.shape[0])

    def __getitem__(self, name: str) -> Constraints:
        """The constraints of group ``name`` (user order)."""
        return self.groups[self._index(name)].c

    def _index(self, name):
        try:
            return self.names.index(name)
        except ValueError:
            raise MeshError(
                f"no constraint group named {name!r}; groups: {list(self.names)}.",
                problem="unknown_group",
            ) from None

    def set(self, name: str, **fields) -> System:
        """Copy with fields of group ``name`` replaced (user order, differentiable, traced
        values allowed), e.g. ``system.set("anchors", target=t)`` or
        ``system.set("teeth", normals=n, offsets=d)``."""
        i = self._index(name)
        return eqx.tree_at(lambda s: s.groups[i], self, self.groups[i].set(**fields))

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
        return {n: g.c.violation(x) for n, g in zip(self.names, self.groups)}

    def max_violation(self, x) -> dict[str, jax.Array]:
        """Largest violation of each group at ``x`` (scalars, units as in :meth:`residuals`)."""
        return {n: jnp.max(r) if r.size else jnp.zeros(()) for n, r in self.residuals(x).items()}


def build_system(
    constraints, inv_mass, *, omega: float | Mapping[str, float] = DEFAULT_OMEGA, color=True
) -> System:
    """Assemble constraint groups into a :class:`System` (NumPy, build time).

    Args:
        constraints: mapping name -> constraints (or a sequence of ``(name, constraints)``),
            projected in this order.
        inv_mass: ``(N,)`` inverse masses 1/g (0 = kinematic), or an int ``N`` for unit masses.
        omega: Jacobi over-relaxation, one value or a mapping name -> value (default 1).
        color: build the Gauss-Seidel colour blocks (greedy + balanced colouring,
            :func:`jaxface.coloring.color_blocks`); needed by ``scheme="gs"``.

    Raises:
        MeshError: inverse masses not finite / negative, a group referring to particles
            ``>= N``, duplicate or non-string names, or an object that is not a constraint group.
    """
    if isinstance(inv_mass, int | np.integer):
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
    items = list(constraints.items()) if isinstance(constraints, Mapping) else list(constraints)
    names, groups = [], []
    for name, c in items:
        if not isinstance(name, str) or name in names:
            raise MeshError(
                f"constraint group names must be unique strings, got {name!r}.", problem="bad_name"
            )
        om = omega.get(name, DEFAULT_OMEGA) if isinstance(omega, Mapping) else omega
        groups.append(make_group(c, w.size, omega=om, name=name, color=color))
        names.append(name)
    return System(groups=tuple(groups), inv_mass=to_jax(w), names=tuple(names))


def _check_x(system: System, x, what="x"):
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
    dt: float = DEFAULT_DT,
    rho: float = 0.0,
    checkpoint_every: int | None = 1,
):
    """Run ``iterations`` projection sweeps over all constraints from positions ``x``
    (thesis loop lines 8-10), XPBD multipliers starting at zero.

    Args:
        system: the :class:`System`.
        x: ``(N, 3)`` mm predicted positions.
        iterations: static number of sweeps.
        scheme: ``"gs"`` (graph-coloured Gauss-Seidel) or ``"jacobi"`` (fused Jacobi).
        dt: s, time step for XPBD ``alpha / dt^2``.
        rho: static Chebyshev spectral-radius estimate (0 = plain sweeps).
        checkpoint_every: sweeps per ``jax.checkpoint`` block (``None``: no checkpointing).
            Only affects reverse-mode memory and time.

    Returns:
        ``(N, 3)`` mm projected positions, same dtype as ``x``.
    """
    x = _check_x(system, x)
    return solve(
        system.groups,
        x,
        system.inv_mass,
        iterations=iterations,
        scheme=scheme,
        rho=rho,
        dt=dt,
        checkpoint_every=checkpoint_every,
    )


@eqx.filter_jit
def relax(
    system: System,
    x,
    *,
    iterations: int,
    passes: int = 1,
    scheme: Scheme = DEFAULT_SCHEME,
    dt: float = DEFAULT_DT,
    rho: float = 0.0,
    checkpoint_every: int | None = 1,
):
    """Quasi-static solve: projections from ``x`` without inertia (no prediction, no velocity).

    ``passes`` blocks of ``iterations`` sweeps; XPBD multipliers are reset at the start of
    every pass (each pass is one implicit step from rest, so more passes approach the
    minimum of ``sum C^2 / 2 alpha``); for plain PBD groups this is ``passes * iterations``
    sweeps.

    Args:
        system: the :class:`System` (anchor targets, planes, ... already set).
        x: ``(N, 3)`` mm start positions (kinematic particles stay where they are).
        iterations, passes: static ints.
        scheme, dt, rho, checkpoint_every: as in :func:`project`.

    Returns:
        ``(N, 3)`` mm relaxed positions.
    """
    x = _check_x(system, x)

    def one(x):
        return solve(
            system.groups,
            x,
            system.inv_mass,
            iterations=iterations,
            scheme=scheme,
            rho=rho,
            dt=dt,
            checkpoint_every=checkpoint_every,
        )

    if passes == 1:
        return one(x)
    return jax.lax.fori_loop(0, max(int(passes), 0), lambda i, c: one(c), x)


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


def time_step(
    project_fn: Callable,
    x,
    v,
    inv_mass,
    *,
    dt: float = DEFAULT_DT,
    damping: float = DEFAULT_DAMPING,
    damping_mode: Literal["linear", "rigid"] = "linear",
    gravity=None,
    external_force=None,
):
    """One PBD time step (thesis sec. 3.2 loop, lines 5-14) around any projection.

    Args:
        project_fn: pure ``(N, 3) -> (N, 3)`` mm, the constraint projection of the predicted
            positions (:func:`relax` of a system, or the rig's skin solve).
        x: ``(N, 3)`` mm; v: ``(N, 3)`` mm/s; inv_mass: ``(N,)`` 1/g (0 = kinematic).
        dt: s; damping: in ``[0, 1]``; damping_mode: ``"linear"`` or ``"rigid"``.
        gravity: ``(3,)`` mm/s^2 acceleration of the dynamic particles, or ``None``.
        external_force: ``(N, 3)`` forces (g mm / s^2), or ``None``.

    Returns:
        ``(x', v')`` at ``t + dt`` (mm, mm/s).

    Raises:
        MeshError: an unknown damping mode.
    """
    w = inv_mass.astype(x.dtype)
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
    p = project_fn(x + dt * v)
    return p, (p - x) / dt


def _advance(system: System, particles: Particles, kw: dict, iterations: int, scheme, rho, ckpt):
    x = _check_x(system, particles.x, "particles.x")
    v = jnp.asarray(particles.v, x.dtype)

    def proj(p):
        return solve(
            system.groups,
            p,
            system.inv_mass,
            iterations=iterations,
            scheme=scheme,
            rho=rho,
            dt=kw["dt"],
            checkpoint_every=ckpt,
        )

    x, v = time_step(proj, x, v, system.inv_mass, **kw)
    return Particles(x=x, v=v)


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
    rho: float = 0.0,
    checkpoint_every: int | None = 1,
) -> Particles:
    """One PBD time step of a :class:`System` (:func:`time_step` around :func:`project`).

    Args:
        system: the :class:`System`.
        particles: state at time t (``x`` mm, ``v`` mm/s).
        iterations: static number of projection sweeps.
        dt, damping, damping_mode, gravity, external_force: as in :func:`time_step`.
        scheme, rho, checkpoint_every: as in :func:`project`.

    Returns:
        :class:`Particles` at ``t + dt``.
    """
    kw = dict(
        dt=dt,
        damping=damping,
        damping_mode=damping_mode,
        gravity=gravity,
        external_force=external_force,
    )
    return _advance(system, particles, kw, iterations, scheme, rho, checkpoint_every)


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
    rho: float = 0.0,
    checkpoint_every: int | None = 1,
    record: bool = False,
):
    """``steps`` time steps of :func:`step` (``lax.scan``).

    Returns:
        the final :class:`Particles`; with ``record=True`` also the positions after every step,
        ``(steps, N, 3)`` mm.
    """
    kw = dict(
        dt=dt,
        damping=damping,
        damping_mode=damping_mode,
        gravity=gravity,
        external_force=external_force,
    )

    def body(ps, _):
        new = _advance(system, ps, kw, iterations, scheme, rho, checkpoint_every)
        return new, (new.x if record else None)

    x = _check_x(system, particles.x, "particles.x")
    particles = Particles(x=x, v=jnp.asarray(particles.v, x.dtype))
    final, xs = jax.lax.scan(body, particles, None, length=steps)
    return (final, xs) if record else final
