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
squares, ``min_c sum_i w_i |B_i c - d_i|^2 / sum_i w_i + l1 * sum_k c_k`` with
``0 <= c_k <= 1``, solved exactly as a box-constrained QP (:func:`box_qp`, through
``scipy.optimize.lsq_linear`` on the Cholesky factor of the normal matrix), re-weighted with
the fit's robust weights (Tukey's biweight at ``max(4.685 * 1.4826 * MAD, floor)``).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import lsq_linear

from ..errors import DataNotFoundError, FitError, LandmarkError

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
    "transfer_ict_basis",
    "box_qp",
    "tukey_weights",
    "solve_arkit",
    "fit_arkit_to_scan",
    "landmark_motion",
    "ArkitReadout",
    "readout_for_subject",
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


# ------------------------------------------------------------------------------------------
# the ICT data at run time
# ------------------------------------------------------------------------------------------
#: Multi-PIE 68-point index (0-based, ICT ``vertex_indices.json`` ``idx_to_landmark_verts``)
#: -> Bosphorus label. Multi-PIE numbers the subject's right side first (17-21 the right brow,
#: 36-39 the right eye), so 26 is the outer *left* eyebrow (+x).
MULTIPIE68_TO_BOSPHORUS: dict[int, str] = {
    17: "Outer right eyebrow",
    19: "Middle right eyebrow",
    21: "Inner right eyebrow",
    22: "Inner left eyebrow",
    24: "Middle left eyebrow",
    26: "Outer left eyebrow",
    36: "Outer right eye corner",
    39: "Inner right eye corner",
    42: "Inner left eye corner",
    45: "Outer left eye corner",
    30: "Nose tip",
    48: "Right mouth corner",
    54: "Left mouth corner",
    51: "Upper lip outer middle",
    62: "Upper lip inner middle",
    66: "Lower lip inner middle",
    57: "Lower lip outer middle",
    8: "Chin middle",
}


def default_ict_path(*, shared_fallback: bool = True) -> Path | None:
    """Where the ICT-FaceKit file is found at run time: ``$JAXFACE_ICT`` (the ``.npz``), else
    (with ``shared_fallback``) ``$JAXFACE_SHARED/data/ict/ict_face.npz`` (default
    ``../shared``); None when neither exists (jaxface ships no ICT data).

    The fit's readout (:func:`readout_for_subject` with ``"auto"``) looks at ``$JAXFACE_ICT``
    only: cloning the 51 shapes costs tens of seconds per subject, which a fit pays only when
    the user asked for it by naming the file."""
    env = os.environ.get("JAXFACE_ICT", "").strip()
    if env:
        p = Path(env).expanduser()
        return p if p.is_file() else None
    if not shared_fallback:
        return None
    root = Path(os.environ.get("JAXFACE_SHARED", "../shared")).expanduser()
    p = root / "data" / "ict" / "ict_face.npz"
    return p.resolve() if p.is_file() else None


def ict_bosphorus_landmarks(npz_path, landmark_ids=None):
    """Bosphorus-labelled landmarks on the ICT neutral (mm) for the motion cloning.

    Args:
        npz_path: ``ict_face.npz``.
        landmark_ids: ``{label: ICT vertex id}``; default: the Multi-PIE 68 ids of
            ``vertex_indices.json`` beside the ``.npz`` (ICT-FaceKit's own file), mapped by
            :data:`MULTIPIE68_TO_BOSPHORUS` (18 labels).

    Raises:
        DataNotFoundError / LandmarkError: neither ids nor ``vertex_indices.json``.
    """
    from ..landmarks import Landmarks

    p = Path(npz_path)
    X = np.asarray(np.load(p)["neutral"], np.float64)
    if landmark_ids is None:
        vi = p.with_name("vertex_indices.json")
        if not vi.is_file():
            raise DataNotFoundError(
                f"no landmark ids for the ICT face: {vi} is missing. Put ICT-FaceKit's "
                "vertex_indices.json beside the .npz or pass landmark_ids={label: vertex id}."
            )
        mp = json.loads(vi.read_text()).get("idx_to_landmark_verts")
        if not isinstance(mp, list) or len(mp) != 68:
            raise LandmarkError(f"{vi}: 'idx_to_landmark_verts' is not the 68 Multi-PIE ids.")
        landmark_ids = {lab: int(mp[i]) for i, lab in MULTIPIE68_TO_BOSPHORUS.items()}
    names = list(landmark_ids)
    return Landmarks(names, X[[int(landmark_ids[n]) for n in names]])


# ------------------------------------------------------------------------------------------
# the basis on a subject
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArkitBasis:
    """The ARKit shapes on one skin topology.

    Attributes:
        deltas: ``(52, V, 3)`` displacement of each ARKit shape at coefficient 1, mm (zero
            outside ``mask`` and for unavailable shapes).
        available: ``(52,)`` bool: the shape has a source (False: ``tongueOut``).
        mask: ``(V,)`` bool vertices the readout uses (the face region).
        source: where the shapes came from (the ICT file; or a description).
        info: clone statistics (iterations, seconds, ...).
    """

    deltas: np.ndarray
    available: np.ndarray
    mask: np.ndarray
    source: str
    info: dict = field(default_factory=dict)

    names = ARKIT_NAMES

    def motion(self, coefficients) -> np.ndarray:
        """``(V, 3)`` mm displacement of a coefficient vector ``(52,)`` or dict."""
        c = _as_vector(coefficients)
        return np.einsum("k,kvd->vd", c, self.deltas)


def _as_vector(c) -> np.ndarray:
    if isinstance(c, dict):
        unknown = sorted(set(c) - set(ARKIT_NAMES))
        if unknown:
            raise FitError(f"unknown ARKit names {unknown}; the names are {list(ARKIT_NAMES)}.")
        return np.array([float(c.get(n, 0.0)) for n in ARKIT_NAMES])
    v = np.asarray(c, np.float64).reshape(-1)
    if v.shape != (len(ARKIT_NAMES),):
        raise FitError(f"expected {len(ARKIT_NAMES)} ARKit coefficients, got {v.shape}.")
    return v


def transfer_ict_basis(
    target_vertices,
    target_triangles,
    target_landmarks,
    target_mask=None,
    *,
    ict_path=None,
    ict_landmark_ids=None,
    max_iterations: int = 3,
    transfer: str = "affine",
) -> ArkitBasis:
    """Clone the ICT ARKit shapes onto a subject's skin (:func:`jaxface.clone.clone_motion`).

    Args:
        target_vertices: ``(V, 3)`` the subject's neutral skin, mm; target_triangles:
            ``(F, 3)``.
        target_landmarks: its Bosphorus landmarks (Landmarks or dict, mm).
        target_mask: ``(V,)`` bool face region (the clone target and the readout's vertices;
            default all).
        ict_path: ``ict_face.npz`` (default :func:`default_ict_path`).
        ict_landmark_ids: see :func:`ict_bosphorus_landmarks`.
        max_iterations: refinement iterations of the cloning (each adds 125 pairs); the
            landmarks and the eye/mouth contours already place the ICT face on the subject.

    Raises:
        DataNotFoundError: no ICT file.
    """
    from ..anatomy.ict import FACE_VERTEX_COUNT, load_ict_face
    from ..clone import clone_motion
    from ..mesh import TriMesh

    p = Path(ict_path) if ict_path is not None else default_ict_path()
    if p is None or not p.is_file():
        raise DataNotFoundError(
            f"the ICT-FaceKit file is needed for the ARKit shapes and was not found "
            f"({p if p is not None else 'set JAXFACE_ICT to ict_face.npz, or JAXFACE_SHARED'})."
        )
    t0 = time.perf_counter()
    ict = load_ict_face(p)
    slm = ict_bosphorus_landmarks(p, ict_landmark_ids)
    deltas, avail = arkit_deltas_from_ict(
        ict.expression_names, ict.expression_deltas[:, :FACE_VERTEX_COUNT]
    )
    V = np.asarray(target_vertices, np.float64)
    T = np.asarray(target_triangles, np.int64)
    mask = np.ones(len(V), bool) if target_mask is None else np.asarray(target_mask, bool)
    if mask.shape != (len(V),):
        raise FitError(f"target_mask must be ({len(V)},) bool, got {mask.shape}.")
    tri_mask = mask[T].all(axis=1)
    sub, old = TriMesh(V, T, validate=False).submesh(tri_mask)
    ids = np.flatnonzero(avail)
    res = clone_motion(
        ict.skin,
        sub,
        slm,
        target_landmarks,
        source_deltas=deltas[ids],
        max_iterations=max_iterations,
        transfer=transfer,
    )
    full = np.zeros((len(ARKIT_NAMES), len(V), 3))
    full[np.ix_(ids, old)] = res.deltas
    m = np.zeros(len(V), bool)
    m[old] = True
    if not np.all(np.isfinite(full)):
        raise FitError("the cloned ARKit shapes hold NaN/inf; check the subject's landmarks.")
    info = {
        "method": "jaxface.clone.clone_motion of the ICT-FaceKit shapes (landmarks, contours, "
        f"{max_iterations} refinement iterations)",
        "landmarks": list(res.fit.landmark_names),
        "contours": list(res.fit.contours_used),
        "iterations": int(res.fit.iterations),
        "seconds": time.perf_counter() - t0,
    }
    return ArkitBasis(full, avail, m, str(p), info)


# ------------------------------------------------------------------------------------------
# the readout
# ------------------------------------------------------------------------------------------
def box_qp(G, g, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """``argmin_c 0.5 c^T G c - g^T c`` over ``lo <= c <= hi`` (exact, bounded-variable least
    squares on ``R`` with ``R^T R = G + eps I``, ``eps = 1e-10 * trace(G) / n``).

    Args:
        G: ``(n, n)`` symmetric positive semi-definite; g: ``(n,)``.
    """
    G = np.asarray(G, np.float64)
    g = np.asarray(g, np.float64)
    n = len(g)
    eps = 1e-10 * max(float(np.trace(G)) / max(n, 1), 1e-300)
    R = np.linalg.cholesky(G + eps * np.eye(n)).T  # upper: R^T R = G
    b = np.linalg.solve(R.T, g)
    res = lsq_linear(R, b, bounds=(lo, hi), method="bvls", tol=1e-12)
    return np.clip(np.asarray(res.x, np.float64), lo, hi)


def tukey_weights(r, floor: float) -> np.ndarray:
    """Tukey biweight of residual magnitudes ``r`` (mm) at ``max(4.685 * 1.4826 * MAD,
    floor)`` (the fit's robust weights, :mod:`jaxface.fit.solve`); all ones if every weight
    would vanish."""
    r = np.abs(np.asarray(r, np.float64))
    mad = float(np.median(np.abs(r - np.median(r)))) if r.size else 0.0
    c = max(4.685 * 1.4826 * mad, float(floor))
    u = r / c
    w = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    return w if w.sum() > 0 else np.ones_like(r)


@dataclass(frozen=True)
class ArkitSolution:
    """ARKit coefficients read from a motion.

    Attributes:
        coefficients: ARKit name -> coefficient in [0, 1] (all 52; unavailable ones 0).
        contribution_mm: name -> RMS over the readout's vertices of that shape's motion at its
            coefficient, mm.
        residual_mm: RMS (robust-weighted) of the motion the coefficients leave unexplained,
            mm; motion_rms_mm: the same of the motion itself.
        unavailable: names without a source shape (reported as 0).
        iterations: robust re-weighting passes.
    """

    coefficients: dict
    contribution_mm: dict
    residual_mm: float
    motion_rms_mm: float
    unavailable: tuple[str, ...]
    iterations: int

    def strongest(self, n: int = 5) -> list[tuple[str, float]]:
        """The ``n`` largest coefficients, largest first."""
        return sorted(self.coefficients.items(), key=lambda kv: -kv[1])[:n]

    def to_dict(self) -> dict:
        return {
            "contribution_mm": {k: float(v) for k, v in self.contribution_mm.items()},
            "residual_mm": float(self.residual_mm),
            "motion_rms_mm": float(self.motion_rms_mm),
            "unavailable": list(self.unavailable),
            "robust_iterations": int(self.iterations),
        }


def _solution(basis: ArkitBasis, c_av: np.ndarray, ids, res_mm, mot_mm, it) -> ArkitSolution:
    c = np.zeros(len(ARKIT_NAMES))
    c[ids] = c_av
    m = basis.mask
    contrib = np.sqrt(np.mean(np.sum((basis.deltas[:, m] * c[:, None, None]) ** 2, -1), -1))
    return ArkitSolution(
        coefficients={n: float(v) for n, v in zip(ARKIT_NAMES, c)},
        contribution_mm={n: float(v) for n, v in zip(ARKIT_NAMES, contrib)},
        residual_mm=float(res_mm),
        motion_rms_mm=float(mot_mm),
        unavailable=tuple(n for n, a in zip(ARKIT_NAMES, basis.available) if not a),
        iterations=it,
    )


def solve_arkit(
    basis: ArkitBasis,
    motion,
    *,
    l1: float = 0.01,
    robust: bool = True,
    robust_floor_mm: float = 1.5,
    iterations: int = 4,
) -> ArkitSolution:
    """ARKit coefficients of a skin motion (e.g. fitted skin minus rest, same topology).

    Minimises ``sum_i w_i |B_i c - d_i|^2 / sum_i w_i + l1 * sum_k c_k`` over ``0 <= c <= 1``
    on the basis's vertices ``i`` (mask), with Tukey weights ``w_i`` of ``|B_i c - d_i|``
    re-estimated ``iterations`` times (``robust=False``: ``w = 1``, one solve).

    Args:
        motion: ``(V, 3)`` mm; l1: mm^2 per unit coefficient (sparsity).

    Raises:
        FitError: shape mismatch or non-finite motion.
    """
    d = np.asarray(motion, np.float64)
    if d.shape != basis.deltas.shape[1:]:
        raise FitError(f"motion must be {basis.deltas.shape[1:]} (mm), got {d.shape}.")
    if not np.all(np.isfinite(d[basis.mask])):
        raise FitError("the motion holds NaN/inf on the face region.")
    ids = np.flatnonzero(basis.available)
    B = basis.deltas[ids][:, basis.mask].reshape(len(ids), -1).T  # (3P, K)
    y = d[basis.mask].reshape(-1)
    P = int(basis.mask.sum())
    w = np.ones(P)
    c = np.zeros(len(ids))
    n_it = iterations if robust else 1
    for _ in range(n_it):
        w3 = np.repeat(w / w.sum(), 3)
        Bw = B * w3[:, None]
        c = box_qp(B.T @ Bw, Bw.T @ y - 0.5 * l1)
        r = np.linalg.norm((B @ c - y).reshape(P, 3), axis=1)
        if robust:
            w = tukey_weights(r, robust_floor_mm)
    r = np.linalg.norm((B @ c - y).reshape(P, 3), axis=1)
    wn = w / w.sum()
    res = float(np.sqrt(np.sum(wn * r**2)))
    mot = float(np.sqrt(np.mean(np.sum(d[basis.mask] ** 2, -1))))
    return _solution(basis, c, ids, res, mot, n_it)


def fit_arkit_to_scan(
    basis: ArkitBasis,
    rest_vertices,
    triangles,
    scan_vertices,
    scan_triangles,
    *,
    landmarks=None,
    landmark_weight: float = 1.0,
    l1: float = 0.01,
    robust_floor_mm: float = 1.5,
    max_distance_mm: float = 10.0,
    iterations: int = 6,
) -> ArkitSolution:
    """ARKit coefficients straight from a scan (no rig): point-to-plane ICP of
    ``rest + sum_k c_k B_k`` to the scan surface (both in the same frame, mm).

    Each pass takes the closest scan point ``p_i`` and scan normal ``n_i`` of every basis
    vertex ``x_i(c)`` and solves ``min sum_i w_i (n_i . (rest_i + B_i c - p_i))^2 / sum w +
    landmark_weight * mean_l |B_l c - m_l|^2 + l1 sum c`` on ``[0, 1]`` with Tukey weights;
    matches on the scan's border or farther than ``max_distance_mm`` are rejected. The
    point-to-plane term leaves motion along the skin (a brow sliding up) free; the landmark
    term pins it.

    Args:
        landmarks: None, or ``(tri (L,), bary (L, 3), motion (L, 3) mm)``: landmarks attached
            to the rest skin's triangles and their motion in the scan (e.g. aligned
            expression landmark minus neutral landmark).

    Returns:
        :class:`ArkitSolution` (``motion_rms_mm``: RMS of the recovered motion).
    """
    from ..fit.metrics import SurfaceIndex

    X0 = np.asarray(rest_vertices, np.float64)
    if X0.shape != basis.deltas.shape[1:]:
        raise FitError(f"rest_vertices must be {basis.deltas.shape[1:]}, got {X0.shape}.")
    index = SurfaceIndex(scan_vertices, scan_triangles)
    ids = np.flatnonzero(basis.available)
    m = basis.mask
    Bm = basis.deltas[ids][:, m]  # (K, P, 3)
    c = np.zeros(len(ids))
    res = 0.0
    GL = np.zeros((len(ids), len(ids)))
    gL = np.zeros(len(ids))
    if landmarks is not None:
        ltri, lbary, lmot = (np.asarray(a) for a in landmarks)
        corners = np.asarray(triangles, np.int64)[np.asarray(ltri, np.int64)]  # (L, 3)
        BL = np.einsum("lj,kljd->kld", lbary, basis.deltas[ids][:, corners]).reshape(len(ids), -1).T
        ml = np.asarray(lmot, np.float64).reshape(-1)
        if not np.all(np.isfinite(ml)):
            raise FitError("landmark motion holds NaN/inf.")
        s_l = float(landmark_weight) / max(len(ml) // 3, 1)
        GL = s_l * BL.T @ BL
        gL = s_l * BL.T @ ml
    for _ in range(iterations):
        x = X0[m] + np.einsum("k,kpd->pd", c, Bm)
        cp = index.query(x, max_distance=2 * max_distance_mm)
        n = cp.normals
        ok = ~cp.on_boundary & (cp.distances <= max_distance_mm)
        if not ok.any():
            raise FitError("no basis vertex found the scan within max_distance_mm.")
        A = np.einsum("pd,kpd->pk", n, Bm)  # (P, K)
        b = np.einsum("pd,pd->p", n, cp.points - X0[m])
        r = np.abs(A @ c - b)
        w = np.where(ok, tukey_weights(np.where(ok, r, 0.0), robust_floor_mm), 0.0)
        if w.sum() <= 0:
            w = ok.astype(np.float64)
        w = w / w.sum()
        Aw = A * w[:, None]
        c = box_qp(A.T @ Aw + GL, Aw.T @ b + gL - 0.5 * l1)
        res = float(np.sqrt(np.sum(w * (A @ c - b) ** 2)))
    mot = float(np.sqrt(np.mean(np.sum(np.einsum("k,kpd->pd", c, Bm) ** 2, -1))))
    return _solution(basis, c, ids, res, mot, iterations)


def landmark_motion(registration, neutral, scan, transform):
    """The landmark term of :func:`fit_arkit_to_scan`: the registered landmarks' attachment
    (``registration.landmark_points``) and their motion ``T(q_scan) - q_neutral`` (mm) for the
    labels present in both scans; ``transform`` maps the scan into the neutral's frame."""
    lp = registration.landmark_points
    qn = dict(zip(neutral.landmarks.names, np.asarray(neutral.landmarks.positions)))
    qe = dict(zip(scan.landmarks.names, np.asarray(scan.landmarks.positions)))
    names = list(registration.landmarks.names)
    keep = [i for i, n in enumerate(names) if n in qn and n in qe]
    if not keep:
        raise LandmarkError("no landmark label common to the registration and both scans.")
    mot = np.stack([transform.apply(qe[names[i]][None])[0] - qn[names[i]] for i in keep])
    return np.asarray(lp.tri)[keep], np.asarray(lp.bary)[keep], mot


# ------------------------------------------------------------------------------------------
# the readout of a fit (used by jaxface.fit.pipeline)
# ------------------------------------------------------------------------------------------
class ArkitReadout:
    """Reads ARKit coefficients from fitted skins of one subject (:func:`solve_arkit`), or
    says why it cannot (no ICT data, a failed transfer): it never makes numbers up.

    Call it with a fitted skin ``(V, 3)`` mm (the rig's frame and topology): returns
    ``(coefficients dict or None, detail dict)``; ``detail`` holds ``available`` and either
    the :meth:`ArkitSolution.to_dict` fields with ``source``/``method``, or ``reason``.
    """

    def __init__(self, rest, basis: ArkitBasis | None = None, reason: str = "", l1: float = 0.01):
        self.rest = np.asarray(rest, np.float64)
        self.basis = basis
        self.reason = reason
        self.l1 = float(l1)

    def __call__(self, skin) -> tuple[dict | None, dict]:
        if self.basis is None:
            return None, {"available": False, "reason": self.reason}
        try:
            sol = solve_arkit(self.basis, np.asarray(skin, np.float64) - self.rest, l1=self.l1)
        except FitError as e:
            return None, {"available": False, "reason": str(e)}
        return dict(sol.coefficients), {
            "available": True,
            **sol.to_dict(),
            "source": self.basis.source,
            "method": "bounded L1-weighted least squares (0 <= c <= 1, l1 "
            f"{self.l1:g} mm^2) of the ICT-FaceKit ARKit shapes cloned onto the subject "
            "(jaxface.interop.arkit) to the fitted skin motion, Tukey-weighted",
            "transfer": dict(self.basis.info),
            "sides": "Left = the subject's own left (+x), as ICT's _L",
        }


_READOUTS: dict[tuple[int, str], ArkitReadout] = {}


def readout_for_subject(subject, ict: Any = "auto") -> ArkitReadout:
    """The :class:`ArkitReadout` of a :class:`jaxface.fit.pipeline.Subject` (cached per
    subject object).

    Args:
        ict: ``"auto"`` (:func:`default_ict_path`), a path to ``ict_face.npz``, an
            :class:`ArkitBasis` on the subject's skin, or None (off: the readout reports
            that it was not requested).
    """
    import weakref

    from ..errors import JaxfaceError

    rest = np.asarray(subject.forward.rest, np.float64)
    if ict is None:
        return ArkitReadout(rest, reason="ARKit readout not requested (arkit=None)")
    if isinstance(ict, ArkitBasis):
        return ArkitReadout(rest, ict)
    key = (id(subject), str(ict))
    hit = _READOUTS.get(key)
    if hit is not None and np.array_equal(hit.rest, rest):
        return hit
    path = default_ict_path(shared_fallback=False) if ict == "auto" else Path(ict)
    if path is None or not Path(path).is_file():
        ro = ArkitReadout(
            rest,
            reason="no ICT-FaceKit data: the ARKit shapes are cloned from ict_face.npz, which "
            "jaxface does not ship; set JAXFACE_ICT to the file (or give jaxface fit --ict FILE) "
            "and fit again" + (f" (not found: {path})" if path is not None else ""),
        )
    else:
        try:
            basis = transfer_ict_basis(
                rest,
                np.asarray(subject.triangles),
                subject.landmarks_on(rest),
                subject.face_mask,
                ict_path=path,
            )
            ro = ArkitReadout(rest, basis)
        except (JaxfaceError, ValueError) as e:
            ro = ArkitReadout(rest, reason=f"the ARKit shapes could not be transferred: {e}")
    try:
        weakref.finalize(subject, _READOUTS.pop, key, None)
    except TypeError:  # not weak-referenceable: no cache (an id could be reused)
        return ro
    _READOUTS[key] = ro
    return ro
