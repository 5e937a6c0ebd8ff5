"""glTF 2.0 binary (``.glb``) of a face with morph targets and a morph-weight animation
(written with pygltflib), and a structural check of such a file.

Units: the inputs are in mm; the file is in metres (glTF's unit), ``x_m = x_mm / 1000``. Frame:
glTF's +y up, +z forward (toward the viewer), which is the project's frame; the subject's left
is +x. Triangles are counter-clockwise seen from outside (glTF's front faces).

Layout written by :func:`build_gltf`: one scene; node 0 ``skin`` holds the morphable mesh
(one primitive: POSITION, NORMAL, indices; one morph target per name, each with POSITION and
NORMAL deltas, ``mesh.extras.targetNames`` holding the names, which Blender and three.js read
as shape-key / ``morphTargetDictionary`` names; ``mesh.weights`` all 0); one node per rigid
part (eyes, teeth) without targets; an optional animation with one ``weights`` channel on
node 0 whose keyframes are the given weight vectors (LINEAR interpolation between them).
A morph target is linear in its weight (glTF): ``x(w) = rest + sum_k w_k delta_k``.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib as gl

from ..errors import DataNotFoundError, MeshError
from ..render import vertex_normals

__all__ = [
    "MM_TO_M",
    "GltfPart",
    "build_gltf",
    "write_glb",
    "load_glb",
    "check_gltf",
    "morph_targets_of",
]

#: mm -> m
MM_TO_M = 1e-3


@dataclass(frozen=True)
class GltfPart:
    """A rigid mesh written beside the skin: ``vertices (V, 3)`` mm, ``triangles (F, 3)``."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray


class _Blob:
    """The binary buffer, built view by view (4-byte aligned)."""

    def __init__(self, g: gl.GLTF2):
        self.g = g
        self.data = bytearray()

    def add(self, arr: np.ndarray, *, kind: str, target: int | None, minmax: bool) -> int:
        comp = gl.UNSIGNED_INT if arr.dtype == np.uint32 else gl.FLOAT
        while len(self.data) % 4:
            self.data.append(0)
        off = len(self.data)
        raw = np.ascontiguousarray(arr).tobytes()
        self.data.extend(raw)
        self.g.bufferViews.append(
            gl.BufferView(buffer=0, byteOffset=off, byteLength=len(raw), target=target)
        )
        count = arr.shape[0] if kind != "SCALAR" or arr.ndim == 1 else arr.size
        acc = gl.Accessor(
            bufferView=len(self.g.bufferViews) - 1,
            componentType=comp,
            count=int(count if kind != "SCALAR" else arr.size),
            type=kind,
        )
        if minmax:
            flat = arr.reshape(int(acc.count), -1)
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.g.accessors.append(acc)
        return len(self.g.accessors) - 1


def _f32(x, name: str) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if not np.all(np.isfinite(a)):
        raise MeshError(f"{name} holds NaN/inf; nothing was written.", problem="nonfinite")
    return a.astype(np.float32)


def build_gltf(
    rest,
    triangles,
    targets: list[tuple[str, np.ndarray]],
    *,
    parts: list[GltfPart] = (),  # type: ignore[assignment]
    animation: tuple[np.ndarray, np.ndarray] | None = None,
    animation_name: str = "fits",
    skin_name: str = "skin",
) -> gl.GLTF2:
    """The glTF document (with its binary blob set) of a morphable skin.

    Args:
        rest: ``(V, 3)`` rest skin, mm; triangles: ``(F, 3)``.
        targets: ``[(name, delta (V, 3) mm)]``, the morph targets (unique names).
        parts: rigid meshes (eyes, teeth), mm.
        animation: ``(times (K,) s increasing, weights (K, T))`` or None.

    Raises:
        MeshError: shapes, duplicate names, NaN/inf.
    """
    X = np.asarray(rest, np.float64)
    T = np.asarray(triangles, np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 3:
        raise MeshError("rest must be (V, 3) and triangles (F, 3).", problem="shape")
    if T.size and (T.min() < 0 or T.max() >= len(X)):
        raise MeshError("triangles index outside the rest vertices.", problem="index")
    names = [str(n) for n, _ in targets]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise MeshError(f"duplicate morph target names {dup}.", problem="duplicate")
    g = gl.GLTF2(asset=gl.Asset(version="2.0", generator="jaxface"))
    g.scene = 0
    scene_nodes: list[int] = [0]
    blob = _Blob(g)
    n0 = vertex_normals(X, T)
    pos = blob.add(_f32(X * MM_TO_M, "rest"), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=True)
    nrm = blob.add(_f32(n0, "normals"), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=False)
    idx = blob.add(
        T.astype(np.uint32).reshape(-1), kind="SCALAR", target=gl.ELEMENT_ARRAY_BUFFER, minmax=False
    )
    tgts = []
    for name, d in targets:
        D = np.asarray(d, np.float64)
        if D.shape != X.shape:
            raise MeshError(
                f"morph target {name!r} has shape {D.shape}; expected {X.shape} (the rest skin).",
                problem="shape",
            )
        dn = vertex_normals(X + D, T) - n0
        tgts.append(
            {
                "POSITION": blob.add(
                    _f32(D * MM_TO_M, name), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=True
                ),
                "NORMAL": blob.add(
                    _f32(dn, name), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=False
                ),
            }
        )
    prim = gl.Primitive(
        attributes=gl.Attributes(POSITION=pos, NORMAL=nrm), indices=idx, mode=gl.TRIANGLES
    )
    prim.targets = tgts or None
    mesh = gl.Mesh(name=skin_name, primitives=[prim])
    if tgts:
        mesh.weights = [0.0] * len(tgts)
        mesh.extras = {"targetNames": names}
    g.meshes.append(mesh)
    g.nodes.append(gl.Node(name=skin_name, mesh=0))
    for part in parts:
        V = np.asarray(part.vertices, np.float64)
        F = np.asarray(part.triangles, np.int64)
        p_pos = blob.add(
            _f32(V * MM_TO_M, part.name), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=True
        )
        p_nrm = blob.add(
            _f32(vertex_normals(V, F), part.name), kind="VEC3", target=gl.ARRAY_BUFFER, minmax=False
        )
        p_idx = blob.add(
            F.astype(np.uint32).reshape(-1),
            kind="SCALAR",
            target=gl.ELEMENT_ARRAY_BUFFER,
            minmax=False,
        )
        g.meshes.append(
            gl.Mesh(
                name=part.name,
                primitives=[
                    gl.Primitive(
                        attributes=gl.Attributes(POSITION=p_pos, NORMAL=p_nrm),
                        indices=p_idx,
                        mode=gl.TRIANGLES,
                    )
                ],
            )
        )
        g.nodes.append(gl.Node(name=part.name, mesh=len(g.meshes) - 1))
        scene_nodes.append(len(g.nodes) - 1)
    if animation is not None:
        times = np.asarray(animation[0], np.float64).reshape(-1)
        W = np.asarray(animation[1], np.float64)
        if W.shape != (len(times), len(tgts)) or not tgts:
            raise MeshError(
                f"animation weights must be (keyframes {len(times)}, targets {len(tgts)}); got "
                f"{W.shape}.",
                problem="shape",
            )
        if len(times) > 1 and np.any(np.diff(times) <= 0):
            raise MeshError("animation times must increase.", problem="order")
        t_acc = blob.add(_f32(times, "times"), kind="SCALAR", target=None, minmax=True)
        w_acc = blob.add(_f32(W.reshape(-1), "weights"), kind="SCALAR", target=None, minmax=False)
        g.animations.append(
            gl.Animation(
                name=animation_name,
                samplers=[gl.AnimationSampler(input=t_acc, output=w_acc, interpolation="LINEAR")],
                channels=[
                    gl.AnimationChannel(
                        sampler=0, target=gl.AnimationChannelTarget(node=0, path="weights")
                    )
                ],
            )
        )
    g.scenes = [gl.Scene(nodes=scene_nodes)]
    while len(blob.data) % 4:
        blob.data.append(0)
    g.buffers = [gl.Buffer(byteLength=len(blob.data))]
    g.set_binary_blob(bytes(blob.data))
    return g


def write_glb(path, g: gl.GLTF2) -> Path:
    """Write ``g`` as a ``.glb`` atomically (temp file + ``os.replace``) after
    :func:`check_gltf`.

    Raises:
        MeshError: the document fails the structural check.
    """
    problems = check_gltf(g)
    if problems:
        raise MeshError("the glTF document is malformed: " + "; ".join(problems[:5]))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    data = b"".join(g.save_to_bytes())
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return p


_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_CSIZE = {gl.FLOAT: 4, gl.UNSIGNED_INT: 4, gl.UNSIGNED_SHORT: 2, gl.UNSIGNED_BYTE: 1}
_CDTYPE = {gl.FLOAT: np.float32, gl.UNSIGNED_INT: np.uint32, gl.UNSIGNED_SHORT: np.uint16}


def _ix(i) -> int:
    if i is None:
        raise MeshError("a glTF index is missing (None).", problem="structure")
    return int(i)


def _acc(t: Any, key: str):
    """A morph target's accessor id (pygltflib keeps targets as dicts)."""
    return t.get(key) if isinstance(t, dict) else getattr(t, key, None)


def load_glb(path) -> gl.GLTF2:
    """Read a ``.glb`` with pygltflib.

    Raises:
        DataNotFoundError: no such file; MeshError: not a readable glTF binary.
    """
    p = Path(path)
    if not p.is_file():
        raise DataNotFoundError(f"glTF file not found: {p}")
    g = gl.GLTF2().load(str(p))
    if g is None:
        raise MeshError(f"{p} is not a readable glTF 2.0 file.", problem="format")
    return g


def _read(g: gl.GLTF2, blob: bytes, i) -> np.ndarray:
    a = g.accessors[_ix(i)]
    v = g.bufferViews[_ix(a.bufferView)]
    n = _NCOMP[a.type]
    arr = np.frombuffer(
        blob,
        dtype=_CDTYPE[a.componentType],
        count=a.count * n,
        offset=(v.byteOffset or 0) + (a.byteOffset or 0),
    )
    return arr.reshape(a.count, n) if n > 1 else arr


def check_gltf(g: gl.GLTF2) -> list[str]:
    """Structural problems of a glTF document (empty list: none). Checks: version 2.0, one
    buffer matching the blob, every buffer view inside its buffer, every accessor's
    ``count * size`` inside its view, POSITION accessors (skin, parts, targets) with
    ``min``/``max`` equal to the data's, indices below the vertex count, every morph target of
    a primitive with the primitive's vertex count and the same attributes, ``extras.targetNames``
    and ``weights`` of the target count, animation samplers with increasing input times and
    ``output.count == input.count * targets``."""
    out: list[str] = []
    if g.asset is None or g.asset.version != "2.0":
        out.append("asset.version is not 2.0")
    blob = g.binary_blob() or b""
    if len(g.buffers) != 1 or g.buffers[0].byteLength > len(blob):
        return out + ["expected one buffer no longer than the binary chunk"]
    blen = g.buffers[0].byteLength
    for k, v in enumerate(g.bufferViews):
        if (v.byteOffset or 0) < 0 or (v.byteOffset or 0) + v.byteLength > blen:
            out.append(f"bufferView {k} leaves the buffer")
    for k, a in enumerate(g.accessors):
        if a.bufferView is None or a.bufferView >= len(g.bufferViews):
            out.append(f"accessor {k} has no valid bufferView")
            continue
        size = a.count * _NCOMP.get(a.type, 0) * _CSIZE.get(a.componentType, 0)
        if size == 0 or (a.byteOffset or 0) + size > g.bufferViews[a.bufferView].byteLength:
            out.append(f"accessor {k} ({a.type}, count {a.count}) overruns its bufferView")
    if out:
        return out

    def check_pos(i: int, what: str) -> None:
        a = g.accessors[i]
        if a.type != "VEC3" or a.componentType != gl.FLOAT:
            out.append(f"{what}: POSITION is not float VEC3")
            return
        d = _read(g, blob, i)
        if a.min is None or a.max is None:
            out.append(f"{what}: POSITION lacks min/max")
        elif not (
            np.allclose(a.min, d.min(0), rtol=0, atol=1e-7)
            and np.allclose(a.max, d.max(0), rtol=0, atol=1e-7)
        ):
            out.append(f"{what}: POSITION min/max differ from the data")
        if not np.all(np.isfinite(d)):
            out.append(f"{what}: POSITION holds NaN/inf")

    for mi, m in enumerate(g.meshes):
        for pi, p in enumerate(m.primitives):
            what = f"mesh {mi} ({m.name}) primitive {pi}"
            if p.attributes.POSITION is None:
                out.append(f"{what}: no POSITION")
                continue
            check_pos(p.attributes.POSITION, what)
            nv = g.accessors[p.attributes.POSITION].count
            if p.attributes.NORMAL is not None:
                if g.accessors[p.attributes.NORMAL].count != nv:
                    out.append(f"{what}: NORMAL count differs from POSITION")
                else:
                    ln = np.linalg.norm(_read(g, blob, p.attributes.NORMAL), axis=1)
                    if not np.allclose(ln, 1.0, atol=1e-3):
                        out.append(f"{what}: NORMAL not unit length")
            if p.indices is not None:
                ia = g.accessors[p.indices]
                idx = _read(g, blob, p.indices)
                if ia.type != "SCALAR" or ia.count % 3 or (idx.size and idx.max() >= nv):
                    out.append(f"{what}: bad triangle indices")
            nt = len(p.targets or [])
            for ti, t in enumerate(p.targets or []):
                keys = [k for k in ("POSITION", "NORMAL", "TANGENT") if _acc(t, k) is not None]
                if "POSITION" not in keys:
                    out.append(f"{what} target {ti}: no POSITION")
                    continue
                for key in keys:
                    if g.accessors[_ix(_acc(t, key))].count != nv:
                        out.append(f"{what} target {ti}: {key} count differs from the vertices")
                check_pos(_ix(_acc(t, "POSITION")), f"{what} target {ti}")
            if nt:
                names = (m.extras or {}).get("targetNames")
                if not isinstance(names, list) or len(names) != nt:
                    out.append(f"{what}: extras.targetNames does not name the {nt} targets")
                if m.weights is not None and len(m.weights) != nt:
                    out.append(f"{what}: mesh.weights length differs from the targets")
    for ai, an in enumerate(g.animations):
        for s in an.samplers:
            tin = _read(g, blob, s.input)
            if tin.size > 1 and np.any(np.diff(tin) <= 0):
                out.append(f"animation {ai}: input times do not increase")
        for c in an.channels:
            if c.target.path == "weights":
                node = g.nodes[_ix(c.target.node)]
                nt = len(g.meshes[_ix(node.mesh)].primitives[0].targets or [])
                s = an.samplers[c.sampler]
                if g.accessors[s.output].count != g.accessors[s.input].count * nt:
                    out.append(f"animation {ai}: output count is not keyframes x {nt} targets")
    return out


def morph_targets_of(g: gl.GLTF2, mesh: int = 0) -> dict:
    """Read back a mesh's rest, triangles and targets (metres), and the animation keyframes:
    ``{"rest": (V, 3), "triangles": (F, 3), "names": [...], "deltas": (T, V, 3),
    "normals": (V, 3), "normal_deltas": (T, V, 3), "times": (K,) or None,
    "weights": (K, T) or None}``."""
    blob = g.binary_blob() or b""
    p = g.meshes[mesh].primitives[0]
    rest = _read(g, blob, p.attributes.POSITION).astype(np.float64)
    tris = _read(g, blob, p.indices).astype(np.int64).reshape(-1, 3)
    deltas = (
        np.stack(
            [_read(g, blob, _acc(t, "POSITION")).astype(np.float64) for t in (p.targets or [])]
        )
        if p.targets
        else np.zeros((0,) + rest.shape)
    )
    normals = _read(g, blob, p.attributes.NORMAL).astype(np.float64)
    normal_deltas = (
        np.stack([_read(g, blob, _acc(t, "NORMAL")).astype(np.float64) for t in p.targets])
        if p.targets
        else np.zeros((0,) + rest.shape)
    )
    names = list((g.meshes[mesh].extras or {}).get("targetNames", []))
    times = weights = None
    for an in g.animations:
        for c in an.channels:
            if c.target.path == "weights" and g.nodes[_ix(c.target.node)].mesh == mesh:
                s = an.samplers[c.sampler]
                times = _read(g, blob, s.input).astype(np.float64)
                weights = _read(g, blob, s.output).astype(np.float64).reshape(len(times), -1)
    return {
        "rest": rest,
        "triangles": tris,
        "names": names,
        "deltas": deltas,
        "normals": normals,
        "normal_deltas": normal_deltas,
        "times": times,
        "weights": weights,
    }
