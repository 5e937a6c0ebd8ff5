"""The :class:`Landmarks` container (named 3-D points in mm, immutable) and
:func:`attach_to_mesh` (closest-point projection onto a mesh)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import cast

import numpy as np

from ..errors import LandmarkError
from .labels import MIRROR_PAIRS, _normalise_name

__all__ = ["Landmarks", "attach_to_mesh"]


# ---------------------------------------------------------------------------------------------
# container
# ---------------------------------------------------------------------------------------------


class Landmarks:
    """Named 3-D landmarks in mm (immutable).

    Names are stored in canonical form when recognised (:func:`canonical_label`); other labels
    are kept as given (whitespace collapsed). Lookup accepts any spelling variant.

    Attributes:
        names: ``(N,)`` tuple of labels.
        positions: ``(N, 3)`` float64 read-only array, mm.

    Args:
        names: N labels (unique after canonicalisation).
        positions: ``(N, 3)`` finite coordinates, mm.

    Raises:
        LandmarkError: wrong shapes, duplicated labels or non-finite positions.
    """

    __slots__ = ("names", "positions", "_index")

    def __init__(self, names: Iterable[str], positions):
        names = tuple(_normalise_name(n) for n in names)
        pos = np.array(positions, dtype=np.float64, copy=True)
        if pos.size == 0 and len(names) == 0:
            pos = pos.reshape(0, 3)
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] != len(names):
            raise LandmarkError(
                f"Landmarks needs N names and (N, 3) positions in mm; got {len(names)} names and "
                f"positions of shape {pos.shape}."
            )
        seen: dict[str, int] = {}
        dups = []
        for n in names:
            seen[n] = seen.get(n, 0) + 1
            if seen[n] == 2:
                dups.append(n)
        if dups:
            raise LandmarkError(
                f"duplicated landmark label(s) {dups} (after normalising spelling variants); "
                f"each landmark must appear once."
            )
        bad = [n for n, p in zip(names, pos) if not np.all(np.isfinite(p))]
        if bad:
            raise LandmarkError(
                f"landmark(s) {bad} have NaN/inf coordinates; leave missing landmarks out "
                f"instead of marking them with NaN."
            )
        pos.setflags(write=False)
        self.names = names
        self.positions = pos
        self._index = {n: i for i, n in enumerate(names)}

    # -------------------------------------------------------------- lookup
    def _find(self, name: str) -> int | None:
        key = _normalise_name(name)
        if key in self._index:
            return self._index[key]
        low = key.lower()
        for n, i in self._index.items():  # custom labels: case-insensitive
            if n.lower() == low:
                return i
        return None

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and self._find(name) is not None

    def __getitem__(self, name: str) -> np.ndarray:
        """``(3,)`` position (mm) of a landmark; any spelling variant of its label.

        Raises:
            LandmarkError: the landmark is absent (the message lists the close matches).
        """
        i = self._find(name)
        if i is None:
            close = difflib.get_close_matches(_normalise_name(name), self.names, n=3, cutoff=0.5)
            hint = f" Did you mean {close}?" if close else ""
            raise LandmarkError(
                f"landmark {name!r} not found among {len(self.names)} landmarks "
                f"{list(self.names)}.{hint}",
                missing=(_normalise_name(name),),
            )
        return self.positions[i]

    def get(self, name: str, default=None):
        """Position of ``name`` (mm) or ``default`` if absent."""
        i = self._find(name)
        return default if i is None else self.positions[i]

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self):
        return iter(self.names)

    def __repr__(self) -> str:
        return f"Landmarks({len(self.names)}: {', '.join(self.names[:4])}{', ...' if len(self) > 4 else ''})"

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Landmarks)
            and self.names == other.names
            and np.array_equal(self.positions, other.positions)
        )

    __hash__ = None  # type: ignore[assignment]

    # -------------------------------------------------------------- selections
    def missing(self, names: Iterable[str]) -> tuple[str, ...]:
        """The labels (normalised) among ``names`` that are absent."""
        if isinstance(names, str):
            names = (names,)
        return tuple(_normalise_name(n) for n in names if self._find(n) is None)

    def require(self, names: Iterable[str]) -> Landmarks:
        """The landmarks ``names`` in that order; raise if any is absent.

        Raises:
            LandmarkError: listing *every* missing name (``error.missing``), not just the first.
        """
        if isinstance(names, str):
            names = (names,)
        names = tuple(names)
        miss = self.missing(names)
        if miss:
            raise LandmarkError(
                f"{len(miss)} required landmark(s) missing: {list(miss)}. Present: "
                f"{list(self.names)}. Add them (e.g. pick them on the mesh) or choose a method "
                f"that needs fewer landmarks.",
                missing=miss,
            )
        idx = [cast(int, self._find(n)) for n in names]  # all present: checked above
        return Landmarks([self.names[i] for i in idx], self.positions[idx])

    def subset(self, names: Iterable[str]) -> Landmarks:
        """The landmarks among ``names`` that are present, in the order of ``names``
        (absent ones are skipped; use :meth:`require` to insist)."""
        if isinstance(names, str):
            names = (names,)
        idx = [i for i in (self._find(n) for n in names) if i is not None]
        return Landmarks([self.names[i] for i in idx], self.positions[idx])

    def array(self, names: Iterable[str]) -> np.ndarray:
        """``(len(names), 3)`` positions, mm, in the given order (all must be present)."""
        return np.array(self.require(names).positions)

    def to_dict(self) -> dict[str, np.ndarray]:
        """``{label: (3,) position in mm}`` (copies)."""
        return {n: np.array(p) for n, p in zip(self.names, self.positions)}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> Landmarks:
        """From ``{label: (3,) position in mm}``."""
        names = list(d.keys())
        pos = np.array([np.asarray(d[n], dtype=np.float64).reshape(3) for n in names]).reshape(
            -1, 3
        )
        return cls(names, pos)

    def with_positions(self, positions) -> Landmarks:
        """Same labels, new ``(N, 3)`` positions (mm)."""
        return Landmarks(self.names, positions)

    def transformed(self, rotation=None, translation=None, scale: float = 1.0) -> Landmarks:
        """``p' = scale * R p + t`` for every landmark (``R`` (3, 3), ``t`` (3,) mm)."""
        p = self.positions * float(scale)
        if rotation is not None:
            p = p @ np.asarray(rotation, dtype=np.float64).T
        if translation is not None:
            p = p + np.asarray(translation, dtype=np.float64)
        return Landmarks(self.names, p)

    def mirrored(self, swap_labels: bool = True) -> Landmarks:
        """Reflect through the x = 0 plane (x -> -x). With ``swap_labels`` the left/right labels
        are exchanged too (the physically mirrored face, correctly labelled again); without,
        the result is what a mirrored input looks like (and fails :func:`check_side`)."""
        p = np.array(self.positions)
        p[:, 0] = -p[:, 0]
        names = list(self.names)
        if swap_labels:
            swap = {}
            for left, right in MIRROR_PAIRS:
                swap[left], swap[right] = right, left
            names = [swap.get(n, n) for n in names]
        return Landmarks(names, p)

    def on_mesh(self, mesh, *, max_distance: float | None = None):
        """Attach to a mesh as surface points: see :func:`attach_to_mesh`."""
        return attach_to_mesh(self, mesh, max_distance=max_distance)


# attaching to a mesh
# ---------------------------------------------------------------------------------------------


def attach_to_mesh(landmarks: Landmarks, mesh, *, max_distance: float | None = None):
    """Attach landmarks to a mesh as surface points (closest-point projection).

    Args:
        landmarks: the landmarks (mm).
        mesh: a :class:`jaxface.mesh.TriMesh` (mm).
        max_distance: if given (mm), raise when a landmark is farther than this from the
            surface (a landmark set that does not belong to this mesh, or wrong units).

    Returns:
        ``(SurfacePoints (N,), distances (N,) mm)`` in the order of ``landmarks.names``.

    Raises:
        LandmarkError: a landmark lies farther than ``max_distance`` from the surface.
    """
    sp, dist = mesh.closest_points(landmarks.positions)
    if max_distance is not None:
        far = [(n, float(d)) for n, d in zip(landmarks.names, dist) if d > max_distance]
        if far:
            listed = ", ".join(f"{n!r} ({d:.2f} mm)" for n, d in far)
            raise LandmarkError(
                f"{len(far)} landmark(s) lie more than {max_distance:g} mm from the mesh "
                f"surface: {listed}. Are the landmarks for this mesh, in the same units and "
                f"frame?",
                missing=tuple(n for n, _ in far),
            )
    return sp, dist
