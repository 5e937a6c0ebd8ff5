"""The AU readout checks of issue 44, shared by ``bench_ict57.py`` and ``bench_fit.py``.

On one fit, for an AU readout (``{AU: intensity}`` with bilateral names, sides ``AUxxL`` /
``AUxxR``):

* ``coded_rank_ok``: every coded AU group has a member among the top (number of groups + 1)
  bilateral AUs (None when nothing is coded);
* ``n_saturated``: bilateral AUs at >= 0.99;
* ``idle_strong``: muscle AUs at >= 0.5 whose removal from the readout's AU combination moves
  the skin by less than 0.05 mm (RMS over the subject's reduced-model points, the dense model,
  the rest of the combination unchanged), with that motion in mm. The jaw AUs (26, 27, 29, 30)
  are read from the jaw pose, not selected, and are not counted.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxface.facs import au_decomposition

STRONG = 0.5  # an AU at or above this intensity must be needed by the motion
IDLE_MM = 0.05  # ... i.e. its removal must move the skin by at least this (mm, RMS)
JAW_AUS = ("AU25", "AU26", "AU27", "AU29", "AU30", "AU33", "AU34")


def coded_rank_ok(values: dict, groups) -> bool | None:
    bil = {a: float(x) for a, x in values.items() if a[-1] not in "LR"}
    order = [a for a, x in sorted(bil.items(), key=lambda kv: -kv[1]) if x > 0.0]
    top = set(order[: len(groups) + 1])
    return all(any(a in top for a in g) for g in groups) if groups else None


def idle_strong_aus(response, values: dict, muscle_names) -> dict[str, float]:
    """``{AU: mm}`` of the muscle AUs at >= STRONG whose removal moves the skin < IDLE_MM."""
    names = list(muscle_names)
    aus, _, rows = au_decomposition(np.zeros(len(names)), names)
    i = np.array([float(values.get(a, 0.0)) for a in aus])
    zero = jnp.zeros(3, response.rest.dtype)

    def disp(x):
        act = jnp.asarray(np.clip(x @ rows, 0.0, 1.0), response.rest.dtype)
        return np.asarray(response.displacement(act, zero), np.float64)

    full = disp(i)
    out = {}
    for au, v in values.items():
        if au[-1] in "LR" or au in JAW_AUS or float(v) < STRONG:
            continue
        parts = [k for k, a in enumerate(aus) if a == au or (a[-1] in "LR" and a[:-1] == au)]
        if not parts:
            continue
        x = i.copy()
        x[parts] = 0.0
        d = full - disp(x)
        mm = float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
        if mm < IDLE_MM:
            out[au] = mm
    return out


def au_check(values: dict, groups, response, muscle_names) -> dict:
    """The three checks on one readout (see the module doc)."""
    bil = {a: float(x) for a, x in values.items() if a[-1] not in "LR"}
    return {
        "coded_rank_ok": coded_rank_ok(values, groups),
        "n_saturated": int(sum(x >= 0.99 for x in bil.values())),
        "idle_strong": idle_strong_aus(response, values, muscle_names),
    }


def summarise(checks: list[dict], single: list[bool]) -> dict:
    """Counts over many fits: coded within the top / coded; single-AU fits with more than 2
    saturated; fits with an idle strong AU."""
    return {
        "n_coded": sum(c["coded_rank_ok"] is not None for c in checks),
        "n_coded_rank_ok": sum(bool(c["coded_rank_ok"]) for c in checks),
        "n_single": sum(single),
        "n_single_over_2_saturated": sum(c["n_saturated"] > 2 for c, s in zip(checks, single) if s),
        "n_with_idle_strong": sum(bool(c["idle_strong"]) for c in checks),
        "n_idle_strong": sum(len(c["idle_strong"]) for c in checks),
    }
