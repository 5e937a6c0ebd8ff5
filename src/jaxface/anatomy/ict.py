"""The ICT-FaceKit face as a test subject for the anatomy rig (NumPy, build time).

``ict_face.npz`` (``shared/data/ict``) holds the whole ICT head; the rig uses its *face*
region (vertices 0..9408, the triangles of the ``face`` group that use only those vertices)
and its ``teeth`` group split into upper and lower teeth (connected components above / below
the mouth slit). Landmarks come from ICT vertex ids (e.g. ``landmark_vertex_ids_ict`` in
``shared/data/bosphorus_style/truth.json``).

Units: mm (the file is in mm); +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import DataNotFoundError, ScanFormatError
from ..landmarks import Landmarks
from ..mesh import TriMesh

__all__ = ["ICTFace", "load_ict_face", "FACE_VERTEX_COUNT"]

FACE_VERTEX_COUNT = 9409


@dataclass(frozen=True)
class ICTFace:
    """The ICT face prepared for the rig.

    Attributes:
        skin: the face-region :class:`TriMesh` (9409 vertices), mm.
        landmarks: :class:`Landmarks` (when vertex ids were given), mm.
        upper_teeth, lower_teeth: :class:`TriMesh` of the teeth, mm.
        neutral: ``(21451, 3)`` the whole ICT neutral head, mm.
        expression_names: ``(57,)``; expression_deltas: ``(57, 21451, 3)`` mm.
    """

    skin: TriMesh
    landmarks: Landmarks | None
    upper_teeth: TriMesh
    lower_teeth: TriMesh
    neutral: np.ndarray
    expression_names: tuple
    expression_deltas: np.ndarray


def _components(tris: np.ndarray, n: int) -> np.ndarray:
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(A, directed=False)[1]


def load_ict_face(npz_path, landmark_ids=None) -> ICTFace:
    """Load the ICT face, its teeth and (optionally) its Bosphorus landmarks.

    Args:
        npz_path: ``ict_face.npz``.
        landmark_ids: ``{label: ICT vertex id}``, or the path of a JSON file holding such a
            dict under ``landmark_vertex_ids_ict`` (``bosphorus_style/truth.json``), or None.

    Returns:
        :class:`ICTFace`.

    Raises:
        DataNotFoundError: a file is missing; ScanFormatError: the npz lacks a needed array.
    """
    p = Path(npz_path)
    if not p.exists():
        raise DataNotFoundError(f"ICT face file not found: {p}.")
    d = np.load(p)
    for k in ("neutral", "triangles", "triangle_group", "group_names"):
        if k not in d.files:
            raise ScanFormatError(f"{p} has no array {k!r}; expected the ICT-FaceKit export.")
    X = np.asarray(d["neutral"], dtype=np.float64)
    T = np.asarray(d["triangles"], dtype=np.int64)
    groups = [str(g) for g in d["group_names"]]
    tg = np.asarray(d["triangle_group"])
    face_t = T[tg == groups.index("face")]
    face_t = face_t[(face_t < FACE_VERTEX_COUNT).all(axis=1)]
    skin = TriMesh(X[:FACE_VERTEX_COUNT], face_t, validate=False)
    lm = None
    if landmark_ids is not None:
        if not isinstance(landmark_ids, dict):
            lp = Path(landmark_ids)
            if not lp.exists():
                raise DataNotFoundError(f"landmark id file not found: {lp}.")
            landmark_ids = json.loads(lp.read_text())["landmark_vertex_ids_ict"]
        names = list(landmark_ids)
        lm = Landmarks(names, X[[int(landmark_ids[n]) for n in names]])
    teeth_t = T[tg == groups.index("teeth")]
    used = np.unique(teeth_t)
    remap = np.full(X.shape[0], -1)
    remap[used] = np.arange(used.size)
    tt = remap[teeth_t]
    comp = _components(tt, used.size)
    V = X[used]
    # split at the height of the mouth slit: the gap between upper and lower teeth
    ys = np.array([V[comp == c, 1].mean() for c in range(comp.max() + 1)])
    if lm is not None:
        cut = 0.5 * (lm["Upper lip inner middle"][1] + lm["Lower lip inner middle"][1])
    else:
        cut = float(np.median(ys))
    upper_c = np.flatnonzero(ys > cut)
    tri_comp = comp[tt[:, 0]]
    upper_mask = np.isin(tri_comp, upper_c)

    def sub(mask):
        m = TriMesh(V, tt, validate=False)
        return m.submesh(mask)[0]

    return ICTFace(
        skin=skin,
        landmarks=lm,
        upper_teeth=sub(upper_mask),
        lower_teeth=sub(~upper_mask),
        neutral=X,
        expression_names=tuple(str(n) for n in d["expression_names"]),
        expression_deltas=np.asarray(d["expression_deltas"]),
    )
