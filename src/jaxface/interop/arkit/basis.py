"""The ARKit basis on a subject: the ICT-backed ARKit displacement fields cloned onto the
subject's face region (:func:`transfer_ict_basis`, :class:`ArkitBasis`, mm)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import DataNotFoundError, FitError
from .ict import default_ict_path, ict_bosphorus_landmarks
from .names import ARKIT_NAMES, arkit_deltas_from_ict

__all__ = ["TRANSFER_VERSION", "ArkitBasis", "ict_transfer_error", "transfer_ict_basis"]

#: Bumped when :func:`transfer_ict_basis` changes its result; on-disk caches of anything built
#: from a basis (the ARKit inverse maps) include it in their key. 2: no Multi-PIE menton as the
#: chin, and the eye/mouth contours kept. 3: the cloning morph is a ridge fit (``reg=1``).
TRANSFER_VERSION = 3


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

    @property
    def scale_mm(self) -> np.ndarray:
        """``(52,)`` RMS over ``mask`` of each shape's displacement at coefficient 1, mm (0 for
        unavailable shapes): the readout's L1 weight of each coefficient."""
        m = self.mask
        return np.sqrt(np.mean(np.sum(self.deltas[:, m] ** 2, -1), -1))

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
    check_contours: bool = False,
    reg: float = 1.0,
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
        transfer: how a displacement is carried over (:func:`jaxface.clone.apply_clone`).
        check_contours: drop the eyelid and inner-lip contour pairs when they raise the mean
            ray error (:func:`jaxface.clone.fit_source_to_target`). Off by default: the ray
            error measures the distance *across* the surface, while the contours pin the
            sliding *along* it that decides where the lid and lip motion lands. On the ICT
            identity (where the true transfer is known), keeping them brings the median
            relative error of the 51 cloned shapes from 38 % to 21 % (``eyeWide`` 67-92 ->
            22-35 %, ``eyeBlink`` 120 -> 45 %, ``jawOpen`` 25 -> 12 %; docs/interop.md).
        reg: ridge of the cloning morph (:func:`jaxface.clone.fit_source_to_target`). An
            exact interpolant (``reg=0``) bends to every refinement pair, each a ray hit
            that is right across the surface but not along it, and slides the lid and lip
            motion off its place: on the two subjects whose true transfer is known (the ICT
            identities under the Bosphorus-style neutrals) the median relative error of the
            51 shapes is 21 / 18 % with ``reg=0`` and 10 / 11 % with ``reg=1``
            (``eyeBlinkLeft`` 45 / 44 -> 10 / 19 %; docs/interop.md).

    Raises:
        DataNotFoundError: no ICT file.
    """
    from ...anatomy.ict import FACE_VERTEX_COUNT, load_ict_face
    from ...clone import clone_motion
    from ...mesh import TriMesh

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
        check_contours=check_contours,
        reg=reg,
    )
    full = np.zeros((len(ARKIT_NAMES), len(V), 3))
    full[np.ix_(ids, old)] = res.deltas
    m = np.zeros(len(V), bool)
    m[old] = True
    if not np.all(np.isfinite(full)):
        raise FitError("the cloned ARKit shapes hold NaN/inf; check the subject's landmarks.")
    info = {
        "method": "jaxface.clone.clone_motion of the ICT-FaceKit shapes (landmarks, contours, "
        f"{max_iterations} refinement iterations, ridge {reg:g})",
        "contours_skipped": dict(res.fit.contours_skipped),
        "landmarks": list(res.fit.landmark_names),
        "contours": list(res.fit.contours_used),
        "iterations": int(res.fit.iterations),
        "seconds": time.perf_counter() - t0,
    }
    return ArkitBasis(full, avail, m, str(p), info)


def ict_transfer_error(
    basis: ArkitBasis,
    vertices,
    ict_path=None,
    *,
    truth_neutral=None,
    rotation=None,
) -> dict[str, float]:
    """How far a basis cloned onto an ICT-FaceKit face is from the ICT shapes themselves.

    When the subject *is* an ICT face (the ICT neutral, or any ICT identity: ICT's expression
    displacements do not depend on the identity), the true transfer is known: each basis
    vertex's closest point on the subject's true neutral face carries the ICT shape's own
    displacement there (barycentric), rotated into the subject's frame. Per ARKit shape
    ``k``: ``RMS_i |B_k(x_i) - R D_k(x_i)| / RMS_i |R D_k(x_i)|`` over the basis's vertices
    ``i``.

    Args:
        basis: the cloned basis; vertices: ``(V, 3)`` its skin, mm.
        ict_path: ``ict_face.npz`` (default :func:`default_ict_path`).
        truth_neutral: ``(9409, 3)`` the subject's true neutral face in the ICT face topology,
            mm, in the frame of ``vertices`` (default: the ICT neutral, in the ICT frame).
        rotation: ``(3, 3)`` rotation from the ICT frame to that frame (default identity).

    Returns:
        ARKit name -> relative RMS error (0 = exact) for the available shapes.
    """
    from ...anatomy.ict import FACE_VERTEX_COUNT, load_ict_face
    from ...mesh import TriMesh

    p = Path(ict_path) if ict_path is not None else default_ict_path()
    if p is None or not p.is_file():
        raise DataNotFoundError(
            f"the ICT-FaceKit file was not found ({p}); pass ict_path=.../ict_face.npz or set "
            "JAXFACE_ICT (or JAXFACE_SHARED)."
        )
    ict = load_ict_face(p)
    deltas, avail = arkit_deltas_from_ict(
        ict.expression_names, ict.expression_deltas[:, :FACE_VERTEX_COUNT]
    )
    tris = np.asarray(ict.skin.triangles)
    surface = np.asarray(ict.skin.vertices if truth_neutral is None else truth_neutral, float)
    if surface.shape != (FACE_VERTEX_COUNT, 3):
        raise FitError(
            f"truth_neutral must be ({FACE_VERTEX_COUNT}, 3) in the ICT face topology, got "
            f"{surface.shape}."
        )
    R = np.eye(3) if rotation is None else np.asarray(rotation, np.float64).reshape(3, 3)
    m = basis.mask
    sp, _ = TriMesh(surface, tris, validate=False).closest_points(
        np.asarray(vertices, np.float64)[m]
    )
    bary, corners = np.asarray(sp.bary), tris[np.asarray(sp.tri)]
    out = {}
    for k in np.flatnonzero(avail & basis.available):
        true = np.einsum("pj,pjd->pd", bary, deltas[k][corners]) @ R.T
        rms = float(np.sqrt(np.mean(np.sum(true**2, -1))))
        err = float(np.sqrt(np.mean(np.sum((basis.deltas[k][m] - true) ** 2, -1))))
        out[ARKIT_NAMES[k]] = err / max(rms, 1e-12)
    return out
