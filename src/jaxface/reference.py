"""Plain sequential Gauss-Seidel PBD in Python/NumPy: the thesis algorithm, for tests and speed
ratios.

This is a deliberately simple, independent implementation of thesis sec. 3.2: the constraints
are projected one at a time, in order, each correction applied immediately (non-linear
Gauss-Seidel, eqs. 3.11-3.14), with the stiffness multiplying the correction (3.18-3.19) and,
optionally, XPBD compliance. It shares no numerical code with :mod:`jaxface.pbd` /
:mod:`jaxface.constraints` (only the constraint containers, read as NumPy arrays): every
constraint function and gradient is written again here in scalar Python float64 arithmetic.

Units: positions mm, velocities mm/s, time s, inverse masses 1/g, angles rad.

Conventions shared with :mod:`jaxface.pbd` (so the two can be compared):

* groups are processed in the given order; inside a group in the user's order
  (``order="user"``) or in the solver's colour order (``order="color"``, needs a
  :class:`jaxface.pbd.System`), which makes the parallel Gauss-Seidel sweep reproducible
  exactly;
* the bending angle is the signed dihedral angle (see :func:`jaxface.constraints.dihedral_angle`)
  with the gradient of Bridson et al. 2003; anchors are projected per axis (identical to eq. 3.23
  for PBD);
* a degenerate constraint (zero length, zero area, zero-area hinge face) is skipped;
* XPBD multipliers start at zero for each :func:`solve` pass / each time step.

It is slow (about 1e6 distance projections per second): use it on small systems or for a few
iterations.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from .constraints import (
    AnchorConstraints,
    AreaConstraints,
    BendingConstraints,
    DistanceConstraints,
    HalfSpaceConstraints,
    HullConstraints,
    VolumeConstraint,
)
from .errors import MeshError

__all__ = ["solve", "jacobi", "step", "simulate", "constraint_values"]

_TINY = np.finfo(np.float64).eps ** 2


# ----------------------------------------------------------------------------------------
# turning constraint groups into per-constraint records
# ----------------------------------------------------------------------------------------


def _groups(constraints):
    """(names, groups, system or None) from a System, a mapping or a sequence of pairs."""
    from .pbd import System

    if isinstance(constraints, System):
        return list(constraints.names), list(constraints.groups), constraints
    if isinstance(constraints, Mapping):
        items = list(constraints.items())
    else:
        items = list(constraints)
    return [n for n, _ in items], [g for _, g in items], None


def _records(g, order):
    """List of (kind, data) per constraint of group ``g`` (constraints, or a
    :class:`jaxface.sweep.Group` of a System) in processing order."""
    blocks = getattr(g, "blocks", None)
    u = g.c if hasattr(g, "c") else g
    if order == "user" or isinstance(u, VolumeConstraint) or blocks is None:
        seq = range(u.size)
    else:
        seq = blocks.order().tolist()
    idx = np.asarray(u.idx).tolist()
    k = np.asarray(u.stiffness, np.float64).tolist()
    a = None if u.compliance is None else np.asarray(u.compliance, np.float64).tolist()
    recs = []
    if isinstance(u, VolumeConstraint):
        owner = np.asarray(u.owner)
        rest = np.asarray(u.rest, np.float64)
        for b in range(u.n_bodies):
            tri = np.asarray(u.idx)[owner == b].tolist()
            recs.append(
                (
                    "volume",
                    (
                        tri,
                        float(rest[b]),
                        np.asarray(u.origin, np.float64).tolist(),
                        k[b],
                        None if a is None else a[b],
                    ),
                )
            )
        return recs
    g = u
    if isinstance(g, DistanceConstraints):
        rest = np.asarray(u.rest, np.float64).tolist()
        for j in seq:
            recs.append(("distance", (idx[j], rest[j], k[j], None if a is None else a[j])))
    elif isinstance(g, BendingConstraints):
        rest = np.asarray(u.rest, np.float64).tolist()
        for j in seq:
            recs.append(("bending", (idx[j], rest[j], k[j], None if a is None else a[j])))
    elif isinstance(g, AreaConstraints):
        rest = np.asarray(u.rest, np.float64).tolist()
        for j in seq:
            recs.append(("area", (idx[j], rest[j], k[j], None if a is None else a[j])))
    elif isinstance(g, AnchorConstraints):
        t = np.asarray(u.target, np.float64).tolist()
        for j in seq:
            recs.append(("anchor", (idx[j][0], t[j], k[j], None if a is None else a[j])))
    elif isinstance(g, HalfSpaceConstraints):
        n = np.asarray(u.normal, np.float64)
        n = (n / np.linalg.norm(n, axis=1, keepdims=True)).tolist()
        d = np.asarray(u.offset, np.float64).tolist()
        for j in seq:
            recs.append(("halfspace", (idx[j][0], n[j], d[j], k[j], None if a is None else a[j])))
    elif isinstance(g, HullConstraints):
        N = np.asarray(u.normals, np.float64)
        N = (N / np.linalg.norm(N, axis=1, keepdims=True)).tolist()
        D = np.asarray(u.offsets, np.float64).tolist()
        c = np.asarray(u.clearance, np.float64).tolist()
        for j in seq:
            recs.append(("hull", (idx[j][0], N, D, c[j], k[j], None if a is None else a[j])))
    else:
        raise MeshError(f"reference solver does not know {type(g).__name__}.", problem="bad_group")
    return recs


# ----------------------------------------------------------------------------------------
# scalar geometry
# ----------------------------------------------------------------------------------------


def _sub(a, b):
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _scale(a, s):
    return [a[0] * s, a[1] * s, a[2] * s]


def _eval(kind, data, x):
    """(C, [(particle, gradient)], unilateral) of one constraint at positions ``x`` (lists)."""
    if kind == "distance":
        (i, j), d, *_ = data
        e = _sub(x[i], x[j])
        l2 = _dot(e, e)
        if l2 <= _TINY:
            return 0.0, [], False
        ln = math.sqrt(l2)
        n = _scale(e, 1.0 / ln)
        return ln - d, [(i, n), (j, _scale(n, -1.0))], False
    if kind == "area":
        (a, b, c), A0, *_ = data
        pa, pb, pc = x[a], x[b], x[c]
        n = _cross(_sub(pb, pa), _sub(pc, pa))
        n2 = _dot(n, n)
        if n2 <= _TINY:
            return 0.0, [], False
        nn = math.sqrt(n2)
        nh = _scale(n, 1.0 / nn)
        return (
            0.5 * nn - A0,
            [
                (a, _scale(_cross(nh, _sub(pc, pb)), 0.5)),
                (b, _scale(_cross(nh, _sub(pa, pc)), 0.5)),
                (c, _scale(_cross(nh, _sub(pb, pa)), 0.5)),
            ],
            False,
        )
    if kind == "bending":
        (a, b, c, d), th0, *_ = data
        pa, pb, pc, pd = x[a], x[b], x[c], x[d]
        e = _sub(pb, pa)
        n1 = _cross(e, _sub(pc, pa))
        n2 = _cross(_sub(pa, pb), _sub(pd, pb))
        L2, s1, s2 = _dot(e, e), _dot(n1, n1), _dot(n2, n2)
        if L2 <= _TINY or s1 <= _TINY * L2 or s2 <= _TINY * L2:
            return 0.0, [], False
        L = math.sqrt(L2)
        theta = math.atan2(_dot(_cross(n1, n2), e), L * _dot(n1, n2))
        dth = theta - th0
        C = math.atan2(math.sin(dth), math.cos(dth))
        q1, q2 = _scale(n1, 1.0 / s1), _scale(n2, 1.0 / s2)
        # d theta / d p for the hinge (a, b), wings c, d
        gc = _scale(q1, -L)
        gd = _scale(q2, -L)
        ca = _dot(_sub(pc, pb), e) / L
        da = _dot(_sub(pd, pb), e) / L
        cb = _dot(_sub(pc, pa), e) / L
        db = _dot(_sub(pd, pa), e) / L
        ga = [-(ca * q1[r] + da * q2[r]) for r in range(3)]
        gb = [cb * q1[r] + db * q2[r] for r in range(3)]
        return C, [(a, ga), (b, gb), (c, gc), (d, gd)], False
    if kind == "anchor":
        raise AssertionError("anchors are projected per axis")
    if kind == "halfspace":
        i, n, d, *_ = data
        return _dot(n, x[i]) - d, [(i, list(n))], True
    if kind == "hull":
        i, N, D, clear, *_ = data
        p = x[i]
        best, h = -math.inf, 0
        for r, (nr, dr) in enumerate(zip(N, D)):
            sd = _dot(nr, p) - dr
            if sd > best:
                best, h = sd, r
        return best - clear, [(i, list(N[h]))], True
    if kind == "volume":
        tri, V0, o, *_ = data
        V = 0.0
        grads: dict[int, list[float]] = {}
        for a, b, c in tri:
            pa, pb, pc = _sub(x[a], o), _sub(x[b], o), _sub(x[c], o)
            ab = _cross(pa, pb)
            V += _dot(ab, pc) / 6.0
            for p, g in ((a, _cross(pb, pc)), (b, _cross(pc, pa)), (c, ab)):
                acc = grads.setdefault(p, [0.0, 0.0, 0.0])
                acc[0] += g[0] / 6.0
                acc[1] += g[1] / 6.0
                acc[2] += g[2] / 6.0
        return V - V0, list(grads.items()), False
    raise AssertionError(kind)


def _project(kind, data, x, w, lam, j, alpha_scale):
    """Project one constraint in place (positions ``x`` list of lists)."""
    k, alpha = data[-2], data[-1]
    if kind == "distance":  # eqs. 3.15-3.19, written out (the bulk of every system)
        (i, j2), d = data[0], data[1]
        pi, pj = x[i], x[j2]
        ex, ey, ez = pi[0] - pj[0], pi[1] - pj[1], pi[2] - pj[2]
        l2 = ex * ex + ey * ey + ez * ez
        if l2 <= _TINY:
            return
        ln = math.sqrt(l2)
        wi, wj = w[i], w[j2]
        C = ln - d
        if alpha is None:
            den = wi + wj
            if den <= 0:
                return
            dl = -k * C / den
        else:
            at = alpha * alpha_scale
            den = wi + wj + at
            if den <= 0:
                return
            dl = k * (-C - at * lam[j]) / den
            lam[j] += dl
        s = dl / ln
        si, sj = wi * s, wj * s
        pi[0] += si * ex
        pi[1] += si * ey
        pi[2] += si * ez
        pj[0] -= sj * ex
        pj[1] -= sj * ey
        pj[2] -= sj * ez
        return
    if kind == "anchor":
        i, t = data[0], data[1]
        wi = w[i]
        for r in range(3):
            C = x[i][r] - t[r]
            if alpha is None:
                if wi > 0:
                    x[i][r] -= k * C
            else:
                at = alpha * alpha_scale
                den = wi + at
                if den > 0:
                    dl = k * (-C - at * lam[j][r]) / den
                    lam[j][r] += dl
                    x[i][r] += wi * dl
        return
    C, grads, unilateral = _eval(kind, data, x)
    if not grads:
        return
    denom = 0.0
    for p, g in grads:
        denom += w[p] * _dot(g, g)
    if alpha is None:
        if unilateral and C >= 0:
            return
        if denom <= 0:
            return
        dl = -k * C / denom
    else:
        at = alpha * alpha_scale
        den = denom + at
        if den <= 0:
            return
        dl = k * (-C - at * lam[j]) / den
        if unilateral:
            dl = max(lam[j] + dl, 0.0) - lam[j]
        lam[j] += dl
    for p, g in grads:
        s = w[p] * dl
        xp = x[p]
        xp[0] += s * g[0]
        xp[1] += s * g[1]
        xp[2] += s * g[2]


def _prepare(constraints, order):
    names, groups, system = _groups(constraints)
    if order not in ("user", "color"):
        raise MeshError(f"order must be 'user' or 'color', got {order!r}.", problem="bad_option")
    if order == "color" and system is None:
        raise MeshError(
            "order='color' needs a jaxface.pbd.System (built with build_system).",
            problem="bad_option",
        )
    return [_records(g, order) for g in groups], system


def _sweeps(recs, x, w, iterations, alpha_scale):
    lams = [[[0.0, 0.0, 0.0] if kind == "anchor" else 0.0 for kind, _ in r] for r in recs]
    for _ in range(iterations):
        for r, lam in zip(recs, lams):
            for j, (kind, data) in enumerate(r):
                _project(kind, data, x, w, lam, j, alpha_scale)


def _inv_mass(constraints, inv_mass, n):
    if inv_mass is None:
        from .pbd import System

        if isinstance(constraints, System):
            return np.asarray(constraints.inv_mass, np.float64).tolist()
        return [1.0] * n
    w = np.asarray(inv_mass, np.float64)
    if w.shape != (n,):
        raise MeshError(f"inv_mass must have shape ({n},), got {w.shape}.", problem="shape")
    return w.tolist()


def solve(
    constraints,
    x,
    *,
    iterations: int,
    inv_mass=None,
    order: str = "user",
    passes: int = 1,
    dt: float = 0.0166,
) -> np.ndarray:
    """Sequential Gauss-Seidel projection (thesis loop lines 8-10), quasi-static.

    Args:
        constraints: a :class:`jaxface.pbd.System`, or a mapping / sequence of
            ``(name, group)``.
        x: ``(N, 3)`` mm start positions.
        iterations: sweeps per pass.
        inv_mass: ``(N,)`` 1/g (default: the system's, or ones).
        order: ``"user"`` (constraints in the order given) or ``"color"`` (the parallel
            solver's colour order; needs a System).
        passes: XPBD multipliers are reset at the start of every pass (as in
            :func:`jaxface.pbd.relax`).
        dt: s, time step of the XPBD compliance scaling ``alpha / dt^2``.

    Returns:
        ``(N, 3)`` float64 mm.
    """
    recs, _ = _prepare(constraints, order)
    xa = np.array(x, dtype=np.float64)
    w = _inv_mass(constraints, inv_mass, xa.shape[0])
    xl = xa.tolist()
    for _ in range(passes):
        _sweeps(recs, xl, w, iterations, 1.0 / (dt * dt))
    return np.asarray(xl)


def jacobi(system, x, *, iterations: int) -> np.ndarray:
    """Sequential oracle of the engine's fused Jacobi scheme (``scheme="jacobi"``), plain PBD.

    Per sweep, group after group (in order): every constraint of the group is projected alone
    from the same positions (with the scalar formulas of this module), the corrections are
    summed per particle, divided by the number of the group's constraint corners on the
    particle and scaled by the group's ``omega``; volume groups are projected directly.

    Args:
        system: a :class:`jaxface.pbd.System` (no XPBD compliance).
        x: ``(N, 3)`` mm start positions.
        iterations: sweeps.

    Returns:
        ``(N, 3)`` float64 mm.

    Raises:
        MeshError: a group with XPBD compliance, or not a System.
    """
    names, groups, sysm = _groups(system)
    if sysm is None:
        raise MeshError("jacobi needs a jaxface.pbd.System.", problem="bad_option")
    xl = np.array(x, dtype=np.float64).tolist()
    w = _inv_mass(system, None, len(xl))
    recs = [_records(g, "user") for g in groups]
    for name, g in zip(names, groups):
        if g.c.compliance is not None:
            raise MeshError(f"jacobi: group {name!r} has XPBD compliance.", problem="bad_option")
    for _ in range(iterations):
        for g, r in zip(groups, recs):
            if isinstance(g.c, VolumeConstraint):
                for kind, data in r:
                    _project(kind, data, xl, w, None, 0, 1.0)
                continue
            acc: dict[int, list[float]] = {}
            cnt: dict[int, int] = {}
            for kind, data in r:
                ids = [data[0]] if isinstance(data[0], int) else list(data[0])
                for p in ids:
                    cnt[p] = cnt.get(p, 0) + 1
                saved = {p: list(xl[p]) for p in ids}
                _project(kind, data, xl, w, None, 0, 1.0)
                for p, old in saved.items():
                    a = acc.setdefault(p, [0.0, 0.0, 0.0])
                    for r3 in range(3):
                        a[r3] += xl[p][r3] - old[r3]
                    xl[p] = old
            for p, a in acc.items():
                s = g.omega / cnt[p]
                xl[p] = [xl[p][r3] + s * a[r3] for r3 in range(3)]
    return np.asarray(xl)


def step(
    constraints,
    x,
    v,
    *,
    iterations: int,
    inv_mass=None,
    dt: float = 0.0166,
    damping: float = 0.2,
    gravity=None,
    order: str = "user",
):
    """One time step of the thesis loop (lines 5-14) with linear damping ``v *= 1 - damping``
    (dynamic particles only) applied before gravity, as in :func:`jaxface.pbd.step`.

    Args:
        x: ``(N, 3)`` mm; v: ``(N, 3)`` mm/s; gravity: ``(3,)`` mm/s^2 or ``None``.

    Returns:
        ``(x', v')`` float64 arrays, mm and mm/s.
    """
    recs, _ = _prepare(constraints, order)
    xa = np.array(x, dtype=np.float64)
    va = np.array(v, dtype=np.float64)
    w = np.asarray(_inv_mass(constraints, inv_mass, xa.shape[0]))
    dyn = w > 0
    va[dyn] *= 1.0 - damping
    if gravity is not None:
        va[dyn] += dt * np.asarray(gravity, np.float64)
    p = (xa + dt * va).tolist()
    _sweeps(recs, p, w.tolist(), iterations, 1.0 / (dt * dt))
    p = np.asarray(p)
    return p, (p - xa) / dt


def simulate(constraints, x, v, *, steps: int, iterations: int, **kwargs):
    """``steps`` calls of :func:`step`; returns the final ``(x, v)``."""
    for _ in range(steps):
        x, v = step(constraints, x, v, iterations=iterations, **kwargs)
    return x, v


def constraint_values(group, x) -> np.ndarray:
    """Constraint values of a group at ``x`` ``(N, 3)`` mm in the user's order, computed with
    the scalar formulas of this module (``|p - t|`` for anchors)."""
    xl = np.asarray(x, np.float64).tolist()
    out = []
    for kind, data in _records(group, "user"):
        if kind == "anchor":
            i, t = data[0], data[1]
            out.append(math.sqrt(sum((xl[i][r] - t[r]) ** 2 for r in range(3))))
        else:
            out.append(_eval(kind, data, xl)[0])
    return np.asarray(out)
