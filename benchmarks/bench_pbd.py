"""Benchmark of the PBD engine in the scheme the rig runs (fused Jacobi, :mod:`jaxface.sweep`).

Run from the repository root (the ICT face needs the shared data: ``JAXFACE_SHARED`` or
``../shared``)::

    python benchmarks/bench_pbd.py [--rig ict|head] [--dtype float32|float64] [--repeat 7]
        [--label new] [--out benchmarks/results/bench_pbd.json]

Measured on one rig (default: the ICT-FaceKit face region with its teeth, 9,409 skin vertices):

* one synthesis at the rig's default sweeps (:func:`jaxface.anatomy.rig.synthesize_state`):
  compile time, min / median ms;
* ms per sweep of the skin solve (all skin groups: anchors, stretch, area, bending, volume,
  teeth) and of the muscle solve: the difference of a 40- and an 8-sweep solve (skin), a 56-
  and a 24-sweep solve (muscles), divided by the extra sweeps;
* the engine's :class:`jaxface.pbd.System` of the same skin (:func:`jaxface.pbd.skin_constraints`
  plus 10% of the particles anchored): ms per sweep and projections per second with
  ``scheme="jacobi"`` (the rig's) and ``scheme="gs"``.

The rig timings use only functions that exist before and after the one-engine refactor (issue
47), so running the script with each code version on one machine compares them. Timings are
wall-clock on whatever machine runs it; say which when you quote them.
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


def _machine():
    return {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "load_avg": list(os.getloadavg()),
    }


def _time(fn, *args, repeat=7):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append((time.perf_counter() - t0) * 1e3)
    return compile_s, min(ts), statistics.median(ts)


def _rig(which):
    from jaxface.anatomy.rig import build_rig

    if which == "head":
        from jaxface.head import generic_head

        return build_rig(generic_head())
    from jaxface.anatomy.ict import load_ict_face

    shared = os.environ.get("JAXFACE_SHARED", "../shared")
    f = load_ict_face(
        os.path.join(shared, "data", "ict", "ict_face.npz"),
        os.path.join(shared, "data", "bosphorus_style", "truth.json"),
    )
    return build_rig(f.skin, f.landmarks, upper_teeth=f.upper_teeth, lower_teeth=f.lower_teeth)


def bench_rig(rig, dtype, repeat):
    """Synthesis and per-sweep timings of the rig's own solves."""
    import equinox as eqx

    from jaxface import facs
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.muscles import solve_muscles
    from jaxface.anatomy.rig import synthesize_state
    from jaxface.anatomy.skin import solve_skin

    a, jaw, _ = facs.emotion_controls("happiness", rig.muscle_names)
    a = jnp.asarray(a, dtype)
    pose = JawPose(jnp.asarray(jaw.pitch_deg, dtype))  # pyright: ignore[reportArgumentType]
    synth = eqx.filter_jit(lambda r, a, p: synthesize_state(r, a, p).skin)
    c, mn, md = _time(synth, rig, a, pose, repeat=repeat)
    out = {"synthesis": {"compile_s": c, "ms_min": mn, "ms_median": md}}
    print(f"  synthesis (happiness): {mn:.1f} ms min, {md:.1f} ms median, compile {c:.1f} s")
    st = synthesize_state(rig, a, pose)

    @eqx.filter_jit
    def skin(sk, tg, R, t):
        return solve_skin(sk, tg, R, t)

    @eqx.filter_jit
    def muscles(ms, a, R, t):
        return solve_muscles(ms, a, R, t)[0]

    for name, fn, args, (lo, hi) in (
        ("skin", skin, (st.targets, st.R, st.t), (8, 40)),
        ("muscles", muscles, (a, st.R, st.t), (24, 56)),
    ):
        ms = {}
        for n in (lo, hi):
            r = rig.with_iterations(**{name: n})
            ms[n] = _time(fn, r.skin if name == "skin" else r.muscles, *args, repeat=repeat)[1]
        per = (ms[hi] - ms[lo]) / (hi - lo)
        out[f"{name}_ms_per_sweep"] = per
        print(
            f"  {name} solve: {per:.3f} ms per sweep ({ms[lo]:.1f} ms at {lo}, {ms[hi]:.1f} at {hi})"
        )
    return out


def _relax_fn(n: int, scheme):
    from jaxface import pbd

    return jax.jit(lambda s, x: pbd.relax(s, x, iterations=n, scheme=scheme))


def bench_system(rig, dtype, repeat):
    """The engine's System of the rig's skin: ms per sweep in both schemes (new code only)."""
    from jaxface import pbd

    if not hasattr(pbd, "make_group"):
        print("  (this code version has no fused Jacobi System scheme; skipped)")
        return None
    from jaxface.mesh import TriMesh

    skin = TriMesh(np.asarray(rig.rest, np.float64), rig.triangles)
    v = skin.vertices
    rng = np.random.default_rng(0)
    ids = rng.choice(len(v), len(v) // 10, replace=False)
    groups = pbd.skin_constraints(skin)
    groups["anchors"] = pbd.anchor_constraints(
        ids, v[ids] + rng.normal(size=(len(ids), 3)), stiffness=0.2
    )
    S = pbd.build_system(groups, len(v), omega={"stretch": 1.5, "cross": 1.5})
    n_proj = sum(int(S[k].size) for k in S.names)
    x0 = jnp.asarray(v, dtype)
    out: dict = {"constraints": n_proj}
    schemes: tuple[pbd.Scheme, ...] = ("jacobi", "gs")
    for scheme in schemes:
        ms = {}
        for n in (8, 40):
            f = _relax_fn(n, scheme)
            ms[n] = _time(f, S, x0, repeat=repeat)[1]
        per = (ms[40] - ms[8]) / 32
        out[scheme] = {"ms_per_sweep": per, "projections_per_s": n_proj / (per / 1e3)}
        print(
            f"  System {scheme:6s}: {per:.3f} ms per sweep, "
            f"{n_proj / (per / 1e3) / 1e6:.1f} M projections/s ({n_proj} constraints)"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--rig", default="ict", choices=["ict", "head"])
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--label", default="")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    dtype = jnp.float32 if args.dtype == "float32" else jnp.float64
    import jaxface

    print(f"jaxface from {Path(jaxface.__file__).parent} {args.label}")
    t = time.perf_counter()
    rig = _rig(args.rig)
    print(
        f"  rig ({args.rig}, {rig.n_vertices} skin vertices) built in {time.perf_counter() - t:.1f} s"
    )
    report = {
        "machine": _machine(),
        "label": args.label,
        "rig": args.rig,
        "dtype": args.dtype,
        **bench_rig(rig, dtype, args.repeat),
        "system": bench_system(rig, dtype, args.repeat),
    }
    out = (
        Path(args.out)
        if args.out
        else Path(__file__).resolve().parent / "results" / "bench_pbd.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
