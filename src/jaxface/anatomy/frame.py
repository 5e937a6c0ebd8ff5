"""A face-local anatomical frame derived from the Bosphorus landmarks (NumPy, build time).

Everything anatomical in jaxface (jaw axes, skull estimate, muscle map) is defined relative to
the landmarks so that it fits any face. :class:`FaceFrame` turns the landmarks into

* an orthonormal frame: ``x`` toward the subject's left (from the right to the left eye
  corners), ``y`` up (the direction from the mouth corners to the eye corners,
  orthogonalised and tilted back about ``x`` by :data:`REFERENCE_TILT_DEG`, its angle to the
  vertical on the reference face), ``z = x cross y``
  forward (the direction the face looks); origin at the *eye centre*, the midpoint of the four
  eye corners moved onto the mid-sagittal plane;
* a per-axis scale ``(sx, sy, sz)`` (dimensionless) comparing this face with the reference
  face in which the offsets of the muscle map and the anatomical estimates are written. The
  reference proportions are those of the ICT-FaceKit generic identity: biocular width (outer
  eye corners) 89.2 mm and eye-centre to chin-middle height 94.3 mm; ``sz = sx``.

Offsets in *reference millimetres* ``(ox, oy, oz)`` map to world millimetres as
``origin + (o * scale) @ axes``.

Estimated points that are not among the Bosphorus landmarks (the thesis's MPEG-4 skull
landmarks) are placed at fixed reference offsets from the eye centre, calibrated on the
ICT-FaceKit head and on standard cephalometric proportions:

===================  =========================  ==============================================
point                reference offset (mm)      used for
===================  =========================  ==============================================
condyle (2.13/2.14)  (+-50, -28, -72)           jaw pitch axis (just in front of the ear)
top of skull (11.4)  (0, 112, -62)              jaw yaw axis (with the condyle midpoint)
top of spine (7.1)   (0, -40, -95)              jaw protrusion direction (with the chin)
gonion               (+-47, -95, -62)           mandible outline, tissue depth
menton               (0, -104, 10)              mandible outline, tissue depth
===================  =========================  ==============================================

When both ear-lobe landmarks are present the condyle estimate is averaged with one derived
from the lobes (the condyle lies about 25 mm above and 10 mm in front of the lobe, 72% of its
lateral distance from the midline), provided the two estimates agree within 20 mm.

Units: mm everywhere; +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import LandmarkError
from ..landmarks import FACE_LABELS

__all__ = [
    "FaceFrame",
    "face_frame",
    "face_axes",
    "AXIS_LABELS",
    "REQUIRED_LABELS",
    "REFERENCE_BIOCULAR_MM",
    "REFERENCE_EYE_TO_CHIN_MM",
    "mirror_label",
]

REFERENCE_BIOCULAR_MM = 89.2
REFERENCE_EYE_TO_CHIN_MM = 94.3
#: angle (degrees) between the mouth-to-eyes direction and the head's vertical on the
#: reference face (the mouth corners lie about 17 mm in front of the eye corners)
REFERENCE_TILT_DEG = 10.66

#: The landmarks the anatomical frame needs (the 22 face labels of Bosphorus, without ears).
REQUIRED_LABELS: tuple[str, ...] = FACE_LABELS

# reference offsets (mm in the reference face), left side (+x); the right side mirrors x
_CONDYLE = np.array([50.0, -28.0, -72.0])
_SKULL_TOP = np.array([0.0, 112.0, -62.0])
_SPINE_TOP = np.array([0.0, -40.0, -95.0])
_GONION = np.array([47.0, -95.0, -62.0])
_MENTON = np.array([0.0, -104.0, 10.0])


def mirror_label(label: str) -> str:
    """The label of the mirror-image landmark ("Outer left eyebrow" <-> "Outer right
    eyebrow", "Left mouth corner" <-> "Right mouth corner"); mid-line labels are unchanged."""
    out = []
    for word in label.split(" "):
        low = word.lower()
        if low == "left":
            out.append("right" if word.islower() else "Right")
        elif low == "right":
            out.append("left" if word.islower() else "Left")
        else:
            out.append(word)
    return " ".join(out)


def _get(landmarks, name: str) -> np.ndarray:
    try:
        p = landmarks[name]
    except (KeyError, IndexError) as e:  # LandmarkError derives from KeyError
        raise LandmarkError(
            f"landmark {name!r} is missing; the anatomical model needs the 22 Bosphorus face "
            f"landmarks {list(REQUIRED_LABELS)}. Add it to the landmark file.",
            missing=(name,),
        ) from e
    p = np.asarray(p, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(p)):
        raise LandmarkError(f"landmark {name!r} has non-finite coordinates {p}.", missing=(name,))
    return p


def _try_get(landmarks, name: str) -> np.ndarray | None:
    try:
        p = np.asarray(landmarks[name], dtype=np.float64).reshape(3)
    except (KeyError, IndexError, ValueError, TypeError):
        return None
    return p if np.all(np.isfinite(p)) else None


def _ear_lobe(landmarks, side: str) -> np.ndarray | None:
    for name in (
        f"{side.capitalize()} ear lobe",
        f"{side} ear lobe",
        f"Ear lobe {side}",
        f"{side.capitalize()} earlobe",
    ):
        p = _try_get(landmarks, name)
        if p is not None:
            return p
    return None


@dataclass(frozen=True)
class FaceFrame:
    """Landmark-derived anatomical frame of one face (NumPy, mm).

    Attributes:
        origin: ``(3,)`` the eye centre, mm.
        axes: ``(3, 3)`` rows are the unit x (subject's left), y (up), z (forward) axes.
        scale: ``(3,)`` per-axis ratio of this face to the reference face (dimensionless).
        points: named landmark positions used to build it, ``name -> (3,)`` mm.
        condyles: ``(2, 3)`` estimated condyle tips [left (+x), right], mm.
    """

    origin: np.ndarray
    axes: np.ndarray
    scale: np.ndarray
    points: dict = field(repr=False)
    condyles: np.ndarray = field(repr=False)

    # ------------------------------------------------------------------ conversions
    def to_world(self, local) -> np.ndarray:
        """Reference-mm offsets ``(..., 3)`` (x left, y up, z forward) -> world mm ``(..., 3)``."""
        local = np.asarray(local, dtype=np.float64)
        return self.origin + (local * self.scale) @ self.axes

    def to_local(self, world) -> np.ndarray:
        """World mm ``(..., 3)`` -> reference-mm offsets ``(..., 3)`` (inverse of to_world)."""
        world = np.asarray(world, dtype=np.float64)
        return ((world - self.origin) @ self.axes.T) / self.scale

    def direction_to_world(self, local_dir) -> np.ndarray:
        """A direction in the frame ``(..., 3)`` -> unit world direction ``(..., 3)``."""
        d = np.asarray(local_dir, dtype=np.float64) @ self.axes
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    @property
    def mean_scale(self) -> float:
        """Geometric mean of the three axis scales (dimensionless)."""
        return float(np.prod(self.scale) ** (1.0 / 3.0))

    # ------------------------------------------------------------------ anatomy
    def landmark(self, name: str) -> np.ndarray:
        """World position ``(3,)`` mm of a landmark used to build the frame."""
        return self.points[name]

    @property
    def condyle_mid(self) -> np.ndarray:
        """``(3,)`` midpoint of the two condyles, mm: the jaw's pivot."""
        return self.condyles.mean(axis=0)

    @property
    def skull_top(self) -> np.ndarray:
        """``(3,)`` estimated MPEG-4 11.4 (top of the skull), mm."""
        return self.to_world(_SKULL_TOP)

    @property
    def spine_top(self) -> np.ndarray:
        """``(3,)`` estimated MPEG-4 7.1 (top of the spine), mm."""
        return self.to_world(_SPINE_TOP)

    @property
    def gonions(self) -> np.ndarray:
        """``(2, 3)`` estimated jaw angles [left, right], mm."""
        g = _GONION
        return np.stack([self.to_world(g), self.to_world(g * [-1, 1, 1])])

    @property
    def menton(self) -> np.ndarray:
        """``(3,)`` estimated lowest point of the chin bone (under the chin), mm."""
        return self.to_world(_MENTON)

    @property
    def stomion(self) -> np.ndarray:
        """``(3,)`` midpoint of the inner lip landmarks (the mouth slit), mm."""
        return 0.5 * (self.points["Upper lip inner middle"] + self.points["Lower lip inner middle"])


#: The landmarks :func:`face_axes` needs.
AXIS_LABELS: tuple[str, ...] = (
    "Outer left eye corner",
    "Inner left eye corner",
    "Outer right eye corner",
    "Inner right eye corner",
    "Left mouth corner",
    "Right mouth corner",
    "Nose tip",
)


def face_axes(landmarks) -> np.ndarray:
    """The face's own directions in the landmarks' frame (unit rows, dimensionless).

    ``x`` toward the subject's left (from the right to the left eye corners), ``y`` up (the
    mouth-to-eyes direction, orthogonalised against ``x`` and tilted back about ``x`` by
    :data:`REFERENCE_TILT_DEG`, its angle to the vertical on the reference face), ``z = x cross
    y`` the direction the face looks.

    Args:
        landmarks: :class:`jaxface.landmarks.Landmarks` or a mapping ``name -> (3,)`` mm with
            :data:`AXIS_LABELS`.

    Returns:
        ``(3, 3)``: rows x, y, z.

    Raises:
        LandmarkError: a label is missing, the landmarks are degenerate, or mirrored (the
            nose tip behind the eyes).
    """
    missing = [n for n in AXIS_LABELS if _try_get(landmarks, n) is None]
    if missing:
        raise LandmarkError(f"the face's axes need the landmarks {missing}.", missing=missing)
    pts = {n: _get(landmarks, n) for n in AXIS_LABELS}
    lo, li = pts["Outer left eye corner"], pts["Inner left eye corner"]
    ro, ri = pts["Outer right eye corner"], pts["Inner right eye corner"]
    xdir = (lo - ro) + (li - ri)
    width = np.linalg.norm(lo - ro)
    if not np.isfinite(width) or width < 1e-6:
        raise LandmarkError("the outer eye corners coincide: the landmarks are degenerate.")
    x = xdir / np.linalg.norm(xdir)
    eye_mid = 0.25 * (lo + li + ro + ri)
    mouth_mid = 0.5 * (pts["Left mouth corner"] + pts["Right mouth corner"])
    up = eye_mid - mouth_mid
    y = up - x * (up @ x)
    ny = np.linalg.norm(y)
    if ny < 1e-6:
        raise LandmarkError("the mouth corners lie on the eye line: the landmarks are degenerate.")
    y /= ny
    z = np.cross(x, y)
    # the mouth lies in front of the eyes: tilt the mouth-to-eyes direction back by the
    # reference angle so that on the reference face the frame is the head's upright frame
    c, s = np.cos(np.radians(REFERENCE_TILT_DEG)), np.sin(np.radians(REFERENCE_TILT_DEG))
    y, z = c * y + s * z, c * z - s * y
    # the nose tip must be in front of the eyes; otherwise the input is mirrored (left at -x)
    if (pts["Nose tip"] - eye_mid) @ z < 0:
        raise LandmarkError(
            "the landmarks look mirrored: with the left eye corners at the subject's left (+x) "
            "and the eyes above the mouth, the nose tip points backwards. Check that 'left' "
            "landmarks are on the subject's left (+x) and that the face looks along +z."
        )
    return np.stack([x, y, z])


def face_frame(landmarks) -> FaceFrame:
    """Build the :class:`FaceFrame` of a face from its Bosphorus landmarks.

    Args:
        landmarks: a :class:`jaxface.landmarks.Landmarks` (or any mapping ``name -> (3,)`` mm)
            with at least :data:`REQUIRED_LABELS`; ear lobes are optional.

    Returns:
        the frame (NumPy).

    Raises:
        LandmarkError: a required landmark is missing (all missing names are listed), or the
            landmarks are mirrored (the left eye at -x) or degenerate.
    """
    missing = [n for n in REQUIRED_LABELS if _try_get(landmarks, n) is None]
    if missing:
        raise LandmarkError(
            f"the anatomical model needs the 22 Bosphorus face landmarks; missing: {missing}. "
            "Add them to the landmark file (labels are matched case-insensitively).",
            missing=missing,
        )
    pts = {n: _get(landmarks, n) for n in REQUIRED_LABELS}
    axes = face_axes(pts)
    x, y = axes[0], axes[1]
    lo, li = pts["Outer left eye corner"], pts["Inner left eye corner"]
    ro, ri = pts["Outer right eye corner"], pts["Inner right eye corner"]
    eye_mid = 0.25 * (lo + li + ro + ri)
    # origin: eye centre moved onto the mid-sagittal plane of the landmarks
    mids = [
        0.5 * (pts[a] + pts[b])
        for a, b in (
            ("Outer left eye corner", "Outer right eye corner"),
            ("Inner left eye corner", "Inner right eye corner"),
            ("Left mouth corner", "Right mouth corner"),
        )
    ] + [pts["Nose tip"], pts["Chin middle"], pts["Upper lip outer middle"]]
    mid_x = float(np.median([(m - eye_mid) @ x for m in mids]))
    origin = eye_mid + x * mid_x
    biocular = float((lo - ro) @ x)
    chin_h = float((origin - pts["Chin middle"]) @ y)
    if biocular <= 0 or chin_h <= 0:
        raise LandmarkError(
            "the landmarks are inconsistent: the chin must be below the eyes and the left eye "
            "corner at +x of the right one."
        )
    sx = biocular / REFERENCE_BIOCULAR_MM
    sy = chin_h / REFERENCE_EYE_TO_CHIN_MM
    scale = np.array([sx, sy, sx])
    frame = FaceFrame(origin=origin, axes=axes, scale=scale, points=pts, condyles=np.zeros((2, 3)))
    cond = np.stack([frame.to_world(_CONDYLE), frame.to_world(_CONDYLE * [-1, 1, 1])])
    lobes = [_ear_lobe(landmarks, "left"), _ear_lobe(landmarks, "right")]
    if all(lb is not None for lb in lobes):
        est = []
        for lb in lobes:
            loc = frame.to_local(lb)
            est.append(frame.to_world([0.72 * loc[0], loc[1] + 25.0, loc[2] + 10.0]))
        est = np.stack(est)
        if np.all(np.linalg.norm(est - cond, axis=1) < 20.0 * frame.mean_scale):
            cond = 0.5 * (cond + est)
    object.__setattr__(frame, "condyles", cond)
    return frame
