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
from ..errors import RigError
from ..render import Layer, draw, head_layers, rasterize, save_figure
from .jaw import JawPose
from .rig import Rig, synthesize

__all__ = [
    "emotion_pictures",
    "expression_sheet",
    "muscle_map_picture",
    "jaw_diagram",
    "EMOTION_ORDER",
]

EMOTION_ORDER = ("happiness", "sadness", "surprise", "fear", "anger", "disgust")


def _layers(rig: Rig, x, jaw, head):
    """The skin ``x`` alone, or with ``head``'s eyes and teeth (lower teeth moved with the jaw)."""
    if head is None:
        return [Layer(np.asarray(x), np.asarray(rig.triangles))]
    R, t = rig.jaw.transform(jaw)
    lower = np.asarray(head.lower_teeth.vertices) @ np.asarray(R).T + np.asarray(t)
    return head_layers(head, skin=np.asarray(x), lower_teeth=lower)


def expression_sheet(
    path,
    rig: Rig,
    expressions,
    *,
    views=("front", (30.0, 5.0)),
    px: int = 420,
    ncol: int | None = None,
    title: str | None = None,
    head=None,
) -> Path:
    """Draw expressions side by side.

    Args:
        path: PNG file to write.
        rig: the :class:`Rig`.
        expressions: list of ``(title, aus)`` with ``aus`` an ``{AU: intensity}`` dict.
        views: view names or ``(azimuth, elevation)`` pairs (see :mod:`jaxface.render`).
        px: pixels per panel.
        ncol: panels per row (default: all views of one expression per row).
        title: figure title.
        head: optional :class:`jaxface.head.Head` the rig was built on (same skin topology):
            its eyes and teeth are drawn too, the lower teeth following the jaw.

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

    if head is not None and head.mesh.n_vertices != rest.shape[0]:
        raise RigError(
            f"head has {head.mesh.n_vertices} skin vertices, the rig {rest.shape[0]}: "
            "pass the head the rig was built on, or head=None."
        )
    panels = []
    for name, aus in expressions:
        a, jaw, puff = facs.aus_to_controls(aus, rig.muscle_names)
        x = np.asarray(synthesize(rig, jnp.asarray(a, rig.rest.dtype), jaw, puff)) if aus else rest
        layers = _layers(rig, x, jaw, head)
        for v in views:
            panels.append(
                (f"{name}", rasterize(layers, view=v, width=px, height=px, bounds=bounds).image)
            )
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

    return save_figure(fig, path, dpi=100, close=True)


def emotion_pictures(
    rig: Rig, out_dir, *, intensity: float = 1.0, px: int = 420, head=None
) -> list[Path]:
    """Write the six emotions (:data:`jaxface.facs.EMOTIONS`) as PNGs into ``out_dir``.

    Files: ``emotion_<name>.png`` (neutral and the emotion, front and three-quarter views) and
    ``emotions.png`` (all six, front view). ``head``: see :func:`expression_sheet`.

    Returns:
        the written paths.
    """
    out = Path(out_dir)
    paths = []
    for name in EMOTION_ORDER:
        aus = {k: v * intensity for k, v in facs.EMOTIONS[name].items()}
        paths.append(
            expression_sheet(
                out / f"emotion_{name}.png",
                rig,
                [("neutral", {}), (name, aus)],
                px=px,
                ncol=2,
                views=("front", (35.0, 5.0)),
                head=head,
            )
        )
    paths.append(
        expression_sheet(
            out / "emotions.png",
            rig,
            [("neutral", {})] + [(n, facs.EMOTIONS[n]) for n in EMOTION_ORDER],
            views=("front",),
            ncol=4,
            px=px,
            head=head,
        )
    )
    return paths


BONE = (0.88, 0.85, 0.76)


def _muscle_colors(placed):
    """One colour per muscle base name (left and right share it)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    bases = sorted({p.spec.base for p in placed})
    return {b: cmap(i % 20)[:3] for i, b in enumerate(bases)}


def muscle_map_picture(path, rig: Rig, *, px: int = 460) -> Path:
    """The muscle map: muscles on the skull (front and three-quarter views, one colour per
    muscle, left and right alike) and their action lines drawn on the face (origin -> insertion
    at the skin; hidden parts dashed). Units: mm.

    Args:
        path: PNG file to write.
        rig: a rig from :func:`jaxface.anatomy.build_rig` (its build-time ``info``).
        px: pixels per panel.

    Returns:
        the written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    info = rig.info
    skull = info.skull
    colors = _muscle_colors(info.placed)
    bone = [
        Layer(np.asarray(skull.cranium.vertices), np.asarray(skull.cranium.triangles), color=BONE),
        Layer(
            np.asarray(skull.mandible.vertices), np.asarray(skull.mandible.triangles), color=BONE
        ),
    ]
    muscles = [
        Layer(
            np.asarray(p.mesh.vertices),
            np.asarray(p.mesh.triangles),
            color=colors[p.spec.base],
            specular=0.05,
        )
        for p in info.placed
        if p.mesh is not None
    ]
    skin = np.asarray(rig.rest)
    lo, hi = skin.min(axis=0), skin.max(axis=0)
    bounds = np.stack([lo, hi])
    lines, lcol = [], []
    for p in info.placed:
        if p.origin_skin is None or p.insertion_skin is None:
            continue
        a = np.asarray(p.origin_skin, float).reshape(-1, 3)[0]
        b = np.asarray(p.insertion_skin, float).reshape(-1, 3)[0]
        lines.append(np.linspace(a, b, 12))
        lcol.append(colors[p.spec.base])
    fig, axs = plt.subplots(1, 3, figsize=(3 * px / 100 + 2.2, px / 100 + 0.4))
    draw(
        axs[0],
        bone + muscles,
        "front",
        width=px,
        height=px,
        bounds=bounds,
        title="muscles on the skull",
    )
    draw(
        axs[1],
        bone + muscles,
        (35.0, 5.0),
        width=px,
        height=px,
        bounds=bounds,
        title="three-quarter view",
    )
    draw(
        axs[2],
        [Layer(skin, np.asarray(rig.triangles))],
        "front",
        width=px,
        height=px,
        bounds=bounds,
        polylines=lines,
        polyline_colors=lcol,
        polyline_width=2.0,
        title="action lines on the face (origin -> insertion)",
    )
    handles = [Patch(color=c, label=b.replace("_", " ")) for b, c in colors.items()]
    fig.legend(handles=handles, loc="center right", fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 0.83, 1))

    return save_figure(fig, path, dpi=100, close=True)


def jaw_diagram(path, rig: Rig, pose=None, *, px: int = 460) -> Path:
    """The jaw model: skull at rest (bone) and the mandible at ``pose`` (blue), with the pitch
    axis through the condyles (red), the yaw axis (green) and the protrusion direction (blue
    arrow), in side and front views, and the limits in the title. Units: mm, degrees.

    Args:
        path: PNG file to write.
        rig: the rig (its :class:`~jaxface.anatomy.jaw.JawModel` and skull).
        pose: a :class:`~jaxface.anatomy.jaw.JawPose` to show (default: pitch 12 deg, yaw 3 deg,
            protrusion 2 mm); smoothly clamped into the limits as in a synthesis.
        px: pixels per panel.

    Returns:
        the written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pose = JawPose(12.0, 3.0, 2.0) if pose is None else pose
    jm = rig.jaw
    skull = rig.info.skull
    R, t = (np.asarray(v, float) for v in jm.transform(pose))
    mand = np.asarray(skull.mandible.vertices, float)
    moved = mand @ R.T + t
    c = np.asarray(jm.pivot, float)
    axes = [
        np.stack([c - 55 * np.asarray(jm.pitch_axis), c + 55 * np.asarray(jm.pitch_axis)]),
        np.stack([c, c + 45 * np.asarray(jm.yaw_axis)]),
        np.stack([c, c + 40 * np.asarray(jm.protrusion_dir)]),
    ]
    axes = [np.linspace(a[0], a[1], 16) for a in axes]
    cols = [(0.85, 0.1, 0.1), (0.1, 0.6, 0.1), (0.1, 0.3, 0.9)]
    layers = [
        Layer(np.asarray(skull.cranium.vertices), np.asarray(skull.cranium.triangles), color=BONE),
        Layer(moved, np.asarray(skull.mandible.triangles), color=(0.55, 0.7, 0.95)),
    ]
    allv = np.concatenate([np.asarray(skull.cranium.vertices), mand, moved])
    bounds = np.stack([allv.min(0) - 10, allv.max(0) + 10])
    pc = jm.clamp(pose)
    fig, axs = plt.subplots(1, 2, figsize=(2 * px / 100, px / 100 + 0.6))
    for ax, view in zip(axs, ("side", "front")):
        draw(
            ax,
            layers,
            view,
            width=px,
            height=px,
            bounds=bounds,
            polylines=axes,
            polyline_colors=cols,
            polyline_width=2.5,
            title=view,
        )
    fig.suptitle(
        f"jaw pose: pitch {float(pc.pitch_deg):.1f} deg (limits {jm.pitch_limits[0]:g}..{jm.pitch_limits[1]:g}), "
        f"yaw {float(pc.yaw_deg):.1f} deg ({jm.yaw_limits[0]:g}..{jm.yaw_limits[1]:g}), protrusion "
        f"{float(pc.protrusion_mm):.1f} mm ({jm.protrusion_limits[0]:g}..{jm.protrusion_limits[1]:g})\n"
        "red: pitch axis through the condyles, green: yaw axis, blue: protrusion",
        fontsize=8,
    )
    fig.tight_layout()

    return save_figure(fig, path, dpi=100, close=True)
