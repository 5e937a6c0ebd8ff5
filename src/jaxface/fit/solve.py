"""Inverse fit, the outer loop: muscle activations, jaw pose and a small rigid correction from
scan points (issue 7).

Units and frame: millimetres, degrees; +y up, the face looks along +z, the subject's left is
+x. The fit works in the frame of the subject's *neutral scan* (where the rig lives);
:mod:`jaxface.fit.pipeline` moves expression scans into that frame first and the result back.

:func:`fit_points` fits a batch of scans. Each scan is fitted by one or more *runs* (one per
jaw start, plus bound-flip restarts), each a :class:`_Run`. Every outer iteration of a run:

1. one exact synthesis at its parameters (:class:`~jaxface.fit.forward.ForwardModel`), with
   its reverse pass when ``gradient_correction`` is on;
2. correspondences on that skin (:func:`~jaxface.fit.correspond.find_correspondences`), the
   rejection distance and Tukey floor annealed over ``outer_iterations``;
3. the inner problem's data (:class:`~jaxface.fit.residuals.PointSet`): the reduced model
   gathered at the matched points, the defect ``x_exact - x_reduced`` there, and the
   gradient correction;
4. inner solves (:func:`~jaxface.fit.inner.solve_inner`), repeated while the active set of the
   activation bounds changes (:class:`~jaxface.fit.active_set.ActiveSet`).

Runs still converging go on at the final annealing (``extra_iterations``); saturated runs may
restart (``restart_iterations``); the run with the lowest final robust cost wins its scan.
Status: ``"successful"`` only when the last inner solve met optimistix's tolerance, the active
set is stable and the outer iterations converged; otherwise the optimistix result name,
``"active_set_changing"`` or ``"outer_not_converged"``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import numpy as np

from .._arrays import to_jax
from .._parallel import thread_map
from ..errors import FitError
from .active_set import ActiveSet, locked_controls
from .correspond import Correspondences, ScanTargets, find_correspondences
from .forward import ForwardModel
from .inner import InnerReport, exact_refine, index_tree, solve_inner, stack_trees
from .options import RESTART_ACTIVATION, RESTART_BOUND_TOL, FitOptions, should_restart
from .params import Params, activations_from_z, rigid_numpy, z_from_activations
from .point_fit import PointFit
from .reduced import ResponseModel, evaluate_jit, gather_jit, landmark_pitch
from .residuals import PointSet, Priors, gradient_correction_from_vjp_jit, make_priors

__all__ = ["PointFit", "fit_points"]


@dataclass
class _Run:
    """One run: a scan fitted from one jaw start, or a restart of another run.

    Attributes:
        scan: index of its scan; start_pitch: its jaw start (deg).
        y: its current parameters; bounds: its active set.
        reports: its inner solves so far.
        parent: the run it restarted (its own index if none); flipped: the controls the
            restart set back inside.
        last_points: the data of its last inner solve; last_changes: active-set changes in
            the last round of its last outer iteration.
        unconverged: still converging when its extra iterations ran out.
    """

    scan: int
    start_pitch: float
    y: Params
    bounds: ActiveSet
    reports: list[InnerReport]
    parent: int
    flipped: tuple[int, ...] = ()
    last_points: PointSet | None = None
    last_changes: int = 0
    unconverged: bool = False


@dataclass
class _Fit:
    """The constants of one :func:`fit_points` call and its runs; the methods are the steps of
    the outer loop."""

    forward: ForwardModel
    response: ResponseModel
    fit_ids: np.ndarray
    face_triangles: np.ndarray
    scans: list[ScanTargets]
    landmark_bary: np.ndarray
    opt: FitOptions
    progress: Callable[[str], None] | None
    local: np.ndarray  # (V,) local fit-vertex id of each vertex, -1 outside
    lm_loc: np.ndarray  # (L, 3) local corner ids of the landmark triangles
    locked: np.ndarray  # (M,) controls held at 0
    centre: np.ndarray  # (3,) centre of the rigid correction, mm
    priors: Priors
    fit_ids_j: jax.Array  # fit_ids on the device
    runs: list[_Run] = field(default_factory=list)

    @property
    def n_outer(self) -> int:
        return max(int(self.opt.outer_iterations), 1)

    def say(self, text: str) -> None:
        if self.progress is not None:
            self.progress(text)

    # ---------------------------------------------------------------- exact model
    def z_of(self, run: _Run) -> np.ndarray:
        """The run's parameters ``z`` with the held activations at their bounds."""
        return run.bounds.effective_z(run.y.z)

    def placed(self, run: _Run, x: np.ndarray) -> np.ndarray:
        """The run's skin ``x`` (V, 3) with its rigid correction applied."""
        if self.opt.rigid:
            R, t = rigid_numpy(np.asarray(run.y.rigid), self.centre)
            x = x @ R.T + t
        return x

    def exact_skins(self, runs: Sequence[_Run]):
        """The runs' exact skins ``(B, V, 3)``, placed skins and activations."""
        A = [np.asarray(activations_from_z(to_jax(self.z_of(r)))) for r in runs]
        J = [np.asarray(r.y.jaw) for r in runs]
        X = self.forward.many(np.stack(A), np.stack(J))
        return X, [self.placed(r, x) for r, x in zip(runs, X)], A

    def exact_skin_vjp(self, run: _Run):
        """The run's exact skin, placed skin, activations and the skin's VJP: one forward
        pass serves the correspondences and the gradient correction."""
        a = activations_from_z(to_jax(self.z_of(run)))
        x, vjp = self.forward.with_vjp(a, run.y.jaw)
        x_np = np.asarray(x, np.float64)
        return x, x_np, self.placed(run, x_np), np.asarray(a), vjp

    def correspondences(self, run: _Run, skin: np.ndarray, k: int) -> Correspondences:
        """The run's scan points matched on ``skin`` at annealing step ``k``."""
        sc, opt = self.scans[run.scan], self.opt
        return find_correspondences(
            skin,
            self.forward.triangles,
            self.face_triangles,
            self.local,
            sc.points,
            sc.normals,
            sc.valid,
            max_distance=opt.anneal(opt.max_distance_mm, k),
            robust_floor=opt.anneal(opt.robust_floor_mm, k),
            max_normal_angle_deg=opt.max_normal_angle_deg,
        )

    def residual_data(self, run: _Run, k: int, exact=None) -> tuple[PointSet, Correspondences]:
        """The run's correspondences and inner-problem data (:class:`PointSet`): one exact
        synthesis (``exact``: ``(skin, placed skin, activations)`` already made) and, with the
        gradient correction, its reverse pass."""
        opt, response = self.opt, self.response
        if opt.gradient_correction:
            # the skin's forward pass, kept for the reverse pass of the correction below
            x_j, x_n, skin_n, a_n, vjp_n = self.exact_skin_vjp(run)
        else:
            assert exact is not None  # made by outer_step without the gradient correction
            x_n, skin_n, a_n = exact
        c = self.correspondences(run, skin_n, k)
        approx = np.asarray(evaluate_jit(response, to_jax(a_n), run.y.jaw))
        defect_v = x_n[self.fit_ids] - approx  # (P, 3): exact minus reduced model
        ids = np.concatenate([c.local, self.lm_loc])
        bary = np.concatenate([c.bary, np.asarray(self.landmark_bary)])
        gm = gather_jit(response, to_jax(ids), to_jax(bary))
        dfx = np.einsum("kc,kcd->kd", bary, defect_v[ids])
        sc = self.scans[run.scan]
        lw = np.where(np.asarray(sc.landmark_valid, bool), 1.0, 0.0)
        lw = opt.landmark_weight * sc.landmark_scale * lw / max(lw.sum(), 1.0)
        target = np.concatenate([c.target, np.asarray(sc.landmarks, np.float64)])
        target = np.where(np.isfinite(target), target, 0.0)
        pts = PointSet(
            model=gm,
            defect=to_jax(dfx),
            target=to_jax(target),
            normal=to_jax(c.normal),
            w_point=to_jax(c.weight),
            w_landmark=to_jax(lw),
            centre=to_jax(self.centre),
            ids=to_jax(ids),
            bary=to_jax(bary),
            free=to_jax(run.bounds.free),
            z_fixed=to_jax(run.bounds.z_fixed),
        )
        if opt.gradient_correction:
            u, p0, r0 = jax.block_until_ready(
                gradient_correction_from_vjp_jit(
                    x_j,
                    vjp_n,
                    self.fit_ids_j,
                    run.y,
                    pts,
                    self.priors.use_rigid,
                )
            )
            del vjp_n  # its residuals (one state per sweep) are freed here
            pts = dataclasses.replace(pts, grad_u=u, grad_p=p0, grad_r=r0)
        return pts, c

    # ---------------------------------------------------------------- one outer iteration
    def outer_step(self, k: int, act: list[int]) -> np.ndarray:
        """One outer iteration of the runs ``act`` (correspondences at annealing step ``k``,
        batched inner solves, active-set rounds); returns their inner costs (mm^2)."""
        opt = self.opt
        runs = [self.runs[i] for i in act]
        t_it = time.perf_counter()
        exact = None
        if not opt.gradient_correction:
            Xr, skins, A = self.exact_skins(runs)
            exact = list(zip(Xr, skins, A))
        # the runs' exact passes are independent: on the thread pool they keep both cores of a
        # 2-core CPU busy
        done = thread_map(
            lambda nr: self.residual_data(nr[1], k, None if exact is None else exact[nr[0]]),
            list(enumerate(runs)),
            outer=True,
        )
        corrs = [d[1] for d in done]
        P = stack_trees([d[0] for d in done])
        Y0 = stack_trees([r.y for r in runs])
        n_act = len(act)
        tot_steps = np.zeros(n_act, np.int64)
        cost0_first = None
        changes = np.zeros(n_act, np.int64)
        res_k = [""] * n_act
        cost_k = np.zeros(n_act)
        settled = np.zeros(n_act, bool)
        for _ in range(max(int(opt.active_set_rounds), 1)):
            # same correspondences; re-solve while the active set of the bounds changes. A run
            # whose set settled keeps that solve (a scan's fit does not depend on its batch);
            # on an accelerator every solve of this fit is padded to the batch size of all its
            # runs, so the subsets that go on compile nothing new
            out = solve_inner(Y0, P, self.priors, opt, pad_to=len(self.runs))
            cost0_first = out.cost0 if cost0_first is None else cost0_first
            flat = np.concatenate(
                [np.asarray(v).reshape(n_act, -1) for v in jax.tree_util.tree_leaves(out.y)],
                axis=1,
            )
            for n, run in enumerate(runs):
                if not settled[n] and not np.all(np.isfinite(flat[n])):
                    raise FitError(
                        f"the inner solve of scan {run.scan} returned non-finite parameters at "
                        f"outer iteration {k} (optimistix result: {out.result[n]})."
                    )
            for n, run in enumerate(runs):
                if settled[n]:
                    continue
                tot_steps[n] += out.steps[n]
                res_k[n], cost_k[n] = out.result[n], out.cost[n]
                yi = index_tree(out.y, n)
                z, n_ch = run.bounds.update(
                    out.activations[n],
                    out.grad_activations[n],
                    yi.z,
                    locked=self.locked,
                    tol_g=opt.release_gradient,
                )
                run.y = yi.with_z(to_jax(z))
                changes[n] = n_ch
                settled[n] = n_ch == 0
            if settled.all():
                break
            P = eqx.tree_at(
                lambda p: (p.free, p.z_fixed),
                P,
                (
                    to_jax(np.stack([r.bounds.free for r in runs])),
                    to_jax(np.stack([r.bounds.z_fixed for r in runs])),
                ),
            )
            Y0 = stack_trees([r.y for r in runs])
        assert cost0_first is not None
        dt = time.perf_counter() - t_it
        for n, run in enumerate(runs):
            run.last_changes = int(changes[n])
            run.reports.append(
                InnerReport(
                    len(run.reports),
                    res_k[n],
                    int(tot_steps[n]),
                    float(cost0_first[n]),
                    float(cost_k[n]),
                    corrs[n].n_accepted,
                    corrs[n].scale_mm,
                    int(changes[n]),
                    run.bounds.n_held(self.locked),
                    dt,
                )
            )
            run.last_points = index_tree(P, n)
        return cost_k

    def params_of(self, run: _Run) -> tuple[np.ndarray, np.ndarray]:
        a = np.asarray(activations_from_z(to_jax(self.z_of(run))))
        return a, np.asarray(run.y.jaw, np.float64)

    def step_and_track(self, k: int, act: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`outer_step`, and whether each run is still converging: its inner cost fell
        by more than ``converge_cost`` (relative) and ``converge_cost_mm2`` (absolute) and its
        parameters moved by more than their tolerances, or its active set still changed in the
        iteration's last round, or its inner solve stopped at ``max_steps``."""
        opt = self.opt
        before = [self.params_of(self.runs[i]) for i in act]
        cost = self.outer_step(k, act)
        move = []
        for (a0, j0), i in zip(before, act):
            run = self.runs[i]
            a1, j1 = self.params_of(run)
            rp = run.reports[-1]
            gain = (rp.cost0 - rp.cost) / max(rp.cost0, 1e-300)
            move.append(
                bool(
                    (
                        np.max(np.abs(a1 - a0), initial=0.0) > opt.converge_activation
                        or np.max(np.abs(j1 - j0)) > opt.converge_jaw
                    )
                    and gain > opt.converge_cost
                    and rp.cost0 - rp.cost > opt.converge_cost_mm2
                )
                or run.last_changes > 0
                or rp.result == "nonlinear_max_steps_reached"
            )
        return cost, np.asarray(move, bool)

    # ---------------------------------------------------------------- phases
    def anneal_all(self) -> set[int]:
        """The annealed outer iterations of every run; returns the runs still moving."""
        act = list(range(len(self.runs)))
        moving = np.zeros(len(act), bool)
        for k in range(self.n_outer):
            cost, moving = self.step_and_track(k, act)
            steps = max(self.runs[i].reports[-1].steps for i in act)
            self.say(
                f"outer iteration {k + 1}/{self.n_outer}: cost {np.mean(cost):.4f} mm^2, "
                f"steps {steps}"
            )
        return {i for i in act if moving[i]}

    def converge(self, unconverged: set[int]) -> None:
        """Runs still converging go on at the final annealing, each until it stops; those
        that did not stop are marked ``unconverged``."""
        for r in range(max(int(self.opt.extra_iterations), 0)):
            act = sorted(unconverged)
            if not act:
                break
            cost, mv = self.step_and_track(self.n_outer - 1, act)
            unconverged = {i for i, m in zip(act, mv) if m}
            self.say(
                f"extra iteration {r + 1}/{self.opt.extra_iterations} ({len(act)} runs still "
                f"converging): cost {np.mean(cost):.4f} mm^2"
            )
        for i in unconverged:
            self.runs[i].unconverged = True

    def status_of(self, run: _Run) -> str:
        """The run's status: its last inner solve's result, or ``"active_set_changing"`` /
        ``"outer_not_converged"`` where that succeeded but the fit had not settled."""
        status = run.reports[-1].result
        if status == "successful" and run.last_changes > 0:
            return "active_set_changing"
        if status == "successful" and run.unconverged:
            return "outer_not_converged"
        return status

    def restart(self) -> None:
        """Bound-flip restarts: a run with activations at the upper bound starts again from
        there with those activations back at ``RESTART_ACTIVATION`` and every activation
        free, for ``restart_iterations`` more outer iterations (then converges)."""
        opt = self.opt
        n_restart = max(int(opt.restart_iterations), 0)
        if not n_restart:
            return
        spawned = []
        for i in range(len(self.runs)):
            run = self.runs[i]
            z = self.z_of(run)  # locked controls are held at z = 0
            hi = (np.asarray(activations_from_z(to_jax(z))) >= 1.0 - RESTART_BOUND_TOL) & ~(
                self.locked
            )
            if not should_restart(
                opt.restart_when, bool(hi.any()), self.status_of(run) == "successful"
            ):
                continue
            z = np.where(hi, float(z_from_activations(RESTART_ACTIVATION)), z)
            spawned.append(len(self.runs))
            self.runs.append(
                _Run(
                    scan=run.scan,
                    start_pitch=run.start_pitch,
                    y=run.y.with_z(to_jax(z)),
                    bounds=ActiveSet.start(self.locked),
                    reports=list(run.reports),
                    parent=i,
                    flipped=tuple(int(m) for m in np.flatnonzero(hi)),
                )
            )
        mv = np.zeros(len(spawned), bool)
        for r in range(n_restart if spawned else 0):
            cost, mv = self.step_and_track(self.n_outer + r, spawned)
            self.say(
                f"restart iteration {r + 1}/{n_restart} ({len(spawned)} runs with activations "
                f"at 1): cost {np.mean(cost):.4f} mm^2"
            )
        self.converge({j for j, m in zip(spawned, mv) if m})

    def results(self, t0: float) -> list[PointFit]:
        """The exact skins of every run, their final robust costs, and per scan the run with
        the lowest one."""
        opt, runs = self.opt, self.runs
        Xr, skins, A = self.exact_skins(runs)
        total = time.perf_counter() - t0
        finals = []
        for run, skin in zip(runs, skins):
            c = self.correspondences(run, skin, self.n_outer - 1)
            finals.append((c, float(np.sum(c.weight * c.distance**2))))
        S = len(self.scans)
        names = list(self.forward.muscle_names)
        results = []
        for s_ in range(S):
            cand = [i for i, r in enumerate(runs) if r.scan == s_]
            i = cand[int(np.argmin([finals[j][1] for j in cand]))]
            run = runs[i]
            y = run.y.with_z(to_jax(self.z_of(run)))
            c = finals[i][0]
            ok = c.weight > 0
            d = np.abs(c.distance[ok])
            restart = {}
            for j in cand:
                if runs[j].parent != j:
                    restart = {
                        "controls": [names[m] for m in runs[j].flipped],
                        "cost_mm2": finals[j][1],
                        "parent_cost_mm2": finals[runs[j].parent][1],
                        "kept": bool(i == j),
                    }
            results.append(
                PointFit(
                    activations=np.asarray(A[i]),
                    jaw=np.asarray(y.jaw),
                    jaw_effective=np.asarray(self.response.clamp_jaw(y.jaw)),
                    rigid=np.asarray(y.rigid) if opt.rigid else np.zeros(6),
                    centre=self.centre,
                    skin=skins[i],
                    y=jax.tree_util.tree_map(np.asarray, y),
                    reports=run.reports,
                    status=self.status_of(run),
                    steps=int(sum(r.steps for r in run.reports)),
                    seconds=total / max(S, 1),
                    start_pitch=float(run.start_pitch),
                    residual_mm={
                        "mean": float(d.mean()),
                        "median": float(np.median(d)),
                        "rms": float(np.sqrt(np.mean(d * d))),
                        "n": int(ok.sum()),
                        "weighted_cost_mm2": finals[i][1],
                    },
                    points=run.last_points,
                    starts={
                        float(runs[j].start_pitch): finals[j][1]
                        for j in cand
                        if runs[j].parent == j
                    },
                    at_bounds=run.bounds.at_bounds(self.locked),
                    restart=restart,
                )
            )
        return results


def fit_points(
    forward: ForwardModel,
    response: ResponseModel,
    fit_ids: np.ndarray,
    face_triangles: np.ndarray,
    scans: Sequence[ScanTargets | Mapping[str, Any]],
    landmark_tri: np.ndarray,
    landmark_bary: np.ndarray,
    options: FitOptions | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> list[PointFit]:
    """Fit activations, jaw and rigid correction to a batch of scans of one subject.

    Arguments:
        forward: the exact rig (:class:`~jaxface.fit.forward.ForwardModel`).
        response: its :class:`~jaxface.fit.reduced.ResponseModel` over the vertices ``fit_ids``.
        fit_ids: ``(P,)`` vertex ids of the response model (every vertex of the face
            triangles and of the landmark triangles).
        face_triangles: ``(F,)`` bool, the rig skin's face region.
        scans: one :class:`ScanTargets` (or a mapping with its fields) per scan.
        landmark_tri, landmark_bary: ``(L,)`` / ``(L, 3)`` the landmarks on the rig skin.
        options: :class:`~jaxface.fit.options.FitOptions`.
        progress: called with a short text after each outer iteration.

    Returns:
        one :class:`PointFit` per scan.

    Raises:
        FitError: non-finite parameters after a solve, no correspondence, a scan without its
            data, or unknown controls in ``options.controls``.
    """
    opt = options or FitOptions()
    t0 = time.perf_counter()
    targets = [ScanTargets.of(s) for s in scans]
    tris = forward.triangles
    M = forward.n_controls
    names = list(forward.muscle_names)
    local = np.full(len(forward.rest), -1, np.int64)
    local[np.asarray(fit_ids)] = np.arange(len(fit_ids))
    lm_loc = local[tris[np.asarray(landmark_tri)]]
    if np.any(lm_loc < 0):
        raise FitError("internal: a landmark triangle corner is missing from the fit-vertex set.")
    locked = locked_controls(names, response.sampled, opt.controls)
    fit = _Fit(
        forward=forward,
        response=response,
        fit_ids=fit_ids,
        face_triangles=face_triangles,
        scans=targets,
        landmark_bary=landmark_bary,
        opt=opt,
        progress=progress,
        local=local,
        lm_loc=lm_loc,
        locked=locked,
        centre=np.asarray(response.rest).mean(axis=0),
        priors=make_priors(names, opt),
        fit_ids_j=to_jax(np.asarray(fit_ids)),
    )
    # runs: (scan, start pitch), solved together in every batched inner solve
    if opt.jaw_starts is None:
        starts = [
            (s, landmark_pitch(response, lm_loc, landmark_bary, sc.landmarks, sc.landmark_valid))
            for s, sc in enumerate(targets)
        ]
    else:
        starts = [
            (s, float(p)) for s in range(len(targets)) for p in (list(opt.jaw_starts) or [0.0])
        ]
    for s, pitch in starts:
        y = Params.initial(M, pitch, opt.init_activation, opt.rigid)
        z = np.asarray(y.z).copy()
        z[locked] = 0.0
        fit.runs.append(
            _Run(
                scan=s,
                start_pitch=pitch,
                y=y.with_z(to_jax(z)),
                bounds=ActiveSet.start(locked),
                reports=[],
                parent=len(fit.runs),
            )
        )
    fit.converge(fit.anneal_all())
    fit.restart()
    if opt.exact_steps > 0:
        for run in fit.runs:
            assert run.last_points is not None
            run.y, report = exact_refine(
                forward, fit_ids, run.y, run.last_points, fit.priors, opt, len(run.reports)
            )
            run.reports.append(report)
    return fit.results(t0)
