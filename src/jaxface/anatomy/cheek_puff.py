"""The cheek puff (AU33/AU34): air pressure in the oral vestibule pushes both cheeks out.

Both backends drive it the same way: each skin vertex of a cheek moves (PBD) or is pushed
(LTW) along its outward smoothed normal, weighted by a cheek bump over the buccal area
between the mouth corner and the masseter (:func:`cheek_bump`). The pressure is one number in
[0, 1] for both cheeks, or ``[left, right]`` for each cheek on its own (a puff with the air
held in one cheek, ICT-FaceKit's ``cheekPuff_L`` / ``cheekPuff_R``).

The fit treats the two cheeks as two more controls, named :data:`PUFF_CONTROLS`, after the
rig's muscles (:class:`jaxface.fit.forward.ForwardModel`), so the reduced model, the priors
and the AU readouts take the puff as they take a muscle.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import RigError
from .frame import FaceFrame

__all__ = ["PUFF_CONTROLS", "cheek_bump", "puff_scale"]

#: The fit's names of the two cheeks' pressures (the subject's left cheek, +x, first).
PUFF_CONTROLS: tuple[str, str] = ("cheek_puff_L", "cheek_puff_R")

# The bump in the face frame's reference millimetres (origin at the eye centre, +y up, +x the
# subject's left): a Gaussian exp(-2 r^2) in the ellipse of radii 22 x 20 around
# (+-42, -58), 17 mm lateral to and 12 mm above an average mouth corner, over the buccinator
# between the corner and the masseter; none within 8 mm of the mid-line.
_CENTRE = (42.0, -58.0)
_RADII = (22.0, 20.0)
_MIDLINE = 8.0


def cheek_bump(x: np.ndarray, frame: FaceFrame) -> tuple[np.ndarray, np.ndarray]:
    """The cheek bump of the skin vertices ``x`` ``(V, 3)`` mm (NumPy, built once).

    Returns:
        ``(weight (V,) in [0, 1], left (V,) bool)``: the bump's weight, and whether a vertex
        belongs to the left cheek's bump (+x in the face frame; the two bumps never overlap).
    """
    loc = frame.to_local(np.asarray(x, np.float64))
    bump = np.zeros(len(loc))
    for sgn in (1.0, -1.0):
        cl = frame.to_local(frame.to_world([sgn * _CENTRE[0], _CENTRE[1], 0.0]))
        r2 = ((loc[:, 0] - cl[0]) / _RADII[0]) ** 2 + ((loc[:, 1] - cl[1]) / _RADII[1]) ** 2
        side_ok = (loc[:, 0] * sgn) > _MIDLINE
        bump = np.maximum(bump, np.where(side_ok, np.exp(-r2 * 2.0), 0.0))
    return bump, loc[:, 0] > _MIDLINE


def puff_scale(cheek_puff, left: jax.Array, dtype) -> jax.Array:
    """The pressure at each vertex: ``cheek_puff`` when it is a scalar (both cheeks), or
    ``cheek_puff[0]`` on the left cheek and ``cheek_puff[1]`` elsewhere when it is
    ``(2,)`` ``[left, right]``. Returns a scalar or ``(V, 1)``; multiply the bump's ``(V, 3)``
    field by it.

    Raises:
        RigError: a pressure of another shape.
    """
    p = jnp.asarray(cheek_puff, dtype)
    if p.ndim == 0:
        return p
    if p.shape != (2,):
        raise RigError(f"cheek_puff must be a number or [left, right], got shape {tuple(p.shape)}.")
    return jnp.where(left, p[0], p[1])[:, None]
