"""RBF kernels, NaN-safe at ``r = 0`` in value and gradient (JAX), with their NumPy twins and
squared distances (see :mod:`jaxface.rbf` for the kernels)."""

from __future__ import annotations

from typing import Literal

import jax.numpy as jnp
import numpy as np

from ..errors import RBFError

__all__ = ["KernelName", "KERNELS", "kernel_values"]

KernelName = Literal["tps", "biharmonic", "multiquadric"]
KERNELS: tuple[str, ...] = ("tps", "biharmonic", "multiquadric")

# Sign of the ridge term per kernel. r^2 log r^2 is conditionally positive definite (order 2)
# while r and the multiquadric are conditionally *negative* definite (order 1): the ridge must
# push the kernel matrix away from singularity, so it is added with the kernel's sign (adding it
# with the wrong sign can make K + reg I singular for some reg and blow the morph up).
_RIDGE_SIGN = {"tps": 1.0, "biharmonic": -1.0, "multiquadric": -1.0}


# --------------------------------------------------------------------------------------
# kernels (JAX), NaN-safe at r = 0 in value and gradient
# --------------------------------------------------------------------------------------
def kernel_values(kernel: str, d2, c2=None):
    """Kernel ``U`` as a function of the squared distance.

    Arguments:
        kernel: ``"tps"``, ``"biharmonic"`` or ``"multiquadric"``.
        d2: ``(..., n)`` squared distances to the centres (any unit; the caller's frame).
        c2: ``(n,)`` squared stiffness radii, multiquadric only (same unit as ``d2``).

    Returns:
        ``(..., n)`` kernel values; 0 (with zero gradient) where the argument of the root or
        the logarithm is 0.
    """
    if kernel == "tps":
        pos = d2 > 0
        safe = jnp.where(pos, d2, 1.0)
        return jnp.where(pos, safe * jnp.log(safe), 0.0)
    if kernel == "biharmonic":
        pos = d2 > 0
        safe = jnp.where(pos, d2, 1.0)
        return jnp.where(pos, jnp.sqrt(safe), 0.0)
    if kernel == "multiquadric":
        s = d2 + c2
        pos = s > 0
        safe = jnp.where(pos, s, 1.0)
        return jnp.where(pos, jnp.sqrt(safe), 0.0)
    raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")


def _kernel_np(kernel: str, d2: np.ndarray, c2: np.ndarray | None) -> np.ndarray:
    if kernel == "tps":
        return d2 * np.log(np.where(d2 > 0, d2, 1.0))
    if kernel == "biharmonic":
        return np.sqrt(np.maximum(d2, 0.0))
    if kernel == "multiquadric":
        return np.sqrt(np.maximum(d2 + c2, 0.0))
    raise RBFError(f"unknown RBF kernel {kernel!r}; choose one of {KERNELS}.")


def _sqdist(a, b):
    """(m, 3), (n, 3) -> (m, n) squared distances by differences (exact 0 at coincidence)."""
    diff = a[:, None, :] - b[None, :, :]
    return jnp.sum(diff * diff, axis=-1)


def _sqdist_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances by coordinate differences (exactly 0 at coincident points)."""
    d2 = np.zeros((a.shape[0], b.shape[0]))
    for k in range(3):
        diff = np.subtract.outer(a[:, k], b[:, k])
        diff *= diff
        d2 += diff
    return d2
