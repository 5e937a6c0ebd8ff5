"""Calibrate the detector's landmark definitions on labelled faces
(:mod:`jaxface.detect.definitions`).

Units mm. For each labelled face (a mesh or range scan with its true landmarks, any frame):

1. register the default head's face onto it exactly as the detector does
   (:func:`jaxface.detect.transfer.register_face`), the head carrying its own landmarks;
2. **points** (:data:`CALIBRATED_LABELS`): the closest point ``q`` of the true landmark on
   the registered face, a triangle ``t`` with barycentric weights ``b``, mapped back onto the
   head at rest: ``p = sum_k b_k X[t_k]`` (``X``: the template's rest vertices, head frame;
   the registration's vertex ``i`` is template vertex ``i``, so ``p`` is the point of the
   head that the registration carries onto the true landmark);
3. **offsets** (:data:`jaxface.detect.features.FEATURE_LABELS`): the relief feature ``e``
   found from the transferred landmark (:func:`jaxface.detect.features.feature_extrema`), and
   the offset ``R^T (x - e) / s`` to the true landmark ``x`` in the head frame (``R``,
   ``s``: the pose's rotation and scale). A feature label that also has a point (the nose
   peaks) is searched from that point, carried by the face's registration, as the detector
   searches it from the calibrated point: the points are calibrated first, over all faces.

A label's point is the mean of ``p`` over the faces, moved to its closest point on the head's
face, with ``spread_mm`` the mean distance of the single ``p`` from that mean; a feature's
offset is the mean of the faces' offsets, with ``spread_mm`` their mean distance from it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from ..closest import SurfaceIndex
from ..landmarks import Landmarks
from .definitions import CALIBRATED_LABELS, LandmarkDefinitions
from .features import FEATURE_LABELS, feature_extrema
from .transfer import FaceTemplate, build_face_template, register_face

__all__ = ["calibrate_definitions", "mapped_points"]


def _register(vertices, triangles, template: FaceTemplate):
    index = SurfaceIndex(np.asarray(vertices, np.float64), np.asarray(triangles, np.int64))
    pose, _, _, reg = register_face(index, template)
    return index, pose, reg


def _points(reg, truth: Landmarks, template: FaceTemplate) -> dict[str, np.ndarray]:
    """Step 2: the true :data:`CALIBRATED_LABELS` carried back onto the head at rest."""
    names = [n for n in CALIBRATED_LABELS if n in truth]
    if not names:
        return {}
    # attached to the registered face, carried back by the same barycentric weights
    attached, _ = reg.mesh.closest_points(truth.array(names))
    rest = attached.positions(template.mesh.vertices, template.mesh.triangles)
    return dict(zip(names, np.asarray(rest, np.float64)))


def _offsets(index, pose, reg, truth: Landmarks, template: FaceTemplate, points) -> dict:
    """Step 3: each feature's offset to its true landmark, head frame; the search starts at
    the label's calibrated point (``points``, head at rest) carried by the registration, or
    at the head's own landmark."""
    names = [n for n in FEATURE_LABELS if n in truth]
    guesses = {n: reg.landmarks[n] for n in names}
    own = [n for n in names if n in points]
    if own:
        attached, _ = template.mesh.closest_points(np.stack([points[n] for n in own]))
        carried = attached.positions(reg.mesh.vertices, reg.mesh.triangles)
        guesses.update(zip(own, np.asarray(carried, np.float64)))
    T = pose.transform
    found = feature_extrema(index, guesses, pose.left, pose.up, pose.forward)
    return {n: T.rotation.T @ (np.asarray(truth[n]) - e) / T.scale for n, e in found.items()}


def mapped_points(
    vertices: np.ndarray,
    triangles: np.ndarray,
    truth: Landmarks,
    template: FaceTemplate | None = None,
    points: dict[str, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """What one face says about the definitions (steps 1-3 of the module doc).

    Arguments:
        vertices, triangles: the face, ``(V, 3)`` mm and ``(F, 3)``; any frame.
        truth: its true landmarks (same frame, mm); labels it lacks are skipped.
        template: the face template (default: the head with its own landmarks; the
            landmarks do not steer the registration, whose landmark weights are zero).
        points: calibrated points (head frame, mm) from which the features that have one
            are searched (default: this face's own mapped points).

    Returns:
        ``(points, offsets)``: label -> ``(3,)`` mm, both in the head frame.
    """
    tpl = template or build_face_template(None)
    index, pose, reg = _register(vertices, triangles, tpl)
    mine = _points(reg, truth, tpl)
    return mine, _offsets(index, pose, reg, truth, tpl, mine if points is None else points)


def calibrate_definitions(
    faces: Iterable[tuple[np.ndarray, np.ndarray, Landmarks]],
    *,
    source: str = "",
    progress: Callable[[int], None] | None = None,
) -> LandmarkDefinitions:
    """Landmark definitions from labelled faces (see the module doc).

    Arguments:
        faces: ``(vertices (V, 3) mm, triangles (F, 3), true landmarks)`` per face.
        source: provenance text stored with the result.
        progress: called with the number of faces done after each face.

    Raises:
        ValueError: no face carries any of the calibrated or feature labels.
    """
    tpl = build_face_template(None)
    pts: dict[str, list[np.ndarray]] = {}
    done = []
    for v, f, truth in faces:
        index, pose, reg = _register(v, f, tpl)
        for n, x in _points(reg, truth, tpl).items():
            pts.setdefault(n, []).append(x)
        done.append((index, pose, reg, truth))
        if progress is not None:
            progress(len(done))
    count = len(done)
    names = [n for n in CALIBRATED_LABELS if n in pts]
    spread: dict[str, float] = {}
    points: dict[str, np.ndarray] = {}
    if names:
        mean = np.stack([np.mean(pts[n], axis=0) for n in names])
        idx = SurfaceIndex(np.asarray(tpl.mesh.vertices), np.asarray(tpl.mesh.triangles))
        on = idx.query(mean)
        for i, n in enumerate(names):
            points[n] = on.points[i].copy()
            spread[n] = float(np.mean(np.linalg.norm(np.asarray(pts[n]) - mean[i], axis=1)))
    offs: dict[str, list[np.ndarray]] = {}
    for index, pose, reg, truth in done:
        for n, x in _offsets(index, pose, reg, truth, tpl, points).items():
            offs.setdefault(n, []).append(x)
    if not pts and not offs:
        raise ValueError(f"none of the {count} faces carries a calibrated or feature label")
    offsets = {n: np.mean(offs[n], axis=0) for n in FEATURE_LABELS if n in offs}
    for n, m in offsets.items():
        spread[n] = float(np.mean(np.linalg.norm(np.asarray(offs[n]) - m, axis=1)))
    return LandmarkDefinitions(
        points=points, spread_mm=spread, offsets_mm=offsets, faces=count, source=source
    )
