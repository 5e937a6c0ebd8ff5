"""Run time of the muscle system (JAX): contraction targets by re-sampling
(:func:`sample_targets`), fibre thickening, the shell targets, the sweep, the warm start and
the solve (:func:`solve_muscles`). Units: mm.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .. import pbd
from .muscle_build import _shell_frames
from .muscle_system import (
    DISTANCE_GROUP,
    MODIOLUS_GAIN,
    THICKENING_RANGE,
    MuscleSystem,
    _eval_support,
)


def shell_targets(system: MuscleSystem, x, ids, tg, thick):
    """Where the shell constraint puts every top particle, ``(K, 3)`` mm (``K`` = all tops).

    The *shell* is our addition to the thesis's muscle (sec. 4.3.1 holds the top sheet only
    by the connections on the grid boundary, the lateral and longitudinal springs and the
    volume). The target of a top particle is its bottom particle's action-line sample plus the
    top's rest offset expressed in the local frame (:func:`_shell_frames`) of the bottom sheet
    laid on the samples, its normal part scaled by the fibre's thickening (rest over
    contracted fibre length, clipped to :data:`THICKENING_RANGE`): a contracting muscle
    shortens and bulges, keeping its volume, instead of shearing its top sheet over the
    bottom one. The frame is read from the samples (the support and the activations), not
    from the muscle's own particles, so it adds no feedback to the solve. At rest the
    targets are the rest positions.

    Args:
        system: the :class:`MuscleSystem`.
        x: ``(Nm, 3)`` muscle particles, mm.
        ids, tg: ``(P,)`` bottom particles and ``(P, 3)`` their samples, mm
            (:func:`sample_targets`).
        thick: ``(Pf,)`` thickening of every fibre sample (:func:`fibre_thickening`).
    """
    dt = x.dtype
    bottom = system.below[system.shell_top]
    base = x.at[ids].set(tg.astype(dt))
    F = _shell_frames(base, bottom, system.shell_along, system.shell_tri, system.shell_mode)
    th = _padded_thickening(thick, dt)[system.shell_sample]
    loc = system.shell_local.astype(dt)
    loc = jnp.concatenate([loc[:, :2], loc[:, 2:] * th[:, None]], axis=1)
    return base[bottom] + jnp.einsum("kij,ki->kj", F, loc)


def _padded_thickening(thick, dt):
    """``(Pf + 1,)`` fibre thickening clipped to :data:`THICKENING_RANGE`, with a trailing 1
    for the index -1 (no fibre sample)."""
    lo, hi = THICKENING_RANGE
    return jnp.concatenate([jnp.clip(thick.astype(dt), lo, hi), jnp.ones((1,), dt)])


def _active_groups(system: MuscleSystem, activations, thick, dt):
    """The fused groups with the distance rest lengths of the contracted muscle: top-sheet
    edges along a fibre shortened by ``1 - c`` (the fibre contracts, eq. 4.11, in both
    sheets) and boundary connections lengthened by the fibre's thickening."""
    groups = system.groups
    if not groups or groups[0].name != DISTANCE_GROUP:
        return groups
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    c_f = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)
    c_s = jnp.concatenate([jnp.repeat(c_f, system.h_max)[system.fib_valid], jnp.zeros((1,), dt)])
    g0 = groups[0]
    assert isinstance(g0.c, pbd.DistanceConstraints)
    r = (
        g0.c.rest.astype(dt)
        * (1.0 - c_s[system.dist_lon_sample])
        * _padded_thickening(thick, dt)[system.dist_conn_sample]
    )
    return (eqx.tree_at(lambda q: q.c.rest, g0, r),) + tuple(groups[1:])


def moved_skull_points(system: MuscleSystem, R, t):
    """``(S, 3)`` skull surface points after the jaw motion ``p' = R p + t`` on the mandible."""
    sk = system.skull_rest.astype(R.dtype)
    moved = sk @ R.T + t
    w = system.skull_jaw_weight.astype(sk.dtype)[:, None]
    return sk + w * (moved - sk)


def sample_targets(system: MuscleSystem, G, activations):
    """Targets of every bottom particle: ``(P,)`` particle ids and ``(P, 3)`` mm positions.

    Fibres: action lines evaluated on the support ``G`` and re-sampled with the contraction
    (eq. 4.11). Sphincters: the ring samples displaced toward the contraction centre
    (sec. 4.3.2).
    """
    dt = G.dtype
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    pts = _eval_support(G, system.fib_ids, system.fib_w)  # (F, m, 3)
    c = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)  # ctrl -1 -> 0
    s = _sample_var(pts, system.fib_h.astype(dt), system.h_max, c)  # (F, H, 3)
    if system.sph_ids.shape[0] == 0:
        return system.fib_bottom, s.reshape(-1, 3)[system.fib_valid]
    P = _eval_support(G, system.sph_ids, system.sph_w)  # (K, 3, n, 3)
    # modiolus: contraction displacement of the corner muscles' insertion ends, per side
    pull = s.reshape(-1, 3)[system.mod_end] - pts[system.mod_last, -1]  # (2, J, 3)
    D = jnp.einsum("sj,sjd->sd", system.mod_fw.astype(dt), pull)  # (2, 3)
    P = P + MODIOLUS_GAIN * jnp.einsum("kmns,sd->kmnd", system.mod_w.astype(dt), D)
    inner, outer = P[:, 0], P[:, 2]
    o = jnp.mean(inner, axis=1, keepdims=True)  # (K, 1, 3)
    ax = system.sph_axes.astype(dt)
    xx = jnp.einsum("knd,kd->kn", outer - o, ax[:, 0])
    yy = jnp.einsum("knd,kd->kn", outer - o, ax[:, 1])
    ab = system.sph_ab.astype(dt)
    r2 = (xx / ab[:, :1]) ** 2 + (yy / ab[:, 1:]) ** 2
    r = jnp.minimum(jnp.sqrt(jnp.maximum(r2, 1e-12)), 1.0)
    cs = acts[system.sph_ctrl] * system.sph_cmax.astype(dt)  # (K,)
    falloff = jnp.cos(0.5 * jnp.pi * (1.0 - r))  # (K, n)
    delta = cs[:, None, None] * (o - inner) * falloff[..., None]
    # protrusion: the ring also moves forward by `protrusion` times its radial motion, whose
    # length cs |o - inner| falloff is linear in the activation (smooth at rest)
    radius = jnp.sqrt(jnp.sum((o - inner) ** 2, axis=-1))  # (K, n), > 0 on a placed ring
    fwd = (system.sph_protrusion.astype(dt) * cs)[:, None] * radius * falloff  # (K, n)
    delta = delta + fwd[..., None] * system.sph_forward.astype(dt)[:, None, :]
    tg_s = (P + delta[:, None]).reshape(-1, 3)
    # the ring drags the modiolus too (its modiolus_drag): each side's corner-muscle fibres
    # move by the ring's contraction displacement at that modiolus (the mean over the ring
    # samples weighted by their modiolus weight), fully at the insertion end and fading
    # linearly to the origin
    mw = system.mod_w.astype(dt)[:, 1]  # (K, n, 2): the middle ring
    drag = system.sph_drag.astype(dt)
    dr = jnp.einsum("kns,k,knd->sd", mw, drag, delta) / jnp.maximum(
        jnp.sum(mw, axis=(0, 1))[:, None], 1e-12
    )  # (2, 3)
    dr = jnp.concatenate([dr, jnp.zeros((1, 3), dt)])  # row 2: fibres off the modiolus
    s = s + system.fib_ramp.astype(dt)[..., None] * dr[system.fib_mod_side][:, None, :]
    tg_f = s.reshape(-1, 3)[system.fib_valid]
    return (
        jnp.concatenate([system.fib_bottom, system.sph_bottom.reshape(-1)]),
        jnp.concatenate([tg_f, tg_s]),
    )


def fibre_thickening(system: MuscleSystem, G, activations):
    """``(P,)`` thickness factor of every fibre sample: rest fibre length over current
    (contracted) length, the factor that keeps a fibre's cross-section times length constant."""
    dt = G.dtype
    acts = jnp.concatenate([jnp.asarray(activations, dt), jnp.zeros((1,), dt)])
    pts = _eval_support(G, system.fib_ids, system.fib_w)
    d = pts[:, 1:] - pts[:, :-1]
    L = jnp.sum(jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12), axis=-1)
    c = acts[system.fib_ctrl] * system.fib_cmax.astype(dt)
    ratio = system.fib_len0.astype(dt) / jnp.maximum(L * (1.0 - c), 1e-6)
    H = system.h_max
    return jnp.repeat(ratio, H)[system.fib_valid]


def _sample_var(points, h, h_max: int, c):
    """:func:`jax_sample_polyline` with a per-polyline sample count ``h`` ``(F,)`` (float),
    padded to ``h_max`` samples (extra samples are clamped to the end and discarded)."""
    p = points
    d = p[..., 1:, :] - p[..., :-1, :]
    d2 = jnp.sum(d * d, axis=-1)
    ok = d2 > 1e-24
    seg = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2, 1.0)), 0.0)
    cum = jnp.concatenate([jnp.zeros_like(seg[..., :1]), jnp.cumsum(seg, axis=-1)], axis=-1)
    total = cum[..., -1:]
    i = jnp.arange(h_max, dtype=p.dtype)
    s = i * (total / (h[:, None] - 1.0)) * (1.0 - c[:, None])
    s = jnp.minimum(s, total)
    m1 = seg.shape[-1]
    j = jnp.clip(jnp.sum(cum[..., None, 1:] <= s[..., :, None], axis=-1), 0, m1 - 1)
    cj = jnp.take_along_axis(cum, j, axis=-1)
    lj = jnp.take_along_axis(seg, j, axis=-1)
    okj = lj > 0
    u = jnp.clip(jnp.where(okj, (s - cj) / jnp.where(okj, lj, 1.0), 0.0), 0.0, 1.0)[..., None]
    pj = jnp.take_along_axis(p, j[..., None], axis=-2)
    pj1 = jnp.take_along_axis(p, (j + 1)[..., None], axis=-2)
    return (1 - u) * pj + u * pj1


def muscle_sweep(system: MuscleSystem, x, skull, activations, inv_mass):
    """One sweep of the muscle solve: refresh the samples from the current support, then
    positions, shell, distances and bending (fused Jacobi) and the per-muscle volumes."""
    G = system.support(skull, x)
    ids, tg = sample_targets(system, G, activations)
    x = pbd.sweep((system.positions.set(target=tg),), x, inv_mass)
    groups = system.groups
    if system.shell_stiffness > 0:
        thick = fibre_thickening(system, G, activations)
        shell = system.shell.set(target=shell_targets(system, x, ids, tg, thick))
        groups = (shell,) + _active_groups(system, activations, thick, x.dtype)
    return pbd.sweep(groups + (system.volume,), x, inv_mass)


def warm_start(system: MuscleSystem, skull, activations):
    """Start positions close to the equilibrium, layer by layer (deepest first): bottom
    particles at their samples computed on the already-placed deeper layers, each top particle
    at its shell target (:func:`shell_targets`; without the shell: above its bottom particle
    at the rest offset scaled by the fibre's shortening, the volume-preserving thickening of
    sec. 4.1)."""
    rest = system.rest.astype(skull.dtype)
    x = rest
    below = system.below  # (Nm,) the bottom particle under each particle
    is_top = below != jnp.arange(rest.shape[0])
    off = rest - rest[below]
    for L in sorted(set(system.layers)):
        G = system.support(skull, x)
        ids, tg = sample_targets(system, G, activations)
        thick = fibre_thickening(system, G, activations)
        mine = system.particle_layer[ids] == L
        xb = x.at[ids].set(jnp.where(mine[:, None], tg, x[ids]))
        if system.shell_stiffness > 0:
            lifted = xb.at[system.shell_top].set(shell_targets(system, x, ids, tg, thick))
        else:
            scale = jnp.ones(rest.shape[0], rest.dtype).at[system.fib_bottom].set(thick)
            lifted = jnp.where(is_top[:, None], xb[below] + off * scale[below][:, None], xb)
        x = jnp.where((system.particle_layer == L)[:, None], lifted, x)
    return x


def solve_muscles(
    system: MuscleSystem, activations, R, t, *, iterations: int | None = None, x0=None
):
    """Quasi-static muscle solve for given activations and jaw motion.

    All layers are refreshed in every sweep (a layer's samples are read from the current
    positions of the deeper layers), so after ``iterations`` sweeps the configuration is the
    layered equilibrium of the thesis's deepest-first loop.

    Args:
        system: the :class:`MuscleSystem`.
        activations: ``(M,)`` in [0, 1] (the rig's control vector).
        R, t: mandible motion (:meth:`JawModel.transform`).
        iterations: sweeps (static; default ``system.iterations``).
        x0: optional warm start ``(Nm, 3)`` mm.

    Returns:
        ``(x (Nm, 3) mm, skull_moved (S, 3) mm)``.
    """
    iters = system.iterations if iterations is None else int(iterations)
    activations = jnp.asarray(activations)
    dt = jnp.result_type(activations.dtype, R.dtype)
    skull = moved_skull_points(system, R.astype(dt), t.astype(dt))
    x = warm_start(system, skull, activations.astype(dt)) if x0 is None else jnp.asarray(x0, dt)
    inv_mass = system.inv_mass.astype(dt)
    a = activations.astype(dt)
    x = pbd.iterate(
        lambda x: muscle_sweep(system, x, skull, a, inv_mass),
        x,
        iters,
        system.chebyshev_rho,
        checkpoint_every=1 if system.checkpoint else None,
    )
    return x, skull
