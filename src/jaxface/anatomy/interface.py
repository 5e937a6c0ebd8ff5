"""The rig interface both simulation backends implement, their config objects, and the
registry :func:`jaxface.anatomy.rig.build_rig` dispatches through.

* :class:`FaceRig`: what a rig provides to the fit, the command line and the exporters,
  whatever simulates it: the controls (``muscle_names``, ``muscle_aus``, ``n_controls``), the
  rest skin (``rest`` ``(V, 3)`` mm, ``triangles`` ``(F, 3)``), the jaw model, the build-time
  objects (``info``: skin, landmarks, frame, skull, placed muscles, specs) and a
  quasi-static ``synthesize(activations (M,), jaw, cheek_puff) -> (V, 3)`` mm. The PBD
  :class:`~jaxface.anatomy.rig.Rig` and the layered-tissue
  :class:`~jaxface.ltw.rig.LTWRig` both satisfy it (``isinstance(rig, FaceRig)``); what
  they share is implemented once in :mod:`jaxface.anatomy.rig_common` (``RigBase``,
  ``BuildInfo``).
* :class:`RigConfig`: base of the per-backend option objects
  (:class:`~jaxface.anatomy.rig_config.PBDRigConfig`, :class:`~jaxface.ltw.rig.LTWRigConfig`).
* :func:`register_backend` / :func:`rig_backend`: each backend module registers its config
  type and builder when it is imported. The anatomy layer never imports the LTW backend
  (which depends on it); :func:`rig_backend` loads a backend's module by its registered
  name the first time it is asked for, like a plug-in.

Units: mm, degrees (jaw angles); +y up, +z forward, subject's left +x.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import jax
import numpy as np

from ..errors import RigError, RigOptionError

__all__ = [
    "FaceRig",
    "RigBackend",
    "RigConfig",
    "configure",
    "register_backend",
    "rig_backend",
]


@runtime_checkable
class FaceRig(Protocol):
    """A face rig of either backend (structural type; ``isinstance`` checks the members).

    Attributes:
        backend: ``"pbd"`` or ``"ltw"``.
        muscle_names: the order of the activation vector (the same for both backends built
            from the same muscle map); muscle_aus: the AUs of each control.
        jaw: the :class:`~jaxface.anatomy.jaw.JawModel`.
        info: build-time objects (``skin``, ``landmarks``, ``frame``, ``skull``, ``placed``,
            ``specs``).
    """

    backend: str
    muscle_names: tuple
    muscle_aus: tuple
    jaw: Any
    info: Any

    @property
    def n_controls(self) -> int:
        """Number of activations ``M``."""
        ...

    @property
    def n_vertices(self) -> int:
        """Number of skin vertices ``V``."""
        ...

    @property
    def rest(self) -> jax.Array:
        """``(V, 3)`` rest skin, mm."""
        ...

    @property
    def triangles(self) -> np.ndarray:
        """``(F, 3)`` skin triangles."""
        ...

    def index(self, name: str) -> int:
        """Index of a control in the activation vector (RigError if unknown)."""
        ...

    def activations(self, values: dict | None = None, **kw) -> jax.Array:
        """``(M,)`` activation vector from ``{name: value}`` (others 0)."""
        ...

    def synthesize(self, activations, jaw=None, cheek_puff=0.0) -> jax.Array:
        """Quasi-static synthesis: ``(M,)`` activations in [0, 1], a
        :class:`~jaxface.anatomy.jaw.JawPose` (neutral if None) and the cheek puff in [0, 1]
        (or ``[left, right]``) -> ``(V, 3)`` skin, mm. Jit-compiled, vmap- and grad-able."""
        ...


@dataclass(frozen=True)
class RigConfig:
    """Base of the backend-specific rig options (a frozen dataclass per backend; every field
    has the backend's default). ``backend`` names the backend the options are for."""

    backend: ClassVar[str] = ""

    def options(self) -> dict[str, Any]:
        """``{field name: value}``, shallow (the keyword arguments of the backend's builder)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class RigBackend:
    """A registered backend: its name, its config type and its builder
    ``build(skin, landmarks, skull, muscle_map, config) -> FaceRig``."""

    name: str
    config_type: type[RigConfig]
    build: Callable[..., Any]


#: Module of each known backend; it calls :func:`register_backend` when imported.
BACKEND_MODULES: dict[str, str] = {"pbd": "jaxface.anatomy.rig", "ltw": "jaxface.ltw.rig"}

_REGISTRY: dict[str, RigBackend] = {}


def register_backend(name: str, config_type: type[RigConfig], build: Callable[..., Any]) -> None:
    """Register a backend (called by the backend's own module when it is imported)."""
    _REGISTRY[name] = RigBackend(name, config_type, build)


def rig_backend(name: str) -> RigBackend:
    """The registered backend ``name``, importing its module on first use.

    Raises:
        RigError: an unknown backend, or one whose module cannot be imported.
    """
    if name not in _REGISTRY:
        module = BACKEND_MODULES.get(name) if isinstance(name, str) else None
        if module is None:
            raise RigError(f"unknown backend {name!r}; use one of {sorted(BACKEND_MODULES)}.")
        try:
            importlib.import_module(module)
        except ImportError as e:  # pragma: no cover - depends on the installation
            raise RigError(f"the {name} backend is not available ({e}).") from None
    return _REGISTRY[name]


def configure(
    backend: RigBackend, config: RigConfig | None, options: Mapping[str, Any]
) -> RigConfig:
    """The config a build runs with: ``config`` (or the backend's defaults) with the keyword
    ``options`` that were given (not None) laid over it.

    Raises:
        RigOptionError: ``config`` is another backend's config, or an option is not one of
            the backend's (named, with the backend's config type to use instead).
    """
    ctype = backend.config_type
    if config is not None and not isinstance(config, ctype):
        raise RigOptionError(
            f"config is a {type(config).__name__}, which does not configure the "
            f"{backend.name!r} backend; give a {ctype.__name__} (or backend="
            f"{getattr(config, 'backend', '?')!r}).",
            backend=backend.name,
            options=("config",),
        )
    names = {f.name for f in dataclasses.fields(ctype)}
    given = {k: v for k, v in options.items() if v is not None}
    bad = sorted(k for k in given if k not in names)
    if bad:
        raise RigOptionError(
            f"option(s) {', '.join(bad)} do not apply to the {backend.name!r} backend and "
            f"would be ignored; its options are those of {ctype.__name__}: "
            f"{', '.join(sorted(names))}.",
            backend=backend.name,
            options=bad,
        )
    base = config if config is not None else ctype()
    return dataclasses.replace(base, **given) if given else base
