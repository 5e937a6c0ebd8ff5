"""Summary statistics of distances (mm): :class:`DistanceStats`, the one summary the fit,
the registration, the alignment and the metrics report. NumPy, off the jit path."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import FitError

__all__ = ["DistanceStats"]


@dataclass(frozen=True)
class DistanceStats:
    """Summary of a set of distances, all in mm (``n`` is a count).

    ``mean``, ``median``, ``rms``, ``p95`` (95th percentile, linear interpolation) and
    ``max``; NaN for an empty set (``n == 0``), which :meth:`to_dict` writes as ``None``.
    """

    n: int
    mean: float
    median: float
    rms: float
    p95: float
    max: float

    @classmethod
    def from_distances(cls, distances) -> DistanceStats:
        d = np.abs(np.asarray(distances, dtype=np.float64).ravel())
        if d.size and not np.all(np.isfinite(d)):
            raise FitError(
                f"{int((~np.isfinite(d)).sum())} of {d.size} distances are NaN/inf; metrics "
                "need finite distances (check the meshes for NaN vertices)."
            )
        if d.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan, nan)
        return cls(
            n=int(d.size),
            mean=float(d.mean()),
            median=float(np.median(d)),
            rms=float(np.sqrt(np.mean(d * d))),
            p95=float(np.percentile(d, 95)),
            max=float(d.max()),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (mm); NaN becomes ``None``."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            x = getattr(self, f.name)
            out[f.name] = None if isinstance(x, float) and math.isnan(x) else x
        return out
