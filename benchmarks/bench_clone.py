"""Benchmark of facial motion cloning (thesis chapter 6): accuracy and time (mm, %, s).

Run from the repository root (needs the shared data, ``JAXFACE_SHARED`` or ``../shared``)::

    python benchmarks/bench_clone.py [--quick] [--full]

Sources and targets are made from the ICT face model (``data/ict/ict_face.npz``, face
vertices 0..9408, its 57 expression morph targets, 22 Bosphorus landmark vertices from
``data/bosphorus_style/truth.json``). Low-resolution faces like the thesis's test models
(367-2197 vertices) are made by re-meshing the ICT face as a frontal range grid (a new mesh,
new connectivity; morph targets carried along by barycentric interpolation; triangles that
jawOpen tears apart, i.e. across the lips, removed).

Tables:

1. self-clone (thesis Table 6.2, eq. 6.1 error in %): each face cloned onto itself;
2. clone time beside thesis Table 6.1 (RT refinement, CT cloning, TT total; 57 morph targets
   here, 84 there) and accuracy for ICT -> ICT identity (neutral + identity modes, weights
   ~N(0, 1)) between meshes of thesis-like sizes; the reference is the identity's own ICT
   expressions (ICT's expression deltas do not depend on the identity). Besides e (eq. 6.1)
   the origin-independent displacement error ``100 * sum|d - d_ref| / sum|d_ref|`` is given
   for the thesis transfer (``disp``), the pre-refinement morph (``rough``), the affine part
   (``affine``) and without refinement (``no-ref``), with the floor that interpolation between
   the two resolutions alone causes (copying the source displacements through the true
   correspondence). ``CPU s`` is the process CPU time of the whole clone (the wall times
   depend on the machine's load, which is printed);
3. with ``--full``: the full-resolution ICT face (9409 vertices) onto itself and onto an
   identity, and onto the Bosphorus-style neutral scan bs901 (``.bnt`` range grid meshed by
   :mod:`jaxface.io.bosphorus`; its truth is the bs901 identity with the ICT expressions,
   moved by the scan's rigid motion).

Prints tables and writes ``benchmarks/results/bench_clone.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np


def load_ict():
    from jaxface.testing import shared_path

    d = np.load(shared_path("data", "ict", "ict_face.npz", pytest_skip=False))
    truth = json.loads(
        shared_path("data", "bosphorus_style", "truth.json", pytest_skip=False).read_text()
    )
    tri, grp = d["triangles"], d["triangle_group"]
    nv = 9409
    F = tri[(grp == 0) & (tri < nv).all(1)].astype(np.int64)
    lm = truth["landmark_vertex_ids_ict"]
    return dict(
        V=d["neutral"][:nv].astype(float),
        F=F,
        E=d["expression_deltas"][:, :nv].astype(float),
        names=[str(n) for n in d["expression_names"]],
        ID=d["identity_deltas"][:, :nv].astype(float),
        lm_names=list(lm),
        lm_ids=np.array(list(lm.values())),
        truth=truth,
    )


def resample_face(V, F, spacing, E, jaw):
    """Re-mesh a face as a frontal range grid (spacing mm). Returns (TriMesh, interp) where
    interp(field (..., Vict, 3)) gives the field at the new vertices, and (tri, bary) of the
    new vertices on the ICT mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from jaxface.clone import cast_segments
    from jaxface.io.bosphorus import grid_triangles
    from jaxface.mesh import TriMesh

    xs = np.arange(-80, 80 + 1e-9, spacing)
    ys = np.arange(75, -75 - 1e-9, -spacing)
    X, Y = np.meshgrid(xs, ys)
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 400.0)], 1)
    hit, tri, bary, _ = cast_segments(
        o, np.tile([0, 0, -1.0], (len(o), 1)), 600.0, V, F, two_sided=False, normal_dot_min=None
    )
    xyz = np.zeros((len(o), 3))
    xyz[hit] = np.einsum("kj,kjd->kd", bary[hit], V[F[tri[hit]]])
    T = grid_triangles(xyz.reshape(*X.shape, 3), hit.reshape(X.shape), spacing=spacing)
    flat = T[..., 0] * X.shape[1] + T[..., 1]

    def interp_at(field, k):
        return np.einsum("kj,...kjd->...kd", bary[k], field[..., F[tri[k]], :])

    J = np.zeros_like(xyz)
    J[hit] = interp_at(E[jaw], np.flatnonzero(hit))
    e0 = np.linalg.norm(xyz[flat] - xyz[np.roll(flat, 1, 1)], axis=2)
    e1 = np.linalg.norm((xyz + J)[flat] - (xyz + J)[np.roll(flat, 1, 1)], axis=2)
    flat = flat[(e1 < 2 * e0 + 1e-9).all(1)]
    keep = np.unique(flat)
    tris = np.searchsorted(keep, flat)
    n = keep.size
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    _, lab = connected_components(
        coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False
    )
    big = np.argmax(np.bincount(lab))
    tris = tris[(lab[tris] == big).all(1)]
    used = np.unique(tris)
    k = keep[used]
    mesh = TriMesh(xyz[k], np.searchsorted(used, tris), validate=False)
    return mesh, (lambda field: interp_at(field, k)), (tri[k], bary[k])


def spacing_for(V, F, E, jaw, n_target):
    s = 6.0
    for _ in range(3):
        m, _, _ = resample_face(V, F, s, E, jaw)
        s *= float(np.sqrt(m.n_vertices / n_target))
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases (for a smoke run)")
    ap.add_argument(
        "--full", action="store_true", help="also the 9409-vertex ICT face and the bs901 scan"
    )
    ap.add_argument("--seed", type=int, default=0, help="identity weights seed")
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    from jaxface import clone
    from jaxface.landmarks import Landmarks
    from jaxface.mesh import TriMesh

    ict = load_ict()
    V, F, E, names = ict["V"], ict["F"], ict["E"], ict["names"]
    jaw = names.index("jawOpen")
    w = np.random.default_rng(args.seed).normal(size=ict["ID"].shape[0])
    VI = V + np.einsum("i,ivd->vd", w, ict["ID"])
    lm_src = Landmarks(ict["lm_names"], V[ict["lm_ids"]])
    lm_id = Landmarks(ict["lm_names"], VI[ict["lm_ids"]])
    results: dict = {
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "loadavg_at_start": os.getloadavg(),
        },
        "n_morph_targets": int(E.shape[0]),
        "identity_weights": w.tolist(),
        "self_clone": [],
        "cross_identity": [],
        "full": [],
    }

    sizes = {"data": 367, "kevin": 498, "joakim": 909, "beta": 2197}
    if args.quick:
        sizes = {"data": 367, "beta": 2197}
    meshes = {}
    for key, n in sizes.items():
        s = spacing_for(V, F, E, jaw, n)
        meshes[key] = (s,) + resample_face(V, F, s, E, jaw)
        meshes[key + "_id"] = (s,) + resample_face(VI, F, s, E, jaw)

    # ---------------------------------------------------------------- self-clone
    print(
        f"self-clone (thesis Table 6.2: 0.028 % - 0.28 %), eq. 6.1 over all {E.shape[0]} ICT expressions"
    )
    print(f"{'face':<10}{'verts':>7}{'e (6.1) %':>12}{'disp err %':>12}{'Is':>4}{'TT s':>8}")
    for key in sizes:
        s, mesh, interp, _ = meshes[key]
        ES = interp(E)
        t = time.perf_counter()
        r = clone.clone_motion(mesh, mesh, lm_src, lm_src, source_deltas=ES)
        tt = time.perf_counter() - t
        e = clone.clone_error(mesh.vertices + ES, r.targets)
        de = clone.delta_error(ES, r.deltas)
        print(f"{key:<10}{mesh.n_vertices:>7}{e:>12.2e}{de:>12.2e}{r.fit.iterations:>4}{tt:>8.2f}")
        results["self_clone"].append(
            dict(
                face=key,
                vertices=mesh.n_vertices,
                spacing_mm=s,
                e_percent=e,
                disp_err_percent=de,
                iterations=r.fit.iterations,
                seconds=tt,
            )
        )

    # ---------------------------------------------------------------- cross identity
    pairs = [
        ("beta", "data"),
        ("data", "beta"),
        ("joakim", "data"),
        ("data", "joakim"),
        ("beta", "kevin"),
        ("kevin", "beta"),
    ]
    thesis = {
        ("beta", "data"): (4.0, 1.0, 5.0),
        ("data", "beta"): (1.3, 3.6, 5.0),
        ("joakim", "data"): (4.4, 1.0, 5.4),
        ("data", "joakim"): (1.0, 1.2, 2.3),
        ("beta", "kevin"): (4.6, 0.8, 5.4),
        ("kevin", "beta"): (10.6, 0.6, 11.3),
    }
    pairs = [p for p in pairs if p[0] in sizes and p[1] in sizes]
    print(
        f"\nICT generic -> ICT identity, thesis-like sizes ({E.shape[0]} morph targets; thesis: 84)"
    )
    hdr = (
        f"{'source->target':<16}{'Vs':>6}{'Vt':>6}{'MVs':>6}{'CPs':>6}{'Is':>4}{'RT s':>7}{'CT s':>7}"
        f"{'TT s':>7}{'CPU s':>7}{'thesis TT':>10}{'e6.1 %':>8}{'disp %':>8}{'rough %':>8}{'affine %':>9}"
        f"{'no-ref %':>9}{'no-ref TT':>10}{'floor %':>8}"
    )
    print(hdr)
    for a, b in pairs:
        _, src, isrc, _ = meshes[a]
        _, tgt, itgt, (ttri, tbary) = meshes[b + "_id"]
        ES, ET = isrc(E), itgt(E)
        c = time.process_time()
        r = clone.clone_motion(src, tgt, lm_src, lm_id, source_deltas=ES)
        cpu = time.process_time() - c
        # the same fit, other transfers of the displacements
        ra = (
            clone.apply_clone(
                r.fit, r.mapping, src.triangles, tgt.vertices, ES, r.moving, transfer="affine"
            )
            - tgt.vertices
        )
        rr = (
            clone.apply_clone(
                r.fit, r.mapping, src.triangles, tgt.vertices, ES, r.moving, transfer="rough"
            )
            - tgt.vertices
        )
        # no refinement at all (landmarks + contours only)
        c0 = time.process_time()
        r0 = clone.clone_motion(src, tgt, lm_src, lm_id, source_deltas=ES, max_iterations=0)
        cpu0 = time.process_time() - c0
        # floor: copy the source displacements through the true correspondence
        tp = np.einsum("kj,kjd->kd", tbary, V[F[ttri]])
        sp, _ = src.closest_points(tp)
        floor = np.einsum(
            "vk,tvkd->tvd", np.asarray(sp.bary), ES[:, src.triangles[np.asarray(sp.tri)]]
        )
        e = clone.clone_error(tgt.vertices + ET, r.targets)
        de = clone.delta_error(ET, r.deltas)
        dea = clone.delta_error(ET, ra)
        der = clone.delta_error(ET, rr)
        de0 = clone.delta_error(ET, r0.deltas)
        fl = clone.delta_error(ET, floor)
        ft = r.timings
        th = thesis[(a, b)]
        print(
            f"{a + '->' + b:<16}{src.n_vertices:>6}{tgt.n_vertices:>6}{int(r.fit.movable.sum()):>6}"
            f"{len(r.fit.src_points):>6}{r.fit.iterations:>4}{ft['fit']:>7.2f}{ft['clone']:>7.2f}"
            f"{ft['total']:>7.2f}{cpu:>7.2f}{th[2]:>10.1f}{e:>8.3f}{de:>8.2f}{der:>8.2f}{dea:>9.2f}"
            f"{de0:>9.2f}{r0.timings['total']:>10.2f}{fl:>8.2f}"
        )
        results["cross_identity"].append(
            dict(
                source=a,
                target=b,
                Vs=src.n_vertices,
                Vt=tgt.n_vertices,
                MVs=int(r.fit.movable.sum()),
                CPs=len(r.fit.src_points),
                Is=r.fit.iterations,
                RT=ft["fit"],
                CT=ft["clone"],
                TT=ft["total"],
                cpu_seconds=cpu,
                thesis_RT_CT_TT=th,
                e_percent=e,
                disp_err_percent=de,
                disp_err_rough_percent=der,
                disp_err_affine_percent=dea,
                disp_err_no_refinement_percent=de0,
                no_refinement_TT=r0.timings["total"],
                no_refinement_cpu_seconds=cpu0,
                floor_percent=fl,
                contours_used=r.fit.contours_used,
                contours_skipped=r.fit.contours_skipped,
                history=r.fit.history,
            )
        )

    if args.full:
        print("\nfull resolution (9409 vertices)")
        t = time.perf_counter()
        mesh = TriMesh(V, F, validate=False)
        r = clone.clone_motion(mesh, mesh, lm_src, lm_src, source_deltas=E)
        tt = time.perf_counter() - t
        e = clone.clone_error(V + E, r.targets)
        print(f"  ICT -> itself: e (6.1) = {e:.2e} %, {tt:.1f} s, {r.fit.iterations} iterations")
        results["full"].append(dict(case="ict_self", e_percent=e, seconds=tt))
        for max_it in (0, 5):
            t = time.perf_counter()
            r = clone.clone_motion(
                mesh,
                TriMesh(VI, F, validate=False),
                lm_src,
                lm_id,
                source_deltas=E,
                max_iterations=max_it,
            )
            tt = time.perf_counter() - t
            e = clone.clone_error(VI + E, r.targets)
            de = clone.delta_error(E, r.deltas)
            print(
                f"  ICT -> identity (max_iterations={max_it}): e (6.1) = {e:.3f} %, displacement "
                f"error {de:.2f} %, {tt:.1f} s, {len(r.fit.src_points)} pairs"
            )
            results["full"].append(
                dict(
                    case=f"ict_identity_it{max_it}",
                    e_percent=e,
                    disp_err_percent=de,
                    seconds=tt,
                    pairs=len(r.fit.src_points),
                )
            )
        bosphorus_case(ict, clone, results)

    out = Path(__file__).resolve().parent / "results" / "bench_clone.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    results["machine"]["loadavg_at_end"] = os.getloadavg()
    out.write_text(json.dumps(results, indent=1, default=float))
    print(
        f"\nwrote {out}; load average {results['machine']['loadavg_at_start']} -> "
        f"{results['machine']['loadavg_at_end']} on {results['machine']['cpus']} CPUs"
    )


def bosphorus_case(ict, clone, results):
    """ICT generic face (2197-vertex grid) -> the bs901 neutral scan (.bnt, meshed)."""
    from jaxface.io.bosphorus import load_scan
    from jaxface.landmarks import Landmarks
    from jaxface.mesh import load_mesh
    from jaxface.testing import shared_path

    V, F, E, names = ict["V"], ict["F"], ict["E"], ict["names"]
    scan = load_scan(shared_path("data", "bosphorus_style", "bs901_N_N_0.bnt", pytest_skip=False))
    tgt = scan.to_mesh()
    truth_mesh = load_mesh(
        shared_path("data", "bosphorus_style", "bs901_N_N_0.truth.ply", pytest_skip=False),
        validate=False,
    )
    rig = ict["truth"]["bs901_N_N_0"]["rigid"]
    p, y = np.radians(rig["pitch"]), np.radians(rig["yaw"])
    Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    R = Rx @ Ry
    # truth displacement at every scan vertex: ICT expression deltas at its closest point on
    # the (rigidly moved) truth mesh, rotated like the scan
    tri_face = F
    face_truth = clone.as_trimesh((np.asarray(truth_mesh.vertices)[:9409], tri_face))
    sp, dist = face_truth.closest_points(tgt.vertices)
    on_face = dist < 1.0
    ET = np.einsum("vk,tvkd->tvd", np.asarray(sp.bary), E[:, tri_face[np.asarray(sp.tri)]]) @ R.T
    s = spacing_for(V, F, E, names.index("jawOpen"), 2197)
    src, isrc, _ = resample_face(V, F, s, E, names.index("jawOpen"))
    lm_src = Landmarks(ict["lm_names"], V[ict["lm_ids"]])
    t = time.perf_counter()
    r = clone.clone_motion(src, tgt, lm_src, scan.landmarks, source_deltas=isrc(E))
    tt = time.perf_counter() - t
    de = clone.delta_error(ET[:, on_face], r.deltas[:, on_face])
    e = clone.clone_error((tgt.vertices + ET)[:, on_face], r.targets[:, on_face])
    print(
        f"  ICT grid ({src.n_vertices} v) -> bs901 neutral .bnt scan ({tgt.n_vertices} v): "
        f"e (6.1) = {e:.3f} %, displacement error {de:.2f} % over {int(on_face.sum())} scan vertices "
        f"on the face, {tt:.1f} s (RT {r.timings['fit']:.1f}, CT {r.timings['clone']:.1f}), "
        f"{r.fit.iterations} iterations; contours used {r.fit.contours_used}, skipped "
        f"{r.fit.contours_skipped}"
    )
    results["full"].append(
        dict(
            case="bs901_scan",
            Vs=src.n_vertices,
            Vt=tgt.n_vertices,
            e_percent=e,
            disp_err_percent=de,
            seconds=tt,
            iterations=r.fit.iterations,
        )
    )


if __name__ == "__main__":
    main()
