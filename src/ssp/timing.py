"""Wall-clock time per stage of a frame (``SceneEstimate.timings``, ``PerceptionResult.timings``).

A :class:`StageTimer` keeps two sums per stage name: ``seconds``, the wall time inside the
stage (inclusive: a stage timed inside another counts in both), and ``own``, the wall time
inside the stage but not inside a stage nested in it (exclusive). The exclusive times of all
stages add up to the time spent inside any stage, so a frame's report adds up to its wall time
(:func:`stage_sum`); time another process worked (``add``: forked lanes) is the exception, kept
apart under :data:`ssp.lanes.LANES_STAGE`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

__all__ = ["StageTimer", "stage_sum"]


class StageTimer:
    """Accumulates wall time (s) per stage name: ``with timer("stepping"): ...``.

    Attributes:
        seconds: stage -> inclusive wall seconds.
        own: stage -> exclusive wall seconds (without the stages nested in it).
        started: ``time.perf_counter()`` when the timer was made (:meth:`elapsed`).
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.own: dict[str, float] = {}
        self.started = time.perf_counter()
        #: open stages: [name, start, seconds of the stages nested in it so far]
        self._stack: list[list] = []
        self._next: str | None = None

    def __call__(self, stage: str) -> StageTimer:
        self._next = stage
        return self

    def __enter__(self) -> StageTimer:
        if self._next is None:
            raise RuntimeError("use `with timer(stage):`")
        self._stack.append([self._next, time.perf_counter(), 0.0])
        self._next = None
        return self

    def __exit__(self, *exc) -> None:
        stage, t0, nested = self._stack.pop()
        dt = time.perf_counter() - t0
        self.seconds[stage] = self.seconds.get(stage, 0.0) + dt
        self.own[stage] = self.own.get(stage, 0.0) + dt - nested
        if self._stack:
            self._stack[-1][2] += dt

    def add(self, stage: str, seconds: float) -> None:
        """Add ``seconds`` to ``stage`` (inclusive and exclusive): time measured elsewhere,
        such as a forked lane's (it is not taken from an open stage)."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + float(seconds)
        self.own[stage] = self.own.get(stage, 0.0) + float(seconds)

    def share(self, wall: float, worked: Mapping[str, float]) -> None:
        """Time ``wall`` seconds spent inside the open stage on work done in threads, as the
        stages of ``worked`` (stage -> seconds the threads spent in it, summed over them):
        each gets the share of ``wall`` its work had, nested in the open stage, so the
        exclusive times still add up to the wall time (threads overlap: their own sums
        would not)."""
        total = float(sum(worked.values()))
        if total <= 0.0:
            return
        for stage, spent in worked.items():
            dt = float(wall) * float(spent) / total
            self.seconds[stage] = self.seconds.get(stage, 0.0) + dt
            self.own[stage] = self.own.get(stage, 0.0) + dt
        if self._stack:
            self._stack[-1][2] += float(wall)

    def elapsed(self) -> float:
        """Wall seconds since the timer was made."""
        return time.perf_counter() - self.started


def stage_sum(timings: Mapping[str, float], skip: tuple[str, ...] = ("total",)) -> float:
    """The sum of a timings dict's exclusive stage seconds: every entry but ``total`` and the
    ``lanes`` CPU seconds (:data:`ssp.lanes.LANES_STAGE`), and any in ``skip``."""
    return float(sum(v for k, v in timings.items() if k not in skip and k != "lanes"))
