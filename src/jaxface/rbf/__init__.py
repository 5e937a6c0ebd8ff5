"""Radial-basis-function volume morphs: Hardy multiquadric and thin-plate splines.

A morph is a smooth map ``G: R^3 -> R^3`` (millimetres in, millimetres out) that sends each
source centre ``P_i`` onto its target ``Q_i`` (thesis sec. 3.4, eqs. 3.26-3.35; Erdoğdu 2010,
eqs. 4.11-4.19)::

    G(p) = sum_i w_i U_i(|p - P_i|) + A^T [1, p]        w_i in R^3, A in R^{4x3}

with the linear-precision side conditions ``sum_i w_i = 0`` and ``sum_i w_i P_i^T = 0`` that
make the affine part absorb every affine component of the correspondence. Fitting solves the
one ``(n+4) x (n+4)`` saddle-point system

    [[K + reg I, P], [P^T, 0]] [W; A] = [Q; 0].

Kernels (``r`` = distance to the centre):

* ``"multiquadric"``: Hardy, ``U_i(r) = sqrt(r^2 + r_i^2)`` with the stiffness radius ``r_i``
  the distance from ``P_i`` to its nearest other centre (eq. 3.30), times ``radius_scale``;
* ``"tps"``: ``U(r) = r^2 log r^2`` (the kernel Erdoğdu uses in 3D);
* ``"biharmonic"``: ``U(r) = r``, the fundamental solution of the biharmonic operator in 3D.

Every kernel is NaN-safe at ``r = 0`` in value and gradient (double ``where``).

Numerics: centres and evaluation points are mapped to a normalised frame (centred on the
centroid of the centres, divided by their RMS radius) before the kernel is applied; this makes
the system well scaled whatever the unit. The interpolant is the same function as in the raw
frame for all three kernels (for TPS the ``log`` of the scale adds a multiple of ``r^2``, which
the side conditions turn into an affine term). ``reg`` is measured in that normalised frame
(a kernel of a unit-radius cloud is O(1)), so it means the same for a nose and for a head.

:func:`fit` validates its inputs when they are concrete (too few centres, coplanar centres,
duplicated centres, shape mismatch, NaN/inf) and raises :class:`~jaxface.errors.RBFError`;
under ``jax.jit``/``jax.grad`` tracing the checks that need values are skipped. The returned
:class:`Morph` is an ``eqx.Module`` whose ``__call__`` is jit-able and differentiable with
respect to the evaluated points and (through :func:`fit`) the centres and their targets; it
evaluates in fixed-size chunks with ``lax.map`` so that a million points fit in memory.

NumPy-side helpers (:func:`fit_numpy`, :meth:`Morph.apply_np`, :func:`warp_points`,
:func:`warp_mesh`) run the same algebra with NumPy/SciPy, without tracing or compilation, for
build-time code (mesh fitting, motion cloning) that solves many differently-sized systems.

Layout: :mod:`.kernels` (kernels), :mod:`.morph` (:class:`Morph`, NumPy warps), :mod:`.checks`
(input validation), :mod:`.fitting` (:func:`fit`, :func:`fit_numpy`).
"""

from __future__ import annotations

from .checks import find_duplicates
from .fitting import fit, fit_numpy
from .kernels import KERNELS, kernel_values
from .kernels import KernelName as KernelName  # not in __all__ (as before), still importable
from .morph import _PARALLEL_MIN_ELEMENTS as _PARALLEL_MIN_ELEMENTS  # read by tests/rbf/test_rbf.py
from .morph import Morph, warp_mesh, warp_points

__all__ = [
    "KERNELS",
    "Morph",
    "fit",
    "fit_numpy",
    "find_duplicates",
    "warp_points",
    "warp_mesh",
    "kernel_values",
]
