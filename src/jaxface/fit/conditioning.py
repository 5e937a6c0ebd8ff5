"""Conditioning of a fit: the singular values of its data Jacobian and how well each
parameter can be told apart from the others (a diagnostic; it does not change the fit)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import to_jax
from .params import Params, activations_from_z
from .residuals import PointSet, Priors, data_residuals

__all__ = ["jacobian_conditioning"]


def jacobian_conditioning(
    y: Params, points: PointSet, priors: Priors, muscle_names: Sequence[str]
) -> dict:
    """Conditioning of the fit's data Jacobian at ``y`` (forward mode, reduced model +
    defect, i.e. the exact rig's residuals to first order).

    The Jacobian is that of the point-to-plane and landmark residuals with respect to the
    *physical* parameters: activations (taken directly, so controls held at a bound get
    their column too), jaw pitch/yaw (deg) and protrusion (mm), rigid rotation (deg) and
    translation (mm).

    Returns:
        dict with ``singular_values`` per group (``"activations"``, ``"jaw"``, ``"rigid"``,
        ``"all"``), ``condition`` per group, ``parameters`` (column names), and per parameter:
        ``sensitivity`` (column norm: mm of weighted residual per unit) and ``vif`` (variance
        inflation factor ``(J^T J)^-1_ii (J^T J)_ii``: 1 = independent of the others; large
        = hard to tell apart from a combination of the others).
    """
    z = to_jax(y.z)
    a0 = activations_from_z(jnp.where(points.free > 0, z, points.z_fixed))

    def phys(p):
        M = a0.shape[0]
        rig = p[M + 3 :] if priors.use_rigid else None
        r_pt, r_lm = data_residuals(p[:M], p[M : M + 3], rig, points, priors.use_rigid)
        return jnp.concatenate([r_pt.ravel(), r_lm.ravel()])

    p0 = [a0, to_jax(y.jaw)]
    if priors.use_rigid:
        p0.append(to_jax(y.rigid))
    p0 = jnp.concatenate(p0)
    Jm = np.asarray(jax.jit(jax.jacfwd(phys))(p0))
    M = int(a0.shape[0])
    groups = {"activations": np.arange(M), "jaw": np.arange(M, M + 3)}
    if priors.use_rigid:
        groups["rigid"] = np.arange(M + 3, M + 9)
    groups["all"] = np.arange(Jm.shape[1])
    out: dict[str, Any] = {"singular_values": {}, "condition": {}}
    for g, cols in groups.items():
        s = np.linalg.svd(Jm[:, cols], compute_uv=False)
        out["singular_values"][g] = s.tolist()
        out["condition"][g] = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    JtJ = Jm.T @ Jm
    sens = np.sqrt(np.diag(JtJ))
    try:
        inv = np.linalg.pinv(JtJ, rcond=1e-14)
        vif = np.diag(inv) * np.diag(JtJ)
    except np.linalg.LinAlgError:  # pragma: no cover
        vif = np.full(len(sens), np.inf)
    names = list(muscle_names) + ["jaw_pitch_deg", "jaw_yaw_deg", "jaw_protrusion_mm"]
    if priors.use_rigid:
        names += ["rot_x_deg", "rot_y_deg", "rot_z_deg", "t_x_mm", "t_y_mm", "t_z_mm"]
    out["parameters"] = names
    out["sensitivity"] = dict(zip(names, sens.tolist()))
    out["vif"] = dict(zip(names, vif.tolist()))
    return out
