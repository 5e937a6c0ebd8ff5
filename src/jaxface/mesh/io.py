"""OBJ/PLY mesh file I/O with units: :func:`load_mesh` (to mm, ids kept) and
:func:`save_mesh` (from mm, atomic, NaN refused)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..atomic import write_bytes_atomic, write_text_atomic
from ..errors import MeshError
from .arrays import _as_triangles, _as_vertices, check_finite_vertices
from .core import TriMesh
from .units import PLAUSIBLE_SIZE_MM, check_input_file, check_plausible_size, unit_scale

__all__ = ["load_mesh", "save_mesh"]

_INT_RE = re.compile(r"^[+-]?\d+$")


def _prescan_obj(path: Path) -> None:
    """Line-level sanity check of an OBJ file (trimesh silently drops broken lines)."""
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise MeshError(
            f"{path}: not a text OBJ file ({e}); is it corrupt or another format?",
            problem="corrupt_file",
        ) from None
    n_v = n_f = 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        tag = parts[0]
        if tag == "v":
            vals = parts[1:]
            ok = len(vals) >= 3
            if ok:
                try:
                    xyz = [float(x) for x in vals[:3]]
                    ok = all(np.isfinite(xyz))
                except ValueError:
                    ok = False
            if not ok:
                raise MeshError(
                    f"{path}, line {lineno}: bad vertex line {raw.strip()!r} (needs three finite "
                    f"numbers). The file is truncated or corrupt.",
                    problem="corrupt_file",
                )
            n_v += 1
        elif tag == "f":
            refs = parts[1:]
            ok = len(refs) >= 3 and all(_INT_RE.match(r.split("/")[0] or "x") for r in refs)
            if not ok:
                raise MeshError(
                    f"{path}, line {lineno}: bad face line {raw.strip()!r} (needs at least three "
                    f"vertex indices). The file is truncated or corrupt.",
                    problem="corrupt_file",
                )
            n_f += 1
    if n_v == 0 or n_f == 0:
        raise MeshError(
            f"{path}: no {'vertices' if n_v == 0 else 'faces'} found in OBJ file (empty, "
            f"truncated, or not an OBJ mesh).",
            problem="corrupt_file",
        )


def _ply_header(path: Path) -> tuple[str, dict[str, int], int]:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshError(
            f"{path}: not a PLY file or truncated header (no 'ply' magic / 'end_header').",
            problem="corrupt_file",
        )
    header = data[:end].decode("ascii", errors="replace")
    fmt = "ascii"
    counts: dict[str, int] = {}
    for line in header.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0] == "format":
            fmt = parts[1]
        if len(parts) >= 3 and parts[0] == "element":
            try:
                counts[parts[1]] = int(parts[2])
            except ValueError:
                raise MeshError(
                    f"{path}: bad PLY header line {line!r}.", problem="corrupt_file"
                ) from None
    body_start = data.find(b"\n", end) + 1
    n_lines = -1
    if fmt == "ascii":
        body = data[body_start:].decode("ascii", errors="replace")
        n_lines = sum(1 for ln in body.splitlines() if ln.strip())
    return fmt, counts, n_lines


def load_mesh(
    path,
    units: str = "mm",
    *,
    check_size: bool = True,
    validate: bool = True,
    size_range=PLAUSIBLE_SIZE_MM,
) -> TriMesh:
    """Read an OBJ or PLY triangle mesh and convert it to millimetres.

    Vertex ids are kept exactly as in the file (trimesh ``process=False, maintain_order=True``:
    no merging, no reordering), so per-vertex data (landmark ids, masks) stays valid. Quads and
    polygons are fan-triangulated by trimesh; for PLY files mixing triangles and polygons
    trimesh lists the triangles first, so triangle order may differ from the file's face order.

    Args:
        path: ``.obj`` or ``.ply`` file.
        units: unit of the file's coordinates: "mm", "cm" or "m".
        check_size: check that the mesh size is plausible for a face/head in mm after
            conversion (largest extent within ``size_range``), raising :class:`UnitsError` with
            advice otherwise. Pass False for parts of other sizes.
        validate: validate the mesh (:meth:`TriMesh.validate`).
        size_range: ``(lo, hi)`` mm for the size check.

    Returns:
        :class:`TriMesh` in mm.

    Raises:
        DataNotFoundError: the file does not exist.
        MeshError: unsupported extension, truncated or corrupt file (naming the file, and the
            line for OBJ), no triangles, or (with ``validate``) a bad mesh.
        UnitsError: unknown unit or implausible size.
    """
    import trimesh

    path = Path(os.fspath(path))
    scale = unit_scale(units)
    check_input_file(path, "mesh file")
    ext = path.suffix.lower()
    if ext not in (".obj", ".ply"):
        raise MeshError(
            f"{path}: unsupported mesh format {ext!r}; use .obj or .ply.",
            problem="unsupported_format",
        )
    ply_counts: dict[str, int] = {}
    if ext == ".obj":
        _prescan_obj(path)
    else:
        fmt, ply_counts, n_lines = _ply_header(path)
        if fmt == "ascii" and n_lines < sum(ply_counts.values()):
            raise MeshError(
                f"{path}: truncated ASCII PLY: the header declares "
                f"{sum(ply_counts.values())} data lines ({ply_counts}) but only {n_lines} follow.",
                problem="corrupt_file",
            )
    try:
        tm = trimesh.load(
            str(path), process=False, maintain_order=True, skip_materials=True, force="mesh"
        )
    except Exception as e:  # trimesh raises assorted exceptions on corrupt input
        raise MeshError(
            f"{path}: cannot read mesh ({type(e).__name__}: {e}). The file is truncated or corrupt.",
            problem="corrupt_file",
        ) from e
    faces = np.asarray(getattr(tm, "faces", np.zeros((0, 3))))
    verts = np.asarray(getattr(tm, "vertices", np.zeros((0, 3))))
    if faces.ndim != 2 or faces.shape[0] == 0:
        raise MeshError(
            f"{path}: file holds no triangles (a point cloud or empty mesh?).",
            problem="corrupt_file",
        )
    if ext == ".ply":
        nv_decl = ply_counts.get("vertex")
        nf_decl = ply_counts.get("face")
        if nv_decl is not None and verts.shape[0] != nv_decl:
            raise MeshError(
                f"{path}: header declares {nv_decl} vertices but {verts.shape[0]} were read; the "
                f"file is truncated or corrupt.",
                problem="corrupt_file",
            )
        if nf_decl is not None and faces.shape[0] < nf_decl:
            raise MeshError(
                f"{path}: header declares {nf_decl} faces but only {faces.shape[0]} triangles "
                f"were read; the file is truncated or corrupt.",
                problem="corrupt_file",
            )
    v_mm = verts.astype(np.float64) * scale
    check_finite_vertices(v_mm, source=f"{path}:")
    if check_size:
        check_plausible_size(v_mm, units, source=str(path), size_range=size_range)
    try:
        return TriMesh(v_mm, faces, validate=validate)
    except MeshError as e:
        err = MeshError(f"{path}: {e}", problem=e.problem, elements=e.elements)
        if hasattr(e, "edges"):
            err.edges = e.edges
        raise err from e


def save_mesh(
    path, mesh_or_vertices, triangles=None, units: str = "mm", *, encoding: str = "binary"
) -> None:
    """Write a triangle mesh to OBJ or PLY, converting from mm to ``units``.

    The file is written atomically (:mod:`jaxface.atomic`); vertices holding NaN/inf are
    refused (:class:`MeshError`, ``problem="nonfinite_vertices"``) and nothing is written.
    Vertex and triangle order are kept. PLY is written by trimesh with float32 coordinates
    (relative precision ~6e-8, i.e. ~2e-5 mm on a head); OBJ with 10 decimals.

    Args:
        path: ``.obj`` or ``.ply`` destination.
        mesh_or_vertices: a :class:`TriMesh`, or ``(V, 3)`` vertices in mm (then ``triangles``
            is required).
        triangles: ``(F, 3)`` int vertex ids when vertices are given.
        units: unit to write: "mm", "cm" or "m".
        encoding: PLY only, "binary" or "ascii".
    """
    import trimesh.exchange.obj
    import trimesh.exchange.ply

    path = Path(os.fspath(path))
    scale = unit_scale(units)
    if isinstance(mesh_or_vertices, TriMesh):
        v, t = mesh_or_vertices.vertices, mesh_or_vertices.triangles
    else:
        if triangles is None:
            raise MeshError(
                "save_mesh: give a TriMesh, or vertices and triangles.", problem="shape"
            )
        v, t = _as_vertices(mesh_or_vertices), _as_triangles(triangles)
    ext = path.suffix.lower()
    if ext not in (".ply", ".obj"):
        raise MeshError(
            f"{path}: unsupported mesh format {ext!r}; use .obj or .ply.",
            problem="unsupported_format",
        )
    check_finite_vertices(v, source=f"{path}: refusing to write the mesh:")
    tm = trimesh.Trimesh(
        vertices=np.array(v) / scale, faces=np.array(t), process=False, validate=False
    )
    if ext == ".ply":
        data = trimesh.exchange.ply.export_ply(
            tm, encoding=encoding, vertex_normal=False, include_attributes=False
        )
        write_bytes_atomic(path, data)
    else:
        text = trimesh.exchange.obj.export_obj(
            tm, include_normals=False, include_color=False, include_texture=False, digits=10
        )
        write_text_atomic(path, text)
