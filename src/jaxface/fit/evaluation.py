"""The issue-7 ground-truth protocol for the shared ``bosphorus_style`` data.

Units and frame: millimetres; +y up; the face looks along +z; the subject's left is +x.

The data (``shared/data/bosphorus_style``, read through :func:`jaxface.testing.shared_path`)
holds, per scan ``<stem>``: the ``.bnt`` range grid, its ``.lm3`` landmarks and
``<stem>.truth.ply``, the exact ICT-FaceKit mesh that was scanned (ICT vertex order; the
face region is vertices ``0..9408``). ``truth.json`` records for each stem the ICT
expression weights and the rigid motion applied to the whole mesh before scanning::

    p' = Rx(pitch) @ Ry(yaw) @ p + shift          (degrees about +x and +y, shift in mm)

so ``truth.ply`` and the scan live in the *scan frame*; undoing the motion gives the ICT
frame.

Protocol (:func:`evaluation_region`, :func:`evaluate_against_truth`):

* **Coverage** ("where the scan has data"): a truth vertex is covered when its exact
  closest point on the meshed scan is within ``coverage_tol_mm`` (default 1 mm; the depth
  noise is 0.1 mm) and does not lie on the scan's border (a hole rim or the silhouette).
* **Evaluation region** of an expression scan: face-region truth vertices (ids < 9409),
  covered by the scan, that the expression moves by more than ``threshold_mm`` (1 mm)
  relative to the same subject's truth neutral, both taken back to the ICT frame by undoing
  their rigid motions. For a **neutral** scan nothing moves, so its region is every covered
  face vertex (the registration accuracy check of issue 7).
* **Error** of a candidate fitted skin (a mesh in the scan frame, any topology): the
  distance from each region vertex of the truth mesh to the candidate's surface (exact
  point-to-triangle), summarised by :class:`jaxface.fit.metrics.DistanceStats`, also for the
  upper and lower face (:class:`jaxface.fit.metrics.FacePlane` from the scan's landmarks).

:func:`ict_template` builds the ICT neutral skin (face + head/neck groups) with the 22
landmarks of ``truth.json`` as a registration template for data tests.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataNotFoundError, FitError
from ..io import load_scan
from ..landmarks import Landmarks
from ..mesh import TriMesh, load_mesh
from ..rigid import RigidTransform, rotation_from_euler
from ..testing import shared_path
from .metrics import DistanceStats, FacePlane, SurfaceIndex, mesh_arrays

__all__ = [
    "ICT_FACE_VERTICES",
    "TruthRecord",
    "TruthSet",
    "load_truth",
    "scan_coverage",
    "evaluation_region",
    "TruthEvaluation",
    "evaluate_against_truth",
    "ict_template",
    "ICTTemplate",
]

#: the ICT face region is vertices 0 .. ICT_FACE_VERTICES - 1 (shared/README.md)
ICT_FACE_VERTICES = 9409


@dataclass(frozen=True)
class TruthRecord:
    """Ground truth of one scan.

    Attributes:
        stem: file stem, e.g. ``"bs901_LFAU_12_0"``; subject: ``"bs901"``; code: ``"LFAU_12"``.
        weights: ICT expression name -> weight (empty for a neutral).
        rigid: the motion ICT frame -> scan frame (identity when none was applied), mm.
    """

    stem: str
    subject: str
    code: str
    weights: dict[str, float]
    rigid: RigidTransform

    @property
    def is_neutral(self) -> bool:
        return not self.weights


def _parse_stem(stem: str) -> tuple[str, str]:
    parts = stem.split("_")
    if len(parts) < 3:
        raise FitError(f"cannot parse scan stem {stem!r} (expected bsXXX_<class>_<code>_<n>).")
    return parts[0], "_".join(parts[1:-1])


@dataclass
class TruthSet:
    """The ``bosphorus_style`` folder with its ``truth.json`` (see the module doc).

    Attributes:
        root: the folder.
        records: stem -> :class:`TruthRecord`.
        landmark_vertex_ids: landmark label -> ICT vertex id.
    """

    root: Path
    records: dict[str, TruthRecord]
    landmark_vertex_ids: dict[str, int]
    _cache: dict = field(default_factory=dict, repr=False)

    def stems(self, subject: str | None = None) -> list[str]:
        """Sorted stems, optionally of one subject."""
        return sorted(s for s, r in self.records.items() if subject is None or r.subject == subject)

    def subjects(self) -> list[str]:
        return sorted({r.subject for r in self.records.values()})

    def neutral_stem(self, subject: str) -> str:
        """The stem of the subject's neutral scan. Raises :class:`FitError` if absent."""
        for s in self.stems(subject):
            if self.records[s].is_neutral:
                return s
        raise FitError(f"no neutral scan of subject {subject!r} in {self.root}.")

    def path(self, stem: str, suffix: str) -> Path:
        p = self.root / f"{stem}{suffix}"
        if not p.is_file():
            raise DataNotFoundError(f"missing data file {p}.")
        return p

    def truth_vertices(self, stem: str) -> np.ndarray:
        """``(21451, 3)`` mm: the truth mesh vertices of ``stem`` in its scan frame."""
        return mesh_arrays(self.truth_mesh(stem))[0]

    def truth_mesh(self, stem: str):
        """The ``.truth.ply`` as a :class:`jaxface.mesh.TriMesh` (scan frame, mm), cached."""
        key = ("truth", stem)
        if key not in self._cache:
            self._cache[key] = load_mesh(self.path(stem, ".truth.ply"), validate=False)
        return self._cache[key]

    def scan(self, stem: str):
        """The scan with its landmarks (:class:`jaxface.io.Scan`, mm), cached."""
        key = ("scan", stem)
        if key not in self._cache:
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self._cache[key] = load_scan(self.path(stem, ".bnt"))
        return self._cache[key]

    def scan_mesh(self, stem: str):
        """The meshed scan (:class:`jaxface.mesh.TriMesh`, mm), cached."""
        key = ("scan_mesh", stem)
        if key not in self._cache:
            self._cache[key] = self.scan(stem).to_mesh(validate=False)
        return self._cache[key]

    def scan_index(self, stem: str) -> SurfaceIndex:
        """:class:`SurfaceIndex` of the meshed scan, cached."""
        key = ("scan_index", stem)
        if key not in self._cache:
            self._cache[key] = SurfaceIndex.from_mesh(self.scan_mesh(stem))
        return self._cache[key]

    def relative_transform(self, moving: str, fixed: str) -> RigidTransform:
        """True rigid transform from the scan frame of ``moving`` to that of ``fixed``
        (what :func:`jaxface.fit.align.align_scans` estimates): ``T_fixed o T_moving^-1``."""
        return self.records[fixed].rigid.compose(self.records[moving].rigid.inverse())

    def ict_frame_vertices(self, stem: str) -> np.ndarray:
        """Truth vertices of ``stem`` with its rigid motion undone (ICT frame), mm."""
        return self.records[stem].rigid.inverse().apply(self.truth_vertices(stem))


def load_truth(root=None) -> TruthSet:
    """Read ``truth.json`` of the Bosphorus-style data.

    Arguments:
        root: the ``bosphorus_style`` folder; default
            ``jaxface.testing.shared_path("data", "bosphorus_style")`` (skips under pytest
            when the data is absent).

    Raises:
        DataNotFoundError: no ``truth.json`` in ``root``.
    """
    if root is None:
        root = shared_path("data", "bosphorus_style")
    root = Path(root)
    f = root / "truth.json"
    if not f.is_file():
        raise DataNotFoundError(
            f"no truth.json in {root}; point root at shared/data/bosphorus_style."
        )
    raw = json.loads(f.read_text())
    ids = {str(k): int(v) for k, v in raw.get("landmark_vertex_ids_ict", {}).items()}
    records = {}
    for stem, rec in raw.items():
        if stem == "landmark_vertex_ids_ict" or not isinstance(rec, dict):
            continue
        subject, code = _parse_stem(stem)
        r = rec.get("rigid") or {}
        if r:
            T = RigidTransform(
                rotation_from_euler(float(r.get("pitch", 0.0)), float(r.get("yaw", 0.0))),
                np.asarray(r.get("shift", [0.0, 0.0, 0.0]), dtype=np.float64),
            )
        else:
            T = RigidTransform()
        w = {str(k): float(v) for k, v in (rec.get("ict_expression_weights") or {}).items()}
        records[stem] = TruthRecord(stem, subject, code, w, T)
    return TruthSet(root=root, records=records, landmark_vertex_ids=ids)


# --------------------------------------------------------------------------------------
# coverage and the evaluation region
# --------------------------------------------------------------------------------------
def scan_coverage(points, scan, *, tol_mm: float = 1.0) -> np.ndarray:
    """``(K,)`` bool: points (mm) where the scan has data: the exact closest point on the
    scan surface is within ``tol_mm`` and not on the scan's border.

    Arguments:
        points: ``(K, 3)`` mm, in the scan's frame.
        scan: a :class:`SurfaceIndex`, a mesh, or a :class:`jaxface.io.Scan`.
    """
    if isinstance(scan, SurfaceIndex):
        index = scan
    elif hasattr(scan, "mesh_arrays") and hasattr(scan, "points"):
        v, t, _ = scan.mesh_arrays()
        index = SurfaceIndex(v, t)
    else:
        index = SurfaceIndex.from_mesh(scan)
    cp = index.query(points, max_distance=tol_mm)
    return (cp.distances <= tol_mm) & ~cp.on_boundary


def evaluation_region(
    truth: TruthSet,
    stem: str,
    *,
    threshold_mm: float = 1.0,
    coverage_tol_mm: float = 1.0,
) -> np.ndarray:
    """``(21451,)`` bool over the truth vertices of ``stem``: the issue-7 evaluation region
    (face region, covered by the scan, moved by more than ``threshold_mm`` vs the subject's
    truth neutral after undoing both rigid motions; all covered face vertices for a neutral).
    Cached per (stem, threshold, tolerance)."""
    key = ("region", stem, float(threshold_mm), float(coverage_tol_mm))
    if key in truth._cache:
        return truth._cache[key]
    rec = truth.records[stem]
    tv = truth.truth_vertices(stem)
    face = np.zeros(len(tv), bool)
    face[:ICT_FACE_VERTICES] = True
    region = face.copy()
    if not rec.is_neutral:
        neutral = truth.neutral_stem(rec.subject)
        a = truth.ict_frame_vertices(stem)
        b = truth.ict_frame_vertices(neutral)
        region &= np.linalg.norm(a - b, axis=1) > threshold_mm
    ids = np.flatnonzero(region)
    cov = scan_coverage(tv[ids], truth.scan_index(stem), tol_mm=coverage_tol_mm)
    out = np.zeros(len(tv), bool)
    out[ids[cov]] = True
    truth._cache[key] = out
    return out


@dataclass(frozen=True)
class TruthEvaluation:
    """Error of a fitted skin against the truth mesh of one scan (mm).

    Attributes:
        stem: the scan.
        n_region: number of truth vertices in the evaluation region.
        error: region -> :class:`DistanceStats` of truth vertex -> fitted surface distances
            (``"all"``, ``"upper"``, ``"lower"``).
    """

    stem: str
    n_region: int
    error: dict[str, DistanceStats]

    @property
    def mean(self) -> float:
        """Mean error over the whole region, mm."""
        return self.error["all"].mean

    def to_dict(self) -> dict[str, Any]:
        return {
            "stem": self.stem,
            "n_region": self.n_region,
            "unit": "mm",
            "error": {k: v.to_dict() for k, v in self.error.items()},
        }


def evaluate_against_truth(
    fitted, truth: TruthSet, stem: str, *, region=None, **region_kw
) -> TruthEvaluation:
    """Distances from the truth vertices in the evaluation region to ``fitted`` (mm).

    Arguments:
        fitted: the candidate skin in the scan frame of ``stem`` (TriMesh / trimesh /
            ``(V, F)``), mm, any topology.
        truth: the :class:`TruthSet`.
        stem: the scan.
        region: optional ``(21451,)`` bool mask overriding :func:`evaluation_region`.
        region_kw: passed to :func:`evaluation_region`.
    """
    m = evaluation_region(truth, stem, **region_kw) if region is None else np.asarray(region, bool)
    tv = truth.truth_vertices(stem)
    pts = tv[m]
    d = SurfaceIndex.from_mesh(fitted).query(pts).distances
    out = {"all": DistanceStats.from_distances(d)}
    lm = truth.scan(stem).landmarks
    try:
        plane = FacePlane.from_landmarks(lm)
        up = plane.is_upper(pts)
        out["upper"] = DistanceStats.from_distances(d[up])
        out["lower"] = DistanceStats.from_distances(d[~up])
    except Exception:  # noqa: BLE001 - landmarks incomplete: whole region only
        pass
    return TruthEvaluation(stem=stem, n_region=int(m.sum()), error=out)


# --------------------------------------------------------------------------------------
# the ICT neutral as a registration template
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ICTTemplate:
    """The ICT-FaceKit neutral skin as a registration template (mm).

    Attributes:
        mesh: :class:`jaxface.mesh.TriMesh` of the face and head/neck groups.
        landmarks: the 22 Bosphorus landmarks at their ICT vertices (``truth.json``).
        face_mask: ``(V,)`` bool, the ICT face region (ICT ids < 9409).
        ict_ids: ``(V,)`` ICT vertex id of each template vertex.
    """

    mesh: Any
    landmarks: Any
    face_mask: np.ndarray
    ict_ids: np.ndarray


def ict_template(
    npz_path=None, truth: TruthSet | None = None, *, groups=("face", "head_neck")
) -> ICTTemplate:
    """Build the ICT neutral skin template from ``shared/data/ict/ict_face.npz``.

    Arguments:
        npz_path: the ``.npz``; default ``shared_path("data", "ict", "ict_face.npz")``.
        truth: the truth set (for the landmark vertex ids); default :func:`load_truth`.
        groups: ICT triangle groups forming the skin.
    """
    if npz_path is None:
        npz_path = shared_path("data", "ict", "ict_face.npz")
    truth = load_truth() if truth is None else truth
    d = np.load(npz_path)
    names = [str(g) for g in d["group_names"]]
    missing = [g for g in groups if g not in names]
    if missing:
        raise FitError(f"{npz_path}: unknown ICT triangle groups {missing}; have {names}.")
    gid = [names.index(g) for g in groups]
    tri_mask = np.isin(d["triangle_group"], gid)
    full = TriMesh(
        np.asarray(d["neutral"], np.float64), np.asarray(d["triangles"], np.int64), validate=False
    )
    mesh, old = full.submesh(tri_mask)
    ids = truth.landmark_vertex_ids
    lm_names = [n for n in ids if ids[n] in set(old.tolist())]
    lm = Landmarks(lm_names, np.asarray(d["neutral"], np.float64)[[ids[n] for n in lm_names]])
    return ICTTemplate(mesh=mesh, landmarks=lm, face_mask=old < ICT_FACE_VERTICES, ict_ids=old)
