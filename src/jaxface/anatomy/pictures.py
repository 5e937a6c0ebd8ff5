"""Pictures of a rig's expressions (PNG, via :mod:`jaxface.render`).

:func:`emotion_pictures` writes the six emotion presets of :mod:`jaxface.facs` (one PNG per
emotion, front and three-quarter view, plus an overview sheet), the pictures the demo shows.
:func:`expression_sheet` draws any list of expressions side by side. Units: mm.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .. import facs
from .rig import Rig, synthesize

__all__ = ["emotion_pictures", "expression_sheet", "EMOTION_ORDER"]

EMOTION_ORDER = ("happiness", "sadness", "surprise", "fear", "anger", "disgust")


def _render(vertices, triangles, view, px, bounds):
    from ..render import Layer, rasterize

    return rasterize([Layer(np.asarray(vertices), np.asarray(triangles))], view=view, width=px,
                     height=px, bounds=bounds).image


def expression_sheet(path, rig: Rig, expressions, *, views=("front", (30.0, 5.0)), px: int = 420,
                     ncol: int | None = None, title: str | None = None) -> Path:
    """Draw expressions side by side.

    Args:
        path: PNG file to write.
        rig: the :class:`Rig`.
        expressions: list of ``(title, aus)`` with ``aus`` an ``{AU: intensity}`` dict.
        views: view names or ``(azimuth, elevation)`` pairs (see :mod:`jaxface.render`).
        px: pixels per panel.
        ncol: panels per row (default: all views of one expression per row).
        title: figure title.

    Returns:
        the written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rest = np.asarray(rig.rest)
    face = rig.info.frame
    # frame the face (landmarks +- margins), the same box for every panel
    lo = face.to_world([-85.0, -125.0, -120.0])
    hi = face.to_world([85.0, 75.0, 60.0])
    bounds = np.stack([np.minimum(lo, hi), np.maximum(lo, hi)])
    panels = []
    for name, aus in expressions:
        a, jaw, puff = facs.aus_to_controls(aus, rig.muscle_names)
        x = np.asarray(synthesize(rig, jnp.asarray(a, rig.rest.dtype), jaw, puff)) if aus else rest
        for v in views:
            panels.append((f"{name}", _render(x, rig.triangles, v, px, bounds)))
    ncol = ncol or len(views)
    nrow = (len(panels) + ncol - 1) // ncol
    fig, axs = plt.subplots(nrow, ncol, figsize=(3.0 * ncol, 3.1 * nrow), squeeze=False)
    for ax in axs.ravel():
        ax.axis("off")
    for ax, (t, img) in zip(axs.ravel(), panels):
        ax.imshow(img)
        ax.set_title(t, fontsize=10)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def emotion_pictures(rig: Rig, out_dir, *, intensity: float = 1.0, px: int = 420) -> list[Path]:
    """Write the six emotions (:data:`jaxface.facs.EMOTIONS`) as PNGs into ``out_dir``.

    Files: ``emotion_<name>.png`` (neutral and the emotion, front and three-quarter views) and
    ``emotions.png`` (all six, front view).

    Returns:
        the written paths.
    """
    out = Path(out_dir)
    paths = []
    for name in EMOTION_ORDER:
        aus = {k: v * intensity for k, v in facs.EMOTIONS[name].items()}
        paths.append(expression_sheet(out / f"emotion_{name}.png", rig,
                                      [("neutral", {}), (name, aus)], px=px, ncol=2,
                                      views=("front", (35.0, 5.0))))
    paths.append(expression_sheet(out / "emotions.png", rig,
                                  [("neutral", {})] + [(n, facs.EMOTIONS[n]) for n in EMOTION_ORDER],
                                  views=("front",), ncol=4, px=px))
    return paths
