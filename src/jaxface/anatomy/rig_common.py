"""What the two rig backends share: the build-time record (:class:`BuildInfo`), the control
accessors of a rig pytree (:class:`RigBase`), the checks of a synthesis' inputs
(:func:`check_activations`, :func:`check_jaw`) and the build steps both builders run the same
way (:func:`muscle_controls`, :func:`eyelid_regions`).

The PBD :class:`~jaxface.anatomy.rig.Rig` and the layered-tissue
:class:`~jaxface.ltw.rig.LTWRig` subclass :class:`RigBase`; their build records
(:class:`~jaxface.anatomy.rig.RigInfo`, :class:`~jaxface.ltw.rig.LTWInfo`) subclass
:class:`BuildInfo`. Units: mm, degrees (eyelid angles).
"""

from __future__ import annotations

from typing import Any, ClassVar, cast

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import RigError
from ..mesh import TriMesh
from .frame import FaceFrame
from .jaw import JawPose
from .muscle_map import MuscleSpec, load_muscle_map
from .skin import eyelid_vertices

__all__ = [
    "BuildInfo",
    "RigBase",
    "check_activations",
    "check_jaw",
    "eyelid_regions",
    "muscle_controls",
]


class BuildInfo:
    """Build-time (NumPy) objects of a rig, kept for inspection and pictures. Compared and
    hashed by identity, so that it can sit in a static field of a rig pytree (jit caches on
    it without comparing meshes).

    Attributes (every backend): skin: the rest skin :class:`~jaxface.mesh.TriMesh` (mm);
    landmarks: the landmarks used; frame: the :class:`~jaxface.anatomy.frame.FaceFrame`;
    skull: the :class:`~jaxface.anatomy.skull.Skull`; placed: the
    :class:`~jaxface.anatomy.muscle_map.PlacedMuscle` list; specs: the
    :class:`~jaxface.anatomy.muscle_map.MuscleSpec` list. A backend's subclass names its own
    further attributes; the constructor takes any keywords.
    """

    skin: TriMesh
    landmarks: Any
    frame: Any
    skull: Any
    placed: Any
    specs: Any

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def __hash__(self):
        return id(self)

    def __eq__(self, other):
        return self is other


class RigBase:
    """The control accessors every rig pytree shares (the
    :class:`~jaxface.anatomy.interface.FaceRig` members that do not depend on the simulator).

    A mixin, listed before :class:`equinox.Module`: ``class Rig(RigBase, eqx.Module)``. It is
    not a dataclass and declares no field, so each rig's field order, ``__init__`` and pytree
    layout are its own. The rig declares the fields ``muscle_names`` and ``muscle_aus``
    (static tuples: the order of the activation vector, and the AUs of each control) and
    ``info`` (static :class:`BuildInfo`), sets the class attribute ``backend`` and provides
    ``n_vertices``, ``rest`` and ``synthesize``.
    """

    backend: ClassVar[str]
    muscle_names: tuple
    muscle_aus: tuple
    info: BuildInfo

    @property
    def n_controls(self) -> int:
        """Number of activations ``M``."""
        return len(self.muscle_names)

    @property
    def triangles(self) -> np.ndarray:
        """``(F, 3)`` skin triangles (vertex indices of :attr:`rest`)."""
        return self.info.skin.triangles

    def index(self, name: str) -> int:
        """Index of a control in the activation vector (RigError listing the names if unknown)."""
        try:
            return self.muscle_names.index(name)
        except ValueError:
            raise RigError(
                f"unknown muscle {name!r}; the rig's controls are {list(self.muscle_names)}."
            ) from None

    def activations(self, values: dict | None = None, **kw) -> jax.Array:
        """``(M,)`` activation vector from ``{name: value}`` and/or keywords (others 0;
        a keyword wins over the same name in ``values``)."""
        a = np.zeros(self.n_controls)
        for k, v in {**(values or {}), **kw}.items():
            a[self.index(k)] = float(v)
        return jnp.asarray(a)


def check_activations(rig: RigBase, activations) -> jax.Array:
    """``activations`` as a floating ``(M,)`` array (an integer array becomes the default
    float type).

    Raises:
        RigError: not of shape ``(rig.n_controls,)`` (a batch: use ``jax.vmap``).
    """
    a = jnp.asarray(activations)
    if a.ndim != 1 or a.shape[0] != rig.n_controls:
        raise RigError(
            f"activations must have shape ({rig.n_controls},) ordered as rig.muscle_names; got "
            f"{tuple(a.shape)}. Use jax.vmap for batches."
        )
    if not jnp.issubdtype(a.dtype, jnp.floating):
        a = a.astype(jnp.result_type(float))
    return a


def check_jaw(jaw) -> JawPose:
    """``jaw``, or the neutral :class:`~jaxface.anatomy.jaw.JawPose` when None.

    Raises:
        RigError: ``jaw`` is neither None nor a JawPose.
    """
    if jaw is None:
        return JawPose()
    if not isinstance(jaw, JawPose):
        raise RigError(f"jaw must be a JawPose, got {type(jaw).__name__}.")
    return jaw


def muscle_controls(muscle_map) -> tuple[list[MuscleSpec], list[MuscleSpec], tuple[str, ...]]:
    """The specs of a muscle map and the rig controls they give.

    Args:
        muscle_map: path of a muscle-map JSON, a list of :class:`MuscleSpec`, or None (the
            packaged default map).

    Returns:
        ``(specs, controls, names)``: every spec; the active ones (one control each, in
        the order of the activation vector); their names.

    Raises:
        RigError: a list that holds something other than MuscleSpecs, or a malformed map.
        DataNotFoundError: a map path that does not exist.
    """
    if isinstance(muscle_map, (list, tuple)):
        specs = list(muscle_map)
        if not all(isinstance(s, MuscleSpec) for s in specs):
            raise RigError("muscle_map must be a path, None, or a list of MuscleSpec.")
    else:
        specs = load_muscle_map(muscle_map)
    controls = [s for s in specs if s.active]
    return specs, controls, tuple(s.name for s in controls)


def eyelid_regions(
    mesh: TriMesh,
    frame: FaceFrame,
    controls: list[MuscleSpec],
    placed: list,
    threshold: float,
) -> list[tuple]:
    """The eyelid regions of a face (thesis sec. 5.5.1): one per eye that some control
    rotates, left first.

    Args:
        mesh: the skin (mm); frame: its face frame.
        controls: the active specs, in the order of the activation vector (``M`` of them).
        placed: the placed muscles (an eyelid's gives the lid pivot and axis).
        threshold: normalised geodesic size of the lid regions
            (:func:`~jaxface.anatomy.skin.eyelid_vertices`).

    Returns:
        ``[(ids (K,), falloff (K,), upper (K,) bool, side_index, pivot (3,) mm, axis (3,),
        angles (M, 2) degrees)]``, where ``angles[c] = (upper, lower)`` is the lid rotation of
        control ``c`` at activation 1 (0 for a control that does not move this lid).
    """
    ci = {s.name: i for i, s in enumerate(controls)}
    regions = []
    for side in ("left", "right"):
        angles = np.zeros((len(controls), 2))
        for s in controls:
            if s.kind == "eyelid" and s.side == side and s.angles_deg:
                angles[ci[s.name]] = (
                    float(s.angles_deg.get("upper", 0.0)),
                    float(s.angles_deg.get("lower", 0.0)),
                )
        if not np.any(angles):
            continue
        ids, fall, upper = eyelid_vertices(mesh, frame, side, threshold)
        pm = next(p for p in placed if p.kind == "eyelid" and p.spec.side == side)
        axes = cast(np.ndarray, pm.axes)  # an eyelid's placement always has its axes
        regions.append((ids, fall, upper, len(regions), pm.centre, axes[0], angles))
    return regions
