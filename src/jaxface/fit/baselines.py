"""Baselines for the expression fit (issue 7), on the same scans as the fitter.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.

* **B0** (:func:`baseline_b0`): the registered neutral, unchanged: what a fit that explains
  nothing would give. It is moved into the expression scan's frame with the inverse of the
  rigid alignment (expression -> neutral) so it can be compared with that scan.
* **B1** (:func:`baseline_b1`): a landmark-only thin-plate-spline warp of the registered
  neutral. In the neutral's frame, each landmark ``l`` present in both scans moves by the
  expression's landmark displacement ``T(q_expr_l) - q_neutral_l`` (``T`` the rigid
  alignment expression -> neutral, ``q`` the scan landmarks); the TPS
  (:func:`jaxface.rbf.fit_numpy`, kernel ``U(r) = r^2 log r^2``, exact interpolation by
  default) through these displacements, anchored at the registered neutral's landmarks,
  warps every vertex; the result is moved back into the expression scan's frame.
  Using displacements (not the scan landmarks themselves) keeps the registration's own
  landmark residual out of the baseline.
* B2 (Erdoğdu 2010) lives in :mod:`jaxface.erdogdu`; it is not wrapped here yet.

Both return a :class:`jaxface.mesh.TriMesh` with the template's topology, in the expression
scan's frame, directly comparable with the fitter's output.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import LandmarkError
from ..io.preprocess import RigidTransform
from .metrics import landmark_dict, mesh_arrays

__all__ = ["baseline_b0", "baseline_b1", "expression_landmark_displacements"]


def _transform_of(alignment) -> RigidTransform:
    if alignment is None:
        return RigidTransform()
    return getattr(alignment, "transform", alignment)


def baseline_b0(registration, alignment=None):
    """B0: the registered neutral in the expression scan's frame.

    Arguments:
        registration: a :class:`jaxface.fit.register.Registration` (or a mesh, mm) in the
            neutral scan's frame.
        alignment: the expression -> neutral alignment (an
            :class:`jaxface.fit.align.AlignmentResult` or a ``RigidTransform``); ``None``
            when both scans share a frame.

    Returns:
        :class:`jaxface.mesh.TriMesh`, mm, expression scan frame.
    """
    from ..mesh import TriMesh

    mesh = getattr(registration, "mesh", registration)
    v, f = mesh_arrays(mesh)
    return TriMesh(_transform_of(alignment).inverse().apply(v), f, validate=False)


def expression_landmark_displacements(
    neutral_landmarks, expression_landmarks, alignment=None, labels: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """label -> ``(3,)`` displacement (mm, neutral frame) of each landmark from the neutral
    scan to the rigidly aligned expression scan: ``T(q_expr) - q_neutral``."""
    T = _transform_of(alignment)
    n = landmark_dict(neutral_landmarks)
    e = landmark_dict(expression_landmarks)
    keys = [k for k in (labels if labels is not None else n) if k in n and k in e]
    return {k: T.apply(e[k][None])[0] - n[k] for k in keys}


def baseline_b1(
    registration,
    expression_landmarks,
    alignment=None,
    *,
    neutral_landmarks=None,
    labels: Sequence[str] | None = None,
    kernel: str = "tps",
    reg: float = 0.0,
):
    """B1: landmark-only TPS warp of the registered neutral (see the module doc).

    Arguments:
        registration: :class:`jaxface.fit.register.Registration` (neutral scan frame).
        expression_landmarks: the expression scan's landmarks (Landmarks or dict), mm, in the
            expression scan's frame.
        alignment: expression -> neutral alignment (AlignmentResult or RigidTransform).
        neutral_landmarks: the neutral scan's landmarks; default
            ``registration.scan_landmarks``.
        labels: restrict to these labels (default: all common to the three sets).
        kernel, reg: passed to :func:`jaxface.rbf.fit_numpy`.

    Returns:
        :class:`jaxface.mesh.TriMesh`, mm, expression scan frame.

    Raises:
        LandmarkError: fewer than 5 common landmarks.
    """
    from ..mesh import TriMesh
    from ..rbf import fit_numpy

    T = _transform_of(alignment)
    nl = neutral_landmarks if neutral_landmarks is not None else registration.scan_landmarks
    disp = expression_landmark_displacements(nl, expression_landmarks, T, labels)
    anchor = landmark_dict(registration.landmarks)
    keys = [k for k in disp if k in anchor]
    if len(keys) < 5:
        raise LandmarkError(
            f"B1 needs at least 5 landmarks present on the registered neutral, the neutral scan and "
            f"the expression scan; found {len(keys)}: {keys}."
        )
    src = np.stack([anchor[k] for k in keys])
    dst = src + np.stack([disp[k] for k in keys])
    morph = fit_numpy(src, dst, kernel=kernel, reg=reg)
    v, f = mesh_arrays(registration.mesh)
    warped = morph.apply_np(v)
    return TriMesh(T.inverse().apply(warped), f, validate=False)
