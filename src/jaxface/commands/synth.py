"""``jaxface synth``: forward synthesis from the command line (muscles and jaw in, face out).

Builds the rig of a face (the embedded default head, or a ``.ply``/``.obj`` mesh with its
``.lm3`` Bosphorus landmarks) with either simulation backend and synthesises one face per
requested expression: each ``--emotion`` preset (:data:`jaxface.facs.EMOTIONS`), and one
custom expression combining every ``--au``, ``--muscle`` and ``--jaw-*`` option.

Outputs, in ``--out`` (mm, the input's frame: +y up, face along +z, subject's left +x), per
expression ``<name>``:

* ``<name>.ply``: the synthesised skin (the input mesh's topology);
* ``<name>.lm3``: its 24 landmarks, carried on the skin surface;
* ``<name>.json``: activations (control -> [0, 1]), jaw pose (degrees, mm; after the jaw
  model's smooth clamping), cheek puff, the AU intensities read back from the activations,
  landmark displacements and timings;
* ``<name>.png`` (unless ``--no-pictures``): neutral and expression, front and
  three-quarter views.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, List  # noqa: UP035 (typer options keep List[str], see UP006 below)

import numpy as np
import typer

from . import Units

__all__ = ["register", "parse_muscles", "synthesize_files"]


def parse_muscles(specs, muscle_names) -> dict[str, float]:
    """``["zygomaticus_major_L=0.6", ...]`` -> ``{control: activation}``.

    Raises:
        RigError: a malformed item, an unknown control (the message lists the controls) or a
            value outside [0, 1].
    """
    from ..errors import RigError

    out: dict[str, float] = {}
    names = list(muscle_names)
    for item in specs:
        name, _, val = str(item).partition("=")
        name = name.strip()
        if name not in names:
            raise RigError(
                f"--muscle {item!r}: unknown control {name!r}; the rig's controls are {names}."
            )
        try:
            v = float(val) if val.strip() else 1.0
        except ValueError:
            raise RigError(
                f"--muscle {item!r}: the activation must be a number in [0, 1]."
            ) from None
        if not 0.0 <= v <= 1.0:
            raise RigError(f"--muscle {item!r}: the activation must be in [0, 1].")
        out[name] = v
    return out


def synthesize_files(
    rig, expressions, out: Path, *, pictures: bool = True, out_units: str = "mm", progress=None
) -> list[dict]:
    """Synthesise ``expressions`` on ``rig`` and write the files described in the module doc.

    Args:
        rig: a PBD or LTW rig (:func:`jaxface.anatomy.build_rig`).
        expressions: list of ``(name, activations (M,), JawPose, cheek_puff)`` (the puff a
            number or ``[left, right]``).
        out: output folder (created).
        pictures: also write a PNG per expression.
        out_units: unit of the written PLY and LM3 coordinates.
        progress: called with each expression's name before it is synthesised.

    Returns:
        one summary dict per expression (what its JSON holds).
    """
    import jax.numpy as jnp

    from ..anatomy.rig import synthesize
    from ..atomic import ensure_out_dir, write_json_atomic
    from ..facs import au_intensities
    from ..io.scanner import SkinLandmarks
    from ..landmarks import Landmarks, write_lm3
    from ..mesh import save_mesh, unit_scale

    out = ensure_out_dir(Path(out))
    rest = np.asarray(rig.rest)
    tris = np.asarray(rig.triangles)
    bound = SkinLandmarks.of_rig(rig)
    names = bound.names
    lm0 = bound.positions(rest)
    s = 1.0 / unit_scale(out_units)  # mm -> output unit
    summaries = []
    for name, a, jaw, puff in expressions:
        if progress is not None:
            progress(name)
        t = time.perf_counter()
        x = np.asarray(synthesize(rig, jnp.asarray(a, rig.rest.dtype), jaw, puff))
        secs = time.perf_counter() - t
        if not np.all(np.isfinite(x)):
            from ..errors import RigError

            raise RigError(f"expression {name!r}: the synthesis produced non-finite positions.")
        lm = bound.positions(x)
        save_mesh(out / f"{name}.ply", x, tris, units=out_units)
        write_lm3(out / f"{name}.lm3", Landmarks(names, lm * s))
        je = rig.jaw.clamp(jaw) if hasattr(rig.jaw, "clamp") else jaw
        jd = {
            "pitch_deg": float(je.pitch_deg),
            "yaw_deg": float(je.yaw_deg),
            "protrusion_mm": float(je.protrusion_mm),
        }
        disp = np.linalg.norm(x - rest, axis=1)
        summary = {
            "name": name,
            "backend": getattr(rig, "backend", "pbd"),
            "units": out_units,
            "activations": {n: float(v) for n, v in zip(rig.muscle_names, np.asarray(a))},
            "jaw": jd,
            "cheek_puff": np.asarray(puff, float).tolist(),  # a number, or [left, right]
            "au_intensities": au_intensities(np.asarray(a), rig.muscle_names, je, cheek_puff=puff),
            "displacement_mm": {"max": float(disp.max()), "mean": float(disp.mean())},
            "landmark_displacement_mm": {n: [float(v) for v in d] for n, d in zip(names, lm - lm0)},
            "synthesis_s": secs,
            "files": {"mesh": f"{name}.ply", "landmarks": f"{name}.lm3"},
        }
        if pictures:
            summary["files"]["picture"] = f"{name}.png"
            _picture(out / f"{name}.png", rig, rest, x, name)
        write_json_atomic(out / f"{name}.json", summary)
        summaries.append(summary)
    return summaries


def _picture(path, rig, rest, x, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..render import Layer, rasterize, save_figure

    face = rig.info.frame
    lo = face.to_world([-85.0, -125.0, -120.0])
    hi = face.to_world([85.0, 75.0, 60.0])
    bounds = np.stack([np.minimum(lo, hi), np.maximum(lo, hi)])
    tris = np.asarray(rig.triangles)
    fig, axs = plt.subplots(1, 4, figsize=(12, 3.3))
    panels = [
        ("neutral", rest, "front"),
        (title, x, "front"),
        ("neutral", rest, (30.0, 5.0)),
        (title, x, (30.0, 5.0)),
    ]
    for ax, (t, v, view) in zip(axs, panels):
        img = rasterize([Layer(v, tris)], view=view, width=360, height=360, bounds=bounds).image
        ax.imshow(img)
        ax.set_title(t, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _safe_name(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s).strip("_") or "expression"


#: Named solve depths of ``--sweeps`` (muscle sweeps, skin sweeps, skin Chebyshev rho). Their
#: equilibrium gap (:func:`jaxface.anatomy.rig.equilibrium_gap`, how far 1,000 more plain sweeps
#: move the result) on the ICT face, for the six emotions, AU26 and the benchmark smile
#: (``benchmarks/bench_synth.py --sweeps converged,reference --expressions``, 2-core CPU):
SWEEP_PRESETS = {
    "fast": (32, 8, 0.0),  # the default: 47 ms, up to 1.6 mm to go
    "converged": (32, 56, 0.995),  # 172 ms (3.7x the default), at most 0.022 mm to go
    "reference": (48, 96, 0.99),  # about twice "converged", under 0.001 mm to go
}


def parse_sweeps(text: str) -> tuple[int, int, float]:
    """``"MUSCLE/SKIN[/RHO]"``: sweep counts of the quasi-static solve and, optionally, the
    Chebyshev spectral-radius estimate of the skin solve (0 = plain sweeps), e.g. ``"384/16"``
    or ``"384/32/0.97"``; or a name of :data:`SWEEP_PRESETS` (``fast``, ``converged``,
    ``reference``).

    Returns:
        ``(muscle_sweeps, skin_sweeps, skin_rho)``.

    Raises:
        RigError: not two positive integers (and a number in [0, 1)) separated by ``/``.
    """
    from ..errors import RigError

    key = str(text).strip().lower()
    if key in SWEEP_PRESETS:
        return SWEEP_PRESETS[key]
    parts = str(text).replace(" ", "").split("/")
    hint = (
        "give MUSCLE/SKIN sweep counts, optionally /RHO for the skin's Chebyshev acceleration, "
        f"e.g. 384/16 or 384/32/0.97, or one of {', '.join(SWEEP_PRESETS)}."
    )
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        m, k = int(parts[0]), int(parts[1])
        rho = float(parts[2]) if len(parts) == 3 else 0.0
    except ValueError:
        raise RigError(f"--sweeps {text!r}: {hint}") from None
    if m < 1 or k < 1:
        raise RigError(f"--sweeps {text!r}: both sweep counts must be at least 1.")
    from ..pbd import check_rho

    return m, k, check_rho(rho, f"--sweeps {text!r}: RHO")


def register(app: typer.Typer) -> None:
    """Add ``jaxface synth`` to ``app``."""
    from ..cli import _EPILOG, console, handle_errors, status_steps
    from . import options

    @app.command(epilog=_EPILOG)
    @handle_errors
    def synth(
        out: Path = options.out_dir(),
        emotion: List[str] = typer.Option(  # noqa: UP006
            [],
            "--emotion",
            "-e",
            help="Emotion preset (happiness, sadness, surprise, fear, anger, "
            "disgust) or 'all'; repeat for several. Each is its own output.",
        ),
        au: List[str] = typer.Option(  # noqa: UP006
            [],
            "--au",
            help="Action unit with intensity in [0, 1], e.g. AU12=0.8, AU12L, AU26=0.5 "
            "(repeat, or comma-separated).",
        ),
        muscle: List[str] = typer.Option(  # noqa: UP006
            [],
            "--muscle",
            "-m",
            help="Muscle control with activation in [0, 1], e.g. zygomaticus_major_L=0.6 (repeat).",
        ),
        jaw_pitch: float = typer.Option(
            0.0, "--jaw-pitch", help="Jaw opening, degrees (default limits -4..18)."
        ),
        jaw_yaw: float = typer.Option(
            0.0, "--jaw-yaw", help="Jaw yaw toward the subject's left, degrees (-5..5)."
        ),
        jaw_protrusion: float = typer.Option(
            0.0, "--jaw-protrusion", help="Jaw protrusion, mm (-2..10)."
        ),
        intensity: float = typer.Option(
            1.0, "--intensity", min=0.0, max=1.0, help="Scale of the emotion presets."
        ),
        name: str | None = typer.Option(  # noqa: UP007
            None,
            "--name",
            help="Output name of the custom expression (default: built from the options).",
        ),
        mesh: Path | None = typer.Option(  # noqa: UP007
            None, "--mesh", help="Face mesh (.ply/.obj) instead of the embedded default head."
        ),
        landmarks: Path | None = typer.Option(  # noqa: UP007
            None,
            "--landmarks",
            help="Its .lm3 landmarks (default: beside the mesh, else detected); 'auto' detects.",
        ),
        units: Units = typer.Option(Units.mm, "--units", help="Units of --mesh and --landmarks."),
        out_units: Units = typer.Option(
            Units.mm, "--out-units", help="Units of the written files."
        ),
        backend: str = typer.Option(
            "pbd",
            "--backend",
            help="Simulation backend: pbd (position-based "
            "dynamics) or ltw (Lee-Terzopoulos-Waters layered springs).",
        ),
        pictures: bool = typer.Option(
            True, "--pictures/--no-pictures", help="Write a PNG per expression."
        ),
        sweeps: str | None = typer.Option(  # noqa: UP007
            None,
            "--sweeps",
            help="Quasi-static solve of the pbd backend as MUSCLE/SKIN sweeps (default "
            "32/8, ~50 ms on the ICT face, up to 1.6 mm short of equilibrium). An optional third "
            "number turns on the Chebyshev acceleration of the skin solve with that spectral-radius "
            "estimate. Presets: 'converged' = 32/56/0.995 (~170 ms on the ICT face, within 0.03 mm "
            "of its equilibrium), 'reference' = 48/96/0.99 (about twice as long, within 0.001 mm). Where "
            "skin buckles or meets the teeth an accelerated solve can settle at another equilibrium "
            "than plain sweeps from rest, e.g. 3000/400 (python benchmarks/bench_synth.py "
            "--sweeps converged,reference --expressions).",
        ),
        compare_backends: bool = typer.Option(
            False,
            "--compare-backends",
            help="Also build the other backend's rig on the same face and write "
            "backends_emotions.png: the six emotions, PBD next to LTW, with their distance (mm) as a heat map.",
        ),
        arkit: List[str] = typer.Option(  # noqa: UP006
            [],
            "--arkit",
            help="ARKit-52 coefficients, e.g. browInnerUp=0.8,jawOpen=0.3: drive the rig through "
            "the inverse map (ARKit shapes -> controls, fitted on this face and cached; needs the "
            "ICT-FaceKit data: $JAXFACE_ICT or $JAXFACE_SHARED).",
        ),
        list_controls: bool = typer.Option(
            False,
            "--list-controls",
            help="Print the rig's muscle controls and the AU table, then exit.",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print errors."),
    ):
        """Synthesise expressions: muscle activations, AUs, emotions and jaw pose in, face meshes out.

        \b
        Examples:
          jaxface synth --emotion all --out synth
          jaxface synth --au AU12=0.8 --au AU26=0.4 --out smile
          jaxface synth --muscle zygomaticus_major_L=0.7 --jaw-pitch 8 --name left_smile --out s
          jaxface synth --mesh face.ply --landmarks face.lm3 --emotion surprise --out s
          jaxface synth --backend ltw --emotion happiness --out s_ltw
          jaxface synth --compare-backends --out compare
          jaxface synth --arkit browInnerUp=0.8,jawOpen=0.3 --out arkit
        """
        from ..anatomy.jaw import JawPose
        from ..anatomy.rig import Rig, build_rig
        from ..errors import RigError
        from ..facs import EMOTIONS, aus_to_controls, emotion_controls, parse_aus

        if backend not in ("pbd", "ltw"):
            raise RigError(f"--backend {backend!r}: use 'pbd' or 'ltw'.")
        n_sweeps = None
        if sweeps is not None:
            if backend != "pbd":
                raise RigError(
                    "--sweeps sets the pbd backend's solve; the ltw backend has its own "
                    "step count (leave --sweeps out)."
                )
            n_sweeps = parse_sweeps(sweeps)
        emotions = []
        for e in emotion:
            for item in (s.strip().lower() for s in e.split(",")):
                if item == "all":
                    emotions += list(EMOTIONS)
                elif item:
                    if item not in EMOTIONS:
                        raise RigError(
                            f"--emotion {item!r}: unknown preset; use one of {sorted(EMOTIONS)} or 'all'."
                        )
                    emotions.append(item)
        aus = parse_aus([s for a in au for s in a.split(",") if s.strip()])
        parse_muscles(muscle, [str(m).partition("=")[0].strip() for m in muscle])  # values
        # are checked before the minute-long rig build; the names once the rig is built
        jaw_given = any(v != 0.0 for v in (jaw_pitch, jaw_yaw, jaw_protrusion))
        from ..interop.inverse import parse_arkit

        arkit_c = parse_arkit(arkit)
        if not (
            emotions or aus or muscle or jaw_given or arkit_c or list_controls or compare_backends
        ):
            raise RigError(
                "nothing to synthesise: give --emotion, --au, --muscle, --arkit or --jaw-* "
                "(see jaxface synth --help)."
            )
        with status_steps("jaxface synth", quiet=quiet) as step:
            step("building the face")
            if mesh is None:
                from ..head import generic_head

                face = generic_head()
                rig_args: tuple[Any, ...] = (face,)
            else:
                from .clone import load_face

                if str(landmarks) == "auto" or (
                    landmarks is None and not mesh.with_suffix(".lm3").is_file()
                ):
                    from ..mesh import load_mesh
                    from .landmarks import detect_for

                    m = load_mesh(mesh, units=units.value, validate=False)
                    note = lambda t: console.print(f"[cyan]note:[/] {t}", markup=True)  # noqa: E731
                    lm = detect_for(m, f"face mesh {mesh.name}", note).landmarks
                else:
                    m, lm = load_face(mesh, units.value, landmarks, "face mesh", clean=True)
                rig_args = (m, lm)
            step(f"building the {backend} rig (skull, jaw, muscles)")
            rig = build_rig(*rig_args, backend=backend)
            if n_sweeps is not None:
                assert isinstance(rig, Rig)  # --sweeps is refused above for the ltw backend
                rig = rig.with_iterations(
                    muscles=n_sweeps[0], skin=n_sweeps[1], skin_rho=n_sweeps[2]
                )
            if list_controls:
                from ..facs import au_matrix

                aus_, A = au_matrix(rig.muscle_names)
                console.print("controls: " + ", ".join(rig.muscle_names))
                for k, row in zip(aus_, A):
                    used = [n for n, w in zip(rig.muscle_names, row) if w > 0]
                    console.print(f"  {k}: {', '.join(used) if used else '(jaw / other)'}")
                raise typer.Exit(0)
            exprs = []
            for e in emotions:
                a, jaw, puff = emotion_controls(e, rig.muscle_names, intensity)
                exprs.append((e, a, jaw, puff))
            if aus or muscle or jaw_given:
                a, jaw, puff = aus_to_controls(aus, rig.muscle_names)
                for k, v in parse_muscles(muscle, rig.muscle_names).items():
                    a[list(rig.muscle_names).index(k)] = v
                jaw = JawPose(
                    float(jaw.pitch_deg) + jaw_pitch,
                    float(jaw.yaw_deg) + jaw_yaw,
                    float(jaw.protrusion_mm) + jaw_protrusion,
                )
                label = name or _safe_name(
                    "_".join(
                        [f"{k}-{v:g}" for k, v in aus.items()]
                        + [m_.replace("=", "-") for m_ in muscle]
                        + (
                            [f"jaw{jaw_pitch:g}_{jaw_yaw:g}_{jaw_protrusion:g}"]
                            if jaw_given
                            else []
                        )
                    )[:80]
                )
                exprs.append((label, np.asarray(a, float), jaw, puff))
            if arkit_c:
                from ..interop.inverse import inverse_map_cached

                step("ARKit inverse map (ICT shapes cloned onto the face, fitted by the rig)")
                lm_ = rig_args[0].landmarks if mesh is None else rig_args[1]
                fm_ = rig_args[0].face_mask if mesh is None else None
                imap, _ = inverse_map_cached(rig, lm_, fm_)
                a_k, (jp, jy, jt), puff_k = imap.controls(arkit_c, rig.muscle_names)
                label_k = name if (name and not (aus or muscle or jaw_given)) else None
                exprs.append(
                    (
                        label_k
                        or _safe_name(
                            "arkit_" + "_".join(f"{k}-{v:g}" for k, v in arkit_c.items())
                        )[:80],
                        a_k,
                        JawPose(jp, jy, jt),
                        puff_k,
                    )
                )
            res = []
            if exprs:
                step(f"compiling and synthesising {len(exprs)} expression(s)")
                res = synthesize_files(
                    rig, exprs, out, pictures=pictures, out_units=out_units.value
                )
            if compare_backends:
                from ..ltw.pictures import compare_emotions
                from ..ltw.rig import LTWRig

                other = "ltw" if backend == "pbd" else "pbd"
                step(f"building the {other} rig on the same face")
                rig2 = build_rig(*rig_args, backend=other)
                pbd_rig, ltw_rig = (rig, rig2) if backend == "pbd" else (rig2, rig)
                assert isinstance(ltw_rig, LTWRig)
                step("synthesising the six emotions with both backends")
                out.mkdir(parents=True, exist_ok=True)
                cmp_path = compare_emotions(
                    out / "backends_emotions.png", ltw_rig, pbd_rig, intensity=intensity
                )
        if not quiet:
            for r in res:
                top = sorted(r["au_intensities"].items(), key=lambda kv: -kv[1])[:4]
                console.print(
                    f"  {r['name']}: max displacement {r['displacement_mm']['max']:.1f} mm, "
                    f"jaw {r['jaw']['pitch_deg']:.1f} deg, strongest AUs "
                    + ", ".join(f"{k} {v:.2f}" for k, v in top if v > 0)
                )
            console.print(f"wrote {len(res)} expression(s) to {out}")
            if compare_backends:
                console.print(f"backend comparison: {cmp_path}")
