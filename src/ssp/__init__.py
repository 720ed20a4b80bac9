"""ssp: Sequential Scene Parsing.

Physically and temporally consistent object poses from segmented point clouds and pose
hypotheses (Jonathan, Paxton, Hager, "Temporal and Physical Reasoning for Perception-Based
Robotic Manipulation"). Physics by MuJoCo.
"""

__version__ = "0.1.0"

from ssp.config import SSPConfig  # noqa: E402
from ssp.errors import SSPError  # noqa: E402

__all__ = ["SSPConfig", "SSPError", "__version__"]
