"""An on-disk cache of prepared subjects: the registered neutral, the rig and its reduced
response model of :func:`jaxface.fit.subject.prepare_subject`, kept between processes.

Building a subject from a neutral scan takes about a minute on a 2-core CPU (bs900: the
registration 4.6 s, the rig 12.5 s, the reduced model's 228 syntheses 34 s, the compilation
8.7 s). A second ``jaxface fit`` of the same person's expressions, a resumed
``jaxface fit-db`` or ``jaxface export`` of a fitted subject builds exactly the same subject
again. The cache keeps what the build computed and loads it in well under a second; only
the compilation remains (and JAX's own compilation cache, :mod:`jaxface.compile_cache`,
shortens that).

**The key** is a SHA-256 of everything the build depends on:

* the neutral's triangulated surface (vertices in mm and triangles, as the registration
  sees them) and its landmarks (labels and positions, mm), not its file name;
* the template: the built-in head, or a user template mesh with its landmarks (by content);
* :class:`~jaxface.fit.subject.SubjectOptions` (with the registration options and the rig
  keywords, by value);
* the code: a digest of jaxface's own source files, the versions of JAX, jaxlib and NumPy,
  and whether JAX runs in float64.

Any change to any of them is a miss, and a fresh build replaces nothing that a different key
points to. A template object the key cannot describe (e.g. a Python head object with custom
fields) is not cached; the build runs as without a cache.

Beside an entry, small JSON side entries keep what a first fit of the subject computes once
per set of fit options: the AU readout's noise floor (the neutral fitted to itself,
:func:`jaxface.fit.pipeline.fit_expressions`), named by a :func:`digest` of the
:class:`~jaxface.fit.options.FitOptions`. They go with their entry.

**The entries** are pickles (about 120 MB for a Bosphorus subject), written atomically
(:mod:`jaxface.atomic`). A truncated or unreadable entry is reported with a warning, removed
and rebuilt. Loading a pickle runs code, so the cache folder must be as trusted as the code
itself (the default is the user's own cache folder). The folder is kept under
``max_bytes`` (default 4 GiB) by removing the entries used longest ago.

Where: ``prepare_subject(..., cache=...)``: ``None`` reads ``JAXFACE_SUBJECT_CACHE`` (a
folder, ``default``, or ``off``; unset: off), ``"default"`` is :func:`default_subject_cache_dir`,
``"off"`` turns it off, a path is that folder, a :class:`SubjectCache` is used as it is. The
command line turns it on by default (``--subject-cache DIR|off``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.metadata
import json
import os
import pickle
import warnings
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..atomic import write_bytes_atomic, write_json_atomic

__all__ = [
    "SubjectCache",
    "CachedParts",
    "default_subject_cache_dir",
    "resolve_subject_cache",
    "code_digest",
    "subject_key",
    "digest",
    "ENV",
    "UncacheableError",
]

#: environment variable of the default cache folder (``off`` / ``default`` / a folder)
ENV = "JAXFACE_SUBJECT_CACHE"
#: values that turn the cache off
OFF = ("off", "none", "no", "false", "0", "")
#: bump when the layout of an entry changes
FORMAT = 1
#: default size limit of the cache folder, bytes
DEFAULT_MAX_BYTES = 4 * 1024**3


class UncacheableError(TypeError):
    """The key cannot describe a build input (the build then runs without the cache)."""


@dataclasses.dataclass
class CachedParts:
    """What a subject build computes that does not depend on the process (mm).

    Attributes:
        registration: the :class:`~jaxface.fit.register.Registration`.
        rig: the rig built on the registered neutral.
        response: the :class:`~jaxface.fit.reduced.ResponseModel` over ``fit_ids``.
        fit_ids: ``(P,)`` vertex ids; face_triangles: ``(F,)`` bool; landmark_names,
            landmark_tri, landmark_bary: the rig landmarks' attachment.
        timings: seconds of the build steps that made the entry.
    """

    registration: Any
    rig: Any
    response: Any
    fit_ids: np.ndarray
    face_triangles: np.ndarray
    landmark_names: tuple[str, ...]
    landmark_tri: np.ndarray
    landmark_bary: np.ndarray
    timings: dict


def default_subject_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/jaxface/subjects``, or ``~/.cache/jaxface/subjects``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxface" / "subjects"


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 (hex) of jaxface's source files (``*.py`` and packaged data, by relative path
    and content) and of the JAX, jaxlib and NumPy versions: any code change invalidates every
    cache entry."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    for v in (jax.__version__, _version("jaxlib"), np.__version__, FORMAT):
        h.update(str(v).encode())
    return h.hexdigest()


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "none"


def _feed(h, obj: Any, where: str = "value") -> None:
    """Feed a canonical description of ``obj`` to the hash ``h``."""
    if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif isinstance(obj, (np.ndarray, np.generic, jax.Array)):
        a = np.ascontiguousarray(np.asarray(obj))
        if a.dtype == object:
            raise UncacheableError(f"{where}: an object array")
        h.update(f"array:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    elif isinstance(obj, (tuple, list)):
        h.update(f"{type(obj).__name__}[{len(obj)}](".encode())
        for i, v in enumerate(obj):
            _feed(h, v, f"{where}[{i}]")
        h.update(b")")
    elif isinstance(obj, dict):
        h.update(f"dict[{len(obj)}](".encode())
        for k in sorted(obj, key=repr):
            _feed(h, k, where)
            _feed(h, obj[k], f"{where}[{k!r}]")
        h.update(b")")
    elif hasattr(obj, "names") and hasattr(obj, "positions"):  # Landmarks
        h.update(b"landmarks(")
        _feed(h, tuple(obj.names), where)
        _feed(h, np.asarray(obj.positions, np.float64), where)
        h.update(b")")
    elif hasattr(obj, "vertices") and (hasattr(obj, "triangles") or hasattr(obj, "faces")):
        tri = obj.triangles if hasattr(obj, "triangles") else obj.faces
        h.update(b"mesh(")
        _feed(h, np.asarray(obj.vertices, np.float64), where)
        _feed(h, np.asarray(tri, np.int64), where)
        h.update(b")")
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        h.update(f"{type(obj).__module__}.{type(obj).__qualname__}(".encode())
        for f in dataclasses.fields(obj):
            h.update(f.name.encode())
            _feed(h, getattr(obj, f.name), f"{where}.{f.name}")
        h.update(b")")
    else:
        raise UncacheableError(f"{where}: a {type(obj).__name__} cannot be keyed by content")


def digest(obj) -> str:
    """SHA-256 (hex) of ``obj``'s content (arrays, numbers, strings, containers, dataclasses,
    meshes, landmarks), e.g. of a :class:`~jaxface.fit.options.FitOptions`.

    Raises:
        UncacheableError: a value the digest cannot describe.
    """
    h = hashlib.sha256()
    _feed(h, obj)
    return h.hexdigest()


def subject_key(vertices, triangles, landmarks: dict, template, template_landmarks, options) -> str:
    """The cache key (hex SHA-256) of a subject build (see the module doc).

    Arguments:
        vertices, triangles: the neutral's ``(V, 3)`` mm and ``(F, 3)`` surface.
        landmarks: the neutral's landmarks, label -> ``(3,)`` mm.
        template, template_landmarks: as given to ``prepare_subject`` (None: built-in head).
        options: the :class:`~jaxface.fit.subject.SubjectOptions`.

    Raises:
        UncacheableError: an input the key cannot describe.
    """
    import jax.numpy as jnp

    h = hashlib.sha256()
    h.update(code_digest().encode())
    h.update(f"float={np.dtype(jnp.result_type(float)).str};".encode())
    _feed(h, np.asarray(vertices, np.float64), "neutral vertices")
    _feed(h, np.asarray(triangles, np.int64), "neutral triangles")
    _feed(h, {str(k): np.asarray(v, np.float64) for k, v in landmarks.items()}, "landmarks")
    _feed(h, template, "template")
    _feed(h, template_landmarks, "template_landmarks")
    _feed(h, options, "options")
    return h.hexdigest()


class SubjectCache:
    """A folder of cached subject builds (see the module doc).

    Arguments:
        folder: the cache folder (created on the first write).
        max_bytes: the folder's size limit; the entries used longest ago go first.
    """

    def __init__(self, folder, max_bytes: int = DEFAULT_MAX_BYTES):
        self.folder = Path(folder).expanduser()
        self.max_bytes = int(max_bytes)

    def __repr__(self) -> str:
        return f"SubjectCache({str(self.folder)!r}, max_bytes={self.max_bytes})"

    def path(self, key: str) -> Path:
        return self.folder / f"subject-{key[:32]}.pkl"

    def entries(self) -> list[Path]:
        """The entry files, most recently used first."""
        if not self.folder.is_dir():
            return []
        files = list(self.folder.glob("subject-*.pkl"))
        return sorted(files, key=lambda p: p.stat().st_mtime, reverse=True)

    @staticmethod
    def _read(p: Path, key: str, read, kind: type):
        """``read(p) -> (stored key, value)``; the value if the file exists, holds ``key``
        and a ``kind``, else None. A damaged file is removed with a warning."""
        if not p.is_file():
            return None
        try:
            stored_key, value = read(p)
            if stored_key != key or not isinstance(value, kind):
                raise ValueError("the entry belongs to another key")
        except Exception as e:  # a damaged entry of any kind is rebuilt
            warnings.warn(
                f"subject cache: {p} is unreadable ({type(e).__name__}: {e}); rebuilding it.",
                stacklevel=3,
            )
            with contextlib.suppress(OSError):
                p.unlink()
            return None
        return value

    def load(self, key: str) -> CachedParts | None:
        """The entry of ``key``, or None (a miss). A damaged entry is removed with a
        warning."""
        p = self.path(key)
        parts = self._read(p, key, lambda f: pickle.loads(f.read_bytes()), CachedParts)
        if parts is not None:
            with contextlib.suppress(OSError):
                os.utime(p)  # most recently used
        return parts

    def side_path(self, key: str, name: str) -> Path:
        return self.folder / f"{name}-{key[:32]}.json"

    def load_json(self, key: str, name: str) -> dict | None:
        """The side entry ``name`` of ``key`` (a JSON object), or None; a damaged one is
        removed with a warning."""

        def read(f: Path):
            obj = json.loads(f.read_text(encoding="utf-8"))
            return obj.get("key"), obj.get("value")

        return self._read(self.side_path(key, name), key, read, dict)

    def store_json(self, key: str, name: str, value: dict) -> Path | None:
        """Write the side entry ``name`` of ``key`` atomically (only beside an entry of
        ``key``); None, with a warning, when it cannot be written."""
        if not self.path(key).is_file():
            return None
        try:
            return write_json_atomic(self.side_path(key, name), {"key": key, "value": value})
        except Exception as e:  # the cache is an optimisation: never fail the fit
            warnings.warn(
                f"subject cache: {name} not written in {self.folder} ({e}).", stacklevel=2
            )
            return None

    def _remove(self, entry: Path) -> None:
        """Remove an entry file and its side entries."""
        stem = entry.stem.removeprefix("subject-")
        for side in self.folder.glob(f"*-{stem}.json"):
            with contextlib.suppress(OSError):
                side.unlink()
        entry.unlink()

    def store(self, key: str, parts: CachedParts) -> Path | None:
        """Write the entry of ``key`` atomically, then trim the folder to ``max_bytes``.
        Returns the file, or None (with a warning) when the folder cannot be written."""
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            data = pickle.dumps((key, parts), protocol=pickle.HIGHEST_PROTOCOL)
            if len(data) > self.max_bytes:
                return None
            p = write_bytes_atomic(self.path(key), data)
        except Exception as e:  # the cache is an optimisation: never fail the build
            warnings.warn(f"subject cache: not written in {self.folder} ({e}).", stacklevel=2)
            return None
        self.trim(keep=p)
        return p

    def trim(self, keep: Path | None = None) -> list[Path]:
        """Remove the entries used longest ago until the folder fits ``max_bytes``
        (never ``keep``). Returns the removed files."""
        removed = []
        files = self.entries()
        total = sum(f.stat().st_size for f in files)
        for f in reversed(files):
            if total <= self.max_bytes:
                break
            if keep is not None and f == keep:
                continue
            with contextlib.suppress(OSError):
                size = f.stat().st_size
                self._remove(f)
                total -= size
                removed.append(f)
        return removed

    def clear(self) -> int:
        """Remove every entry; returns how many."""
        files = self.entries()
        for f in files:
            with contextlib.suppress(OSError):
                self._remove(f)
        return len(files)


def resolve_subject_cache(cache) -> SubjectCache | None:
    """The :class:`SubjectCache` of a ``cache`` argument (see the module doc), or None (off)."""
    if isinstance(cache, SubjectCache):
        return cache
    if cache is None:
        cache = os.environ.get(ENV)
        if cache is None:
            return None
    text = str(cache).strip()
    if text.lower() in OFF:
        return None
    if text.lower() == "default":
        return SubjectCache(default_subject_cache_dir())
    return SubjectCache(text)
