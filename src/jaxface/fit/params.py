"""The unknowns of one scan's fit (:class:`Params`) and their maps to physical quantities.

Units and frame: millimetres, degrees; +y up, the face looks along +z, the subject's left is
+x. Every unknown is unconstrained and smooth, so the inner solves need no bounds: the
activations' box [0, 1] is the image of ``a = sin^2(pi z / 2)``, and the jaw limits are the
rig's smooth clamp.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import to_jax

__all__ = [
    "Params",
    "activations_from_z",
    "z_from_activations",
    "rotation_from_rotvec_deg",
    "apply_rigid",
    "rigid_numpy",
]


class Params(eqx.Module):
    """The parameters of one fit (a pytree; batched along a leading axis in a batch).

    Attributes:
        jaw: ``(3,)`` ``[pitch_deg, yaw_deg, protrusion_mm]`` of a
            :class:`~jaxface.anatomy.jaw.JawPose`, before the rig's smooth clamp into its limits.
        rigid: ``(6,)`` ``[rotation vector (deg), translation (mm)]`` of the rigid correction
            ``x -> c + R (x - c) + t`` about the face centre ``c``
            (:func:`apply_rigid`); ``None`` when the fit has none.
        z: ``(M,)`` activation parameters, ``a = sin^2(pi z / 2)``
            (:func:`activations_from_z`), ordered as the rig's ``muscle_names``.

    The fields are in this order (the alphabetical order of the former dict keys) so the
    leaves flatten, and the solver's sums run, in one fixed order.
    """

    jaw: jax.Array
    rigid: jax.Array | None
    z: jax.Array

    @classmethod
    def initial(
        cls, n_controls: int, pitch_deg: float, init_activation: float, rigid: bool
    ) -> Params:
        """Every activation at ``init_activation``, the jaw at ``pitch_deg`` (yaw and
        protrusion 0), no rigid correction (when ``rigid``). Strongly typed float64 leaves
        (built in NumPy first), so a compiled solve is not re-traced."""
        return cls(
            jaw=to_jax(np.array([float(pitch_deg), 0.0, 0.0])),
            rigid=to_jax(np.zeros(6)) if rigid else None,
            z=to_jax(np.full(int(n_controls), float(z_from_activations(init_activation)))),
        )

    def with_z(self, z) -> Params:
        """These parameters with the activation parameters ``z`` ``(M,)`` replaced."""
        return dataclasses.replace(self, z=z)


def activations_from_z(z):
    """Activations ``(M,)`` in [0, 1] from the unconstrained parameters:
    ``a = sin^2(pi z / 2)``.

    Why not a sigmoid: the bounds are reached at *finite* parameters (``z = 0`` and
    ``z = 1``, where ``da/dz = 0``), so a muscle that the data would drive past 0 or 1
    settles there instead of running away to infinity (a sigmoid's ``z`` keeps growing with
    steps of O(1) and the solver never meets its tolerance); and ``sqrt(lambda) sin(pi z /
    2)`` is a smooth residual whose square is the L1 sparsity prior ``lambda a``."""
    return jnp.sin(0.5 * jnp.pi * z) ** 2


def z_from_activations(a, eps: float = 0.0):
    """Inverse of :func:`activations_from_z` on ``z`` in [0, 1] (activations clipped to
    ``[eps, 1 - eps]``)."""
    a = jnp.clip(to_jax(a), eps, 1.0 - eps)
    return (2.0 / jnp.pi) * jnp.arcsin(jnp.sqrt(a))


def rotation_from_rotvec_deg(w_deg):
    """Rotation matrix ``(3, 3)`` of a rotation vector ``(3,)`` in degrees (Rodrigues;
    NaN-safe at 0 in value and gradient: a Taylor series below 1e-6 rad)."""
    w = to_jax(w_deg) * (jnp.pi / 180.0)
    th2 = jnp.sum(w * w)
    small = th2 < 1e-12
    th2s = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2s)
    A = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    B = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / th2s)
    z = jnp.zeros((), w.dtype)
    K = jnp.array([[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]])
    return jnp.eye(3, dtype=w.dtype) + A * K + B * (K @ K)


def apply_rigid(rigid, centre, x):
    """``c + R (x - c) + t`` for ``rigid = [rotvec_deg (3), t_mm (3)]``, ``x`` ``(N, 3)`` mm."""
    R = rotation_from_rotvec_deg(rigid[:3])
    return centre + (x - centre) @ R.T + rigid[3:]


def rigid_numpy(rigid, centre) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` with ``x -> R x + t`` equal to :func:`apply_rigid` (NumPy)."""
    R = np.asarray(rotation_from_rotvec_deg(to_jax(np.asarray(rigid, np.float64)[:3])))
    c = np.asarray(centre, np.float64)
    return R, c - R @ c + np.asarray(rigid, np.float64)[3:]
