"""Layers of a whole head: skin, eye (iris, sclera) and teeth colours (:func:`eye_colors`,
:func:`head_layers`)."""

from __future__ import annotations

import numpy as np

from .layers import SKIN, Layer

__all__ = ["IRIS", "SCLERA", "TEETH", "eye_colors", "head_layers"]


# ----------------------------------------------------------------------------- heads
IRIS = (0.36, 0.42, 0.46)
SCLERA = (0.94, 0.93, 0.90)
TEETH = (0.95, 0.93, 0.84)


def eye_colors(
    vertices: np.ndarray,
    center: np.ndarray,
    gaze=(0.0, 0.0, 1.0),
    *,
    iris_deg: float = 28.0,
    pupil_deg: float = 11.0,
    iris=IRIS,
) -> np.ndarray:
    """``(V, 3)`` RGB of an eyeball mesh: pupil, iris and sclera by the angle between each
    vertex direction (from ``center``, mm) and the gaze direction."""
    d = np.asarray(vertices, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    g = np.asarray(gaze, dtype=np.float64)
    g = g / np.linalg.norm(g)
    ang = np.degrees(np.arccos(np.clip(d @ g, -1.0, 1.0)))
    col = np.tile(np.asarray(SCLERA), (len(d), 1))
    t = _smooth01((iris_deg + 1.5 - ang) / 3.0)  # soft limbus
    col = col * (1 - t[:, None]) + np.asarray(iris) * t[:, None]
    p = _smooth01((pupil_deg + 1.0 - ang) / 2.0)
    col = col * (1 - p[:, None]) + 0.04 * p[:, None]
    return col


def _smooth01(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def head_layers(
    head,
    *,
    skin=None,
    scalars=None,
    cmap: str = "viridis",
    vmin=None,
    vmax=None,
    skin_color=SKIN,
    eyes=None,
    upper_teeth=None,
    lower_teeth=None,
    show_eyes: bool = True,
    show_teeth: bool = True,
) -> list[Layer]:
    """Layers for a :class:`jaxface.head.Head`: skin, eyeballs (with iris and pupil) and teeth.

    Any part can be given as deformed ``(V, 3)`` vertex positions (mm) of the same topology
    (``skin``, ``eyes=(left, right)``, ``upper_teeth``, ``lower_teeth``), e.g. a simulated
    expression. ``scalars`` (``(V,)``, e.g. an error in mm) colour the skin through ``cmap``.
    """
    sv = head.mesh.vertices if skin is None else np.asarray(skin)
    layers = [
        Layer(
            sv,
            head.mesh.triangles,
            color=skin_color,
            scalars=scalars,
            cmap=cmap,
            vmin=vmin,
            vmax=vmax,
            shade=0.55 if scalars is not None else 1.0,
            specular=0.04 if scalars is not None else 0.12,
            label="skin",
        )
    ]
    if show_eyes:
        for k, (mesh, c) in enumerate(zip(head.eyes, head.eye_centers)):
            v = mesh.vertices if eyes is None else np.asarray(eyes[k])
            shift = v.mean(axis=0) - mesh.vertices.mean(axis=0)
            layers.append(
                Layer(
                    v,
                    mesh.triangles,
                    colors=eye_colors(v, c + shift),
                    specular=0.35,
                    label=f"eye_{'left' if k == 0 else 'right'}",
                )
            )
    if show_teeth:
        for mesh, v, name in (
            (head.upper_teeth, upper_teeth, "upper_teeth"),
            (head.lower_teeth, lower_teeth, "lower_teeth"),
        ):
            layers.append(
                Layer(
                    mesh.vertices if v is None else np.asarray(v),
                    mesh.triangles,
                    color=TEETH,
                    specular=0.2,
                    label=name,
                )
            )
    return layers
