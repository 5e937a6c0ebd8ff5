"""The result of fitting one expression scan, :class:`ExpressionFit` (activations, jaw pose, AU
intensities, fitted skin in mm, metrics, baselines), and its ``<stem>.json`` contract
(:data:`JSON_KEYS`), fitted mesh and picture."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..anatomy.frame import face_axes
from ..atomic import ensure_out_dir, write_json_atomic
from ..errors import LandmarkError
from ..facs import intensity_letters, sided_aus
from ..mesh import save_mesh
from ..render import Layer, draw, save_figure
from .metrics import SurfaceIndex
from .options import FitOptions
from .params import rigid_numpy
from .point_fit import PointFit

#: The largest angle (degrees) between the face's measured left / up / forward and +x / +y /
#: +z for the JSON to call the scan's frame the project's convention.
FRAME_TOLERANCE_DEG = 30.0

__all__ = ["ExpressionFit", "JSON_KEYS"]

#: top-level keys of the ``<stem>.json`` written by :meth:`ExpressionFit.write`
JSON_KEYS = (
    "activations",
    "au_intensities",
    "au_intensity_letters",
    "au_from_activations",
    "au_motion_mm",
    "au_readout",
    "jaw",
    "rigid",
    "metrics",
    "baselines",
    "solver",
    "frame",
    "quality",
    "arkit",
    "arkit_detail",
)


@dataclass
class ExpressionFit:
    """The fit of one expression scan (see :meth:`to_dict` for the JSON contract).

    Attributes:
        stem: the scan's file stem; scan: the :class:`jaxface.io.Scan`.
        alignment: :class:`jaxface.fit.align.AlignmentResult` (scan -> neutral frame).
        fit: the :class:`~jaxface.fit.solve.PointFit` (neutral frame).
        fitted: the fitted skin, :class:`jaxface.mesh.TriMesh` in the scan's own frame, mm.
        fitted_landmarks: the rig's landmarks on it (scan frame, mm).
        activations: muscle -> activation.
        au_intensities: AU -> intensity in [0, 1]: the fewest AUs that reproduce the fit's
            skin motion, calibrated (:func:`jaxface.fit.au_motion.read_aus`).
        au_from_activations: AU -> intensity, the AU table's inverse of the fitted activations
            (:func:`jaxface.facs.au_intensities`): how hard each AU's muscles work, including
            controls the motion does not need.
        au_motion_mm: AU -> RMS skin motion (mm) that AU's share of the fit produces alone
            (:func:`jaxface.fit.au_motion.au_skin_motion`).
        au_readout: the :class:`~jaxface.fit.au_motion.AuReadout` behind ``au_intensities``
            (its misfit and each AU's removal effect, mm), or None.
        metrics: :class:`jaxface.fit.metrics.FitMetrics` of the fit; baselines: ``{"B0":
            FitMetrics, "B1": FitMetrics}``; baseline_meshes: ``{"B0": TriMesh, "B1": TriMesh}``.
        muscle_names: the rig's control order.
        arkit: ARKit-52 name -> coefficient in [0, 1] read from the fitted skin motion
            (:mod:`jaxface.interop.arkit`), or None when unavailable; arkit_detail: each
            coefficient's contribution (mm), the residual (mm), or the reason it is missing.
    """

    stem: str
    scan: Any
    alignment: Any
    fit: PointFit
    fitted: Any
    fitted_landmarks: Any
    activations: dict
    au_intensities: dict
    au_motion_mm: dict
    metrics: Any
    baselines: dict
    baseline_meshes: dict
    muscle_names: tuple
    backend: str
    options: FitOptions
    notes: list = field(default_factory=list)
    face_mask: np.ndarray | None = None
    au_from_activations: dict = field(default_factory=dict)
    au_readout: Any = None
    quality: Any = None
    arkit: dict | None = None
    arkit_detail: dict = field(default_factory=dict)

    @property
    def status(self) -> str:
        return self.fit.status

    @property
    def jaw(self) -> dict:
        j = self.fit.jaw_effective
        return {"pitch_deg": float(j[0]), "yaw_deg": float(j[1]), "protrusion_mm": float(j[2])}

    def rigid_dict(self) -> dict:
        R, t = rigid_numpy(self.fit.rigid, self.fit.centre)
        Tn = self.alignment.transform  # scan -> neutral
        # fitted skin in the scan frame = Tn^-1 (R x + t) for rig coordinates x
        Ti = Tn.inverse()
        M = Ti.rotation @ R
        tt = Ti.rotation @ t + Ti.translation
        return {
            "alignment": {
                "description": "scan frame -> neutral scan frame (p_neutral = R p_scan + t), mm",
                **self.alignment.to_dict(),
            },
            "correction": {
                "description": "fitted rigid correction in the neutral frame: x -> c + R(w) (x - c) + t",
                "rotation_vector_deg": [float(x) for x in self.fit.rigid[:3]],
                "translation_mm": [float(x) for x in self.fit.rigid[3:]],
                "centre_mm": [float(x) for x in self.fit.centre],
            },
            "rig_to_scan": {
                "description": "rig (registered neutral) coordinates -> this scan's frame: p = R x + t, mm",
                "rotation": M.tolist(),
                "translation": tt.tolist(),
            },
        }

    def solver_dict(self) -> dict:
        f = self.fit
        return {
            "status": f.status,
            "converged": f.status == "successful",
            "steps": f.steps,
            "time_s": f.seconds,
            "method": "optimistix LevenbergMarquardt (forward-mode Jacobian) on the rig's reduced model "
            "with exact-rig defect correction; correspondences refreshed per outer iteration"
            + (
                f"; {self.options.exact_steps} exact-rig LM steps at the end"
                if self.options.exact_steps
                else ""
            ),
            "backend": self.backend,
            "outer_iterations": [r.to_dict() for r in f.reports],
            "jaw_start_pitch_deg": f.start_pitch,
            "jaw_as_fitted": {
                "pitch_deg": float(f.jaw[0]),
                "yaw_deg": float(f.jaw[1]),
                "protrusion_mm": float(f.jaw[2]),
            },
            "residual_mm": f.residual_mm,
            "restart": dict(f.restart) if f.restart else None,
            "notes": list(self.notes),
        }

    def frame_dict(self) -> dict:
        """The input scan's frame, as measured: the face's left, up and forward directions in
        the scan's coordinates from its landmarks (:func:`jaxface.anatomy.frame.face_axes`),
        and whether they follow the project's convention (each within 30 degrees of +x, +y,
        +z). The fit runs in the scan's frame whatever it is; only the words change."""
        out: dict[str, Any] = {
            "name": "scan",
            "description": "the input scan's own coordinate frame (the .fitted.ply and every "
            "landmark and metric are in it)",
            "scan": str(getattr(self.scan, "path", "") or self.stem),
            "units": "mm",
        }
        try:
            axes = face_axes(self.scan.landmarks)
        except LandmarkError as e:
            out["axes"] = f"not measured ({e})"
            out["face_axes"] = None
            out["conventional"] = None
            return out
        angles = np.degrees(np.arccos(np.clip(np.diag(axes), -1.0, 1.0)))
        conventional = bool(np.all(angles <= FRAME_TOLERANCE_DEG))
        names = ("left", "up", "forward")
        out["face_axes"] = {n: [round(float(v), 4) for v in a] for n, a in zip(names, axes)}
        out["angles_to_convention_deg"] = {n: round(float(a), 1) for n, a in zip(names, angles)}
        out["conventional"] = conventional
        if conventional:
            out["axes"] = (
                "+y up, +z toward the viewer (the face looks along +z), subject's left +x "
                f"(measured from the landmarks: within {float(angles.max()):.0f} degrees)"
            )
        else:
            v = out["face_axes"]
            out["axes"] = (
                "not the convention (+y up, +z forward, subject's left +x): in this scan's "
                f"frame the face's up is {tuple(v['up'])}, it looks along {tuple(v['forward'])} "
                f"and its left is {tuple(v['left'])} (from the landmarks)"
            )
        return out

    def to_dict(self) -> dict:
        """The JSON contract of ``jaxface fit`` (mm, degrees)."""
        return {
            "scan": self.stem,
            "activations": {k: float(v) for k, v in self.activations.items()},
            "au_intensities": {k: float(v) for k, v in self.au_intensities.items()},
            "au_intensity_letters": intensity_letters(self.au_intensities),
            "au_motion_mm": {k: float(v) for k, v in self.au_motion_mm.items()},
            "au_from_activations": {k: float(v) for k, v in self.au_from_activations.items()},
            "au_readout": None if self.au_readout is None else self.au_readout.to_dict(),
            "jaw": self.jaw,
            "rigid": self.rigid_dict(),
            "metrics": self.metrics.to_dict(),
            "baselines": {k: v.to_dict() for k, v in self.baselines.items()},
            "solver": self.solver_dict(),
            "frame": self.frame_dict(),
            "quality": None if self.quality is None else self.quality.to_dict(),
            "arkit": None if self.arkit is None else {k: float(v) for k, v in self.arkit.items()},
            "arkit_detail": dict(self.arkit_detail),
        }

    def strongest_aus(
        self,
        n: int = 5,
        *,
        bilateral_only: bool = False,
        by: str = "intensity",
        sided: bool = False,
    ) -> list[tuple[str, float]]:
        """The ``n`` strongest AUs, strongest first: ``(name, intensity)`` with
        ``by="intensity"`` (:attr:`au_intensities`, the fewest AUs that reproduce the motion),
        ``(name, mm)`` with ``by="motion"`` (:attr:`au_motion_mm`, the skin motion each AU's
        share of the activations accounts for), ``(name, intensity)`` with
        ``by="activations"`` (:attr:`au_from_activations`, the table's inverse of the
        activations). ``bilateral_only`` leaves the ``L``/``R`` entries out; ``sided`` lists
        the AUs as FACS codes them (:func:`jaxface.facs.sided_aus`: once where both sides
        agree within 0.1, else per side; none below 0.005), and overrides
        ``bilateral_only``."""
        srcs = {
            "intensity": self.au_intensities,
            "motion": self.au_motion_mm,
            "activations": self.au_from_activations,
        }
        if by == "sparse":
            raise ValueError(
                "by='sparse' is gone: the sparse readout is now au_intensities (by='intensity'); "
                "the table's inverse of the activations is by='activations'."
            )
        if by not in srcs:
            raise ValueError(f"by must be 'intensity', 'motion' or 'activations', got {by!r}.")
        src = srcs[by]
        if sided:
            return sided_aus(src, n)
        items = [(k, v) for k, v in src.items() if not (bilateral_only and k[-1] in "LR")]
        return sorted(items, key=lambda kv: -kv[1])[:n]

    def write(self, out_dir, *, pictures: bool = False) -> dict[str, Path]:
        """Write ``<stem>.json``, ``<stem>.fitted.ply`` (and ``<stem>.fit.png``). Returns the
        paths."""
        out = ensure_out_dir(out_dir)
        files = {}
        p = out / f"{self.stem}.json"
        write_json_atomic(p, _jsonable(self.to_dict()))
        files["json"] = p
        m = out / f"{self.stem}.fitted.ply"
        save_mesh(m, self.fitted, units="mm")
        files["ply"] = m
        if pictures:
            files["picture"] = self.picture(out / f"{self.stem}.fit.png")
        return files

    def picture(self, path) -> Path:
        """Before/after panel: the scan, B0 (before), the fit, and the fit coloured by its
        distance to the scan (mm, colour bar)."""
        import os

        os.environ.setdefault("MPLBACKEND", "Agg")
        import matplotlib
        import matplotlib.cm
        import matplotlib.colors
        from matplotlib.figure import Figure

        v, tr, _ = self.scan.mesh_arrays()
        fv = np.asarray(self.fitted.vertices)
        ft = np.asarray(self.fitted.triangles)
        face = self._face_mask()
        err = np.full(len(fv), np.nan)
        cp = SurfaceIndex(v, tr).query(fv[face], max_distance=20.0)
        e = np.where(cp.on_boundary, np.nan, cp.distances)
        err[face] = e
        hi = float(np.nanpercentile(err, 98)) if np.isfinite(err).any() else 1.0
        hi = max(hi, 0.5)
        ftri = face[ft].all(axis=1)
        sub = ft[ftri]
        b0 = self.baseline_meshes["B0"]
        bounds = np.stack([v.min(0), v.max(0)])
        panels = [
            ("scan", Layer(v, tr)),
            ("before (B0: neutral)", Layer(np.asarray(b0.vertices), sub)),
            ("fit", Layer(fv, sub)),
            (
                "fit: distance to scan",
                Layer(
                    fv, sub, scalars=err, cmap="magma", vmin=0.0, vmax=hi, shade=0.55, specular=0.04
                ),
            ),
        ]
        dpi, px = 100, 360
        fig = Figure(figsize=(len(panels) * px / dpi + 1.0, px / dpi + 0.4), dpi=dpi)
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        fig.subplots_adjust(
            left=0.005, right=1.0 - 1.0 / fig.get_figwidth(), bottom=0.01, top=0.88, wspace=0.02
        )
        for ax, (name, layer) in zip(axes, panels):
            draw(ax, [layer], "front", width=px, height=px, bounds=bounds, title=name)
        sm = matplotlib.cm.ScalarMappable(
            norm=matplotlib.colors.Normalize(0.0, hi), cmap=matplotlib.colormaps["magma"]
        )
        cax = fig.add_axes((1.0 - 0.8 / fig.get_figwidth(), 0.12, 0.18 / fig.get_figwidth(), 0.7))
        fig.colorbar(sm, cax=cax).set_label("distance to scan (mm)")
        s = self.metrics.scan_to_fit["all"]
        fig.suptitle(
            f"{self.stem}: scan-to-fit mean {s.mean:.2f} mm (B0 "
            f"{self.baselines['B0'].scan_to_fit['all'].mean:.2f} mm), status {self.status}",
            fontsize=10,
        )
        return save_figure(fig, path)

    def _face_mask(self) -> np.ndarray:
        m = self.face_mask
        return np.ones(len(self.fitted.vertices), bool) if m is None else np.asarray(m, bool)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x
