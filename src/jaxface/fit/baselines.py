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
* **B2** (:func:`baseline_b2`): the Erdoğdu (2010) thin-plate-spline AU transfer
  (:func:`jaxface.erdogdu.animate`) onto the registered neutral, from a *source* subject's
  neutral and AU scan of the same action unit. It applies to single-AU scans whose AU the
  method has control points for (:func:`b2_action_unit`: AU1, 2, 4, 12 with its sides, 14,
  15, 17, 20). The expression magnitude ``m`` is fitted to the expression scan
  (:func:`jaxface.erdogdu.fit_magnitude`: mean distance of the moved face vertices to the
  nearest scan points, each capped at ``cap_mm``, so that vertices where the scan has no
  data do not count), so B2, like the fitter, sees the scan it is compared with.

All return a :class:`jaxface.mesh.TriMesh` with the template's topology, in the expression
scan's frame, directly comparable with the fitter's output.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ..erdogdu import SUPPORTED_AUS, animate, fit_magnitude
from ..errors import FitError, LandmarkError
from ..io.bosphorus import parse_scan_name
from ..mesh import TriMesh
from ..rbf import KernelName, fit_numpy
from ..rigid import RigidTransform
from .metrics import landmark_dict, mesh_arrays

__all__ = [
    "baseline_b0",
    "baseline_b1",
    "baseline_b2",
    "b2_action_unit",
    "BaselineB2",
    "expression_landmark_displacements",
]


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
    kernel: KernelName = "tps",
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


def b2_action_unit(scan) -> str | None:
    """The action unit B2 reproduces for a scan, from its Bosphorus name, or ``None``.

    B2 applies to single-AU scans (classes ``LFAU`` and ``UFAU``) whose AU has an Erdoğdu
    control-point layout (:data:`jaxface.erdogdu.SUPPORTED_AUS`); the side is kept
    (``"12L"``). Emotions, AU combinations, neutral, pose and occlusion scans give ``None``.

    Arguments:
        scan: a :class:`jaxface.io.Scan`, a path or a stem such as ``"bs000_LFAU_12L_0"``.
    """
    name = getattr(scan, "path", None) or getattr(scan, "stem", None) or scan
    info = parse_scan_name(str(name))
    if info is None or info.kind not in ("LFAU", "UFAU") or len(info.aus) != 1:
        return None
    au = info.aus[0]
    if au.au not in SUPPORTED_AUS:
        return None
    return f"{au.au}{au.side or ''}"


class BaselineB2(NamedTuple):
    """Result of :func:`baseline_b2`.

    Attributes:
        mesh: :class:`jaxface.mesh.TriMesh`, mm, expression scan frame (template topology).
        magnitude: the expression magnitude ``m`` used (fitted or given).
        animation: the :class:`jaxface.erdogdu.Animation` (neutral frame, at ``m = 1``).
    """

    mesh: Any
    magnitude: float
    animation: Any


def baseline_b2(
    registration,
    expression_scan,
    alignment,
    source_neutral,
    source_au_scan,
    au,
    *,
    magnitude: float | None = None,
    bounds: tuple[float, float] = (0.0, 2.0),
    cap_mm: float = 5.0,
    **animate_kw,
) -> BaselineB2:
    """B2: Erdoğdu (2010) TPS transfer of ``au`` onto the registered neutral (module doc).

    Arguments:
        registration: :class:`jaxface.fit.register.Registration` (neutral scan frame), or any
            object with ``mesh`` (TriMesh, mm) and ``landmarks`` (its Bosphorus landmarks).
        expression_scan: the expression scan (:class:`jaxface.io.Scan`, or ``(P, 3)`` points),
            mm, in its own frame; used to fit ``m``.
        alignment: expression -> neutral alignment (AlignmentResult or RigidTransform; None
            when both scans share a frame).
        source_neutral, source_au_scan: the source subject's neutral and AU scans (Scan, or
            anything :func:`jaxface.erdogdu.animate` accepts), mm.
        au: the AU, e.g. ``12``, ``"12L"`` (:func:`b2_action_unit` reads it from a scan name).
        magnitude: a fixed ``m``; ``None`` fits it to the expression scan within ``bounds``,
            over the moved vertices of the registration's ``face_mask`` (all moved vertices
            when it has none), each distance capped at ``cap_mm`` (mm).
        animate_kw: passed to :func:`jaxface.erdogdu.animate`.

    Returns:
        :class:`BaselineB2`.

    Raises:
        RigError (unsupported AU), LandmarkError (landmarks missing): from
        :func:`jaxface.erdogdu.animate`; FitError: an expression scan without points.
    """
    T = _transform_of(alignment)
    pts = None
    if magnitude is None:
        pts = np.asarray(
            getattr(expression_scan, "points", expression_scan), dtype=np.float64
        ).reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) == 0:
            raise FitError(
                "B2: the expression scan has no valid (finite) points to fit the magnitude "
                "to; give a scan with data, or a fixed magnitude=."
            )
    v, f = mesh_arrays(registration.mesh)
    target = (TriMesh(v, f, validate=False), registration.landmarks)
    anim = animate(source_neutral, source_au_scan, target, au, 1.0, **animate_kw)
    if pts is not None:
        mask = anim.moved_mask
        fm = getattr(registration, "face_mask", None)
        if fm is not None:
            mask = mask & np.asarray(fm, bool)
        m, _ = fit_magnitude(anim, T.apply(pts), mask=mask, bounds=bounds, cap_mm=cap_mm)
    else:
        assert magnitude is not None  # pts is None only for a given magnitude
        m = float(magnitude)
    return BaselineB2(
        TriMesh(T.inverse().apply(anim.at_magnitude(m)), f, validate=False), float(m), anim
    )
