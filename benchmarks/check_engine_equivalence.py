"""Check that a change of the PBD engine leaves the rig's syntheses unchanged (issue 47).

Run once with each code version, then compare::

    JAXFACE_SHARED=../shared PYTHONPATH=<old>/src python benchmarks/check_engine_equivalence.py \
        --save /tmp/old.npz
    JAXFACE_SHARED=../shared PYTHONPATH=$PWD/src python benchmarks/check_engine_equivalence.py \
        --save /tmp/new.npz
    python benchmarks/check_engine_equivalence.py --compare /tmp/old.npz /tmp/new.npz

Rigs: the default head (:func:`jaxface.head.generic_head`), the ICT face with its teeth, and
bs901's rig (the template registered to ``bs901_N_N_0`` as ``jaxface fit`` does). Poses: rest,
four single-muscle activations (controls at 1), happiness, a jaw opening (12 degrees), all in
float64, and on the default head a 3-frame dynamic animation (:func:`jaxface.anatomy.rig.simulate`).
The comparison prints the largest vertex difference (mm) per rig and pose.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

if TYPE_CHECKING:
    from jaxface.anatomy.rig import Rig


def _rigs(which) -> Iterator[tuple[str, Rig]]:
    from jaxface.anatomy.rig import Rig, build_rig
    from jaxface.head import generic_head

    shared = os.environ.get("JAXFACE_SHARED", "../shared")

    def pbd_rig(r) -> Rig:
        assert isinstance(r, Rig)
        return r

    if "head" in which:
        yield "head", pbd_rig(build_rig(generic_head()))
    if "ict" in which:
        from jaxface.anatomy.ict import load_ict_face

        f = load_ict_face(
            os.path.join(shared, "data", "ict", "ict_face.npz"),
            os.path.join(shared, "data", "bosphorus_style", "truth.json"),
        )
        yield (
            "ict",
            pbd_rig(
                build_rig(f.skin, f.landmarks, upper_teeth=f.upper_teeth, lower_teeth=f.lower_teeth)
            ),
        )
    if "bs901" in which:
        from jaxface.fit.pipeline import warp_teeth
        from jaxface.fit.register import register_template
        from jaxface.io import load_scan

        scan = load_scan(os.path.join(shared, "data", "bosphorus_style", "bs901_N_N_0.bnt"))
        template = generic_head()
        reg = register_template(scan, template=template)
        upper, lower = warp_teeth(template, reg)
        yield (
            "bs901",
            pbd_rig(build_rig(reg.mesh, reg.landmarks, upper_teeth=upper, lower_teeth=lower)),
        )


def _poses(rig):
    from jaxface import facs

    n = rig.n_controls
    out = {"rest": (np.zeros(n), 0.0)}
    for i in np.linspace(0, n - 1, 4).astype(int):
        a = np.zeros(n)
        a[i] = 1.0
        out[f"only_{rig.muscle_names[i]}"] = (a, 0.0)
    a, j, _ = facs.emotion_controls("happiness", rig.muscle_names)
    out["happiness"] = (np.asarray(a), float(j.pitch_deg))
    out["jaw_open_12deg"] = (np.zeros(n), 12.0)
    return out


def save(path, which):
    from jaxface.anatomy.jaw import JawPose
    from jaxface.anatomy.rig import simulate, synthesize

    res = {}
    for name, rig in _rigs(which):
        t0 = time.perf_counter()
        for pose, (a, pitch) in _poses(rig).items():
            x = synthesize(rig, jnp.asarray(a, jnp.float64), JawPose(jnp.float64(pitch)))
            res[f"{name}/{pose}"] = np.asarray(x)
        if name == "head":
            n = rig.n_controls
            A = np.zeros((3, n))
            A[:, 0] = [0.3, 0.6, 1.0]
            res[f"{name}/simulate_3_frames"] = np.asarray(simulate(rig, jnp.asarray(A)))
        print(f"{name}: {time.perf_counter() - t0:.1f} s", flush=True)
    tmp = path + ".tmp.npz"
    np.savez(tmp, **res)
    os.replace(tmp, path)
    print(f"wrote {len(res)} syntheses to {path}")


def compare(a_path, b_path, tol):
    a, b = np.load(a_path), np.load(b_path)
    worst = 0.0
    for k in sorted(set(a.files) | set(b.files)):
        if k not in a.files or k not in b.files:
            print(f"{k:50s} missing in one file")
            worst = np.inf
            continue
        d = float(np.max(np.abs(a[k] - b[k])))
        worst = max(worst, d)
        print(f"{k:50s} max |dx| = {d:.3e} mm")
    print(f"largest difference {worst:.3e} mm (tolerance {tol:g} mm)")
    return worst <= tol


def main(argv=None):
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--save")
    p.add_argument("--rigs", default="head,ict,bs901")
    p.add_argument("--compare", nargs=2)
    p.add_argument("--tol", type=float, default=1e-6)
    args = p.parse_args(argv)
    if args.save:
        save(args.save, args.rigs.split(","))
    if args.compare:
        return 0 if compare(args.compare[0], args.compare[1], args.tol) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
