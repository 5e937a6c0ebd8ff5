"""Cloning the morph targets (thesis 6.3): the target mapped onto the deformed source, then
each source morph target carried over (:func:`apply_clone`, :func:`clone_motion`,
:class:`CloneResult`, mm)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import numpy as np

from ..errors import MeshError
from ..normals import vertex_normals
from .geometry import SurfaceMap, as_trimesh, map_onto_surface
from .source_fit import FitResult, fit_source_to_target

__all__ = ["CloneResult", "apply_clone", "clone_motion"]


# ------------------------------------------------------------------------------------------
# cloning
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CloneResult:
    """Cloned morph targets and everything needed to reuse or inspect the clone.

    Attributes:
        targets: ``(T, Vt, 3)`` target morph targets (vertex positions), mm.
        deltas: ``(T, Vt, 3)`` the same as displacements from the target neutral, mm.
        names: ``T`` morph-target names (or ``"0"``, ``"1"``, ... when none were given).
        fit: the :class:`FitResult` (the morph ``G``, correspondences, iterations).
        mapping: :class:`SurfaceMap` of the target vertices on the deformed source.
        moving: ``(T, Vs)`` bool, the moving source vertices of each morph target.
        mode: ``"displacement"`` or ``"thesis"``; transfer: ``"morph"``, ``"rough"`` or
            ``"affine"``.
        timings: seconds: ``fit`` (refinement time RT), ``clone`` (mapping + cloning, CT),
            ``total``.
    """

    targets: np.ndarray
    deltas: np.ndarray
    names: tuple[str, ...]
    fit: FitResult
    mapping: SurfaceMap
    moving: np.ndarray
    mode: str
    transfer: str
    timings: dict


def _source_deltas(S0, source_targets, source_deltas):
    if (source_targets is None) == (source_deltas is None):
        raise MeshError(
            "pass exactly one of source_targets ((T, Vs, 3) morph-target positions, mm) or "
            "source_deltas ((T, Vs, 3) displacements from the neutral, mm).",
            problem="bad_arguments",
        )
    arr = np.asarray(source_targets if source_deltas is None else source_deltas, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != S0.shape:
        raise MeshError(
            f"source morph targets must have shape (T, {S0.shape[0]}, 3) to match the source "
            f"neutral mesh; got {arr.shape}.",
            problem="shape",
        )
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
    if bad.size:
        raise MeshError(
            f"source morph target(s) {bad.tolist()} contain NaN/inf coordinates.",
            problem="nonfinite",
            elements=bad,
        )
    return arr - S0 if source_deltas is None else arr


def apply_clone(
    fit: FitResult,
    mapping: SurfaceMap,
    source_triangles,
    target_vertices,
    deltas: np.ndarray,
    moving: np.ndarray,
    mode: str = "displacement",
    transfer: str = "morph",
) -> np.ndarray:
    """Clone source morph targets with a fitted ``G`` and a target-on-source mapping.

    Arguments:
        fit: the :class:`FitResult`; mapping: target vertices on ``fit.deformed``.
        source_triangles: ``(F, 3)`` source triangles; target_vertices: ``(Vt, 3)`` mm.
        deltas: ``(T, Vs, 3)`` source morph-target displacements, mm.
        moving: ``(T, Vs)`` bool moving vertices (only they are transformed).
        mode: ``"displacement"`` or ``"thesis"`` (see the module doc).
        transfer: how a moving source vertex's displacement is carried to the target frame:
            ``"morph"`` (thesis: ``G(S_j) - G(S_0)``, with ``G`` evaluated at the moving
            vertices of ``S_j``), ``"rough"`` (the same with the morph before refinement,
            ``fit.rough_morph``: the refined ``G`` still places the target on the source,
            but its many surface centres leave it wavy off the surface, which distorts the
            transferred motion), or ``"affine"`` (only the affine part ``M`` of ``G``:
            ``M (S_j - S_0)``; keeps the global rotation/scale between the faces but not the
            local stretching of the RBF).

    Returns:
        ``(T, Vt, 3)`` cloned target morph-target positions, mm.
    """
    D = fit.deformed
    T = deltas.shape[0]
    tri_v = np.asarray(source_triangles)[mapping.tri]  # (Vt, 3)
    # only the source vertices the target vertices are mapped onto matter
    used = np.zeros(D.shape[0], bool)
    used[tri_v.ravel()] = True
    tt, vv = np.nonzero(np.asarray(moving, bool) & used[None])
    disp = np.zeros((T,) + D.shape)
    if transfer in ("morph", "rough"):
        G = fit.morph if transfer == "morph" else fit.rough_morph
        pts = fit.source_neutral[vv] + deltas[tt, vv]
        moved = G.apply_np(pts) if pts.size else np.zeros((0, 3))
        if transfer == "morph":
            base = D[vv]
        else:
            base = np.zeros_like(D)
            u = np.flatnonzero(used)
            base[u] = G.apply_np(fit.source_neutral[u])
            base = base[vv]
        disp[tt, vv] = moved - base
    elif transfer == "affine":
        M, _ = fit.morph.affine_part()
        disp[tt, vv] = deltas[tt, vv] @ np.asarray(M, dtype=np.float64).T
    else:
        raise MeshError(
            f"unknown transfer {transfer!r}; use 'morph', 'rough' or 'affine'.",
            problem="bad_arguments",
        )
    tv = np.asarray(target_vertices, dtype=np.float64)
    out = tv[None] + np.einsum("vk,tvkd->tvd", mapping.bary, disp[:, tri_v])
    if mode == "thesis":
        snapped = np.einsum("vk,vkd->vd", mapping.bary, D[tri_v])
        touched = np.asarray(moving[:, tri_v].any(axis=2))  # (T, Vt)
        out = np.where(touched[..., None], out - tv[None] + snapped[None], out)
    elif mode != "displacement":
        raise MeshError(
            f"unknown cloning mode {mode!r}; use 'displacement' or 'thesis'.",
            problem="bad_arguments",
        )
    return out


def clone_motion(
    source_neutral,
    target_neutral,
    source_landmarks,
    target_landmarks,
    *,
    source_targets=None,
    source_deltas=None,
    names: Sequence[str] | None = None,
    move_tol: float = 0.01,
    mode: str = "displacement",
    transfer: str = "morph",
    **fit_kwargs,
) -> CloneResult:
    """Clone a source face's morph targets onto a target face (thesis chapter 6).

    Arguments:
        source_neutral, target_neutral: neutral meshes (TriMesh, trimesh.Trimesh or
            ``(vertices, triangles)``), mm, same frame conventions.
        source_landmarks, target_landmarks: ``Landmarks`` or ``{name: (3,) mm}``; every name
            common to both is a correspondence.
        source_targets: ``(T, Vs, 3)`` source morph targets as positions, mm; or
        source_deltas: ``(T, Vs, 3)`` as displacements from the source neutral, mm.
        names: optional ``T`` morph-target names.
        move_tol: a source vertex moves in a morph target if it is displaced by more than
            this (mm); movable vertices are those moving in any target.
        mode: ``"displacement"`` (default) or ``"thesis"``.
        transfer: ``"morph"`` (default, thesis), ``"rough"`` or ``"affine"``, see
            :func:`apply_clone`.
        **fit_kwargs: passed to :func:`fit_source_to_target` (``kernel``, ``ray_factor``,
            ``pairs_per_iteration``, ``max_iterations``, ``error_tol``, ``ens0``, ...).

    Returns:
        :class:`CloneResult` with the ``(T, Vt, 3)`` target morph targets.
    """
    t0 = time.perf_counter()
    src = as_trimesh(source_neutral, "source_neutral")
    tgt = as_trimesh(target_neutral, "target_neutral")
    deltas = _source_deltas(src.vertices, source_targets, source_deltas)
    moving = np.linalg.norm(deltas, axis=2) > move_tol
    if names is None:
        names = tuple(str(i) for i in range(deltas.shape[0]))
    names = tuple(names)
    if len(names) != deltas.shape[0]:
        raise MeshError(f"{len(names)} names for {deltas.shape[0]} morph targets.", problem="shape")
    fit = fit_source_to_target(
        src, tgt, source_landmarks, target_landmarks, movable=moving.any(axis=0), **fit_kwargs
    )
    t1 = time.perf_counter()
    tn = vertex_normals(tgt.vertices, tgt.triangles)
    mapping = map_onto_surface(tgt.vertices, tn, fit.ray_length, fit.deformed, src.triangles)
    targets = apply_clone(fit, mapping, src.triangles, tgt.vertices, deltas, moving, mode, transfer)
    t2 = time.perf_counter()
    return CloneResult(
        targets=targets,
        deltas=targets - tgt.vertices[None],
        names=names,
        fit=fit,
        mapping=mapping,
        moving=moving,
        mode=mode,
        transfer=transfer,
        timings=dict(fit=t1 - t0, clone=t2 - t1, total=t2 - t0),
    )
