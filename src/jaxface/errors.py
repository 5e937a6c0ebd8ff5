"""Typed errors raised by jaxface.

Every error a user can trigger with bad input derives from :class:`JaxfaceError`, and
each message says what was wrong, where (file, element indices, landmark names) and what
to do about it. Catch ``JaxfaceError`` to handle all of them; the subclasses also derive
from the matching builtin (``ValueError``, ``KeyError``, ``FileNotFoundError``) so that
generic handlers keep working.
"""

from __future__ import annotations

from typing import Any


class JaxfaceError(Exception):
    """Base class of every error jaxface raises on bad input."""


class MeshError(JaxfaceError, ValueError):
    """A mesh is malformed: NaN/inf coordinates, bad indices, degenerate or
    non-manifold triangles, inconsistent orientation, unreadable or truncated file.

    Attributes:
        problem: short machine-readable tag, e.g. ``"non_manifold_edges"``.
        elements: indices of the offending vertices/triangles/edges (may be empty).
        edges: ``(k, 2)`` offending vertex pairs; set only for edge problems (non-manifold
            edges, inconsistent orientation).
    """

    edges: Any

    def __init__(self, message: str, *, problem: str = "invalid_mesh", elements=()):
        super().__init__(message)
        self.problem = problem
        self.elements = tuple(int(e) for e in elements) if elements is not None else ()


class UnitsError(JaxfaceError, ValueError):
    """Unknown unit, or coordinates whose size does not fit the declared unit
    (for example a face 0.2 units wide declared as millimetres)."""


class LandmarkError(JaxfaceError, KeyError):
    """Missing, misnamed, duplicated or mirrored landmarks.

    Attributes:
        missing: the canonical names that were required but absent.
    """

    def __init__(self, message: str, *, missing=()):
        super().__init__(message)
        self.missing = tuple(missing)

    def __str__(self) -> str:  # KeyError would otherwise repr() the message
        return str(self.args[0]) if self.args else ""


class ScanFormatError(JaxfaceError, ValueError):
    """A scan file (.bnt, .lm2, .lm3, OBJ/PLY scan) is truncated, corrupt, has wrong
    counts, contains no valid points, or contains NaN where data is expected."""


class RBFError(JaxfaceError, ValueError):
    """An RBF/TPS morph cannot be fitted: too few centres, coplanar centres,
    duplicated centres, or mismatched source/target shapes."""


class RigError(JaxfaceError, ValueError):
    """The anatomical rig cannot be built or driven with the given inputs
    (unknown muscle names, activations of the wrong shape, bad muscle-map file)."""


class RigOptionError(RigError):
    """A rig option or config object that the chosen backend does not take (for example
    ``muscle_iterations`` with ``backend="ltw"``), refused instead of silently dropped.

    Attributes:
        backend: the backend asked for; options: the names of the options refused.
    """

    def __init__(self, message: str, *, backend: str = "", options=()):
        super().__init__(message)
        self.backend = backend
        self.options = tuple(options)


class FitError(JaxfaceError, RuntimeError):
    """An inverse fit could not be set up or did not produce a usable result."""


class DataNotFoundError(JaxfaceError, FileNotFoundError):
    """Reference data (the ``shared/`` folder) or an input file is missing."""


class OutputError(JaxfaceError, ValueError):
    """An output cannot be written: its folder cannot be created (a parent is a file, no
    permission), the path is a folder, or the data to write holds NaN/inf (jaxface never
    writes non-finite numbers)."""


class InputPathError(JaxfaceError, ValueError):
    """An input path exists but is not usable as given: a folder where a file is expected,
    an unreadable file, or a file of another format than its suffix says."""
