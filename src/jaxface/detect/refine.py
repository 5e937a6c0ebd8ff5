"""Surface snap, visibility and confidence of landmarks (mm, scan frame).

* **Surface snap.** Every landmark is moved to its closest point on the scan surface.
* **Visibility.** A label is left out, with a reason, when the scan has no surface under it:
  its closest scan point is on a hole rim or the scan border (and more than
  :data:`BOUNDARY_GAP_MM` away), farther than
  :data:`MAX_GAP_MM`, or the registered template has no data around it.
* **Confidence** in [0, 1]: ``coverage * exp(-(rms / 1.5 mm)^2)``, with ``coverage`` the
  fraction of registered template vertices within :data:`CONF_RADIUS_MM` of the landmark that
  found scan data and ``rms`` their residual distance to the scan. A landmark in a hole, at
  the scan border or where the template does not fit the surface gets a low value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import KDTree

from ..fit.metrics import SurfaceIndex

__all__ = ["Placement", "place_landmarks"]

MAX_GAP_MM = 3.0
CONF_RADIUS_MM = 6.0
BOUNDARY_GAP_MM = 1.5
MIN_COVERAGE = 0.3


@dataclass(frozen=True)
class Placement:
    """Per-label outcome (scan frame, mm).

    Attributes:
        position: ``(3,)`` on the scan surface, mm (``None`` when omitted).
        confidence: in [0, 1].
        reason: why the label is omitted (``None`` when visible).
    """

    position: np.ndarray | None
    confidence: float
    reason: str | None


def place_landmarks(
    index: SurfaceIndex,
    names: list[str],
    guesses: np.ndarray,
    reg_vertices: np.ndarray,
    reg_residuals: np.ndarray,
    reg_has_data: np.ndarray,
) -> dict[str, Placement]:
    """Snap and score the landmark ``guesses`` ``(N, 3)`` mm (labels ``names``).

    Arguments:
        reg_vertices, reg_residuals, reg_has_data: the registered template's ``(V, 3)``
            vertices, ``(V,)`` residuals (mm) and ``(V,)`` data flags (for confidence; an
            empty array means no registration covers these labels, e.g. the ear lobes).
    """
    guesses = np.asarray(guesses, float).reshape(-1, 3)
    cp = index.query(guesses)
    tree = KDTree(reg_vertices) if len(reg_vertices) else None
    out: dict[str, Placement] = {}
    for i, n in enumerate(names):
        gap = float(cp.distances[i])
        if tree is not None:
            near = tree.query_ball_point(guesses[i], CONF_RADIUS_MM)
            near = np.asarray(near, dtype=np.int64)
            cov = float(reg_has_data[near].mean()) if near.size else 0.0
            res = reg_residuals[near][reg_has_data[near]] if near.size else np.zeros(0)
            rms = float(np.sqrt(np.mean(res**2))) if res.size else np.inf
        else:
            cov = 1.0 if gap <= MAX_GAP_MM else 0.0
            rms = gap
        conf = float(cov * np.exp(-((rms / 1.5) ** 2))) if np.isfinite(rms) else 0.0
        reason = None
        if cp.on_boundary[i] and gap > BOUNDARY_GAP_MM:
            reason = (
                f"the scan has no surface here: the closest scan point ({gap:.1f} mm away) "
                f"is on a hole rim or the scan border"
            )
        elif gap > MAX_GAP_MM:
            reason = f"no scan surface within {MAX_GAP_MM:g} mm (nearest {gap:.1f} mm)"
        elif tree is not None and cov < MIN_COVERAGE:
            reason = (
                f"the scan covers only {100 * cov:.0f}% of the face within "
                f"{CONF_RADIUS_MM:g} mm (hole or out of view)"
            )
        if reason is not None:
            out[n] = Placement(None, 0.0, reason)
        else:
            out[n] = Placement(cp.points[i].copy(), conf, None)
    return out
