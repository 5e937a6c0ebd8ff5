"""Speed cost of the input checks (issue 49) on the default head (12,140 vertices).

Run from the repository root::

    python benchmarks/bench_checks.py [--repeat 15] [--dtype float32|float64]

Measures, alternately in one run (min and median over ``--repeat`` calls, ms):

* the Python-side control check alone (:func:`jaxface.validate.check_controls`, min of 50);
* ``synthesize`` with its checks (:func:`jaxface.validate.checked_controls`: NaN/range checks
  of concrete controls in Python) against the same jit-compiled body without them
  (``synthesize.__wrapped__``);
* a ``jax.jit`` of a function calling ``synthesize`` (traced controls: the run-time
  :func:`equinox.error_if` check inside the compiled program) against the same with the
  unchecked body;
* ``jax.vmap`` over a batch of 8 activation vectors, checked (the ``error_if`` under vmap)
  against unchecked;
* mesh hygiene: :func:`jaxface.hygiene.clean_mesh` of the skin against reading it from a
  PLY (:func:`jaxface.mesh.load_mesh`), and :func:`jaxface.validate.check_skin` against
  ``build_rig``.

Prints a table and writes ``benchmarks/results/bench_checks.json``. Timings are wall-clock on
whatever machine runs it (say which when you quote them).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def _alternate(fns: dict, repeat: int) -> dict:
    """Time each callable ``repeat`` times, interleaved; ms min/median."""
    times = {k: [] for k in fns}
    for _ in range(repeat):
        for k, f in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(f())
            times[k].append(1e3 * (time.perf_counter() - t))
    return {k: {"min_ms": min(v), "median_ms": statistics.median(v)} for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = ap.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)

    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import build_rig, synthesize
    from jaxface.head import generic_head
    from jaxface.hygiene import clean_mesh
    from jaxface.mesh import load_mesh, save_mesh
    from jaxface.validate import check_controls, check_skin

    head = generic_head()
    t = time.perf_counter()
    check_skin(head)
    skin_check_ms = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    rig = build_rig(head)
    build_s = time.perf_counter() - t
    dt = jnp.float32 if args.dtype == "float32" else jnp.float64
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.uniform(0.0, 0.3, rig.n_controls), dt)
    jaw = JawPose(4.0, 0.0, 0.0)
    raw = synthesize.__wrapped__

    jit_checked = jax.jit(lambda x: synthesize(rig, x, jaw))
    jit_raw = jax.jit(lambda x: raw(rig, x, jaw))
    A = jnp.asarray(rng.uniform(0.0, 0.3, (8, rig.n_controls)), dt)
    vm_checked = jax.jit(jax.vmap(lambda x: synthesize(rig, x, jaw)))
    vm_raw = jax.jit(jax.vmap(lambda x: raw(rig, x, jaw)))
    for f in (
        lambda: synthesize(rig, a, jaw),
        lambda: raw(rig, a, jaw, 0.0),
        lambda: jit_checked(a),
        lambda: jit_raw(a),
        lambda: vm_checked(A),
        lambda: vm_raw(A),
    ):
        jax.block_until_ready(f())  # compile
    same = float(jnp.max(jnp.abs(jit_checked(a) - jit_raw(a))))
    # the Python-side check alone (what the checked synthesize adds to a concrete call)
    t_chk = []
    for _ in range(50):
        t = time.perf_counter()
        check_controls(rig.muscle_names, a, jaw, 0.0)
        t_chk.append(1e3 * (time.perf_counter() - t))
    res = _alternate(
        {
            "synthesize_checked": lambda: synthesize(rig, a, jaw),
            "synthesize_unchecked": lambda: raw(rig, a, jaw, 0.0),
            "jit_checked": lambda: jit_checked(a),
            "jit_unchecked": lambda: jit_raw(a),
            "vmap8_checked": lambda: vm_checked(A),
            "vmap8_unchecked": lambda: vm_raw(A),
        },
        args.repeat,
    )
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "head.ply")
        save_mesh(p, head.mesh)
        t_load, t_clean = [], []
        for _ in range(5):
            t = time.perf_counter()
            m = load_mesh(p, validate=False)
            t_load.append(1e3 * (time.perf_counter() - t))
            t = time.perf_counter()
            clean_mesh(m)
            t_clean.append(1e3 * (time.perf_counter() - t))
    out = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "dtype": args.dtype,
        "vertices": int(head.mesh.n_vertices),
        "build_rig_s": build_s,
        "check_skin_ms": skin_check_ms,
        "load_mesh_ms_min": min(t_load),
        "clean_mesh_ms_min": min(t_clean),
        "checked_vs_unchecked_max_diff_mm": same,
        "check_controls_ms_min": min(t_chk),
        **{f"{k}_{s}": v[s] for k, v in res.items() for s in ("min_ms", "median_ms")},
    }
    for k in ("synthesize", "jit", "vmap8"):
        out[f"{k}_ratio_min"] = res[f"{k}_checked"]["min_ms"] / res[f"{k}_unchecked"]["min_ms"]
        out[f"{k}_ratio_median"] = (
            res[f"{k}_checked"]["median_ms"] / res[f"{k}_unchecked"]["median_ms"]
        )
    print(f"{'case':<22}{'checked ms':>12}{'unchecked ms':>14}{'ratio (min)':>13}")
    for k in ("synthesize", "jit", "vmap8"):
        print(
            f"{k:<22}{res[f'{k}_checked']['min_ms']:>12.2f}"
            f"{res[f'{k}_unchecked']['min_ms']:>14.2f}{out[f'{k}_ratio_min']:>13.3f}"
        )
    print(f"check_controls alone: {min(t_chk):.3f} ms (min of 50)")
    print(
        f"check_skin {skin_check_ms:.1f} ms vs build_rig {build_s:.1f} s; clean_mesh "
        f"{min(t_clean):.1f} ms vs load_mesh {min(t_load):.1f} ms; results equal to "
        f"{same:.2g} mm"
    )
    dest = Path(__file__).parent / "results" / "bench_checks.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=1))
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
