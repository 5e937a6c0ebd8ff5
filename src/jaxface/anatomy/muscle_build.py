"""Build time of the muscle system (thesis sec. 4.3, NumPy): the constraint network of every
placed muscle (:func:`build_muscle_system`), the shell data, the modiolus and the sphincter
ring geometry. Units: mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import pbd
from ..errors import RigError
from ..mesh import TriMesh
from .muscle_map import PlacedMuscle, check_sphincter_rings
from .muscle_system import (
    DISTANCE_GROUP,
    MODIOLUS_MAX_OFFSET_MM,
    MODIOLUS_SIGMA_MM,
    POSITION_STIFFNESS,
    SHELL_STIFFNESS,
    STIFFNESS,
    PendingMuscles,
    SupportPoints,
)


def build_muscle_system(
    placed: list[PlacedMuscle],
    registry,
    control_index: dict,
    iterations: int = 24,
    shell_stiffness: float = SHELL_STIFFNESS,
) -> tuple[PendingMuscles, SupportPoints]:
    """Assemble the muscle particle system (NumPy build time).

    Args:
        placed: the placed muscles (layer order).
        registry: their :class:`~jaxface.anatomy.muscle_map.SurfaceRegistry`.
        control_index: muscle name -> index in the activation vector.
        iterations: static number of sweeps of the quasi-static muscle solve.
        shell_stiffness: in [0, 1], :data:`SHELL_STIFFNESS` (0 = the thesis's muscle).

    Returns:
        ``(PendingMuscles, SupportPoints)``: add the skin's skull points to the collector,
        then call ``PendingMuscles.finalize()``.
    """
    meshes = registry.meshes
    with_mesh = [p for p in placed if p.mesh is not None]
    offsets = [0]
    muscle_offset = {}
    rests: list[np.ndarray] = []
    for p in with_mesh:
        assert p.rest_vertices is not None  # placement sets it together with the mesh
        rests.append(p.rest_vertices)
        muscle_offset[p.surface_id] = offsets[-1]
        offsets.append(offsets[-1] + p.rest_vertices.shape[0])
    n = offsets[-1]
    rest = np.concatenate(rests) if with_mesh else np.zeros((0, 3))
    sp = SupportPoints([], [], muscle_offset)
    dist, bend, vol = [], [], []
    dist_key = []
    fib = []  # (ids (m,3), w (m,3), ctrl, cmax, h, bottom (h,))
    mod_fib = {0: [], 1: []}  # side -> (fibre index, weight, insertion-end bottom particle)
    sph = []
    for mi, p in enumerate(with_mesh):
        off = offsets[mi]
        g = p.grid
        assert g is not None  # placement sets it together with the mesh
        kk = STIFFNESS[p.kind]
        ctrl = control_index.get(p.name, -1) if p.spec.active else -1
        cmax = p.spec.max_contraction
        for key, arr in (
            ("lat_up", g.latitudinal_up),
            ("lon_up", g.longitudinal_up),
            ("lat_low", g.latitudinal_low),
            ("lon_low", g.longitudinal_low),
            ("connection", g.connection),
            ("shear_up", g.shear_up),
            ("shear_low", g.shear_low),
        ):
            if kk[key] > 0 and len(arr):
                dist.append((arr + off, kk[key]))
                dist_key.append((key, g.w * g.h))
        tm = TriMesh(p.rest_vertices, g.triangles, validate=False)
        if kk["bend"] > 0 and len(tm.edge_pairs):
            bend.append((np.asarray(tm.edge_pairs) + off, kk["bend"]))
        vol.append((g.triangles + off, kk["volume"], np.arange(off, offsets[mi + 1])))
        if p.kind == "sphincter":
            rings = [sp.add(f.surface, f.tri, f.bary, f.positions, meshes) for f in p.fibres]
            sph.append(
                dict(
                    ids=np.stack([r[0] for r in rings]),
                    w=np.stack([r[1] for r in rings]),
                    bottom=off + np.arange(3 * g.w).reshape(3, g.w),
                    ctrl=ctrl,
                    cmax=cmax,
                    axes=p.axes,
                    ab=p.semi_axes,
                    fwd=_ring_forward(p.axes),
                    prot=float(p.spec.protrusion),
                    drag=float(p.spec.modiolus_drag),
                    skin=np.stack([p.insertion_skin, p.origin_skin]),
                )
            )
        else:
            corner = _is_corner_muscle(p)
            for j, f in enumerate(p.fibres):
                ids, w = sp.add(f.surface, f.tri, f.bary, f.positions, meshes)
                if corner:
                    mod_fib[0 if p.spec.side == "left" else 1].append(
                        (len(fib), 1.0 / len(p.fibres), off + (g.h - 1) * g.w + j)
                    )
                fib.append((ids, w, ctrl, cmax, g.h, off + np.arange(g.h) * g.w + j))
    h_max = max([f[4] for f in fib], default=2)
    m_max = max([f[0].shape[0] for f in fib], default=2)
    check_sphincter_rings([p.spec for p in placed])
    mod = _modiolus(mod_fib, fib, sph, rest, h_max)
    F = len(fib)
    fib_ids = np.zeros((F, m_max, 3), np.int64)
    fib_w = np.zeros((F, m_max, 3))
    for i, f in enumerate(fib):
        m = f[0].shape[0]
        fib_ids[i, :m] = f[0]
        fib_w[i, :m] = f[1]
        fib_ids[i, m:] = f[0][-1]  # pad with the last point (zero-length segments)
        fib_w[i, m:] = f[1][-1]
    valid = (
        np.concatenate([i * h_max + np.arange(f[4]) for i, f in enumerate(fib)])
        if fib
        else np.zeros(0, np.int64)
    )
    fib_len0 = np.zeros(F)
    for i, f in enumerate(fib):
        ids_, w_ = f[0], f[1]
        corner = np.stack(
            [[sp.skull_rest[-k - 1] if k < 0 else rest[k] for k in row] for row in ids_]
        )
        sp_pts = np.einsum("mk,mkd->md", w_, corner)
        fib_len0[i] = np.linalg.norm(np.diff(sp_pts, axis=0), axis=1).sum()
    bottom = np.concatenate([f[5] for f in fib]) if fib else np.zeros(0, np.int64)
    pos_ids = np.concatenate([bottom] + [s["bottom"].ravel() for s in sph])
    groups = []
    if dist:
        pairs = np.concatenate([a for a, _ in dist])
        ks = np.concatenate([np.full(len(a), k) for a, k in dist])
        groups.append(
            pbd.make_group(
                pbd.distance_constraints(pairs, rest, stiffness=ks),
                n,
                omega=1.5,
                name=DISTANCE_GROUP,
            )
        )
    if bend:
        ep = np.concatenate([a for a, _ in bend])
        ks = np.concatenate([np.full(len(a), k) for a, k in bend])
        groups.append(
            pbd.make_group(
                pbd.bending_constraints(ep, rest, stiffness=ks), n, omega=1.0, name="muscle bending"
            )
        )
    # the bottom particles follow their action-line samples (targets set every sweep)
    positions = pbd.make_group(
        pbd.anchor_constraints(pos_ids, rest[pos_ids], stiffness=POSITION_STIFFNESS),
        n,
        name="muscle positions",
    )
    shell = _shell_data(with_mesh, offsets, rest, fib, dist, dist_key)
    tri = np.concatenate([t for t, _, _ in vol])
    owner = np.concatenate([np.full(len(t), i) for i, (t, _, _) in enumerate(vol)])
    volume = pbd.make_group(
        pbd.volume_constraint(
            tri, rest, origin=np.zeros(3), owner=owner, stiffness=np.asarray([k for _, k, _ in vol])
        ),
        n,
        name="muscle volume",
    )
    top = shell["shell_top"]
    if len(np.unique(top)) != len(top):
        raise RigError("a muscle particle is the top of two shell frames; check the muscle grid.")
    shell_group = pbd.make_group(
        pbd.anchor_constraints(top, rest[top], stiffness=shell_stiffness), n, name="muscle shell"
    )
    data = dict(
        rest=rest,
        fib_ids=fib_ids,
        fib_w=fib_w,
        fib_ctrl=np.array([f[2] for f in fib], np.int32),
        fib_cmax=np.array([f[3] for f in fib], float),
        fib_h=np.array([f[4] for f in fib], float),
        fib_valid=valid,
        fib_bottom=bottom,
        fib_len0=fib_len0,
        sph_ids=np.stack([s["ids"] for s in sph]) if sph else np.zeros((0, 3, 2, 3), np.int64),
        sph_w=np.stack([s["w"] for s in sph]) if sph else np.zeros((0, 3, 2, 3)),
        sph_bottom=np.stack([s["bottom"] for s in sph]) if sph else np.zeros((0, 3, 2), np.int64),
        sph_ctrl=np.array([s["ctrl"] for s in sph], np.int32),
        sph_cmax=np.array([s["cmax"] for s in sph], float),
        sph_axes=np.stack([s["axes"] for s in sph]) if sph else np.zeros((0, 2, 3)),
        sph_ab=np.stack([s["ab"] for s in sph]) if sph else np.zeros((0, 2)),
        sph_forward=np.stack([s["fwd"] for s in sph]) if sph else np.zeros((0, 3)),
        sph_protrusion=np.array([s["prot"] for s in sph], float),
        sph_drag=np.array([s["drag"] for s in sph], float),
        **mod,
        groups=tuple(groups),
        positions=positions,
        shell=shell_group,
        volume=volume,
        inv_mass=np.ones(n),
        particle_layer=np.concatenate(
            [np.full(offsets[i + 1] - offsets[i], p.spec.layer) for i, p in enumerate(with_mesh)]
        )
        if with_mesh
        else np.zeros(0, np.int64),
        below=np.concatenate(
            [
                offsets[i] + np.tile(np.arange((offsets[i + 1] - offsets[i]) // 2), 2)
                for i in range(len(with_mesh))
            ]
        )
        if with_mesh
        else np.zeros(0, np.int64),
        **shell,
        offsets=tuple(offsets),
        names=tuple(p.name for p in with_mesh),
        layers=tuple(p.spec.layer for p in with_mesh),
        h_max=int(h_max),
        iterations=int(iterations),
        shell_stiffness=float(shell_stiffness),
    )
    return PendingMuscles(data, sp), sp


def _shell_frames(x, bottom, along, tri, mode=None):
    """Local frames ``(K, 3, 3)`` (rows: tangent, second tangent, normal) of the bottom sheet at
    the ``K`` particles ``bottom``, NumPy or JAX.

    The normal is the area-weighted mean normal of the bottom-sheet triangles ``tri`` ``(T, 3)``
    around the particle. The first tangent is the difference of the particle's neighbours
    along its fibre (``along[:, 0] - along[:, 1]``) with the normal part removed (``mode``
    0); where ``mode`` ``(K,)`` is 1 (fibre direction nearly along the normal, or neighbours
    coincident, e.g. on the inrolled lip) the normal crossed with the difference of its
    neighbours across the fibres (``along[:, 2] - along[:, 3]``); where it is 2 (no usable
    frame at rest) the identity. NaN-safe: degenerate geometry gives zero rows, not NaN.
    """
    xp = jnp if isinstance(x, jax.Array) else np
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    tn = xp.cross(b - a, c - a)
    if xp is jnp:
        vn = jax.ops.segment_sum(jnp.concatenate([tn, tn, tn]), tri.T.reshape(-1), x.shape[0])
    else:
        vn = np.zeros(x.shape)
        for k in range(3):
            np.add.at(vn, tri[:, k], tn)

    def unit(v):
        n2 = xp.sum(v * v, axis=-1, keepdims=True)
        ok = n2 > 1e-18
        return xp.where(ok, v / xp.sqrt(xp.where(ok, n2, 1.0)), 0.0)

    n = unit(vn[bottom])
    tu = x[along[:, 0]] - x[along[:, 1]]
    e1 = tu - xp.sum(tu * n, axis=-1, keepdims=True) * n
    if mode is not None:
        tv = x[along[:, 2]] - x[along[:, 3]]
        e1 = xp.where((mode == 1)[:, None], xp.cross(n, tv), e1)
    e1 = unit(e1)
    F = xp.stack([e1, xp.cross(n, e1), n], axis=1)
    if mode is not None:
        F = xp.where((mode == 2)[:, None, None], xp.eye(3, dtype=F.dtype), F)
    return F


def _shell_data(with_mesh, offsets, rest, fib, dist, dist_key) -> dict:
    """Build-time data of the shell constraint and of the active shortening (NumPy).

    Returns the fields ``shell_*`` (per top particle: its bottom particle, the bottom's
    neighbours along the fibre, the rest offset in the bottom sheet's frame, the row of its
    fibre sample or -1 for sphincters; all bottom-sheet triangles) and, per row of the fused
    distance group, the fibre sample whose contraction shortens a top-sheet edge along the
    fibre (``dist_lon_sample``) or thickens a connection (``dist_conn_sample``), -1 otherwise.
    """
    sample_of = {}  # bottom particle -> its row in the (P,) valid fibre samples
    for f in fib:
        for b in f[5]:
            sample_of[int(b)] = len(sample_of)
    tops, bots, along, tris = [], [], [], []
    for mi, p in enumerate(with_mesh):
        off, w, h = offsets[mi], p.grid.w, p.grid.h
        t = p.grid.triangles
        tris.append(t[(t < w * h).all(axis=1)] + off)
        for i in range(h):
            for j in range(w):
                bots.append(off + i * w + j)
                tops.append(off + w * h + i * w + j)
                jp, jm = (
                    ((j + 1) % w, (j - 1) % w)
                    if p.grid.periodic
                    else (min(j + 1, w - 1), max(j - 1, 0))
                )
                along.append(
                    (
                        off + min(i + 1, h - 1) * w + j,
                        off + max(i - 1, 0) * w + j,
                        off + i * w + jp,
                        off + i * w + jm,
                    )
                )
    top = np.asarray(tops, np.int64)
    bot = np.asarray(bots, np.int64)
    al = np.asarray(along, np.int64).reshape(-1, 4)
    tri = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    # the frame's construction is chosen once, at rest, so that it never switches: from the
    # fibre direction where that is at least ~17 degrees off the normal, else from the
    # neighbours across the fibres, else (degenerate rest geometry) the identity
    F0 = _shell_frames(rest, bot, al, tri)
    tu = rest[al[:, 0]] - rest[al[:, 1]]
    tu_n = np.einsum("kd,kd->k", tu, F0[:, 2])
    mode = np.where(tu_n**2 >= 0.91 * np.einsum("kd,kd->k", tu, tu), 1, 0)
    det = np.linalg.det(_shell_frames(rest, bot, al, tri, mode))
    mode = np.where(np.abs(det) < 0.5, 2, mode)
    local = np.einsum("kij,kj->ki", _shell_frames(rest, bot, al, tri, mode), rest[top] - rest[bot])
    lon, conn = [], []
    for (pairs, _), (key, nwh) in zip(dist, dist_key):
        none = np.full(len(pairs), -1)
        lon.append(
            np.array([sample_of.get(int(e[0]) - nwh, -1) for e in pairs])
            if key == "lon_up"
            else none
        )
        conn.append(
            np.array([sample_of.get(int(e[0]), -1) for e in pairs]) if key == "connection" else none
        )
    cat = lambda v: np.concatenate(v).astype(np.int64) if v else np.zeros(0, np.int64)  # noqa: E731
    return dict(
        shell_top=top,
        shell_along=al,
        shell_tri=tri,
        shell_local=local,
        shell_mode=mode.astype(np.int32),
        shell_sample=np.asarray([sample_of.get(int(b_), -1) for b_ in bot], np.int64),
        dist_lon_sample=cat(lon),
        dist_conn_sample=cat(conn),
    )


def _is_corner_muscle(p) -> bool:
    """A fibred, active, sided muscle whose insertion is placed at a mouth corner."""
    ins = p.spec.insertion if isinstance(p.spec.insertion, dict) else {}
    at = ins.get("at", {})
    off = np.asarray(ins.get("offset", [0.0, 0.0, 0.0]), float)
    return (
        p.kind in ("linear", "sheet")
        and p.spec.active
        and p.spec.side in ("left", "right")
        and any("mouth corner" in str(k).lower() for k in at)
        and float(np.linalg.norm(off)) <= MODIOLUS_MAX_OFFSET_MM
    )


def _modiolus(mod_fib, fib, sph, rest, h_max: int) -> dict:
    """Build-time modiolus data (:data:`MODIOLUS_GAIN`): per side the corner muscles' fibres
    (insertion-end sample index, weight), per sphincter ring sample and side a Gaussian weight
    of its rest distance to that side's modiolus.

    The modiolus of a side is the mouth corner: the ring's middle ellipse on the skin (the mean
    of its inner and outer skin rings) at its lateral end on that side (:func:`_ring_end`: sample
    0 on the left, ``n / 2`` on the right). Only a ring with a
    sample within ``2 MODIOLUS_SIGMA_MM`` of the side's corner muscles' insertion ends (the mean
    rest position of those fibres' end particles) has one: the ring they insert into.
    """
    J = max(1, len(mod_fib[0]), len(mod_fib[1]))
    end = np.zeros((2, J), np.int64)
    last = np.zeros((2, J), np.int64)
    fw = np.zeros((2, J))
    ends = np.zeros((2, 3))
    ok = np.zeros(2, bool)
    for s_ in (0, 1):
        for k, (fi, w, _pid) in enumerate(mod_fib[s_]):
            end[s_, k] = fi * h_max + fib[fi][4] - 1
            last[s_, k] = fi
            fw[s_, k] = w
        if mod_fib[s_]:
            ends[s_] = rest[[pid for _, _, pid in mod_fib[s_]]].mean(axis=0)
            ok[s_] = True
    n = sph[0]["ids"].shape[1] if sph else 2
    mod_w = np.zeros((len(sph), 3, n, 2))
    for k, s in enumerate(sph):
        pos = rest[s["bottom"]]  # (3, n, 3)
        mid_skin = 0.5 * (s["skin"][0] + s["skin"][1])  # (n, 3)
        g = np.zeros((3, n, 2))
        for i in (0, 1):
            if not ok[i] or np.linalg.norm(pos - ends[i], axis=-1).min() > 2.0 * MODIOLUS_SIGMA_MM:
                continue
            corner = _ring_end(mid_skin, 0.0 if i == 0 else 0.5 * n)  # left, right
            d = np.linalg.norm(pos - corner, axis=-1)  # (3, n)
            g[..., i] = np.exp(-0.5 * (d / MODIOLUS_SIGMA_MM) ** 2)
        # each sample follows its nearer modiolus, the two blended across the mid-line
        mod_w[k] = g * (g / np.maximum(g.sum(axis=-1, keepdims=True), 1e-300))
    side = np.full(len(fib), 2, np.int32)  # 2: the fibre is not a corner muscle's
    for s_ in (0, 1):
        if np.any(mod_w[..., s_] > 0):
            for fi, _w, _pid in mod_fib[s_]:
                side[fi] = s_
    ramp = np.zeros((len(fib), h_max))
    for i, f in enumerate(fib):
        ramp[i, : f[4]] = np.arange(f[4]) / max(f[4] - 1, 1)
    return dict(
        mod_w=mod_w, fib_mod_side=side, fib_ramp=ramp, mod_end=end, mod_last=last, mod_fw=fw
    )


def _ring_end(ring, u: float):
    """The point at sample parameter ``u`` of a closed ring of samples ``(n, 3)`` (sample ``k``
    at ``u = k``): the sample itself for a whole ``u``, else the cubic through the four samples
    around it. A sphincter's rings are drawn from ``phi = 2 pi k / n`` (:func:`ellipse_points`),
    so its lateral ends are ``u = 0`` (left) and ``u = n / 2`` (right, between two samples when
    ``n`` is odd)."""
    n = len(ring)
    k = int(np.floor(u))
    f = u - k
    if f == 0.0:
        return ring[k % n]
    w = np.array(
        [
            -f * (f - 1) * (f - 2) / 6,
            (f + 1) * (f - 1) * (f - 2) / 2,
            -(f + 1) * f * (f - 2) / 2,
            (f + 1) * f * (f - 1) / 6,
        ]
    )
    return w @ ring[[(k - 1) % n, k % n, (k + 1) % n, (k + 2) % n]]


def _ring_forward(axes) -> np.ndarray:
    """``(3,)`` unit normal of a sphincter ring's plane (its two ``(2, 3)`` ellipse axes),
    oriented toward the face's front (+z)."""
    n = np.cross(np.asarray(axes[0], float), np.asarray(axes[1], float))
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    return n if n[2] >= 0 else -n
