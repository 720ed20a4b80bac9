"""``ObjectLibrary``: the object models ssp knows, by class name.

Build one from a folder of meshes (:meth:`ObjectLibrary.from_folder`, with an optional
``models.yaml``, see :mod:`ssp.library.properties`), from the built-in models
(:meth:`ObjectLibrary.builtin`) or from models you built yourself. :func:`prepare_folder`
decomposes and checks every model of a folder ahead of time (filling the hull cache) and
reports per model instead of stopping at the first bad one.
"""

from __future__ import annotations

import difflib
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from ssp.config import LibraryConfig, SSPConfig
from ssp.errors import ModelError, UnknownObjectError
from ssp.library.build import build_model
from ssp.library.decomposition import default_cache_dir
from ssp.library.mesh import load_convex_parts, load_mesh
from ssp.library.model import ObjectModel
from ssp.library.properties import ModelEntry, read_folder

log = logging.getLogger(__name__)

Progress = Callable[[str], Any]


def _library_config(config: LibraryConfig | SSPConfig | None) -> LibraryConfig:
    if config is None:
        return LibraryConfig()
    if isinstance(config, SSPConfig):
        return config.library
    return config


def build_entry(
    entry: ModelEntry, config: LibraryConfig, cache_dir: Path | None = None
) -> ObjectModel:
    """Build the model of one folder entry (see :func:`ssp.library.properties.read_folder`)."""
    if entry.problem is not None:
        raise entry.problem
    mesh = load_mesh(entry.mesh_path)
    parts = load_convex_parts(entry.convex_parts_path) if entry.convex_parts_path else None
    return build_model(
        entry.name,
        mesh,
        config=config,
        mass=entry.mass,
        density=entry.density,
        friction=entry.friction,
        symmetry=entry.symmetry,
        convex_parts=parts,
        source=entry.mesh_path,
        scale=entry.scale,
        cache_dir=cache_dir,
    )


class ObjectLibrary(Mapping[str, ObjectModel]):
    """Read-only mapping class name -> :class:`ObjectModel` (insertion order)."""

    def __init__(self, models: Iterable[ObjectModel] = ()) -> None:
        self._models: dict[str, ObjectModel] = {}
        for m in models:
            if not isinstance(m, ObjectModel):
                raise ModelError(f"ObjectLibrary takes ObjectModel instances, got {type(m)}")
            if m.name in self._models:
                raise ModelError(f"two models are named {m.name!r}")
            self._models[m.name] = m

    def __getitem__(self, name: str) -> ObjectModel:
        try:
            return self._models[name]
        except KeyError:
            close = difflib.get_close_matches(str(name), list(self._models), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            known = ", ".join(self._models) or "none"
            raise UnknownObjectError(
                f"unknown object class {name!r}{hint}; known classes: {known}"
            ) from None

    def __contains__(self, name: object) -> bool:
        return name in self._models

    def __iter__(self) -> Iterator[str]:
        return iter(self._models)

    def __len__(self) -> int:
        return len(self._models)

    def __repr__(self) -> str:
        return f"ObjectLibrary({list(self._models)})"

    @property
    def names(self) -> tuple[str, ...]:
        """Class names, in insertion order."""
        return tuple(self._models)

    @classmethod
    def from_folder(
        cls,
        path: str | Path,
        config: LibraryConfig | SSPConfig | None = None,
        progress: Progress | None = None,
    ) -> ObjectLibrary:
        """Every model of a folder (``models.yaml`` optional), hulls from the cache or CoACD.

        ``progress(name)`` is called after each model is built (for a progress bar; the
        number of models is ``len(ssp.library.properties.read_folder(path))``).

        Raises:
            ModelError (or a subclass) for the first model that cannot be built.
        """
        cfg = _library_config(config)
        cache_dir = default_cache_dir(cfg)
        models = []
        for entry in read_folder(path):
            models.append(build_entry(entry, cfg, cache_dir))
            if progress is not None:
                progress(entry.name)
        return cls(models)

    @classmethod
    def builtin(cls, config: LibraryConfig | SSPConfig | None = None) -> ObjectLibrary:
        """The models shipped with ssp (:mod:`ssp.library.builtin`), with exact convex parts."""
        from ssp.library.builtin import builtin_specs

        cfg = _library_config(config)
        return cls(
            build_model(
                spec.name,
                spec.mesh,
                config=cfg,
                density=spec.density,
                friction=spec.friction,
                symmetry=spec.symmetry,
                convex_parts=spec.parts,
            )
            for spec in builtin_specs()
        )


def prepare_folder(
    path: str | Path,
    config: LibraryConfig | SSPConfig | None = None,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Build every model of a folder (filling the hull cache), reporting instead of raising.

    Returns one dict per model: ``name``, ``n_parts``, ``method``, ``iou``, ``seconds``
    (decomposition, 0 when cached), ``cached``, ``build_seconds`` (whole model) and ``error``
    (None, or the message of the model that failed; its other fields are then None).

    Raises:
        ModelFileError / ModelError: only when the folder or its ``models.yaml`` is unusable.
    """
    cfg = _library_config(config)
    cache_dir = default_cache_dir(cfg)
    report = []
    for entry in read_folder(path):
        row: dict[str, Any] = {
            "name": entry.name,
            "n_parts": None,
            "method": None,
            "iou": None,
            "seconds": None,
            "cached": None,
            "note": "",
            "build_seconds": None,
            "error": None,
        }
        t0 = time.perf_counter()
        try:
            model = build_entry(entry, cfg, cache_dir)
        except Exception as exc:  # one bad model must not stop the others
            if isinstance(exc, ModelError):
                log.warning("model %r failed: %s", entry.name, exc)
            else:
                log.exception("model %r failed unexpectedly", entry.name)
            row["error"] = (
                str(exc) if isinstance(exc, ModelError) else (f"{type(exc).__name__}: {exc}")
            )
        else:
            d = model.decomposition
            row.update(
                n_parts=d.n_parts,
                method=d.method,
                iou=d.iou,
                seconds=d.seconds,
                cached=d.cached,
                note=d.note,
            )
        row["build_seconds"] = time.perf_counter() - t0
        report.append(row)
        if progress is not None:
            progress(entry.name)
    return report
