"""Pictures comparing the LTW backend with the PBD rig (PNG, via :mod:`jaxface.render`).

:func:`compare_emotions` synthesizes the six emotion presets of :mod:`jaxface.facs` with both
backends (the same activation vector, jaw pose and cheek puff) and writes them side by side,
with the per-vertex distance between the two results as a heat map. Units: mm.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .. import facs
from ..anatomy.rig import synthesize
from ..errors import RigError
from ..render import Layer, rasterize, save_figure
from .rig import LTWRig, synthesize_ltw

__all__ = ["EMOTION_ORDER", "emotion_faces", "compare_emotions"]

EMOTION_ORDER = ("happiness", "sadness", "surprise", "fear", "anger", "disgust")


def emotion_faces(rig, synth, intensity: float = 1.0) -> dict[str, np.ndarray]:
    """``{emotion: (V, 3) mm}`` for the six presets (plus ``"neutral"``) with ``synth(rig, a,
    jaw, puff)`` (e.g. :func:`synthesize_ltw` or ``jaxface.anatomy.rig.synthesize``)."""
    out = {"neutral": np.asarray(rig.rest)}
    for name in EMOTION_ORDER:
        a, jaw, puff = facs.emotion_controls(name, rig.muscle_names, intensity)
        out[name] = np.asarray(synth(rig, jnp.asarray(a, rig.rest.dtype), jaw, puff))
    return out


def compare_emotions(
    path, ltw_rig: LTWRig, pbd_rig=None, *, intensity: float = 1.0, px: int = 300, view="front"
) -> Path:
    """Write the six emotions, LTW next to PBD, to a PNG.

    Args:
        path: PNG file to write.
        ltw_rig: the :class:`LTWRig`.
        pbd_rig: the PBD ``jaxface.anatomy.rig.Rig`` of the same face (same control order), or
            None to draw the LTW backend alone.
        intensity: emotion intensity.
        px: pixels per panel.
        view: view name or ``(azimuth, elevation)``.

    Returns:
        the written path. Columns: PBD, LTW, |PBD - LTW| (mm heat map); rows: emotions.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tris = np.asarray(ltw_rig.triangles)
    faces = {"LTW": emotion_faces(ltw_rig, synthesize_ltw, intensity)}
    if pbd_rig is not None:
        if tuple(pbd_rig.muscle_names) != tuple(ltw_rig.muscle_names):
            raise RigError(
                "the PBD and LTW rigs have different controls; build both from the same map."
            )

        faces = {"PBD": emotion_faces(pbd_rig, synthesize, intensity), **faces}
    rest = np.asarray(ltw_rig.rest)
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    pad = 0.08 * (hi - lo)
    bounds = np.stack([lo - pad, hi + pad])
    rows = ("neutral",) + EMOTION_ORDER
    cols = list(faces) + (["|PBD - LTW|"] if pbd_rig is not None else [])
    fig, axs = plt.subplots(
        len(rows), len(cols), figsize=(2.6 * len(cols), 2.7 * len(rows)), squeeze=False
    )
    vmax = 0.0
    if pbd_rig is not None:
        diffs = {r: np.linalg.norm(faces["PBD"][r] - faces["LTW"][r], axis=1) for r in rows}
        vmax = max(float(np.percentile(np.concatenate(list(diffs.values())), 99)), 1e-3)
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            ax = axs[i, j]
            ax.axis("off")
            if c.startswith("|"):
                layer = Layer(
                    faces["LTW"][r], tris, scalars=diffs[r], cmap="magma", vmin=0.0, vmax=vmax
                )
                title = f"{r}: max {diffs[r].max():.1f} mm"
            else:
                layer = Layer(faces[c][r], tris)
                disp = np.linalg.norm(faces[c][r] - rest, axis=1).max()
                title = f"{c} {r} (max {disp:.1f} mm)"
            img = rasterize([layer], view=view, width=px, height=px, bounds=bounds).image
            ax.imshow(img)
            ax.set_title(title, fontsize=8)
    fig.suptitle(
        f"emotions, intensity {intensity:g}" + (f"; heat map 0..{vmax:.1f} mm" if vmax else ""),
        fontsize=10,
    )
    fig.tight_layout()

    return save_figure(fig, path, dpi=100, close=True)
