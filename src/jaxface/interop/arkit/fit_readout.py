"""The ARKit readout of a fit (used by :mod:`jaxface.fit.pipeline`): :class:`ArkitReadout`, one
per subject and ICT file (:func:`readout_for_subject`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import FitError
from .basis import ArkitBasis, transfer_ict_basis
from .ict import default_ict_path
from .readout import attached_landmark_motion, eye_rim_motion, fit_arkit_to_scan, solve_arkit

__all__ = ["ArkitReadout", "readout_for_subject"]


# ------------------------------------------------------------------------------------------
# the readout of a fit (used by jaxface.fit.pipeline)
# ------------------------------------------------------------------------------------------
class ArkitReadout:
    """Reads ARKit coefficients for the fits of one subject, or says why it cannot (no ICT
    data, a failed transfer): it never makes numbers up.

    Call it with a fitted skin ``(V, 3)`` mm (the rig's frame and topology) to read the
    fitted skin motion (:func:`solve_arkit`), or use :meth:`from_scan` to read the scan
    itself (:func:`fit_arkit_to_scan`). Both return ``(coefficients dict or None, detail
    dict)``; ``detail`` holds ``available`` and either the :meth:`ArkitSolution.to_dict`
    fields with ``source``/``method``, or ``reason``.
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
        return dict(sol.coefficients), self._detail(sol, "the fitted skin motion, Tukey-weighted")

    def _detail(self, sol, data: str) -> dict:
        """The ``detail`` of an available readout of ``data`` (what the shapes were fitted to)."""
        return {
            "available": True,
            **sol.to_dict(),
            "source": self.basis.source if self.basis is not None else "",
            "method": "bounded L1-weighted least squares (0 <= c <= 1, l1 "
            f"{self.l1:g} mm per mm of each shape's RMS motion) of the ICT-FaceKit ARKit "
            f"shapes cloned onto the subject (jaxface.interop.arkit) to {data}",
            "transfer": dict(self.basis.info) if self.basis is not None else {},
            "sides": "Left = the subject's own left (+x), as ICT's _L",
        }

    def from_scan(
        self,
        scan,
        neutral,
        transform,
        triangles,
        landmark_names,
        landmark_tri,
        landmark_bary,
        fitted_skin=None,
    ) -> tuple[dict | None, dict]:
        """ARKit coefficients read from the expression scan itself: point-to-plane ICP of the
        cloned shapes to the scan, with the landmarks' motion and the eye rims
        (:func:`fit_arkit_to_scan`, :func:`eye_rim_motion`). The rig cannot make every
        expression (a cheek that rises into the lower lid, a lid sliding across the eye), so
        the scan says more than the fitted skin; with ``fitted_skin`` the detail also holds
        the readout of the fitted skin motion (``fitted_skin``), what the rig made.

        Args:
            scan, neutral: the expression and neutral :class:`jaxface.io.Scan` (landmarks
                mm); transform: maps ``scan`` into the neutral's (the rig's) frame.
            triangles: ``(F, 3)`` the rig skin's; landmark_names, landmark_tri,
                landmark_bary: the rig's landmarks on it.
            fitted_skin: ``(V, 3)`` the fitted skin (mm, rig frame), or None.
        """
        if self.basis is None:
            return None, {"available": False, "reason": self.reason}
        tris = np.asarray(triangles, np.int64)
        lmk = attached_landmark_motion(
            landmark_names, landmark_tri, landmark_bary, neutral, scan, transform
        )
        try:
            rims = eye_rim_motion(self.rest, tris, neutral, scan, transform, mask=self.basis.mask)
            v, t, _ = scan.mesh_arrays()
            sol = fit_arkit_to_scan(
                self.basis,
                self.rest,
                tris,
                transform.apply(np.asarray(v, np.float64)),
                t,
                landmarks=lmk,
                rims=rims,
                l1=self.l1,
            )
        except FitError as e:
            return None, {"available": False, "reason": str(e)}
        n_lm = 0 if lmk is None else len(lmk[0])
        detail = self._detail(
            sol,
            "the expression scan: point-to-plane ICP, Tukey-weighted, with the landmarks' "
            f"motion ({n_lm} labels) and the eye holes' rims ({', '.join(rims.sides) or 'none'})",
        )
        if fitted_skin is not None:
            coeffs, fd = self(fitted_skin)
            detail["fitted_skin"] = {
                "coefficients": coeffs,
                "residual_mm": fd.get("residual_mm"),
                "method": "the same shapes read from the fitted skin motion: what the rig made",
            }
        return dict(sol.coefficients), detail


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
