"""The jaw: a rigid mandible (and lower teeth) with pitch, yaw and protrusion (thesis sec. 5.2).

* **pitch** rotates about the axis through the two condyles (MPEG-4 2.13/2.14); positive
  opens the mouth; default limits -4..18 degrees (``jaw_pitch_limits_deg``);
* **yaw** rotates about the axis through the top of the skull (11.4) and the condyle
  midpoint; positive turns the chin toward the subject's left (+x); limits -5..5 degrees;
* **protrusion** translates along the line from the top of the spine (7.1) to the chin
  (2.10, the "Chin middle" landmark); positive is forward; limits -2..10 mm (``jaw_protrusion_limits_mm``).

The condyles, skull top and spine top are estimated from the Bosphorus landmarks by
:mod:`jaxface.anatomy.frame`. The mandible motion is ``p' = R p + t`` with ``R = R_yaw R_pitch``
(pitch first, both about axes through the condyle midpoint; Rodrigues' formula, thesis
eq. 5.1-5.3) followed by the protrusion translation (eq. 5.5).

Limits are enforced with a *smooth clamp*
``f(x) = lo + softplus_b(x - lo) - softplus_b(x - hi)`` (``softplus_b(u) = log(1 + e^{b u}) / b``):
``f`` never leaves ``[lo, hi]`` (strictly inside in exact arithmetic), equals ``x`` to within
``e^{-b d}/b`` when ``x`` is a distance ``d`` inside the range, and its derivative is in
``[0, 1]``, positive near the limits (it decays like ``e^{-b d}`` a distance ``d`` beyond a
limit), so gradients never stop abruptly. ``b = 1 / softness``.

Everything is jit-able, vmap-able and differentiable with respect to the pose.
Units: degrees for angles, mm for lengths.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._arrays import to_jax
from ..rigid import rotation_matrix
from .frame import FaceFrame, face_frame

__all__ = [
    "JawPose",
    "JawModel",
    "PITCH_LIMITS_DEG",
    "YAW_LIMITS_DEG",
    "PROTRUSION_LIMITS_MM",
    "smooth_clamp",
    "rotation_matrix",
]

#: Default pitch limits, degrees (closing, opening). An adult mandible opens about 25-30
#: degrees about the condyles at the widest mouth opening (40-50 mm between the incisors);
#: ICT-FaceKit's ``jawOpen`` drops the chin 42 mm, about 22 degrees. The default stops at 18
#: (a wider range fits the Bosphorus-style scans slightly worse, ``docs/design/anatomy.md``);
#: ``build_rig(..., jaw_pitch_limits_deg=(-4, 28))`` opens the full range.
PITCH_LIMITS_DEG = (-4.0, 18.0)
YAW_LIMITS_DEG = (-5.0, 5.0)
#: Default protrusion limits, mm (retrusion, protrusion). Adults push the lower incisors about
#: 7-11 mm forward at the limit of protrusion and pull them back 1-2 mm; ICT-FaceKit's
#: ``jawForward`` moves the lower lip 11 mm forward.
PROTRUSION_LIMITS_MM = (-2.0, 10.0)


def smooth_clamp(x, lo: float, hi: float, softness: float):
    """Smoothly clamp ``x`` into ``(lo, hi)``.

    Args:
        x: array of any shape (any unit).
        lo, hi: the limits (same unit), ``lo < hi``.
        softness: width of the transition zone at each limit (same unit), > 0.

    Returns:
        array like ``x``, strictly inside ``(lo, hi)``; ``~x`` well inside the range.
    """
    x = jnp.asarray(x)
    b = 1.0 / softness
    sp = jax.nn.softplus
    # two algebraically identical forms, each exact near its own limit (no cancellation)
    low = lo + (sp(b * (x - lo)) - sp(b * (x - hi))) / b
    high = hi - (sp(b * (hi - x)) - sp(b * (lo - x))) / b
    return jnp.where(x < 0.5 * (lo + hi), low, high)


class JawPose(eqx.Module):
    """The jaw state, a tiny JAX pytree.

    Attributes:
        pitch_deg: ``()`` degrees, opening positive (default limits -4..18).
        yaw_deg: ``()`` degrees, chin toward the subject's left (+x) positive (limits -5..5).
        protrusion_mm: ``()`` mm, forward (+z) positive (limits -2..10).

    Values outside the limits are accepted: :class:`JawModel` clamps them smoothly.
    Batched poses (leading dimensions) work under ``jax.vmap``.
    """

    pitch_deg: jax.Array
    yaw_deg: jax.Array
    protrusion_mm: jax.Array

    def __init__(
        self, pitch_deg: ArrayLike = 0.0, yaw_deg: ArrayLike = 0.0, protrusion_mm: ArrayLike = 0.0
    ):
        dt = jnp.result_type(pitch_deg, yaw_deg, protrusion_mm, float)
        self.pitch_deg = jnp.asarray(pitch_deg, dtype=dt)
        self.yaw_deg = jnp.asarray(yaw_deg, dtype=dt)
        self.protrusion_mm = jnp.asarray(protrusion_mm, dtype=dt)

    @staticmethod
    def neutral() -> JawPose:
        """The closed, centred jaw (all zeros)."""
        return JawPose(0.0, 0.0, 0.0)

    def as_array(self) -> jax.Array:
        """``(..., 3)`` [pitch_deg, yaw_deg, protrusion_mm]."""
        return jnp.stack([self.pitch_deg, self.yaw_deg, self.protrusion_mm], axis=-1)

    @staticmethod
    def from_array(a) -> JawPose:
        """Inverse of :meth:`as_array`: ``(..., 3)`` [pitch_deg, yaw_deg, protrusion_mm]."""
        a = jnp.asarray(a)
        return JawPose(a[..., 0], a[..., 1], a[..., 2])


class JawModel(eqx.Module):
    """Jaw kinematics of one face: axes from landmarks, smooth limits.

    Attributes:
        pivot: ``(3,)`` condyle midpoint, mm (a point on both rotation axes).
        pitch_axis: ``(3,)`` unit, from the right to the left condyle (+x-ish).
        yaw_axis: ``(3,)`` unit, from the condyle midpoint toward the top of the skull.
        protrusion_dir: ``(3,)`` unit, from the top of the spine toward the chin.
        pitch_limits, yaw_limits: degrees (static); protrusion_limits: mm (static).
        softness_deg, softness_mm: widths of the smooth-clamp transition zones (static).
    """

    pivot: jax.Array
    pitch_axis: jax.Array
    yaw_axis: jax.Array
    protrusion_dir: jax.Array
    pitch_limits: tuple[float, float] = eqx.field(static=True, default=PITCH_LIMITS_DEG)
    yaw_limits: tuple[float, float] = eqx.field(static=True, default=YAW_LIMITS_DEG)
    protrusion_limits: tuple[float, float] = eqx.field(static=True, default=PROTRUSION_LIMITS_MM)
    softness_deg: float = eqx.field(static=True, default=0.25)
    softness_mm: float = eqx.field(static=True, default=0.1)

    @staticmethod
    def from_landmarks(landmarks, *, condyles=None, **limits) -> JawModel:
        """Build the jaw of a face from its Bosphorus landmarks.

        Args:
            landmarks: :class:`jaxface.landmarks.Landmarks` (22 face labels; ear lobes optional)
                or a :class:`~jaxface.anatomy.frame.FaceFrame`.
            condyles: optional ``(2, 3)`` [left, right] condyle positions in mm (e.g. from a
                user-supplied skull); estimated from the landmarks when None.
            **limits: optional ``pitch_limits``, ``yaw_limits`` (degrees), ``protrusion_limits``
                (mm), ``softness_deg``, ``softness_mm``.
        """
        frame = landmarks if isinstance(landmarks, FaceFrame) else face_frame(landmarks)
        cond = frame.condyles if condyles is None else np.asarray(condyles, np.float64)
        pivot = cond.mean(axis=0)
        pitch = cond[0] - cond[1]
        pitch = pitch / np.linalg.norm(pitch)
        yaw = frame.skull_top - pivot
        yaw = yaw - pitch * (yaw @ pitch)  # keep the two axes orthogonal
        yaw = yaw / np.linalg.norm(yaw)
        prot = frame.landmark("Chin middle") - frame.spine_top
        prot = prot / np.linalg.norm(prot)
        kw: dict[str, Any] = {
            k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in limits.items()
        }
        return JawModel(to_jax(pivot), to_jax(pitch), to_jax(yaw), to_jax(prot), **kw)

    @property
    def limits(self) -> dict:
        """``{"pitch_deg": (lo, hi), "yaw_deg": (lo, hi), "protrusion_mm": (lo, hi)}``."""
        return {
            "pitch_deg": tuple(self.pitch_limits),
            "yaw_deg": tuple(self.yaw_limits),
            "protrusion_mm": tuple(self.protrusion_limits),
        }

    def clamp(self, pose: JawPose) -> JawPose:
        """The effective pose after smooth clamping into the limits (same pytree shape)."""
        return JawPose(
            smooth_clamp(pose.pitch_deg, *self.pitch_limits, self.softness_deg),
            smooth_clamp(pose.yaw_deg, *self.yaw_limits, self.softness_deg),
            smooth_clamp(pose.protrusion_mm, *self.protrusion_limits, self.softness_mm),
        )

    def transform(self, pose: JawPose):
        """Rigid motion of the mandible for a pose (smoothly clamped).

        Args:
            pose: a single :class:`JawPose` (scalars; vmap for batches).

        Returns:
            ``(R (3, 3), t (3,))`` with moved points ``p' = R p + t`` (mm).
        """
        p = self.clamp(pose)
        dt = jnp.result_type(self.pivot.dtype, p.pitch_deg.dtype)
        deg = jnp.pi / 180.0
        Rp = rotation_matrix(self.pitch_axis.astype(dt), p.pitch_deg.astype(dt) * deg)
        Ry = rotation_matrix(self.yaw_axis.astype(dt), p.yaw_deg.astype(dt) * deg)
        R = Ry @ Rp
        c = self.pivot.astype(dt)
        t = c - R @ c + self.protrusion_dir.astype(dt) * p.protrusion_mm.astype(dt)
        return R, t

    def apply(self, pose: JawPose, points):
        """Move mandible points: ``(K, 3)`` rest positions, mm -> ``(K, 3)`` moved, mm."""
        R, t = self.transform(pose)
        points = jnp.asarray(points)
        return points @ R.T.astype(points.dtype) + t.astype(points.dtype)
