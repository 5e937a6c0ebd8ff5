"""Muscle geometry (thesis sec. 4.2): action-line sampling and the hexahedral muscle mesh.

An *action line* is a polyline of surface points lying on the skull or on other muscles. It is
sampled at regular arc-length intervals (eqs. 4.1-4.5): with the polyline points ``sp_j`` and
its length ``L``, the ``i``-th of ``N`` samples lies at arc length ``i * step`` with
``step = L / (N - 1)`` (the thesis counts the two ends as samples), found on the segment
``j`` whose cumulative length first exceeds it (4.5) by linear interpolation (4.2), with the
normal interpolated the same way (4.3). Contraction re-samples with ``step' = step (1 - c)``
(4.11); :func:`sample_polyline` (NumPy) and :func:`jax_sample_polyline` (JAX, differentiable
in the point positions and in ``c``) implement both.

The muscle body is a *w x h* hexahedral mesh (4.2.2): ``w`` fibres across, ``h`` samples along
each fibre, a bottom sheet lying on the action-line samples and a top sheet at thickness ``t``
along the sample normals (4.10). Here every fibre is an action line (the thesis's internal
action lines for flat, wide muscles), so the bottom grid *is* the set of samples and the RBF
morph of eqs. 4.6-4.9 is the identity on it. Sphincters are closed rings: ``w = n`` samples
around, ``h = 3`` rings (inner, middle, outer), periodic across.

Vertex layout of a muscle mesh: bottom vertex (fibre sample ``i`` in ``0..h-1``, fibre ``j`` in
``0..w-1``) is ``i * w + j``; the top vertex above it is ``w * h + i * w + j``.

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

__all__ = [
    "sample_polyline",
    "jax_sample_polyline",
    "MuscleGrid",
    "grid_topology",
    "ellipse_points",
]


def sample_polyline(points, n_samples: int, contraction: float = 0.0, normals=None):
    """Regular arc-length samples of a polyline (thesis eqs. 4.1-4.5, 4.11), NumPy.

    Args:
        points: ``(m, 3)`` polyline vertices (surface-point positions), mm, ``m >= 2``.
        n_samples: number of samples ``N >= 2`` (first at the start, last at the end when
            ``contraction == 0``).
        contraction: ``c`` in [0, 1]; samples at arc length ``i * step * (1 - c)``.
        normals: optional ``(m, 3)`` normals at the polyline vertices (eq. 4.3).

    Returns:
        ``(N, 3)`` sample positions (and ``(N, 3)`` unit normals if ``normals`` given).
    """
    p = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    step = cum[-1] / (n_samples - 1)
    s = np.arange(n_samples) * step * (1.0 - contraction)
    j = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    u = np.where(seg[j] > 0, (s - cum[j]) / np.where(seg[j] > 0, seg[j], 1.0), 0.0)
    u = np.clip(u, 0.0, 1.0)[:, None]
    out = (1 - u) * p[j] + u * p[j + 1]
    if normals is None:
        return out
    nrm = np.asarray(normals, dtype=np.float64)
    n = (1 - u) * nrm[j] + u * nrm[j + 1]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return out, n


def jax_sample_polyline(points, n_samples: int, contraction):
    """JAX version of :func:`sample_polyline` for batches of polylines.

    Differentiable with respect to ``points`` and ``contraction`` (the segment index is
    piecewise constant; zero-length segments are guarded, also in gradients).

    Args:
        points: ``(..., m, 3)`` polyline vertices, mm.
        n_samples: static number of samples ``N >= 2``.
        contraction: ``(...)`` contraction ``c`` per polyline (broadcast).

    Returns:
        ``(..., N, 3)`` samples, mm.
    """
    p = jnp.asarray(points)
    d = p[..., 1:, :] - p[..., :-1, :]
    d2 = jnp.sum(d * d, axis=-1)
    ok = d2 > 1e-24
    seg = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2, 1.0)), 0.0)  # (..., m-1)
    cum = jnp.concatenate([jnp.zeros_like(seg[..., :1]), jnp.cumsum(seg, axis=-1)], axis=-1)
    total = cum[..., -1:]
    i = jnp.arange(n_samples, dtype=p.dtype)
    c = jnp.asarray(contraction, dtype=p.dtype)[..., None]
    s = i * (total / (n_samples - 1)) * (1.0 - c)  # (..., N)
    m1 = seg.shape[-1]
    # j = number of cumulative knots (excluding the first) <= s, clipped to a valid segment
    j = jnp.sum(cum[..., None, 1:] <= s[..., :, None], axis=-1)
    j = jnp.clip(j, 0, m1 - 1)
    cj = jnp.take_along_axis(cum, j, axis=-1)
    lj = jnp.take_along_axis(seg, j, axis=-1)
    okj = lj > 0
    u = jnp.where(okj, (s - cj) / jnp.where(okj, lj, 1.0), 0.0)
    u = jnp.clip(u, 0.0, 1.0)[..., None]
    pj = jnp.take_along_axis(p, j[..., None], axis=-2)
    pj1 = jnp.take_along_axis(p, (j + 1)[..., None], axis=-2)
    return (1 - u) * pj + u * pj1


@dataclass(frozen=True)
class MuscleGrid:
    """Topology of a w x h hexahedral muscle mesh (see the module doc for the layout).

    Attributes:
        w, h: fibres across and samples along (rings and samples around for a sphincter).
        periodic: True for a sphincter (closed across).
        triangles: ``(F, 3)`` closed, outward-oriented surface (when the bottom grid is
            oriented with its normal along the outward support normal).
        latitudinal_up: ``(E, 2)`` top-sheet edges across the fibres.
        longitudinal_up: ``(E, 2)`` top-sheet edges along the fibres.
        latitudinal_low, longitudinal_low: the same on the bottom sheet.
        connection: ``(E, 2)`` bottom-top pairs (on the boundary of the grid only, thesis
            Fig. 4.6: connections are not placed inside the volume).
        shear_up, shear_low: ``(E, 2)`` quad diagonals on the top and bottom sheets.
    """

    w: int
    h: int
    periodic: bool
    triangles: np.ndarray
    latitudinal_up: np.ndarray
    longitudinal_up: np.ndarray
    latitudinal_low: np.ndarray
    longitudinal_low: np.ndarray
    connection: np.ndarray
    shear_up: np.ndarray
    shear_low: np.ndarray

    @property
    def n_vertices(self) -> int:
        return 2 * self.w * self.h


def grid_topology(w: int, h: int, periodic: bool = False) -> MuscleGrid:
    """Build the :class:`MuscleGrid` of a ``w x h`` muscle (``periodic`` across for rings)."""
    if w < 2 or h < 2:
        raise ValueError(f"a muscle grid needs w >= 2 and h >= 2, got w={w}, h={h}.")
    n = w * h

    def b(i, j):
        return i * w + (j % w)

    def t(i, j):
        return n + i * w + (j % w)

    jmax = w if periodic else w - 1
    tris = []
    lat_u, lon_u, lat_l, lon_l, sh_u, sh_l = [], [], [], [], [], []
    for i in range(h):
        for j in range(jmax):
            lat_l.append((b(i, j), b(i, j + 1)))
            lat_u.append((t(i, j), t(i, j + 1)))
    for i in range(h - 1):
        for j in range(w):
            lon_l.append((b(i, j), b(i + 1, j)))
            lon_u.append((t(i, j), t(i + 1, j)))
    for i in range(h - 1):
        for j in range(jmax):
            # quad (i, j), (i, j+1), (i+1, j+1), (i+1, j); bottom faces point down (-normal),
            # top faces up. With fibre direction u (increasing i) and across v (increasing j),
            # the grid normal is v x u ... orientation is fixed later by the builder.
            a, bb, c, d = b(i, j), b(i, j + 1), b(i + 1, j + 1), b(i + 1, j)
            tris += [(a, bb, c), (a, c, d)]
            A, B, C, D = t(i, j), t(i, j + 1), t(i + 1, j + 1), t(i + 1, j)
            tris += [(A, C, B), (A, D, C)]
            sh_l += [(a, c), (bb, d)]
            sh_u += [(A, C), (B, D)]

    # side walls along the boundary loop(s)
    def wall(p0, p1):
        # bottom edge p0 -> p1 with top above: two triangles
        return [(p0, p1, p1 + n), (p0, p1 + n, p0 + n)]

    walls = []
    conn = []
    if periodic:
        # inner ring (i = 0) and outer ring (i = h-1) walls, fibre-direction walls do not exist
        for j in range(w):
            walls += wall(b(0, j + 1), b(0, j))
            walls += wall(b(h - 1, j), b(h - 1, j + 1))
            conn += [(b(0, j), t(0, j)), (b(h - 1, j), t(h - 1, j))]
    else:
        for j in range(w - 1):
            walls += wall(b(0, j + 1), b(0, j))  # origin end (i = 0)
            walls += wall(b(h - 1, j), b(h - 1, j + 1))  # insertion end
        for i in range(h - 1):
            walls += wall(b(i, 0), b(i + 1, 0))  # fibre j = 0 side
            walls += wall(b(i + 1, w - 1), b(i, w - 1))  # fibre j = w-1 side
        ring = set()
        for i in range(h):
            for j in range(w):
                if i in (0, h - 1) or j in (0, w - 1):
                    ring.add((b(i, j), t(i, j)))
        conn = sorted(ring)
    tris = np.array(tris + walls, dtype=np.int64)
    arr = lambda x: np.array(x, dtype=np.int64).reshape(-1, 2)  # noqa: E731
    return MuscleGrid(
        w,
        h,
        periodic,
        tris,
        arr(lat_u),
        arr(lon_u),
        arr(lat_l),
        arr(lon_l),
        arr(conn),
        arr(sh_u),
        arr(sh_l),
    )


def ellipse_points(centre, dir_a, dir_b, a: float, b: float, n: int) -> np.ndarray:
    """``(n, 3)`` points of the ellipse ``centre + a cos(phi) dir_a + b sin(phi) dir_b``,
    ``phi = 2 pi k / n`` (counter-clockwise seen from ``dir_a x dir_b``), mm."""
    phi = 2.0 * np.pi * np.arange(n) / n
    return (
        np.asarray(centre)[None]
        + a * np.cos(phi)[:, None] * np.asarray(dir_a)[None]
        + b * np.sin(phi)[:, None] * np.asarray(dir_b)[None]
    )
