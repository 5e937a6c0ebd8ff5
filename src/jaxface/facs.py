"""FACS action units <-> muscle activations, jaw pose and cheek puff; emotion presets.

:data:`AU_MUSCLES` gives, for each action unit at full intensity (1.0 = FACS level E), the
activation of the muscles of the default map (:mod:`jaxface.anatomy.muscle_map`, base names;
a bilateral muscle means both its ``_L`` and ``_R`` controls). ``AU12L`` / ``AU12R`` are the
unilateral variants (the subject's left is +x). Jaw AUs move the jaw (:data:`AU_JAW`), AU33/34
set the cheek puff: a separate pressure for a rig, or, where the control names include the
fit's two cheek pressures (:data:`jaxface.anatomy.cheek_puff.PUFF_CONTROLS`), those controls
(``AU34L`` / ``AU34R`` one cheek). Lip AUs 18, 22, 23 and 28 all act through the single orbicularis oris
sphincter of the map (with different intensities), so they are not separable from muscle
activations: the readout attributes that sphincter to AU23 (plus AU24 where the mentalis
joins it).

* :func:`aus_to_controls` turns ``{"AU12": 0.8, "AU26": 1}`` into an activation vector (ordered
  as ``rig.muscle_names``), a :class:`~jaxface.anatomy.jaw.JawPose` and a cheek puff;
* :data:`EMOTIONS` holds the Ekman/Friesen prototypes (happiness 6+12, sadness 1+4+15,
  surprise 1+2+5+26, fear 1+2+4+5+20+26, anger 4+5+7+23, disgust 9+15+16);
* :func:`au_intensities` is the inverse readout: non-negative least squares of the
  activations against the table (and the jaw pose against :data:`AU_JAW`), the function the
  fitter uses to report AUs.

Units: AU intensities and activations are dimensionless in [0, 1]; jaw in degrees and mm.
"""

from __future__ import annotations

import re

import numpy as np

from .anatomy.cheek_puff import PUFF_CONTROLS
from .anatomy.jaw import JawPose
from .errors import RigError

__all__ = [
    "AU_MUSCLES",
    "AU_JAW",
    "AU_NAMES",
    "EMOTIONS",
    "parse_aus",
    "expand_au",
    "au_matrix",
    "aus_to_controls",
    "emotion_controls",
    "au_intensities",
    "au_decomposition",
    "au_dict",
    "INTENSITY_LETTERS",
    "intensity_letter",
    "intensity_letters",
    "sided_aus",
    "sort_aus",
]

#: AU -> {muscle base name: activation at AU intensity 1}.
AU_MUSCLES: dict[str, dict[str, float]] = {
    "AU1": {"frontalis_medial": 1.0},
    "AU2": {"frontalis_lateral": 1.0},
    "AU4": {"corrugator": 1.0, "depressor_supercilii": 0.8, "procerus": 0.6},
    "AU5": {"levator_palpebrae": 1.0},
    "AU6": {"malaris": 0.6, "orbicularis_oculi": 0.2},
    "AU7": {"orbicularis_oculi": 0.4, "orbicularis_oculi_palpebral": 0.3},
    "AU9": {"levator_labii_superioris_alaeque_nasi": 1.0, "procerus": 0.4},
    "AU10": {"levator_labii_superioris": 1.0},
    "AU11": {"zygomaticus_minor": 1.0},
    "AU12": {"zygomaticus_major": 1.0},
    "AU13": {"levator_anguli_oris": 1.0},
    "AU14": {"buccinator": 1.0},
    "AU15": {"depressor_anguli_oris": 1.0},
    "AU16": {"depressor_labii_inferioris": 1.0},
    "AU17": {"mentalis": 1.0},
    "AU18": {"orbicularis_oris": 0.7},
    "AU20": {"risorius": 1.0, "platysma": 0.3},
    "AU21": {"platysma": 1.0},
    "AU22": {"orbicularis_oris": 0.5},
    "AU23": {"orbicularis_oris": 1.0},
    "AU24": {"orbicularis_oris": 0.7, "mentalis": 0.4},
    "AU25": {"depressor_labii_inferioris": 0.4},
    "AU27": {"depressor_labii_inferioris": 0.3},
    "AU28": {"orbicularis_oris": 0.9},
    "AU38": {"nasalis": 1.0},
    "AU39": {"nasalis": 0.6},
    "AU43": {"orbicularis_oculi_palpebral": 1.0},
    "AU45": {"orbicularis_oculi_palpebral": 1.0},
    "AU46": {"orbicularis_oculi_palpebral": 1.0},
}

#: Jaw AUs at intensity 1: pitch (deg, opening), yaw (deg, to the subject's left), protrusion (mm).
AU_JAW: dict[str, tuple[float, float, float]] = {
    "AU25": (2.0, 0.0, 0.0),
    "AU26": (10.0, 0.0, 0.0),
    "AU27": (18.0, 0.0, 0.0),
    "AU29": (0.0, 0.0, 5.0),
    "AU30": (0.0, 4.0, 0.0),
}

#: AUs of the cheek puff (air pressure; value = puff at intensity 1).
AU_PUFF = {"AU33": 1.0, "AU34": 1.0}

AU_NAMES: tuple[str, ...] = tuple(
    sorted(set(AU_MUSCLES) | set(AU_JAW) | set(AU_PUFF), key=lambda s: int(s[2:]))
)

#: Emotion prototypes (Ekman & Friesen): AU -> intensity.
EMOTIONS: dict[str, dict[str, float]] = {
    "happiness": {"AU6": 1.0, "AU12": 1.0},
    "sadness": {"AU1": 1.0, "AU4": 0.8, "AU15": 1.0},
    "surprise": {"AU1": 1.0, "AU2": 1.0, "AU5": 1.0, "AU26": 1.0},
    "fear": {"AU1": 1.0, "AU2": 0.8, "AU4": 0.7, "AU5": 1.0, "AU20": 1.0, "AU26": 0.7},
    "anger": {"AU4": 1.0, "AU5": 0.7, "AU7": 1.0, "AU23": 1.0},
    "disgust": {"AU9": 1.0, "AU15": 0.8, "AU16": 0.7},
}

_AU_RE = re.compile(r"^\s*AU\s*(\d+)\s*([LR])?\s*$", re.IGNORECASE)


def _canon(au: str) -> tuple[str, str | None]:
    m = _AU_RE.match(str(au))
    if not m:
        raise RigError(f"not an action unit: {au!r}; write e.g. 'AU12', 'AU12L' or 'AU12R'.")
    base = f"AU{int(m.group(1))}"
    side = m.group(2).upper() if m.group(2) else None
    if base not in AU_NAMES:
        raise RigError(f"action unit {base} is not modelled; known AUs: {', '.join(AU_NAMES)}.")
    return base, side


def parse_aus(specs) -> dict[str, float]:
    """Parse ``["AU12=0.8", "AU26"]`` (or one comma-separated string) into ``{AU: intensity}``.

    A missing value means 1. Raises :class:`RigError` on malformed items or values outside
    [0, 1].
    """
    if isinstance(specs, str):
        specs = [s for s in specs.split(",") if s.strip()]
    out: dict[str, float] = {}
    for item in specs:
        name, _, val = str(item).partition("=")
        base, side = _canon(name)
        try:
            v = float(val) if val.strip() else 1.0
        except ValueError:
            raise RigError(f"bad AU intensity in {item!r}; use a number in [0, 1].") from None
        if not 0.0 <= v <= 1.0:
            raise RigError(f"AU intensity in {item!r} must be in [0, 1].")
        out[base + (side or "")] = v
    return out


def expand_au(au: str, muscle_names) -> dict[str, float]:
    """Controls of one AU at intensity 1: ``{control name: activation}`` for the rig's
    ``muscle_names`` (bilateral muscles on both sides, or one side for ``AUxxL``/``AUxxR``;
    a mid-line muscle gets half the weight in a unilateral AU). AU33/34 give the cheek
    pressures where ``muscle_names`` include :data:`~jaxface.anatomy.cheek_puff.PUFF_CONTROLS`."""
    base, side = _canon(au)
    names = set(muscle_names)
    out: dict[str, float] = {}
    if base in AU_PUFF and set(PUFF_CONTROLS) <= names:
        # the fit's cheek-pressure controls (jaxface.anatomy.cheek_puff), one per cheek
        for n, s in zip(PUFF_CONTROLS, ("L", "R")):
            if side in (None, s):
                out[n] = AU_PUFF[base]
    for m, w in AU_MUSCLES.get(base, {}).items():
        if m in names:
            out[m] = out.get(m, 0.0) + (w if side is None else 0.5 * w)
        sides = ("L", "R") if side is None else (side,)
        for s in sides:
            n = f"{m}_{s}"
            if n in names:
                out[n] = out.get(n, 0.0) + w
    return out


def au_matrix(muscle_names, aus=None) -> tuple[list[str], np.ndarray]:
    """The AU table as a matrix for the rig's controls.

    Args:
        muscle_names: the rig's control names (``rig.muscle_names``).
        aus: AU names (default: every muscle AU, bilateral AUs split into their ``L``/``R``
            variants).

    Returns:
        ``(aus, A)`` with ``A`` ``(len(aus), M)``: row ``i`` = activations of AU ``i`` at 1.
    """
    names = list(muscle_names)
    if aus is None:
        aus = []
        for base in (*AU_MUSCLES, "AU34"):  # AU34: the cheeks' pressures, where controls
            row = expand_au(base, names)
            if not row:
                continue
            left = expand_au(base + "L", names)
            bilateral = any(n.endswith(("_L", "_R")) for n in row)
            aus += [base + "L", base + "R"] if bilateral and left != row else [base]
    A = np.zeros((len(aus), len(names)))
    for i, au in enumerate(aus):
        for n, w in expand_au(au, names).items():
            A[i, names.index(n)] += w
    return list(aus), A


def aus_to_controls(aus: dict, muscle_names):
    """Activations, jaw pose and cheek puff of a set of AUs.

    Args:
        aus: ``{AU: intensity}`` (e.g. from :func:`parse_aus`), intensities in [0, 1].
        muscle_names: the rig's control names.

    Returns:
        ``(activations (M,) in [0, 1], JawPose, cheek_puff)``; contributions add up and are
        clipped to [0, 1] (jaw: to its limits by the jaw model). ``cheek_puff`` is a number
        in [0, 1] for both cheeks, or ``[left, right]`` (NumPy ``(2,)``) when a one-sided
        ``AU34L`` / ``AU34R`` makes the cheeks differ; the rig's ``synthesize`` takes both.
        Where ``muscle_names`` include the cheek pressures
        (:data:`~jaxface.anatomy.cheek_puff.PUFF_CONTROLS`) the puff is in the activations
        and ``cheek_puff`` is 0.
    """
    names = list(muscle_names)
    a = np.zeros(len(names))
    jaw = np.zeros(3)
    puff = np.zeros(2)  # left, right
    puff_in_a = set(PUFF_CONTROLS) <= set(names)  # then expand_au puts the puff in ``a``
    for au, v in aus.items():
        base, side = _canon(au)
        v = float(v)
        for n, w in expand_au(au, names).items():
            a[names.index(n)] += v * w
        if base in AU_JAW:
            j = np.array(AU_JAW[base], float)
            if base == "AU30" and side == "R":
                j[1] = -j[1]
            jaw += v * j
        if not puff_in_a:
            puff += v * AU_PUFF.get(base, 0.0) * np.array([side != "R", side != "L"], float)
    puff = np.clip(puff, 0.0, 1.0)
    return (
        np.clip(a, 0.0, 1.0),
        JawPose(float(jaw[0]), float(jaw[1]), float(jaw[2])),
        float(puff[0]) if puff[0] == puff[1] else puff,
    )


def emotion_controls(name: str, muscle_names, intensity: float = 1.0):
    """:func:`aus_to_controls` of an :data:`EMOTIONS` preset scaled by ``intensity``."""
    key = name.lower()
    if key not in EMOTIONS:
        raise RigError(f"unknown emotion {name!r}; presets: {sorted(EMOTIONS)}.")
    return aus_to_controls({k: v * intensity for k, v in EMOTIONS[key].items()}, muscle_names)


def sort_aus(values: dict) -> dict:
    """``{AU: value}`` ordered by AU number, a side after its bilateral AU (AU12, AU12L, AU12R)."""

    def key(k):
        m = _AU_RE.match(k)
        assert m is not None, k  # the keys are AU names
        return (int(m.group(1)), m.group(2) or "")

    return dict(sorted(values.items(), key=lambda kv: key(kv[0])))


def au_decomposition(activations, muscle_names) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The muscle part of :func:`au_intensities`: activations as a non-negative combination of
    the AU table's rows.

    Solves ``min_i |A^T i - a|``, ``i >= 0`` (non-negative least squares) over the unilateral
    AU variants of :func:`au_matrix`, leaving out AUs whose rows duplicate an earlier AU's
    (see the module doc) and AUs with no muscle on this rig; ``i`` is clipped to [0, 1].

    Args:
        activations: ``(M,)`` in [0, 1], ordered as ``muscle_names``.
        muscle_names: the rig's control names.

    Returns:
        ``(aus, intensities (K,), rows (K, M))``: AU ``k``'s share of the activations is
        ``intensities[k] * rows[k]``.

    Raises:
        RigError: ``activations`` and ``muscle_names`` differ in length.
    """
    from scipy.optimize import nnls

    a = np.asarray(activations, dtype=np.float64).ravel()
    names = list(muscle_names)
    if a.shape[0] != len(names):
        raise RigError(f"activations have {a.shape[0]} entries, muscle_names {len(names)}.")
    aus, A = au_matrix(names)
    keep, seen = [], []
    for i, row in enumerate(A):
        if any(np.allclose(row, r) for r in seen) or not row.any():
            continue
        seen.append(row)
        keep.append(i)
    aus = [aus[i] for i in keep]
    A = A[keep]
    x, _ = nnls(A.T, a)
    return aus, np.clip(x, 0.0, 1.0), A


def au_intensities(
    activations, muscle_names, jaw=None, *, cheek_puff: float = 0.0
) -> dict[str, float]:
    """Read AU intensities out of muscle activations (and a jaw pose): the inverse of the table.

    Muscle AUs: non-negative least squares ``min_i |A^T i - a|``, ``i >= 0`` over the
    unilateral AU variants (:func:`au_matrix`; AUs whose rows duplicate an earlier AU's are
    left out, see the module doc), then clipped to [0, 1]; a bilateral AU is reported as the
    mean of its sides, and its sides as ``AUxxL`` / ``AUxxR``. Jaw AUs: an opening ``p`` up
    to 10 degrees is AU26 ``p / 10``; beyond, AU27 ``t = (p - 10) / 8`` (1 at 18 degrees) and
    AU26 ``1 - t`` (the two are alternative codes of one opening, and the table's pitch of the
    pair is ``p``), protrusion gives AU29, yaw AU30
    (``AU30L``/``AU30R`` by direction).

    Args:
        activations: ``(M,)`` in [0, 1], ordered as ``muscle_names``.
        muscle_names: the rig's control names.
        jaw: optional :class:`~jaxface.anatomy.jaw.JawPose` (scalars).
        cheek_puff: the puff (reported as AU34), a number or ``[left, right]`` (then also
            ``AU34L`` / ``AU34R``).

    Returns:
        ``{AU: intensity}`` sorted by AU number, plus the L/R variants.
    """
    aus, x, _ = au_decomposition(activations, muscle_names)
    return au_dict(aus, x, jaw, cheek_puff)


def au_dict(aus, values, jaw=None, cheek_puff: float = 0.0) -> dict[str, float]:
    """``{AU: intensity}`` from unilateral-variant intensities ``values`` (``aus`` as
    :func:`au_decomposition` returns them; a bilateral AU is the mean of its sides) and the
    jaw AUs of ``jaw`` (:func:`au_intensities`' rules); sorted by AU number. Shared by
    :func:`au_intensities` and :func:`jaxface.fit.au_motion.au_sparse`."""
    out: dict[str, float] = {}
    for au, v in zip(aus, values):
        out[au] = float(v)
        if au.endswith(("L", "R")):
            base = au[:-1]
            out[base] = out.get(base, 0.0) + 0.5 * float(v)
    if jaw is not None:
        p = float(np.asarray(jaw.pitch_deg))
        y = float(np.asarray(jaw.yaw_deg))
        q = float(np.asarray(jaw.protrusion_mm))
        # AU26 (jaw drop) and AU27 (mouth stretch) are alternative codes of one opening: up
        # to AU26's pitch it is AU26; beyond, AU27 takes over as AU26 gives way, so that the
        # table's pitch of the pair, 10 * AU26 + 18 * AU27 degrees, is the opening read
        p26, p27 = AU_JAW["AU26"][0], AU_JAW["AU27"][0]
        t = float(np.clip((p - p26) / (p27 - p26), 0.0, 1.0))
        out["AU26"] = float(np.clip(p / p26, 0.0, 1.0)) - t
        out["AU27"] = t
        out["AU29"] = float(np.clip(q / AU_JAW["AU29"][2], 0.0, 1.0))
        out["AU30L"] = float(np.clip(y / AU_JAW["AU30"][1], 0.0, 1.0))
        out["AU30R"] = float(np.clip(-y / AU_JAW["AU30"][1], 0.0, 1.0))
        out["AU30"] = max(out["AU30L"], out["AU30R"])
    p = np.clip(np.asarray(cheek_puff, np.float64), 0.0, 1.0)
    if p.shape == (2,):  # [left, right]
        out["AU34L"], out["AU34R"] = float(p[0]), float(p[1])
        out["AU34"] = float(p.mean())
    elif p.ndim == 0 and p > 0:
        out["AU34"] = float(p)
    return sort_aus(out)


#: FACS intensity letters (Ekman, Friesen & Hager 2002: A trace, B slight, C marked or
#: pronounced, D severe or extreme, E maximum) as lower bounds on the intensity in [0, 1].
#: The manual's scale is not even: A and E are narrow and C and D cover most of the range, so
#: the bins are unequal too; below A's bound the AU is not scored.
INTENSITY_LETTERS = (("A", 0.10), ("B", 0.25), ("C", 0.45), ("D", 0.70), ("E", 0.90))


def intensity_letter(x: float) -> str | None:
    """The FACS letter ``"A"``..``"E"`` of an intensity in [0, 1] (:data:`INTENSITY_LETTERS`),
    or None below A (not scored).

    Raises:
        ValueError: ``x`` is not finite.
    """
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"an AU intensity must be finite, got {x}.")
    letter = None
    for name, lo in INTENSITY_LETTERS:
        if x >= lo:
            letter = name
    return letter


def intensity_letters(intensities: dict) -> dict[str, str]:
    """``{AU: letter}`` for the AUs of ``{AU: intensity}`` scored A or above (in the same
    order)."""
    out = {}
    for k, v in intensities.items():
        letter = intensity_letter(v)
        if letter is not None:
            out[k] = letter
    return out


def sided_aus(
    values: dict, n: int | None = None, *, asymmetry: float = 0.1, floor: float = 0.005
) -> list[tuple[str, float]]:
    """The AUs of ``{AU: value}`` as FACS codes them, strongest first: an AU whose sides differ
    by at most ``asymmetry`` (in the values' unit: intensity, or mm of motion) appears once,
    bilateral (``"AU12"``, its bilateral value); a one-sided or uneven AU appears per side
    (``"AU12L"``, ``"AU12R"``, each side at or above ``floor``). AUs without sides (the jaw's
    AU26, AU27) appear as they are. Values below ``floor`` are left out.

    Args:
        values: ``{AU: value}`` with bilateral keys and, where the AU has sides, ``"...L"`` /
            ``"...R"`` keys (:attr:`jaxface.fit.ExpressionFit.au_intensities`).
        n: at most this many (None: all).
        asymmetry: largest ``|L - R|`` still coded bilateral, >= 0.
        floor: smallest value listed, >= 0.

    Raises:
        ValueError: a negative ``asymmetry`` or ``floor``, or a non-finite value.
    """
    if not (asymmetry >= 0.0 and floor >= 0.0):
        raise ValueError(f"asymmetry and floor must be >= 0, got {asymmetry} and {floor}.")
    vals = {k: float(v) for k, v in values.items()}
    bad = [k for k, v in vals.items() if not np.isfinite(v)]
    if bad:
        raise ValueError(f"AU values must be finite: {bad}.")
    out = []
    for k, v in vals.items():
        m = _AU_RE.match(k)
        au, side = (f"AU{int(m.group(1))}", m.group(2)) if m else (k, None)
        if side is not None:
            if au not in vals:  # a side without its bilateral key stands alone
                out.append((k, v))
            continue
        left, right = vals.get(au + "L"), vals.get(au + "R")
        if left is None or right is None or abs(left - right) <= asymmetry:
            out.append((k, v))
        else:
            out += [(au + "L", left), (au + "R", right)]
    out = [(k, v) for k, v in out if v >= floor]
    out.sort(key=lambda kv: -kv[1])
    return out if n is None else out[: max(int(n), 0)]
