"""Where the detector puts each Bosphorus label on the default head: its landmark definitions.

Units mm, in the default head's frame (:func:`jaxface.head.generic_head`: +y up, the face
along +z, the subject's left at +x).

The detector registers the default head's face onto a scan and carries points of the head
along (:mod:`jaxface.detect.transfer`). Which point of the head stands for a label is a
convention. The head's own landmarks (:attr:`jaxface.head.Head.landmarks`) follow the
anthropometric definitions: the nose tip is the most anterior point, the nose peaks lie on the
outer edge of the nasal alae. A labelled database follows its annotators' convention, and the
registration slides the template tangentially in a way the geometry does not see. Both make a
systematic offset at a label that no local refinement removes.

The definitions in ``data/landmark_definitions.json`` remove it, in two ways:

* **Points** for the labels on a smooth surface (:data:`CALIBRATED_LABELS`: the nose saddles,
  nose peaks, the outer lip midpoints and the chin): the point of the head the registration
  carries instead of the head's own landmark.
* **Offsets** for the labels found at a relief feature (:data:`jaxface.detect.features.
  FEATURE_LABELS`: the nose tip, the brows and the nose peaks, :mod:`jaxface.detect.features`):
  the offset from the feature to the label, in the head frame (x left, y up, z forward). The
  nose peaks have both: the point is where the search for the ala's edge starts, and where
  the label stays when the edge is not found.

Both are calibrated (:func:`jaxface.detect.calibrate.calibrate_definitions`) on labelled faces
that are not used to measure the detector: each face is registered exactly as the detector
registers a scan; each labelled point is mapped back through the registration onto the head
at rest, and the mean of the mapped points over the faces, moved onto the head's surface, is
the label's point; each feature's offset is the mean of the faces' offsets. The labels found
on the scan's slits (eye corners, mouth corners, inner lip midpoints:
:mod:`jaxface.detect.slits`) keep the head's own definitions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from ..atomic import write_json_atomic
from ..errors import DataNotFoundError
from ..landmarks import FACE_LABELS
from .features import FEATURE_LABELS

__all__ = [
    "CALIBRATED_LABELS",
    "LandmarkDefinitions",
    "load_definitions",
    "save_definitions",
]

#: labels on a smooth surface, placed by the registration alone: calibrated
CALIBRATED_LABELS: tuple[str, ...] = (
    "Nose saddle left",
    "Nose saddle right",
    "Left nose peak",
    "Right nose peak",
    "Upper lip outer middle",
    "Lower lip outer middle",
    "Chin middle",
)


@dataclass(frozen=True)
class LandmarkDefinitions:
    """Calibrated label positions on the default head (head frame, mm).

    Attributes:
        points: label -> ``(3,)`` position on the head's surface at rest, mm.
        spread_mm: label -> mean distance of the single faces' mapped points (or offsets)
            from the definition, mm (how much the faces and the registration disagree); for
            a label with both a point and an offset (the nose peaks), the offsets' spread.
        offsets_mm: label -> ``(3,)`` mean offset from the label's relief extremum
            (:func:`jaxface.detect.features.feature_extrema`) to the label, head frame (x
            left, y up, z forward), mm.
        faces: number of calibration faces.
        source: what the faces were and the command that produced the file.
    """

    points: dict[str, np.ndarray]
    spread_mm: dict[str, float] = field(default_factory=dict)
    offsets_mm: dict[str, np.ndarray] = field(default_factory=dict)
    faces: int = 0
    source: str = ""

    def __post_init__(self):
        _check(self.points, FACE_LABELS, "landmark definitions for unknown labels", "point")
        _check(
            self.offsets_mm,
            FEATURE_LABELS,
            "offsets for labels that are not relief features",
            "offset",
        )

    def _table(self, values: dict[str, np.ndarray], key: str) -> dict:
        return {
            n: {
                key: [round(float(x), 4) for x in values[n]],
                "spread_mm": round(float(self.spread_mm.get(n, 0.0)), 3),
            }
            for n in FACE_LABELS
            if n in values
        }

    def to_dict(self) -> dict:
        """JSON-ready (mm)."""
        return {
            "units": "mm",
            "frame": "default head (jaxface.head.generic_head): +y up, face along +z, left +x",
            "faces": self.faces,
            "source": self.source,
            "offsets": self._table(self.offsets_mm, "offset_mm"),
            "labels": self._table(self.points, "point_mm"),
        }


def _check(table: dict, allowed, unknown_message: str, what: str) -> None:
    """Raise ``ValueError`` for labels outside ``allowed`` or a value that is not a finite
    3-vector."""
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ValueError(f"{unknown_message}: {unknown}")
    for n, p in table.items():
        p = np.asarray(p, np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"the {what} of {n!r} is not a finite 3-vector: {p}")


def _default_path():
    return resources.files("jaxface").joinpath("data", "landmark_definitions.json")


def load_definitions(path=None) -> LandmarkDefinitions:
    """Read landmark definitions (default: the packaged calibration).

    Raises:
        DataNotFoundError: ``path`` does not exist.
        ValueError: the file is not a definitions file (unknown labels, non-finite points).
    """
    src = _default_path() if path is None else Path(path)
    if not src.is_file():
        raise DataNotFoundError(f"no landmark definitions file at {src}")
    raw = json.loads(src.read_text())
    labels = raw.get("labels")
    if not isinstance(labels, dict):
        raise ValueError(f"{src}: not a landmark definitions file (no 'labels' table)")
    offsets = raw.get("offsets") or {}
    return LandmarkDefinitions(
        points={n: np.asarray(d["point_mm"], np.float64) for n, d in labels.items()},
        spread_mm={
            n: float(d.get("spread_mm", 0.0)) for n, d in [*labels.items(), *offsets.items()]
        },
        offsets_mm={str(n): np.asarray(d["offset_mm"], np.float64) for n, d in offsets.items()},
        faces=int(raw.get("faces", 0)),
        source=str(raw.get("source", "")),
    )


def save_definitions(defs: LandmarkDefinitions, path) -> Path:
    """Write ``defs`` as JSON (atomically)."""
    return write_json_atomic(path, defs.to_dict())
