"""The ARKit readout of a fit (used by :mod:`jaxface.fit.pipeline`): :class:`ArkitReadout`, one
per subject and ICT file (:func:`readout_for_subject`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import FitError
from .basis import ArkitBasis, transfer_ict_basis
from .ict import default_ict_path
from .readout import solve_arkit

__all__ = ["ArkitReadout", "readout_for_subject"]


# ------------------------------------------------------------------------------------------
# the readout of a fit (used by jaxface.fit.pipeline)
# ------------------------------------------------------------------------------------------
class ArkitReadout:
    """Reads ARKit coefficients from fitted skins of one subject (:func:`solve_arkit`), or
    says why it cannot (no ICT data, a failed transfer): it never makes numbers up.

    Call it with a fitted skin ``(V, 3)`` mm (the rig's frame and topology): returns
    ``(coefficients dict or None, detail dict)``; ``detail`` holds ``available`` and either
    the :meth:`ArkitSolution.to_dict` fields with ``source``/``method``, or ``reason``.
    """

    def __init__(self, rest, basis: ArkitBasis | None = None, reason: str = "", l1: float = 0.01):
        self.rest = np.asarray(rest, np.float64)
        self.basis = basis
        self.reason = reason
        self.l1 = float(l1)

    def __call__(self, skin) -> tuple[dict | None, dict]:
        if self.basis is None:
            return None, {"available": False, "reason": self.reason}
        try:
            sol = solve_arkit(self.basis, np.asarray(skin, np.float64) - self.rest, l1=self.l1)
        except FitError as e:
            return None, {"available": False, "reason": str(e)}
        return dict(sol.coefficients), {
            "available": True,
            **sol.to_dict(),
            "source": self.basis.source,
            "method": "bounded L1-weighted least squares (0 <= c <= 1, l1 "
            f"{self.l1:g} mm per mm of each shape's RMS motion) of the ICT-FaceKit ARKit "
            "shapes cloned onto the subject "
            "(jaxface.interop.arkit) to the fitted skin motion, Tukey-weighted",
            "transfer": dict(self.basis.info),
            "sides": "Left = the subject's own left (+x), as ICT's _L",
        }


_READOUTS: dict[tuple[int, str], ArkitReadout] = {}


def readout_for_subject(subject, ict: Any = "auto") -> ArkitReadout:
    """The :class:`ArkitReadout` of a :class:`jaxface.fit.pipeline.Subject` (cached per
    subject object).

    Args:
        ict: ``"auto"`` (:func:`default_ict_path`), a path to ``ict_face.npz``, an
            :class:`ArkitBasis` on the subject's skin, or None (off: the readout reports
            that it was not requested).
    """
    import weakref

    from ...errors import JaxfaceError

    rest = np.asarray(subject.forward.rest, np.float64)
    if ict is None:
        return ArkitReadout(rest, reason="ARKit readout not requested (arkit=None)")
    if isinstance(ict, ArkitBasis):
        return ArkitReadout(rest, ict)
    key = (id(subject), str(ict))
    hit = _READOUTS.get(key)
    if hit is not None and np.array_equal(hit.rest, rest):
        return hit
    path = default_ict_path(shared_fallback=False) if ict == "auto" else Path(ict)
    if path is None or not Path(path).is_file():
        ro = ArkitReadout(
            rest,
            reason="no ICT-FaceKit data: the ARKit shapes are cloned from ict_face.npz, which "
            "jaxface does not ship; set JAXFACE_ICT to the file (or give jaxface fit --ict FILE) "
            "and fit again" + (f" (not found: {path})" if path is not None else ""),
        )
    else:
        try:
            basis = transfer_ict_basis(
                rest,
                np.asarray(subject.triangles),
                subject.landmarks_on(rest),
                subject.face_mask,
                ict_path=path,
            )
            ro = ArkitReadout(rest, basis)
        except (JaxfaceError, ValueError) as e:
            ro = ArkitReadout(rest, reason=f"the ARKit shapes could not be transferred: {e}")
    try:
        weakref.finalize(subject, _READOUTS.pop, key, None)
    except TypeError:  # not weak-referenceable: no cache (an id could be reused)
        return ro
    _READOUTS[key] = ro
    return ro
