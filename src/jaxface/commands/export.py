"""``jaxface export``: a subject's physical rig and fits as a glTF 2.0 binary (``.glb``).

Contract::

    jaxface export SUBJECT_OR_MESH --out rig.glb [--landmarks FACE.lm3] [--fit S.json ...]
                   [--exact] [--arkit] [--no-muscles] [--no-aus] [--ict ict_face.npz]

``SUBJECT_OR_MESH``: ``default`` (the embedded head: skin, eyes, teeth), a face mesh
``.ply``/``.obj`` with its ``.lm3`` (the rig is built on it; teeth from the estimated skull;
no eyes), or a neutral scan ``.bnt`` (the default head registered to it exactly as ``jaxface
fit`` does, eyes and teeth carried along: export this to animate that subject's fits).

The ``.glb`` (metres, +y up, +z forward): node ``skin`` with morph targets named
``muscle.<control>`` (each control at activation 1), ``AU<n>`` (each AU at intensity 1), with
``--arkit`` the 52 ARKit names (the ICT shapes cloned onto the subject; ``tongueOut`` zero),
with ``--exact`` ``fit.<stem>`` (each fit's exact fitted skin); nodes ``eye_left``,
``eye_right``, ``upper_teeth``, ``lower_teeth`` where present; with ``--fit`` an animation
``fits``, one keyframe per fit at 1 s spacing: weights = the fit's activations on the
``muscle.*`` targets (a linear blend of the exact per-control shapes), or with ``--exact``
weight 1 on that fit's own target and 0 elsewhere (reproduces the fitted skin exactly).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, List  # noqa: UP035

import numpy as np
import typer

__all__ = ["register", "ExportSubject", "load_export_subject", "run_export"]


@dataclass
class ExportSubject:
    """What is exported: the rig, its rest skin (mm), rigid parts, landmarks, face mask."""

    rig: Any
    rest: np.ndarray
    triangles: np.ndarray
    parts: list = field(default_factory=list)
    landmarks: Any = None
    face_mask: np.ndarray | None = None
    description: str = ""


def load_export_subject(
    source, landmarks: Path | None = None, *, units: str = "mm", progress=None
) -> ExportSubject:
    """Build the subject: ``"default"``, a mesh path (with landmarks) or a ``.bnt`` neutral
    scan (registered like :func:`jaxface.fit.pipeline.prepare_subject`).

    Raises:
        DataNotFoundError / LandmarkError: missing files; RigError / FitError: rig or
            registration failure.
    """
    from ..anatomy.rig import build_rig
    from ..errors import DataNotFoundError
    from ..head import generic_head
    from ..interop.gltf import GltfPart

    say = progress or (lambda s: None)
    if str(source) == "default":
        head = generic_head()
        say("building the rig of the default head")
        rig = build_rig(head)
        parts = [
            GltfPart("eye_left", head.eyes[0].vertices, head.eyes[0].triangles),
            GltfPart("eye_right", head.eyes[1].vertices, head.eyes[1].triangles),
            GltfPart("upper_teeth", head.upper_teeth.vertices, head.upper_teeth.triangles),
            GltfPart("lower_teeth", head.lower_teeth.vertices, head.lower_teeth.triangles),
        ]
        return ExportSubject(
            rig,
            np.asarray(rig.rest, np.float64),
            np.asarray(rig.triangles),
            parts,
            head.landmarks,
            np.asarray(head.face_mask, bool),
            "the default head",
        )
    path = Path(source)
    if not path.is_file():
        raise DataNotFoundError(
            f"{path} not found: give 'default', a face mesh (.ply/.obj with .lm3) or a neutral "
            "scan (.bnt)."
        )
    if path.suffix.lower() == ".bnt":
        from ..fit.metrics import SurfaceIndex
        from ..fit.pipeline import warp_teeth
        from ..fit.register import register_template
        from ..io import load_scan

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scan = load_scan(path, landmarks=landmarks)
        head = generic_head()
        say("registering the default head to the neutral scan")
        v, tr, _ = scan.mesh_arrays()
        reg = register_template(scan, template=head, scan_index=SurfaceIndex(v, tr))
        upper, lower = warp_teeth(head, reg)
        eyes = warp_teeth(SimpleNamespace(upper_teeth=head.eyes[0], lower_teeth=head.eyes[1]), reg)
        say("building the rig on the registered neutral")
        rig = build_rig(reg.mesh, reg.landmarks, upper_teeth=upper, lower_teeth=lower)
        parts = [
            GltfPart(n, m.vertices, m.triangles)
            for n, m in zip(
                ("eye_left", "eye_right", "upper_teeth", "lower_teeth"), (*eyes, upper, lower)
            )
            if m is not None
        ]
        return ExportSubject(
            rig,
            np.asarray(rig.rest, np.float64),
            np.asarray(rig.triangles),
            parts,
            reg.landmarks,
            np.asarray(reg.face_mask, bool),
            f"the default head registered to {path.name}",
        )
    from .clone import load_face

    m, lm = load_face(path, units, landmarks, "face mesh")
    say("building the rig on the mesh")
    rig = build_rig(m, lm)
    parts = []
    skull = getattr(getattr(rig, "info", None), "skull", None)
    for n in ("upper_teeth", "lower_teeth"):
        t = getattr(skull, n, None)
        if t is not None:
            parts.append(GltfPart(n, t.vertices, t.triangles))
    return ExportSubject(
        rig, np.asarray(rig.rest, np.float64), np.asarray(rig.triangles), parts, lm, None, path.name
    )


def run_export(
    subject: ExportSubject,
    out: Path,
    *,
    fits: list[Path] = (),  # type: ignore[assignment]
    exact: bool = False,
    arkit: bool = False,
    muscles: bool = True,
    aus: bool = True,
    controls=None,
    au_names=None,
    ict=None,
    progress=None,
) -> dict:
    """Write the ``.glb`` (see the module doc). Returns a summary: target names, keyframes,
    file size, seconds.

    Args:
        controls, au_names: restrict the muscle / AU targets (default all).
        ict: ``ict_face.npz`` for ``arkit`` (default ``$JAXFACE_ICT`` / the shared folder).

    Raises:
        DataNotFoundError: ``arkit`` without ICT data; FitError: a fit of another subject.
    """
    from ..interop.arkit import ARKIT_NAMES, transfer_ict_basis
    from ..interop.gltf import build_gltf, write_glb
    from ..interop.targets import FIT_PREFIX, MUSCLE_PREFIX, read_fit, rig_targets

    say = progress or (lambda s: None)
    t0 = time.perf_counter()
    targets = rig_targets(
        subject.rig,
        controls=(controls if muscles else []),
        aus=(au_names if aus else []),
        progress=lambda n: say(f"synthesising {n}"),
    )
    notes = []
    if arkit:
        say("cloning the ICT ARKit shapes onto the subject")
        basis = transfer_ict_basis(
            subject.rest, subject.triangles, subject.landmarks, subject.face_mask, ict_path=ict
        )
        targets += [(n, basis.deltas[k]) for k, n in enumerate(ARKIT_NAMES)]
        notes += [
            f"{n}: no ICT shape, zero target" for n, a in zip(ARKIT_NAMES, basis.available) if not a
        ]
    frames = [read_fit(p, len(subject.rest)) for p in fits]
    if exact:
        targets += [(FIT_PREFIX + f.stem, f.skin - subject.rest) for f in frames]
    animation = None
    names = [n for n, _ in targets]
    if frames:
        W = np.zeros((len(frames), len(targets)))
        for i, f in enumerate(frames):
            if exact:
                W[i, names.index(FIT_PREFIX + f.stem)] = 1.0
            else:
                for c, a in f.activations.items():
                    if MUSCLE_PREFIX + c in names:
                        W[i, names.index(MUSCLE_PREFIX + c)] = a
        animation = (np.arange(len(frames), dtype=np.float64), W)
        if not exact:
            notes.append(
                "keyframes blend the per-control targets linearly with the fitted activations "
                "(jaw pose not included); use --exact for the exact fitted skins"
            )
    say(f"writing {out}")
    g = build_gltf(
        subject.rest,
        subject.triangles,
        targets,
        parts=subject.parts,
        animation=animation,
    )
    write_glb(out, g)
    return {
        "file": str(out),
        "subject": subject.description,
        "targets": names,
        "keyframes": [f.stem for f in frames],
        "parts": [p.name for p in subject.parts],
        "bytes": Path(out).stat().st_size,
        "seconds": time.perf_counter() - t0,
        "notes": notes,
    }


def register(app: typer.Typer) -> None:
    """Add ``jaxface export`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors, status_steps

    @app.command(epilog=_EPILOG)
    @handle_errors
    def export(
        subject: str = typer.Argument(
            ..., help="'default', a face mesh (.ply/.obj + .lm3) or a neutral scan (.bnt)."
        ),
        out: Path = typer.Option(..., "--out", "-o", dir_okay=False, help="The .glb to write."),
        landmarks: Path | None = typer.Option(  # noqa: UP007
            None, "--landmarks", help="Landmarks of the mesh/scan (.lm3; default: beside it)."
        ),
        fit: List[Path] = typer.Option(  # noqa: UP006
            [],
            "--fit",
            help="jaxface fit JSON (with its .fitted.ply beside it); repeat: one keyframe each.",
        ),
        exact: bool = typer.Option(
            False, "--exact", help="Add each fit's exact fitted skin as its own morph target."
        ),
        arkit: bool = typer.Option(
            False, "--arkit", help="Add the 52 ARKit shapes (needs the ICT-FaceKit data)."
        ),
        muscles: bool = typer.Option(True, "--muscles/--no-muscles", help="Per-control targets."),
        aus: bool = typer.Option(True, "--aus/--no-aus", help="Per-AU targets."),
        ict: Path | None = typer.Option(  # noqa: UP007
            None, "--ict", help="ict_face.npz (default $JAXFACE_ICT or $JAXFACE_SHARED/data/ict)."
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Export a subject's rig (skin, eyes, teeth, one morph target per control and AU,
        optionally the ARKit shapes) and its fits (an animation of the morph weights) as glTF
        2.0 binary, in metres.

        \b
        Examples:
          jaxface export default --out head.glb --arkit
          jaxface export bs000_N_N_0.bnt --fit fits/bs000_LFAU_12_0.json --exact --out bs000.glb
        """
        with status_steps("jaxface export", quiet=quiet) as step:
            step("building the subject")
            subj = load_export_subject(subject, landmarks, progress=step)
            res = run_export(
                subj,
                out,
                fits=list(fit),
                exact=exact,
                arkit=arkit,
                muscles=muscles,
                aus=aus,
                ict=ict,
                progress=step,
            )
        if not quiet:
            console.print(
                f"wrote {res['file']}: {len(res['targets'])} morph targets, "
                f"{len(res['keyframes'])} keyframes, parts {res['parts']}, "
                f"{res['bytes'] / 1e6:.1f} MB ({res['seconds']:.1f} s)"
            )
            for n in res["notes"]:
                console.print(f"  note: {n}")
