"""The face rig: :func:`build_rig` assembles skull, jaw, muscles and skin for one face, and
:func:`synthesize` turns muscle activations and a jaw pose into the deformed skin.

Forward model (thesis sec. 5.7, quasi-static):

1. the jaw pose gives the rigid motion of the mandible and lower teeth (:mod:`.jaw`); the
   tissue attached to the skull follows it with the weights of :func:`jaw_follow_weights`;
2. the muscles are solved (:func:`jaxface.anatomy.muscles.solve_muscles`): action lines
   re-sampled with the activations, layers deepest first, thesis constraints;
3. the skin anchors are refreshed from the surface points they are bound to, averaged over the
   tissue footprint and weighted by the influence map; eyelids rotate; optional cheek puff;
4. the skin is solved (:func:`jaxface.anatomy.skin.solve_skin`) with the thesis constraints and
   the teeth collisions.

:func:`synthesize` is jit-compiled (``eqx.filter_jit``), works under ``jax.vmap`` over batches
of activations / jaw poses, and is differentiable in forward and reverse mode with respect to
the activations, the jaw pose and the cheek puff. :func:`simulate` runs the dynamic version
(time steps of 16.6 ms with damping 0.2) for animation.

Units: mm, degrees (jaw angles); +y up, +z forward, subject's left +x.

Layout: :mod:`.rig_synth` (:class:`Rig`, synthesis, simulation), :mod:`.rig_build`
(:func:`build_rig`, the ``pbd`` backend, :func:`jaw_follow_weights`); every name is
re-exported here.
"""

from __future__ import annotations

from .rig_build import build_rig, jaw_follow_weights
from .rig_config import (
    FAT_VOLUME,
    FOOTPRINT_CLUSTER_MM,
    FOOTPRINT_MM,
    JAW_FOLLOW_MM,
    PBDRigConfig,
)
from .rig_synth import (
    Rig,
    RigInfo,
    SynthState,
    equilibrium_gap,
    simulate,
    synthesize,
    synthesize_state,
)

__all__ = [
    "FAT_VOLUME",
    "FOOTPRINT_CLUSTER_MM",
    "FOOTPRINT_MM",
    "JAW_FOLLOW_MM",
    "PBDRigConfig",
    "Rig",
    "RigInfo",
    "SynthState",
    "build_rig",
    "equilibrium_gap",
    "jaw_follow_weights",
    "synthesize",
    "synthesize_state",
    "simulate",
]
