"""Morph targets of a subject for export: the rig's controls and AUs (exact physics shape at
full activation), and the exact fitted skins of ``jaxface fit`` results.

Units mm; frame +y up, the face looks along +z, the subject's left is +x. A target is a
displacement ``(V, 3)`` from the rig's rest skin; in a morph-target player it is linear in
its weight (``rest + w * delta``), so it is the rig's exact synthesis at weight 1 (and at 0)
and a linear blend in between, while the rig itself is not linear in the activation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataNotFoundError, FitError, RigError

__all__ = ["rig_targets", "FitFrame", "read_fit", "MUSCLE_PREFIX", "FIT_PREFIX"]

#: morph-target name prefixes (AU and ARKit targets carry their bare names, e.g. ``AU12``,
#: ``browInnerUp``)
MUSCLE_PREFIX = "muscle."
FIT_PREFIX = "fit."


def rig_targets(rig, *, controls=None, aus=None, progress=None) -> list[tuple[str, np.ndarray]]:
    """One target per rig control (``muscle.<control>``: that control at activation 1, the
    others 0, jaw at rest; the controls include the fit's two cheek pressures
    :data:`~jaxface.anatomy.cheek_puff.PUFF_CONTROLS`, one cheek puffed at 1) and per AU
    (``AU12``: :func:`jaxface.facs.aus_to_controls` of that AU at intensity 1, jaw and cheek
    puff included), minus the rest skin.

    Args:
        rig: a rig (:func:`jaxface.anatomy.rig.build_rig`).
        controls: control names (default all; ``[]`` none).
        aus: AU names (default :data:`jaxface.facs.AU_NAMES`; ``[]`` none).
        progress: called with each target's name.

    Returns:
        ``[(name, delta (V, 3) mm)]``.

    Raises:
        RigError: an unknown control or AU; a synthesis with NaN/inf.
    """
    import jax.numpy as jnp

    from ..anatomy.cheek_puff import PUFF_CONTROLS
    from ..anatomy.jaw import JawPose
    from ..anatomy.rig import synthesize
    from ..facs import AU_NAMES, aus_to_controls

    names = list(rig.muscle_names)
    every = names + list(PUFF_CONTROLS)
    controls = every if controls is None else list(controls)
    aus = list(AU_NAMES) if aus is None else list(aus)
    bad = [c for c in controls if c not in every]
    if bad:
        raise RigError(f"unknown controls {bad}; the rig's controls are {every}.")
    bad = [a for a in aus if a not in AU_NAMES]
    if bad:
        raise RigError(f"unknown AUs {bad}; known: {list(AU_NAMES)}.")
    rest = np.asarray(rig.rest, np.float64)
    jobs = []
    for c in controls:
        a = np.zeros(len(names))
        puff = np.zeros(2)
        if c in PUFF_CONTROLS:  # one cheek's pressure, as the fit's control of that name
            puff[PUFF_CONTROLS.index(c)] = 1.0
        else:
            a[names.index(c)] = 1.0
        jobs.append((MUSCLE_PREFIX + c, a, JawPose(0.0, 0.0, 0.0), puff))
    for au in aus:
        a, jaw, puff = aus_to_controls({au: 1.0}, names)
        jobs.append((au, a, jaw, puff))
    out = []
    for name, a, jaw, puff in jobs:
        if progress is not None:
            progress(name)
        x = np.asarray(synthesize(rig, jnp.asarray(a, rig.rest.dtype), jaw, puff), np.float64)
        if not np.all(np.isfinite(x)):
            raise RigError(f"the synthesis of {name!r} produced NaN/inf.")
        out.append((name, x - rest))
    return out


@dataclass(frozen=True)
class FitFrame:
    """One ``jaxface fit`` result mapped onto the rig.

    Attributes:
        stem: the scan's stem; activations: control -> activation; jaw: the JSON's jaw dict.
        skin: ``(V, 3)`` the fitted skin in the rig's frame (the registered neutral), mm.
        arkit: the JSON's ``arkit`` coefficients (or None).
    """

    stem: str
    activations: dict
    jaw: dict
    skin: np.ndarray
    arkit: dict | None


def read_fit(json_path, n_vertices: int | None = None) -> FitFrame:
    """Read ``<stem>.json`` and ``<stem>.fitted.ply`` (beside it) and take the fitted skin
    from the scan's frame back to the rig's with the JSON's ``rigid.rig_to_scan``
    (``p = R x + t``, so ``x = R^-1 (p - t)``).

    Raises:
        DataNotFoundError: a file is missing; FitError: the JSON lacks the keys or the mesh
            has another vertex count than ``n_vertices`` (the fit belongs to another subject).
    """
    from ..mesh import load_mesh

    p = Path(json_path)
    if not p.is_file():
        raise DataNotFoundError(f"fit JSON not found: {p}")
    d = json.loads(p.read_text())
    stem = str(d.get("scan") or p.stem)
    ply = p.with_name(f"{p.stem}.fitted.ply")
    if not ply.is_file():
        raise DataNotFoundError(
            f"the fitted skin {ply} (written by jaxface fit beside {p.name}) is missing."
        )
    try:
        r2s = d["rigid"]["rig_to_scan"]
        R = np.asarray(r2s["rotation"], np.float64)
        t = np.asarray(r2s["translation"], np.float64)
        acts = {str(k): float(v) for k, v in d["activations"].items()}
    except (KeyError, TypeError) as e:
        raise FitError(f"{p} is not a jaxface fit JSON (missing {e}).") from None
    m = load_mesh(ply, validate=False, check_size=False)
    P = np.asarray(m.vertices, np.float64)
    if n_vertices is not None and len(P) != n_vertices:
        raise FitError(
            f"{ply} has {len(P)} vertices, the subject's skin {n_vertices}: the fit belongs to "
            "another subject (export the neutral scan the fit used)."
        )
    x = np.linalg.solve(R, (P - t).T).T
    arkit = d.get("arkit") if isinstance(d.get("arkit"), dict) else None
    return FitFrame(stem, acts, dict(d.get("jaw") or {}), x, arkit)
