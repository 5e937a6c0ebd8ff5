"""Design values (mm), small smooth helpers and the base loft of the default head.

The base head is a loft of horizontal super-ellipses joined to an ellipsoidal cranial dome;
:func:`_base_points` casts rays from :data:`RAY_ORIGIN` onto it (mm, +y up, face along +z).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import make_smoothing_spline

#: origin of the parametrising rays (mm); every skin vertex is seen from it (star-shaped base)
RAY_ORIGIN = np.array([0.0, 20.0, 0.0])
#: eyeball radius (mm)
EYE_RADIUS = 12.0

# ----------------------------------------------------------------------------- design values (mm)
# eyes (left = +x); the right side mirrors x
_EYE_CENTER = np.array([31.5, 33.6, 82.5])  # eyeball centre
_LID_SHELL = 1.8  # lid skin shell outside the eyeball, at the fissure
_CANTHUS_IN = np.array([18.4, 32.6])  # (x, y) inner eye corner
_CANTHUS_OUT = np.array([44.6, 34.3])  # (x, y) outer eye corner
_LID_UP = 6.3  # upper lid margin above the canthal line (max)
_LID_LO = 3.9  # lower lid margin below the canthal line (max)
# mouth
_MOUTH_CORNER = np.array([25.3, -35.2])  # (x, y) left mouth corner
_MOUTH_MID_Y = -33.6  # slit height at the midline
_MOUTH_GAP = 0.76  # closed-mouth gap between the lip edges at x = 0
# neck cut
_NECK_Y = -118.0


# ----------------------------------------------------------------------------- small helpers
def _smoothstep(e0, e1, x):
    t = np.clip((np.asarray(x, dtype=np.float64) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _bump(u):
    """C2 compact bump (1 - u^2)^3 on |u| < 1 (u may be a squared-radius argument >= 0)."""
    return np.clip(1.0 - u, 0.0, 1.0) ** 3


def _smax(a, b, k):
    """Polynomial smooth maximum with blend width ``k`` (mm)."""
    with np.errstate(invalid="ignore"):
        gap = np.abs(a - b)
    gap = np.where(np.isnan(gap), np.inf, gap)  # both -inf: no blend
    h = np.clip(k - gap, 0.0, None) / k
    return np.maximum(a, b) + h * h * k * 0.25


def _gauss(x, y, cx, cy, sx, sy):
    return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2))


# ----------------------------------------------------------------------------- base loft
_Y_TAB = np.array(
    [
        -135,
        -118,
        -104,
        -95,
        -88,
        -82,
        -77,
        -71,
        -65,
        -59,
        -50,
        -41,
        -32,
        -23,
        -14,
        -5,
        5,
        15,
        25,
        35,
        45,
        55,
        65,
    ],
    dtype=np.float64,
)
_ZF_TAB = np.array(
    [
        47,
        47.5,
        50,
        55,
        63,
        80,
        94,
        101.5,
        105,
        106.3,
        106.5,
        107.3,
        107.8,
        107.8,
        106.5,
        104.5,
        103.5,
        103.5,
        104,
        105,
        105.8,
        106,
        105.5,
    ]
)
_ZB_TAB = np.array(
    [
        -62,
        -62,
        -61.5,
        -60.5,
        -59.8,
        -59.2,
        -58.7,
        -58.2,
        -57.8,
        -57.4,
        -57.2,
        -57.5,
        -59,
        -61.5,
        -65,
        -69.5,
        -74.5,
        -79.5,
        -83.2,
        -85.6,
        -86.8,
        -87.2,
        -86.6,
    ]
)
_W_TAB = np.array(
    [
        58,
        57,
        55.5,
        55,
        55,
        55.2,
        55.8,
        56.8,
        58,
        59.3,
        61.2,
        63.6,
        66.5,
        69.5,
        72,
        74,
        75.5,
        76.7,
        77.7,
        78.5,
        79,
        79,
        78.6,
    ]
)
_ZC_TAB = np.array(
    [-7, -7, -6.5, -5.5, -4, -2, 0, 3, 6, 9, 12, 13.5, 13, 10, 6, 3, 1, 0, 0, 0, 0, 0, 0],
    dtype=np.float64,
)
_NF_TAB = np.array(
    [
        2.0,
        2.0,
        2.0,
        2.0,
        2.0,
        1.97,
        1.93,
        1.9,
        1.9,
        1.9,
        1.9,
        1.95,
        2.0,
        2.05,
        2.15,
        2.3,
        2.4,
        2.5,
        2.5,
        2.45,
        2.3,
        2.15,
        2.1,
    ]
)
_NB = 2.15
_DOME_Y0 = 65.0
_DOME_TOP = 145.0


def _cranium(y):
    """Cranial dome above y = 65 mm: (w, zf, zb, zc) shrinking to the vertex at y = 145."""
    t = np.clip((y - _DOME_Y0) / (_DOME_TOP - _DOME_Y0), 0.0, 1.0)
    w = _W_TAB[-1] * np.sqrt(np.clip(1.0 - t**2.5, 0.0, None))
    s = np.sqrt(np.clip(1.0 - t * t, 0.0, None))
    zf = _ZF_TAB[-1] * s
    zb = _ZB_TAB[-1] * s
    return w, zf, zb


def _make_profiles(step: float = 0.25):
    """Fine tables (y grid; rows w, zf, zb, zc, nf) of cubic smoothing splines through the
    design values, joined to the cranial dome; evaluated by linear interpolation (fast)."""
    ys = np.array([70.0, 75.0, 80.0])
    w, zf, zb = _cranium(ys)
    y = np.concatenate([_Y_TAB, ys])
    grid = np.arange(_Y_TAB[0], _DOME_Y0 + step / 2, step)
    cols = []
    # smoothing splines (the design values are hand-set: smoothing removes curvature ripples
    # that would show as bands in the shading); the front profile is kept close (chin)
    for a, b, lam in (
        (_W_TAB, w, 50.0),
        (_ZF_TAB, zf, 2.0),
        (_ZB_TAB, zb, 50.0),
        (_ZC_TAB, np.zeros(3), 50.0),
        (_NF_TAB, np.full(3, _NF_TAB[-1]), 50.0),
    ):
        cols.append(make_smoothing_spline(y, np.concatenate([a, b]), lam=lam)(grid))
    return grid, np.stack(cols)


_PROFILE_Y, _PROFILE_TAB = _make_profiles()


def _base_level(p: np.ndarray) -> np.ndarray:
    """Super-ellipse level of points ``(..., 3)`` (mm): < 0 inside the base head, > 0 outside."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    yc = np.clip(y, _Y_TAB[0], _DOME_TOP)
    low = yc < _DOME_Y0
    ym = np.minimum(yc, _DOME_Y0)
    w, zf, zb, zc, nf = (np.interp(ym, _PROFILE_Y, row) for row in _PROFILE_TAB)
    dw, dzf, dzb = _cranium(yc)
    w = np.where(low, w, dw)
    zf = np.where(low, zf, dzf)
    zb = np.where(low, zb, dzb)
    zc = np.where(low, zc, 0.0)
    nf = np.where(low, nf, _NF_TAB[-1])
    front = z >= zc
    depth = np.where(front, zf - zc, zc - zb)
    n = np.where(front, nf, _NB)
    u = np.abs(x) / np.maximum(w, 1e-9)
    v = np.abs(z - zc) / np.maximum(depth, 1e-9)
    g = (u**n + v**n) ** (1.0 / n) - 1.0
    return np.where(y > _DOME_TOP, 1.0 + (y - _DOME_TOP), g)


def _directions(theta, phi):
    """Unit ray directions ``(..., 3)``: azimuth ``theta`` about +y (0 = +z, +pi/2 = +x) and
    elevation ``phi`` (radians)."""
    c = np.cos(phi)
    return np.stack([c * np.sin(theta), np.sin(phi), c * np.cos(theta)], axis=-1)


def _base_points(theta, phi) -> np.ndarray:
    """Base-head surface points ``(..., 3)`` (mm) along the rays (theta, phi): bisection to a
    1.6 mm bracket, then Illinois (modified regula falsi) steps to ~1e-9 mm."""
    d = _directions(np.asarray(theta, dtype=np.float64), np.asarray(phi, dtype=np.float64))
    lo = np.full(d.shape[:-1], 20.0)
    hi = np.full(d.shape[:-1], 230.0)
    for _ in range(7):
        mid = 0.5 * (lo + hi)
        out = _base_level(RAY_ORIGIN + mid[..., None] * d) > 0.0
        hi = np.where(out, mid, hi)
        lo = np.where(out, lo, mid)
    flo = _base_level(RAY_ORIGIN + lo[..., None] * d)
    fhi = _base_level(RAY_ORIGIN + hi[..., None] * d)
    side = np.zeros(lo.shape)
    for _ in range(8):
        r = (lo * fhi - hi * flo) / np.where(fhi - flo == 0.0, 1.0, fhi - flo)
        r = np.clip(r, lo, hi)
        fr = _base_level(RAY_ORIGIN + r[..., None] * d)
        pos = fr > 0.0
        # keep the bracket; halve the retained end's value when the same end stays twice
        hi = np.where(pos, r, hi)
        lo = np.where(pos, lo, r)
        flo_new = np.where(pos, np.where(side == -1, flo * 0.5, flo), fr)
        fhi_new = np.where(pos, fr, np.where(side == 1, fhi * 0.5, fhi))
        side = np.where(pos, -1, 1)
        flo, fhi = flo_new, fhi_new
    r = (lo * fhi - hi * flo) / np.where(fhi - flo == 0.0, 1.0, fhi - flo)
    return RAY_ORIGIN + np.clip(r, lo, hi)[..., None] * d


def _base_normals(p: np.ndarray, h: float = 0.05) -> np.ndarray:
    """Outward unit normals of the base head at surface points ``(N, 3)`` (central differences)."""
    g = np.empty_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[:, k] = _base_level(p + e) - _base_level(p - e)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
