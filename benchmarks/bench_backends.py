"""Benchmark: PBD rig vs Lee-Terzopoulos-Waters layered tissue, on the ICT face, in one run.

Run from the repository root::

    JAXFACE_SHARED=../shared python benchmarks/bench_backends.py [--dtype float32|float64] [--repeat 5]

Both rigs are built on the same face (ICT-FaceKit face region, 9,409 vertices, with its teeth;
``jaxface.anatomy.ict.load_ict_face``) from the same muscle map and skull, and driven by the
same activation vector and jaw pose (a smile with the jaw opened: AU6 + AU12 + AU26 at 0.6).
For each backend it measures the build time, the compile time and the wall-clock time of one
*converged* synthesis (min / median over ``--repeat`` calls, default iteration counts), and
how converged that is: the largest vertex difference (mm) to a synthesis with 4x (LTW) / 10x
(PBD) the iterations, and for LTW the equilibrium residual (mm). The headline number is the
ratio LTW time / PBD time. Prints a table and writes ``benchmarks/results/bench_backends.json``.
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


def _time(fn, *args, repeat=5):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append((time.perf_counter() - t0) * 1000.0)
    return compile_s, min(ts), statistics.median(ts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from jaxface import facs
    from jaxface.anatomy.ict import load_ict_face
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, synthesize
    from jaxface.ltw.rig import build_ltw_rig, equilibrium_residual, synthesize_ltw
    from jaxface.testing import shared_path

    dt = jnp.float32 if args.dtype == "float32" else jnp.float64
    f = load_ict_face(
        shared_path("data", "ict", "ict_face.npz", pytest_skip=False),
        shared_path("data", "bosphorus_style", "truth.json", pytest_skip=False),
    )
    res = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "backend": jax.default_backend(),
        "dtype": args.dtype,
        "vertices": f.skin.n_vertices,
    }
    t0 = time.perf_counter()
    pbd = build_rig(f.skin, f.landmarks, upper_teeth=f.upper_teeth, lower_teeth=f.lower_teeth)
    res["pbd_build_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ltw = build_ltw_rig(f.skin, f.landmarks, skull=pbd.info.skull)
    res["ltw_build_s"] = time.perf_counter() - t0
    assert ltw.muscle_names == pbd.muscle_names
    a, jaw, _ = facs.aus_to_controls({"AU12": 1.0, "AU6": 1.0, "AU26": 0.6}, pbd.muscle_names)
    a = jnp.asarray(a, dt)
    jaw = JawPose(jnp.asarray(jaw.pitch_deg, dt), jnp.asarray(0.0, dt), jnp.asarray(0.0, dt))
    ltw = (
        ltw
        if args.dtype == "float64"
        else jax.tree_util.tree_map(
            lambda x: (
                x.astype(dt) if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating) else x
            ),
            ltw,
        )
    )

    res.update(pbd_muscle_sweeps=pbd.muscles.iterations, pbd_skin_sweeps=pbd.skin.iterations)
    c, mn, md = _time(synthesize, pbd, a, jaw, repeat=args.repeat)
    res.update(pbd_compile_s=c, pbd_ms_min=mn, pbd_ms_median=md)
    x = synthesize(pbd, a, jaw)
    ref = synthesize(
        pbd.with_iterations(muscles=10 * pbd.muscles.iterations, skin=10 * pbd.skin.iterations),
        a,
        jaw,
    )
    res["pbd_convergence_mm_vs_10x"] = float(jnp.abs(x - ref).max())
    res["pbd_motion_mm"] = float(jnp.linalg.norm(x - pbd.rest, axis=1).max())

    res.update(
        ltw_nodes=3 * ltw.n_vertices,
        ltw_springs=int(ltw.model.tissue.spring_i.shape[0]),
        ltw_elements=int(ltw.model.tissue.elements.shape[0]),
        ltw_steps=ltw.n_steps,
    )
    c, mn, md = _time(synthesize_ltw, ltw, a, jaw, repeat=args.repeat)
    res.update(ltw_compile_s=c, ltw_ms_min=mn, ltw_ms_median=md, ltw_ms_per_step=mn / ltw.n_steps)
    x = synthesize_ltw(ltw, a, jaw)
    ref = synthesize_ltw(ltw.with_iterations(4 * ltw.n_steps), a, jaw)
    res["ltw_convergence_mm_vs_4x"] = float(jnp.abs(x - ref).max())
    res["ltw_residual_mm"] = equilibrium_residual(ltw, a, jaw)
    res["ltw_motion_mm"] = float(jnp.linalg.norm(x - ltw.rest, axis=1).max())
    res["pbd_vs_ltw_max_mm"] = float(jnp.linalg.norm(x - synthesize(pbd, a, jaw), axis=1).max())
    res["time_ratio_ltw_over_pbd"] = res["ltw_ms_min"] / res["pbd_ms_min"]

    width = max(len(k) for k in res)
    for k, v in res.items():
        print(f"{k:<{width}}  {v:.4g}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    out = Path(__file__).resolve().parent / "results"
    out.mkdir(exist_ok=True)
    (out / "bench_backends.json").write_text(json.dumps(res, indent=2))
    print(f"wrote {out / 'bench_backends.json'}")


if __name__ == "__main__":
    main()
