"""ARKit-52 blendshape names and the ICT-FaceKit mapping (sides and merged shapes, see
:mod:`jaxface.interop.arkit`): names, weights and ``(K, V, 3)`` mm displacement fields."""

from __future__ import annotations

import numpy as np

from ...errors import DataNotFoundError

__all__ = [
    "ARKIT_NAMES",
    "ICT_TO_ARKIT",
    "ICT_UNUSED",
    "ARKIT_MISSING_IN_ICT",
    "arkit_from_ict_name",
    "arkit_weights_from_ict",
    "arkit_deltas_from_ict",
]

#: Apple ARKit's 52 ``ARFaceAnchor.BlendShapeLocation`` names, in ARKit's documented order
ARKIT_NAMES: tuple[str, ...] = (
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeLookDownLeft",
    "eyeLookDownRight",
    "eyeLookInLeft",
    "eyeLookInRight",
    "eyeLookOutLeft",
    "eyeLookOutRight",
    "eyeLookUpLeft",
    "eyeLookUpRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "eyeWideLeft",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawOpen",
    "jawRight",
    "mouthClose",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthFunnel",
    "mouthLeft",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthPucker",
    "mouthRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)

#: ICT-FaceKit shapes without an ARKit counterpart (not used by the basis)
ICT_UNUSED: tuple[str, ...] = ("PupilDilate_L", "PupilDilate_R", "cheekRaiser_L", "cheekRaiser_R")
#: ARKit shapes that ICT-FaceKit lacks: always reported as 0 and marked unavailable
ARKIT_MISSING_IN_ICT: tuple[str, ...] = ("tongueOut",)
#: ARKit shapes that are the sum of an ICT left and right shape
_MERGED = ("browInnerUp", "cheekPuff")


def arkit_from_ict_name(name: str) -> str | None:
    """The ARKit name of an ICT-FaceKit expression (``eyeBlink_L`` -> ``eyeBlinkLeft``,
    ``browInnerUp_R`` -> ``browInnerUp``, ``jawOpen`` -> ``jawOpen``); None for the ICT shapes
    ARKit lacks (:data:`ICT_UNUSED`). Same side: both ``_L`` and ``Left`` mean the subject's
    own left (+x)."""
    if name in ICT_UNUSED:
        return None
    base, side = name, ""
    if name.endswith("_L"):
        base, side = name[:-2], "Left"
    elif name.endswith("_R"):
        base, side = name[:-2], "Right"
    arkit = base if base in _MERGED else base + side
    if arkit not in ARKIT_NAMES:
        return None
    return arkit


#: ICT-FaceKit expression name -> ARKit name (the 53 ICT shapes ARKit has)
ICT_TO_ARKIT: dict[str, str] = {
    f"{b}{s}": a
    for b, s in (
        [
            (b, s)
            for b in ("browDown", "browInnerUp", "browOuterUp", "cheekPuff")
            for s in "_L _R".split()
        ]
        + [
            (b, s)
            for b in (
                "cheekSquint",
                "eyeBlink",
                "eyeLookDown",
                "eyeLookIn",
                "eyeLookOut",
                "eyeLookUp",
                "eyeSquint",
                "eyeWide",
                "mouthDimple",
                "mouthFrown",
                "mouthLowerDown",
                "mouthPress",
                "mouthSmile",
                "mouthStretch",
                "mouthUpperUp",
                "noseSneer",
            )
            for s in "_L _R".split()
        ]
        + [
            (b, "")
            for b in (
                "jawForward",
                "jawLeft",
                "jawOpen",
                "jawRight",
                "mouthClose",
                "mouthFunnel",
                "mouthLeft",
                "mouthPucker",
                "mouthRight",
                "mouthRollLower",
                "mouthRollUpper",
                "mouthShrugLower",
                "mouthShrugUpper",
            )
        ]
    )
    if (a := arkit_from_ict_name(f"{b}{s}")) is not None
}


def arkit_weights_from_ict(weights: dict) -> dict[str, float]:
    """ARKit coefficients (all 52 names) equivalent to ICT expression weights: same-named
    shapes copy their weight; a merged ARKit shape (``browInnerUp``, ``cheekPuff``) takes the
    mean of ICT's left and right weights (exact when they are equal, as in the shared
    recipes); unmapped ICT shapes are ignored."""
    out = dict.fromkeys(ARKIT_NAMES, 0.0)
    merged: dict[str, list[float]] = {}
    for k, v in weights.items():
        a = ICT_TO_ARKIT.get(str(k))
        if a is None:
            continue
        if a in _MERGED:
            merged.setdefault(a, []).append(float(v))
        else:
            out[a] = float(v)
    for a, vals in merged.items():
        out[a] = float(sum(vals) / 2.0)
    return out


def arkit_deltas_from_ict(names, deltas) -> tuple[np.ndarray, np.ndarray]:
    """The 52 ARKit displacement fields from ICT's expression shapes.

    Args:
        names: ``(E,)`` ICT expression names; deltas: ``(E, V, 3)`` mm.

    Returns:
        ``(deltas (52, V, 3) mm, available (52,) bool)``; unavailable shapes are zero.

    Raises:
        DataNotFoundError: an ARKit shape's ICT source (e.g. ``jawOpen``) is missing from
            ``names`` while others are present (not an ICT-FaceKit expression set).
    """
    d = np.asarray(deltas, np.float64)
    idx = {str(n): i for i, n in enumerate(names)}
    out = np.zeros((len(ARKIT_NAMES),) + d.shape[1:])
    avail = np.zeros(len(ARKIT_NAMES), bool)
    for ict, a in ICT_TO_ARKIT.items():
        if ict not in idx:
            raise DataNotFoundError(
                f"the ICT expression {ict!r} (ARKit {a!r}) is missing; expected the ICT-FaceKit "
                f"expression set (ict_face.npz 'expression_names'), got {sorted(idx)[:8]}..."
            )
        k = ARKIT_NAMES.index(a)
        out[k] += d[idx[ict]]
        avail[k] = True
    return out, avail
