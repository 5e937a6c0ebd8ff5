"""Benchmark of the forward model (issue 5): one quasi-static synthesis on the ICT face.

Run from the repository root::

    JAXFACE_SHARED=../shared python benchmarks/bench_synth.py [--dtype float32|float64] [--repeat 7]
        [--sweeps 32/8,256/16,...] [--expressions] [--no-jacobian] [--muscle-shell 0]
        [--footprint-clusters 0,6]

Prints a table and writes ``benchmarks/results/bench_synth.json``. Measures (ICT-FaceKit face
region, 9,409 vertices, with its teeth):

* rig build time (NumPy: skull estimate, muscle placement, binding, constraints);
* compile time and run time (min / median over ``--repeat`` calls) of one synthesis with the
  default sweep counts;
* convergence: the largest vertex difference (mm) between the default synthesis and one with
  ten times more sweeps, for a smile + jaw opening;
* the converged synthesis: the ``converged`` preset of ``jaxface synth --sweeps``, timed
  alternately with the default (``converged_ms_min``, ``converged_over_default``), and the
  equilibrium gap of both (:func:`jaxface.anatomy.rig.equilibrium_gap`: how far 1,000 more
  plain sweeps still move the result, mm);
* with ``--sweeps 32/8,128/8,512/24/0.97,...``: the time-accuracy curve of the quasi-static
  solve, each ``muscle/skin[/rho]`` sweep count (``rho``: the skin's Chebyshev acceleration,
  :func:`jaxface.pbd.iterate`; or a preset name: ``converged``, ``reference``) timed
  and compared (max, 99th percentile and mean vertex distance, mm) with a 3,000 / 400-sweep
  plain solve from rest, and its equilibrium gap;
* with ``--expressions``: the same distances to a 3,000 / 400-sweep solve and the equilibrium
  gaps (max and 99th percentile, mm) for each of the six emotion presets, a jaw opening (AU26)
  and every control at 1 with the jaw at 18 degrees, at the default sweeps and at each
  ``--sweeps`` count: how converged the solve is beyond the one benchmark expression. Where
  skin buckles or touches the teeth the problem has several equilibria, and an accelerated
  solve can settle in another one than the plain sweeps from rest: there the distance to the
  deep solve stays large while the gap is 0;
* with ``--muscle-shell 0``: all of the above for the thesis's muscle, without the shell
  constraint (:func:`jaxface.anatomy.muscles.shell_targets`);
* with ``--footprint-clusters 0,6`` (default ``0``): the synthesis with other cluster widths
  of the tissue footprint (0 = the exact footprint), timed alternately with the default's, with
  the largest vertex distance to the default's result;
* batch throughput with ``jax.vmap`` (syntheses per second at batch 8 and 32);
* a forward-mode Jacobian over all controls and the jaw pitch (``jax.jacfwd``), the operation
  the fitter repeats;
* the reverse pass of one synthesis (``jax.vjp`` of the skin against a fixed random cotangent,
  the fitter's gradient correction) with the rig's default per-sweep ``jax.checkpoint`` (the
  skin's sweeps) and without any (``rig.with_iterations(checkpoint=False)``), timed
  alternately, with their compile times and the largest difference of the two gradients;
  and the fit's per-iteration pair, the skin and its reverse pass, as a forward call beside a
  jitted forward+reverse (``separate``) or as one ``jax.vjp`` whose skin and VJP leave the jit
  (``fused``, :func:`jaxface.fit.forward.exact_skin_and_vjp`), timed alternately.
Timings are wall-clock on whatever machine runs it (say which when you quote them).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def _time(fn, *args, repeat=7):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append((time.perf_counter() - t0) * 1000.0)
    return compile_s, min(ts), statistics.median(ts)


def _label(m: int, s: int, q: float) -> str:
    return f"{m}/{s}" + (f"/{q:g}" if q else "")


def _expression_convergence(rig, sweeps: str, dt) -> dict:
    """Distance (mm) of the solve at each sweep count to a 3000/400-sweep solve, per expression."""
    from jaxface import facs
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import equilibrium_gap, synthesize
    from jaxface.commands.synth import parse_sweeps

    cases = {}
    for name in sorted(facs.EMOTIONS):
        a, jaw, _ = facs.emotion_controls(name, rig.muscle_names)
        cases[name] = (np.asarray(a), float(jaw.pitch_deg))
    cases["AU26"] = (np.zeros(rig.n_controls), 12.0)
    cases["all_controls_1_jaw_18"] = (np.ones(rig.n_controls), 18.0)
    A = jnp.asarray(np.stack([c[0] for c in cases.values()]), dt)
    P = jnp.asarray([c[1] for c in cases.values()], dt)

    def run(r):
        return np.asarray(jax.jit(jax.vmap(lambda a, p: synthesize(r, a, JawPose(p))))(A, P))

    def gap(r):
        return np.asarray(jax.jit(jax.vmap(lambda a, p: equilibrium_gap(r, a, JawPose(p))))(A, P))

    ref = run(rig.with_iterations(muscles=3000, skin=400))
    counts = [(rig.muscles.iterations, rig.skin.iterations, rig.skin.chebyshev_rho)]
    counts += [parse_sweeps(item) for item in sweeps.split(",") if item]
    out = {}
    rigs = [rig.with_iterations(muscles=m, skin=s, skin_rho=q) for m, s, q in counts]
    cols = [np.linalg.norm(run(r) - ref, axis=2) for r in rigs]
    gaps = [gap(r) for r in rigs]
    for title, table, key in (
        ("distance to 3000/400 from rest, max / p99 mm", cols, "to_deep_solve"),
        ("equilibrium gap (1000 more sweeps), max / p99 mm", gaps, "equilibrium_gap"),
    ):
        print(f"{title:50s}" + "".join(_label(*c).rjust(14) for c in counts))
        for i, name in enumerate(cases):
            row = out.setdefault(name, {})
            for c, d in zip(counts, table):
                row.setdefault(_label(*c), {})[key] = {
                    "max_mm": float(d[i].max()),
                    "p99_mm": float(np.percentile(d[i], 99)),
                }
            print(
                f"{name:50s}"
                + "".join(f"{d[i].max():6.2f} / {np.percentile(d[i], 99):5.2f}" for d in table)
            )
    return out


def _reverse_pass(rig, a, jaw, dt, *, repeat: int) -> dict:
    """The reverse pass of one synthesis with and without the per-sweep checkpoint, timed
    alternately (three rounds, the best of each)."""
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import synthesize

    ct = jnp.asarray(np.random.default_rng(0).normal(size=(rig.n_vertices, 3)), dt)
    th = jnp.concatenate([a, jaw.pitch_deg[None]])

    def grad_of(r):
        def g(th):
            _, vjp = jax.vjp(lambda t: synthesize(r, t[:-1], JawPose(t[-1])), th)
            return vjp(ct)[0]

        return jax.jit(g)

    on, off = grad_of(rig), grad_of(rig.with_iterations(checkpoint=False))
    c_on, _, _ = _time(on, th, repeat=1)
    c_off, _, _ = _time(off, th, repeat=1)
    t_on, t_off = [], []
    for _ in range(3):
        t_on.append(_time(on, th, repeat=repeat)[1])
        t_off.append(_time(off, th, repeat=repeat)[1])
    g_on, g_off = np.asarray(on(th)), np.asarray(off(th))
    # the fit's outer iteration needs the skin (correspondences) and the reverse pass
    # (gradient correction): a forward call beside a jitted forward+reverse, or one jitted
    # jax.vjp whose skin and VJP leave the jit and a second jit that applies the VJP
    # (jaxface.fit.forward.exact_skin_and_vjp), timed alternately
    fwd = jax.jit(lambda t: synthesize(rig, t[:-1], JawPose(t[-1])))
    vjp_of = jax.jit(lambda t: jax.vjp(lambda u: synthesize(rig, u[:-1], JawPose(u[-1])), t))
    apply = jax.jit(lambda f, c: f(c)[0])

    def separate(t):
        return fwd(t), on(t)

    def fused(t):
        x, f = vjp_of(t)
        return x, apply(f, ct)

    _time(separate, th, repeat=1)
    _time(fused, th, repeat=1)
    t_sep, t_fus = [], []
    for _ in range(3):
        t_sep.append(_time(separate, th, repeat=repeat)[1])
        t_fus.append(_time(fused, th, repeat=repeat)[1])
    g_fus = np.asarray(fused(th)[1])
    return {
        "skin_and_reverse_separate_ms_min": min(t_sep),
        "skin_and_reverse_fused_ms_min": min(t_fus),
        "skin_and_reverse_separate_over_fused": min(t_sep) / min(t_fus),
        "skin_and_reverse_fused_gradient_difference": float(np.abs(g_fus - g_on).max()),
        "reverse_compile_s": c_on,
        "reverse_plain_compile_s": c_off,
        "reverse_ms_min": min(t_on),
        "reverse_plain_ms_min": min(t_off),
        "reverse_plain_over_checkpointed": min(t_off) / min(t_on),
        "reverse_max_gradient_difference": float(np.abs(g_on - g_off).max()),
        "reverse_gradient_scale": float(np.abs(g_off).max()),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--no-jacobian", action="store_true")
    ap.add_argument("--no-reverse", action="store_true", help="skip the reverse-pass timing")
    ap.add_argument(
        "--expressions",
        action="store_true",
        help="also measure the convergence on the six emotions, AU26 and all controls at 1",
    )
    ap.add_argument(
        "--muscle-shell",
        type=float,
        default=None,
        help="the muscles' shell stiffness (default: the rig's, 1; 0 = the thesis's muscle)",
    )
    ap.add_argument(
        "--footprint-clusters",
        default="0",
        help="comma-separated cluster widths (reference mm) of the tissue footprint to time "
        "beside the default, side by side, 0 = the exact footprint "
        "(jaxface.anatomy.skin.footprint_operator)",
    )
    ap.add_argument(
        "--sweeps",
        default="",
        help="comma-separated muscle/skin sweep counts for the time-accuracy curve, "
        "e.g. 32/8,128/8,256/16 (each compiles once); a third number turns on the "
        "skin's Chebyshev acceleration, e.g. 512/24/0.97",
    )
    args = ap.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from jaxface import facs
    from jaxface.anatomy.ict import load_ict_face
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, equilibrium_gap, synthesize
    from jaxface.commands.synth import SWEEP_PRESETS, parse_sweeps
    from jaxface.testing import shared_path

    dt = jnp.float32 if args.dtype == "float32" else jnp.float64
    f = load_ict_face(
        shared_path("data", "ict", "ict_face.npz", pytest_skip=False),
        shared_path("data", "bosphorus_style", "truth.json", pytest_skip=False),
    )
    t0 = time.perf_counter()
    kw = {} if args.muscle_shell is None else {"muscle_shell_stiffness": args.muscle_shell}
    rig = build_rig(f.skin, f.landmarks, upper_teeth=f.upper_teeth, lower_teeth=f.lower_teeth, **kw)
    build_s = time.perf_counter() - t0
    a, jaw, _ = facs.aus_to_controls({"AU12": 1.0, "AU6": 1.0, "AU26": 0.6}, rig.muscle_names)
    a = jnp.asarray(a, dt)
    jaw = JawPose(jnp.asarray(jaw.pitch_deg, dt), jnp.asarray(0.0, dt), jnp.asarray(0.0, dt))
    res = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "backend": jax.default_backend(),
        "dtype": args.dtype,
        "vertices": rig.n_vertices,
        "controls": rig.n_controls,
        "muscle_particles": rig.muscles.n_particles,
        "muscle_sweeps": rig.muscles.iterations,
        "skin_sweeps": rig.skin.iterations,
        "muscle_shell_stiffness": rig.muscles.shell_stiffness,
        "build_s": build_s,
    }
    c, mn, md = _time(synthesize, rig, a, jaw, repeat=args.repeat)
    res.update(synth_compile_s=c, synth_ms_min=mn, synth_ms_median=md)
    x = synthesize(rig, a, jaw)
    ref = synthesize(
        rig.with_iterations(muscles=10 * rig.muscles.iterations, skin=10 * rig.skin.iterations),
        a,
        jaw,
    )
    res["convergence_mm_vs_10x_sweeps"] = float(jnp.abs(x - ref).max())
    res["motion_mm"] = float(jnp.linalg.norm(x - rig.rest, axis=1).max())
    # the converged synthesis: the 'converged' preset of `jaxface synth --sweeps`, timed
    # alternately with the default, and how far each still is from its equilibrium
    m_, s_, q_ = SWEEP_PRESETS["converged"]
    conv = rig.with_iterations(muscles=m_, skin=s_, skin_rho=q_)
    t_def, t_conv = [], []
    for _ in range(3):
        t_def.append(_time(synthesize, rig, a, jaw, repeat=args.repeat)[1])
        t_conv.append(_time(synthesize, conv, a, jaw, repeat=args.repeat)[1])
    g_def = np.asarray(equilibrium_gap(rig, a, jaw))
    g_conv = np.asarray(equilibrium_gap(conv, a, jaw))
    res.update(
        converged_sweeps=_label(m_, s_, q_),
        converged_ms_min=min(t_conv),
        converged_over_default=min(t_conv) / min(t_def),
        default_gap_max_mm=float(g_def.max()),
        converged_gap_max_mm=float(g_conv.max()),
        converged_gap_p99_mm=float(np.percentile(g_conv, 99)),
    )
    if args.footprint_clusters:
        # the same synthesis with other footprint cluster widths, timed alternately with the
        # default so that both see the same machine
        from jaxface.anatomy.rig import FOOTPRINT_CLUSTER_MM

        fp = {
            "default_cluster_mm": FOOTPRINT_CLUSTER_MM,
            "default_nnz": int(rig.skin.fp_vals.shape[0]),
            "other": [],
        }
        for item in args.footprint_clusters.split(","):
            h = float(item)
            r = build_rig(
                f.skin,
                f.landmarks,
                upper_teeth=f.upper_teeth,
                lower_teeth=f.lower_teeth,
                footprint_cluster_mm=h,
                **kw,
            )
            t_def, t_oth = [], []
            for _ in range(3):
                t_def.append(_time(synthesize, rig, a, jaw, repeat=args.repeat)[1])
                t_oth.append(_time(synthesize, r, a, jaw, repeat=args.repeat)[1])
            d = np.linalg.norm(np.asarray(synthesize(r, a, jaw)) - np.asarray(x), axis=1)
            row = {
                "cluster_mm": h,
                "nnz": int(r.skin.fp_vals.shape[0]),
                "ms_min": min(t_oth),
                "default_ms_min": min(t_def),
                "ratio_over_default": min(t_oth) / min(t_def),
                "max_mm_from_default": float(d.max()),
                "p99_mm_from_default": float(np.percentile(d, 99)),
            }
            fp["other"].append(row)
            print(
                f"footprint clusters {h:g} mm: {row['nnz']} entries (default {fp['default_nnz']}), "
                f"{row['ms_min']:.1f} ms against {row['default_ms_min']:.1f} ms (x{row['ratio_over_default']:.2f}), "
                f"max {d.max():.3f} / p99 {np.percentile(d, 99):.3f} mm from the default",
                flush=True,
            )
        res["footprint"] = fp
    if args.sweeps:
        deep = np.asarray(synthesize(rig.with_iterations(muscles=3000, skin=400), a, jaw))
        curve = []
        for item in args.sweeps.split(","):
            m_, s_, q_ = parse_sweeps(item)
            r = rig.with_iterations(muscles=m_, skin=s_, skin_rho=q_)
            _, mn, _ = _time(synthesize, r, a, jaw, repeat=max(3, args.repeat // 2))
            d = np.linalg.norm(np.asarray(synthesize(r, a, jaw)) - deep, axis=1)
            g = np.asarray(equilibrium_gap(r, a, jaw))
            curve.append(
                dict(
                    muscle_sweeps=m_,
                    skin_sweeps=s_,
                    skin_rho=q_,
                    ms_min=mn,
                    max_mm=float(d.max()),
                    p99_mm=float(np.percentile(d, 99)),
                    mean_mm=float(d.mean()),
                    gap_max_mm=float(g.max()),
                    gap_p99_mm=float(np.percentile(g, 99)),
                )
            )
            print(
                f"sweeps {_label(m_, s_, q_):<14} {mn:7.1f} ms   vs 3000/400 sweeps: max {d.max():.3f}  "
                f"p99 {np.percentile(d, 99):.3f}  mean {d.mean():.4f} mm   equilibrium gap: max "
                f"{g.max():.3f}  p99 {np.percentile(g, 99):.4f} mm",
                flush=True,
            )
        res["time_accuracy"] = curve
    if args.expressions:
        res["expressions"] = _expression_convergence(rig, args.sweeps, dt)
    for B in (8, 32):
        A = jnp.tile(a[None], (B, 1)) * jnp.linspace(0.2, 1.0, B, dtype=dt)[:, None]
        P = jnp.full((B,), jaw.pitch_deg, dt)
        fb = jax.jit(jax.vmap(lambda a, p: synthesize(rig, a, JawPose(p))))
        c, mn, md = _time(fb, A, P, repeat=max(2, args.repeat // 2))
        res[f"batch{B}_ms_min"] = mn
        res[f"batch{B}_syntheses_per_s"] = B / (mn / 1000.0)
    if not args.no_jacobian:
        theta = jnp.concatenate([a, jaw.pitch_deg[None]])
        fj = jax.jit(jax.jacfwd(lambda th: synthesize(rig, th[:-1], JawPose(th[-1]))))
        c, mn, md = _time(fj, theta, repeat=max(2, args.repeat // 2))
        res.update(jacfwd_params=int(theta.shape[0]), jacfwd_compile_s=c, jacfwd_ms_min=mn)
    if not args.no_reverse:
        res.update(_reverse_pass(rig, a, jaw, dt, repeat=max(3, args.repeat // 2)))
    width = max(len(k) for k in res)
    for k, v in res.items():
        if isinstance(v, (list, dict)):
            continue
        print(f"{k:<{width}}  {v:.4g}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    out = Path(__file__).resolve().parent / "results"
    out.mkdir(exist_ok=True)
    (out / "bench_synth.json").write_text(json.dumps(res, indent=2))
    print(f"wrote {out / 'bench_synth.json'}")


if __name__ == "__main__":
    main()
