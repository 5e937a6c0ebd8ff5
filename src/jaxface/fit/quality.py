"""Quality checks of an expression fit: is the input usable, and which AUs are real?

Every fit (:func:`jaxface.fit.pipeline.fit_expressions`) carries a :class:`FitQuality`
(the ``quality`` key of ``<stem>.json``; ``jaxface fit`` prints its warnings). The fit still
completes on a poor input, with the warnings saying why its result is doubtful; only a
mirrored scan is refused before fitting (:func:`check_mirror`), since no fit of a mirror
image of the face means anything.

Checks (units mm; thresholds measured on ``shared/data/bosphorus_style``, see
``docs/input-checks.md`` for the table):

* **coverage**: the share of the registered face (fitted skin, face region) that has scan
  data within :data:`COVERAGE_DISTANCE_MM` and off the scan's border. Whole scans of the
  shared data cover 0.77-0.92 of the face region (the self-fit 0.92, a smile 0.84, another
  person's smile 0.77: the region reaches under the chin and toward the ears where a frontal
  scanner sees little); half of the smile's scan (x < 0) covers 0.42, a tenth of its
  triangles 0.09; a scan with 90 % of its grid points removed keeps almost no triangles (a
  range-grid cell needs three valid corners) and is refused before the fit
  (:func:`check_usable`). Warned below :data:`MIN_COVERAGE`: about half of a whole scan's
  coverage, where half of the face is fitted from no data.
* **mirror**: the handedness of the landmark frame (:func:`handedness`: the sign of the
  triple product of eye axis, face height and nose direction) of the expression scan must
  equal the neutral's. A rigid alignment cannot undo a reflection; a mirrored scan is
  refused (:class:`~jaxface.errors.FitError`).
* **identity**: the RMS difference (mm) of the mutual distances of the eye corners and nose
  saddles (:func:`identity_distance`) between the neutral's and the expression scan's
  landmarks: a rigid invariant of the bony upper face. Same subject: at most 0.57 mm on the
  shared data, another person: 3.5 mm and more; warned above :data:`IDENTITY_MAX_MM`. (A
  surface measure, the distance of the registered nose bridge to the scan after the rigid
  alignment, separates worse: the alignment fits exactly that region, so another person's
  smile came within 0.47 mm while the same person's nose wrinkle stood 1.0 mm off.)
* **noise floor**: the AU intensities of the *self-fit*, the subject's neutral scan fitted
  to itself with the same options (:func:`jaxface.fit.pipeline.fit_expressions` runs it once
  per subject): a scan without expression, so whatever it reports is the readout's bias for
  this subject (the registered neutral does not match the scan exactly, and the fit spends
  activations on that misfit). An AU whose intensity is at most :data:`NOISE_FACTOR` times
  its self-fit value cannot be told from that bias: it is listed in ``aus_within_noise`` and
  reported as 0 in ``au_intensities_above_noise``. A fit where every AU is within noise
  shows no expression (the self-fit itself, or a neutral of the same session).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import FitError

__all__ = [
    "COVERAGE_DISTANCE_MM",
    "MIN_COVERAGE",
    "MIN_USABLE_COVERAGE",
    "check_usable",
    "IDENTITY_LABELS",
    "NOISE_FACTOR",
    "IDENTITY_MAX_MM",
    "FitQuality",
    "handedness",
    "check_mirror",
    "coverage",
    "identity_distance",
    "assess",
]

#: Below this share of the face covered by the scan (before the fit: the registered neutral
#: moved into the scan's frame, whose mouth and brows an expression has moved away from the
#: scan, so whole scans give 0.6-0.9) the scan is refused as unusable: a scan with 90 % of its
#: grid points removed gives 0.001 on the shared data.
MIN_USABLE_COVERAGE = 0.05

#: A face vertex is covered when the scan surface lies within this distance (mm) of it: about
#: four times the 0.5 mm grid step of the scans, well above the fit residual (0.2-0.4 mm).
COVERAGE_DISTANCE_MM = 2.0

#: Least share of the face region covered by scan data before a warning (dimensionless).
MIN_COVERAGE = 0.45

#: The landmarks whose mutual distances the identity check compares: the eye corners and
#: the nose saddles sit on bone and cartilage that no expression deforms much (the nose tip,
#: moved 3.6 mm by a nose wrinkle, is left out).
IDENTITY_LABELS = (
    "Outer left eye corner",
    "Inner left eye corner",
    "Inner right eye corner",
    "Outer right eye corner",
    "Nose saddle left",
    "Nose saddle right",
)

#: Largest RMS difference (mm) of those distances for the same person. Measured on the
#: shared data: the same subject's scans differ by at most 0.57 mm (E_HAPPY: the squint moves
#: the outer eye corners), the other subject's by at least 3.49 mm; 2 mm lies between them
#: and leaves room for about 1.5 mm of landmark placement noise of hand-placed landmarks.
IDENTITY_MAX_MM = 2.0

#: An AU counts only when its intensity exceeds this many times its self-fit intensity: the
#: self-fit's bias comes from the misfit of the registered neutral, which another scan of the
#: same session repeats only roughly (scan noise, a slightly different alignment); a factor
#: of 2 keeps the bias of one scan from passing for an expression in the next.
NOISE_FACTOR = 2.0

_EYES = ("Outer left eye corner", "Outer right eye corner")
_NOSE = "Nose tip"
_LOW = ("Chin middle", "Upper lip outer middle", "Left mouth corner", "Right mouth corner")
_SADDLES = ("Nose saddle left", "Nose saddle right")


@dataclass
class FitQuality:
    """The quality report of one fit (the ``quality`` key of the JSON; mm).

    Attributes:
        coverage: share of the face region with scan data within
            :data:`COVERAGE_DISTANCE_MM` (0-1).
        identity_mm: :func:`identity_distance` of the neutral's and the scan's landmarks,
            mm (None when the landmarks are missing).
        noise_floor: AU -> intensity of the self-fit (empty when it was not run).
        aus_within_noise: AUs at most :data:`NOISE_FACTOR` times their self-fit intensity.
        au_intensities_above_noise: the AU intensities with those set to 0.
        handedness: ``(neutral, scan)`` handedness values (see :func:`handedness`).
        warnings: human-readable warnings (empty when all checks pass).
    """

    coverage: float
    identity_mm: float | None
    noise_floor: dict[str, float]
    aus_within_noise: list[str]
    au_intensities_above_noise: dict[str, float]
    handedness: tuple[float | None, float | None] = (None, None)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.warnings

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "coverage": float(self.coverage),
            "coverage_distance_mm": COVERAGE_DISTANCE_MM,
            "min_coverage": MIN_COVERAGE,
            "identity_mm": None if self.identity_mm is None else float(self.identity_mm),
            "identity_max_mm": IDENTITY_MAX_MM,
            "noise_floor": {k: float(v) for k, v in self.noise_floor.items()},
            "noise_factor": NOISE_FACTOR,
            "aus_within_noise": list(self.aus_within_noise),
            "au_intensities_above_noise": {
                k: float(v) for k, v in self.au_intensities_above_noise.items()
            },
            "handedness": {"neutral": self.handedness[0], "scan": self.handedness[1]},
            "warnings": list(self.warnings),
        }


def _lm(landmarks, name):
    try:
        return np.asarray(landmarks[name], dtype=np.float64)
    except (KeyError, TypeError):
        return None


def handedness(landmarks) -> float | None:
    """The normalised triple product ``det[e1, e2, e3] / (|e1| |e2| |e3|)`` in [-1, 1] of
    the eye axis ``e1`` (outer right -> outer left eye corner), the face height ``e2`` (the
    mean of the available mouth/chin landmarks -> the eyes' midpoint) and the nose direction
    ``e3`` (the eyes' midpoint -> nose tip). Rotations keep it, a reflection flips its sign:
    a face with the subject's left at +x looking along +z gives about +0.3 to +0.6.
    None when the landmarks needed are missing."""
    le, re_, nose = (_lm(landmarks, n) for n in (*_EYES, _NOSE))
    low = [p for p in (_lm(landmarks, n) for n in _LOW) if p is not None]
    if le is None or re_ is None or nose is None or not low:
        return None
    mid = 0.5 * (le + re_)
    e1, e2, e3 = le - re_, mid - np.mean(low, axis=0), nose - mid
    n = np.linalg.norm(e1) * np.linalg.norm(e2) * np.linalg.norm(e3)
    if not np.isfinite(n) or n <= 0:
        return None
    return float(np.linalg.det(np.stack([e1, e2, e3])) / n)


def check_mirror(neutral_landmarks, scan_landmarks, what: str = "the scan"):
    """Refuse an expression scan that is a mirror image of the neutral.

    Returns:
        ``(neutral handedness, scan handedness)`` (None where landmarks are missing).

    Raises:
        FitError: the handedness signs differ (:func:`handedness`).
    """
    hn, hs = handedness(neutral_landmarks), handedness(scan_landmarks)
    if hn is not None and hs is not None and np.sign(hn) != np.sign(hs):
        raise FitError(
            f"{what} is a mirror image of the neutral scan (landmark handedness {hs:+.2f} vs "
            f"{hn:+.2f}: left and right are swapped, or the scan was flipped). A rigid "
            "alignment cannot undo a reflection, so no fit would mean anything. Negate x of "
            "the scan and its landmarks (Landmarks.mirrored()) or fix its left/right labels."
        )
    return hn, hs


def check_usable(cov: float, what: str = "the scan") -> None:
    """Refuse a scan whose coverage (before the fit) is under :data:`MIN_USABLE_COVERAGE`.

    Raises:
        FitError: naming the coverage and what to do.
    """
    if not cov >= MIN_USABLE_COVERAGE:
        raise FitError(
            f"{what} covers only {cov:.1%} of the face (scan surface within "
            f"{COVERAGE_DISTANCE_MM:g} mm of the registered neutral after the rigid alignment, "
            f"at least {MIN_USABLE_COVERAGE:.0%} needed): it is too sparse or holey to fit "
            "(a range grid with most points removed keeps almost no triangles). Use a "
            "complete scan."
        )


def coverage(vertices, face_mask, scan_index, distance_mm: float = COVERAGE_DISTANCE_MM) -> float:
    """Share (0-1) of the face vertices ``vertices[face_mask]`` (mm, in the scan's frame)
    with a scan-surface point within ``distance_mm`` that is not on the scan's border.

    Args:
        vertices: ``(V, 3)`` mm. face_mask: ``(V,)`` bool.
        scan_index: :class:`jaxface.fit.metrics.SurfaceIndex` of the scan.
    """
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(face_mask, bool)]
    if len(v) == 0:
        return 0.0
    cp = scan_index.query(v, max_distance=2.0 * distance_mm)
    return float(np.mean((cp.distances <= distance_mm) & ~cp.on_boundary))


def identity_distance(neutral_landmarks, scan_landmarks) -> float | None:
    """RMS difference (mm) of the 15 distances between the four eye corners and the two nose
    saddles (:data:`IDENTITY_LABELS`) of two landmark sets: 0 for the same rigid shape, in
    any pose and after a reflection too. None when fewer than four of the labels are in both.
    """
    pairs = [(_lm(neutral_landmarks, n), _lm(scan_landmarks, n)) for n in IDENTITY_LABELS]
    both = [(p, q) for p, q in pairs if p is not None and q is not None]
    if len(both) < 4:
        return None
    a = np.stack([p for p, _ in both])
    b = np.stack([q for _, q in both])
    names = range(len(both))
    i, j = np.triu_indices(len(names), 1)
    da = np.linalg.norm(a[i] - a[j], axis=1)
    db = np.linalg.norm(b[i] - b[j], axis=1)
    return float(np.sqrt(np.mean((da - db) ** 2)))


def assess(
    *,
    fitted_vertices,
    face_mask,
    neutral_landmarks,
    scan_landmarks,
    scan_index,
    au_intensities: dict,
    noise_floor: dict | None,
    hands: tuple = (None, None),
) -> FitQuality:
    """All the checks of the module doc for one fit.

    Args:
        fitted_vertices: ``(V, 3)`` the fitted skin in the scan's frame, mm.
        face_mask: ``(V,)`` bool face region.
        neutral_landmarks, scan_landmarks: the landmarks of the neutral and the expression
            scan (mm, any frames).
        scan_index: SurfaceIndex of the expression scan.
        au_intensities: AU -> intensity.
        noise_floor: AU -> the self-fit's intensity (None or empty: no noise check).
        hands: the handedness pair from :func:`check_mirror`.
    """
    warn = []
    cov = coverage(fitted_vertices, face_mask, scan_index)
    if cov < MIN_COVERAGE:
        warn.append(
            f"the scan covers only {cov:.0%} of the face (scan data within "
            f"{COVERAGE_DISTANCE_MM:g} mm; at least {MIN_COVERAGE:.0%} expected): most of the "
            "fit is guessed, not measured. Use a complete scan."
        )
    ident = identity_distance(neutral_landmarks, scan_landmarks)
    if ident is not None and ident > IDENTITY_MAX_MM:
        warn.append(
            f"the eye corners and nose saddles of the scan are spaced {ident:.1f} mm (RMS) "
            f"differently from the neutral's (at most {IDENTITY_MAX_MM:g} mm for the same "
            "person): the scan may be of another person than the neutral. The AUs then "
            "describe the difference of two faces, not an expression."
        )
    floor = dict(noise_floor or {})
    within = (
        sorted(k for k, v in au_intensities.items() if float(v) <= NOISE_FACTOR * floor.get(k, 0.0))
        if floor
        else []
    )
    above = {k: (0.0 if k in within else float(v)) for k, v in au_intensities.items()}
    if floor and au_intensities and len(within) == len(au_intensities):
        top = max(au_intensities.items(), key=lambda kv: kv[1])
        warn.append(
            f"every AU is within the noise floor (at most {NOISE_FACTOR:g} times what the "
            f"neutral fitted to itself reports; strongest {top[0]} {top[1]:.2f}): no expression "
            "is detected; au_intensities_above_noise are all 0."
        )
    return FitQuality(
        coverage=cov,
        identity_mm=ident,
        noise_floor=floor,
        aus_within_noise=within,
        au_intensities_above_noise=above,
        handedness=tuple(hands),
        warnings=warn,
    )
