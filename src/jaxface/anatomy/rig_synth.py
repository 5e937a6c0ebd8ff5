"""The PBD face rig and its synthesis (thesis sec. 5.7): :class:`RigInfo` (build-time NumPy
objects), the :class:`Rig` pytree, :func:`synthesize` (quasi-static; jit, vmap, grad, jvp),
:func:`synthesize_state`, :func:`equilibrium_gap` and the dynamic :func:`simulate`.
Units: mm, degrees (jaw angles).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .. import pbd
from ..errors import RigError
from ..validate import checked_controls
from .jaw import JawModel, JawPose
from .muscles import (
    MuscleSystem,
    moved_skull_points,
    muscle_sweep,
    solve_muscles,
)
from .rig_common import BuildInfo, RigBase, check_activations, check_jaw
from .skin import (
    SkinSystem,
    skin_targets,
    solve_skin,
)


class RigInfo(BuildInfo):
    """Build-time (NumPy) objects of a PBD rig (:class:`~jaxface.anatomy.rig_common.BuildInfo`:
    skin, landmarks, frame, skull, placed, specs; compared by identity), and:

    Attributes:
        binding: the skin :class:`~jaxface.anatomy.skin.Binding`; influence: ``(V,)`` the
        influence map; registry: the placement registry of the bones and muscles.
    """

    binding: Any
    influence: Any
    registry: Any


class Rig(RigBase, eqx.Module):
    """A face rig (JAX pytree): the model of one face, on the PBD backend. The control
    accessors (``n_controls``, ``triangles``, ``index``, ``activations``) are
    :class:`~jaxface.anatomy.rig_common.RigBase`'s.

    Attributes:
        jaw: :class:`JawModel`.
        muscles: :class:`~jaxface.anatomy.muscles.MuscleSystem`.
        skin: :class:`~jaxface.anatomy.skin.SkinSystem`.
        muscle_names: static tuple, the order of the activation vector.
        muscle_aus: static tuple of the AUs of each control.
        info: static :class:`RigInfo` (build-time objects).
    """

    backend = "pbd"  # which simulator synthesize() runs; LTWRig says "ltw"

    jaw: JawModel
    muscles: MuscleSystem
    skin: SkinSystem
    muscle_names: tuple = eqx.field(static=True)
    muscle_aus: tuple = eqx.field(static=True)
    info: RigInfo = eqx.field(static=True)

    @property
    def n_vertices(self) -> int:
        """Number of skin vertices ``V``."""
        return self.skin.n_vertices

    @property
    def rest(self) -> jax.Array:
        """``(V, 3)`` rest skin, mm."""
        return self.skin.rest

    def synthesize(
        self, activations, jaw: JawPose | None = None, cheek_puff: ArrayLike = 0.0
    ) -> jax.Array:
        """:func:`synthesize` of this rig: ``(V, 3)`` skin, mm (the
        :class:`~jaxface.anatomy.interface.FaceRig` method)."""
        return synthesize(self, activations, jaw, cheek_puff)

    def with_iterations(
        self,
        muscles: int | None = None,
        skin: int | None = None,
        *,
        muscle_rho: float | None = None,
        skin_rho: float | None = None,
        checkpoint: bool | None = None,
    ) -> Rig:
        """A copy with other static sweep counts (e.g. many for a converged reference) and,
        optionally, other Chebyshev spectral-radius estimates of the two quasi-static solves
        (:func:`jaxface.pbd.iterate`; 0 = plain sweeps). ``muscle_rho`` is for
        experiments only: the muscle iteration is too non-linear for it (see
        :func:`build_rig`, ``skin_chebyshev_rho``). ``checkpoint`` turns the per-sweep
        ``jax.checkpoint`` of both solves on or off (by default the skin's is on, the
        muscles' off): it only changes the reverse pass's memory and time.

        Raises:
            RigError: a sweep count below 1 or a spectral radius outside ``[0, 1)``.
        """
        for label, v in (("muscles", muscles), ("skin", skin)):
            if v is not None and int(v) < 1:
                raise RigError(f"{label} sweeps must be at least 1, got {v}.")
        for label, v in (("muscle_rho", muscle_rho), ("skin_rho", skin_rho)):
            if v is not None:
                pbd.check_rho(v, f"{label} (a Chebyshev spectral-radius estimate)")
        r = self
        mk, sk = {}, {}
        if muscles is not None:
            mk["iterations"] = int(muscles)
        if muscle_rho is not None:
            mk["chebyshev_rho"] = float(muscle_rho)
        if skin is not None:
            sk["iterations"] = int(skin)
        if skin_rho is not None:
            sk["chebyshev_rho"] = float(skin_rho)
        if checkpoint is not None:
            mk["checkpoint"] = sk["checkpoint"] = bool(checkpoint)
        if mk:
            r = eqx.tree_at(lambda q: q.muscles, r, _replace_static(r.muscles, **mk))
        if sk:
            r = eqx.tree_at(lambda q: q.skin, r, _replace_static(r.skin, **sk))
        return r


def _replace_static(module, **kw):
    return dataclasses.replace(module, **kw)


class SynthState(eqx.Module):
    """Everything a synthesis computes (for tests and pictures).

    Attributes:
        skin: ``(V, 3)`` mm; muscles: ``(Nm, 3)`` mm; targets: ``(V, 3)`` skin anchor
        targets, mm; R, t: the mandible motion.
    """

    skin: jax.Array
    muscles: jax.Array
    targets: jax.Array
    R: jax.Array
    t: jax.Array


def _synth(rig: Rig, activations, jaw: JawPose | None, cheek_puff):
    a = check_activations(rig, activations)
    jaw = check_jaw(jaw)
    dt = jnp.result_type(a.dtype, jaw.pitch_deg.dtype)
    a = a.astype(dt)
    R, t = rig.jaw.transform(jaw)
    R, t = R.astype(dt), t.astype(dt)
    xm, skull = solve_muscles(rig.muscles, a, R, t)
    G = rig.muscles.support(skull, xm)
    tg = skin_targets(rig.skin, G, a, jnp.asarray(cheek_puff, dt))
    x = solve_skin(rig.skin, tg, R, t)
    return SynthState(skin=x, muscles=xm, targets=tg, R=R, t=t)


@eqx.filter_jit
def synthesize_state(
    rig: Rig, activations, jaw: JawPose | None = None, cheek_puff: ArrayLike = 0.0
) -> SynthState:
    """:func:`synthesize`, returning the whole :class:`SynthState`."""
    return _synth(rig, activations, jaw, cheek_puff)


@eqx.filter_jit
def equilibrium_gap(
    rig: Rig,
    activations,
    jaw: JawPose | None = None,
    cheek_puff: ArrayLike = 0.0,
    *,
    sweeps: tuple[int, int] = (1000, 1000),
):
    """How far a synthesis still is from the equilibrium it is heading for, mm per vertex.

    The synthesis of ``rig`` (at its own sweep counts) is continued with ``sweeps`` =
    ``(muscle, skin)`` more *plain* sweeps, warm-started from its muscles and its skin, and the
    distance each skin vertex moves on the way is returned. A converged synthesis moves
    nowhere.

    This measures convergence where a distance to a deep solve from rest cannot: with contact
    against the teeth, and where compressed skin buckles (under the brows in a smile, in the
    crease under the chin of an open jaw), the quasi-static problem has more than one
    equilibrium, and an accelerated solve can settle in another one than plain sweeps from
    rest reach. Such a result is converged (it is a fixed point of the sweep) although it lies
    away from the plain solve's. Where the equilibrium is unique the two measures agree.

    Args:
        rig: a :class:`Rig` (the PBD backend).
        activations: ``(M,)`` in [0, 1], ordered as ``rig.muscle_names``.
        jaw: :class:`JawPose` (degrees, mm); neutral if None.
        cheek_puff: AU33/34 pressure in [0, 1], or ``[left, right]``.
        sweeps: static ``(muscle, skin)`` plain sweeps of the continuation. 1,000 skin sweeps
            are slow enough to show a creeping buckle (a plain 64-sweep solve of a smile on
            the ICT face still moves 0.34 mm in them) and cheap next to a deep solve.

    Returns:
        ``(V,)`` mm, the distance from the synthesis to its continuation. Jit-compiled and
        vmap-able; a diagnostic, not meant for differentiation.

    Raises:
        RigError: an LTW rig, a sweep count below 1, or activations of the wrong shape.
    """
    if rig.backend == "ltw":
        raise RigError(
            "equilibrium_gap measures the PBD solve; an LTW rig integrates in time "
            "(see jaxface.ltw.rig.synthesize_ltw and its steps)."
        )
    try:
        m_sweeps, s_sweeps = (int(v) for v in sweeps)
    except (TypeError, ValueError):
        raise RigError(f"sweeps must be two integers (muscle, skin), got {sweeps!r}.") from None
    if m_sweeps < 1 or s_sweeps < 1:
        raise RigError(f"sweeps must be at least 1 each, got {sweeps!r}.")
    st = _synth(rig, activations, jaw, cheek_puff)
    dt = st.skin.dtype
    a = check_activations(rig, activations).astype(dt)
    plain = rig.with_iterations(muscle_rho=0.0, skin_rho=0.0)
    xm, skull = solve_muscles(plain.muscles, a, st.R, st.t, iterations=m_sweeps, x0=st.muscles)
    tg = skin_targets(plain.skin, plain.muscles.support(skull, xm), a, jnp.asarray(cheek_puff, dt))
    x = solve_skin(plain.skin, tg, st.R, st.t, iterations=s_sweeps, x0=st.skin)
    return jnp.sqrt(jnp.sum((x - st.skin) ** 2, axis=1))


@checked_controls  # NaN / out-of-range controls refused (jaxface.validate)
@eqx.filter_jit
def synthesize(rig: Rig, activations, jaw: JawPose | None = None, cheek_puff: ArrayLike = 0.0):
    """Synthesize the face for muscle activations and a jaw pose (quasi-static).

    Args:
        rig: the :class:`Rig`, or any other :class:`~jaxface.anatomy.interface.FaceRig`
            (a :class:`jaxface.ltw.rig.LTWRig` from ``build_rig(..., backend="ltw")``).
        activations: ``(M,)`` in [0, 1], ordered as ``rig.muscle_names``.
        jaw: :class:`JawPose` (degrees, mm; smoothly clamped to the limits); neutral if None.
        cheek_puff: AU33/34 air pressure in [0, 1] (outward cheek displacement of
            ``puff_mm`` at 1; 0 = off), or ``[left, right]`` for each cheek on its own
            (:mod:`jaxface.anatomy.cheek_puff`).

    Returns:
        ``(V, 3)`` skin vertices, mm.

    Raises:
        RigError: activations of the wrong shape (use ``jax.vmap`` for batches).

    A rig built with ``backend="ltw"`` is synthesized by
    :func:`jaxface.ltw.rig.synthesize_ltw` (same controls, same units).
    """
    if rig.backend != "pbd":  # another backend's rig synthesizes itself (FaceRig)
        return rig.synthesize(activations, jaw, cheek_puff)
    return _synth(rig, activations, jaw, cheek_puff).skin


def simulate(
    rig: Rig,
    activations,
    jaw: JawPose | None = None,
    *,
    dt: float = 0.0166,
    damping: float = 0.2,
    muscle_sweeps: int = 4,
    skin_sweeps: int = 4,
    cheek_puff=None,
):
    """Dynamic animation (thesis sec. 5.7): one time step per frame.

    Each frame: jaw transform; ``muscle_sweeps`` sweeps of the muscles from the previous frame;
    skin anchors refreshed; the skin integrated with position-based dynamics (velocity damped
    by ``damping``, prediction ``p = x + dt v``, ``skin_sweeps`` sweeps of the constraints and
    collisions, ``v = (p - x) / dt``).

    Args:
        rig: the :class:`Rig`.
        activations: ``(T, M)`` per frame.
        jaw: :class:`JawPose` with ``(T,)`` leaves (neutral if None).
        dt: time step, s (16.6 ms).
        damping: velocity damping per step (thesis 0.2).
        muscle_sweeps, skin_sweeps: static sweeps per frame.
        cheek_puff: optional ``(T,)``.

    Returns:
        ``(T, V, 3)`` skin per frame, mm.
    """
    A = jnp.asarray(activations)
    if A.ndim != 2 or A.shape[1] != rig.n_controls:
        raise RigError(
            f"simulate needs activations of shape (T, {rig.n_controls}); got {tuple(A.shape)}."
        )
    T = A.shape[0]
    dtp = A.dtype if jnp.issubdtype(A.dtype, jnp.floating) else jnp.result_type(float)
    A = A.astype(dtp)
    if jaw is None:
        jaw = JawPose(jnp.zeros(T, dtp), jnp.zeros(T, dtp), jnp.zeros(T, dtp))
    puff = jnp.zeros(T, dtp) if cheek_puff is None else jnp.asarray(cheek_puff, dtp)
    return _simulate(
        rig, A, jaw, puff, float(dt), float(damping), int(muscle_sweeps), int(skin_sweeps)
    )


@eqx.filter_jit
def _simulate(rig, A, jaw, puff, dt, damping, muscle_sweeps, skin_sweeps):
    ms = rig.muscles
    dtp = A.dtype
    x_m0 = ms.rest.astype(dtp)
    x_s0 = rig.skin.rest.astype(dtp)
    v0 = jnp.zeros_like(x_s0)
    inv_m = ms.inv_mass.astype(dtp)

    def frame(carry, inp):
        xm, xs, v = carry
        a, pose, p = inp
        R, t = rig.jaw.transform(pose)
        R, t = R.astype(dtp), t.astype(dtp)
        skull = moved_skull_points(ms, R, t)
        xm = pbd.iterate(
            lambda x: muscle_sweep(ms, x, skull, a, inv_m),
            xm,
            muscle_sweeps,
            checkpoint_every=None,
        )
        tg = skin_targets(rig.skin, ms.support(skull, xm), a, p)
        new, v = pbd.time_step(
            lambda q: solve_skin(rig.skin, tg, R, t, iterations=skin_sweeps, x0=q),
            xs,
            v,
            rig.skin.inv_mass,
            dt=dt,
            damping=damping,
        )
        return (xm, new, v), new

    poses = JawPose(
        jaw.pitch_deg.astype(dtp), jaw.yaw_deg.astype(dtp), jaw.protrusion_mm.astype(dtp)
    )
    _, out = jax.lax.scan(frame, (x_m0, x_s0, v0), (A, poses, puff))
    return out
