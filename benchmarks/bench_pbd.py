"""Benchmark of the PBD solver (issue 3): throughput, convergence of the two parallel schemes,
reverse-mode gradient cost, and the speed ratio against the sequential NumPy reference.

Run from the repository root (the ICT face needs the shared data: ``JAXFACE_SHARED`` or
``../shared``)::

    python benchmarks/bench_pbd.py [--quick] [--sizes 1k,ict,100k] [--dtype float32]

Meshes: a ~1k-vertex patch cut from the ICT face around the mouth, the ICT-FaceKit face region
(9,409 vertices) and a 100,489-vertex sheet (a regular 317 x 317 grid, 0.5 mm spacing, bent onto
a cylinder of radius 80 mm). Each carries the thesis's
skin constraint set (:func:`jaxface.pbd.skin_constraints`: stretch and cross-edge distance,
bending, area, capped volume) and 10% of its particles anchored (k = 0.2) to targets displaced
by N(0, 1 mm).

Measured, per mesh and scheme (``gs`` = graph-coloured Gauss-Seidel, ``jacobi`` = averaged
Jacobi with over-relaxation ``omega`` = 1.5):

* distance projections per second: a system of the distance constraints alone (stretch +
  cross), ``iterations`` x constraints / wall time of one ``relax`` call;
* ms per iteration of the full skin system;
* iterations (and wall time) for every particle to come within 1e-3 mm of the scheme's own
  converged configuration (float64, 20,000 iterations of the same scheme; with plain-PBD
  stiffness k < 1 the fixed point depends on the scheme, so their distance is reported too);
* a reverse-mode gradient through 100 iterations of the full system on the ICT face: wall time
  and XLA's peak buffer memory (``compiled.memory_analysis()``: arguments + outputs + temporaries)
  with and without checkpointing, plus the process's peak RSS growth;
* the sequential reference (:func:`jaxface.reference.solve`, plain Python loops over
  constraints, thesis order) on the same system: time per iteration and the ratio.

Prints a table and writes ``benchmarks/results/bench_pbd.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

TOL = 1e-3  # mm


def _machine():
    return {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "load_avg": list(os.getloadavg()),
    }


def _wall(fn, *args, repeat=5):
    jax.block_until_ready(fn(*args))  # compile
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return min(ts)


def ict_face():
    from jaxface.mesh import TriMesh
    from jaxface.testing import shared_path

    d = np.load(shared_path("data", "ict", "ict_face.npz"))
    n = 9409
    tri = d["triangles"][d["triangle_group"] == 0].astype(np.int64)
    tri = tri[(tri < n).all(1)]
    return TriMesh(d["neutral"][:n].astype(np.float64), tri)


def patch(face, n_target=1000):
    """A roughly round patch of ``face`` around the mouth with about ``n_target`` vertices."""
    x = face.vertices
    c = x[np.argmin(np.abs(x[:, 0]) + np.abs(x[:, 1] + 40.0))]
    d = np.linalg.norm(x[face.triangles].mean(1) - c, axis=1)
    r = np.sort(d)[min(len(d) - 1, 2 * n_target)]
    m, _ = face.submesh(d < r)
    return m


def big_sheet(n=317, spacing=0.5):
    """A regular n x n grid (spacing mm) bent onto a cylinder of radius 80 mm."""
    from jaxface.mesh import TriMesh

    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    u = (i.ravel() - n / 2) * spacing
    v = (j.ravel() - n / 2) * spacing
    R = 80.0
    x = np.stack([R * np.sin(u / R), v, R * np.cos(u / R) - R], 1)
    a = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    tri = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return TriMesh(x, tri)


def systems(mesh, seed=0):
    from jaxface import pbd

    rng = np.random.default_rng(seed)
    x = mesh.vertices
    groups = pbd.skin_constraints(mesh, origin=x.mean(0) - [0.0, 0.0, 60.0])
    sel = rng.choice(mesh.n_vertices, mesh.n_vertices // 10, replace=False)
    groups["anchors"] = pbd.anchor_constraints(
        sel, x[sel] + rng.normal(size=(len(sel), 3)), stiffness=0.2
    )
    full = pbd.build_system(groups, mesh.n_vertices)
    dist = pbd.build_system({k: groups[k] for k in ("stretch", "cross")}, mesh.n_vertices)
    return full, dist


def bench_mesh(name, mesh, dtype, *, converge=True, reference=True, quick=False):
    from jaxface import pbd
    from jaxface import reference as ref

    print(f"== {name}: {mesh.n_vertices} vertices, {len(mesh.triangles)} triangles", flush=True)
    t = time.perf_counter()
    S, D = systems(mesh)
    build_s = time.perf_counter() - t
    counts = {k: int(S[k].size) for k in S.names}
    n_dist = counts["stretch"] + counts.get("cross", 0)
    x32 = jnp.asarray(mesh.vertices, dtype)
    out = {
        "mesh": name,
        "n_vertices": mesh.n_vertices,
        "constraints": counts,
        "n_colors": {k: int(S[k].n_colors) for k in S.names if hasattr(S[k], "n_colors")},
        "build_s": build_s,
        "dtype": str(jnp.dtype(dtype)),
        "schemes": {},
    }
    iters = 100  # per call, so the per-call overhead is small against the sweeps
    for scheme in ("gs", "jacobi"):
        f_d = jax.jit(lambda s, x, sc=scheme: pbd.relax(s, x, iterations=iters, scheme=sc))
        t_d = _wall(f_d, D, x32)
        f_s = jax.jit(lambda s, x, sc=scheme: pbd.relax(s, x, iterations=iters, scheme=sc))
        t_s = _wall(f_s, S, x32)
        r = {
            "distance_proj_per_s": n_dist * iters / t_d,
            "ms_per_iteration_distance_only": 1e3 * t_d / iters,
            "ms_per_iteration_full": 1e3 * t_s / iters,
            "all_proj_per_s": sum(counts.values()) * iters / t_s,
        }
        out["schemes"][scheme] = r
        print(
            f"  {scheme:6s} distance-only {r['distance_proj_per_s'] / 1e6:7.1f} M proj/s "
            f"({r['ms_per_iteration_distance_only']:.2f} ms/iter)   full system "
            f"{r['ms_per_iteration_full']:.2f} ms/iter ({r['all_proj_per_s'] / 1e6:.1f} M proj/s)",
            flush=True,
        )
    if converge:
        x64 = jnp.asarray(mesh.vertices, jnp.float64)
        n_ref = 4000 if quick else 20000
        stars = {
            sc: np.asarray(
                jax.jit(lambda s, x, sc=sc: pbd.relax(s, x, iterations=n_ref, scheme=sc))(S, x64)
            )
            for sc in ("gs", "jacobi")
        }
        out["fixed_point_difference_mm"] = float(np.abs(stars["gs"] - stars["jacobi"]).max())
        print(
            f"  converged gs and jacobi configurations differ by {out['fixed_point_difference_mm']:.3f} mm "
            "(plain-PBD stiffness: the fixed point depends on the scheme)",
            flush=True,
        )
        for scheme in ("gs", "jacobi"):
            x_star = stars[scheme]
            step = 25
            f = jax.jit(lambda s, x, sc=scheme: pbd.relax(s, x, iterations=step, scheme=sc))
            x = x64
            k, hist = 0, []
            limit = 4000 if quick else 20000
            while k < limit:
                x = f(S, x)
                k += step
                err = float(np.abs(np.asarray(x) - x_star).max())
                hist.append((k, err))
                if err < TOL:
                    break
            reached = hist[-1][1] < TOL
            r = out["schemes"][scheme]
            r["iterations_to_1e-3mm"] = k if reached else None
            r["error_after_limit_mm"] = None if reached else hist[-1][1]
            r["error_history"] = hist[:: max(1, len(hist) // 40)]
            if reached:
                r["seconds_to_1e-3mm"] = k * r["ms_per_iteration_full"] / 1e3
            print(
                f"  {scheme:6s} iterations to {TOL:g} mm: "
                + (
                    f"{k} ({r['seconds_to_1e-3mm'] * 1e3:.0f} ms at {r['ms_per_iteration_full']:.2f} ms/iter)"
                    if reached
                    else f"not within {limit} (max error {hist[-1][1]:.2e} mm)"
                ),
                flush=True,
            )
    if reference:
        xs = mesh.vertices.copy()
        t = time.perf_counter()
        ref.solve(S, xs, iterations=1, order="user")
        ref_s = time.perf_counter() - t
        out["reference_s_per_iteration"] = ref_s
        for scheme in ("gs", "jacobi"):
            out["schemes"][scheme]["speedup_vs_reference"] = ref_s / (
                out["schemes"][scheme]["ms_per_iteration_full"] / 1e3
            )
        print(
            f"  sequential reference {ref_s * 1e3:.0f} ms/iter -> speed-up gs "
            f"{out['schemes']['gs']['speedup_vs_reference']:.0f}x, jacobi "
            f"{out['schemes']['jacobi']['speedup_vs_reference']:.0f}x",
            flush=True,
        )
    return out


def bench_gradient(mesh, dtype, iterations=100):
    """Reverse-mode gradient of a scalar of the solve w.r.t. start positions and anchor
    targets through ``iterations`` iterations: wall time and peak memory."""
    from jaxface import pbd

    S, _ = systems(mesh)
    x0 = jnp.asarray(mesh.vertices, dtype)
    w = jnp.asarray(np.random.default_rng(3).normal(size=mesh.vertices.shape), dtype)
    tgt = S["anchors"].target[S["anchors"].inv_perm]
    out = {
        "iterations": iterations,
        "n_vertices": mesh.n_vertices,
        "dtype": str(jnp.dtype(dtype)),
        "runs": [],
    }
    for ck in (None, 1, 10):

        def loss(x, t, ck=ck):
            return jnp.sum(
                w
                * pbd.relax(
                    S.set("anchors", target=t), x, iterations=iterations, checkpoint_every=ck
                )
            )

        g = jax.jit(jax.grad(loss, argnums=(0, 1)))
        t = time.perf_counter()
        comp = g.lower(x0, tgt).compile()
        compile_s = time.perf_counter() - t
        ma = comp.memory_analysis()
        peak = None
        if ma is not None:
            peak = (
                ma.argument_size_in_bytes
                + ma.output_size_in_bytes
                + ma.temp_size_in_bytes
                - ma.alias_size_in_bytes
            )
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        wall = _wall(comp, x0, tgt, repeat=2)
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        r = {
            "checkpoint_every": ck,
            "compile_s": compile_s,
            "wall_s": wall,
            "xla_peak_mb": None if peak is None else peak / 2**20,
            "xla_temp_mb": None if ma is None else ma.temp_size_in_bytes / 2**20,
            "rss_growth_mb": (rss1 - rss0) / 1024,
        }
        out["runs"].append(r)
        print(
            f"  gradient through {iterations} iterations, checkpoint_every={ck}: "
            f"{wall:.2f} s, XLA peak {r['xla_peak_mb']:.0f} MB (temporaries {r['xla_temp_mb']:.0f} MB), "
            f"compile {compile_s:.1f} s",
            flush=True,
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1k,ict,100k")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument(
        "--quick", action="store_true", help="fewer iterations, no 100k convergence run"
    )
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    dtype = jnp.float32 if args.dtype == "float32" else jnp.float64
    report = {"machine": _machine(), "tolerance_mm": TOL, "meshes": []}
    sizes = args.sizes.split(",")
    face = ict_face() if ("ict" in sizes or "1k" in sizes) else None
    for s in sizes:
        if s == "1k":
            report["meshes"].append(
                bench_mesh("ict_patch_1k", patch(face), dtype, quick=args.quick)
            )
        elif s == "ict":
            report["meshes"].append(bench_mesh("ict_face", face, dtype, quick=args.quick))
            report["gradient"] = bench_gradient(face, dtype)
        elif s == "100k":
            report["meshes"].append(
                bench_mesh(
                    "sheet_100k",
                    big_sheet(),
                    dtype,
                    converge=False,
                    reference=False,
                    quick=args.quick,
                )
            )
        else:
            raise SystemExit(f"unknown size {s!r}: use 1k, ict, 100k")
    out = Path(__file__).resolve().parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_pbd.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {out / 'bench_pbd.json'}")


if __name__ == "__main__":
    main()
