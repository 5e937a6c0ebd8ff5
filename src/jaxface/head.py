"""The embedded procedural default head: :func:`generic_head`.

jaxface ships its own deterministic, human-proportioned head so that every command works on a
fresh machine with no data: it stands in for a scan (the default face of synthesis, scanning
and fitting). No outside mesh or data is used. Proportions follow adult anthropometric norms
and the landmark spacing of a neutral Bosphorus-style face (inter-canthal and bi-ocular
widths, nose-tip height and projection, mouth width, lip and chin heights, midline profile).

Construction (all in mm, +y up, face looking along +z, the subject's left at +x):

1. **Base head**: a loft of horizontal super-ellipses (front and back halves with their own
   depth and exponent; width, depths and exponent by height, smoothing splines through design
   values) joined to an ellipsoidal cranial dome: head length ~194 mm, breadth ~158 mm,
   vertex to menton ~225 mm.
2. **Parametrisation**: rays from :data:`RAY_ORIGIN` hit the base head (a deformed sphere).
   Rings of rays run around the head, nearly horizontal, spaced ~2.9 mm on the face band and
   ~1.7 mm at the eye, nose-base and mouth heights; each ring has its own columns (~2.8 mm on
   the face and the ears, ~7 mm at the back). Neighbouring rings are stitched by a merge
   ("zipper") triangulation of the left half, mirrored to the right half (the mesh is exactly
   symmetric, :attr:`Head.mirror`), and the vertex is closed by a fan; the neck is cut open
   horizontally at y = -118 mm.
3. **Openings**: the mouth and the two eyes are slits along a ring: the slit vertices are
   duplicated, so the upper and lower lip (lid) edges are distinct vertices that meet at the
   shared mouth (eye) corner vertices. A smooth warp of the ring elevations bends each slit
   onto its designed line and opens it: almond-shaped palpebral fissures (~10 mm high) and a
   closed mouth whose lips touch with a 0.76 mm gap.
4. **Relief**: displacement fields along +z on the face (brow ridge, glabella, eye sockets
   with the upper-lid crease, cheek bones, perioral mound, lips with vermilion, cupid's bow,
   philtrum and the inward roll at the slit, nasolabial folds, chin) and along +-x on the sides
   (ears: helix rim, antihelix, concha, tragus, lobe). The nose is the smooth maximum of
   height-field primitives (dorsum ridge, tip lobule, columella, alae) with nostril
   impressions; the lids are the smooth maximum of the socket and a shell 1.8 mm outside the
   eyeball. A tangential relaxation on the face (vertices stay on the exact surface) evens
   out the triangles on steep parts (nose base, lip roll).

The result (:class:`Head`) carries the skin mesh (:class:`jaxface.mesh.TriMesh`, ~12k
vertices, every triangle angle above 17 degrees), the 24 Bosphorus landmarks on its surface,
named vertex regions and ordered slit edges, two eyeballs and upper/lower teeth (closed
meshes). :func:`save_head` writes it all (PLY, ``.lm3``, PNG). Building takes ~1 s (CPU).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy.interpolate import make_smoothing_spline

from .landmarks import BOSPHORUS_LABELS, Landmarks, write_lm3
from .mesh import TriMesh, save_mesh
from .render import head_layers, save_views

__all__ = ["Head", "generic_head", "build_head", "save_head", "RAY_ORIGIN", "EYE_RADIUS"]

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


# ----------------------------------------------------------------------------- eyes and teeth
def _eyeball(sx: float) -> TriMesh:
    """Closed eyeball mesh (mm): a sphere of radius :data:`EYE_RADIUS` with a corneal bulge
    (1.3 mm) toward +z, centred in the socket on side ``sx`` (+1 left, -1 right)."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    d = np.asarray(ico.vertices, dtype=np.float64)
    ang = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    r = EYE_RADIUS + 1.3 * _bump((ang / np.deg2rad(36.0)) ** 2)
    c = _EYE_CENTER * np.array([sx, 1.0, 1.0])
    return TriMesh(c + r[:, None] * d, np.asarray(ico.faces, dtype=np.int64))


# tooth widths (mm) from the midline back: central and lateral incisor, canine, 2 premolars,
# 2 molars
_TOOTH_WIDTHS = np.array([8.5, 6.5, 7.5, 7.0, 6.8, 10.0, 9.0])


def _teeth(upper: bool) -> TriMesh:
    """Closed dental arch (crowns + gum band) as a swept rounded section (mm).

    The arch runs through x = a sin u, z = z0 - b (1 - cos u); the labial surface follows it,
    the section (labio-lingual thickness t(u), height h) lies inward. Shallow grooves mark the
    tooth boundaries."""
    if upper:
        a, b, z0 = 25.5, 40.0, 104.0
        y_edge, y_gum, t_front, t_back = -35.0, -21.0, 6.5, 10.5
        sgn = -1.0  # the biting edge is at the bottom
    else:
        a, b, z0 = 23.5, 38.0, 98.6
        y_edge, y_gum, t_front, t_back = -33.6, -47.0, 6.0, 10.0
        sgn = 1.0  # the biting edge is at the top

    # the arch: a half ellipse in front, continued straight back (C1) past u = pi/2
    def arch(u):
        u = np.asarray(u, dtype=np.float64)
        au = np.abs(u)
        ell = au <= np.pi / 2
        x = np.where(ell, a * np.sin(au), a)
        z = np.where(ell, z0 - b * (1.0 - np.cos(au)), z0 - b - b * (au - np.pi / 2))
        return np.sign(u) * x, z

    uu = np.linspace(0.0, np.pi, 4001)
    ax_, az_ = arch(uu)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(ax_), np.diff(az_)))])
    half = _TOOTH_WIDTHS.sum() * (0.93 if not upper else 1.0)
    u_max = float(np.interp(half, arc, uu))
    n_u, n_s = 61, 20
    s_arc = np.linspace(-half, half, n_u)
    u = np.sign(s_arc) * np.interp(np.abs(s_arc), arc, uu)
    px, pz = arch(u)
    e = 1e-6
    qx, qz = arch(u + e)
    tx, tz = (qx - px) / e, (qz - pz) / e
    tn = np.hypot(tx, tz)
    tx, tz = tx / tn, tz / tn
    nx, nz = -tz, tx  # outward (labial/buccal) normal in the xz plane
    rel = np.abs(u) / u_max
    thick = t_front + (t_back - t_front) * rel**2
    # tooth boundary grooves along the arch
    bounds = np.cumsum(_TOOTH_WIDTHS) * (half / _TOOTH_WIDTHS.sum())
    bounds = np.concatenate([[0.0], bounds[:-1]])
    dist = np.min(np.abs(np.abs(s_arc)[:, None] - bounds[None, :]), axis=1)
    groove = 0.6 * np.exp(-0.5 * (dist / 0.9) ** 2)
    # rounded-rectangle section: psi around the section, superellipse exponent 4
    psi = np.linspace(0.0, 2.0 * np.pi, n_s, endpoint=False)
    cs, sn = np.cos(psi), np.sin(psi)
    q = 4.0
    sec_n = np.sign(cs) * np.abs(cs) ** (2.0 / q)  # [-1, 1] across (outward +)
    sec_y = np.sign(sn) * np.abs(sn) ** (2.0 / q)  # [-1, 1] along the height
    # height coordinate: -1 at the biting edge, +1 at the gum
    # occlusal plane: the incisors overlap vertically (overbite), the back teeth meet edge to
    # edge with a small gap
    back = _smoothstep(0.06, 0.2, np.abs(s_arc) / half)[:, None]
    y_edge_u = y_edge + back * ((-34.1 if upper else -34.3) - y_edge)
    yy = 0.5 * (y_edge_u + y_gum) + sec_y[None, :] * 0.5 * (y_gum - y_edge_u)  # (n_u, n_s)
    s_edge = (yy - y_edge_u) / (y_gum - y_edge_u)  # 0 at the edge, 1 at the gum
    taper = 0.55 + 0.45 * np.sqrt(np.clip(s_edge, 0.0, 1.0))  # chisel-shaped edge
    V = np.empty((n_u, n_s, 3))
    half_t = 0.5 * thick[:, None] * taper
    off = -0.5 * thick[:, None] + sec_n[None, :] * half_t  # from the labial surface
    off = off - groove[:, None] * (np.abs(sec_n)[None, :] > 0.3)
    V[:, :, 0] = px[:, None] + off * nx[:, None]
    V[:, :, 2] = pz[:, None] + off * nz[:, None]
    # bite edge notches at the tooth boundaries
    V[:, :, 1] = yy - sgn * 0.4 * groove[:, None] / 0.6 * (s_edge < 0.05)
    verts = V.reshape(-1, 3)
    tris = []
    idx = np.arange(n_u * n_s).reshape(n_u, n_s)
    for i in range(n_u - 1):
        a0, a1 = idx[i], idx[i + 1]
        b0, b1 = np.roll(a0, -1), np.roll(a1, -1)
        tris.append(np.stack([a0, b0, b1], axis=1))
        tris.append(np.stack([a0, b1, a1], axis=1))
    c0 = len(verts)
    c1 = c0 + 1
    caps = np.stack([V[0].mean(axis=0), V[-1].mean(axis=0)])
    verts = np.concatenate([verts, caps])
    tris.append(np.stack([np.full(n_s, c0), np.roll(idx[0], -1), idx[0]], axis=1))
    tris.append(np.stack([np.full(n_s, c1), idx[-1], np.roll(idx[-1], -1)], axis=1))
    F = np.concatenate(tris).astype(np.int64)
    # orient outward: the signed volume must be positive
    vol = np.einsum("ij,ij->i", verts[F[:, 0]], np.cross(verts[F[:, 1]], verts[F[:, 2]])).sum()
    if vol < 0:
        F = F[:, ::-1]
    return TriMesh(verts, F)


# ----------------------------------------------------------------------------- assembly
def _first_hits(V: np.ndarray, F: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """First intersection points ``(R, 3)`` (mm) of rays with a triangle mesh (Moller-Trumbore,
    vectorised over the triangles); NaN where a ray misses."""
    out = np.full((len(origins), 3), np.nan)
    tri = V[F]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    for i, (o, d) in enumerate(zip(origins, dirs)):
        d = d / np.linalg.norm(d)
        # candidate triangles: bounding box meets the ray's line (axis-aligned rays: exact cut)
        axis = int(np.argmax(np.abs(d)))
        other = [k for k in range(3) if k != axis]
        if np.abs(d[other]).max() < 1e-12:
            cand = np.all(
                (lo[:, other] <= o[other] + 1e-9) & (hi[:, other] >= o[other] - 1e-9), axis=1
            )
        else:
            cand = np.ones(len(F), dtype=bool)
        if not cand.any():
            continue
        a, b, c = tri[cand, 0], tri[cand, 1], tri[cand, 2]
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - a
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12) & (t > 0)
        if hit.any():
            out[i] = o + t[hit].min() * d
    return out


def _front_hits(V, F, xy: np.ndarray) -> np.ndarray:
    """Points (mm) of the skin seen from the front (+z) above ``(N, 2)`` positions (x, y)."""
    xy = np.atleast_2d(xy)
    o = np.column_stack([xy, np.full(len(xy), 400.0)])
    return _first_hits(V, F, o, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))


def _most_anterior(V, F, y_lo: float, y_hi: float, step: float = 0.1) -> np.ndarray:
    """The most anterior (max z) skin point on the midline x = 0 with y in [y_lo, y_hi]."""
    ys = np.arange(y_lo, y_hi + step / 2, step)
    # only the triangles near the midline matter
    near = np.abs(V[F].mean(axis=1)[:, 0]) < 6.0
    pts = _front_hits(V, F[near], np.column_stack([np.zeros_like(ys), ys]))
    i = int(np.nanargmax(pts[:, 2]))
    return pts[i]


@dataclasses.dataclass(frozen=True)
class Head:
    """The embedded default head (all in mm; +y up, face along +z, subject's left at +x).

    Attributes:
        mesh: the skin, a :class:`TriMesh` closed behind; its only boundaries are the two
            palpebral fissures, the closed mouth slit and the neck cut.
        landmarks: the 24 Bosphorus landmarks (:data:`BOSPHORUS_LABELS`), on the skin surface.
        face_mask: ``(V,)`` bool, the face region (forehead to under the chin, ear to ear in
            front of the ears).
        upper_teeth, lower_teeth: closed dental arches (crowns and gum band) behind the lips.
        regions: named ``(V,)`` bool vertex masks: ``face``, ``upper_lip``, ``lower_lip``,
            ``lips``, ``nose``, ``eye_left``/``eye_right`` (lids and surroundings),
            ``upper_lid_left``, ``lower_lid_left``, ``upper_lid_right``, ``lower_lid_right``,
            ``jaw`` (skin carried by the mandible: lower lip, chin, jaw line, below the mouth
            line back to the ear), ``forehead``, ``cheek_left``, ``cheek_right``, ``ear_left``,
            ``ear_right``, ``neck``, ``scalp``.
        edges: named ordered vertex-id paths, ``(n,)`` int64: ``upper_lip_edge`` and
            ``lower_lip_edge`` (the two edges of the mouth slit, from the right mouth corner
            to the left one, both ending at the shared corner vertices),
            ``upper_lid_left``/``lower_lid_left``/``upper_lid_right``/``lower_lid_right``
            (lid margins from the inner to the outer eye corner), ``neck`` (the neck cut loop).
        eyes: ``(left, right)`` closed eyeball meshes (radius :data:`EYE_RADIUS` + cornea).
        eye_centers: ``(2, 3)`` eyeball centres (left, right).
        landmark_vertex: for the landmarks that are mesh vertices (eye and mouth corners,
            inner lip midpoints), the vertex id.
        mirror: ``(V,)`` int64, the vertex mirrored through the plane x = 0 (the head is
            exactly symmetric: ``vertices[mirror] == vertices * (-1, 1, 1)`` up to rounding,
            and the triangulation is mirrored too).
    """

    mesh: TriMesh
    landmarks: Landmarks
    face_mask: np.ndarray
    upper_teeth: TriMesh
    lower_teeth: TriMesh
    regions: dict
    edges: dict
    eyes: tuple
    eye_centers: np.ndarray
    landmark_vertex: dict
    mirror: np.ndarray

    @property
    def eye_radius(self) -> float:
        """Eyeball radius, mm."""
        return EYE_RADIUS

    def eye_axis(self, side: str = "left") -> tuple[np.ndarray, np.ndarray]:
        """(inner corner, outer corner) positions (mm) of the ``"left"`` or ``"right"`` eye:
        the axis about which the lids turn."""
        s = "left" if side.startswith("l") else "right"
        lm = self.landmarks
        return lm[f"Inner {s} eye corner"].copy(), lm[f"Outer {s} eye corner"].copy()

    def parts(self) -> dict:
        """All meshes by name: ``skin``, ``eye_left``, ``eye_right``, ``upper_teeth``,
        ``lower_teeth``."""
        return {
            "skin": self.mesh,
            "eye_left": self.eyes[0],
            "eye_right": self.eyes[1],
            "upper_teeth": self.upper_teeth,
            "lower_teeth": self.lower_teeth,
        }


def _readonly(a):
    a = np.array(a)
    a.setflags(write=False)
    return a


def build_head() -> Head:
    """Build the procedural default head (deterministic; ~1 s). Prefer the cached
    :func:`generic_head`."""
    g = _build_grid()
    V, F = g.vertices, g.triangles
    mesh = TriMesh(V, F)

    # ---- ordered edges of the slits
    def slit_path(s: _Slit, upper: bool) -> np.ndarray:
        on = (g.ring == s.ring) & (g.theta > s.theta_a + 1e-12) & (g.theta < s.theta_b - 1e-12)
        on &= g.upper_copy if upper else ~g.upper_copy
        ids = np.nonzero(on)[0]
        ids = ids[np.argsort(g.theta[ids])]
        corners = corner_ids(s)
        return np.concatenate([[corners[0]], ids, [corners[1]]]).astype(np.int64)

    def corner_ids(s: _Slit) -> tuple[int, int]:
        ring = np.nonzero(g.ring == s.ring)[0]
        a = ring[np.argmin(np.abs(g.theta[ring] - s.theta_a))]
        b = ring[np.argmin(np.abs(g.theta[ring] - s.theta_b))]
        return int(a), int(b)

    edges = {}
    mouth = g.slits["mouth"]
    edges["upper_lip_edge"] = slit_path(mouth, True)
    edges["lower_lip_edge"] = slit_path(mouth, False)
    for side in ("left", "right"):
        s = g.slits[f"eye_{side}"]
        up, lo = slit_path(s, True), slit_path(s, False)
        if side == "right":  # order from the inner corner (near x = 0) outward
            up, lo = up[::-1], lo[::-1]
        edges[f"upper_lid_{side}"] = up
        edges[f"lower_lid_{side}"] = lo
    neck = np.nonzero(g.ring == 0)[0]
    edges["neck"] = neck[np.argsort(g.theta[neck])].astype(np.int64)

    # ---- landmarks
    mid_up = edges["upper_lip_edge"][np.argmin(np.abs(V[edges["upper_lip_edge"], 0]))]
    mid_lo = edges["lower_lip_edge"][np.argmin(np.abs(V[edges["lower_lip_edge"], 0]))]
    vid = {
        "Inner left eye corner": edges["upper_lid_left"][0],
        "Outer left eye corner": edges["upper_lid_left"][-1],
        "Inner right eye corner": edges["upper_lid_right"][0],
        "Outer right eye corner": edges["upper_lid_right"][-1],
        "Right mouth corner": edges["upper_lip_edge"][0],
        "Left mouth corner": edges["upper_lip_edge"][-1],
        "Upper lip inner middle": mid_up,
        "Lower lip inner middle": mid_lo,
    }
    vid = {k: int(v) for k, v in vid.items()}
    pos = {k: V[v] for k, v in vid.items()}
    brow_x = {"Outer": 58.2, "Middle": 37.9, "Inner": 11.7}
    front_xy, front_names = [], []
    for which, bx in brow_x.items():
        for side, sx in (("left", 1.0), ("right", -1.0)):
            front_names.append(f"{which} {side} eyebrow")
            front_xy.append((sx * bx, float(_brow_line(bx))))
    for side, sx in (("left", 1.0), ("right", -1.0)):
        front_names.append(f"Nose saddle {side}")
        front_xy.append((sx * 8.5, 27.4))
        front_names.append(f"{side.capitalize()} nose peak")
        front_xy.append((sx * 19.8, -2.5))
    hits = _front_hits(V, F, np.array(front_xy))
    pos.update(dict(zip(front_names, hits)))
    pos["Nose tip"] = _most_anterior(V, F, -6.0, 14.0)
    # labrale superius / inferius: the midpoints of the upper and lower vermilion borders
    lips = _front_hits(
        V,
        F,
        np.array(
            [[0.0, float(_upper_vermilion_border(0.0))], [0.0, _MOUTH_MID_Y - _LOWER_LIP_BORDER]]
        ),
    )
    pos["Upper lip outer middle"], pos["Lower lip outer middle"] = lips[0], lips[1]
    pos["Chin middle"] = _most_anterior(V, F, -74.0, -52.0)
    # ear lobes: lowest part of the lobe relief, seen from the side
    ly, lz = _ear_point(-1.0, -26.0)  # the lower part of the lobe
    lobe = _first_hits(
        V,
        F,
        np.array([[200.0, ly, lz], [-200.0, ly, lz]]),
        np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
    )
    pos["Left ear lobe"], pos["Right ear lobe"] = lobe[0], lobe[1]
    landmarks = Landmarks(BOSPHORUS_LABELS, np.array([pos[n] for n in BOSPHORUS_LABELS]))

    # ---- regions
    p0 = _base_points(g.theta, g.phi)
    n0 = _base_normals(p0)
    x, y, z = V[:, 0], V[:, 1], V[:, 2]
    ax = np.abs(x)
    face = (p0[:, 2] > 15.0) & (y > -90.0) & (y < 88.0) & (n0[:, 2] > 0.3)
    # which side of the mouth slit: vertices of the slit ring by their copy, others by ring
    mouth_side = np.where(
        g.ring == mouth.ring, np.where(g.upper_copy, 1, -1), np.sign(g.ring - mouth.ring)
    )
    in_mouth_x = ax < _MOUTH_CORNER[0] + 3.0
    upper_lip = (
        face
        & in_mouth_x
        & (mouth_side > 0)
        & (y < -12.5)
        & (y > _mouth_line(np.minimum(ax, _MOUTH_CORNER[0])) - 1.0)
    )
    lower_lip = face & in_mouth_x & (mouth_side < 0) & (y > -48.0) & (y < -30.0)
    regions = {
        "face": face,
        "upper_lip": upper_lip,
        "lower_lip": lower_lip,
        "lips": upper_lip | lower_lip,
    }
    nose = face & (ax < 23.0) & (y > -14.0) & (y < 42.0)
    nose &= _nose_z(x, y) > _front_base_z(x, y) + _relief_z(x, y) - 1.0
    regions["nose"] = nose
    eye_ring = g.slits["eye_left"].ring
    eye_side = np.where(
        g.ring == eye_ring, np.where(g.upper_copy, 1, -1), np.sign(g.ring - eye_ring)
    )
    for side, sx in (("left", 1.0), ("right", -1.0)):
        c = _EYE_CENTER * np.array([sx, 1.0, 1.0])
        near = face & (np.abs(x - c[0]) < 17.0) & (y > 20.0) & (y < 47.0) & (sx * x > 12.0)
        regions[f"eye_{side}"] = near
        lid_x = (sx * x > _CANTHUS_IN[0] - 1.0) & (sx * x < _CANTHUS_OUT[0] + 1.0)
        line, up, lo = _lid_margin_curves(np.clip(sx * x, _CANTHUS_IN[0], _CANTHUS_OUT[0]))
        regions[f"upper_lid_{side}"] = near & lid_x & (eye_side > 0) & (y < up + 8.0)
        regions[f"lower_lid_{side}"] = near & lid_x & (eye_side < 0) & (y > lo - 6.0)
    # jaw: below the mouth line in front, below a line from the mouth corner to under the ear
    t = np.clip((ax - _MOUTH_CORNER[0]) / (70.0 - _MOUTH_CORNER[0]), 0.0, 1.0)
    jaw_line = _MOUTH_CORNER[1] + t * (-22.0 - _MOUTH_CORNER[1])
    below = np.where(in_mouth_x & (np.abs(y - _MOUTH_MID_Y) < 6.0), mouth_side < 0, y < jaw_line)
    regions["jaw"] = below & (y > -92.0) & (p0[:, 2] > -15.0) & (z > -15.0)
    regions["forehead"] = face & (y > 45.0)
    for side, sx in (("left", 1.0), ("right", -1.0)):
        regions[f"cheek_{side}"] = (
            face & (sx * x > 18.0) & (y < 24.0) & (y > -40.0) & ~regions["jaw"]
        )
        eu, ev = _ear_frame(y, z)
        regions[f"ear_{side}"] = (sx * x > 55.0) & ((ev / 31.0) ** 2 + (eu / 17.5) ** 2 < 1.0)
    regions["neck"] = (y < -85.0) & ~face
    regions["scalp"] = (y > 60.0) & ~face
    regions = {k: _readonly(v.astype(bool)) for k, v in regions.items()}

    eyes = (_eyeball(1.0), _eyeball(-1.0))
    centers = np.stack([_EYE_CENTER, _EYE_CENTER * np.array([-1.0, 1.0, 1.0])])
    return Head(
        mesh=mesh,
        landmarks=landmarks,
        face_mask=regions["face"],
        upper_teeth=_teeth(True),
        lower_teeth=_teeth(False),
        regions=regions,
        edges={k: _readonly(v) for k, v in edges.items()},
        eyes=eyes,
        eye_centers=_readonly(centers),
        landmark_vertex=vid,
        mirror=_readonly(g.mirror.astype(np.int64)),
    )


@functools.lru_cache(maxsize=1)
def generic_head() -> Head:
    """The embedded procedural default head (cached; see :class:`Head`). All units mm."""
    return build_head()


def save_head(
    head: Head,
    directory,
    *,
    stem: str = "head",
    picture: bool = True,
    panel_px: int = 600,
    labels: bool = False,
    units: str = "mm",
) -> dict:
    """Write a head to ``directory``: the skin ``<stem>.ply``, its landmarks ``<stem>.lm3``,
    ``upper_teeth.ply``, ``lower_teeth.ply``, ``eye_left.ply``, ``eye_right.ply`` and, if
    ``picture``, ``<stem>.png`` (front and side views with the landmarks).

    Args:
        head: the :class:`Head` (mm).
        directory: output folder (created if needed).
        stem: file name stem of the skin mesh, landmarks and picture.
        picture: also render the PNG (matplotlib, headless).
        panel_px: picture panel size, pixels.
        labels: write the landmark names on the picture.
        units: unit of the written meshes ("mm", "cm" or "m"); landmarks are always mm.

    Returns:
        ``{name: Path}`` of the files written.
    """
    from pathlib import Path

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    files["skin"] = out / f"{stem}.ply"
    save_mesh(files["skin"], head.mesh, units=units)
    files["landmarks"] = out / f"{stem}.lm3"
    write_lm3(
        files["landmarks"],
        head.landmarks,
        comment=f"jaxface default head: 24 Bosphorus landmarks (mm) on {stem}.ply",
    )
    for name, mesh in (
        ("upper_teeth", head.upper_teeth),
        ("lower_teeth", head.lower_teeth),
        ("eye_left", head.eyes[0]),
        ("eye_right", head.eyes[1]),
    ):
        files[name] = out / f"{name}.ply"
        save_mesh(files[name], mesh, units=units)
    if picture:
        files["picture"] = save_views(
            out / f"{stem}.png",
            head_layers(head),
            ("front", "side"),
            landmarks=head.landmarks,
            labels=labels,
            panel_px=panel_px,
            title="jaxface default head (mm): front and left side",
        )
    return files
