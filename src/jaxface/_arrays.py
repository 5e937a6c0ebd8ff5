"""Moving build-time NumPy data into JAX arrays cheaply.

``jnp.asarray(numpy_array)`` (no ``dtype``) goes through ``lax.stage`` in the pinned JAX,
which compiles a small program for every new shape: about 20-25 ms each on a CPU, tens of
them per rig build. :func:`to_jax` makes the same array (same dtype canonicalisation:
float64 becomes float32 unless x64 is enabled) with a plain host-to-device copy (``jax.device_put``; ``jnp.array`` takes the same
slow path whenever no dtype conversion is needed).
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["to_jax"]


def to_jax(x) -> jax.Array:
    """``jnp.asarray(x)`` for concrete data, without a compile; JAX arrays and tracers pass
    through unchanged."""
    if isinstance(x, jax.Array):  # includes tracers
        return x
    return jax.device_put(np.asarray(x))
