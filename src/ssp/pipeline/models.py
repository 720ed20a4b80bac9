"""What ``ssp models list`` and ``ssp models show`` report about an object model
(:class:`ssp.library.ObjectModel`), as JSON-ready dicts."""

from __future__ import annotations

from typing import Any

__all__ = ["model_details", "model_record"]


def model_record(model: Any) -> dict[str, Any]:
    """The model's :meth:`~ssp.library.ObjectModel.summary` and how long its convex
    decomposition took (``decomposition_seconds``) and whether it came from the cache."""
    return {
        **model.summary(),
        "decomposition_seconds": round(model.decomposition.seconds, 3),
        "decomposition_cached": model.decomposition.cached,
    }


def model_details(
    model: Any, tolerance: float, *, gravity: float, library_config: Any
) -> dict[str, Any]:
    """Everything about one model: its summary, the largest angular acceleration gravity
    (m/s^2) can give it, its convex decomposition (seconds, cached, note) and its approximate
    symmetries detected within ``tolerance`` (MSSD, m; the detection is cached in the hull
    cache of ``library_config``, :class:`ssp.config.LibraryConfig`)."""
    from ssp.library.build import cached_symmetry_detection
    from ssp.library.decomposition import default_cache_dir

    summary = model.summary()
    summary["max_angular_acceleration_rad_s2"] = round(model.max_angular_acceleration(gravity), 2)
    summary["decomposition_seconds"] = round(model.decomposition.seconds, 3)
    summary["decomposition_cached"] = model.decomposition.cached
    if model.decomposition.note:
        summary["decomposition_note"] = model.decomposition.note
    detected = model.detected_symmetry
    if detected is None or abs(detected.tolerance - tolerance) > 1e-12:
        detected = cached_symmetry_detection(
            model.mesh,
            model.center_of_mass,
            model.inertia,
            tolerance,
            default_cache_dir(library_config),
        )
    summary["detected_symmetries"] = detected.to_dict()
    return summary
