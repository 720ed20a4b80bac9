"""ssp: Sequential Scene Parsing.

Physically and temporally consistent object poses from segmented point clouds and pose
hypotheses (Jonathan, Paxton, Hager, "Temporal and Physical Reasoning for Perception-Based
Robotic Manipulation"). Physics by MuJoCo.
"""

__version__ = "0.1.0"

from ssp.config import SSPConfig  # noqa: E402
from ssp.errors import SSPError  # noqa: E402

#: Public names loaded on first use (keeps ``import ssp`` and the CLI quick).
_LAZY = {
    "Frame": "ssp.scene",
    "Hypothesis": "ssp.scene",
    "ObjectLibrary": "ssp.library",
    "SceneEstimate": "ssp.parser",
    "SceneParser": "ssp.parser",
}

__all__ = ["SSPConfig", "SSPError", "__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'ssp' has no attribute {name!r}")
