"""The active set of the activation bounds (NumPy, one run).

``a = sin^2(pi z / 2)`` has zero slope at both bounds, where Gauss-Newton steps degenerate, so
the box [0, 1] is handled as an active set: after each inner solve, an activation within
``tol_a`` of a bound whose cost gradient pushes it outward is held at the bound (its Jacobian
column vanishes), and a held one whose gradient points back inside is released. An activation
released and then held again stays held (anti-cycling). At the end the KKT conditions of the
box hold to ``tol_a``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import FitError
from .params import z_from_activations

__all__ = ["update_active_set", "ActiveSet", "locked_controls"]


def update_active_set(
    a, grad, free, z_fixed, *, tol_a: float = 1e-2, tol_g: float = 1e-4, locked=None, keep=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Active-set update of the activation bounds (NumPy, one scan).

    A free activation within ``tol_a`` of a bound whose cost gradient pushes it outward by
    more than ``tol_g`` (``grad > tol_g`` at 0, ``grad < -tol_g`` at 1; mm^2 per unit
    activation) is held at that bound; a held one whose gradient points back inside by more
    than ``tol_g`` is released, restarting 0.02 inside. The dead band ``|grad| <= tol_g``
    keeps an activation whose optimum lies just inside a bound from flipping back and forth.
    ``locked`` ``(M,)`` bools stay held at 0 (controls the fit leaves out). ``keep`` ``(M,)``
    bools are not released once held (anti-cycling: :class:`ActiveSet` sets it for an
    activation that was released and then held again, whose optimum therefore lies within
    ``tol_a`` of the bound, where the zero slope of ``sin^2`` makes every solve creep).

    Returns:
        ``(free, z_fixed, z_start, changes)``: new mask, bound parameters, a starting ``z``
        for the released ones (NaN elsewhere) and the number of changes.
    """
    a = np.asarray(a, np.float64)
    g = np.asarray(grad, np.float64)
    free = np.asarray(free, np.float64).copy()
    zf = np.asarray(z_fixed, np.float64).copy()
    z_start = np.full(len(a), np.nan)
    lock = np.zeros(len(a), bool) if locked is None else np.asarray(locked, bool)
    kept = np.zeros(len(a), bool) if keep is None else np.asarray(keep, bool)
    changes = 0
    for i in range(len(a)):
        if lock[i]:
            free[i], zf[i] = 0.0, 0.0
            continue
        if free[i] > 0:
            if a[i] <= tol_a and g[i] > tol_g:
                free[i], zf[i] = 0.0, 0.0
                changes += 1
            elif a[i] >= 1.0 - tol_a and g[i] < -tol_g:
                free[i], zf[i] = 0.0, 1.0
                changes += 1
        elif not kept[i]:
            if zf[i] == 0.0 and g[i] < -tol_g:
                free[i] = 1.0
                z_start[i] = float(z_from_activations(0.02))
                changes += 1
            elif zf[i] == 1.0 and g[i] > tol_g:
                free[i] = 1.0
                z_start[i] = float(z_from_activations(0.98))
                changes += 1
    return free, zf, z_start, changes


@dataclass
class ActiveSet:
    """One run's activations held at a bound, with the anti-cycling memory (NumPy, ``(M,)``).

    Attributes:
        free: 1 for a free activation, 0 for one held at a bound.
        z_fixed: the parameter of a held activation (0 -> a = 0, 1 -> a = 1).
        released: held once, then released.
        cycled: released, then held again: kept at its bound from then on.
    """

    free: np.ndarray
    z_fixed: np.ndarray
    released: np.ndarray
    cycled: np.ndarray

    @classmethod
    def start(cls, locked: np.ndarray) -> ActiveSet:
        """Every activation free except the ``locked`` ``(M,)`` ones, held at 0."""
        M = len(locked)
        return cls(
            free=np.where(locked, 0.0, 1.0),
            z_fixed=np.zeros(M),
            released=np.zeros(M, bool),
            cycled=np.zeros(M, bool),
        )

    def effective_z(self, z) -> np.ndarray:
        """``(M,)`` parameters ``z`` with the held activations at their bounds."""
        return np.where(self.free > 0, np.asarray(z), self.z_fixed)

    def update(self, a, grad, z, *, locked, tol_g: float) -> tuple[np.ndarray, int]:
        """:func:`update_active_set` after an inner solve (activations ``a``, cost gradient
        ``grad`` mm^2 per unit, solution parameters ``z``), with the anti-cycling memory
        updated. Returns the run's new parameters ``z`` ``(M,)`` (released ones restarted
        inside, held ones at their bound) and the number of changes."""
        f_new, zf_new, z_start, n_ch = update_active_set(
            a, grad, self.free, self.z_fixed, locked=locked, tol_g=tol_g, keep=self.cycled
        )
        # anti-cycling: released before and held again -> stays held
        self.cycled |= self.released & (self.free > 0) & (f_new == 0)
        self.released |= (self.free == 0) & (f_new > 0)
        z = np.asarray(z).copy()
        z = np.where(np.isfinite(z_start), z_start, z)
        z = np.where(f_new > 0, z, zf_new)
        self.free, self.z_fixed = f_new, zf_new
        return z, n_ch

    def n_held(self, locked: np.ndarray) -> int:
        """Activations held at a bound, not counting the ``locked`` ones."""
        return int(np.sum((self.free == 0) & ~locked))

    def at_bounds(self, locked: np.ndarray) -> dict[int, float]:
        """Control index -> bound (0 or 1) of the held activations (not the ``locked`` ones)."""
        return {
            int(m): float(self.z_fixed[m])
            for m in range(len(self.free))
            if self.free[m] == 0 and not locked[m]
        }


def locked_controls(
    names: Sequence[str], sampled: Sequence[bool], controls: Sequence[str] | None
) -> np.ndarray:
    """``(M,)`` bools: the controls held at 0: not ``sampled`` by the reduced model
    (:attr:`jaxface.fit.reduced.ResponseModel.sampled`; empty: all sampled), or left out of
    ``controls`` (``FitOptions.controls``; ``None``: none left out).

    Raises:
        FitError: ``controls`` names an unknown or unsampled control."""
    names = list(names)
    locked = np.zeros(len(names), bool)
    if sampled:
        locked |= ~np.asarray(sampled, bool)
    if controls is not None:
        unknown = [c for c in controls if c not in names]
        if unknown:
            raise FitError(
                f"FitOptions.controls names unknown controls {unknown}; the rig has {names}."
            )
        locked |= ~np.isin(names, list(controls))
    for c in controls or ():
        if locked[names.index(c)]:
            raise FitError(
                f"control {c!r} is to be fitted but the reduced model did not sample it "
                "(build_response_model(controls=...))."
            )
    return locked
