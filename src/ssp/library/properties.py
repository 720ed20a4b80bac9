"""The per-folder ``models.yaml``: units, scale, masses, friction, convex parts, decomposition
settings and symmetries.

In the spirit of the reference's ``object_property_database.yaml`` (notes/reference-impl.md
section 8), but every key is validated (unknown keys are errors, so typos fail loudly)::

    units: m            # or cm / mm; applies to every mesh of the folder unless overridden
    defaults: {density: 700, friction: 1.0}
    objects:
      drill:
        mesh: drill.obj            # default: <name>.obj / .ply / .stl in the folder
        mass: 1.2                  # kg, or density: kg/m^3 (not both)
        friction: 0.8
        units: m                   # optional per-object override
        scale: 0.05                # or [sx, sy, sz]; multiplies the mesh after `units`
        convex_parts: drill.parts.obj   # one convex part per OBJ object/group; skips CoACD
        decomposition: {threshold: 0.03, max_parts: 12}   # any DecompositionConfig field
        symmetries: ["rotate 180 about x", {axis: [0, 0, 1], angle: 90, offset: [0, 0, 0]}]
        symmetries_discrete: [[16 numbers, row-major 4x4, translation in the file's units]]
        symmetries_continuous: [{axis: [0, 0, 1], offset: [0, 0, 0]}]
        symmetry: {detect: true, tolerance: 0.002}   # use detected approximate symmetries

``symmetries`` and ``symmetries_discrete`` are generators: the model's discrete symmetries are
the group they generate (:meth:`ssp.library.symmetry.Symmetry.from_generators`). Offsets and
translations are in the file's units (``units`` and ``scale`` apply); angles in degrees; the
detection tolerance in metres.

A folder without ``models.yaml`` is fine: every mesh file is a model named after its stem, with
the defaults. Mesh files a present ``models.yaml`` does not list are loaded with the defaults too.
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from ssp.config import DecompositionConfig, read_yaml
from ssp.errors import ModelError, ModelFileError
from ssp.library.mesh import UNIT_SCALES
from ssp.library.symmetry import Symmetry, rotation_transform

log = logging.getLogger(__name__)

PROPERTIES_FILE = "models.yaml"
#: Mesh file suffixes picked up from a models folder, in order of preference.
MESH_SUFFIXES = (".obj", ".ply", ".stl")

Units = Literal["m", "cm", "mm"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Properties(_Strict):
    mass: float | None = Field(None, gt=0, allow_inf_nan=False, description="kg")
    density: float | None = Field(None, gt=0, allow_inf_nan=False, description="kg/m^3")
    friction: float | None = Field(None, ge=0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _mass_or_density(self) -> _Properties:
        if self.mass is not None and self.density is not None:
            raise ValueError("give mass or density, not both")
        return self


class DefaultsSpec(_Properties):
    """Folder-wide defaults (an object's own values win)."""


class ContinuousSymmetrySpec(_Strict):
    axis: tuple[float, float, float]
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class RotationSpec(_Strict):
    """A rotation by ``angle`` degrees about ``axis`` through ``offset`` (file units)."""

    axis: tuple[float, float, float]
    angle: float = Field(allow_inf_nan=False, description="degrees")
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


_ROTATE = re.compile(
    r"^\s*rotate\s+(?P<angle>[-+]?\d+(?:\.\d*)?)\s*(?:deg|degrees)?\s+about\s+"
    r"(?P<sign>[-+]?)(?P<axis>[xyz])\s*$",
    re.IGNORECASE,
)


def parse_rotation(text: str) -> RotationSpec:
    """``"rotate 90 about z"`` (degrees; axis x, y or z, optionally signed) as a rotation."""
    m = _ROTATE.match(text)
    if m is None:
        raise ValueError(
            f"cannot read symmetry {text!r}; write 'rotate N about x|y|z' (N in degrees), "
            "{axis: [x, y, z], angle: N, offset: [x, y, z]}, or use symmetries_discrete"
        )
    axis = [0.0, 0.0, 0.0]
    axis["xyz".index(m["axis"].lower())] = -1.0 if m["sign"] == "-" else 1.0
    return RotationSpec(axis=(axis[0], axis[1], axis[2]), angle=float(m["angle"]))


class SymmetryDetectSpec(_Strict):
    """Approximate symmetries detected from the shape (see :mod:`ssp.library.symmetry`)."""

    detect: bool = Field(False, description="use the detected symmetries as the model's")
    tolerance: float = Field(
        0.002, gt=0, allow_inf_nan=False, description="largest surface distance (MSSD), m"
    )


def _optional_model(name: str, source: type[BaseModel]) -> type[BaseModel]:
    """A strict model with every field of ``source`` optional (same types and bounds)."""
    fields: dict[str, Any] = {}
    for key, info in source.model_fields.items():
        annotation: Any = info.annotation
        if info.metadata:
            # a name, not a (x, *y) display in the brackets: mypy reads that as 3.11 syntax
            params = (annotation, *info.metadata)
            annotation = Annotated[params]
        fields[key] = (annotation | None, Field(None, description=info.description))
    return create_model(name, __base__=_Strict, **fields)


#: Per-object ``decomposition:`` settings: any :class:`~ssp.config.DecompositionConfig` field.
DecompositionSpec = _optional_model("DecompositionSpec", DecompositionConfig)


class ObjectSpec(_Properties):
    """One ``objects:`` entry."""

    mesh: str | None = None
    units: Units | None = None
    scale: float | tuple[float, float, float] | None = Field(
        None, description="factor (or x, y, z factors) applied after units"
    )
    convex_parts: str | None = None
    description: str = ""
    decomposition: DecompositionSpec | None = None  # type: ignore[valid-type]
    symmetries: list[RotationSpec] = Field(default_factory=list)
    symmetries_discrete: list[list[float]] = Field(default_factory=list)
    symmetries_continuous: list[ContinuousSymmetrySpec] = Field(default_factory=list)
    symmetry: SymmetryDetectSpec | None = None

    @field_validator("symmetries", mode="before")
    @classmethod
    def _rotations(cls, v: Any) -> Any:
        if isinstance(v, list):
            return [parse_rotation(x) if isinstance(x, str) else x for x in v]
        return v

    @field_validator("scale")
    @classmethod
    def _positive_scale(cls, v: Any) -> Any:
        values = [v] if isinstance(v, (int, float)) else list(v or ())
        if any(not (math.isfinite(x) and x > 0) for x in values):
            raise ValueError(f"scale must be positive and finite, got {v!r}")
        return v

    @field_validator("symmetries_discrete")
    @classmethod
    def _sixteen(cls, v: list[list[float]]) -> list[list[float]]:
        for i, s in enumerate(v):
            if len(s) != 16:
                raise ValueError(f"entry {i} has {len(s)} numbers; a row-major 4x4 needs 16")
        return v


class PropertiesFile(_Strict):
    """The whole ``models.yaml``."""

    units: Units = "m"
    defaults: DefaultsSpec = Field(default_factory=DefaultsSpec)
    objects: dict[str, ObjectSpec | None] = Field(default_factory=dict)


@dataclass(frozen=True)
class ModelEntry:
    """Everything needed to build one model of a folder (paths absolute, scale to metres)."""

    name: str
    mesh_path: Path
    #: To metres: one factor or (x, y, z) factors (units times scale).
    scale: float | tuple[float, float, float] = 1.0
    mass: float | None = None
    density: float | None = None
    friction: float | None = None
    convex_parts_path: Path | None = None
    symmetry: Symmetry | None = None
    description: str = ""
    #: Per-model :class:`~ssp.config.DecompositionConfig` overrides (``decomposition:``).
    decomposition: dict[str, Any] = field(default_factory=dict)
    #: ``symmetry: {detect, tolerance}``, or None (detection not asked for).
    symmetry_detect: SymmetryDetectSpec | None = None
    #: Why this entry cannot be built (e.g. its mesh file is missing); raised when building it.
    problem: ModelError | None = None


def _allowed_keys(model: type[BaseModel]) -> list[str]:
    return list(model.model_fields)


def _describe_error(err: Mapping[str, Any]) -> str:
    loc = [str(x) for x in err.get("loc", ())]
    # pydantic adds the union member name ("ObjectSpec") to the location; drop it
    wrappers = (
        "ObjectSpec",
        "DefaultsSpec",
        "ContinuousSymmetrySpec",
        "DecompositionSpec",
        "RotationSpec",
        "SymmetryDetectSpec",
    )
    loc = [x for x in loc if x not in wrappers]
    where = ".".join(loc) or "(top level)"
    if err.get("type") == "extra_forbidden":
        key = loc[-1] if loc else "?"
        if len(loc) == 1:
            allowed = _allowed_keys(PropertiesFile)
        elif loc[0] == "defaults":
            allowed = _allowed_keys(DefaultsSpec)
        elif "symmetries_continuous" in loc:
            allowed = _allowed_keys(ContinuousSymmetrySpec)
        elif "decomposition" in loc:
            allowed = _allowed_keys(DecompositionSpec)
        elif "symmetries" in loc:
            allowed = _allowed_keys(RotationSpec)
        elif "symmetry" in loc:
            allowed = _allowed_keys(SymmetryDetectSpec)
        else:
            allowed = _allowed_keys(ObjectSpec)
        close = difflib.get_close_matches(key, allowed, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"{where}: unknown key {key!r}{hint}; allowed keys: {', '.join(allowed)}"
    msg = str(err.get("msg", "invalid value"))
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    return f"{where}: {msg}"


def read_properties(path: str | Path) -> PropertiesFile:
    """Parse and validate a ``models.yaml``.

    Raises:
        ModelFileError: unreadable or not YAML. ModelError: invalid content (file and key named).
    """
    path = Path(path)
    data = read_yaml(path, ModelFileError)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ModelError(f"{path}: the top level must be a mapping (units, defaults, objects)")
    try:
        return PropertiesFile.model_validate(data)
    except ValidationError as exc:
        lines = [_describe_error(e) for e in exc.errors()]
        raise ModelError(f"{path}: invalid model properties:\n  " + "\n  ".join(lines)) from None


def _find_mesh(folder: Path, name: str) -> Path | None:
    for suffix in MESH_SUFFIXES:
        for candidate in (folder / f"{name}{suffix}", folder / f"{name}{suffix.upper()}"):
            if candidate.is_file():
                return candidate
    return None


def _mesh_files(folder: Path) -> dict[str, Path]:
    """Mesh files of ``folder`` by stem (preferring .obj, then .ply, then .stl)."""
    found: dict[str, Path] = {}
    files = sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES),
        key=lambda p: (p.stem, MESH_SUFFIXES.index(p.suffix.lower()), p.name),
    )
    for p in files:
        if p.stem in found:
            log.warning("ignoring %s: %s has the same model name", p.name, found[p.stem].name)
            continue
        found[p.stem] = p
    return found


def _entry(
    folder: Path, props_path: Path, props: PropertiesFile, name: str, spec: ObjectSpec
) -> ModelEntry:
    """The :class:`ModelEntry` of one ``objects:`` item; ModelError naming the file and key."""
    defaults = props.defaults
    if spec.mesh is not None:
        mesh_path = (folder / spec.mesh).resolve()
        if not mesh_path.is_file():
            raise ModelFileError(f"{props_path}: objects.{name}.mesh: file not found: {spec.mesh}")
    else:
        found = _find_mesh(folder, name)
        if found is None:
            raise ModelFileError(
                f"{props_path}: objects.{name}: no mesh file {name}.obj/.ply/.stl in "
                f"{folder}; add `mesh: <file>`"
            )
        mesh_path = found.resolve()
    parts_path = None
    if spec.convex_parts is not None:
        parts_path = (folder / spec.convex_parts).resolve()
        if not parts_path.is_file():
            raise ModelFileError(
                f"{props_path}: objects.{name}.convex_parts: file not found: {spec.convex_parts}"
            )
    unit = UNIT_SCALES[spec.units or props.units]
    factors = unit * np.broadcast_to(np.asarray(1.0 if spec.scale is None else spec.scale), (3,))
    scale: float | tuple[float, float, float] = (
        float(factors[0])
        if np.all(factors == factors[0])
        else (float(factors[0]), float(factors[1]), float(factors[2]))
    )
    if spec.mass is not None or spec.density is not None:
        mass, density = spec.mass, spec.density
    else:
        mass, density = defaults.mass, defaults.density
    symmetry = None
    if spec.symmetries or spec.symmetries_discrete or spec.symmetries_continuous:
        generators = [np.asarray(s, dtype=float).reshape(4, 4) for s in spec.symmetries_discrete]
        generators += [rotation_transform(r.axis, r.angle, r.offset) for r in spec.symmetries]
        try:
            symmetry = Symmetry.from_generators(
                generators,
                [(c.axis, c.offset) for c in spec.symmetries_continuous],
                scale=factors,
            )
        except ModelError as exc:
            raise ModelError(f"{props_path}: objects.{name}: {exc}") from exc
    return ModelEntry(
        name=name,
        mesh_path=mesh_path,
        scale=scale,
        mass=mass,
        density=density,
        friction=spec.friction if spec.friction is not None else defaults.friction,
        convex_parts_path=parts_path,
        symmetry=symmetry,
        description=spec.description,
        decomposition=(
            spec.decomposition.model_dump(exclude_none=True) if spec.decomposition else {}
        ),
        symmetry_detect=spec.symmetry,
    )


def read_folder(folder: str | Path) -> list[ModelEntry]:
    """The models of a folder: its ``models.yaml`` entries plus unlisted mesh files.

    An entry whose mesh or parts file is missing is returned with ``problem`` set (building
    it raises that error), so one bad entry does not hide the others.

    Raises:
        ModelFileError: the folder is missing. ModelError: ``models.yaml`` is invalid.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ModelFileError(f"models folder not found: {folder}")
    props_path = folder / PROPERTIES_FILE
    if not props_path.is_file() and (folder / BOP_MODELS_INFO).is_file():
        return read_bop_models(folder)
    props = read_properties(props_path) if props_path.is_file() else PropertiesFile()
    defaults = props.defaults
    entries: list[ModelEntry] = []
    used: set[Path] = set()

    for name, spec in props.objects.items():
        try:
            entry = _entry(folder, props_path, props, name, spec or ObjectSpec())
        except ModelError as exc:
            entry = ModelEntry(name=name, mesh_path=folder / name, problem=exc)
        if entry.problem is None:
            used.add(entry.mesh_path)
            if entry.convex_parts_path is not None:
                used.add(entry.convex_parts_path)
        entries.append(entry)

    listed = {e.name for e in entries}
    for stem, path in _mesh_files(folder).items():
        if path.resolve() in used or stem in listed:
            continue
        if props_path.is_file():
            log.info("%s is not listed in %s; loading it with the defaults", path.name, props_path)
        entries.append(
            ModelEntry(
                name=stem,
                mesh_path=path.resolve(),
                scale=UNIT_SCALES[props.units],
                mass=defaults.mass,
                density=defaults.density,
                friction=defaults.friction,
            )
        )
    return entries


#: The BOP toolkit's model description file (``models/models_info.json``).
BOP_MODELS_INFO = "models_info.json"


def read_bop_models(folder: str | Path) -> list[ModelEntry]:
    """The models of a BOP ``models/`` folder as the toolkit publishes it: ``obj_XXXXXX.ply``
    meshes in **mm** and ``models_info.json`` (``{obj_id: {diameter, ..., symmetries_discrete
    (4x4 row-major, mm), symmetries_continuous ({axis, offset mm})}}``).

    Each ``obj_id`` of ``models_info.json`` is one model named ``obj_XXXXXX`` (the mesh's file
    name), scaled to metres, with its declared symmetries; mass and friction are the defaults.
    An obj_id without its mesh file is returned with ``problem`` set.

    Raises:
        ModelFileError: the folder or ``models_info.json`` is missing or unreadable.
        ModelError: a malformed ``models_info.json`` entry.
    """
    folder = Path(folder)
    info_path = folder / BOP_MODELS_INFO
    try:
        info = json.loads(info_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ModelFileError(f"{info_path}: cannot read: {exc}") from exc
    if not isinstance(info, dict):
        raise ModelError(f"{info_path}: expected an object {{obj_id: {{...}}}}")
    entries: list[ModelEntry] = []
    for key in sorted(
        info, key=lambda k: (not str(k).isdigit(), int(k) if str(k).isdigit() else k)
    ):
        if not str(key).isdigit() or int(key) < 1:
            raise ModelError(f"{info_path}: obj_id {key!r} is not an integer >= 1")
        name = f"obj_{int(key):06d}"
        mesh = folder / f"{name}.ply"
        try:
            sym = Symmetry.from_bop(
                info[key] or {}, scale=UNIT_SCALES["mm"], name=f"{info_path}: obj_id {key}"
            )
        except ModelError as exc:
            raise ModelError(f"{info_path}: obj_id {key}: {exc}") from exc
        problem = None if mesh.is_file() else ModelFileError(f"{mesh}: no such mesh file")
        entries.append(
            ModelEntry(
                name=name,
                mesh_path=mesh.resolve(),
                scale=UNIT_SCALES["mm"],
                symmetry=sym,
                description=f"BOP obj_id {int(key)} ({info_path})",
                problem=problem,
            )
        )
    return entries
