"""ARKit coefficients -> the physical rig's controls (``jaxface synth --arkit``).

Units mm, degrees; frame +y up, the face looks along +z, the subject's left is +x.

The map is linear and fitted once per rig (:func:`fit_inverse_map`): the rig's response to
each *unit input* is synthesised exactly (each control at activation 1; the jaw at 18 degrees
pitch, +5 and -5 degrees yaw as two inputs, 6 mm protrusion; cheek puff 1), and each ARKit
shape ``B_k`` on the rig's skin (:func:`jaxface.interop.arkit.transfer_ict_basis`) is
fitted by bounded least squares ``min_x |R x - B_k|^2``, ``0 <= x <= 1``, on the face region
(``R``: the unit responses as columns). ARKit coefficients ``c`` then drive the rig with
``x = clip(sum_k c_k x_k, 0, 1)`` (:meth:`InverseMap.controls`). The physics is not linear,
so the synthesised face approximates the ARKit blend; the map's per-shape misfit (mm) is
stored with it. Maps are cached as JSON in ``$XDG_CACHE_HOME/jaxface/arkit`` (or
``~/.cache/jaxface/arkit``), keyed by a hash of the rig's rest skin, triangles, controls, the
ICT file and the transfer's version (:data:`jaxface.interop.arkit.basis.TRANSFER_VERSION`).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FitError
from .arkit import ARKIT_NAMES, ArkitBasis, box_qp

__all__ = ["JAW_UNITS", "InverseMap", "fit_inverse_map", "inverse_map_cached", "parse_arkit"]

#: the jaw / puff unit inputs: name -> (pitch deg, yaw deg, protrusion mm, cheek puff)
JAW_UNITS: dict[str, tuple[float, float, float, float]] = {
    "jaw_pitch": (18.0, 0.0, 0.0, 0.0),
    "jaw_yaw_left": (0.0, 5.0, 0.0, 0.0),
    "jaw_yaw_right": (0.0, -5.0, 0.0, 0.0),
    "jaw_protrusion": (0.0, 0.0, 6.0, 0.0),
    "cheek_puff": (0.0, 0.0, 0.0, 1.0),
}


def parse_arkit(specs) -> dict[str, float]:
    """``["browInnerUp=0.8,jawOpen=0.3", ...]`` -> ``{name: coefficient}``.

    Raises:
        FitError: an unknown ARKit name (the message lists them), a malformed item or a value
            outside [0, 1].
    """
    out: dict[str, float] = {}
    for spec in specs:
        for item in str(spec).split(","):
            if not item.strip():
                continue
            name, _, val = item.partition("=")
            name = name.strip()
            if name not in ARKIT_NAMES:
                raise FitError(
                    f"--arkit {item!r}: unknown ARKit shape {name!r}; the names are "
                    f"{', '.join(ARKIT_NAMES)}."
                )
            try:
                v = float(val) if val.strip() else 1.0
            except ValueError:
                raise FitError(f"--arkit {item!r}: the coefficient must be a number.") from None
            if not 0.0 <= v <= 1.0:
                raise FitError(f"--arkit {item!r}: the coefficient must be in [0, 1].")
            out[name] = v
    return out


@dataclass(frozen=True)
class InverseMap:
    """Linear ARKit -> rig input map.

    Attributes:
        inputs: the rig's controls then the :data:`JAW_UNITS` names.
        matrix: ``(52, n_inputs)`` input fractions in [0, 1] per ARKit shape at coefficient 1.
        misfit_mm: ``(52,)`` RMS over the face of ``R x_k - B_k``, mm (0 for unavailable).
        shape_rms_mm: ``(52,)`` RMS of ``B_k``, mm.
        key: the cache key.
    """

    inputs: tuple[str, ...]
    matrix: np.ndarray
    misfit_mm: np.ndarray
    shape_rms_mm: np.ndarray
    key: str

    def controls(self, coefficients: dict, muscle_names) -> tuple[np.ndarray, tuple, float]:
        """``(activations (M,), (pitch deg, yaw deg, protrusion mm), cheek puff)`` of ARKit
        coefficients (name -> [0, 1])."""
        c = np.array([float(coefficients.get(n, 0.0)) for n in ARKIT_NAMES])
        x = np.clip(c @ self.matrix, 0.0, 1.0)
        names = list(muscle_names)
        a = np.array([x[self.inputs.index(n)] for n in names])
        u = {n: x[self.inputs.index(n)] for n in JAW_UNITS}
        pitch = 18.0 * u["jaw_pitch"]
        yaw = 5.0 * (u["jaw_yaw_left"] - u["jaw_yaw_right"])
        prot = 6.0 * u["jaw_protrusion"]
        return a, (float(pitch), float(yaw), float(prot)), float(u["cheek_puff"])

    def to_json(self) -> dict:
        return {
            "inputs": list(self.inputs),
            "arkit": list(ARKIT_NAMES),
            "matrix": self.matrix.tolist(),
            "misfit_mm": self.misfit_mm.tolist(),
            "shape_rms_mm": self.shape_rms_mm.tolist(),
            "key": self.key,
        }

    @classmethod
    def from_json(cls, d: dict) -> InverseMap:
        if list(d.get("arkit", [])) != list(ARKIT_NAMES):
            raise FitError("cached ARKit inverse map with other ARKit names; delete it.")
        return cls(
            tuple(d["inputs"]),
            np.asarray(d["matrix"], np.float64),
            np.asarray(d["misfit_mm"], np.float64),
            np.asarray(d["shape_rms_mm"], np.float64),
            str(d["key"]),
        )


def _unit_responses(rig, progress=None) -> tuple[tuple[str, ...], np.ndarray]:
    import jax.numpy as jnp

    from ..anatomy.jaw import JawPose
    from ..anatomy.rig import synthesize

    names = list(rig.muscle_names)
    rest = np.asarray(rig.rest, np.float64)
    cols = []
    jobs = [(n, np.eye(len(names))[i], (0.0, 0.0, 0.0, 0.0)) for i, n in enumerate(names)]
    jobs += [(n, np.zeros(len(names)), u) for n, u in JAW_UNITS.items()]
    for n, a, (p, y, t, puff) in jobs:
        if progress is not None:
            progress(n)
        x = np.asarray(
            synthesize(rig, jnp.asarray(a, rig.rest.dtype), JawPose(p, y, t), puff), np.float64
        )
        if not np.all(np.isfinite(x)):
            raise FitError(f"the rig's synthesis of the unit input {n!r} produced NaN/inf.")
        cols.append(x - rest)
    return tuple(names) + tuple(JAW_UNITS), np.stack(cols)  # (n_inputs, V, 3)


def fit_inverse_map(rig, basis: ArkitBasis, *, key: str = "", progress=None) -> InverseMap:
    """Fit the ARKit -> rig map (module doc) for a rig and the ARKit basis on its skin."""
    rest = np.asarray(rig.rest, np.float64)
    if basis.deltas.shape[1:] != rest.shape:
        raise FitError(
            f"the ARKit basis is on {basis.deltas.shape[1]} vertices, the rig's skin has "
            f"{len(rest)}."
        )
    inputs, R3 = _unit_responses(rig, progress)
    m = basis.mask
    R = R3[:, m].reshape(len(inputs), -1).T  # (3P, n)
    G = R.T @ R
    X = np.zeros((len(ARKIT_NAMES), len(inputs)))
    mis = np.zeros(len(ARKIT_NAMES))
    rms = np.zeros(len(ARKIT_NAMES))
    P = int(m.sum())
    for k in range(len(ARKIT_NAMES)):
        if not basis.available[k]:
            continue
        b = basis.deltas[k][m].reshape(-1)
        x = box_qp(G, R.T @ b)
        X[k] = x
        mis[k] = float(np.sqrt(np.sum((R @ x - b) ** 2) / P))
        rms[k] = float(np.sqrt(np.sum(b**2) / P))
    return InverseMap(inputs, X, mis, rms, key)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxface" / "arkit"


def inverse_map_cached(
    rig, landmarks, face_mask=None, *, ict_path=None, cache_dir=None, progress=None
) -> tuple[InverseMap, bool]:
    """The :class:`InverseMap` of a rig, from the cache or fitted (then cached).

    Returns:
        ``(map, from_cache)``.

    Raises:
        DataNotFoundError: no ICT data (:func:`jaxface.interop.arkit.transfer_ict_basis`).
    """
    from .arkit import default_ict_path, transfer_ict_basis
    from .arkit.basis import TRANSFER_VERSION

    rest = np.asarray(rig.rest, np.float64)
    tris = np.asarray(rig.triangles, np.int64)
    ict = Path(ict_path) if ict_path is not None else default_ict_path()
    h = hashlib.sha256()
    for arr in (rest.round(6), tris):
        h.update(np.ascontiguousarray(arr).tobytes())
    h.update("|".join(rig.muscle_names).encode())
    h.update(str(ict).encode())
    h.update(f"transfer-v{TRANSFER_VERSION}".encode())
    if face_mask is not None:
        h.update(np.asarray(face_mask, bool).tobytes())
    key = h.hexdigest()[:24]
    folder = Path(cache_dir) if cache_dir is not None else _cache_dir()
    path = folder / f"inverse_{key}.json"
    if path.is_file():
        try:
            return InverseMap.from_json(json.loads(path.read_text())), True
        except (ValueError, KeyError, FitError):
            pass  # a broken cache entry is refitted and overwritten
    basis = transfer_ict_basis(rest, tris, landmarks, face_mask, ict_path=ict)
    imap = fit_inverse_map(rig, basis, key=key, progress=progress)
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(imap.to_json(), f)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return imap, False
