"""Triggers: which steps (or wall-clock moments) a writer acts at (engine/output/writers/__init__.py)."""

from __future__ import annotations

import abc
import time


class Trigger(abc.ABC):
    """A set of cooling-run steps: ``trigger(step)`` says whether a writer acts at ``step``; :meth:`steps` lists them
    (the driver stops the scene at every one)."""

    @abc.abstractmethod
    def __call__(self, step: int) -> bool:
        """True when the writer acts at ``step``."""

    @abc.abstractmethod
    def steps(self) -> set:
        """Every step the trigger fires at."""


class Periodic(Trigger):
    """Every ``period`` steps from 0, and the ``last`` step (the end of the run) whatever its phase."""

    def __init__(self, period: int, last: int):
        if period < 1:
            raise ValueError(f"period = {period}: a periodic trigger needs a period of at least one step")
        self.period, self.last = int(period), int(last)

    def __call__(self, step: int) -> bool:
        return step % self.period == 0 or step == self.last

    def steps(self) -> set:
        return set(range(0, self.last + 1, self.period)) | {self.last}


class AtSteps(Trigger):
    """An explicit set of steps."""

    def __init__(self, steps):
        self._steps = {int(s) for s in steps}

    def __call__(self, step: int) -> bool:
        return step in self._steps

    def steps(self) -> set:
        return set(self._steps)


class WallClock:
    """Due every ``interval`` wall seconds (monotonic clock) since the last :meth:`reset` (or the start); never with
    ``interval`` None. Not a step trigger: it is asked at the stops the step triggers make."""

    def __init__(self, interval):
        self.interval = interval
        self.last = time.monotonic()

    def due(self) -> bool:
        return self.interval is not None and time.monotonic() - self.last >= self.interval

    def reset(self) -> None:
        self.last = time.monotonic()
