"""The ring/column grid of the default head: ring elevations and column spacing, the zipper
triangulation between rings, and the eye and mouth slits (:func:`_build_grid`; mm).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .base import (
    _CANTHUS_IN,
    _CANTHUS_OUT,
    _MOUTH_CORNER,
    _MOUTH_GAP,
    _MOUTH_MID_Y,
    _NECK_Y,
    RAY_ORIGIN,
    _base_normals,
    _base_points,
    _smoothstep,
)
from .relief import _lid_margin_curves, _mouth_line, _relax_front, _skin_from_base

# ----------------------------------------------------------------------------- grid
_ROW_FACE = 2.9  # mm between rings on the face band (front meridian)
_ROW_FINE = 1.7  # mm between rings at the eye and mouth slits
_ROW_OTHER = 5.5  # mm between rings on the scalp and the neck (front meridian)
_COL_FACE = 2.8  # mm between columns on the face
_COL_SIDE = 4.5
_COL_BACK = 7.0
_FACE_Y = (-84.0, 92.0)  # height band (mm) of the face on the front meridian


def _row_spacing(y):
    """Ring spacing (mm) along the front meridian at height y (mm)."""
    lo, hi = _FACE_Y
    face = _smoothstep(lo - 10.0, lo, y) * _smoothstep(hi + 10.0, hi, y)
    h = _ROW_OTHER + (_ROW_FACE - _ROW_OTHER) * face
    fine = np.maximum(
        np.exp(-0.5 * ((y - 0.5 * (_CANTHUS_IN[1] + _CANTHUS_OUT[1])) / 4.5) ** 2),
        np.exp(-0.5 * ((y - _MOUTH_MID_Y) / 4.0) ** 2),
    )
    fine = np.maximum(fine, np.exp(-0.5 * ((y + 9.5) / 3.5) ** 2))  # nose base
    return h + (_ROW_FINE - h) * fine


def _col_spacing(theta, y):
    """Column spacing (mm) at azimuth theta on a ring through front height y (mm)."""
    a = np.abs(theta)
    h = np.where(
        a < 0.75,
        _COL_FACE,
        np.where(
            a < 1.6,
            _COL_FACE + (_COL_SIDE - _COL_FACE) * _smoothstep(0.75, 1.6, a),
            _COL_SIDE + (_COL_BACK - _COL_SIDE) * _smoothstep(1.6, 2.4, a),
        ),
    )
    lo, hi = _FACE_Y
    face = _smoothstep(lo - 12.0, lo, y) * _smoothstep(hi + 15.0, hi, y)
    h = face * h + (1.0 - face) * np.maximum(h, 4.2)
    # the ears (|theta| ~ 1.62 rad, -28 < y < 42 mm) get face-like spacing
    ear = (
        np.exp(-0.5 * ((a - 1.62) / 0.17) ** 2)
        * _smoothstep(-40.0, -28.0, y)
        * _smoothstep(52.0, 40.0, y)
    )
    return h + (2.7 - h) * np.clip(ear, 0.0, 1.0) * (h > 2.7)


_MERIDIANS = np.linspace(0.0, np.pi, 13)


def _ring_elevations() -> np.ndarray:
    """Ring elevations (radians), ``(n_rings, len(_MERIDIANS))``: ring k on the meridians
    theta = _MERIDIANS.

    On every meridian the rings are spaced along the base head in proportion to
    :func:`_row_spacing` of the height (dense on the face band, densest at the eye and mouth
    slits), from the neck cut y = _NECK_Y to about 0.8 ring from the vertex; the number of
    rings is set by the front meridian. Rings are therefore nearly horizontal."""
    phis = np.linspace(np.deg2rad(-80.0), np.deg2rad(89.95), 1500)
    TH, PH = np.meshgrid(_MERIDIANS, phis, indexing="ij")
    p = _base_points(TH, PH)  # (M, S, 3)
    top = _base_points(np.zeros(1), np.full(1, np.pi / 2))[0]
    ds = np.linalg.norm(np.diff(p, axis=1), axis=2)
    ym = 0.5 * (p[:, 1:, 1] + p[:, :-1, 1])
    # the face spacing on the front meridians, even spacing at the back
    f = _smoothstep(2.4, 1.2, _MERIDIANS)[:, None]
    h = f * _row_spacing(ym) + (1.0 - f) * _ROW_FACE
    steps = np.concatenate([np.zeros((len(_MERIDIANS), 1)), np.cumsum(ds / h, axis=1)], axis=1)
    d_top = np.linalg.norm(p - top, axis=2)
    out = []
    n = None
    for j in range(len(_MERIDIANS)):
        s0 = np.interp(_NECK_Y, p[j, :, 1], steps[j])  # y grows with phi on a meridian
        s1 = np.interp(0.8 * _ROW_OTHER, d_top[j, ::-1], steps[j, ::-1])
        if n is None:
            n = int(round(s1 - s0))
        out.append(np.interp(np.linspace(s0, s1, n + 1), steps[j], phis))
    return np.stack(out, axis=1)


def _ring_phi(ring_tab: np.ndarray, theta):
    """Elevation of a ring (row of :func:`_ring_elevations`) at azimuths theta."""
    return np.interp(np.abs(np.asarray(theta, dtype=np.float64)), _MERIDIANS, ring_tab)


def _ring_thetas(rows: np.ndarray) -> list[np.ndarray]:
    """Column azimuths of each ring, symmetric (0 and pi included), ascending in [-pi, pi),
    spaced by :func:`_col_spacing` along the base head."""
    th = np.linspace(0.0, np.pi, 241)
    PH = np.stack([_ring_phi(r, th) for r in rows])
    TH = np.broadcast_to(th, PH.shape)
    p = _base_points(TH, PH)
    y_front = p[:, :1, 1]
    ds = np.linalg.norm(np.diff(p, axis=1), axis=2)
    mid = 0.5 * (TH[:, 1:] + TH[:, :-1])
    steps = np.concatenate(
        [np.zeros((len(rows), 1)), np.cumsum(ds / _col_spacing(mid, y_front), axis=1)], axis=1
    )
    out = []
    for k in range(len(rows)):
        m = max(int(round(steps[k, -1])), 3)
        half = np.interp(np.linspace(0.0, steps[k, -1], m + 1), steps[k], th)
        half[0], half[-1] = 0.0, np.pi
        full = np.concatenate([half, -half[1:-1]])
        full = np.where(full >= np.pi, -np.pi, full)
        out.append(np.sort(full))
    return out


def _zip_half(a_ids, a_th, b_ids, b_th):
    """Triangles between half rings A (below) and B (above), both running from theta = 0 to
    theta = pi (ascending), counter-clockwise from outside."""
    ev = np.concatenate([a_th[1:], b_th[1:] + 1e-12])
    kind = np.concatenate(
        [np.zeros(len(a_th) - 1, dtype=np.int64), np.ones(len(b_th) - 1, dtype=np.int64)]
    )
    kind = kind[np.argsort(ev, kind="stable")]
    i = np.cumsum(kind == 0) - (kind == 0)
    j = np.cumsum(kind == 1) - (kind == 1)
    return np.where(
        (kind == 0)[:, None],
        np.stack([a_ids[i], a_ids[np.minimum(i + 1, len(a_ids) - 1)], b_ids[j]], axis=1),
        np.stack([a_ids[i], b_ids[np.minimum(j + 1, len(b_ids) - 1)], b_ids[j]], axis=1),
    )


def _solve_phi_for_y(theta, y_target, phi0, fn, half_width=0.25, iters=12):
    """Elevation phi near phi0 such that fn(theta, phi)[:, 1] == y_target (secant steps,
    safeguarded to [phi0 - half_width, phi0 + half_width])."""
    phi0 = np.asarray(phi0, dtype=np.float64)
    lo, hi = phi0 - half_width, phi0 + half_width
    a = phi0
    b = phi0 + 0.01
    fa = fn(theta, a)[:, 1] - y_target
    fb = fn(theta, b)[:, 1] - y_target
    for _ in range(iters):
        den = np.where(np.abs(fb - fa) < 1e-14, 1e-14, fb - fa)
        c = np.clip(b - fb * (b - a) / den, lo, hi)
        a, fa = b, fb
        b = c
        fb = fn(theta, b)[:, 1] - y_target
        if np.max(np.abs(fb)) < 1e-9:
            break
    return b


def _solve_param_for_xy(x, y, iters=40):
    """Ray parameters (theta, phi) of the base point with the given front (x, y) (mm)."""
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    th = np.arcsin(np.clip(x / 110.0, -1, 1))
    ph = np.arctan2(y - RAY_ORIGIN[1], 100.0)
    for _ in range(iters):
        p = _base_points(th, ph)
        e = 1e-5
        px = _base_points(th + e, ph)
        py = _base_points(th, ph + e)
        J = np.stack(
            [
                [(px[:, 0] - p[:, 0]) / e, (py[:, 0] - p[:, 0]) / e],
                [(px[:, 1] - p[:, 1]) / e, (py[:, 1] - p[:, 1]) / e],
            ]
        )  # (2, 2, N)
        rx, ry = x - p[:, 0], y - p[:, 1]
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        dth = (J[1, 1] * rx - J[0, 1] * ry) / det
        dph = (-J[1, 0] * rx + J[0, 0] * ry) / det
        th, ph = th + dth, ph + dph
        if np.max(np.abs(rx) + np.abs(ry)) < 1e-6:
            break
    return th, ph


def _snap_ring(thetas: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move the columns nearest to ``anchors`` exactly onto them (piecewise-linear remap).

    Returns the new sorted thetas and the column index of each anchor."""
    idx = np.array([int(np.argmin(np.abs(thetas - a))) for a in anchors])
    src = np.concatenate([[-np.pi], thetas[idx], [np.pi]])
    dst = np.concatenate([[-np.pi], anchors, [np.pi]])
    order = np.argsort(src)
    new = np.interp(thetas, src[order], dst[order])
    if np.any(np.diff(new) <= 0):
        raise RuntimeError("internal error: snapping the slit corners broke the column order")
    return new, idx


@dataclasses.dataclass
class _Slit:
    name: str
    ring: int
    theta_a: float  # corner azimuths (a < b)
    theta_b: float
    line: object  # x -> y of the slit line (mm)
    upper: object  # x -> y of the upper edge
    lower: object  # x -> y of the lower edge
    bend_width: float  # decay of the bend with elevation (radians)
    open_width_up: float  # decay of the opening with elevation (radians)
    open_width_lo: float
    # filled by the builder
    cols: np.ndarray | None = None  # column ids (in the ring) strictly inside
    theta_knots: np.ndarray | None = None
    bend: np.ndarray | None = None
    a_up: np.ndarray | None = None
    a_lo: np.ndarray | None = None


def _phi_on_curve(theta, curve, phi0):
    """Elevations phi such that the base point (theta, phi) lies on y = curve(x) (mm)."""
    phi = np.asarray(phi0, dtype=np.float64).copy()
    for _ in range(4):
        x = _base_points(theta, phi)[:, 0]
        phi = _solve_phi_for_y(theta, curve(x), phi, _base_points, half_width=0.2)
    return phi


def _prepare_slit(s: _Slit, thetas: np.ndarray, ring_phi) -> None:
    inside = (thetas > s.theta_a + 1e-12) & (thetas < s.theta_b - 1e-12)
    s.cols = np.nonzero(inside)[0]
    knots = np.concatenate([[s.theta_a], thetas[s.cols], [s.theta_b]])
    s.theta_knots = knots
    phi0 = ring_phi(knots)
    ph_line = _phi_on_curve(knots, s.line, phi0)
    ph_up = _phi_on_curve(knots, s.upper, ph_line)
    ph_lo = _phi_on_curve(knots, s.lower, ph_line)
    s.bend = ph_line - phi0
    s.a_up = np.clip(ph_up - ph_line, 0.0, None)
    s.a_lo = np.clip(ph_line - ph_lo, 0.0, None)
    s.a_up[[0, -1]] = 0.0
    s.a_lo[[0, -1]] = 0.0


def _slit_warp(s: _Slit, theta, dphi, side):
    """Elevation change (radians) of vertices at azimuth theta, elevation offset ``dphi`` from
    the slit ring, on ``side`` (+1 above / upper edge, -1 below / lower edge)."""
    span = s.theta_b - s.theta_a
    k = s.theta_knots
    assert k is not None and s.bend is not None and s.a_up is not None and s.a_lo is not None
    inside = (theta >= k[0]) & (theta <= k[-1])
    bend_in = np.interp(theta, k, s.bend)
    # outside the slit the bend fades out over half a slit length
    fade = np.where(
        theta < k[0],
        _smoothstep(k[0] - 0.5 * span, k[0], theta),
        _smoothstep(k[-1] + 0.5 * span, k[-1], theta),
    )
    bend_out = np.where(theta < k[0], s.bend[0], s.bend[-1]) * fade
    bend = np.where(inside, bend_in, bend_out)
    a_up = np.where(inside, np.interp(theta, k, s.a_up), 0.0)
    a_lo = np.where(inside, np.interp(theta, k, s.a_lo), 0.0)
    g_b = np.exp(-((dphi / s.bend_width) ** 2))
    opening = np.where(
        side > 0,
        a_up * np.exp(-((dphi / s.open_width_up) ** 2)),
        -a_lo * np.exp(-((dphi / s.open_width_lo) ** 2)),
    )
    return bend * g_b + opening


@dataclasses.dataclass
class _Grid:
    vertices: np.ndarray
    triangles: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    ring: np.ndarray  # ring index per vertex (-1 for the vertex at the top)
    upper_copy: np.ndarray  # bool: vertex is the upper copy of a slit column
    slits: dict
    n_rings: int
    mirror: np.ndarray  # mirror vertex id (x -> -x)


def _eye_curves(sx: float):
    """(line, upper, lower) curves x -> y (mm) for the eye on side sx (+1 left, -1 right)."""

    def line(x):
        return _lid_margin_curves(sx * x)[0]

    def upper(x):
        return _lid_margin_curves(sx * x)[1]

    def lower(x):
        return _lid_margin_curves(sx * x)[2]

    return line, upper, lower


def _mouth_curves():
    xc = _MOUTH_CORNER[0]

    def shape(x):
        return np.clip(1.0 - (np.asarray(x) / xc) ** 2, 0.0, 1.0) ** 0.8

    def upper(x):
        return _mouth_line(np.clip(x, -xc, xc)) + 0.5 * _MOUTH_GAP * shape(x)

    def lower(x):
        return _mouth_line(np.clip(x, -xc, xc)) - 0.5 * _MOUTH_GAP * shape(x)

    return (lambda x: _mouth_line(np.clip(x, -xc, xc))), upper, lower


def _build_grid() -> _Grid:
    rows = _ring_elevations()
    n_rings = len(rows)
    rings = _ring_thetas(rows)

    # slit corners in ray parameters
    cx = np.array([_CANTHUS_IN[0], _CANTHUS_OUT[0], _MOUTH_CORNER[0], 0.0])
    cy = np.array([_CANTHUS_IN[1], _CANTHUS_OUT[1], _MOUTH_CORNER[1], _MOUTH_MID_Y])
    th_c, ph_c = _solve_param_for_xy(cx, cy)

    def ring_at(k, th):
        k = np.asarray(k)
        th = np.abs(np.asarray(th, dtype=np.float64))
        if k.ndim == 0:
            return _ring_phi(rows[int(k)], th)
        # per-vertex ring ids: interpolate each vertex on its own ring
        j = np.clip(np.searchsorted(_MERIDIANS, th) - 1, 0, len(_MERIDIANS) - 2)
        t = (th - _MERIDIANS[j]) / (_MERIDIANS[j + 1] - _MERIDIANS[j])
        return (1 - t) * rows[k, j] + t * rows[k, j + 1]

    k_eye = int(
        np.argmin(
            np.abs(
                ring_at(np.arange(n_rings), np.full(n_rings, 0.5 * (th_c[0] + th_c[1])))
                - 0.5 * (ph_c[0] + ph_c[1])
            )
        )
    )
    k_mouth = int(
        np.argmin(
            np.abs(ring_at(np.arange(n_rings), np.zeros(n_rings)) - 0.5 * (ph_c[2] + ph_c[3]))
        )
    )
    rings[k_eye], _ = _snap_ring(rings[k_eye], np.array([-th_c[1], -th_c[0], th_c[0], th_c[1]]))
    rings[k_mouth], _ = _snap_ring(rings[k_mouth], np.array([-th_c[2], 0.0, th_c[2]]))

    row = _ROW_FINE / 100.0  # ~ one ring at the slits, radians
    slits = {}
    for name, sx in (("eye_left", 1.0), ("eye_right", -1.0)):
        line, up, lo = _eye_curves(sx)
        a, b = sorted((sx * th_c[0], sx * th_c[1]))
        slits[name] = _Slit(
            name,
            k_eye,
            a,
            b,
            line,
            up,
            lo,
            bend_width=3.0 * row,
            open_width_up=6.5 * row,
            open_width_lo=4.5 * row,
        )
    line, up, lo = _mouth_curves()
    slits["mouth"] = _Slit(
        "mouth",
        k_mouth,
        -th_c[2],
        th_c[2],
        line,
        up,
        lo,
        bend_width=3.0 * row,
        open_width_up=1.0 * row,
        open_width_lo=1.0 * row,
    )
    for s in slits.values():
        _prepare_slit(s, rings[s.ring], lambda th, k=s.ring: ring_at(k, th))

    # vertex ids: ring by ring; slit columns get an extra upper copy
    theta_l, ring_l, upper_l = [], [], []
    ids_lo, ids_up = [], []
    nxt = 0
    for k, th in enumerate(rings):
        n = len(th)
        base = np.arange(nxt, nxt + n)
        nxt += n
        theta_l.append(th)
        ring_l.append(np.full(n, k))
        upper_l.append(np.zeros(n, dtype=bool))
        up = base.copy()
        for s in slits.values():
            if s.ring != k:
                continue
            m = len(s.cols)
            copies = np.arange(nxt, nxt + m)
            nxt += m
            up[s.cols] = copies
            theta_l.append(th[s.cols])
            ring_l.append(np.full(m, k))
            upper_l.append(np.ones(m, dtype=bool))
        ids_lo.append(base)
        ids_up.append(up)
    pole = nxt
    theta = np.concatenate(theta_l + [np.zeros(1)])
    ring = np.concatenate(ring_l + [np.full(1, -1)])
    upper_copy = np.concatenate(upper_l + [np.zeros(1, dtype=bool)])
    phi = np.where(ring >= 0, ring_at(np.maximum(ring, 0), theta), np.pi / 2)

    # triangulate the left half (0 <= theta <= pi) and mirror it: the mesh is symmetric
    mirror = np.arange(pole + 1)
    halves = []
    for k, th in enumerate(rings):
        n = len(th)
        mi = (n - np.arange(n)) % n  # index of -theta in the sorted ring
        if not np.allclose(th[mi], np.where(th == -np.pi, -np.pi, -th), atol=1e-9):
            raise RuntimeError("internal error: a ring of the head is not mirror symmetric")
        mirror[ids_lo[k]] = ids_lo[k][mi]
        mirror[ids_up[k]] = ids_up[k][mi]
        half = np.concatenate([np.nonzero(th >= 0.0)[0], [0]])  # 0 .. pi (index 0 is -pi)
        halves.append((half, np.concatenate([th[half[:-1]], [np.pi]])))
    tris = []
    for k in range(n_rings - 1):
        (ha, ta), (hb, tb) = halves[k], halves[k + 1]
        tris.append(_zip_half(ids_up[k][ha], ta, ids_lo[k + 1][hb], tb))
    ht, _ = halves[-1]
    top = ids_up[-1][ht]
    tris.append(np.stack([top[:-1], top[1:], np.full(len(top) - 1, pole)], axis=1))
    left = np.concatenate(tris)
    tris = [left, mirror[left][:, ::-1]]
    triangles = np.concatenate(tris).astype(np.int64)

    # ---- warps of the elevations
    phi_w = phi.copy()
    for s in slits.values():
        dphi = phi - ring_at(s.ring, theta)
        side = np.where(ring == s.ring, np.where(upper_copy, 1, -1), np.sign(dphi))
        near = (np.abs(dphi) < 0.5) & (ring >= 0)
        phi_w[near] += _slit_warp(s, theta[near], dphi[near], side[near])
    # neck: the lowest ring lies exactly on the horizontal cut y = _NECK_Y
    bottom = ring == 0
    phi_w[bottom] = _solve_phi_for_y(
        theta[bottom], _NECK_Y, phi[bottom], _base_points, half_width=0.3
    )
    p0 = _base_points(theta, phi_w)
    vertices = _skin_from_base(p0)
    vertices[pole] = _base_points(np.zeros(1), np.full(1, np.pi / 2))[0]
    # even out the triangles on the steep parts of the face (nose, lip roll, lids)
    fixed = np.zeros(len(theta), dtype=bool)
    for s in slits.values():
        on = (ring == s.ring) & (theta >= s.theta_a - 1e-12) & (theta <= s.theta_b + 1e-12)
        fixed |= on
    fixed[pole] = True
    fixed[ring == 0] = True
    n0 = _base_normals(p0)
    movable = (
        _smoothstep(0.55, 0.8, n0[:, 2])
        * (p0[:, 2] > 30.0)
        * ~fixed
        * _smoothstep(-100.0, -90.0, p0[:, 1])
    )
    vertices = _relax_front(vertices, triangles, movable)
    return _Grid(vertices, triangles, theta, phi_w, ring, upper_copy, slits, n_rings, mirror)
