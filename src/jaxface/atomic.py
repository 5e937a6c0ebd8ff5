"""Atomic output files and output folders, shared by every writer of jaxface.

A file is written to a temporary file in the destination folder and moved over the
destination with :func:`os.replace` (atomic on POSIX and Windows within one file system):
a reader never sees a half-written file, and an interrupted or failed write leaves the old
file (or none) in place. JSON is written with ``allow_nan=False``: a NaN or inf anywhere
in the data is refused with the key path that holds it.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .errors import OutputError

__all__ = [
    "atomic_path",
    "write_bytes_atomic",
    "write_text_atomic",
    "write_json_atomic",
    "ensure_out_dir",
    "check_out_dir",
    "find_nonfinite",
]


def check_out_dir(path, option: str = "--out") -> Path:
    """Check, without creating anything, that the output folder ``path`` exists or can be
    created: it is not a file, no parent is a file, and the nearest existing parent is
    writable. Returns it as a :class:`Path`.

    Raises:
        OutputError: naming the reason.
    """
    p = Path(os.fspath(path))
    if p.exists() and not p.is_dir():
        raise OutputError(f"{option} {p}: exists and is a file, not a folder; give a folder path.")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(
                    f"{option} {p}: cannot create the folder because {parent} is a file, not "
                    "a folder; choose another output path."
                )
            if not p.exists() and not os.access(parent, os.W_OK | os.X_OK):
                raise OutputError(
                    f"{option} {p}: cannot create the folder: {parent} is not writable; choose "
                    "a writable path."
                )
            break
    return p


def ensure_out_dir(path, option: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) if missing and return it.

    Raises:
        OutputError: the folder cannot be created or used: ``path`` or one of its parents is
            a file, permission is denied, or the file system refuses (the reason is named).
    """
    p = check_out_dir(path, option)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(
            f"{option} {p}: cannot create the folder ({e.strerror or e}); choose a writable path."
        ) from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"{option} {p}: the folder is not writable; choose a writable path.")
    return p


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on a normal exit it replaces ``path``
    (:func:`os.replace`), on an exception it is removed and ``path`` is untouched.

    The temporary name keeps ``path``'s suffix (writers that choose the format by suffix,
    such as matplotlib, keep working).

    Raises:
        OutputError: ``path`` is a folder, or its folder does not exist or is not writable.
    """
    p = Path(os.fspath(path))
    if p.is_dir():
        raise OutputError(f"{p}: is a folder; give a file path to write.")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(
            f"{p}: its folder {folder} does not exist (or is a file); create it first."
        )
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".tmp{p.suffix}", dir=folder)
    except OSError as e:
        raise OutputError(f"{p}: cannot write in {folder} ({e.strerror or e}).") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def write_bytes_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see the module doc). Returns the path."""
    p = Path(os.fspath(path))
    with atomic_path(p) as tmp:
        tmp.write_bytes(data)
    return p


def write_text_atomic(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see the module doc). Returns the path."""
    return write_bytes_atomic(path, text.encode(encoding))


def find_nonfinite(obj, where: str = "") -> str | None:
    """The key path (``a.b[3]``) of the first NaN/inf number in a JSON-like object, or None.

    Numbers are Python/NumPy floats, ints, and NumPy arrays; dicts, lists and tuples are
    searched depth first."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            hit = find_nonfinite(v, f"{where}.{k}" if where else str(k))
            if hit is not None:
                return hit
        return None
    if isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            hit = find_nonfinite(v, f"{where}[{i}]")
            if hit is not None:
                return hit
        return None
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc":
            bad = np.flatnonzero(~np.isfinite(obj.ravel()))
            if bad.size:
                return f"{where}[flat {int(bad[0])}]"
        return None
    if isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        return where or "(top level)"
    return None


def write_json_atomic(path, obj, *, indent: int = 1, default=None) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically, refusing NaN/inf.

    Raises:
        OutputError: ``obj`` holds a NaN or inf (the message names its key path), or the
            file cannot be written.
    """
    bad = find_nonfinite(obj)
    if bad is not None:
        raise OutputError(
            f"{path}: refusing to write a non-finite number (NaN/inf) at {bad}; the result "
            "is unusable (a NaN input or a failed computation)."
        )
    try:
        text = json.dumps(obj, indent=indent, allow_nan=False, default=default)
    except ValueError as e:  # a NaN hidden in an object serialised by ``default``
        raise OutputError(f"{path}: refusing to write non-finite numbers ({e}).") from None
    return write_text_atomic(path, text)
