"""Inverse fit: muscle activations, jaw pose and a small rigid correction from a scan (issue 7).

Units and frame: millimetres, degrees for angles; +y up; the face looks along +z; the
subject's left is +x. The fit works in the frame of the subject's *neutral scan* (where the
rig lives: the registered neutral is the rig's rest state); :mod:`jaxface.fit.pipeline` moves
expression scans into that frame first and the result back out.

Unknowns (one pytree ``y``, all smooth, no bounds needed):

* ``y["z"]`` ``(M,)``: activations ``a = sin^2(pi z / 2)`` in [0, 1], ordered as
  ``rig.muscle_names`` (:func:`activations_from_z`; smooth, bounded, and the bounds are
  reached at finite ``z``);
* ``y["jaw"]`` ``(3,)``: ``[pitch_deg, yaw_deg, protrusion_mm]`` of a
  :class:`~jaxface.anatomy.jaw.JawPose`; the rig's :class:`~jaxface.anatomy.jaw.JawModel`
  clamps them smoothly into its limits, and so does every model here;
* ``y["rigid"]`` ``(6,)`` (optional): ``[rotation vector (deg), translation (mm)]`` of a
  rigid correction ``x -> c + R (x - c) + t`` about the face centre ``c`` (the expression
  scan's alignment to the neutral is never exact where the expression moves the whole face).

Forward models (same call signature ``(a (M,), jaw (3,)) -> (N, 3) mm``):

* :class:`ForwardModel`: the rig itself (PBD :func:`jaxface.anatomy.synthesize`, or the LTW
  backend), jit-compiled once with the rig closed over; the *exact* quasi-static model.
* :class:`ResponseModel`: a reduced model of the same rig built from a few hundred
  syntheses (:func:`build_response_model`): per muscle, the displacement field at activation
  knots ``0, 1/L, ..., 1`` (jaw closed) interpolated by a cubic Hermite spline in the
  activation; for the jaw, the displacement field at pitch knots over the whole range with
  first and second derivatives in yaw and protrusion at each knot, interpolated in pitch; the
  contributions add. It costs microseconds instead of 50-300 ms per evaluation, and its
  forward-mode Jacobian costs milliseconds instead of 10-40 s (measured on the 2-core CPU:
  the rig's Jacobian by ``jax.jacfwd`` took 16-40 s per evaluation on the default head).

Residuals (:func:`residuals`), for ``K`` scan points and ``L`` landmarks:

* point-to-plane: ``sqrt(w_k) n_k . (S_k(y) - q_k)`` where ``q_k`` is a scan point, ``S_k`` the
  simulated skin point it corresponds to (a triangle id and barycentrics on the rig skin,
  fixed during an inner solve) and ``n_k`` the skin normal there; ``w_k`` are robust
  (Tukey) weights normalised to sum to 1, so the term is a weighted mean in mm^2;
* landmarks: ``sqrt(lambda_lm / L) (S_l(y) - q_l)`` with ``S_l`` the landmark's surface
  point on the rig skin;
* priors: sparsity ``sqrt(lambda_s) sin(pi z_i / 2)`` (its square is ``lambda_s a_i``: an L1
  penalty on the non-negative activations),
  left/right symmetry ``sqrt(lambda_sym) tau tanh((a_L - a_R) / tau)`` (``lambda_sym (a_L -
  a_R)^2`` for differences well under ``tau``; it saturates at ``lambda_sym tau^2`` where the
  data say the sides differ), and small ridges on the rigid correction and on jaw
  yaw/protrusion.

Solver (:func:`fit_points`): an outer loop refreshes correspondences (exact closest points of
the scan points on the current simulated skin, :class:`jaxface.fit.metrics.SurfaceIndex`,
NumPy) and robust weights; each inner solve is optimistix Levenberg-Marquardt (forward-mode
Jacobian, ``throw=False``) on the reduced model plus a *defect* ``d = x_exact(y_k) -
x_reduced(y_k)``, the exact rig's disagreement with the reduced model at the current iterate
(defect correction: at the fixed point the residuals are those of the exact rig, so the
reduced model only has to supply good derivatives). Good, not exact: the reduced model adds
the muscles' and the jaw's effects, which interact (up to several mm on the default head),
so the outer loop could settle where only the reduced gradient of the exact residuals
vanishes. :func:`gradient_correction` therefore gives each inner problem the exact rig's
gradient at its start (a rank-one term from one reverse-mode pass through the rig); its fixed
points are stationary points of the exact fit. Every outer iteration costs one exact
synthesis and that reverse pass. The reduced model's forward-mode derivative has a custom rule
(:func:`hermite_sum`): a Jacobian costs about one evaluation plus a small matrix product.

Bounds: ``a = sin^2(pi z / 2)`` has zero slope at both bounds, where Gauss-Newton steps
degenerate, so the bounds are handled as an *active set* (:func:`update_active_set`): after
each inner solve, an activation within 0.01 of a bound whose cost gradient pushes it outward
is held at the bound (its Jacobian column vanishes), and a held one whose gradient points
back inside is released; the inner solve is repeated (same correspondences) while the set
changes. An activation released and then held again stays held (anti-cycling: its optimum
lies within 0.01 of the bound, where each solve creeps and the set would flip for ever). At
the end the KKT conditions of the box hold, to that 0.01.

Jaw start: by default at the pitch whose reduced-model landmarks best match the scan's
landmarks; ``FitOptions.jaw_starts`` gives an explicit multi-start instead (all starts in
one batch, the best final cost wins). Optionally (``FitOptions.exact_steps``) a final
Levenberg-Marquardt solve runs through the exact rig's own forward-mode Jacobian. Batches of
scans (and starts) share their residual layout (padded, zero-weight residuals). On the CPU
one compiled single-scan solve is called per scan, each stopping at its own convergence, so
no batch size compiles anything new; the scans' solves, and their exact syntheses with the
reverse passes of the gradient correction, run on the outer thread pool
(:mod:`jaxface._parallel`), two at a time on a 2-core CPU, where one alone keeps about 1.7
cores busy (a batch of bs901's 11 scans: 6.6 s per scan, the same scans one at a time
8.2 s, the same fits to the last digit); on an accelerator
one ``jax.vmap`` solves them all in parallel, padded to a power of two
(:func:`padded_batch_size`) and, within one fit, to the size of all its runs, so the
subsets that go on compile nothing new. (A ``vmap`` of a while loop runs every member
for the largest number of steps in the batch; on the 2-core CPU a batch of 11 Bosphorus scans
took 5.5 s per scan with ``vmap`` and 3.3 s one after the other, same fits.)

Outer iterations: ``FitOptions.outer_iterations`` anneal the correspondence rejection; a scan
whose cost still falls while its activations or jaw still move goes on at the final annealing
for up to ``FitOptions.extra_iterations`` more, each scan stopping on its own.

Status is reported honestly (:class:`PointFit.status`): ``"successful"`` only when the last
inner solve met optimistix's tolerance, the active set is stable and the outer iterations
converged; otherwise the optimistix ``RESULTS`` name (e.g. ``"nonlinear_max_steps_reached"``),
``"active_set_changing"`` or ``"outer_not_converged"``. Every
inner solve is recorded (:class:`InnerReport`); non-finite parameters raise
:class:`jaxface.errors.FitError`.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._arrays import to_jax
from .._parallel import thread_map
from ..errors import FitError
from .au_motion import AU_SPARSE_WEIGHT
from .metrics import SurfaceIndex

__all__ = [
    "FitOptions",
    "ForwardModel",
    "ResponseModel",
    "build_response_model",
    "hermite_sum",
    "activations_from_z",
    "z_from_activations",
    "rotation_from_rotvec_deg",
    "apply_rigid",
    "PointSet",
    "gradient_correction",
    "Priors",
    "make_priors",
    "residuals",
    "solve_inner",
    "Correspondences",
    "find_correspondences",
    "InnerReport",
    "update_active_set",
    "effective_z",
    "PointFit",
    "fit_points",
    "jacobian_conditioning",
    "result_name",
]


# --------------------------------------------------------------------------------------
# options
# --------------------------------------------------------------------------------------
#: An activation at least ``1 - RESTART_BOUND_TOL`` counts as at the upper bound for the
#: bound-flip restart (:attr:`FitOptions.restart_iterations`).
RESTART_BOUND_TOL = 0.02
#: The activation the bound-flip restart starts those activations from.
RESTART_ACTIVATION = 0.05
#: The values of :attr:`FitOptions.restart_when`.
RESTART_WHEN = ("unconverged", "saturated")


def _should_restart(when: str, saturated: bool, converged: bool) -> bool:
    """Whether a run restarts (:attr:`FitOptions.restart_when`): it has activations at the
    upper bound (``saturated``) and, for ``"unconverged"``, its fit did not converge."""
    return saturated and (when == "saturated" or not converged)


@dataclass(frozen=True)
class FitOptions:
    """Settings of the inverse fit (lengths in mm, angles in degrees).

    Attributes:
        n_points: scan points per fit (fixed, padded; subsampled as ``motion_fraction``
            says).
        motion_fraction: share of the ``n_points`` drawn from the expression's moving region:
            the aligned scan's points farther than ``motion_threshold_mm`` from the registered
            neutral (as many as there are, up to this share); the rest are drawn evenly from
            all the scan's face points. The neutral already matches the static face, so the
            data term then weighs what the expression moves instead of the static area around
            it, which a model that cannot match every motion exactly otherwise trades it for.
            0: every point drawn evenly. 0.5 (default): 19 of the 20 Bosphorus-style scans at
            least twice as good as B0, where the even draw had 17 (README, How it works, for
            the figures; 0.75 drove bs901's jaw opening past 1 mm).
        motion_threshold_mm: see ``motion_fraction`` (mm; above the scans' noise, below the
            1 mm of the issue's evaluation region, because a point's distance to the neutral
            sees only the motion across the surface).
        outer_iterations: correspondence refreshes (each costs one exact synthesis, and one
            reverse-mode pass through the rig with ``gradient_correction``). 6: on the default
            head's synthetic round trip the 5th and 6th still lower the cost by 17 % and 2 %.
        max_steps: Levenberg-Marquardt steps per inner solve.
        rtol, atol: optimistix convergence tolerances of the inner solves.
        init_activation: the activations' starting value (``a(z0)``).
        jaw_starts: starting jaw pitches (deg) of a multi-start: every start runs the
            whole fit (in the same batch, so nothing is compiled twice) and the one
            with the lowest final robust point-to-plane cost on the exact skin wins.
            ``None`` (default): one start per scan, at the pitch whose reduced-model
            landmarks (activations 0) best match the scan's landmark targets, searched on a
            1-degree grid over the pitch limits. (On the shared data, starts at 0 and 8
            degrees reached the same minimum on every scan, at twice the cost.)
        rigid: fit the 6-dof rigid correction.
        landmark_weight: ``lambda_lm``: weight of the mean squared landmark error relative
            to the mean squared point-to-plane error. The landmarks steer the fit where the
            surface alone cannot (the lips' mid-line, the mouth corners), but as 3-D point
            targets they also hold the skin to where the template's landmark vertices land,
            against the surface's evidence. 0.05 fits the Bosphorus-style scans better than
            0.1 and keeps both synthetic round trips within 0.04, where 0.03 let the ICT
            face's converge into a trap (the sweep: README, "Landmarks weigh less than the
            surface"; ``bench_fit.py --landmark-weight``).
        sparsity_weight: ``lambda_s`` (mm^2 per unit activation).
        symmetry_weight: ``lambda_sym`` (mm^2 per unit activation^2).
        symmetry_scale: ``tau`` (unit activation, > 0): the left/right difference beyond which
            the symmetry prior lets go (it costs at most ``lambda_sym tau^2``; a large value
            gives the plain quadratic prior). A quadratic prior biases every asymmetric
            expression towards symmetry: on the synthetic round trips (corrugator R at 0.3,
            L at 0; sensitivity 0.08-0.1 mm per unit) it took about 0.03 off the right and
            put 0.02-0.03 on the left, as the muscles' sensitivities predict. Saturated at
            0.1, the default head's round trip recovers corrugator L within 0.002 and R
            within 0.014 (the sparsity prior's share, predicted 0.013), against 0.022 and
            0.049 before; the 20 Bosphorus-style scans' mean error went from 0.663 to
            0.658 mm (bs900's LFAU_12L 0.897 -> 0.943, bs901's LFAU_20 0.868 -> 0.828).
        rigid_weight: ridge on the rigid correction (mm^2 per deg^2 and per mm^2).
        jaw_weight: ridge on jaw yaw (deg) and protrusion (mm) (mm^2 per unit^2).
        max_distance_mm: rejection distance of the correspondences, annealed from the first
            to the second value over the outer iterations.
        robust_floor_mm: lower bound of the Tukey cut-off, annealed likewise.
        max_normal_angle_deg: reject correspondences whose scan and skin normals differ more.
        exact_steps: Levenberg-Marquardt steps through the exact rig at the end (0 = none;
            each step costs a forward-mode Jacobian of the rig: seconds to tens of seconds).
        gradient_correction: give every inner solve the exact rig's gradient at its start
            (:func:`gradient_correction`, one reverse-mode pass through the rig per scan and
            outer iteration), so that the fit cannot settle where only the reduced model's
            gradient vanishes.
        release_gradient: dead band of the active set (mm^2 per unit activation): an
            activation is held at a bound when the cost gradient pushes it outward by more
            than this, and released when it points inside by more than this.
        active_set_rounds: inner re-solves per outer iteration while the set of activations
            held at a bound changes (same correspondences).
        controls: fit only these controls (names); the others are held at 0. Default all.
        seed: subsampling seed.
        restart_iterations: outer iterations of the bound-flip restart (0 = off). A run that
            ends with activations at the upper bound (within ``RESTART_BOUND_TOL``) and
            meets ``restart_when`` is fitted again from there with those activations back at
            ``RESTART_ACTIVATION`` and every activation free, for this many more outer
            iterations at the final annealing (then, while still converging, for up to
            ``extra_iterations`` more); the lower final cost wins
            (:attr:`PointFit.restart`). It lets a fit leave a minimum where a control
            saturated early and the active set held it: started with every activation at
            0.9, a synthetic round trip on the default head ends with depressor labii
            inferioris L at 1 instead of 0 (cost 3.38e-3 mm^2, not converged), and with 4
            restart iterations at 8.85e-4 mm^2, 0.012 mm from its scan, that control back
            at 0 (the test's case; it ends in a lower-bound minimum at the left mouth
            corner, depressor anguli oris standing in for risorius).
            Restarting every saturated fit did not pay on the Bosphorus-style scans (model
            mismatch): the restarts found lower scan costs but
            not lower truth errors (bs900's 11 scans: mean 0.664 against 0.669 mm, LFAU_20
            0.781 against 0.745) at 1.3-3x the time, hence ``restart_when``.
        restart_when: which saturated runs restart. ``"unconverged"`` (default): only those
            whose fit did not converge (still moving after ``extra_iterations``, active set
            still changing, or the last inner solve at ``max_steps``: the statuses other than
            ``"successful"``). A fit crawling along a valley with controls at 1 is the trap's
            signature: the ICT face's synthetic round trip ends so, levator anguli oris at 1
            on both sides (true 0) against the depressor anguli oris, and the restart takes it
            to 0.0008 mm from its scan and within 0.024 of every activation; of the 20
            Bosphorus-style scans it restarts one (bs900's LFAU_12L, whose restart loses).
            ``"saturated"``: every run with activations at the upper bound.
        extra_iterations: at most this many more outer iterations, at the final annealing,
            for a scan still converging: in its last outer iteration the inner solve lowered
            the cost by more than ``converge_cost`` (relative) *and* the parameters moved by
            more than ``converge_activation`` (any activation) or ``converge_jaw`` (pitch or
            yaw in degrees, protrusion in mm). Each scan stops on its own; one still
            converging after them is reported as ``"outer_not_converged"``. Six annealed
            iterations alone left the default head's synthetic round trip 0.0047 mm from its
            scan with an activation 0.083 off, the sixth still lowering its cost by 8.8 %
            and moving an activation by 0.04. (Both tests are needed: on the Bosphorus-style
            scans activations wander by 0.05-0.3 per iteration along directions the cost
            hardly sees, the cost falling by well under 1 %, and following them lowered no
            truth error.) A scan whose active set of bounds was still changing after the
            ``active_set_rounds`` of its last iteration also goes on; one still changing at the
            end is reported as ``"active_set_changing"``. So does one whose last inner solve
            stopped at ``max_steps``: the next solve starts where it stopped (on the default
            head's synthetic surprise scan the fit stopped there with small spurious
            activations at twice the cost of the truth; four more iterations reached it).
        converge_activation: see ``extra_iterations`` (unit activation).
        converge_jaw: see ``extra_iterations`` (degrees and mm).
        converge_cost: see ``extra_iterations`` (relative decrease of the inner cost).
        au_sparse_weight: L1 weight of the sparse AU readout
            (:func:`jaxface.fit.au_motion.au_sparse`, mm^2 of mean squared skin motion per unit
            intensity; it reads the fit, it does not change it). 0.02 was chosen on the 20
            Bosphorus-style scans' fits from 0.005-0.05 (README, "AU readouts").
    """

    n_points: int = 1000
    motion_fraction: float = 0.5
    motion_threshold_mm: float = 0.3
    outer_iterations: int = 6
    max_steps: int = 40
    rtol: float = 1e-3
    atol: float = 1e-4
    init_activation: float = 0.05
    jaw_starts: tuple[float, ...] | None = None
    rigid: bool = True
    landmark_weight: float = 0.05
    sparsity_weight: float = 2e-4
    symmetry_weight: float = 1e-3
    symmetry_scale: float = 0.1
    rigid_weight: float = 1e-4
    jaw_weight: float = 1e-4
    max_distance_mm: tuple[float, float] = (10.0, 4.0)
    robust_floor_mm: tuple[float, float] = (6.0, 1.5)
    max_normal_angle_deg: float = 60.0
    exact_steps: int = 0
    gradient_correction: bool = True
    release_gradient: float = 5e-5
    active_set_rounds: int = 3
    controls: tuple[str, ...] | None = None
    seed: int = 0
    restart_iterations: int = 2
    restart_when: str = "unconverged"
    extra_iterations: int = 6
    converge_activation: float = 5e-3
    converge_jaw: float = 0.05
    converge_cost: float = 0.01
    au_sparse_weight: float = AU_SPARSE_WEIGHT

    def __post_init__(self):
        w = float(self.au_sparse_weight)
        if not (np.isfinite(w) and w >= 0.0):
            raise ValueError(
                f"FitOptions.au_sparse_weight must be a finite number >= 0 (mm^2 per unit "
                f"intensity), got {self.au_sparse_weight!r}."
            )
        if not 0.0 <= float(self.motion_fraction) <= 1.0:
            raise ValueError(
                f"FitOptions.motion_fraction must lie in [0, 1], got {self.motion_fraction!r}."
            )
        if not float(self.motion_threshold_mm) >= 0.0:
            raise ValueError(
                f"FitOptions.motion_threshold_mm must be >= 0 mm, got {self.motion_threshold_mm!r}."
            )
        if self.restart_when not in RESTART_WHEN:
            raise ValueError(
                f"FitOptions.restart_when must be one of {RESTART_WHEN}, got {self.restart_when!r}."
            )

    def anneal(self, pair: tuple[float, float], k: int) -> float:
        """Value of an annealed ``(first, last)`` setting at outer iteration ``k``
        (geometric interpolation)."""
        n = max(self.outer_iterations - 1, 1)
        s = min(max(k / n, 0.0), 1.0)
        a, b = float(pair[0]), float(pair[1])
        return float(a * (b / a) ** s) if a > 0 and b > 0 else a + (b - a) * s


# --------------------------------------------------------------------------------------
# parameterisation
# --------------------------------------------------------------------------------------
def activations_from_z(z):
    """Activations ``(M,)`` in [0, 1] from the unconstrained parameters:
    ``a = sin^2(pi z / 2)``.

    Why not a sigmoid: the bounds are reached at *finite* parameters (``z = 0`` and
    ``z = 1``, where ``da/dz = 0``), so a muscle that the data would drive past 0 or 1
    settles there instead of running away to infinity (a sigmoid's ``z`` keeps growing with
    steps of O(1) and the solver never meets its tolerance); and ``sqrt(lambda) sin(pi z /
    2)`` is a smooth residual whose square is the L1 sparsity prior ``lambda a``."""
    return jnp.sin(0.5 * jnp.pi * z) ** 2


def z_from_activations(a, eps: float = 0.0):
    """Inverse of :func:`activations_from_z` on ``z`` in [0, 1] (activations clipped to
    ``[eps, 1 - eps]``)."""
    a = jnp.clip(to_jax(a), eps, 1.0 - eps)
    return (2.0 / jnp.pi) * jnp.arcsin(jnp.sqrt(a))


def rotation_from_rotvec_deg(w_deg):
    """Rotation matrix ``(3, 3)`` of a rotation vector ``(3,)`` in degrees (Rodrigues;
    NaN-safe at 0 in value and gradient: a Taylor series below 1e-6 rad)."""
    w = to_jax(w_deg) * (jnp.pi / 180.0)
    th2 = jnp.sum(w * w)
    small = th2 < 1e-12
    th2s = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2s)
    A = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    B = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / th2s)
    z = jnp.zeros((), w.dtype)
    K = jnp.array([[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]])
    return jnp.eye(3, dtype=w.dtype) + A * K + B * (K @ K)


def apply_rigid(rigid, centre, x):
    """``c + R (x - c) + t`` for ``rigid = [rotvec_deg (3), t_mm (3)]``, ``x`` ``(N, 3)`` mm."""
    R = rotation_from_rotvec_deg(rigid[:3])
    return centre + (x - centre) @ R.T + rigid[3:]


def rigid_numpy(rigid, centre) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` with ``x -> R x + t`` equal to :func:`apply_rigid` (NumPy)."""
    R = np.asarray(rotation_from_rotvec_deg(to_jax(np.asarray(rigid, np.float64)[:3])))
    c = np.asarray(centre, np.float64)
    return R, c - R @ c + np.asarray(rigid, np.float64)[3:]


# --------------------------------------------------------------------------------------
# the exact forward model
# --------------------------------------------------------------------------------------
def _synth_fn(rig) -> Callable:
    """``(a (M,), jaw (3,)) -> (V, 3)`` for a PBD :class:`~jaxface.anatomy.rig.Rig` or an
    LTW rig."""
    from ..anatomy.jaw import JawPose

    try:
        from ..ltw.rig import LTWRig, synthesize_ltw
    except ImportError:  # pragma: no cover - the LTW backend is optional
        LTWRig, synthesize_ltw = (), None
    if LTWRig and isinstance(rig, LTWRig):
        return lambda a, j: synthesize_ltw(rig, a, JawPose.from_array(j))
    from ..anatomy.rig import synthesize

    return lambda a, j: synthesize(rig, a, JawPose.from_array(j))


class ForwardModel:
    """The rig's quasi-static synthesis, jit-compiled once with the rig closed over.

    Arguments:
        rig: a :class:`jaxface.anatomy.rig.Rig` (or an LTW rig), mm.
        chunk: how many syntheses :meth:`many` dispatches before it waits for their results.

    Calling ``model(a (M,), jaw (3,))`` returns the ``(V, 3)`` skin in mm (NumPy).
    :meth:`many` evaluates a batch one synthesis at a time through the same compiled
    function, so any batch size costs one compilation and no padding. On the 2-core CPU a
    ``vmap`` of the PBD solve was 4x slower per item than a loop, and a ``lax.map`` over a
    padded chunk of 8 cost the same per item as this loop (0.042 vs 0.043 s on bs901's rig)
    but made a single scan pay for 8 (0.34 s per call instead of 0.043 s).
    """

    def __init__(self, rig, *, chunk: int = 8):
        self.rig = rig
        self.n_controls = int(rig.n_controls)
        self.muscle_names = tuple(rig.muscle_names)
        self.chunk = int(chunk)
        fn = _synth_fn(rig)
        self._fn = fn
        self._one = jax.jit(fn)
        self.calls = 0
        self._count_lock = threading.Lock()  # with_vjp runs on several threads in a batch

    def _count(self, n: int = 1) -> None:
        with self._count_lock:
            self.calls += n

    @property
    def triangles(self) -> np.ndarray:
        return np.asarray(self.rig.triangles)

    @property
    def rest(self) -> np.ndarray:
        return np.asarray(self.rig.rest)

    def __call__(self, a, jaw) -> np.ndarray:
        self._count()
        dt = jnp.result_type(float)  # float64 when x64 is enabled, else float32
        return np.asarray(self._one(jnp.asarray(a, dt), jnp.asarray(jaw, dt)))

    def with_vjp(self, a, jaw):
        """The skin ``(V, 3)`` mm (a JAX array) at ``a (M,)``, ``jaw (3,)`` and its VJP
        (:func:`exact_skin_and_vjp`, compiled once): one synthesis, counted in ``calls``."""
        self._count()
        dt = jnp.result_type(float)
        return _exact_vjp_jit(self._fn, jnp.asarray(a, dt), jnp.asarray(jaw, dt))

    def many(self, A, J) -> np.ndarray:
        """``(B, V, 3)`` mm for activations ``(B, M)`` and jaw poses ``(B, 3)``."""
        A = np.asarray(A, np.float64).reshape(-1, self.n_controls)
        J = np.asarray(J, np.float64).reshape(-1, 3)
        if len(A) != len(J):
            raise FitError(
                f"many() needs one jaw pose per activation row; got {len(J)} jaw poses for "
                f"{len(A)} rows."
            )
        dt = jnp.result_type(float)  # float64 when x64 is enabled, else float32
        out = np.zeros((len(A), len(self.rest), 3))
        step = max(self.chunk, 1)
        for s in range(0, len(A), step):
            # dispatch a chunk asynchronously, then collect it
            pending = [
                self._one(jnp.asarray(a, dt), jnp.asarray(j, dt))
                for a, j in zip(A[s : s + step], J[s : s + step])
            ]
            for n, x in enumerate(pending):
                out[s + n] = np.asarray(x)
            self._count(len(pending))
        return out


# --------------------------------------------------------------------------------------
# the reduced (response) model
# --------------------------------------------------------------------------------------
def _hermite_basis(x, knots):
    """Segment ``s`` ``(M,)`` of every abscissa ``x`` ``(M,)`` among the ``knots`` ``(N,)``,
    and the weights ``w`` / their ``x``-derivatives ``dw`` ``(M, 4)`` of the values at knots
    ``s`` and ``s + 1`` and the slopes there (cubic Hermite; linear continuation with the end
    slope beyond the knot range)."""
    t = knots
    n = t.shape[0]
    xc = jnp.clip(x, t[0], t[-1])
    s = jnp.clip(jnp.searchsorted(t, xc, side="right") - 1, 0, n - 2)  # (M,)
    h = t[s + 1] - t[s]
    u = (xc - t[s]) / h
    u2, u3 = u * u, u * u * u
    below = (x < t[0]).astype(x.dtype)
    above = (x > t[-1]).astype(x.dtype)
    inside = 1.0 - below - above
    e = x - xc  # linear continuation beyond the ends
    w = jnp.stack(
        [
            2 * u3 - 3 * u2 + 1,
            -2 * u3 + 3 * u2,
            (u3 - 2 * u2 + u) * h + e * below,
            (u3 - u2) * h + e * above,
        ],
        axis=1,
    )
    dw = jnp.stack(
        [
            (6 * u2 - 6 * u) / h * inside,
            (-6 * u2 + 6 * u) / h * inside,
            (3 * u2 - 4 * u + 1) * inside + below,
            (3 * u2 - 2 * u) * inside + above,
        ],
        axis=1,
    )
    return s, w, dw


def _hermite_parts(x, knots, values, slopes):
    """Value ``(K, 3)`` of ``sum_m H_m(x_m)`` and the derivative fields ``dH_m/dx_m``
    ``(M, K, 3)`` (see :func:`hermite_sum`)."""
    s, w, dw = _hermite_basis(x, knots)
    idx = s[:, None, None, None]
    Y0 = jnp.take_along_axis(values, idx, axis=1)[:, 0]
    Y1 = jnp.take_along_axis(values, idx + 1, axis=1)[:, 0]
    m0 = jnp.take_along_axis(slopes, idx, axis=1)[:, 0]
    m1 = jnp.take_along_axis(slopes, idx + 1, axis=1)[:, 0]
    val = (
        jnp.einsum("m,mkd->kd", w[:, 0], Y0)
        + jnp.einsum("m,mkd->kd", w[:, 1], Y1)
        + jnp.einsum("m,mkd->kd", w[:, 2], m0)
        + jnp.einsum("m,mkd->kd", w[:, 3], m1)
    )
    D = (
        dw[:, 0, None, None] * Y0
        + dw[:, 1, None, None] * Y1
        + dw[:, 2, None, None] * m0
        + dw[:, 3, None, None] * m1
    )
    return val, D


@jax.custom_jvp
def hermite_sum(x, knots, values, slopes):
    """``sum_m H_m(x_m)``: cubic Hermite splines, one per row, summed.

    Arguments:
        x: ``(M,)`` abscissae (one per spline).
        knots: ``(N,)`` increasing knots shared by the splines.
        values, slopes: ``(M, N, K, 3)`` values and slopes at the knots.

    Returns:
        ``(K, 3)``. Beyond the knot range each spline continues linearly with its end slope.

    The forward-mode derivative has a custom rule: with respect to ``x`` it is
    ``sum_m dx_m dH_m/dx_m``, whose fields are computed once per evaluation, so a
    ``jax.jacfwd`` over ``T`` tangents costs one evaluation plus a ``(T, M) x (M, 3K)``
    product instead of ``T`` evaluations (the fitter's Jacobian). Tangents of the tables
    fall back to plain autodiff.
    """
    return _hermite_parts(x, knots, values, slopes)[0]


def _hermite_sum_jvp(primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    x, knots, values, slopes = primals
    dx, dk, dv, ds = tangents
    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    if not (zero(dk) and zero(dv) and zero(ds)):
        inst = [jnp.zeros_like(p) if zero(t) else t for p, t in zip(primals, tangents)]
        return jax.jvp(lambda *a: _hermite_parts(*a)[0], primals, tuple(inst))
    val, D = _hermite_parts(x, knots, values, slopes)
    if zero(dx):
        return val, jnp.zeros_like(val)
    return val, jnp.einsum("m,mkd->kd", dx, D)


hermite_sum.defjvp(_hermite_sum_jvp, symbolic_zeros=True)


def _hermite_slopes(knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Three-point slopes of ``values`` ``(N, ...)`` at non-uniform ``knots`` ``(N,)``."""
    t = np.asarray(knots, np.float64)
    y = np.asarray(values, np.float64)
    n = len(t)
    m = np.zeros_like(y)
    h = np.diff(t)
    d = np.diff(y, axis=0) / h.reshape((-1,) + (1,) * (y.ndim - 1))
    if n == 2:
        m[:] = d[0]
        return m
    for k in range(1, n - 1):
        a, b = h[k - 1], h[k]
        m[k] = (b * d[k - 1] + a * d[k]) / (a + b)
    m[0] = 2 * d[0] - m[1]
    m[-1] = 2 * d[-1] - m[-2]
    return m


class ResponseModel(eqx.Module):
    """Reduced model of a rig over ``P`` points (vertices, or surface points after
    :meth:`gather`), mm.

    ``x(a, jaw) = rest + J(jaw) + sum_i H_i(a_i)`` with ``H_i`` the Hermite interpolant of
    muscle ``i``'s displacement at the activation knots (jaw closed) and
    ``J = X(p) + y Dy(p) + y^2/2 Dyy(p) + q Dq(p) + q^2/2 Dqq(p)`` for the clamped pitch
    ``p`` (deg), yaw ``y`` (deg) and protrusion ``q`` (mm), each field interpolated in ``p``.

    Attributes:
        rest: ``(P, 3)`` mm.
        levels: ``(NL,)`` activation knots (``levels[0] = 0``).
        mus, mus_slope: ``(M, NL, P, 3)`` displacements (mm) and their activation slopes.
        pitch: ``(NJ,)`` pitch knots (deg, effective = after the jaw's smooth clamp).
        jaw_tab, jaw_slope: ``(NJ, 5, P, 3)`` fields ``[X, Dy, Dyy, Dq, Dqq]`` (mm, mm/deg,
            mm/deg^2, mm/mm, mm/mm^2) and their pitch slopes.
        jaw: the rig's :class:`~jaxface.anatomy.jaw.JawModel` (for the smooth clamp).
        sampled: static ``(M,)`` bools: controls whose tables were sampled (the others are
            zero and must stay at activation 0).
    """

    rest: jax.Array
    levels: jax.Array
    mus: jax.Array
    mus_slope: jax.Array
    pitch: jax.Array
    jaw_tab: jax.Array
    jaw_slope: jax.Array
    jaw: Any
    sampled: tuple = eqx.field(static=True, default=())

    @property
    def n_points(self) -> int:
        return int(self.rest.shape[0])

    def clamp_jaw(self, jaw):
        """Effective ``(3,)`` jaw pose after the rig's smooth limits."""
        from ..anatomy.jaw import JawPose

        p = self.jaw.clamp(JawPose.from_array(jaw))
        return jnp.stack([p.pitch_deg, p.yaw_deg, p.protrusion_mm])

    def displacement(self, a, jaw):
        """``(P, 3)`` displacement from rest, mm, for ``a`` ``(M,)`` in [0, 1] and ``jaw``
        ``(3,)`` (forward-mode derivatives through :func:`hermite_sum`'s custom rule)."""
        return hermite_sum(a, self.levels, self.mus, self.mus_slope) + self.jaw_displacement(jaw)

    def jaw_displacement(self, jaw):
        """``(P, 3)`` the jaw's part of :meth:`displacement`, mm (``jaw`` ``(3,)``: pitch
        deg, yaw deg, protrusion mm, before the smooth clamp)."""
        j = self.clamp_jaw(jaw)
        nj, nf, P = self.jaw_tab.shape[:3]
        F = hermite_sum(
            j[:1],
            self.pitch,
            self.jaw_tab.reshape(1, nj, nf * P, 3),
            self.jaw_slope.reshape(1, nj, nf * P, 3),
        ).reshape(nf, P, 3)
        y, q = j[1], j[2]
        return F[0] + y * F[1] + (0.5 * y * y) * F[2] + q * F[3] + (0.5 * q * q) * F[4]

    def __call__(self, a, jaw):
        """``(P, 3)`` positions, mm."""
        return self.rest + self.displacement(a, jaw)

    def muscle_terms(self, muscles, values):
        """``(T, P, 3)``: term ``t`` is muscle ``muscles[t]``'s own displacement at activation
        ``values[t]`` less its displacement at activation 0, mm (the model is additive, so a
        displacement is a sum of such terms; :func:`jaxface.fit.au_motion.au_motion` evaluates
        only the few terms each AU has instead of every muscle's).

        Arguments:
            muscles: ``(T,)`` control indices; values: ``(T,)`` activations.
        """
        s, w, _ = _hermite_basis(values, self.levels)
        s0, w0, _ = _hermite_basis(jnp.zeros_like(values), self.levels)

        def spline(seg, wt):
            return (
                wt[:, 0, None, None] * self.mus[muscles, seg]
                + wt[:, 1, None, None] * self.mus[muscles, seg + 1]
                + wt[:, 2, None, None] * self.mus_slope[muscles, seg]
                + wt[:, 3, None, None] * self.mus_slope[muscles, seg + 1]
            )

        return spline(s, w) - spline(s0, w0)

    def gather(self, ids, bary) -> ResponseModel:
        """The model at surface points: ``ids`` ``(K, 3)`` local point ids of triangle
        corners, ``bary`` ``(K, 3)`` barycentrics. Returns a :class:`ResponseModel` over
        the ``K`` points."""
        ids = to_jax(ids)
        b = jnp.asarray(bary, self.rest.dtype)

        def g(arr, axis):
            taken = jnp.take(arr, ids, axis=axis)  # (..., K, 3, 3)
            return jnp.einsum("...kcd,kc->...kd", taken, b)

        return ResponseModel(
            rest=g(self.rest, 0),
            levels=self.levels,
            mus=g(self.mus, 2),
            mus_slope=g(self.mus_slope, 2),
            pitch=self.pitch,
            jaw_tab=g(self.jaw_tab, 2),
            jaw_slope=g(self.jaw_slope, 2),
            jaw=self.jaw,
            sampled=self.sampled,
        )


_gather_jit = eqx.filter_jit(lambda m, ids, bary: m.gather(ids, bary))
_eval_jit = eqx.filter_jit(lambda m, a, j: m(a, j))


def build_response_model(
    forward: ForwardModel,
    point_ids=None,
    *,
    levels: int = 4,
    pitch_knots: int = 12,
    yaw_step_deg: float = 2.5,
    protrusion_step_mm: float = 2.0,
    controls: Sequence[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ResponseModel:
    """Sample the rig and build its :class:`ResponseModel` over ``point_ids`` (vertex ids,
    default all vertices).

    Syntheses: ``M * levels`` (each muscle alone at ``1/levels, ..., 1``, jaw closed) plus
    ``5 * pitch_knots`` (pitch knots over the jaw's limits; at each, yaw ``+-h`` and
    protrusion ``h, 2h``).

    Arguments:
        forward: the :class:`ForwardModel` of the rig.
        point_ids: ``(P,)`` vertex ids to keep (default all).
        levels: activation knots above 0.
        pitch_knots: number of pitch knots (over the jaw's pitch limits).
        yaw_step_deg, protrusion_step_mm: finite-difference steps.
        controls: only sample these controls (names; default all); the others get zero
            tables and must stay at 0 (:attr:`ResponseModel.sampled`, ``FitOptions.controls``).
        progress: called as ``progress(done, total)`` after each batch of syntheses.

    Raises:
        FitError: a synthesis produced NaN/inf.
    """
    from ..anatomy.jaw import smooth_clamp

    rig = forward.rig
    M = forward.n_controls
    rest_all = forward.rest
    ids = np.arange(len(rest_all)) if point_ids is None else np.asarray(point_ids, np.int64)
    lv = np.linspace(0.0, 1.0, int(levels) + 1)
    jm = rig.jaw
    plo, phi = jm.pitch_limits
    raw_p = np.linspace(plo - 1.0, phi + 1.0, int(pitch_knots))  # clamped: just inside the limits
    eff_p = np.asarray(smooth_clamp(to_jax(raw_p), plo, phi, jm.softness_deg))
    hy, hq = float(yaw_step_deg), float(protrusion_step_mm)
    names = list(forward.muscle_names)
    if controls is None:
        sampled = list(range(M))
    else:
        unknown = [c for c in controls if c not in names]
        if unknown:
            raise FitError(f"unknown controls {unknown}; the rig's controls are {names}.")
        sampled = sorted(names.index(c) for c in controls)
    A, J = [], []
    for i in sampled:
        for v in lv[1:]:
            a = np.zeros(M)
            a[i] = v
            A.append(a)
            J.append(np.zeros(3))
    jaw_offsets = [(0.0, 0.0), (hy, 0.0), (-hy, 0.0), (0.0, hq), (0.0, 2 * hq)]
    for p in raw_p:
        for y, q in jaw_offsets:
            A.append(np.zeros(M))
            J.append(np.array([p, y, q]))
    A = np.stack(A)
    J = np.stack(J)
    total = len(A)
    out = np.zeros((total, len(ids), 3))
    step = max(forward.chunk, 1)
    for s in range(0, total, step):
        x = forward.many(A[s : s + step], J[s : s + step])
        out[s : s + len(x)] = x[:, ids]
        if progress is not None:
            progress(min(s + step, total), total)
    if not np.all(np.isfinite(out)):
        bad = np.flatnonzero(~np.isfinite(out).all(axis=(1, 2)))
        raise FitError(
            f"the rig produced NaN/inf in {bad.size} of {total} syntheses (first rows "
            f"{bad[:5].tolist()}); the reduced model cannot be built."
        )
    rest = rest_all[ids]
    nl = len(lv)
    mus = np.zeros((M, nl, len(ids), 3))
    ns = len(sampled)
    mus[sampled, 1:] = out[: ns * levels].reshape(ns, levels, len(ids), 3) - rest
    mus_slope = np.stack([_hermite_slopes(lv, mus[i]) for i in range(M)])
    jt = out[ns * levels :].reshape(len(raw_p), len(jaw_offsets), len(ids), 3)
    f0, fyp, fym, fq1, fq2 = (jt[:, k] for k in range(5))
    tab = np.stack(
        [
            f0 - rest,
            (fyp - fym) / (2 * hy),
            (fyp - 2 * f0 + fym) / hy**2,
            (-3 * f0 + 4 * fq1 - fq2) / (2 * hq),
            (f0 - 2 * fq1 + fq2) / hq**2,
        ],
        axis=1,
    )
    tab_slope = _hermite_slopes(eff_p, tab)
    return ResponseModel(
        rest=to_jax(rest),
        levels=to_jax(lv),
        mus=to_jax(mus),
        mus_slope=to_jax(mus_slope),
        pitch=to_jax(eff_p),
        jaw_tab=to_jax(tab),
        jaw_slope=to_jax(tab_slope),
        jaw=jm,
        sampled=tuple(bool(i in set(sampled)) for i in range(M)),
    )


# --------------------------------------------------------------------------------------
# the inner least-squares problem
# --------------------------------------------------------------------------------------
class PointSet(eqx.Module):
    """The data of one inner solve (one scan, fixed correspondences), mm.

    Attributes:
        model: :class:`ResponseModel` gathered at the ``K + L`` surface points (scan
            correspondences first, then landmarks).
        defect: ``(K + L, 3)`` exact-minus-reduced model at those points (mm).
        target: ``(K + L, 3)`` scan points, then landmark targets (mm).
        normal: ``(K, 3)`` unit skin normals at the correspondences.
        w_point: ``(K,)`` weights (sum 1; 0 for padding / rejected).
        w_landmark: ``(L,)`` weights (``lambda_lm / L``; 0 for missing landmarks).
        centre: ``(3,)`` centre of the rigid correction (mm).
        ids, bary: ``(K + L, 3)`` local fit-vertex ids and barycentrics of the points (for
            evaluating the exact rig at them).
        free: ``(M,)`` 1 for a free activation, 0 for one held at a bound (active set).
        z_fixed: ``(M,)`` the parameter of a held activation (0 -> a = 0, 1 -> a = 1).
        grad_u, grad_p: ``(M + 3,)`` the gradient correction (:func:`gradient_correction`):
            the data residuals get ``r_k (grad_u . ([a, jaw] - grad_p))``; None = none.
        grad_r: ``(K + 3 L,)`` ``r_k``, the data residuals at ``grad_p`` (points, then the
            landmarks' x, y, z).
    """

    model: ResponseModel
    defect: jax.Array
    target: jax.Array
    normal: jax.Array
    w_point: jax.Array
    w_landmark: jax.Array
    centre: jax.Array
    ids: jax.Array
    bary: jax.Array
    free: jax.Array
    z_fixed: jax.Array
    grad_u: jax.Array | None = None
    grad_p: jax.Array | None = None
    grad_r: jax.Array | None = None


class Priors(eqx.Module):
    """Prior terms (shared by every scan of a batch).

    Attributes:
        left, right: ``(S,)`` indices of the paired ``_L`` / ``_R`` controls.
        sparsity, symmetry, rigid, jaw: weights (mm^2 per unit, see :class:`FitOptions`).
        symmetry_scale: ``tau`` of the saturating symmetry prior (unit activation).
        use_rigid: static, whether ``y`` has a ``"rigid"`` entry.
    """

    left: jax.Array
    right: jax.Array
    sparsity: jax.Array
    symmetry: jax.Array
    rigid: jax.Array
    jaw: jax.Array
    symmetry_scale: jax.Array
    use_rigid: bool = eqx.field(static=True, default=True)


def make_priors(muscle_names: Sequence[str], options: FitOptions) -> Priors:
    """:class:`Priors` for a rig's control names (``name_L`` pairs with ``name_R``)."""
    names = list(muscle_names)
    tau = float(options.symmetry_scale)
    if not (np.isfinite(tau) and tau > 0.0):
        raise ValueError(
            f"FitOptions.symmetry_scale must be a positive number (unit activation), got "
            f"{options.symmetry_scale!r}; use a large value (e.g. 1e3) for the plain "
            "quadratic symmetry prior"
        )
    left, right = [], []
    for i, n in enumerate(names):
        if n.endswith("_L") and n[:-2] + "_R" in names:
            left.append(i)
            right.append(names.index(n[:-2] + "_R"))
    f = lambda v: jnp.asarray(float(v))  # noqa: E731
    return Priors(
        left=to_jax(np.array(left, np.int64)),
        right=to_jax(np.array(right, np.int64)),
        sparsity=f(options.sparsity_weight),
        symmetry=f(options.symmetry_weight),
        rigid=f(options.rigid_weight),
        jaw=f(options.jaw_weight),
        symmetry_scale=f(tau),
        use_rigid=bool(options.rigid),
    )


def effective_z(y, pts: PointSet):
    """``(M,)`` activation parameters with the held ones replaced by their bound."""
    return jnp.where(pts.free > 0, y["z"], pts.z_fixed)


def _point_residuals(x, pts: PointSet):
    """Weighted point-to-plane ``(K,)`` and landmark ``(L, 3)`` residuals (mm) of the simulated
    surface points ``x`` ``(K + L, 3)`` (rigid correction already applied)."""
    K = pts.normal.shape[0]
    r_pt = jnp.sqrt(pts.w_point) * jnp.sum(pts.normal * (x[:K] - pts.target[:K]), axis=-1)
    r_lm = jnp.sqrt(pts.w_landmark)[:, None] * (x[K:] - pts.target[K:])
    return r_pt, r_lm


def _data_vector_plain(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """The data residuals ``(K + 3 L,)`` (points, then the landmarks' x, y, z), mm."""
    x = pts.model(a, jaw) + pts.defect
    if use_rigid:
        x = apply_rigid(rigid, pts.centre, x)
    r_pt, r_lm = _point_residuals(x, pts)
    r = jnp.concatenate([r_pt, r_lm.ravel()])
    if pts.grad_u is not None:
        r = r + jnp.dot(pts.grad_u, jnp.concatenate([a, jaw]) - pts.grad_p) * pts.grad_r
    return r


def _data_jacobian(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """The data residuals ``r`` ``(K + 3 L,)`` and their Jacobian ``(K + 3 L, M + 3 [+ 6])``
    with respect to ``[a, jaw (, rigid)]``, assembled from the reduced model's own derivative
    fields: the muscles' (:func:`_hermite_parts`, one evaluation), the jaw's (3 tangents) and
    the rigid correction's (6 tangents), then projected on the normals once. Pushing every
    tangent through the whole residual instead (plain forward mode) takes 1.4-2.2x as long
    (2.9 ms against 1.3-2.0 ms per Jacobian on the shared subjects' rigs, ``bench_fit.py``'s
    ``timing.jacobian``)."""
    model = pts.model
    val, D = _hermite_parts(a, model.levels, model.mus, model.mus_slope)  # (P, 3), (M, P, 3)
    xj = model.jaw_displacement(jaw)
    Jj = jax.jacfwd(model.jaw_displacement)(jaw)  # (P, 3, 3)
    x = model.rest + val + xj + pts.defect
    dx = jnp.concatenate([jnp.moveaxis(D, 0, 2), Jj], axis=2)  # (P, 3, M + 3)
    if use_rigid:
        R = rotation_from_rotvec_deg(rigid[:3])
        Jr = jax.jacfwd(lambda w: apply_rigid(w, pts.centre, x))(rigid)  # (P, 3, 6)
        x = apply_rigid(rigid, pts.centre, x)
        dx = jnp.concatenate([jnp.einsum("ij,pjn->pin", R, dx), Jr], axis=2)
    K = pts.normal.shape[0]
    r_pt, r_lm = _point_residuals(x, pts)
    J_pt = jnp.sqrt(pts.w_point)[:, None] * jnp.einsum("kd,kdn->kn", pts.normal, dx[:K])
    J_lm = (jnp.sqrt(pts.w_landmark)[:, None, None] * dx[K:]).reshape(-1, dx.shape[2])
    r = jnp.concatenate([r_pt, r_lm.ravel()])
    J = jnp.concatenate([J_pt, J_lm])
    if pts.grad_u is not None:
        M3 = pts.grad_u.shape[0]
        r = r + jnp.dot(pts.grad_u, jnp.concatenate([a, jaw]) - pts.grad_p) * pts.grad_r
        J = J.at[:, :M3].add(pts.grad_r[:, None] * pts.grad_u[None, :])
    return r, J


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _data_vector(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """:func:`_data_vector_plain` with a forward-mode rule that applies the Jacobian of
    :func:`_data_jacobian` (the inner solves' Levenberg-Marquardt Jacobians and the KKT
    gradients go through it; derivatives with respect to ``pts`` fall back to plain autodiff)."""
    return _data_vector_plain(a, jaw, rigid, pts, use_rigid)


def _data_vector_jvp(use_rigid, primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    a, jaw, rigid, pts = primals
    da, djaw, drigid, dpts = tangents
    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    inst = lambda p, t: jnp.zeros_like(p) if zero(t) else t  # noqa: E731
    if not all(zero(t) for t in jax.tree_util.tree_leaves(dpts, is_leaf=zero)):
        # plain forward mode in the perturbed leaves only: the others stay constants (a zero
        # tangent pushed through sqrt(w) at a zero weight would give NaN)
        leaves, tree = jax.tree_util.tree_flatten(primals)
        tans = tree.flatten_up_to(tangents)
        moving = [i for i, t in enumerate(tans) if not zero(t)]

        def plain(*sub):
            full = list(leaves)
            for i, v in zip(moving, sub):
                full[i] = v
            return _data_vector_plain(*jax.tree_util.tree_unflatten(tree, full), use_rigid)

        return jax.jvp(plain, [leaves[i] for i in moving], [tans[i] for i in moving])
    r, J = _data_jacobian(a, jaw, rigid, pts, use_rigid)
    parts = [inst(a, da), inst(jaw, djaw)] + ([inst(rigid, drigid)] if use_rigid else [])
    return r, J @ jnp.concatenate(parts)


_data_vector.defjvp(_data_vector_jvp, symbolic_zeros=True)


def _data_residuals(a, jaw, rigid, pts: PointSet, use_rigid: bool):
    """Point-to-plane ``(K,)`` and landmark ``(L, 3)`` residuals (mm) of the reduced model with
    the defect and gradient corrections, after the rigid correction."""
    r = _data_vector(a, jaw, rigid, pts, use_rigid)
    K = pts.normal.shape[0]
    return r[:K], r[K:].reshape(-1, 3)


def gradient_correction(exact_fn, fit_ids, y, pts: PointSet, use_rigid: bool):
    """Rank-one correction that gives the inner problem the exact rig's gradient at ``y``.

    Defect correction makes the inner residuals those of the exact rig at the current
    iterate, but their Jacobian stays the reduced model's. Where the reduced model is not
    additive enough (muscles interacting with each other and with the jaw: up to several mm
    on the default head), the outer loop can settle where the *reduced* gradient of the exact
    residuals vanishes while the exact gradient does not: a spurious fit. With
    ``g = J^T r`` over the data residuals ``r_k`` at ``p_k = [a, jaw]`` for the exact rig
    (one reverse-mode pass through it) and the reduced model, the data residuals get
    ``r_k (u . (p - p_k))`` with ``u = (g_exact - g_reduced) / |r_k|^2``: the corrected
    Jacobian ``J + r_k u^T`` has ``(J + r_k u^T)^T r_k = g_exact``. At a fixed point of the
    outer loop the exact gradient of the data term then vanishes.

    Args:
        exact_fn: the exact rig, ``(a (M,), jaw (3,)) -> (V, 3)`` mm.
        fit_ids: ``(P,)`` fit vertices of the rig skin.
        y: parameters at which to correct; pts: its :class:`PointSet` (with the defect
            of ``y``); use_rigid: whether ``y`` has a rigid correction.

    Returns:
        ``(u (M + 3,), p_k (M + 3,), r_k (K + 3 L,))``; ``u = 0`` (no correction) where the
        reverse pass is not finite.
    """
    a = activations_from_z(effective_z(y, pts))
    skin, skin_vjp = jax.vjp(exact_fn, a, y["jaw"])
    return gradient_correction_from_vjp(skin, skin_vjp, fit_ids, y, pts, use_rigid)


def exact_skin_and_vjp(exact_fn, a, jaw):
    """The exact rig's skin ``(V, 3)`` mm at ``(a (M,), jaw (3,))`` and its VJP (a pytree:
    it can leave a ``jit`` and be called in another): the one forward pass that both the
    correspondences and :func:`gradient_correction_from_vjp` of an outer iteration use."""
    return jax.vjp(exact_fn, a, jaw)


def gradient_correction_from_vjp(skin, skin_vjp, fit_ids, y, pts: PointSet, use_rigid: bool):
    """:func:`gradient_correction` from a forward pass already made
    (:func:`exact_skin_and_vjp` at ``y``'s effective activations and jaw): ``skin`` ``(V, 3)``
    mm and its VJP. Same returns."""
    a = activations_from_z(effective_z(y, pts))
    p0 = jnp.concatenate([a, y["jaw"]])

    def data_of_points(x):
        if use_rigid:
            x = apply_rigid(y["rigid"], pts.centre, x)
        r_pt, r_lm = _point_residuals(x, pts)
        return jnp.concatenate([r_pt, r_lm.ravel()])

    def reduced(p):
        return data_of_points(pts.model(p[: a.shape[0]], p[a.shape[0] :]) + pts.defect)

    r, vjp_x = jax.vjp(lambda xv: data_of_points(_points_from_vertices(xv[fit_ids], pts)), skin)
    _, vjp_r = jax.vjp(reduced, p0)
    (ct,) = vjp_x(r)
    g_a, g_j = skin_vjp(ct)
    g_e = jnp.concatenate([g_a, g_j])
    (g_r,) = vjp_r(r)
    rr = jnp.sum(r * r)
    # no correction where the reverse pass through the rig is not finite (seen once, in
    # float32 at a wide jaw opening): the inner solve then has the reduced gradient
    ok = (rr > 1e-20) & jnp.all(jnp.isfinite(g_e)) & jnp.all(jnp.isfinite(r))
    u = jnp.where(ok, (g_e - g_r) / jnp.where(ok, rr, 1.0), 0.0)
    return u, p0, jnp.where(ok, r, 0.0)


_exact_vjp_jit = eqx.filter_jit(exact_skin_and_vjp)
_gradient_correction_vjp_jit = eqx.filter_jit(gradient_correction_from_vjp)


def model_points(y, pts: PointSet, use_rigid: bool):
    """``(K + L, 3)`` simulated points (mm, neutral-scan frame) for parameters ``y``."""
    a = activations_from_z(effective_z(y, pts))
    x = pts.model(a, y["jaw"]) + pts.defect
    if use_rigid:
        x = apply_rigid(y["rigid"], pts.centre, x)
    return x


def _symmetry_gap(a, pri: Priors):
    """``(S,)`` saturated left/right differences ``tau tanh((a_L - a_R) / tau)`` (unit
    activation): ``a_L - a_R`` while small, at most ``tau`` in size."""
    tau = pri.symmetry_scale
    return tau * jnp.tanh((a[pri.left] - a[pri.right]) / tau)


def residuals(y, args):
    """Residual pytree of the inner problem (see the module doc); ``args = (PointSet,
    Priors)``. All terms in mm (or sqrt(mm^2) for the priors)."""
    pts, pri = args
    z = effective_z(y, pts)
    a = activations_from_z(z)
    r_pt, r_lm = _data_residuals(a, y["jaw"], y.get("rigid"), pts, pri.use_rigid)
    r_sp = jnp.sqrt(pri.sparsity) * jnp.sin(0.5 * jnp.pi * z)  # r^2 = lambda a
    r_sym = jnp.sqrt(pri.symmetry) * _symmetry_gap(a, pri)
    r_jaw = jnp.sqrt(pri.jaw) * y["jaw"][1:]
    out = {"points": r_pt, "landmarks": r_lm, "sparsity": r_sp, "symmetry": r_sym, "jaw": r_jaw}
    if pri.use_rigid:
        out["rigid"] = jnp.sqrt(pri.rigid) * y["rigid"]
    return out


def _cost(y, args):
    r = residuals(y, args)
    return sum(jnp.sum(v * v) for v in jax.tree_util.tree_leaves(r))


def _cost_of_activations(a, y, pts: PointSet, pri: Priors):
    """The inner cost as a function of the activations themselves (mm^2); its gradient
    is the KKT test of the bounds."""
    r_pt, r_lm = _data_residuals(a, y["jaw"], y.get("rigid"), pts, pri.use_rigid)
    c = jnp.sum(r_pt**2) + jnp.sum(r_lm**2)
    c = c + pri.sparsity * jnp.sum(a) + pri.symmetry * jnp.sum(_symmetry_gap(a, pri) ** 2)
    return c


def _linear_solver(dtype) -> lx.AbstractLinearSolver:
    """The damped Gauss-Newton steps' linear solver: the normal equations by Cholesky in
    float64, QR otherwise.

    Each Levenberg-Marquardt step solves the tall system ``[J; sqrt(lambda) D] dy = [-r; 0]``
    (K + 3 L + prior rows, M + 9 columns); with the damping the normal matrix is positive
    definite and its condition number the square of the Jacobian's (at most about 1e6 on the
    shared data, harmless in float64). On a bs900 inner solve (1,000 points) a step took 2.9
    ms against 5.0 ms with optimistix's default QR, to the same solution. In float32 the
    squared conditioning would cost digits, so QR stays.
    """
    return lx.Normal(lx.Cholesky()) if jnp.dtype(dtype) == jnp.float64 else lx.QR()


def _solve_one(y0, pts, pri, *, max_steps, rtol, atol):
    solver = optx.LevenbergMarquardt(
        rtol=rtol, atol=atol, linear_solver=_linear_solver(y0["z"].dtype)
    )
    sol = optx.least_squares(
        residuals, solver, y0, args=(pts, pri), max_steps=max_steps, throw=False
    )
    y = sol.value
    a = activations_from_z(effective_z(y, pts))
    g = jax.grad(_cost_of_activations)(a, y, pts, pri)
    return (
        y,
        sol.result._value,
        sol.stats["num_steps"],
        _cost(y, (pts, pri)),
        _cost(y0, (pts, pri)),
        a,
        g,
    )


def batch_mode() -> str:
    """How :func:`solve_inner` runs a batch: ``"map"`` (one compiled single-scan solve called
    per scan, each stopping at its own convergence) on the CPU, ``"vmap"`` (parallel) on
    accelerators."""
    return "map" if jax.default_backend() == "cpu" else "vmap"


@functools.lru_cache(maxsize=16)
def _batched_solver(max_steps: int, rtol: float, atol: float, mode: str = "vmap"):
    fn = functools.partial(_solve_one, max_steps=max_steps, rtol=rtol, atol=atol)
    if mode == "map":
        return eqx.filter_jit(fn)
    return eqx.filter_jit(jax.vmap(fn, in_axes=(0, 0, None)))


def padded_batch_size(n: int) -> int:
    """The batch size a ``"vmap"`` inner solve of ``n`` members is compiled for: the next
    power of two (1, 2, 4, 8, 16, ...), so the shrinking subsets of a fit and batches of other
    sizes reuse a few compiled solves instead of compiling one per size."""
    n = int(n)
    if n < 1:
        raise FitError(f"padded_batch_size needs a batch of at least one member; got {n}.")
    return 1 << (n - 1).bit_length()


def _pad_leading(tree, n: int, size: int):
    """Every array leaf of ``tree`` padded from ``n`` to ``size`` rows along its leading axis
    by repeating its last row (padding members repeat a real member's solve, so they cannot
    fail where it does not and never take more steps than the batch's slowest member)."""
    if size == n:
        return tree

    def pad(x):
        if not eqx.is_array(x):
            return x
        x = np.asarray(x)
        return to_jax(np.concatenate([x, np.repeat(x[n - 1 : n], size - n, axis=0)], axis=0))

    return jax.tree_util.tree_map(pad, tree)


def solve_inner(
    y0,
    points: PointSet,
    priors: Priors,
    options: FitOptions,
    *,
    mode: str | None = None,
    pad_to: int | None = None,
):
    """Batched Levenberg-Marquardt solves over the leading axis of ``y0`` and ``points``,
    ``throw=False``.

    In ``"map"`` mode (the CPU default) each scan is solved by the same compiled single-scan
    solve, the scans on the outer thread pool (:func:`jaxface._parallel.thread_map`): a batch
    of any size, and the subsets that :func:`fit_points` goes on with, cost no new
    compilation (on the 2-core CPU
    a ``lax.map`` over the batch ran at the same speed per scan but compiled once per batch
    size). ``"vmap"`` (accelerators) pads the batch to a power of two
    (:func:`padded_batch_size`) and compiles one parallel solve per padded size.

    Args:
        y0, points: batched parameters and residual data; priors: shared.
        options: :class:`FitOptions` (``max_steps``, ``rtol``, ``atol``).
        mode: ``"map"`` or ``"vmap"``; default :func:`batch_mode`.
        pad_to: ``"vmap"`` only: pad the batch to at least this many members, rounded up by
            :func:`padded_batch_size` (default: ``padded_batch_size`` of the batch). The
            padding repeats the last member and is cut from the results, so one compiled
            solve serves every batch size up to it. ``"map"`` ignores it.

    Returns:
        ``(y, result (B,) int, steps (B,), cost (B,), cost0 (B,), a (B, M), grad_a (B, M))``;
        ``result`` indexes ``optimistix.RESULTS`` (0 = successful, see
        :func:`result_name`); ``grad_a`` is the gradient of the cost with respect to the
        activations at the solution (mm^2 per unit activation).
    """
    mode = batch_mode() if mode is None else mode
    if mode not in ("map", "vmap"):
        raise FitError(f"solve_inner mode {mode!r}: use 'map' or 'vmap'.")
    fn = _batched_solver(int(options.max_steps), float(options.rtol), float(options.atol), mode)
    n = int(np.shape(jax.tree_util.tree_leaves(y0)[0])[0])
    if mode == "map":
        # one solve per thread of the pool: a solve's small kernels keep one core busy
        outs = thread_map(
            lambda b: jax.block_until_ready(fn(_index(y0, b), _index(points, b), priors)),
            range(n),
            outer=True,
        )
        y = _stack([o[0] for o in outs])
        rest = [np.stack([np.asarray(o[k]) for o in outs]) for k in range(1, 7)]
        return (y, *rest)
    size = padded_batch_size(max(n, int(pad_to or 0)))
    y, res, steps, cost, cost0, a, g = fn(
        _pad_leading(y0, n, size), _pad_leading(points, n, size), priors
    )
    if size != n:
        y = _index(y, slice(0, n))
    return (y, *(np.asarray(v)[:n] for v in (res, steps, cost, cost0, a, g)))


def result_name(code: int) -> str:
    """Name of an ``optimistix.RESULTS`` code (``"successful"``, ``"max_steps_reached"``,
    ``"nonlinear_max_steps_reached"``, ...)."""
    for name, item in optx.RESULTS._name_to_item.items():
        if int(item._value) == int(code):
            return name
    return f"unknown({int(code)})"


def update_active_set(
    a, grad, free, z_fixed, *, tol_a: float = 1e-2, tol_g: float = 1e-4, locked=None, keep=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Active-set update of the activation bounds (NumPy, one scan).

    A free activation within ``tol_a`` of a bound whose cost gradient pushes it outward by
    more than ``tol_g`` (``grad > tol_g`` at 0, ``grad < -tol_g`` at 1; mm^2 per unit
    activation) is held at that bound; a held one whose gradient points back inside by more
    than ``tol_g`` is released, restarting 0.02 inside. The dead band ``|grad| <= tol_g``
    keeps an activation whose optimum lies just inside a bound from flipping back and forth.
    ``locked`` ``(M,)`` bools stay held at 0 (controls the fit leaves out). ``keep`` ``(M,)``
    bools are not released once held (anti-cycling: :func:`fit_points` sets it for an
    activation that was released and then held again, whose optimum therefore lies within
    ``tol_a`` of the bound, where the zero slope of ``sin^2`` makes every solve creep).

    Returns:
        ``(free, z_fixed, z_start, changes)``: new mask, bound parameters, a starting ``z``
        for the released ones (NaN elsewhere) and the number of changes.
    """
    a = np.asarray(a, np.float64)
    g = np.asarray(grad, np.float64)
    free = np.asarray(free, np.float64).copy()
    zf = np.asarray(z_fixed, np.float64).copy()
    z_start = np.full(len(a), np.nan)
    lock = np.zeros(len(a), bool) if locked is None else np.asarray(locked, bool)
    kept = np.zeros(len(a), bool) if keep is None else np.asarray(keep, bool)
    changes = 0
    for i in range(len(a)):
        if lock[i]:
            free[i], zf[i] = 0.0, 0.0
            continue
        if free[i] > 0:
            if a[i] <= tol_a and g[i] > tol_g:
                free[i], zf[i] = 0.0, 0.0
                changes += 1
            elif a[i] >= 1.0 - tol_a and g[i] < -tol_g:
                free[i], zf[i] = 0.0, 1.0
                changes += 1
        elif not kept[i]:
            if zf[i] == 0.0 and g[i] < -tol_g:
                free[i] = 1.0
                z_start[i] = float(z_from_activations(0.02))
                changes += 1
            elif zf[i] == 1.0 and g[i] > tol_g:
                free[i] = 1.0
                z_start[i] = float(z_from_activations(0.98))
                changes += 1
    return free, zf, z_start, changes


# --------------------------------------------------------------------------------------
# correspondences (NumPy)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Correspondences:
    """Scan points matched to the simulated skin (one outer iteration), padded to ``K``.

    Attributes:
        tri: ``(K,)`` skin triangle ids; bary: ``(K, 3)``; local: ``(K, 3)`` local point ids
            of the triangle corners (into the fit-vertex set).
        target: ``(K, 3)`` scan points (mm); normal: ``(K, 3)`` skin normals.
        weight: ``(K,)`` robust weights summing to 1 (0 = rejected or padding).
        distance: ``(K,)`` point-to-plane residual at the current skin (mm, signed).
        n_accepted: accepted matches; scale_mm: the Tukey cut-off used.
    """

    tri: np.ndarray
    bary: np.ndarray
    local: np.ndarray
    target: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    distance: np.ndarray
    n_accepted: int
    scale_mm: float


def find_correspondences(
    skin,
    triangles: np.ndarray,
    face_triangles: np.ndarray,
    local_ids: np.ndarray,
    points: np.ndarray,
    point_normals: np.ndarray | None,
    valid: np.ndarray,
    *,
    max_distance: float,
    robust_floor: float,
    max_normal_angle_deg: float = 60.0,
) -> Correspondences:
    """Closest points of scan ``points`` ``(K, 3)`` on the simulated ``skin`` ``(V, 3)``
    (face triangles only), with rejection and Tukey weights.

    A match is rejected when the point is padding (``valid`` False), its closest point lies
    on the border of the face region (the scan point is outside the face), it is farther
    than ``max_distance`` mm, or the scan normal differs from the skin normal by more than
    ``max_normal_angle_deg``. Weights: Tukey's biweight at
    ``max(4.685 * 1.4826 * MAD, robust_floor)`` of the point-to-plane residuals, normalised
    to sum to 1.

    Raises:
        FitError: no match accepted.
    """
    index = SurfaceIndex(skin, triangles, face_triangles)
    cp = index.query(points, max_distance=max_distance * 2.0)
    tri = cp.triangles
    bary = cp.bary
    nrm = cp.normals
    d_signed = np.einsum("kd,kd->k", cp.points - points, nrm)  # n . (S - q)
    ok = np.asarray(valid, bool) & ~cp.on_boundary & (cp.distances <= max_distance)
    if point_normals is not None:
        cos_max = np.cos(np.radians(max_normal_angle_deg))
        ok &= np.einsum("kd,kd->k", point_normals, nrm) >= cos_max
    if not ok.any():
        raise FitError(
            "no scan point found a compatible point on the simulated skin (all farther than "
            f"{max_distance:.1f} mm, outside the face region or with opposed normals); the scan "
            "and the subject's neutral do not overlap (check the landmarks and the alignment)."
        )
    r = np.abs(d_signed[ok])
    mad = float(np.median(np.abs(r - np.median(r))))
    c = max(4.685 * 1.4826 * mad, float(robust_floor))
    u = np.abs(d_signed) / c
    w = np.where(ok & (u < 1.0), (1.0 - u * u) ** 2, 0.0)
    if w.sum() <= 0:
        w = ok.astype(np.float64)
    w = w / w.sum()
    loc = local_ids[triangles[tri]]
    if np.any(loc[ok] < 0):  # pragma: no cover - face triangles are always in the fit set
        raise FitError("internal: a face triangle corner is missing from the fit-vertex set.")
    loc = np.where(loc < 0, 0, loc)
    return Correspondences(
        tri=tri,
        bary=bary,
        local=loc,
        target=np.asarray(points, np.float64),
        normal=nrm,
        weight=w,
        distance=d_signed,
        n_accepted=int(ok.sum()),
        scale_mm=c,
    )


# --------------------------------------------------------------------------------------
# the outer loop
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InnerReport:
    """One inner solve of one scan: outer iteration, optimistix result name, LM steps,
    cost before/after (mm^2), accepted correspondences, Tukey cut-off (mm), active-set
    changes after the solve, activations held at a bound, seconds (of the whole batched
    call)."""

    outer: int
    result: str
    steps: int
    cost0: float
    cost: float
    n_accepted: int
    scale_mm: float
    active_set_changes: int
    n_at_bounds: int
    seconds: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class PointFit:
    """Result of :func:`fit_points` for one scan (neutral-scan frame, mm).

    Attributes:
        activations: ``(M,)`` in [0, 1]; jaw: ``(3,)`` [pitch_deg, yaw_deg, protrusion_mm]
            as fitted (the rig clamps it smoothly; ``jaw_effective`` is the clamped pose).
        rigid: ``(6,)`` [rotation vector deg, translation mm] about ``centre`` ``(3,)``.
        skin: ``(V, 3)`` the exact rig's skin at the fit with the rigid correction, mm.
        y: the parameter pytree; reports: the inner solves.
        status: ``"successful"`` when the last inner solve met its tolerance, the active
            set of the activation bounds did not change (KKT conditions hold) and the outer
            iterations converged (:attr:`FitOptions.extra_iterations`), else the optimistix
            result name of the last solve, ``"active_set_changing"`` or
            ``"outer_not_converged"``.
        steps: total LM steps; seconds: wall time per scan; start_pitch: the winning start.
        residual_mm: point-to-plane residual stats of the final correspondences (exact skin).
        points: the last :class:`PointSet` (for conditioning).
        starts: jaw start pitch (deg) -> final weighted cost (mm^2) of every start.
        at_bounds: control index -> bound (0 or 1) of the activations held there.
        restart: the bound-flip restart of this scan (``FitOptions.restart_iterations``),
            empty when none ran: ``controls`` restarted from their starting value,
            ``cost_mm2`` its final cost, ``parent_cost_mm2`` that of the run it restarted,
            ``kept`` whether it won.
    """

    activations: np.ndarray
    jaw: np.ndarray
    jaw_effective: np.ndarray
    rigid: np.ndarray
    centre: np.ndarray
    skin: np.ndarray
    y: dict
    reports: list[InnerReport]
    status: str
    steps: int
    seconds: float
    start_pitch: float
    residual_mm: dict = field(default_factory=dict)
    points: Any = None
    starts: dict = field(default_factory=dict)
    at_bounds: dict = field(default_factory=dict)
    restart: dict = field(default_factory=dict)


def _stack(trees):
    """The pytrees ``trees`` stacked along a new leading axis. Stacked and sliced on the host
    (:func:`_index` too): the same bits as ``jnp.stack`` / ``x[i]``, without the eager XLA
    dispatch (and a compilation per new shape) for every leaf, which took up to a tenth of a
    warm batch fit's time on the 2-core CPU (README, "How it works")."""
    return jax.tree_util.tree_map(lambda *xs: to_jax(np.stack([np.asarray(x) for x in xs])), *trees)


def _index(tree, i):
    """Entry (or slice) ``i`` of the leading axis of every array leaf of ``tree`` (on the
    host, see :func:`_stack`)."""
    return jax.tree_util.tree_map(
        lambda x: to_jax(np.asarray(x)[i]) if eqx.is_array(x) else x, tree
    )


def _y0(M: int, options: FitOptions, pitch: float):
    # NumPy first: strongly typed float64 leaves (a weakly typed leaf would re-trace the
    # compiled solver on the next call)
    y = {
        "z": to_jax(np.full(M, float(z_from_activations(options.init_activation)))),
        "jaw": to_jax(np.array([float(pitch), 0.0, 0.0])),
    }
    if options.rigid:
        y["rigid"] = to_jax(np.zeros(6))
    return y


def _landmark_pitch(response: ResponseModel, lm_loc, lm_bary, scan: dict) -> float:
    """Jaw pitch (deg, 1-degree grid over the limits) whose reduced-model landmarks at
    activations 0 best match the scan's landmark targets (least squares)."""
    valid = np.asarray(scan["landmark_valid"], bool)
    if valid.sum() < 3:
        return 0.0
    gm = _gather_jit(response, to_jax(lm_loc), to_jax(lm_bary))
    lo, hi = response.jaw.pitch_limits
    grid = np.arange(np.ceil(lo), np.floor(hi) + 1.0, 1.0)
    M = response.mus.shape[0]
    X = np.asarray(_pitch_sweep(gm, to_jax(grid), M))  # (G, L, 3)
    tgt = np.asarray(scan["landmarks"], np.float64)
    err = np.sum(((X - tgt[None]) ** 2).sum(-1)[:, valid], axis=1)
    return float(grid[int(np.argmin(err))])


@eqx.filter_jit
def _pitch_sweep(model: ResponseModel, pitches, M: int):
    z = jnp.zeros(M, pitches.dtype)
    return jax.vmap(lambda p: model(z, jnp.stack([p, 0.0 * p, 0.0 * p])))(pitches)


def fit_points(
    forward: ForwardModel,
    response: ResponseModel,
    fit_ids: np.ndarray,
    face_triangles: np.ndarray,
    scans: Sequence[dict],
    landmark_tri: np.ndarray,
    landmark_bary: np.ndarray,
    options: FitOptions | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> list[PointFit]:
    """Fit activations, jaw and rigid correction to a batch of scans of one subject.

    Arguments:
        forward: the exact rig (:class:`ForwardModel`).
        response: its :class:`ResponseModel` over the vertices ``fit_ids``.
        fit_ids: ``(P,)`` vertex ids of the response model (every vertex of the face
            triangles and of the landmark triangles).
        face_triangles: ``(F,)`` bool, the rig skin's face region.
        scans: one dict per scan (neutral-scan frame, mm): ``points`` ``(K, 3)`` (exactly
            ``options.n_points`` rows), ``normals`` ``(K, 3)`` or None, ``valid`` ``(K,)``
            bool, ``landmarks`` ``(L, 3)`` targets and ``landmark_valid`` ``(L,)`` bool.
        landmark_tri, landmark_bary: ``(L,)`` / ``(L, 3)`` the landmarks on the rig skin.
        options: :class:`FitOptions`.
        progress: called with a short text after each outer iteration.

    Returns:
        one :class:`PointFit` per scan.

    Raises:
        FitError: non-finite parameters after a solve, no correspondence, or unknown
            controls in ``options.controls``.
    """
    opt = options or FitOptions()
    t0 = time.perf_counter()
    tris = forward.triangles
    V = len(forward.rest)
    M = forward.n_controls
    names = list(forward.muscle_names)
    local = np.full(V, -1, np.int64)
    local[np.asarray(fit_ids)] = np.arange(len(fit_ids))
    lm_loc = local[tris[np.asarray(landmark_tri)]]
    if np.any(lm_loc < 0):
        raise FitError("internal: a landmark triangle corner is missing from the fit-vertex set.")
    locked = np.zeros(M, bool)
    if response.sampled:
        locked |= ~np.asarray(response.sampled, bool)
    if opt.controls is not None:
        unknown = [c for c in opt.controls if c not in names]
        if unknown:
            raise FitError(
                f"FitOptions.controls names unknown controls {unknown}; the rig has {names}."
            )
        locked |= ~np.isin(names, list(opt.controls))
    for c in opt.controls or ():
        if locked[names.index(c)]:
            raise FitError(
                f"control {c!r} is to be fitted but the reduced model did not sample it "
                "(build_response_model(controls=...))."
            )
    centre = np.asarray(response.rest).mean(axis=0)
    priors = make_priors(names, opt)
    S = len(scans)
    # runs: (scan index, start pitch), all solved in one batched call (solve_inner)
    if opt.jaw_starts is None:
        runs = [
            (s, _landmark_pitch(response, lm_loc, landmark_bary, sc)) for s, sc in enumerate(scans)
        ]
    else:
        runs = [(s, float(p)) for s in range(S) for p in (list(opt.jaw_starts) or [0.0])]
    R_ = len(runs)
    ys = [_y0(M, opt, p) for _, p in runs]
    free = [np.where(locked, 0.0, 1.0) for _ in runs]
    zfix = [np.zeros(M) for _ in runs]
    released = [np.zeros(M, bool) for _ in runs]  # held once, then released
    cycled = [np.zeros(M, bool) for _ in runs]  # ... and held again: kept at its bound
    for i in range(R_):
        z = np.asarray(ys[i]["z"]).copy()
        z[locked] = 0.0
        ys[i]["z"] = to_jax(z)
    reports: dict[int, list[InnerReport]] = {i: [] for i in range(R_)}
    last_pts: dict[int, PointSet] = {}
    last_changes = [0] * R_
    parent = list(range(R_))  # the run a restart run was spawned from (itself if none)
    flipped: dict[int, tuple[int, ...]] = {}

    def z_of(i):
        """Run ``i``'s parameters ``z`` with the held activations at their bounds."""
        return np.where(free[i] > 0, np.asarray(ys[i]["z"]), zfix[i])

    def placed(i, x):
        """Run ``i``'s skin ``x`` (V, 3) with its rigid correction applied."""
        if opt.rigid:
            R, t = rigid_numpy(np.asarray(ys[i]["rigid"]), centre)
            x = x @ R.T + t
        return x

    def exact_skins(ids):
        A, J = [], []
        for i in ids:
            A.append(np.asarray(activations_from_z(to_jax(z_of(i)))))
            J.append(np.asarray(ys[i]["jaw"]))
        X = forward.many(np.stack(A), np.stack(J))
        return X, [placed(i, x) for i, x in zip(ids, X)], A

    def exact_skin_vjp(i):
        """Run ``i``'s exact skin, placed skin, activations and the skin's VJP: one forward
        pass serves the correspondences and the gradient correction."""
        a = activations_from_z(to_jax(z_of(i)))
        x, vjp = forward.with_vjp(a, ys[i]["jaw"])
        x_np = np.asarray(x, np.float64)
        return x, x_np, placed(i, x_np), np.asarray(a), vjp

    def corr_for(run, skin, k):
        sc = scans[runs[run][0]]
        return find_correspondences(
            skin,
            tris,
            face_triangles,
            local,
            sc["points"],
            sc.get("normals"),
            sc["valid"],
            max_distance=opt.anneal(opt.max_distance_mm, k),
            robust_floor=opt.anneal(opt.robust_floor_mm, k),
            max_normal_angle_deg=opt.max_normal_angle_deg,
        )

    outer = max(int(opt.outer_iterations), 1)
    fit_ids_j = to_jax(np.asarray(fit_ids))

    def outer_step(k, act):
        """One outer iteration of the runs ``act`` (correspondences at annealing step ``k``,
        batched inner solves, active-set rounds); returns their inner costs."""
        t_it = time.perf_counter()
        if not opt.gradient_correction:
            Xr, skins, A = exact_skins(act)

        def residual_data(n, i):
            """Run ``i``'s correspondences and residual data (:class:`PointSet`): one exact
            synthesis (and, with the gradient correction, its reverse pass)."""
            if opt.gradient_correction:
                # the skin's forward pass, kept for the reverse pass of the correction below
                x_j, x_n, skin_n, a_n, vjp_n = exact_skin_vjp(i)
            else:
                x_n, skin_n, a_n = Xr[n], skins[n], A[n]
            c = corr_for(i, skin_n, k)
            approx = np.asarray(_eval_jit(response, to_jax(a_n), ys[i]["jaw"]))
            defect_v = x_n[fit_ids] - approx  # (P, 3): exact minus reduced model
            ids = np.concatenate([c.local, lm_loc])
            bary = np.concatenate([c.bary, np.asarray(landmark_bary)])
            gm = _gather_jit(response, to_jax(ids), to_jax(bary))
            dfx = np.einsum("kc,kcd->kd", bary, defect_v[ids])
            sc = scans[runs[i][0]]
            lw = np.where(np.asarray(sc["landmark_valid"], bool), 1.0, 0.0)
            lw = opt.landmark_weight * lw / max(lw.sum(), 1.0)
            target = np.concatenate([c.target, np.asarray(sc["landmarks"], np.float64)])
            target = np.where(np.isfinite(target), target, 0.0)
            pts = PointSet(
                model=gm,
                defect=to_jax(dfx),
                target=to_jax(target),
                normal=to_jax(c.normal),
                w_point=to_jax(c.weight),
                w_landmark=to_jax(lw),
                centre=to_jax(centre),
                ids=to_jax(ids),
                bary=to_jax(bary),
                free=to_jax(free[i]),
                z_fixed=to_jax(zfix[i]),
            )
            if opt.gradient_correction:
                u, p0, r0 = jax.block_until_ready(
                    _gradient_correction_vjp_jit(
                        x_j, vjp_n, fit_ids_j, ys[i], pts, priors.use_rigid
                    )
                )
                del vjp_n  # its residuals (one state per sweep) are freed here
                pts = dataclasses.replace(pts, grad_u=u, grad_p=p0, grad_r=r0)
            return pts, c

        # the runs' exact passes are independent: on the thread pool they keep both cores of a
        # 2-core CPU busy (one synthesis with its reverse pass keeps about 1.7 busy; README,
        # "A batch fits its scans two at a time")
        done = thread_map(lambda ni: residual_data(*ni), list(enumerate(act)), outer=True)
        pts_list = [d[0] for d in done]
        corrs = [d[1] for d in done]
        P = _stack(pts_list)
        Y0 = _stack([ys[i] for i in act])
        n_act = len(act)
        tot_steps = np.zeros(n_act, np.int64)
        cost0_first = None
        changes = np.zeros(n_act, np.int64)
        res_k = np.zeros(n_act, np.int64)
        cost_k = np.zeros(n_act)
        settled = np.zeros(n_act, bool)
        for rnd in range(max(int(opt.active_set_rounds), 1)):
            # same correspondences; re-solve while the active set of the bounds changes. A run
            # whose set settled keeps that solve: it is not re-solved with the others, so a
            # scan's fit does not depend on the batch it is in
            # on an accelerator every solve of this fit is padded to the batch size of all its
            # runs, so the subsets that go on compile nothing new
            Y, res, steps, cost, cost0, acts, grads = solve_inner(
                Y0, P, priors, opt, pad_to=len(runs)
            )
            cost0_first = cost0 if cost0_first is None else cost0_first
            flat = np.concatenate(
                [np.asarray(v).reshape(n_act, -1) for v in jax.tree_util.tree_leaves(Y)], axis=1
            )
            for n, i in enumerate(act):
                if not settled[n] and not np.all(np.isfinite(flat[n])):
                    raise FitError(
                        f"the inner solve of scan {runs[i][0]} returned non-finite parameters at outer "
                        f"iteration {k} (optimistix result: {result_name(res[n])})."
                    )
            for n, i in enumerate(act):
                if settled[n]:
                    continue
                tot_steps[n] += steps[n]
                res_k[n], cost_k[n] = res[n], cost[n]
                yi = dict(_index(Y, n))
                f_new, zf_new, z_start, n_ch = update_active_set(
                    acts[n],
                    grads[n],
                    free[i],
                    zfix[i],
                    locked=locked,
                    tol_g=opt.release_gradient,
                    keep=cycled[i],
                )
                # anti-cycling: released before and held again -> stays held
                cycled[i] |= released[i] & (free[i] > 0) & (f_new == 0)
                released[i] |= (free[i] == 0) & (f_new > 0)
                z = np.asarray(yi["z"]).copy()
                z = np.where(np.isfinite(z_start), z_start, z)
                z = np.where(f_new > 0, z, zf_new)
                yi["z"] = to_jax(z)
                ys[i] = yi
                free[i], zfix[i] = f_new, zf_new
                changes[n] = n_ch
                settled[n] = n_ch == 0
            if settled.all():
                break
            P = eqx.tree_at(
                lambda p: (p.free, p.z_fixed),
                P,
                (
                    to_jax(np.stack([free[i] for i in act])),
                    to_jax(np.stack([zfix[i] for i in act])),
                ),
            )
            Y0 = _stack([ys[i] for i in act])
        dt = time.perf_counter() - t_it
        for n, i in enumerate(act):
            last_changes[i] = int(changes[n])
            reports[i].append(
                InnerReport(
                    len(reports[i]),
                    result_name(res_k[n]),
                    int(tot_steps[n]),
                    float(cost0_first[n]),
                    float(cost_k[n]),
                    corrs[n].n_accepted,
                    corrs[n].scale_mm,
                    int(changes[n]),
                    int(np.sum((free[i] == 0) & ~locked)),
                    dt,
                )
            )
            last_pts[i] = _index(P, n)
        return cost_k

    def params_of(i):
        a = np.asarray(activations_from_z(to_jax(z_of(i))))
        return a, np.asarray(ys[i]["jaw"], np.float64)

    def step_and_track(k, act):
        """outer_step, and whether each run is still converging: its inner cost fell by more
        than ``converge_cost`` and its parameters moved by more than their tolerances, or its
        active set of bounds still changed in the iteration's last round, or its inner solve
        stopped at ``max_steps`` (FitOptions.extra_iterations)."""
        before = [params_of(i) for i in act]
        cost = outer_step(k, act)
        move = []
        for (a0, j0), i in zip(before, act):
            a1, j1 = params_of(i)
            rp = reports[i][-1]
            gain = (rp.cost0 - rp.cost) / max(rp.cost0, 1e-300)
            move.append(
                bool(
                    (
                        np.max(np.abs(a1 - a0), initial=0.0) > opt.converge_activation
                        or np.max(np.abs(j1 - j0)) > opt.converge_jaw
                    )
                    and gain > opt.converge_cost
                )
                or last_changes[i] > 0
                or rp.result == "nonlinear_max_steps_reached"
            )
        return cost, np.asarray(move, bool)

    for k in range(outer):
        cost, moving = step_and_track(k, list(range(R_)))
        if progress is not None:
            steps = max(reports[i][-1].steps for i in range(R_))
            progress(
                f"outer iteration {k + 1}/{outer}: cost {np.mean(cost):.4f} mm^2, steps {steps}"
            )

    def converge(unconverged: set) -> set:
        """Runs still converging go on at the final annealing, each until it stops; returns
        those that did not."""
        for r in range(max(int(opt.extra_iterations), 0)):
            act = sorted(unconverged)
            if not act:
                break
            cost, mv = step_and_track(outer - 1, act)
            unconverged = {i for i, m in zip(act, mv) if m}
            if progress is not None:
                progress(
                    f"extra iteration {r + 1}/{opt.extra_iterations} ({len(act)} runs still "
                    f"converging): cost {np.mean(cost):.4f} mm^2"
                )
        return unconverged

    unconverged = converge({i for i in range(R_) if moving[i]})

    def status_of(i) -> str:
        """Run ``i``'s status: its last inner solve's result, or ``"active_set_changing"`` /
        ``"outer_not_converged"`` where that succeeded but the fit had not settled."""
        status = reports[i][-1].result
        if status == "successful" and last_changes[i] > 0:
            return "active_set_changing"
        if status == "successful" and i in unconverged:
            return "outer_not_converged"
        return status

    # bound-flip restarts: a run with activations at the upper bound starts again from there
    # with those activations back at RESTART_ACTIVATION and every activation free
    n_restart = max(int(opt.restart_iterations), 0)
    spawned = []
    if n_restart:
        for i in range(R_):
            z = z_of(i)  # locked controls are held at z = 0
            hi = (np.asarray(activations_from_z(to_jax(z))) >= 1.0 - RESTART_BOUND_TOL) & ~locked
            if not _should_restart(opt.restart_when, bool(hi.any()), status_of(i) == "successful"):
                continue
            j = len(runs)
            runs.append(runs[i])
            z = np.where(hi, float(z_from_activations(RESTART_ACTIVATION)), z)
            y = dict(ys[i])
            y["z"] = to_jax(z)
            ys.append(y)
            free.append(np.where(locked, 0.0, 1.0))
            zfix.append(np.zeros(M))
            released.append(np.zeros(M, bool))
            cycled.append(np.zeros(M, bool))
            reports[j] = list(reports[i])
            last_changes.append(0)
            parent.append(i)
            flipped[j] = tuple(int(m) for m in np.flatnonzero(hi))
            spawned.append(j)
        mv = np.zeros(len(spawned), bool)
        for r in range(n_restart if spawned else 0):
            cost, mv = step_and_track(outer + r, spawned)
            if progress is not None:
                progress(
                    f"restart iteration {r + 1}/{n_restart} ({len(spawned)} runs with activations at 1): "
                    f"cost {np.mean(cost):.4f} mm^2"
                )
        unconverged |= converge({j for j, m in zip(spawned, mv) if m})
    R_all = len(runs)

    if opt.exact_steps > 0:
        for i in range(R_all):
            ys[i] = _exact_refine(
                forward, fit_ids, ys[i], last_pts[i], priors, opt, reports[i], len(reports[i])
            )
    Xr, skins, A = exact_skins(list(range(R_all)))
    total = time.perf_counter() - t0
    finals = []
    for i in range(R_all):
        c = corr_for(i, skins[i], outer - 1)
        finals.append((c, float(np.sum(c.weight * c.distance**2))))
    results = []
    for s_ in range(S):
        cand = [i for i, (ss, _) in enumerate(runs) if ss == s_]
        i = cand[int(np.argmin([finals[j][1] for j in cand]))]
        y = dict(ys[i])
        y["z"] = to_jax(z_of(i))
        c = finals[i][0]
        ok = c.weight > 0
        d = np.abs(c.distance[ok])
        status = status_of(i)
        restart = {}
        for j in cand:
            if parent[j] != j:
                restart = {
                    "controls": [names[m] for m in flipped[j]],
                    "cost_mm2": finals[j][1],
                    "parent_cost_mm2": finals[parent[j]][1],
                    "kept": bool(i == j),
                }
        results.append(
            PointFit(
                activations=np.asarray(A[i]),
                jaw=np.asarray(y["jaw"]),
                jaw_effective=np.asarray(response.clamp_jaw(y["jaw"])),
                rigid=np.asarray(y["rigid"]) if opt.rigid else np.zeros(6),
                centre=centre,
                skin=skins[i],
                y=jax.tree_util.tree_map(np.asarray, y),
                reports=reports[i],
                status=status,
                steps=int(sum(r.steps for r in reports[i])),
                seconds=total / max(S, 1),
                start_pitch=float(runs[i][1]),
                residual_mm={
                    "mean": float(d.mean()),
                    "median": float(np.median(d)),
                    "rms": float(np.sqrt(np.mean(d * d))),
                    "n": int(ok.sum()),
                    "weighted_cost_mm2": finals[i][1],
                },
                points=last_pts[i],
                starts={float(runs[j][1]): finals[j][1] for j in cand if parent[j] == j},
                at_bounds={
                    int(m): float(zfix[i][m]) for m in range(M) if free[i][m] == 0 and not locked[m]
                },
                restart=restart,
            )
        )
    return results


# --------------------------------------------------------------------------------------
# exact refinement through the rig
# --------------------------------------------------------------------------------------
def _points_from_vertices(xv, pts: PointSet):
    """``(K + L, 3)`` surface points (mm) of fit-vertex positions ``xv`` ``(P, 3)``."""
    return jnp.einsum("kc,kcd->kd", pts.bary, xv[pts.ids])


def _exact_refine(
    forward, fit_ids, y, pts: PointSet, priors: Priors, opt: FitOptions, reports, outer
):
    """Levenberg-Marquardt through the exact rig (forward-mode Jacobian of the PBD solve)
    with the last correspondences and active set."""
    t0 = time.perf_counter()
    fn = forward._fn
    fit_ids_j = to_jax(fit_ids)

    def resid(yy, args):
        pts_, pri = args
        a = activations_from_z(effective_z(yy, pts_))
        x = _points_from_vertices(fn(a, yy["jaw"])[fit_ids_j], pts_)
        if pri.use_rigid:
            x = apply_rigid(yy["rigid"], pts_.centre, x)
        out = residuals(yy, args)
        out["points"], out["landmarks"] = _point_residuals(x, pts_)
        return out

    cost = jax.jit(
        lambda yy, args: sum(jnp.sum(v * v) for v in jax.tree_util.tree_leaves(resid(yy, args)))
    )
    solver = optx.LevenbergMarquardt(rtol=opt.rtol, atol=opt.atol)
    c0 = float(cost(y, (pts, priors)))

    def run(y0, args):
        sol = optx.least_squares(
            resid, solver, y0, args=args, max_steps=int(opt.exact_steps), throw=False
        )
        return sol.value, sol.result._value, sol.stats["num_steps"]  # arrays only out of the jit

    yv, code, n_steps = jax.jit(run)(y, (pts, priors))
    c1 = float(cost(yv, (pts, priors)))
    reports.append(
        InnerReport(
            outer,
            "exact:" + result_name(int(code)),
            int(n_steps),
            c0,
            c1,
            int(np.sum(np.asarray(pts.w_point) > 0)),
            float("nan"),
            0,
            int(np.sum(np.asarray(pts.free) == 0)),
            time.perf_counter() - t0,
        )
    )
    return yv


# --------------------------------------------------------------------------------------
# conditioning
# --------------------------------------------------------------------------------------
def jacobian_conditioning(y, points: PointSet, priors: Priors, muscle_names: Sequence[str]) -> dict:
    """Conditioning of the fit's data Jacobian at ``y`` (forward mode, reduced model +
    defect, i.e. the exact rig's residuals to first order).

    The Jacobian is that of the point-to-plane and landmark residuals with respect to the
    *physical* parameters: activations (taken directly, so controls held at a bound get
    their column too), jaw pitch/yaw (deg) and protrusion (mm), rigid rotation (deg) and
    translation (mm).

    Returns:
        dict with ``singular_values`` per group (``"activations"``, ``"jaw"``, ``"rigid"``,
        ``"all"``), ``condition`` per group, ``parameters`` (column names), and per parameter:
        ``sensitivity`` (column norm: mm of weighted residual per unit) and ``vif`` (variance
        inflation factor ``(J^T J)^-1_ii (J^T J)_ii``: 1 = independent of the others; large
        = hard to tell apart from a combination of the others).
    """
    z = to_jax(y["z"])
    a0 = activations_from_z(jnp.where(points.free > 0, z, points.z_fixed))

    def phys(p):
        M = a0.shape[0]
        rig = p[M + 3 :] if priors.use_rigid else None
        r_pt, r_lm = _data_residuals(p[:M], p[M : M + 3], rig, points, priors.use_rigid)
        return jnp.concatenate([r_pt.ravel(), r_lm.ravel()])

    p0 = [a0, to_jax(y["jaw"])]
    if priors.use_rigid:
        p0.append(to_jax(y["rigid"]))
    p0 = jnp.concatenate(p0)
    Jm = np.asarray(jax.jit(jax.jacfwd(phys))(p0))
    M = int(a0.shape[0])
    groups = {"activations": np.arange(M), "jaw": np.arange(M, M + 3)}
    if priors.use_rigid:
        groups["rigid"] = np.arange(M + 3, M + 9)
    groups["all"] = np.arange(Jm.shape[1])
    out: dict[str, Any] = {"singular_values": {}, "condition": {}}
    for g, cols in groups.items():
        s = np.linalg.svd(Jm[:, cols], compute_uv=False)
        out["singular_values"][g] = s.tolist()
        out["condition"][g] = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    JtJ = Jm.T @ Jm
    sens = np.sqrt(np.diag(JtJ))
    try:
        inv = np.linalg.pinv(JtJ, rcond=1e-14)
        vif = np.diag(inv) * np.diag(JtJ)
    except np.linalg.LinAlgError:  # pragma: no cover
        vif = np.full(len(sens), np.inf)
    names = list(muscle_names) + ["jaw_pitch_deg", "jaw_yaw_deg", "jaw_protrusion_mm"]
    if priors.use_rigid:
        names += ["rot_x_deg", "rot_y_deg", "rot_z_deg", "t_x_mm", "t_y_mm", "t_z_mm"]
    out["parameters"] = names
    out["sensitivity"] = dict(zip(names, sens.tolist()))
    out["vif"] = dict(zip(names, vif.tolist()))
    return out
