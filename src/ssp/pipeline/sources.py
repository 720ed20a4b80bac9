"""Run inputs as frame sources: what :func:`ssp.pipeline.run.run` reads, one frame at a time.

An input format is one module holding a class that implements :class:`FrameSource` (folders of
clouds: :mod:`ssp.pipeline.folder`; BOP scenes: :mod:`ssp.pipeline.bop`; ROS bags and MCAP
files: :mod:`ssp.pipeline.bag`), and its line in :mod:`ssp.pipeline.inputs`, which picks the
source of an input path. A source yields :class:`InputFrame` records; a frame's files are read
when its :attr:`InputFrame.perceive` is called, so one unreadable frame fails alone and a long
input is never in memory at once.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from ssp.io.results import ObjectIds
from ssp.perception.pipeline import Perception, PerceptionResult

__all__ = [
    "HYPOTHESES_MODES",
    "Committed",
    "FrameSource",
    "InputFrame",
    "Perceive",
    "unknown_class",
]

#: ``auto``: the input's hypotheses when it has them, else the built-in estimator;
#: ``given``: only the input's (a frame without is an error); ``estimated``: always estimate.
HYPOTHESES_MODES = ("auto", "given", "estimated")

#: Reads a frame's files and runs the perception front end on them: the result and the
#: warnings of the frame (about its input; the front end logs its own).
Perceive = Callable[[], tuple[PerceptionResult, list[str]]]


@dataclass
class InputFrame:
    """One input frame: its name, index (BOP ``im_id`` or folder position), the files it is
    read from, and a function that reads and perceives it (result and warnings)."""

    name: str
    index: int
    files: tuple[str, ...]
    perceive: Perceive

    def where(self, message: str) -> str:
        """The file to name in an error ``message`` that names none: the hypotheses file for
        a problem with a hypothesis (when the frame has one), else the frame's main file."""
        if any(f in message for f in self.files):
            return message
        about_hyp = message.startswith(("hypothesis", "instance id", "invalid pose"))
        f = self.files[1] if about_hyp and len(self.files) > 1 else self.files[0]
        return f"{f}: {message}"


#: A resumed run's committed frame JSON by frame name (None: the frame has none).
Committed = Callable[[str], "Mapping | None"]


@runtime_checkable
class FrameSource(Protocol):
    """An opened run input: the frames of a folder of clouds, a BOP scene, a bag, ...

    A source is opened (its index read and checked: an input that cannot be used at all
    raises :class:`ssp.errors.InputError` there) with the object library, the settings, the
    estimator's candidate classes and one of :data:`HYPOTHESES_MODES`; reading a frame is left
    to the frame's :attr:`InputFrame.perceive`. Errors of one frame (raised by ``perceive``)
    fail that frame only.

    Attributes:
        kind: the input kind, recorded in ``run.json`` and the summary (``folder``, ``bop``,
            ``bag``).
        total: the number of frames.
        perception: the front end the frames are perceived with (its segment memory,
            :mod:`ssp.perception.reuse`, is part of the run's state).
    """

    kind: str
    total: int
    perception: Perception

    def frames(self, start: int = 0, committed: Committed | None = None) -> Iterator[InputFrame]:
        """The frames from position ``start`` on, in order. A source whose frames depend on
        the frames before them (a camera located frame after frame) brings that state up to
        ``start`` first, as an uninterrupted run left it: from the ``committed`` frame
        records of a resumed run."""
        ...

    def object_ids(self) -> ObjectIds:
        """The BOP ``obj_id`` of each class of the library, for the results CSV."""
        ...


def unknown_class(name: str, library: Mapping) -> str:
    """The message for class ``name`` missing from ``library``, with the closest known name."""
    close = difflib.get_close_matches(name, list(library), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"class {name!r} is not in the library{hint}; known: {', '.join(library) or 'none'}"
