"""Scan registration, rigid alignment, fit metrics and baselines (issue 7).

Submodules (NumPy/SciPy at build time; nothing here is on the jit path):

* :mod:`jaxface.fit.align`: rigid / similarity alignment of an expression scan to the neutral
  on the expression-stable landmarks, then robust point-to-plane ICP on stable regions.
* :mod:`jaxface.fit.register`: template skin -> neutral scan registration (landmark TPS, then
  Laplacian-regularised non-rigid ICP).
* :mod:`jaxface.fit.metrics`: point-to-surface and landmark metrics (mm), upper/lower split.
* :mod:`jaxface.fit.baselines`: B0 (registered neutral), B1 (landmark TPS warp) and B2
  (Erdoğdu 2010 AU transfer from a source subject).
* :mod:`jaxface.fit.evaluation`: the issue-7 ground-truth protocol for the shared
  ``bosphorus_style`` data.
* :mod:`jaxface.fit.solve` (JAX): the inverse solve: activations, jaw pose and a rigid
  correction by optimistix Levenberg-Marquardt on point-to-plane + landmark residuals.
* :mod:`jaxface.fit.au_motion` (JAX): AU readouts from a fit's skin motion: the motion (mm)
  each action unit accounts for (the AUs an expression *shows*) and the sparse intensities
  (the fewest AUs that reproduce the motion), alongside the intensities of
  :func:`jaxface.facs.au_intensities`.
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
    "FitOptions": "jaxface.fit.solve",
    "SubjectOptions": "jaxface.fit.pipeline",
    "prepare_subject": "jaxface.fit.pipeline",
    "fit_expressions": "jaxface.fit.pipeline",
    "ExpressionFit": "jaxface.fit.pipeline",
    "au_motion": "jaxface.fit.au_motion",
}
_SUBMODULES = {
    "align",
    "register",
    "metrics",
    "baselines",
    "evaluation",
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
