"""Faces and face frames of the Erdoğdu method: :class:`Face` (vertices in mm, triangles,
landmarks), :func:`as_face`, and :class:`FaceFrame` / :func:`face_frame` (eye-corner x axis,
eye-mouth y axis, ``z`` toward the viewer, scale ``D``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

from ..errors import LandmarkError, ScanFormatError
from ..io.bosphorus import Scan
from ..landmarks import FACE_LABELS, Landmarks
from ..mesh import TriMesh

__all__ = ["Face", "FaceFrame", "as_face", "face_frame"]


@dataclass(frozen=True, eq=False)
class Face:
    """A face surface with landmarks, mm.

    Attributes:
        vertices: (V, 3) mm.
        triangles: (F, 3) int64 or ``None`` (point set).
        landmarks: :class:`jaxface.landmarks.Landmarks`, mm.
        name: for messages.
    """

    vertices: np.ndarray
    triangles: np.ndarray | None
    landmarks: Landmarks
    name: str = "face"

    def tree(self) -> cKDTree:
        t = self.__dict__.get("_tree")
        if t is None:
            t = cKDTree(self.vertices)
            object.__setattr__(self, "_tree", t)
        return t

    def mesh(self):
        m = self.__dict__.get("_mesh")
        if m is None and self.triangles is not None:
            m = TriMesh(self.vertices, self.triangles, validate=False)
            object.__setattr__(self, "_mesh", m)
        return m


def as_face(obj, landmarks: Landmarks | None = None, name: str | None = None) -> Face:
    """Normalise a face given as :class:`Face`, :class:`jaxface.io.Scan` (range grids are
    meshed), :class:`jaxface.mesh.TriMesh`, ``(V, 3)`` vertex array, or a tuple
    ``(mesh_or_vertices, landmarks)``.

    Raises:
        LandmarkError: no landmarks given or found.
        ScanFormatError: vertices not (V, 3) finite.
    """
    if isinstance(obj, Face):
        return obj if landmarks is None else Face(obj.vertices, obj.triangles, landmarks, obj.name)
    if isinstance(obj, tuple) and len(obj) == 2 and isinstance(obj[1], Landmarks):
        return as_face(obj[0], obj[1] if landmarks is None else landmarks, name)
    tri = None
    if isinstance(obj, Scan):
        lm = landmarks if landmarks is not None else obj.landmarks
        nm = name or (obj.path.name if obj.path is not None else "scan")
        if obj.is_grid:
            v, tri, _ = obj.mesh_arrays()  # range grid meshed, unreferenced points dropped
        else:
            v, tri = obj.points, obj.triangles  # mesh scan: vertex order kept
    elif isinstance(obj, TriMesh):
        v, tri, lm, nm = obj.vertices, obj.triangles, landmarks, name or "mesh"
    else:
        v, lm, nm = obj, landmarks, name or "vertices"
    v = np.asarray(v, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or not np.all(np.isfinite(v)):
        raise ScanFormatError(
            f"{nm}: face vertices must be a finite (V >= 4, 3) array in mm, got shape {v.shape}."
        )
    if lm is None:
        raise LandmarkError(
            f"{nm}: no landmarks; pass (mesh, Landmarks) or a Scan loaded with its .lm3 file.",
            missing=FACE_LABELS,
        )
    return Face(v, None if tri is None else np.asarray(tri, dtype=np.int64), lm, nm)


@dataclass(frozen=True)
class FaceFrame:
    """Face-aligned frame built from landmarks (mm).

    Attributes:
        origin: (3,) midpoint of the eye corners, mm.
        axes: (3, 3) rows x (toward the subject's left), y (up), z (toward the viewer).
        size: outer-eye-corner distance ``D``, mm.
        eye_height, mouth_height: heights (along y, relative to origin) of the eye-corner and
            mouth-corner midpoints, mm.
    """

    origin: np.ndarray
    axes: np.ndarray
    size: float
    eye_height: float
    mouth_height: float

    def local(self, p: np.ndarray) -> np.ndarray:
        """(..., 3) mm -> (..., 3) frame coordinates, mm."""
        return (np.asarray(p, dtype=np.float64) - self.origin) @ self.axes.T

    def border_height(self, fraction: float = 0.12) -> float:
        """Height of the upper/lower region border (mm, frame y)."""
        return self.eye_height - fraction * (self.eye_height - self.mouth_height)


def face_frame(landmarks: Landmarks) -> FaceFrame:
    """:class:`FaceFrame` from the eye corners and mouth corners.

    Raises:
        LandmarkError: any of the four eye corners or two mouth corners missing.
    """
    need = (
        "Outer left eye corner",
        "Inner left eye corner",
        "Inner right eye corner",
        "Outer right eye corner",
        "Left mouth corner",
        "Right mouth corner",
    )
    lm = landmarks.require(need)
    ole, ile, ire, ore, lmc, rmc = (np.asarray(lm[n]) for n in need)
    eye = (ole + ile + ire + ore) / 4
    mouth = (lmc + rmc) / 2
    x = ole - ore
    D = float(np.linalg.norm(x))
    if D <= 0:
        raise LandmarkError(
            "the outer eye corners coincide; cannot build the face frame", missing=()
        )
    x = x / D
    y = eye - mouth
    y = y - (y @ x) * x
    ny = np.linalg.norm(y)
    if ny <= 1e-9 * D:
        raise LandmarkError(
            "eye and mouth midpoints are aligned with the eye axis; cannot build the face frame",
            missing=(),
        )
    y = y / ny
    z = np.cross(x, y)
    return FaceFrame(eye, np.stack([x, y, z]), D, 0.0, float((mouth - eye) @ y))
