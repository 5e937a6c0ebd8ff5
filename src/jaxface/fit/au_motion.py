"""AU motion readout: how much of a fitted expression's skin motion each action unit accounts
for, in mm.

:func:`jaxface.facs.au_intensities` reads AU intensities out of the fitted activations: how hard
the muscles of each AU work, in [0, 1]. That is not how strongly an AU shows. A small muscle
(mentalis, depressor labii inferioris, buccinator) reaches activation 1 while it moves the skin
a millimetre, and a large one (zygomaticus major) at 0.6 moves the mouth corner 10 mm. On the
Bosphorus-style smiles the fit saturates several small muscles at 1 while most of the motion is
the zygomaticus major's, so AU12 ranks 6th-8th by intensity. FACS coders score intensity by the
visible change, and this readout follows them:

* the activations are split into AU shares by :func:`jaxface.facs.au_decomposition` (the same
  non-negative least squares the intensities come from): AU ``k``'s share is
  ``intensity_k * row_k``;
* the jaw pose is split like the intensities: the opening up to AU26's 10 degrees is AU26, the
  rest AU27; positive protrusion is AU29; yaw is AU30L (toward the subject's left, +) or
  AU30R;
* each share is applied *alone* to the subject's reduced model
  (:class:`jaxface.fit.solve.ResponseModel`, the model the fit solves with) and the RMS skin
  displacement over its points (the face region, mm) is that AU's motion. A bilateral AU
  (``AU12``) is both sides' shares together, its sides (``AU12L``, ``AU12R``) each alone.

The numbers do not add up to the whole motion (the reduced model is additive in the muscles
and the jaw, but the RMS of a sum is not the sum of the RMSs): they rank the AUs by their
visible effect; they are not a decomposition of the motion's variance.
"""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..facs import AU_JAW, au_decomposition, sort_aus

__all__ = ["au_motion"]


@eqx.filter_jit
def _rms_motion(model, rows, muscles, values, J, n_rows: int):
    """RMS displacement (mm) of ``n_rows`` shares of the activations, then of ``Q`` jaw poses.

    The reduced model is additive in the muscles, so a share's displacement is the sum of its
    muscles' own terms (:meth:`~jaxface.fit.solve.ResponseModel.muscle_terms`): the triples
    ``(rows, muscles, values)`` ``(T,)`` list the activations of every share (the table's
    non-zero pattern, so ``T`` is fixed per rig and this compiles once per subject).
    ``J`` ``(Q, 3)``: jaw poses, muscles at rest. Returns ``(n_rows + Q,)``."""
    D = jax.ops.segment_sum(model.muscle_terms(muscles, values), rows, num_segments=n_rows)
    z = jnp.zeros(model.mus.shape[0], J.dtype)
    base = model.displacement(z, jnp.zeros(3, J.dtype))
    DJ = jax.vmap(lambda j: model.displacement(z, j))(J) - base[None]
    D = jnp.concatenate([D, DJ])
    return jnp.sqrt(jnp.mean(jnp.sum(D * D, axis=-1), axis=-1))


def au_motion(response, activations, jaw, muscle_names: Sequence[str]) -> dict[str, float]:
    """RMS skin motion (mm) each action unit accounts for in a fitted expression.

    Args:
        response: the subject's :class:`~jaxface.fit.solve.ResponseModel` (mm).
        activations: ``(M,)`` fitted activations in [0, 1], ordered as ``muscle_names``.
        jaw: ``(3,)`` effective jaw pose ``[pitch_deg, yaw_deg, protrusion_mm]`` (after the
            rig's limits, e.g. ``PointFit.jaw_effective``).
        muscle_names: the rig's control names.

    Returns:
        ``{AU: mm}`` for every AU of the table present on the rig (bilateral AUs and their
        ``L``/``R`` sides) and the jaw AUs 26, 27, 29, 30 (``AU30L``/``AU30R``), sorted by AU
        number.

    Raises:
        RigError: ``activations`` and ``muscle_names`` differ in length.
    """
    aus, inten, rows = au_decomposition(activations, muscle_names)
    M = rows.shape[1]
    own = inten[:, None] * rows                       # (K, M) each AU variant's share
    sided = [au for au in aus if au[-1] in "LR"]
    bases = list(dict.fromkeys(au[:-1] for au in sided))
    labels = list(aus) + bases                        # bilateral AUs: both sides together
    shares = list(own) + [sum(own[aus.index(au)] for au in sided if au[:-1] == b) for b in bases]
    je = np.asarray(jaw, np.float64).ravel()
    p, y, q = max(float(je[0]), 0.0), float(je[1]), max(float(je[2]), 0.0)
    p26 = AU_JAW["AU26"][0]
    jaw_rows = [("AU26", (min(p, p26), 0.0, 0.0)), ("AU29", (0.0, 0.0, q)),
                ("AU30L", (0.0, max(y, 0.0), 0.0)), ("AU30R", (0.0, min(y, 0.0), 0.0)),
                ("_open", (p, 0.0, 0.0))]
    dt = response.rest.dtype
    S = np.asarray(shares).reshape(-1, M)
    # every share's activations lie on its table rows' non-zero pattern (fixed per rig)
    pattern = np.vstack([rows] + [sum(rows[aus.index(au)] for au in sided if au[:-1] == b) for b in bases])
    r, m = np.nonzero(pattern)
    J = np.asarray([j for _, j in jaw_rows], np.float64)
    rms = np.asarray(_rms_motion(response, jnp.asarray(r), jnp.asarray(m), jnp.asarray(S[r, m], dt),
                                 jnp.asarray(J, dt), len(S)), np.float64)
    out = {lab: float(v) for lab, v in zip(labels, rms[: len(labels)])}
    jaw_rms = {lab: float(v) for (lab, _), v in zip(jaw_rows, rms[len(labels):])}
    out["AU26"] = jaw_rms["AU26"]
    # the opening beyond AU26's range: the extra motion of the whole opening over AU26's part
    out["AU27"] = max(jaw_rms["_open"] - jaw_rms["AU26"], 0.0) if p > p26 else 0.0
    out["AU29"] = jaw_rms["AU29"]
    out["AU30L"], out["AU30R"] = jaw_rms["AU30L"], jaw_rms["AU30R"]
    out["AU30"] = max(out["AU30L"], out["AU30R"])
    return sort_aus(out)
