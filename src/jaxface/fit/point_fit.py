"""The result of :func:`jaxface.fit.solve.fit_points` for one scan (:class:`PointFit`; neutral
scan frame, mm, degrees)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .inner import InnerReport
from .params import Params

__all__ = ["PointFit"]


@dataclass
class PointFit:
    """Result of :func:`fit_points` for one scan (neutral-scan frame, mm).

    Attributes:
        activations: ``(M,)`` in [0, 1]; jaw: ``(3,)`` [pitch_deg, yaw_deg, protrusion_mm]
            as fitted (the rig clamps it smoothly; ``jaw_effective`` is the clamped pose).
        rigid: ``(6,)`` [rotation vector deg, translation mm] about ``centre`` ``(3,)``.
        skin: ``(V, 3)`` the exact rig's skin at the fit with the rigid correction, mm.
        y: the :class:`~jaxface.fit.params.Params` (NumPy leaves; held activations at their
            bound); reports: the inner solves.
        status: ``"successful"``, an optimistix result name, ``"active_set_changing"`` or
            ``"outer_not_converged"`` (module doc).
        steps: total LM steps; seconds: wall time per scan; start_pitch: the winning start.
        residual_mm: point-to-plane residual stats of the final correspondences (exact skin).
        points: the last :class:`~jaxface.fit.residuals.PointSet` (for conditioning).
        starts: jaw start pitch (deg) -> final weighted cost (mm^2) of every start.
        at_bounds: control index -> bound (0 or 1) of the activations held there.
        restart: the bound-flip restart of this scan, empty when none ran: ``controls``
            restarted, ``cost_mm2`` its final cost, ``parent_cost_mm2`` that of the run it
            restarted, ``kept`` whether it won.
    """

    activations: np.ndarray
    jaw: np.ndarray
    jaw_effective: np.ndarray
    rigid: np.ndarray
    centre: np.ndarray
    skin: np.ndarray
    y: Params
    reports: list[InnerReport]
    status: str
    steps: int
    seconds: float
    start_pitch: float
    residual_mm: dict = field(default_factory=dict)
    points: Any = None
    starts: dict = field(default_factory=dict)
    at_bounds: dict = field(default_factory=dict)
    restart: dict = field(default_factory=dict)
