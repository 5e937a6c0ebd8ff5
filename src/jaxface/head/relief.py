"""Relief of the default head: displacement fields on the face (brow, eye sockets and lids,
cheeks, nose, lips, chin) and the ears, the skin surface from the base head, and the tangential
relaxation on the face (all in mm).
"""

from __future__ import annotations

import numpy as np

from .base import (
    _CANTHUS_IN,
    _CANTHUS_OUT,
    _DOME_TOP,
    _DOME_Y0,
    _EYE_CENTER,
    _LID_LO,
    _LID_SHELL,
    _LID_UP,
    _MOUTH_CORNER,
    _MOUTH_MID_Y,
    _NF_TAB,
    _PROFILE_TAB,
    _PROFILE_Y,
    _Y_TAB,
    EYE_RADIUS,
    _base_normals,
    _bump,
    _cranium,
    _gauss,
    _smax,
    _smoothstep,
)


# ----------------------------------------------------------------------------- relief
def _lid_margin_curves(x):
    """Canthal line, upper and lower lid margin heights (mm) at |x| (left eye coordinates)."""
    a, b = _CANTHUS_IN, _CANTHUS_OUT
    s = np.clip((x - a[0]) / (b[0] - a[0]), 0.0, 1.0)
    line = a[1] + s * (b[1] - a[1])
    up = line + _LID_UP * _skew_bump(s, 0.42)
    lo = line - _LID_LO * _skew_bump(s, 0.56)
    return line, up, lo


def _skew_bump(s, peak, order: float = 1.7):
    """0 at s = 0 and 1, 1 at ``peak``: s^a (1-s)^b normalised, a/(a+b) = peak."""
    a = order * peak
    b = order * (1.0 - peak)
    s = np.clip(s, 0.0, 1.0)
    return (s**a) * ((1.0 - s) ** b) / (peak**a * (1.0 - peak) ** b)


def _mouth_line(x):
    """Slit height (mm) of the closed mouth at x (both sides)."""
    return _MOUTH_MID_Y + (_MOUTH_CORNER[1] - _MOUTH_MID_Y) * (x / _MOUTH_CORNER[0]) ** 2


def _brow_line(ax):
    """Height (mm) of the eyebrow arch at |x| (through the inner, middle, outer brow points)."""
    return 51.3 + 0.833 * ax - 0.0141 * ax * ax


def _relief_z(x, y):
    """Forward (+z) displacement of the face (mm) at base points (x, y), without the nose and
    the eyelid shells."""
    ax = np.abs(x)
    d = np.zeros_like(x)

    # ---- forehead and brow ridge (the ridge lies just below the eyebrow arch)
    ridge = np.exp(-0.5 * ((y - (_brow_line(np.maximum(ax, 14.0)) - 4.0)) / 5.5) ** 2)
    d += 1.8 * ridge * _smoothstep(64.0, 50.0, ax)
    d += 0.6 * _gauss(ax, y, 0.0, 47.0, 10.0, 6.0)  # glabella
    d -= 0.5 * _gauss(ax, y, 0.0, 38.5, 7.0, 3.0)  # nasion

    # ---- eye sockets (the lid shells are added afterwards with a smooth max)
    d -= 10.0 * _gauss(ax, y, 30.0, 34.0, 12.0, 7.5)
    d -= 3.5 * _gauss(ax, y, 18.0, 32.5, 4.5, 4.0)  # medial canthus
    d += 1.2 * _gauss(ax, y, 34.0, 21.0, 13.0, 3.5)  # infra-orbital rim
    crease_y = _lid_margin_curves(np.clip(ax, _CANTHUS_IN[0], _CANTHUS_OUT[0]))[1] + 6.5
    on = _smoothstep(_CANTHUS_IN[0] - 2.0, _CANTHUS_IN[0] + 4.0, ax) * _smoothstep(
        _CANTHUS_OUT[0] + 4.0, _CANTHUS_OUT[0] - 2.0, ax
    )
    d -= 1.2 * on * np.exp(-0.5 * ((y - crease_y) / 1.3) ** 2)  # upper lid crease

    # ---- cheeks
    d += 3.0 * _gauss(ax, y, 48.0, 15.0, 11.0, 9.0)  # cheekbone
    d += 2.8 * _gauss(ax, y, 33.0, 4.0, 11.0, 10.0)  # malar fat
    d -= 1.0 * _gauss(ax, y, 53.0, -20.0, 9.0, 11.0)  # buccal hollow

    # ---- mouth: the muzzle over the dental arch, then lips, philtrum and folds
    d += 8.3 * np.exp(-((ax / 27.0) ** 2.6) - ((y + 28.5) / 16.5) ** 6)
    d += _lips(ax, y)
    t = np.clip((y + 1.0) / (-38.0 + 1.0), 0.0, 1.0)  # nasolabial fold
    fold_x = 22.0 + 9.5 * t + 2.0 * np.sin(np.pi * t)
    fold_on = _smoothstep(3.0, -5.0, y) * _smoothstep(-46.0, -36.0, y)
    dist = ax - fold_x
    d += fold_on * (
        1.0 * np.exp(-0.5 * ((dist - 3.5) / 3.5) ** 2) - 0.7 * np.exp(-0.5 * (dist / 1.5) ** 2)
    )

    # ---- chin and mentolabial sulcus
    d -= 1.8 * _gauss(ax, y, 0.0, -50.0, 12.0, 3.0)
    d += 4.6 * _gauss(ax, y, 0.0, -62.0, 13.0, 7.0)
    d += 1.2 * _gauss(ax, y, 0.0, -72.0, 18.0, 4.0)
    return d


def _dome_z(x, y, c, r, z0, height, power):
    """Height field of a dome (mm): z0 + height * q^power with q = 1 - |(p - c) / r|^2 inside
    the elliptic outline, -inf outside."""
    q = 1.0 - ((x - c[0]) / r[0]) ** 2 - ((y - c[1]) / r[1]) ** 2
    return np.where(q > 0.0, z0 + height * np.clip(q, 0.0, None) ** power, -np.inf)


def _nose_z(x, y):
    """Absolute z (mm) of the nose surface at (x, y) (-inf where there is no nose): dorsum,
    tip lobule, columella and alae, blended by smooth maxima (creases at the alar grooves)."""
    ax = np.abs(x)
    # dorsum ridge: height profile and a rounded cross-section (ridge radius ~3.5 mm)
    yy = np.array(
        [
            41.0,
            39.5,
            38.0,
            36.0,
            33.0,
            30.0,
            27.0,
            24.0,
            21.0,
            18.0,
            15.0,
            12.0,
            9.0,
            6.0,
            3.0,
            0.0,
            -3.0,
            -6.0,
            -9.0,
        ]
    )
    zz = np.array(
        [
            100.0,
            104.0,
            106.5,
            107.8,
            109.9,
            112.6,
            115.0,
            117.2,
            119.2,
            121.3,
            123.6,
            125.4,
            126.6,
            126.8,
            125.5,
            123.0,
            119.0,
            114.0,
            108.0,
        ]
    )
    zd = np.interp(-y, -yy, zz, left=-np.inf, right=-np.inf)
    slope = np.interp(-y, -yy, np.linspace(1.6, 1.15, len(yy)))
    rho = 9.0
    dorsum = zd - (np.sqrt(rho * rho + (slope * ax) ** 2) - rho)
    dorsum = np.where(np.isfinite(zd), dorsum, -np.inf)
    tip = _dome_z(ax, y, (0.0, 2.5), (11.5, 11.0), 112.0, 19.0, 0.55)
    col = _dome_z(ax, y, (0.0, -7.0), (5.0, 6.5), 108.0, 11.0, 0.7)
    ala = _dome_z(ax, y, (13.2, -3.5), (7.5, 6.2), 100.0, 13.5, 0.9)
    z = _smax(dorsum, tip, 5.0)
    z = _smax(z, col, 3.0)
    z = _smax(z, ala, 4.0)
    return z


_LOWER_LIP_BORDER = 10.0  # mm from the slit down to the lower vermilion border (midline)


def _upper_vermilion_border(ax):
    """Height (mm) of the upper lip's vermilion border (cupid's bow) at |x|, descending toward
    the mouth corners."""
    xc = _MOUTH_CORNER[0]
    return (
        -25.2
        + 1.0 * np.exp(-0.5 * ((ax - 4.8) / 2.2) ** 2)
        - 0.7 * np.exp(-0.5 * (ax / 1.6) ** 2)
        - 7.5 * (np.minimum(ax, xc) / xc) ** 2
    )


def _lips(ax, y):
    """Lip relief (mm) over the muzzle: upper vermilion with cupid's bow and white roll,
    philtrum, lower lip, and the inward roll of both lips at the closed slit."""
    xc = _MOUTH_CORNER[0]
    slit = _mouth_line(np.minimum(ax, xc))
    wl = _smoothstep(xc + 2.0, xc - 8.0, ax)  # lateral fade
    border = _upper_vermilion_border(ax)
    up_t = np.clip((y - slit) / np.maximum(border - slit, 1.0), 0.0, 1.0)
    upper = 1.9 * np.sin(np.pi * up_t**0.8) * (y >= slit)
    upper += 0.5 * np.exp(-0.5 * ((y - border) / 0.9) ** 2)  # white roll
    phil = _smoothstep(-12.5, -15.5, y) * _smoothstep(border, border + 2.5, y)
    upper += phil * (
        0.8 * np.exp(-0.5 * ((ax - 5.2) / 1.5) ** 2) - 0.5 * np.exp(-0.5 * (ax / 2.0) ** 2)
    )
    # lower lip: a full roll from the slit down to ~ -46
    lo_t = np.clip((slit - y) / 13.5, 0.0, 1.0)
    lower = 2.6 * np.sin(np.pi * lo_t**1.05) * (y < slit)
    lip = (upper + lower) * wl
    # both lips turn in at the slit: the edges sit ~4.5 mm behind the lip fronts
    dist = y - slit
    roll = 4.6 * np.exp(-0.5 * (dist / 1.25) ** 2) * _smoothstep(xc + 1.0, xc - 5.0, ax)
    return lip - roll


_EAR_CENTER = (8.0, -4.0)  # (y, z) of the ear's centre, mm
_EAR_TILT = np.deg2rad(15.0)  # the ear leans back


def _ear_frame(y, z):
    """Ear coordinates (mm): u across the ear (toward the face +), v along its long axis (up +)."""
    cy, cz = _EAR_CENTER
    v = (y - cy) * np.cos(_EAR_TILT) + (z - cz) * np.sin(_EAR_TILT)
    u = -(y - cy) * np.sin(_EAR_TILT) + (z - cz) * np.cos(_EAR_TILT)
    return u, v


def _ear_point(u, v):
    """(y, z) (mm) of ear coordinates (u, v)."""
    cy, cz = _EAR_CENTER
    return (
        cy + v * np.cos(_EAR_TILT) - u * np.sin(_EAR_TILT),
        cz + v * np.sin(_EAR_TILT) + u * np.cos(_EAR_TILT),
    )


def _relief_x(p):
    """Sideways (+-x) displacement (mm) at base points ``(N, 3)``: the ears (a plate standing
    off the head more at the back, the helix rim, antihelix, concha bowl, tragus, lobe)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    side = _smoothstep(45.0, 65.0, np.abs(x))
    u, v = _ear_frame(y, z)
    rr = np.sqrt((v / 30.0) ** 2 + (u / 16.5) ** 2)
    body = (7.0 + 4.0 * np.clip(-u / 16.5, -0.5, 1.0)) * _bump(rr**2) ** 0.6
    c_open = _smoothstep(0.35, -0.1, u / 16.5) + _smoothstep(-0.2, 0.3, v / 30.0)  # C-shape
    rim = 3.0 * np.exp(-0.5 * ((rr - 0.84) / 0.09) ** 2) * np.clip(c_open, 0.0, 1.0)
    anti = 1.6 * np.exp(-0.5 * ((rr - 0.52) / 0.08) ** 2) * _smoothstep(-0.3, 0.2, v / 30.0)
    concha = 6.5 * _gauss(u, v, 3.0, -4.0, 5.5, 7.0)
    lobe = 3.0 * _gauss(u, v, -1.0, -24.0, 6.0, 5.0)
    tragus = 2.5 * _gauss(u, v, 12.0, -6.0, 2.5, 3.5)
    return side * (body + rim + anti - concha + lobe + tragus)


def _skin_from_base(p0: np.ndarray) -> np.ndarray:
    """Skin points ``(N, 3)`` (mm) over base-head points ``p0`` ``(N, 3)``: the face relief
    moves points along +z (so front points keep their x, y), the ears along +-x."""
    n0 = _base_normals(p0)
    x, y, z = p0[:, 0], p0[:, 1], p0[:, 2]
    front = _smoothstep(0.25, 0.6, n0[:, 2]) * (z > 30.0)
    zf = z + front * _relief_z(x, y)
    on_face = front > 0.99
    zf = np.where(on_face, _smax(zf, _nose_z(x, y), 3.5), zf)
    zf -= front * 2.0 * _gauss(np.abs(x), y, 6.5, -9.0, 2.2, 1.5)  # nostrils
    # lids: smooth maximum of the socket surface and a shell around each eyeball
    for sx in (1.0, -1.0):
        c = _EYE_CENTER * np.array([sx, 1.0, 1.0])
        rs = EYE_RADIUS + _LID_SHELL
        q = rs * rs - (x - c[0]) ** 2 - (y - c[1]) ** 2
        shell = np.where((q > 0) & on_face, c[2] + np.sqrt(np.clip(q, 0.0, None)), -np.inf)
        zf = _smax(zf, shell, 2.2)
    return np.stack([x + np.sign(x) * _relief_x(p0), y, zf], axis=1)


def _front_base_z(x, y):
    """z (mm) of the front half of the base head above (x, y) (closed form; NaN off the head)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    yc = np.clip(y, _Y_TAB[0], _DOME_TOP)
    ym = np.minimum(yc, _DOME_Y0)
    w, zf, zb, zc, nf = (np.interp(ym, _PROFILE_Y, row) for row in _PROFILE_TAB)
    dw, dzf, _ = _cranium(yc)
    low = yc < _DOME_Y0
    w = np.where(low, w, dw)
    zf = np.where(low, zf, dzf)
    zc = np.where(low, zc, 0.0)
    nf = np.where(low, nf, _NF_TAB[-1])
    u = np.abs(x) / np.maximum(w, 1e-9)
    with np.errstate(invalid="ignore"):
        return zc + (zf - zc) * (1.0 - u**nf) ** (1.0 / nf)


def _skin_xy(x, y) -> np.ndarray:
    """Skin points ``(N, 3)`` (mm) on the front of the face above (x, y)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    return _skin_from_base(np.stack([x, y, _front_base_z(x, y)], axis=1))


def _relax_front(vertices, triangles, movable, iters: int = 16, step: float = 0.6):
    """Tangential relaxation of the face vertices (mm), keeping them on the exact surface.

    Each step moves every movable vertex a fraction ``step`` (times its weight in
    ``movable``, 0..1) toward the average of its neighbours, within the tangent plane,
    expressed as a move of its (x, y) on the height field of the face, then re-evaluates the
    skin at the new (x, y). Vertices gather where the surface is steep (nose, lip roll), which
    evens out the triangle shapes there."""
    V = vertices.copy()
    n = len(V)
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    import scipy.sparse as sp

    A = sp.coo_matrix(
        (
            np.ones(2 * len(e)),
            (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])),
        ),
        shape=(n, n),
    ).tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    idx = np.nonzero(movable > 0)[0]
    wgt = movable[idx]
    # faces around the movable vertices, and the (vertex x face) incidence for their normals
    faces = np.nonzero(np.isin(triangles, idx).any(axis=1))[0]
    T = triangles[faces]
    rows = np.concatenate([T[:, 0], T[:, 1], T[:, 2]])
    cols = np.tile(np.arange(len(T)), 3)
    inc = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, len(T))).tocsr()[idx]
    A_idx = A[idx]
    for _ in range(iters):
        L = (A_idx @ V) / deg[idx, None] - V[idx]
        # local height-field gradient from the (area-weighted) mesh normals
        fn = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
        vn = inc @ fn
        nn = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
        nz = np.maximum(nn[:, 2], 0.08)
        gx, gy = -nn[:, 0] / nz, -nn[:, 1] / nz
        # least squares: (I + g g^T) d = L_xy + g L_z
        rx = L[:, 0] + gx * L[:, 2]
        ry = L[:, 1] + gy * L[:, 2]
        det = (1 + gx * gx) * (1 + gy * gy) - (gx * gy) ** 2
        dx = ((1 + gy * gy) * rx - gx * gy * ry) / det
        dy = ((1 + gx * gx) * ry - gx * gy * rx) / det
        x = V[idx, 0] + step * wgt * dx
        y = V[idx, 1] + step * wgt * dy
        V[idx] = _skin_xy(x, y)
    return V
