"""Typed exceptions of ssp. Library code raises these; only the CLI turns them into messages."""

from __future__ import annotations


class SSPError(Exception):
    """Base class of every error ssp raises on purpose."""


class ConfigError(SSPError):
    """A configuration file or value is invalid."""


class ModelError(SSPError):
    """An object model (mesh or its properties) cannot be used."""


class ModelFileError(ModelError):
    """A model file is missing or cannot be read."""


class UnitsError(ModelError):
    """A model's size shows it is not in metres (most often: it is in millimetres)."""


class GeometryError(ModelError):
    """A mesh is degenerate, not watertight after repair, or otherwise unusable."""


class DecompositionError(ModelError):
    """Convex decomposition failed (after every fallback)."""


class UnknownObjectError(SSPError, KeyError):
    """An object id or class name that the library or world does not know."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else "unknown object"


class InvalidPoseError(SSPError, ValueError):
    """A pose that is not a finite rigid transform (4x4, orthonormal rotation)."""


class PhysicsError(SSPError):
    """The physics engine failed (unstable simulation, bad state)."""


class DuplicateObjectError(SSPError, ValueError):
    """Two objects given to a world or scene share one id."""


class WorldMismatchError(PhysicsError, ValueError):
    """A saved world state was restored into a world other than the one that saved it."""


class ArgumentError(SSPError, ValueError):
    """A function argument or command option that cannot be used (an unknown mode, a BOP
    method name with ``_``, an output folder that holds something else)."""


class InputError(SSPError, ValueError):
    """An input file or folder (cloud, hypotheses JSON, scene description) that cannot be used."""


class CloudFormatError(InputError):
    """A point-cloud file (PLY, PCD) that is corrupt, empty or lacks the x, y, z fields."""


class PerceptionError(SSPError):
    """The perception front end could not process a frame (segmentation, pose hypotheses)."""


class TableNotFoundError(PerceptionError):
    """No support plane (table) was found in a cloud, so gravity cannot be derived."""


class OutputError(SSPError, OSError):
    """An output file or folder that cannot be written safely: a symbolic link in an output
    folder (ssp never writes, truncates or deletes through one), or a write that failed (a full
    disk, no permission); the message names the file."""


class OutputLockedError(OutputError):
    """An output folder another run is writing (it holds the folder's lock)."""
