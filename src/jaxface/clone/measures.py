"""Error measures of a clone against a reference (mm)."""

from __future__ import annotations

import numpy as np

__all__ = ["clone_error", "delta_error"]


# ------------------------------------------------------------------------------------------
# error measures
# ------------------------------------------------------------------------------------------
def clone_error(reference, cloned) -> float:
    """Thesis eq. 6.1, in percent: the mean over morph targets of
    ``sum_i |v_i^S - v_i^T| / sum_i |v_i^S|`` (positions in mm, so the value depends on the
    origin; the thesis's self-clone table uses it).

    Arguments:
        reference, cloned: ``(T, V, 3)`` (or ``(V, 3)``) morph-target positions, mm.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(cloned, dtype=np.float64)
    if a.ndim == 2:
        a, b = a[None], b[None]
    num = np.linalg.norm(a - b, axis=2).sum(axis=1)
    den = np.linalg.norm(a, axis=2).sum(axis=1)
    return float(np.mean(num / den) * 100.0)


def delta_error(reference_deltas, cloned_deltas) -> float:
    """Origin-independent relative error in percent: ``100 * sum |d_ref - d_clone| / sum
    |d_ref|`` over all morph targets and vertices (displacements in mm)."""
    a = np.asarray(reference_deltas, dtype=np.float64)
    b = np.asarray(cloned_deltas, dtype=np.float64)
    den = np.linalg.norm(a, axis=-1).sum()
    return float(np.linalg.norm(a - b, axis=-1).sum() / den * 100.0) if den > 0 else 0.0
