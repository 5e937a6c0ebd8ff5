"""The :class:`Morph` (an ``eqx.Module``: centres, weights and affine part; jit-able, chunked
evaluation in mm) and the NumPy helpers :func:`warp_points` / :func:`warp_mesh`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._parallel import thread_map
from ..errors import RBFError
from ..mesh import TriMesh
from .kernels import _kernel_np, _sqdist, _sqdist_np, kernel_values

__all__ = ["Morph", "warp_points", "warp_mesh"]

# the largest (points x centres) block evaluated at once
_MAX_BLOCK_ELEMENTS = 1 << 21
_PARALLEL_MIN_ELEMENTS = 1 << 20  # Morph.apply_np: below this, threads cost more than they save


# --------------------------------------------------------------------------------------
# the morph
# --------------------------------------------------------------------------------------
class Morph(eqx.Module):
    """A fitted RBF morph ``G: R^3 -> R^3`` (mm -> mm). Build it with :func:`fit`.

    Attributes:
        centres: ``(n, 3)`` source centres ``P_i``, mm (after duplicate merging).
        targets: ``(n, 3)`` their images ``Q_i``, mm.
        weights: ``(n, 3)`` kernel coefficients ``w_i`` (mm per kernel unit).
        affine: ``(4, 3)`` affine coefficients acting on ``[1, (p - shift) / scale]``.
        shift: ``(3,)`` centroid of the centres, mm.
        scale: ``()`` RMS radius of the centres about ``shift``, mm.
        radii2: ``(n,)`` squared stiffness radii in the normalised frame (multiquadric;
            zeros otherwise).
        kernel: kernel name (static).

    Arrays are JAX from :func:`fit`, NumPy from :func:`fit_numpy`.
    """

    centres: jax.Array | np.ndarray
    targets: jax.Array | np.ndarray
    weights: jax.Array | np.ndarray
    affine: jax.Array | np.ndarray
    shift: jax.Array | np.ndarray
    scale: jax.Array | np.ndarray
    radii2: jax.Array | np.ndarray
    kernel: str = eqx.field(static=True)

    @property
    def n_centres(self) -> int:
        return int(self.centres.shape[0])

    def _normalised_centres(self):
        return (self.centres - self.shift) / self.scale

    def _eval_block(self, x, cn):
        """x: (m, 3) mm -> (m, 3) mm."""
        xn = (x - self.shift) / self.scale
        kx = kernel_values(self.kernel, _sqdist(xn, cn), self.radii2)
        return kx @ self.weights + self.affine[0] + xn @ self.affine[1:]

    def __call__(self, points, chunk_size: int = 65536):
        """Evaluate the morph.

        Arguments:
            points: ``(..., 3)`` points, mm.
            chunk_size: the most points evaluated at once (static). It is further capped so
                that one chunk's ``(points x centres)`` kernel block holds at most 2M entries.

        Returns:
            ``(..., 3)`` morphed points, mm. Jit-able; differentiable with respect to
            ``points`` and to the morph's arrays (hence to ``fit``'s ``src``/``dst``).
        """
        points = jnp.asarray(points)
        if points.shape[-1] != 3:
            raise RBFError(f"points must have shape (..., 3) in mm, got {points.shape}.")
        n = max(self.n_centres, 1)
        chunk = int(max(1, min(int(chunk_size), max(256, _MAX_BLOCK_ELEMENTS // n))))
        return _evaluate(self, points, chunk)

    def displacement(self, points, chunk_size: int = 65536):
        """``G(p) - p`` for ``(..., 3)`` points, mm."""
        return self(points, chunk_size=chunk_size) - jnp.asarray(points)

    def apply_np(self, points, chunk_size: int = 65536) -> np.ndarray:
        """NumPy evaluation (no tracing, no compilation) of ``(..., 3)`` points, mm -> mm.

        Same function as :meth:`__call__`; for build-time code on concrete arrays.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1] != 3:
            raise RBFError(f"points must have shape (..., 3) in mm, got {pts.shape}.")
        lead = pts.shape[:-1]
        x = pts.reshape(-1, 3)
        shift = np.asarray(self.shift, np.float64)
        scale = float(self.scale)
        cn = (np.asarray(self.centres, np.float64) - shift) / scale
        W = np.asarray(self.weights, np.float64)
        A = np.asarray(self.affine, np.float64)
        c2 = np.asarray(self.radii2, np.float64)
        n = max(cn.shape[0], 1)
        # blocks of about 1 M kernel values stay in cache (2x faster than 4x larger blocks)
        chunk = int(max(1, min(int(chunk_size), max(256, (_MAX_BLOCK_ELEMENTS // 2) // n))))
        out = np.empty_like(x)
        smooth = self.kernel == "multiquadric"  # r_i > 0: no precision loss near r = 0
        cc = np.einsum("ij,ij->i", cn, cn)
        cnT = np.ascontiguousarray(cn.T)

        def block(s):
            xn = (x[s : s + chunk] - shift) / scale
            if smooth:  # sqrt(max(|x|^2 + |c|^2 - 2 x.c, 0) + r_i^2), in place
                kx = xn @ cnT
                kx *= -2.0
                kx += np.einsum("ij,ij->i", xn, xn)[:, None]
                kx += cc[None, :]
                np.maximum(kx, 0.0, out=kx)
                kx += c2[None, :]
                np.sqrt(kx, out=kx)
            else:
                kx = _kernel_np(self.kernel, _sqdist_np(xn, cn), c2)
            out[s : s + chunk] = kx @ W + A[0] + xn @ A[1:]

        starts = range(0, x.shape[0], chunk)
        if x.shape[0] * n >= _PARALLEL_MIN_ELEMENTS:
            thread_map(block, starts)  # NumPy releases the GIL in these kernels
        else:
            for s in starts:
                block(s)
        return out.reshape(*lead, 3)

    def affine_part(self):
        """The affine part ``p -> M p + t`` in mm: returns ``(M (3, 3), t (3,))``."""
        M = (self.affine[1:] / self.scale).T
        t = self.affine[0] - M @ self.shift
        return M, t


@eqx.filter_jit
def _evaluate(morph: Morph, points, chunk: int):
    lead = points.shape[:-1]
    dtype = jnp.result_type(points.dtype, morph.weights.dtype)
    x = points.reshape(-1, 3).astype(dtype)
    m = x.shape[0]
    cn = morph._normalised_centres()
    if m <= chunk:
        out = morph._eval_block(x, cn)
    else:
        n_chunks = -(-m // chunk)
        pad = n_chunks * chunk - m
        xp = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, 3))], axis=0) if pad else x
        out = jax.lax.map(lambda xc: morph._eval_block(xc, cn), xp.reshape(n_chunks, chunk, 3))
        out = out.reshape(n_chunks * chunk, 3)[:m]
    return out.reshape(*lead, 3)


# --------------------------------------------------------------------------------------
# NumPy helpers
# --------------------------------------------------------------------------------------
def warp_points(morph: Morph, points) -> np.ndarray:
    """Apply ``morph`` to ``(..., 3)`` points (mm) with NumPy; returns float64 mm."""
    return morph.apply_np(points)


def warp_mesh(morph: Morph, mesh):
    """Return a new :class:`jaxface.mesh.TriMesh` whose vertices are ``morph(mesh.vertices)``
    (mm) with the same triangles. Accepts a ``TriMesh`` or a ``trimesh.Trimesh``."""
    tris = mesh.triangles if hasattr(mesh, "triangles") else mesh.faces
    return TriMesh(morph.apply_np(np.asarray(mesh.vertices)), np.asarray(tris), validate=False)
