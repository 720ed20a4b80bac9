"""Wall-clock time per stage of a frame (reported in ``SceneEstimate.timings``)."""

from __future__ import annotations

import time

__all__ = ["StageTimer"]


class StageTimer:
    """Accumulates wall time (s) per stage name: ``with timer("stepping"): ...``."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._stack: list[tuple[str, float]] = []
        self._next: str | None = None

    def __call__(self, stage: str) -> StageTimer:
        self._next = stage
        return self

    def __enter__(self) -> StageTimer:
        if self._next is None:
            raise RuntimeError("use `with timer(stage):`")
        self._stack.append((self._next, time.perf_counter()))
        self._next = None
        return self

    def __exit__(self, *exc) -> None:
        stage, t0 = self._stack.pop()
        self.add(stage, time.perf_counter() - t0)

    def add(self, stage: str, seconds: float) -> None:
        """Add ``seconds`` to ``stage``."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + float(seconds)
