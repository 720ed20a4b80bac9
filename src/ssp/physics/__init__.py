"""Physics: MuJoCo worlds of rigid objects on a table.

This package is the only part of ssp that imports ``mujoco``. Everything else talks to
:class:`World` with plain numpy poses (4x4 ``T_world_obj``), forces and contact arrays.
"""

from ssp.physics.contacts import ContactRecord, Contacts
from ssp.physics.world import DuplicateObjectError, World, WorldMismatchError, WorldState

__all__ = [
    "ContactRecord",
    "Contacts",
    "DuplicateObjectError",
    "World",
    "WorldMismatchError",
    "WorldState",
]
