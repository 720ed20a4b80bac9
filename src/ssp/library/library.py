"""``ObjectLibrary``: the object models ssp knows, by class name.

Build one from a folder of meshes (:meth:`ObjectLibrary.from_folder`, with an optional
``models.yaml``, see :mod:`ssp.library.properties`), from the built-in models
(:meth:`ObjectLibrary.builtin`) or from models you built yourself. :func:`prepare_folder`
decomposes and checks every model of a folder ahead of time (filling the hull cache, and
detecting approximate symmetries) and reports per model instead of stopping at the first bad
one; ``from_folder(..., on_error="skip")`` loads the good models of a folder and reports the
bad ones in :attr:`ObjectLibrary.skipped`.
"""

from __future__ import annotations

import difflib
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, Literal

from ssp.config import DecompositionConfig, LibraryConfig, SSPConfig
from ssp.errors import ModelError, UnknownObjectError
from ssp.library.build import build_model
from ssp.library.decomposition import Status, default_cache_dir
from ssp.library.mesh import load_convex_parts, load_mesh
from ssp.library.model import ObjectModel
from ssp.library.properties import ModelEntry, read_folder
from ssp.library.symmetry import DETECT_TOLERANCE

log = logging.getLogger(__name__)

Progress = Callable[[str], Any]


def _library_config(config: LibraryConfig | SSPConfig | None) -> LibraryConfig:
    if config is None:
        return LibraryConfig()
    if isinstance(config, SSPConfig):
        return config.library
    return config


def entry_config(entry: ModelEntry, config: LibraryConfig) -> LibraryConfig:
    """``config`` with the entry's own ``decomposition:`` settings (models.yaml) applied."""
    if not entry.decomposition:
        return config
    merged = DecompositionConfig.model_validate(
        {**config.decomposition.model_dump(), **entry.decomposition}
    )
    return config.model_copy(update={"decomposition": merged})


def build_entry(
    entry: ModelEntry,
    config: LibraryConfig,
    cache_dir: Path | None = None,
    status: Status | None = None,
    detect_symmetry: bool = False,
) -> ObjectModel:
    """Build the model of one folder entry (see :func:`ssp.library.properties.read_folder`).

    Symmetries are detected when the entry asks for it (``symmetry:`` in models.yaml, then
    also used when ``detect: true``) or when ``detect_symmetry`` is set (reported only).
    """
    if entry.problem is not None:
        raise entry.problem
    mesh = load_mesh(entry.mesh_path)
    parts = load_convex_parts(entry.convex_parts_path) if entry.convex_parts_path else None
    spec = entry.symmetry_detect
    tolerance = spec.tolerance if spec is not None else None
    if tolerance is None and detect_symmetry:
        tolerance = DETECT_TOLERANCE
    return build_model(
        entry.name,
        mesh,
        config=entry_config(entry, config),
        mass=entry.mass,
        density=entry.density,
        friction=entry.friction,
        symmetry=entry.symmetry,
        convex_parts=parts,
        source=entry.mesh_path,
        scale=entry.scale,
        cache_dir=cache_dir,
        status=status,
        detect_symmetry=tolerance,
        use_detected_symmetry=spec is not None and spec.detect,
    )


def _error_text(exc: Exception) -> str:
    return str(exc) if isinstance(exc, ModelError) else f"{type(exc).__name__}: {exc}"


class ObjectLibrary(Mapping[str, ObjectModel]):
    """Read-only mapping class name -> :class:`ObjectModel` (insertion order)."""

    def __init__(
        self, models: Iterable[ObjectModel] = (), skipped: Mapping[str, str] | None = None
    ) -> None:
        self._skipped = dict(skipped or {})
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

    @property
    def skipped(self) -> dict[str, str]:
        """Models of the folder that could not be built: name -> reason (``on_error="skip"``)."""
        return dict(self._skipped)

    @classmethod
    def from_folder(
        cls,
        path: str | Path,
        config: LibraryConfig | SSPConfig | None = None,
        progress: Progress | None = None,
        *,
        on_error: Literal["raise", "skip"] = "raise",
        status: Status | None = None,
    ) -> ObjectLibrary:
        """Every model of a folder (``models.yaml`` optional), hulls from the cache or CoACD.

        ``progress(name)`` is called after each model is built (for a progress bar; the
        number of models is ``len(ssp.library.properties.read_folder(path))``), and
        ``status(text)`` with what is being done meanwhile (decomposition stages, CoACD's
        running time). ``on_error="skip"``: a model that cannot be built is logged (warning,
        with the reason) and left out, and listed in :attr:`skipped`; the others load.

        Raises:
            ModelError (or a subclass) for the first model that cannot be built (``"raise"``),
            or when the folder or its ``models.yaml`` is unusable, or (``"skip"``) when no
            model at all could be built.
        """
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        cfg = _library_config(config)
        cache_dir = default_cache_dir(cfg)
        models = []
        skipped: dict[str, str] = {}
        entries = read_folder(path)
        for entry in entries:
            try:
                models.append(build_entry(entry, cfg, cache_dir, status=status))
            except Exception as exc:  # in "skip" mode one bad model must not stop the others
                if on_error == "raise":
                    raise
                skipped[entry.name] = _error_text(exc)
                log.warning(
                    "skipping model %r: %s",
                    entry.name,
                    skipped[entry.name],
                    exc_info=not isinstance(exc, ModelError),
                )
            if progress is not None:
                progress(entry.name)
        if entries and not models:
            raise ModelError(
                f"no model of {path} could be built: "
                + "; ".join(f"{k}: {v}" for k, v in skipped.items())
            )
        return cls(models, skipped)

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
                parts_method="exact",
            )
            for spec in builtin_specs()
        )


def prepare_folder(
    path: str | Path,
    config: LibraryConfig | SSPConfig | None = None,
    progress: Progress | None = None,
    status: Status | None = None,
) -> list[dict[str, Any]]:
    """Build every model of a folder (filling the hull and symmetry caches), reporting
    instead of raising.

    Returns one dict per model: ``name``, ``n_parts``, ``method``, ``iou``, ``seconds``
    (decomposition, 0 when cached), ``cached``, ``note``, ``warnings`` (list of texts),
    ``symmetries`` (declared or used discrete symmetries), ``detected_symmetries`` (the
    approximate ones found, see :func:`ssp.library.symmetry.detect_symmetries`; tolerance
    from ``symmetry:`` in models.yaml, else 2 mm), ``build_seconds`` (whole model) and
    ``error`` (None, or the message of the model that failed; its other fields are then None).
    ``progress`` and ``status`` as in :meth:`ObjectLibrary.from_folder`.

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
            "warnings": [],
            "symmetries": None,
            "detected_symmetries": None,
            "build_seconds": None,
            "error": None,
        }
        t0 = time.perf_counter()
        try:
            model = build_entry(entry, cfg, cache_dir, status=status, detect_symmetry=True)
        except Exception as exc:  # one bad model must not stop the others
            if isinstance(exc, ModelError):
                log.warning("model %r failed: %s", entry.name, exc)
            else:
                log.exception("model %r failed unexpectedly", entry.name)
            row["error"] = _error_text(exc)
        else:
            d = model.decomposition
            row.update(
                n_parts=d.n_parts,
                method=d.method,
                iou=d.iou,
                seconds=d.seconds,
                cached=d.cached,
                note=d.note,
                warnings=list(d.warnings),
                symmetries=int(len(model.symmetry.discrete)),
                detected_symmetries=(
                    None if model.detected_symmetry is None else model.detected_symmetry.to_dict()
                ),
            )
        row["build_seconds"] = time.perf_counter() - t0
        report.append(row)
        if progress is not None:
            progress(entry.name)
    return report
