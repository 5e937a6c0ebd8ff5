"""Rigid and similarity transforms and rotations: the one set of helpers of the package.

Units: millimetres for points and translations, radians unless a name says ``_deg``. Frame:
+y up, the face looks along +z, the subject's left is +x.

NumPy (preprocessing, off the jit path): :class:`RigidTransform` (``p -> s R p + t``),
:func:`procrustes` (weighted Kabsch/Umeyama), :func:`rotvec_matrix` (rotation vector ->
matrix) and :func:`rotation_from_euler` (the ``truth.json`` convention of the shared data).

JAX (jit-able, differentiable): :func:`rotation_matrix` (Rodrigues, one axis) and
:func:`rotate_about_axes` (Rodrigues rotation of points about per-point axes and pivots).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from .errors import FitError

__all__ = [
    "RigidTransform",
    "procrustes",
    "rotvec_matrix",
    "rotation_from_euler",
    "rotation_matrix",
    "rotate_about_axes",
]


# --------------------------------------------------------------------------------------
# NumPy
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RigidTransform:
    """``p -> scale * rotation @ p + translation`` (mm in, mm out).

    Attributes:
        rotation: (3, 3) proper rotation (det +1).
        translation: (3,) mm.
        scale: uniform scale (1 for a rigid transform).
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def __post_init__(self):
        object.__setattr__(
            self, "rotation", np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        )
        object.__setattr__(
            self, "translation", np.asarray(self.translation, dtype=np.float64).reshape(3)
        )
        object.__setattr__(self, "scale", float(self.scale))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) mm -> (..., 3) mm."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    __call__ = apply

    def apply_vectors(self, vectors: np.ndarray) -> np.ndarray:
        """Rotate (and scale) direction/displacement vectors (..., 3); no translation."""
        return self.scale * np.asarray(vectors, dtype=np.float64) @ self.rotation.T

    def inverse(self) -> RigidTransform:
        Rt = self.rotation.T
        return RigidTransform(Rt, -(Rt @ self.translation) / self.scale, 1.0 / self.scale)

    def compose(self, first: RigidTransform) -> RigidTransform:
        """``self ∘ first``: apply ``first``, then ``self``."""
        return RigidTransform(
            self.rotation @ first.rotation,
            self.scale * self.rotation @ first.translation + self.translation,
            self.scale * first.scale,
        )

    @property
    def angle_deg(self) -> float:
        """Rotation angle in degrees."""
        c = np.clip((np.trace(self.rotation) - 1.0) / 2.0, -1.0, 1.0)
        return float(np.degrees(np.arccos(c)))

    def as_dict(self) -> dict:
        """JSON-friendly: rotation matrix, translation (mm), scale, rotation angle (deg)."""
        return {
            "rotation": self.rotation.tolist(),
            "translation_mm": self.translation.tolist(),
            "scale": self.scale,
            "angle_deg": self.angle_deg,
        }


def procrustes(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, *, scale: bool = False
) -> RigidTransform:
    """Least-squares rigid (or similarity, ``scale=True``) transform mapping ``src`` to ``dst``
    (Kabsch/Umeyama with reflection guard).

    Args:
        src, dst: (n, 3) mm, n >= 3 and not collinear.
        weights: (n,) non-negative.

    Raises:
        FitError: fewer than 3 points, or (nearly) collinear points.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise FitError(
            f"procrustes needs two (n, 3) arrays of equal shape, got {src.shape} and {dst.shape}"
        )
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    if int((w > 0).sum()) < 3:
        raise FitError(
            f"rigid alignment needs at least 3 weighted point pairs, got {int((w > 0).sum())}"
        )
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    a, b = src - cs, dst - cd
    H = (a * w[:, None]).T @ b
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):
        raise FitError("rigid alignment is undetermined: the points are (nearly) collinear")
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    s = 1.0
    if scale:
        var = float(w @ np.sum(a * a, axis=1))
        s = float(np.sum(S * np.diag(D)) / var)
    return RigidTransform(R, cd - s * R @ cs, s)


def rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation matrix of a rotation vector ``w (3,)`` (radians)."""
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def rotation_from_euler(pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """``Rx(pitch) @ Ry(yaw)`` ``(3, 3)``: the rotation convention of ``truth.json`` in the
    shared Bosphorus-style data (angles in degrees about +x and +y)."""
    a, b = np.radians(pitch_deg), np.radians(yaw_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return rx @ ry


# --------------------------------------------------------------------------------------
# JAX
# --------------------------------------------------------------------------------------
def rotation_matrix(axis, angle_rad):
    """Rodrigues rotation matrix (thesis eq. 5.2) about a unit ``axis (3,)`` by ``angle_rad``
    (radians, right-hand rule). Returns ``(3, 3)``."""
    axis = jnp.asarray(axis)
    c = jnp.cos(angle_rad)
    s = jnp.sin(angle_rad)
    x, y, z = axis[0], axis[1], axis[2]
    K = jnp.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=axis.dtype)
    return c * jnp.eye(3, dtype=axis.dtype) + s * K + (1.0 - c) * jnp.outer(axis, axis)


def rotate_about_axes(p, pivot, axis, angle):
    """Rodrigues rotation of points ``p (K, 3)`` about unit ``axis (K, 3)`` through
    ``pivot (K, 3)`` by ``angle (K,)`` radians (right-hand rule). Returns ``(K, 3)``."""
    c = jnp.cos(angle)[:, None]
    s = jnp.sin(angle)[:, None]
    v = p - pivot
    kxv = jnp.cross(axis, v)
    kdv = jnp.sum(axis * v, axis=1, keepdims=True)
    return pivot + v * c + kxv * s + axis * kdv * (1.0 - c)
