"""Scan registration, rigid alignment, fit metrics and baselines (issue 7).

Submodules:

* :mod:`jaxface.fit.align`: rigid / similarity alignment of an expression scan to the neutral
  on the expression-stable landmarks, then robust point-to-plane ICP on stable regions.
* :mod:`jaxface.fit.register`: template skin -> neutral scan registration (landmark TPS, then
  Laplacian-regularised non-rigid ICP).
* :mod:`jaxface.fit.metrics`: point-to-surface and landmark metrics (mm), upper/lower split.
* :mod:`jaxface.fit.baselines`: B0 (registered neutral), B1 (landmark TPS warp) and B2
  (Erdoğdu 2010 AU transfer from a source subject).
* :mod:`jaxface.fit.evaluation`: the issue-7 ground-truth protocol for the shared
  ``bosphorus_style`` data.
* the inverse solve (JAX), in parts: :mod:`jaxface.fit.options` (:class:`FitOptions` and its
  groups), :mod:`jaxface.fit.params` (the unknowns), :mod:`jaxface.fit.forward` (the exact rig),
  :mod:`jaxface.fit.reduced` (its reduced response model), :mod:`jaxface.fit.residuals`
  (residuals and the exact-gradient correction), :mod:`jaxface.fit.inner` (the
  Levenberg-Marquardt solves), :mod:`jaxface.fit.active_set` (the activation bounds),
  :mod:`jaxface.fit.correspond` (scan-to-skin correspondences), :mod:`jaxface.fit.conditioning`
  (a diagnostic) and :mod:`jaxface.fit.solve` (the outer loop, :func:`fit_points`); the design
  is in ``docs/design/fit.md``.
* :mod:`jaxface.fit.au_motion` (JAX): AU readouts from a fit's skin motion: the fit's AU
  intensities (:func:`read_aus`: the fewest AUs that reproduce the motion, calibrated) and the
  motion (mm) each AU's share of the activations accounts for (:func:`au_skin_motion`).
* :mod:`jaxface.fit.pipeline`: neutral scan -> subject rig (:func:`prepare_subject`);
  expression scans -> activations, AUs, fitted skin, metrics, baselines
  (:func:`fit_expressions`); what ``jaxface fit`` runs.
"""

from __future__ import annotations

import importlib

_LAZY = {
    "RigidTransform": "jaxface.fit.align",
    "umeyama": "jaxface.fit.align",
    "align_scans": "jaxface.fit.align",
    "AlignmentResult": "jaxface.fit.align",
    "register_template": "jaxface.fit.register",
    "Registration": "jaxface.fit.register",
    "RegisterOptions": "jaxface.fit.register",
    "SurfaceIndex": "jaxface.fit.metrics",
    "DistanceStats": "jaxface.fit.metrics",
    "FacePlane": "jaxface.fit.metrics",
    "fit_metrics": "jaxface.fit.metrics",
    "landmark_errors": "jaxface.fit.metrics",
    "baseline_b0": "jaxface.fit.baselines",
    "baseline_b1": "jaxface.fit.baselines",
    "baseline_b2": "jaxface.fit.baselines",
    "b2_action_unit": "jaxface.fit.baselines",
    "Template": "jaxface.fit.register",
    "load_truth": "jaxface.fit.evaluation",
    "evaluation_region": "jaxface.fit.evaluation",
    "evaluate_against_truth": "jaxface.fit.evaluation",
    "ict_template": "jaxface.fit.evaluation",
    "FitOptions": "jaxface.fit.options",
    "SubjectOptions": "jaxface.fit.pipeline",
    "prepare_subject": "jaxface.fit.pipeline",
    "fit_expressions": "jaxface.fit.pipeline",
    "ExpressionFit": "jaxface.fit.pipeline",
    "au_skin_motion": "jaxface.fit.au_motion",
    "read_aus": "jaxface.fit.au_motion",
    "AuReadout": "jaxface.fit.au_motion",
}
_SUBMODULES = {
    "align",
    "register",
    "metrics",
    "baselines",
    "evaluation",
    "options",
    "params",
    "forward",
    "reduced",
    "residuals",
    "inner",
    "active_set",
    "correspond",
    "conditioning",
    "solve",
    "pipeline",
    "au_motion",
}

__all__ = sorted(set(_LAZY) | _SUBMODULES)


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        mod = importlib.import_module(f"jaxface.fit.{name}")
        globals()[name] = mod
        return mod
    raise AttributeError(f"module 'jaxface.fit' has no attribute {name!r}")


def __dir__():
    return __all__
