"""Settings of the inverse fit, in a few groups (lengths in mm, angles in degrees).

:class:`FitOptions` is the one object the CLI and :func:`jaxface.fit.pipeline.fit_expressions`
take. It inherits every field from the groups below, so each part of the fit can type the
group it reads (:func:`jaxface.fit.residuals.make_priors` a :class:`PriorOptions`,
:func:`jaxface.fit.inner.solve_inner` a :class:`SolverOptions`, ...). The maths behind each
setting is in ``docs/design/fit.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "AU_SPARSE_WEIGHT",
    "AU_MIN_MOTION_MM",
    "RESTART_ACTIVATION",
    "RESTART_BOUND_TOL",
    "RESTART_WHEN",
    "SamplingOptions",
    "SolverOptions",
    "PriorOptions",
    "CorrespondenceOptions",
    "OuterOptions",
    "ReadoutOptions",
    "FitOptions",
    "should_restart",
]

#: Default L1 weight of the AU readout's selection step (:func:`jaxface.fit.au_motion.read_aus`),
#: mm^2 of mean squared skin motion per unit intensity.
AU_SPARSE_WEIGHT = 0.02
#: Default pruning threshold of the AU readout (:func:`jaxface.fit.au_motion.read_aus`), mm: an
#: AU whose removal moves the readout's skin motion by less than this (RMS over the face
#: region, the rest solved again) is not reported: 0.05 mm is far below what a range scan
#: resolves (a 0.3-1 mm grid with noise of that order), so such an AU has no visible effect.
AU_MIN_MOTION_MM = 0.05
#: An activation at least ``1 - RESTART_BOUND_TOL`` counts as at the upper bound for the
#: bound-flip restart (:attr:`OuterOptions.restart_iterations`).
RESTART_BOUND_TOL = 0.02
#: The activation the bound-flip restart starts those activations from.
RESTART_ACTIVATION = 0.05
#: The values of :attr:`OuterOptions.restart_when`.
RESTART_WHEN = ("unconverged", "saturated")


def should_restart(when: str, saturated: bool, converged: bool) -> bool:
    """Whether a run restarts (:attr:`OuterOptions.restart_when`): it has activations at the
    upper bound (``saturated``) and, for ``"unconverged"``, its fit did not converge."""
    return saturated and (when == "saturated" or not converged)


@dataclass(frozen=True)
class SamplingOptions:
    """Which scan points the fit uses.

    Attributes:
        n_points: scan points per fit (fixed; padded when the scan has fewer).
        motion_fraction: share of ``n_points`` drawn from the expression's moving region (aligned
            scan points farther than ``motion_threshold_mm`` from the registered neutral), the
            rest evenly over the face; in [0, 1]. The neutral already matches the static face,
            so the data term weighs what the expression moves.
        motion_threshold_mm: distance (mm, >= 0) from the neutral above which a point moves;
            above the scan noise.
        seed: subsampling seed.
    """

    n_points: int = 1000
    motion_fraction: float = 0.5
    motion_threshold_mm: float = 0.3
    seed: int = 0

    def _check_sampling(self) -> None:
        if not 0.0 <= float(self.motion_fraction) <= 1.0:
            raise ValueError(
                f"FitOptions.motion_fraction must lie in [0, 1], got {self.motion_fraction!r}."
            )
        if not float(self.motion_threshold_mm) >= 0.0:
            raise ValueError(
                f"FitOptions.motion_threshold_mm must be >= 0 mm, got {self.motion_threshold_mm!r}."
            )


@dataclass(frozen=True)
class SolverOptions:
    """The inner Levenberg-Marquardt solves, their unknowns and the active set.

    Attributes:
        max_steps: Levenberg-Marquardt steps per inner solve.
        rtol, atol: optimistix convergence tolerances of the inner solves.
        init_activation: starting activation of every control (in [0, 1]).
        jaw_starts: starting jaw pitches (deg) of a multi-start (every start runs the whole fit,
            the lowest final robust point-to-plane cost wins). ``None``: one start per scan at
            the pitch whose reduced-model landmarks best match the scan's (1-degree grid).
        rigid: fit the 6-dof rigid correction ``x -> c + R (x - c) + t``.
        controls: fit only these controls (names); the others stay at 0. ``None``: all.
        exact_steps: Levenberg-Marquardt steps through the exact rig at the end (0 = none; each
            step costs a forward-mode Jacobian of the rig).
        gradient_correction: give every inner solve the exact rig's gradient at its start (one
            reverse-mode pass per scan and outer iteration), so fixed points are stationary
            points of the exact fit.
        release_gradient: dead band of the active set (mm^2 per unit activation): a bound is
            held when the cost gradient pushes outward by more, released when it points inside
            by more.
        active_set_rounds: inner re-solves per outer iteration while the set of activations held
            at a bound changes.
    """

    max_steps: int = 40
    rtol: float = 1e-3
    atol: float = 1e-4
    init_activation: float = 0.05
    jaw_starts: tuple[float, ...] | None = None
    rigid: bool = True
    controls: tuple[str, ...] | None = None
    exact_steps: int = 0
    gradient_correction: bool = True
    release_gradient: float = 5e-5
    active_set_rounds: int = 3


@dataclass(frozen=True)
class PriorOptions:
    """Weights of the landmark term and of the priors (see :func:`jaxface.fit.residuals.residuals`).

    Attributes:
        landmark_weight: ``lambda_lm``, weight of the mean squared landmark error relative to the
            mean squared point-to-plane error; small, because landmarks as 3-D targets also pull
            the skin against the surface's evidence.
        detected_landmark_weight: factor on ``landmark_weight`` for a scan whose landmarks, or
            whose neutral's, were detected from the scans' own surfaces (:mod:`jaxface.detect`).
            Such landmarks are a function of the surface the point term already fits, so they
            add the detector's error (2-4 mm per label) and no independent evidence; at the
            default 0 they still align the scans and set the jaw's starting pitch, but do not
            pull the skin.
        sparsity_weight: ``lambda_s`` (mm^2 per unit activation): L1 prior ``lambda_s a``.
        symmetry_weight: ``lambda_sym`` (mm^2 per unit activation^2).
        symmetry_scale: ``tau`` (unit activation, > 0): the symmetry prior
            ``lambda_sym tau^2 tanh^2((a_L - a_R) / tau)`` is quadratic below ``tau`` and lets
            go beyond it, so asymmetric expressions are not pulled to symmetry.
        rigid_weight: ridge on the rigid correction (mm^2 per deg^2 and per mm^2).
        jaw_weight: ridge on jaw yaw (deg) and protrusion (mm) (mm^2 per unit^2).
    """

    landmark_weight: float = 0.05
    detected_landmark_weight: float = 0.0
    sparsity_weight: float = 2e-4
    symmetry_weight: float = 1e-3
    symmetry_scale: float = 0.1
    rigid_weight: float = 1e-4
    jaw_weight: float = 1e-4


@dataclass(frozen=True)
class CorrespondenceOptions:
    """Matching scan points to the simulated skin (:func:`jaxface.fit.correspond.find_correspondences`).

    Attributes:
        max_distance_mm: rejection distance (mm), annealed from the first to the second value
            over the outer iterations (:meth:`OuterOptions.anneal`).
        robust_floor_mm: lower bound of the Tukey cut-off (mm), annealed likewise.
        max_normal_angle_deg: reject a match whose scan and skin normals differ by more (deg).
    """

    max_distance_mm: tuple[float, float] = (10.0, 4.0)
    robust_floor_mm: tuple[float, float] = (6.0, 1.5)
    max_normal_angle_deg: float = 60.0


@dataclass(frozen=True)
class OuterOptions:
    """The outer loop: correspondence refreshes, convergence, and the bound-flip restart.

    Attributes:
        outer_iterations: annealed correspondence refreshes (each one exact synthesis, and one
            reverse pass with ``gradient_correction``).
        extra_iterations: at most this many more iterations at the final annealing for a run
            still converging (see ``converge_*``), or whose active set still changed, or whose
            last inner solve stopped at ``max_steps``; each run stops on its own.
        converge_activation: a run still converges while an activation moves by more than this
            (unit activation) ...
        converge_jaw: ... or pitch / yaw by more than this (deg) or protrusion (mm) ...
        converge_cost: ... *and* its inner cost falls by more than this (relative) ...
        converge_cost_mm2: ... and by more than this (absolute, mm^2; the cost is a mean of
            squared distances). 1e-4 mm^2 is ``converge_cost`` of a cost of (0.1 mm)^2, a range
            scanner's noise: it acts only on fits already that close (synthetic scans), whose
            cost keeps falling by a few 1e-5 mm^2 an iteration without changing the face.
        restart_iterations: outer iterations of the bound-flip restart (0 = off): a run with
            activations at the upper bound (within :data:`RESTART_BOUND_TOL`) restarts with
            them at :data:`RESTART_ACTIVATION` and every activation free; the lower final cost
            wins. It leaves minima where a control saturated early.
        restart_when: which saturated runs restart: ``"unconverged"`` (only those whose fit did
            not converge) or ``"saturated"`` (all).
    """

    outer_iterations: int = 6
    extra_iterations: int = 6
    converge_activation: float = 5e-3
    converge_jaw: float = 0.05
    converge_cost: float = 0.01
    converge_cost_mm2: float = 1e-4
    restart_iterations: int = 2
    restart_when: str = "unconverged"

    def _check_outer(self) -> None:
        if self.restart_when not in RESTART_WHEN:
            raise ValueError(
                f"FitOptions.restart_when must be one of {RESTART_WHEN}, got {self.restart_when!r}."
            )

    def anneal(self, pair: tuple[float, float], k: int) -> float:
        """Value of an annealed ``(first, last)`` setting at outer iteration ``k``: geometric
        interpolation over ``outer_iterations`` (linear where a value is not positive)."""
        n = max(self.outer_iterations - 1, 1)
        s = min(max(k / n, 0.0), 1.0)
        a, b = float(pair[0]), float(pair[1])
        return float(a * (b / a) ** s) if a > 0 and b > 0 else a + (b - a) * s


@dataclass(frozen=True)
class ReadoutOptions:
    """The AU readouts of a fit (they read the fit, they do not change it).

    Attributes:
        au_sparse_weight: L1 weight of the AU readout's selection step
            (:func:`jaxface.fit.au_motion.read_aus`; mm^2 of mean squared skin motion per unit
            intensity, finite and >= 0).
        au_min_motion_mm: the readout's pruning threshold (mm, finite and >= 0): an AU whose
            removal moves the readout's skin motion by less than this is not reported.
    """

    au_sparse_weight: float = AU_SPARSE_WEIGHT
    au_min_motion_mm: float = AU_MIN_MOTION_MM

    def _check_readout(self) -> None:
        for name, unit in (
            ("au_sparse_weight", "mm^2 per unit intensity"),
            ("au_min_motion_mm", "mm"),
        ):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(
                    f"FitOptions.{name} must be a finite number >= 0 ({unit}), "
                    f"got {getattr(self, name)!r}."
                )


@dataclass(frozen=True)
class FitOptions(
    ReadoutOptions,
    OuterOptions,
    CorrespondenceOptions,
    PriorOptions,
    SolverOptions,
    SamplingOptions,
):
    """Every setting of the inverse fit: the fields of :class:`SamplingOptions`,
    :class:`SolverOptions`, :class:`PriorOptions`, :class:`CorrespondenceOptions`,
    :class:`OuterOptions` and :class:`ReadoutOptions` (see each for units and meaning).

    Raises:
        ValueError: ``au_sparse_weight`` or ``au_min_motion_mm`` not finite and >= 0, ``motion_fraction`` outside
            [0, 1], ``motion_threshold_mm`` < 0, or ``restart_when`` not in
            :data:`RESTART_WHEN`.
    """

    def __post_init__(self):
        self._check_readout()
        self._check_sampling()
        self._check_outer()
