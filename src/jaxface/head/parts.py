"""Eyeballs and dental arches of the default head (closed :class:`~jaxface.mesh.TriMesh`, mm)."""

from __future__ import annotations

import numpy as np

from ..mesh import TriMesh
from .base import _EYE_CENTER, EYE_RADIUS, _bump, _smoothstep


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
