"""Input checks at the rig's public entry points: :func:`jaxface.anatomy.build_rig` and
:func:`jaxface.anatomy.synthesize` (applied there as decorators, one line each).

``synthesize`` (controls):

* concrete inputs (NumPy / JAX arrays, Python numbers: the normal call) are checked in
  Python before the jit-compiled body runs: NaN/inf in the activations, the jaw pose or the
  cheek puff, activations outside the documented ``[0, 1]`` (beyond :data:`RANGE_TOL`) and a
  cheek puff outside ``[0, 1]`` raise :class:`jaxface.errors.RigError` naming the first
  offending control. Out-of-range values are refused, not clamped: a 5 or a -1 is a caller's
  bug (a percentage, a sign) that a clamp would hide. The jaw pose needs no range check: the
  jaw model clamps it smoothly to its limits (documented there).
* traced inputs (the call sits inside the caller's ``jax.jit`` / ``vmap`` / ``grad``, as in
  the fit) cannot be inspected in Python; there :func:`equinox.error_if` makes the compiled
  call fail at run time when an activation, the jaw pose or the cheek puff is NaN/inf: under
  ``equinox.filter_jit`` an ``EquinoxRuntimeError`` whose message starts with ``RigError:``;
  under a plain ``jax.jit`` JAX wraps the same message in a ``JaxRuntimeError`` or
  ``ValueError`` about a failed callback. Ranges are not checked under tracing: a fit keeps
  its controls within its own bounds.

  The run-time check is a host callback, and JAX never writes a program with a host callback
  to its persistent compilation cache. A caller that checks its inputs on the host itself
  traces the synthesis inside ``with traced_checks(False):`` (the fit's
  :class:`~jaxface.fit.forward.ForwardModel` does): the compiled program then has no
  callback, a non-finite input gives a NaN skin, and the program can be cached on disk.

``build_rig`` (the skin): a :class:`~jaxface.mesh.TriMesh` (or a head with ``.mesh``) with
NaN/inf vertices (count and first id), more than
:data:`jaxface.hygiene.MAX_RIG_VERTICES` vertices, or an unwelded triangle soup (more than
:data:`MAX_DUPLICATE_SHARE` of the vertices repeat another's position) is refused with a
:class:`~jaxface.errors.MeshError` that says what to do (:func:`jaxface.hygiene.clean_mesh`
welds and drops what a file loader should).

The speed cost of these checks: ``benchmarks/bench_checks.py``.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .errors import MeshError, RigError
from .hygiene import MAX_RIG_VERTICES
from .mesh import TriMesh, check_finite_vertices

__all__ = [
    "RANGE_TOL",
    "MAX_DUPLICATE_SHARE",
    "check_controls",
    "check_skin",
    "checked_build",
    "checked_controls",
    "traced_checks",
]

#: Tolerance of the activation/cheek-puff range check (rounding of a value computed in
#: float32 that should be 0 or 1).
RANGE_TOL = 1e-6

#: A skin where more than this share of the vertices sit on another vertex's position is an
#: unwelded triangle soup (a welded face has none; the default head and the ICT face: 0).
MAX_DUPLICATE_SHARE = 0.05

_TRACED_CHECKS: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "jaxface_traced_checks", default=True
)


@contextlib.contextmanager
def traced_checks(enabled: bool) -> Iterator[None]:
    """Turn the run-time check of traced controls (:func:`equinox.error_if`, see the module
    doc) on or off for what is traced inside the ``with`` block (this thread/context only).
    Concrete inputs are always checked."""
    token = _TRACED_CHECKS.set(bool(enabled))
    try:
        yield
    finally:
        _TRACED_CHECKS.reset(token)


_TRACER_ERRORS = (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError)


def _concrete(x):
    """``x`` as a NumPy array, or None when it is a tracer (inside a transformation)."""
    try:
        return np.asarray(x)
    except _TRACER_ERRORS:
        return None


def _jaw_leaves(jaw) -> list:
    if jaw is None:
        return []
    return [getattr(jaw, f, None) for f in ("pitch_deg", "yaw_deg", "protrusion_mm")]


def check_controls(names, activations, jaw=None, cheek_puff: ArrayLike = 0.0):
    """Check the controls of a synthesis (see the module doc).

    Args:
        names: the rig's control names (for messages). activations: ``(M,)``.
        jaw: a :class:`jaxface.anatomy.jaw.JawPose` or None. cheek_puff: in [0, 1], a number
            or ``[left, right]``.

    Returns:
        ``activations``, unchanged when concrete, or wrapped by :func:`equinox.error_if`
        (same values) when traced.

    Raises:
        RigError: concrete NaN/inf or out-of-range values.
    """
    leaves = [("cheek_puff", cheek_puff)] + [
        (f"jaw.{f}", v)
        for f, v in zip(("pitch_deg", "yaw_deg", "protrusion_mm"), _jaw_leaves(jaw))
        if v is not None
    ]
    a_np = _concrete(activations)
    conc = [(k, _concrete(v)) for k, v in leaves]
    if a_np is not None and all(c is not None for _, c in conc):
        if a_np.dtype.kind in "fciu":
            a_f = a_np.astype(np.float64).reshape(-1)
            bad = np.flatnonzero(~np.isfinite(a_f))
            if bad.size:
                raise RigError(
                    f"{bad.size} activation(s) are NaN or inf (first: {_name(names, bad[0])}); "
                    "give numbers in [0, 1]."
                )
            out = np.flatnonzero((a_f < -RANGE_TOL) | (a_f > 1.0 + RANGE_TOL))
            if out.size:
                i = int(out[0])
                raise RigError(
                    f"{out.size} activation(s) outside [0, 1] (first: {_name(names, i)} = "
                    f"{a_f[i]:g}); activations are fractions of the full contraction, in [0, 1]."
                )
        for k, c in conc:
            c = np.asarray(c, dtype=np.float64)
            if not np.all(np.isfinite(c)):
                raise RigError(f"{k} is NaN or inf; give a finite number.")
        p = np.asarray(conc[0][1], dtype=np.float64)
        if np.any(p < -RANGE_TOL) or np.any(p > 1.0 + RANGE_TOL):
            raise RigError(f"cheek_puff = {p.tolist()} is outside [0, 1].")
        return activations
    # traced: a run-time check inside the compiled call
    if not _TRACED_CHECKS.get():
        return activations
    a = jnp.asarray(activations)
    ok = jnp.all(jnp.isfinite(a))
    for _, v in leaves:
        ok = ok & jnp.all(jnp.isfinite(jnp.asarray(v)))
    return eqx.error_if(
        a, ~ok, "RigError: NaN or inf in the activations, jaw pose or cheek puff of a synthesis"
    )


def _name(names, i) -> str:
    i = int(i)
    names = tuple(names or ())
    return f"{names[i]!r} (index {i})" if i < len(names) else f"index {i}"


def checked_controls(fn):
    """Decorator of ``synthesize(rig, activations, jaw=None, cheek_puff=0.0)``: runs
    :func:`check_controls` first (see the module doc)."""

    @functools.wraps(fn)
    def wrapper(rig, activations, jaw=None, cheek_puff: ArrayLike = 0.0, *args, **kwargs):
        activations = check_controls(getattr(rig, "muscle_names", ()), activations, jaw, cheek_puff)
        return fn(rig, activations, jaw, cheek_puff, *args, **kwargs)

    return wrapper


def check_skin(skin, *, max_vertices: int | None = MAX_RIG_VERTICES) -> None:
    """Refuse a skin a rig cannot be built on (see the module doc).

    Args:
        skin: a :class:`TriMesh` or an object with a ``.mesh`` TriMesh (a head); anything
            else is left to ``build_rig``'s own checks.
        max_vertices: the size limit (None: no limit).

    Raises:
        MeshError: ``nonfinite_vertices``, ``too_large`` or ``unwelded``.
    """
    mesh = skin if isinstance(skin, TriMesh) else getattr(skin, "mesh", None)
    if not isinstance(mesh, TriMesh):
        return
    v = mesh.vertices
    check_finite_vertices(v, source="build_rig: the skin:")
    if max_vertices is not None and len(v) > max_vertices:
        raise MeshError(
            f"build_rig: the skin has {len(v)} vertices, more than the limit of {max_vertices} "
            "(about 30 kB of memory per vertex). Decimate it below the limit; the default head "
            "has 12,140.",
            problem="too_large",
        )
    if len(v):
        _, counts = np.unique(v, axis=0, return_counts=True)
        dup = int((counts - 1).sum())
        if dup > MAX_DUPLICATE_SHARE * len(v):
            raise MeshError(
                f"build_rig: {dup} of the skin's {len(v)} vertices repeat another vertex's "
                "position: an unwelded triangle soup, on which a rig cannot be built. Weld it "
                "first: jaxface.hygiene.clean_mesh(mesh) (the command line does this itself).",
                problem="unwelded",
            )


def checked_build(fn):
    """Decorator of ``build_rig(skin, ...)``: runs :func:`check_skin` first."""

    @functools.wraps(fn)
    def wrapper(skin, *args, **kwargs):
        check_skin(skin)
        return fn(skin, *args, **kwargs)

    return wrapper
