"""The muscle map file (thesis sec. 4.2): :class:`MuscleSpec`, loading and validating a JSON map
(:func:`load_muscle_map`; the packaged default at :func:`default_muscle_map_path`), mirroring
of one-sided entries and the sphincter ring checks. Units: mm.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import cast

import numpy as np

from ..errors import DataNotFoundError, RigError
from .frame import mirror_label

KINDS = ("linear", "sheet", "sphincter", "passive", "eyelid")
_SEGMENTS_PER_LINE = 6  # split points per action line (the polyline has this many segments)


def default_muscle_map_path() -> Path:
    """Path of the packaged default map ``jaxface/data/muscle_map.json``."""
    return Path(str(resources.files("jaxface") / "data" / "muscle_map.json"))


# ------------------------------------------------------------------------------ specs
@dataclass(frozen=True)
class MuscleSpec:
    """One muscle of the map, face-independent (reference mm, landmark-relative).

    Attributes:
        name: unique control name, e.g. ``"zygomaticus_major_L"`` (``_L``/``_R`` for the
            subject's left/right; mid-line muscles have no suffix).
        base: the name in the file (``"zygomaticus_major"``).
        side: ``"left"``, ``"right"`` or ``"mid"``.
        kind: ``"linear"``, ``"sheet"``, ``"sphincter"``, ``"passive"`` or ``"eyelid"``.
        aus: FACS action units it takes part in.
        layer: simulation layer (0 deepest).
        lies_on: control names of the muscles it lies on (resolved per side), then "skull".
        origin, insertion: ``{"at": {label: weight}, "offset": [x, y, z]}`` points (fibres).
        centre, inner, outer: sphincter centre point and inner/outer semi-axes (ref mm).
        width: ``(origin, insertion)`` widths, ref mm; thickness: ref mm.
        grid: ``(w, h)``; n_around: samples around a sphincter.
        max_contraction: fraction of the fibre length removed at activation 1.
        angles_deg: eyelid rotation per lid at activation 1 (degrees, + moves the lid down).
        protrusion: sphincters only: forward motion of the ring (along the face's +z) per mm
            of its radial contraction, dimensionless (the lips leave the dental arch as the
            orbicularis oris purses them; 0: the ring only narrows, thesis sec. 4.3.2).
        modiolus_drag: sphincters only: how much the ring's own contraction at each mouth
            corner moves the corner muscles inserted there (0: not at all, the thesis's
            one-way coupling; 1: the modiolus moves with the ring).
        project: sphincters only: how the ring's skin samples are projected onto what the
            muscle lies on: ``"normal"`` along the smoothed skin normal (thesis sec. 4.2.1),
            ``"backward"`` along the face's -z. The lips' normals turn up and down into the
            mouth slit, so along them the orbicularis oris's inner samples landed above
            its middle ones; straight back they land on the teeth behind the red lip.
        note: free text.
    """

    name: str
    base: str
    side: str
    kind: str
    aus: tuple[str, ...] = ()
    layer: int = 0
    lies_on: tuple[str, ...] = ("skull",)
    origin: dict | None = None
    insertion: dict | None = None
    centre: dict | None = None
    inner: tuple[float, float] | None = None
    outer: tuple[float, float] | None = None
    width: tuple[float, float] = (8.0, 8.0)
    thickness: float = 3.0
    grid: tuple[int, int] = (2, 8)
    n_around: int = 16
    max_contraction: float = 0.3
    angles_deg: dict | None = None
    protrusion: float = 0.0
    modiolus_drag: float = 0.0
    project: str = "normal"
    note: str = ""

    @property
    def active(self) -> bool:
        """True for muscles that have a control (everything but ``passive``)."""
        return self.kind != "passive"


def _mirror_point(pt: dict | None) -> dict | None:
    if pt is None:
        return None
    at = {}
    for k, v in pt.get("at", {}).items():
        if k.startswith("@"):
            key = k.replace("_left", "_TMP").replace("_right", "_left").replace("_TMP", "_right")
        else:
            key = mirror_label(k)
        at[key] = v
    off = list(pt.get("offset", [0.0, 0.0, 0.0]))
    return {"at": at, "offset": [-off[0], off[1], off[2]]}


def _check_point(pt, where: str, path) -> None:
    if not isinstance(pt, dict) or not isinstance(pt.get("at"), dict) or not pt["at"]:
        raise RigError(
            f"muscle map {path}: {where} must be {{'at': {{label: weight}}, 'offset': "
            f"[x, y, z]}}, got {pt!r}."
        )
    w = np.array(list(pt["at"].values()), dtype=float)
    if not np.all(np.isfinite(w)) or w.sum() <= 0:
        raise RigError(
            f"muscle map {path}: {where} has bad weights {pt['at']!r} (finite, "
            "positive sum needed)."
        )
    off = pt.get("offset", [0, 0, 0])
    if len(off) != 3 or not np.all(np.isfinite(np.asarray(off, float))):
        raise RigError(f"muscle map {path}: {where} offset must be 3 finite numbers, got {off!r}.")


#: The expressive-range variant of the default map (issue 44; opt-in, see
#: ``docs/design/anatomy.md``): the orbicularis oris lies on the teeth behind the red lip
#: (projected straight back), purses and protrudes the lips and drags the modiolus.
#: ``load_muscle_map(edits=RANGE_EDITS)``.
RANGE_EDITS: dict[str, dict] = {
    "orbicularis_oris": {
        "protrusion": 1.2,
        "modiolus_drag": 1.0,
        "max_contraction": 0.65,
        "project": "backward",
    },
}


def load_muscle_map(path=None, *, edits: dict | None = None) -> list[MuscleSpec]:
    """Read a muscle map.

    Args:
        path: a JSON file in the format of ``jaxface/data/muscle_map.json`` (its
            ``description`` documents the fields); the packaged default map when None.
        edits: ``{muscle name in the file: {field: value}}`` applied to the entries before
            they are checked (e.g. :data:`RANGE_EDITS`).

    Returns:
        the expanded specs (bilateral muscles as separate ``_L``/``_R`` entries), sorted by
        layer (stable).

    Raises:
        DataNotFoundError: the file does not exist.
        RigError: the file is not valid JSON or an entry is malformed (named in the message).
    """
    p = default_muscle_map_path() if path is None else Path(path)
    if not p.exists():
        raise DataNotFoundError(f"muscle map not found: {p}.")
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise RigError(f"muscle map {p} is not valid JSON: {e}.") from None
    if not isinstance(data, dict) or not isinstance(data.get("muscles"), list):
        raise RigError(f"muscle map {p} must be a JSON object with a 'muscles' list.")
    for name, fields in (edits or {}).items():
        hits = [m for m in data["muscles"] if isinstance(m, dict) and m.get("name") == name]
        if not hits or not isinstance(fields, dict):
            raise RigError(
                f"muscle map {p}: edits name {name!r}, which is not a muscle of the map, or "
                "its fields are not a dict."
            )
        for m in hits:
            m.update(fields)
    defaults = data.get("defaults", {})
    out: list[MuscleSpec] = []
    seen = set()
    for k, m in enumerate(data["muscles"]):
        where = f"entry {k} ({m.get('name', '?') if isinstance(m, dict) else m!r})"
        if not isinstance(m, dict) or "name" not in m or "kind" not in m:
            raise RigError(f"muscle map {p}: {where} needs at least 'name' and 'kind'.")
        if m.get("disabled") or m.get("sides") == "none":
            continue
        kind = m["kind"]
        if kind not in KINDS:
            raise RigError(
                f"muscle map {p}: {where} has unknown kind {kind!r}; use one of {KINDS}."
            )
        d = dict(defaults.get(kind, {}))
        d.update(m)
        sides = d.get("sides", "both")
        if sides not in ("both", "mid", "left"):
            raise RigError(
                f"muscle map {p}: {where} has sides={sides!r}; use 'both', 'mid', 'left' or 'none'."
            )
        if kind == "sphincter":
            _check_point(d.get("centre"), f"{where} centre", p)
            for key in ("inner", "outer"):
                ax = d.get(key)
                if ax is None or len(ax) != 2 or min(ax) <= 0:
                    raise RigError(
                        f"muscle map {p}: {where} needs positive '{key}' semi-axes [a, b]."
                    )
            if not (d["inner"][0] < d["outer"][0] and d["inner"][1] < d["outer"][1]):
                raise RigError(
                    f"muscle map {p}: {where}: the inner ellipse must lie inside the outer."
                )
            na = d.get("n_around", 16)
            if isinstance(na, bool) or not isinstance(na, int) or na < 8:
                raise RigError(
                    f"muscle map {p}: {where} n_around must be a whole number of samples "
                    f"around the ring, at least 8; got {na!r}."
                )
        elif kind != "eyelid":
            _check_point(d.get("origin"), f"{where} origin", p)
            _check_point(d.get("insertion"), f"{where} insertion", p)
        mc = float(d.get("max_contraction", 0.0))
        if not 0.0 <= mc < 1.0:
            raise RigError(f"muscle map {p}: {where} max_contraction must be in [0, 1), got {mc}.")
        prot = d.get("protrusion", 0.0)
        if isinstance(prot, bool) or not isinstance(prot, (int, float)) or not 0.0 <= prot <= 3.0:
            raise RigError(
                f"muscle map {p}: {where} protrusion must be a number in [0, 3] (mm forward per "
                f"mm of radial contraction), got {prot!r}."
            )
        if prot and kind != "sphincter":
            raise RigError(f"muscle map {p}: {where} protrusion applies to sphincters only.")
        drag = d.get("modiolus_drag", 0.0)
        if isinstance(drag, bool) or not isinstance(drag, (int, float)) or not 0.0 <= drag <= 2.0:
            raise RigError(
                f"muscle map {p}: {where} modiolus_drag must be a number in [0, 2], got {drag!r}."
            )
        if drag and kind != "sphincter":
            raise RigError(f"muscle map {p}: {where} modiolus_drag applies to sphincters only.")
        project = d.get("project", "normal")
        if project not in ("normal", "backward"):
            raise RigError(
                f"muscle map {p}: {where} project must be 'normal' or 'backward', got {project!r}."
            )
        if project != "normal" and kind != "sphincter":
            raise RigError(f"muscle map {p}: {where} project applies to sphincters only.")
        grid = tuple(int(x) for x in d.get("grid", (2, 8)))
        if kind not in ("eyelid", "sphincter") and (len(grid) != 2 or min(grid) < 2):
            raise RigError(f"muscle map {p}: {where} grid must be [w >= 2, h >= 2], got {grid}.")
        variants = (
            [("left", "_L"), ("right", "_R")]
            if sides == "both"
            else ([("left", "_L")] if sides == "left" else [("mid", "")])
        )
        for side, suf in variants:
            mirror = side == "right"
            spec = MuscleSpec(
                name=d["name"] + suf,
                base=d["name"],
                side=side,
                kind=kind,
                aus=tuple(d.get("aus", ())),
                layer=int(d.get("layer", 0)),
                lies_on=tuple(d.get("lies_on", ("skull",))),
                origin=_mirror_point(d.get("origin")) if mirror else d.get("origin"),
                insertion=_mirror_point(d.get("insertion")) if mirror else d.get("insertion"),
                centre=_mirror_point(d.get("centre")) if mirror else d.get("centre"),
                inner=tuple(d["inner"]) if "inner" in d else None,
                outer=tuple(d["outer"]) if "outer" in d else None,
                width=cast(
                    tuple[float, float], tuple(float(x) for x in d.get("width", (8.0, 8.0)))
                ),
                thickness=float(d.get("thickness", 3.0)),
                grid=cast(tuple[int, int], grid),
                n_around=int(d.get("n_around", 16)),
                max_contraction=mc,
                angles_deg=dict(d["angles_deg"]) if "angles_deg" in d else None,
                protrusion=float(d.get("protrusion", 0.0)),
                modiolus_drag=float(d.get("modiolus_drag", 0.0)),
                project=str(project),
                note=str(d.get("note", "")),
            )
            if spec.name in seen:
                raise RigError(f"muscle map {p}: duplicate muscle name {spec.name!r}.")
            seen.add(spec.name)
            out.append(spec)
    check_sphincter_rings(out, f"muscle map {p}: ")
    known = {s.base for s in out}
    for s in out:
        for sup in s.lies_on:
            if sup != "skull" and sup not in known:
                raise RigError(f"muscle map {p}: {s.name} lies on unknown muscle {sup!r}.")
    return sorted(out, key=lambda s: s.layer)


def check_sphincter_rings(specs, where: str = "") -> None:
    """Refuse sphincters with different ``n_around``: the rig stacks their rings in one array.

    Raises:
        RigError: naming each sphincter and its number of samples around (``where`` prefixes
            the message, e.g. the map's file).
    """
    around = {s.name: s.n_around for s in specs if s.kind == "sphincter"}
    if len(set(around.values())) > 1:
        raise RigError(
            f"{where}all sphincters must have the same n_around (the rig stacks their rings); "
            f"got {around}. Set one value on each, or in defaults['sphincter']."
        )
