"""The exact forward model: the rig's quasi-static synthesis, ``(a (M,), jaw (3,)) -> (V, 3)`` mm.

The fit's controls ``a`` are the rig's muscle activations, followed, by default, by the two
cheeks' pressures :data:`jaxface.anatomy.cheek_puff.PUFF_CONTROLS` (AU34), all in [0, 1].

The fit evaluates it once per scan and outer iteration (the defect of the reduced model, and
with the gradient correction one reverse-mode pass through it), and, with
``FitOptions.exact_steps``, differentiates it in forward mode.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..anatomy.cheek_puff import PUFF_CONTROLS
from ..anatomy.interface import FaceRig
from ..anatomy.jaw import JawPose
from ..errors import FitError, RigError
from ..validate import traced_checks

__all__ = ["ForwardModel", "synthesis_function", "exact_skin_and_vjp"]


def synthesis_function(rig: FaceRig, cheek_puff: bool = False) -> Callable:
    """``(a (M,), jaw (3,)) -> (V, 3)`` mm for a rig of either backend (a PBD
    :class:`~jaxface.anatomy.rig.Rig` or an LTW :class:`~jaxface.ltw.rig.LTWRig`: its
    :meth:`~jaxface.anatomy.interface.FaceRig.synthesize`).

    With ``cheek_puff``, ``a`` has ``rig.n_controls + 2`` entries: the muscles, then the left
    and right cheeks' pressures (:data:`~jaxface.anatomy.cheek_puff.PUFF_CONTROLS`), passed
    to the rig as ``cheek_puff=[left, right]``.

    Traced without the rig's run-time input check (:func:`jaxface.validate.traced_checks`):
    a program that contains it has a host callback, and JAX never keeps such a program in its
    persistent compilation cache. The callers check their inputs on the host
    (:class:`ForwardModel`), and the fit's solvers keep their controls finite and bounded;
    a non-finite input gives a NaN skin."""

    M = int(rig.n_controls)

    def fn(a, j):
        with traced_checks(False):
            if cheek_puff:
                return rig.synthesize(a[:M], JawPose.from_array(j), a[M:])
            return rig.synthesize(a, JawPose.from_array(j))

    return fn


def _check_finite(a, jaw) -> None:
    """Refuse non-finite controls before a compiled synthesis (RigError)."""
    if not (np.all(np.isfinite(np.asarray(a))) and np.all(np.isfinite(np.asarray(jaw)))):
        raise RigError(
            "NaN or inf in the activations or the jaw pose of a synthesis; give finite numbers."
        )


def exact_skin_and_vjp(exact_fn, a, jaw):
    """The exact rig's skin ``(V, 3)`` mm at ``(a (M,), jaw (3,))`` and its VJP (a pytree:
    it can leave a ``jit`` and be called in another): the one forward pass that both the
    correspondences and :func:`jaxface.fit.residuals.gradient_correction_from_vjp` of an outer
    iteration use."""
    return jax.vjp(exact_fn, a, jaw)


_exact_vjp_jit = eqx.filter_jit(exact_skin_and_vjp)


class ForwardModel:
    """The rig's quasi-static synthesis, jit-compiled once with the rig closed over.

    Arguments:
        rig: a :class:`jaxface.anatomy.rig.Rig` (or an LTW rig), mm.
        chunk: how many syntheses :meth:`many` dispatches before it waits for their results.
        cheek_puff: the two cheeks' pressures are controls too, after the muscles
            (:func:`synthesis_function`).

    ``muscle_names`` are the names of the fit's controls (the rig's muscles, then
    :data:`~jaxface.anatomy.cheek_puff.PUFF_CONTROLS` with ``cheek_puff``); ``n_controls``
    is their number.

    Calling ``model(a (M,), jaw (3,))`` returns the ``(V, 3)`` skin in mm (NumPy); ``fn`` is
    the same synthesis un-jitted (for tracing it inside other functions). :meth:`many`
    evaluates a batch one synthesis at a time through the same compiled function, so any
    batch size costs one compilation and no padding (on a CPU a ``vmap`` of the PBD solve is
    slower per item than this loop).

    Every entry point checks its inputs on the host and raises
    :class:`~jaxface.errors.RigError` for NaN or inf; the compiled programs carry no host
    callback, so JAX's persistent compilation cache keeps them between processes.
    """

    def __init__(self, rig, *, chunk: int = 8, cheek_puff: bool = False):
        self.rig = rig
        self.cheek_puff = bool(cheek_puff)
        self.muscle_names = tuple(rig.muscle_names) + (PUFF_CONTROLS if cheek_puff else ())
        self.n_controls = len(self.muscle_names)
        self.chunk = int(chunk)
        fn = synthesis_function(rig, self.cheek_puff)
        self.fn = fn
        self._one = jax.jit(fn)
        self.calls = 0
        self._count_lock = threading.Lock()  # with_vjp runs on several threads in a batch

    def _count(self, n: int = 1) -> None:
        with self._count_lock:
            self.calls += n

    @property
    def triangles(self) -> np.ndarray:
        return np.asarray(self.rig.triangles)

    @property
    def rest(self) -> np.ndarray:
        return np.asarray(self.rig.rest)

    def __call__(self, a, jaw) -> np.ndarray:
        _check_finite(a, jaw)
        self._count()
        dt = jnp.result_type(float)  # float64 when x64 is enabled, else float32
        return np.asarray(self._one(jnp.asarray(a, dt), jnp.asarray(jaw, dt)))

    def with_vjp(self, a, jaw):
        """The skin ``(V, 3)`` mm (a JAX array) at ``a (M,)``, ``jaw (3,)`` and its VJP
        (:func:`exact_skin_and_vjp`, compiled once): one synthesis, counted in ``calls``."""
        _check_finite(a, jaw)
        self._count()
        dt = jnp.result_type(float)
        return _exact_vjp_jit(self.fn, jnp.asarray(a, dt), jnp.asarray(jaw, dt))

    def many(self, A, J) -> np.ndarray:
        """``(B, V, 3)`` mm for activations ``(B, M)`` and jaw poses ``(B, 3)``."""
        A = np.asarray(A, np.float64).reshape(-1, self.n_controls)
        J = np.asarray(J, np.float64).reshape(-1, 3)
        if len(A) != len(J):
            raise FitError(
                f"many() needs one jaw pose per activation row; got {len(J)} jaw poses for "
                f"{len(A)} rows."
            )
        _check_finite(A, J)
        dt = jnp.result_type(float)  # float64 when x64 is enabled, else float32
        out = np.zeros((len(A), len(self.rest), 3))
        step = max(self.chunk, 1)
        for s in range(0, len(A), step):
            # dispatch a chunk asynchronously, then collect it
            pending = [
                self._one(jnp.asarray(a, dt), jnp.asarray(j, dt))
                for a, j in zip(A[s : s + step], J[s : s + step])
            ]
            for n, x in enumerate(pending):
                out[s + n] = np.asarray(x)
            self._count(len(pending))
        return out
