"""The command line's progress: fraction of the run, N, steps/s, Cundall number, ETA, phase.

On a terminal a tqdm bar (:class:`ProgressBar`); elsewhere (a log file, a pipe, a batch job's output)
plain lines without carriage returns (:class:`ProgressLines`): one per 10 % of the run, and at least one
every 10 s while it runs. :func:`progress_for` picks one by the stream. ``update`` takes what the engine
reports (engine.driver.simulate.Progress) or a job's progress fields.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Optional

from tqdm import tqdm

BAR_FORMAT = "{desc}{percentage:5.1f}%|{bar}| {stats}"


def stats_text(n_particles: Optional[int], phase: str = "", eta_s: Optional[float] = None,
               cundall: Optional[float] = None) -> str:
    """The fields after the percentage: N, steps/s (= cundall / N), Cundall number, ETA, phase."""
    parts = []
    if n_particles:
        parts.append(f"N={n_particles}")
    if cundall and cundall > 0:
        if n_particles:
            parts.append(f"{cundall / n_particles:.3g} steps/s")
        parts.append(f"Cundall {cundall:.3g}")
    if eta_s is not None and math.isfinite(eta_s):
        parts.append(f"ETA {tqdm.format_interval(max(eta_s, 0.0))}")
    if phase:
        parts.append(phase)
    return "  ".join(parts)


class _Bar(tqdm):
    """tqdm with one more field, ``{stats}``, in its format (tqdm's own ``{postfix}`` starts with a comma)."""

    stats = ""

    @property
    def format_dict(self):
        return dict(super().format_dict, stats=self.stats)


class ProgressBar:
    """``update(fraction, ...)`` moves the bar; ``close()`` ends the line. Units: cundall in particle-steps per
    wall second, steps/s = cundall / N, eta_s in wall seconds."""

    def __init__(self, n_particles: Optional[int] = None, desc: str = "", stream=None, disable: Optional[bool] = None):
        self.n = n_particles
        self.bar = _Bar(total=1.0, desc=desc, file=stream or sys.stderr, disable=disable, bar_format=BAR_FORMAT,
                        mininterval=0.2, dynamic_ncols=True, leave=True)
        self.last = 0.0

    @property
    def enabled(self) -> bool:
        return not self.bar.disable

    def postfix(self, phase: str = "", eta_s: Optional[float] = None, cundall: Optional[float] = None) -> str:
        return stats_text(self.n, phase, eta_s, cundall)

    def update(self, fraction: float, phase: str = "", eta_s: Optional[float] = None,
               cundall: Optional[float] = None) -> None:
        now = time.monotonic()
        if self.bar.disable or (now - self.last < 0.2 and fraction < 1.0):
            return
        self.last = now
        self.bar.n = min(max(float(fraction or 0.0), 0.0), 1.0)
        self.bar.stats = self.postfix(phase, eta_s, cundall)
        self.bar.refresh()

    def __call__(self, pr) -> None:
        """Callback of engine.driver.simulate.run (an engine Progress)."""
        self.update(pr.fraction, pr.phase, pr.eta_s, pr.cundall)

    def close(self) -> None:
        self.bar.close()


class ProgressLines:
    """Progress as plain lines for a stream that is not a terminal: a line when the run passes the next
    ``step`` of its fraction (10 %), or ``every_s`` wall seconds after the last line, and one at the end.
    Same interface as :class:`ProgressBar`."""

    def __init__(self, n_particles: Optional[int] = None, desc: str = "", stream=None, step: float = 0.1,
                 every_s: float = 10.0):
        self.n, self.desc, self.stream = n_particles, desc.strip(), stream or sys.stderr
        self.step, self.every_s = step, every_s
        self.tier = 0                     # the number of whole steps of the fraction already reported
        self.last_line = time.monotonic()
        self.printed_end = False

    enabled = True

    def _line(self, fraction: float, phase: str, eta_s, cundall) -> None:
        head = f"{self.desc}: " if self.desc else ""
        print(f"{head}{100.0 * fraction:5.1f}%  {stats_text(self.n, phase, eta_s, cundall)}".rstrip(), file=self.stream,
              flush=True)
        self.last_line = time.monotonic()

    def update(self, fraction: float, phase: str = "", eta_s: Optional[float] = None,
               cundall: Optional[float] = None) -> None:
        fraction = min(max(float(fraction or 0.0), 0.0), 1.0)
        if fraction >= 1.0:
            if not self.printed_end:
                self.printed_end = True
                self._line(fraction, phase, None, cundall)
            return
        tier = int(fraction / self.step + 1e-9)   # 0.3 / 0.1 is 2.9999999999999996
        if tier > self.tier or time.monotonic() - self.last_line >= self.every_s:
            self._line(fraction, phase, eta_s, cundall)
            self.tier = max(self.tier, tier)

    def __call__(self, pr) -> None:
        """Callback of engine.driver.simulate.run (an engine Progress)."""
        self.update(pr.fraction, pr.phase, pr.eta_s, pr.cundall)

    def close(self) -> None:
        """Nothing to end (a run that stopped early leaves its last line as it was)."""


def progress_for(n_particles: Optional[int] = None, desc: str = "", stream=None):
    """A :class:`ProgressBar` when ``stream`` (default stderr) is a terminal, else :class:`ProgressLines`."""
    stream = stream or sys.stderr
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return ProgressBar(n_particles, desc=desc, stream=stream)
    return ProgressLines(n_particles, desc=desc, stream=stream)
