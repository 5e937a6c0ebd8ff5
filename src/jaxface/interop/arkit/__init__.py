"""ARKit-52 blendshape coefficients: names, the ICT-FaceKit mapping, the basis transferred onto
a subject, and the bounded sparse least-squares readout.

Units mm; frame +y up, the face looks along +z, the subject's left is +x.

**Sides.** ARKit's ``...Left`` shapes act on the *subject's own* left (Apple's face anchor has
+x toward the face's own left, i.e. the viewer's right). ICT-FaceKit's ``_L`` shapes act on
the subject's left too (in ``ict_face.npz`` ``mouthSmile_L`` moves vertices at +x), and the
project's subject's left is +x. So ``eyeBlink_L`` -> ``eyeBlinkLeft`` with no mirroring
(checked against the one-sided shared scan LFAU_12L: ``mouthSmile_L`` only).

**Mapping** (:data:`ICT_TO_ARKIT`): ``<shape>_L``/``_R`` -> ``<shape>Left``/``Right``;
ARKit's single ``browInnerUp`` and ``cheekPuff`` are the sums of ICT's left and right shapes;
ICT's ``PupilDilate_L/R`` and ``cheekRaiser_L/R`` have no ARKit name and are not used; ARKit's
``tongueOut`` has no ICT shape (:data:`ARKIT_MISSING_IN_ICT`): it is reported as 0 and marked
unavailable.

**Basis** (:func:`transfer_ict_basis`): the 51 ICT-backed ARKit displacement fields
(``(51, 9409, 3)`` mm on the ICT face region) are carried onto the subject's skin with the
project's facial motion cloning (:func:`jaxface.clone.clone_motion`, landmarks + contours +
``max_iterations`` refinement steps), restricted to the subject's face region.

**Readout** (:func:`solve_arkit`, :func:`fit_arkit_to_scan`): bounded, L1-weighted least
squares, ``min_c sum_i w_i |B_i c - d_i|^2 / sum_i w_i + l1 * sum_k s_k c_k`` with
``0 <= c_k <= 1`` and ``s_k`` shape ``k``'s RMS motion (the lasso on unit-RMS shapes),
solved exactly as a box-constrained QP (:func:`box_qp`, through
``scipy.optimize.lsq_linear`` on the Cholesky factor of the normal matrix), re-weighted with
the fit's robust weights (Tukey's biweight at ``max(4.685 * 1.4826 * MAD, floor)``).

Layout: :mod:`.names` (names, ICT mapping), :mod:`.ict` (the ICT data), :mod:`.basis` (the basis
on a subject), :mod:`.readout` (the least-squares readout), :mod:`.fit_readout` (the readout
of a fit).
"""

from __future__ import annotations

from .basis import ArkitBasis, ict_transfer_error, transfer_ict_basis
from .fit_readout import ArkitReadout, readout_for_subject
from .ict import MULTIPIE68_TO_BOSPHORUS, default_ict_path, ict_bosphorus_landmarks
from .names import (
    ARKIT_MISSING_IN_ICT,
    ARKIT_NAMES,
    ICT_TO_ARKIT,
    ICT_UNUSED,
    arkit_deltas_from_ict,
    arkit_from_ict_name,
    arkit_weights_from_ict,
)
from .readout import (
    ArkitSolution,
    EyeRims,
    box_qp,
    eye_rim_motion,
    fit_arkit_to_scan,
    landmark_motion,
    solve_arkit,
    tukey_weights,
)

__all__ = [
    "ARKIT_NAMES",
    "ICT_TO_ARKIT",
    "ICT_UNUSED",
    "ARKIT_MISSING_IN_ICT",
    "MULTIPIE68_TO_BOSPHORUS",
    "arkit_from_ict_name",
    "arkit_weights_from_ict",
    "arkit_deltas_from_ict",
    "default_ict_path",
    "ict_bosphorus_landmarks",
    "ArkitBasis",
    "ArkitSolution",
    "ict_transfer_error",
    "transfer_ict_basis",
    "box_qp",
    "tukey_weights",
    "solve_arkit",
    "fit_arkit_to_scan",
    "EyeRims",
    "eye_rim_motion",
    "landmark_motion",
    "ArkitReadout",
    "readout_for_subject",
]
