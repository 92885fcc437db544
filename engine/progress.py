"""The command line's progress bar (tqdm): fraction of the run, N, steps/s, Cundall number, ETA, phase.

Quiet when the stream is not a terminal (tqdm's ``disable=None``), so logs and pipes get no carriage
returns. ``update`` takes what the engine reports (engine.simulate.Progress) or a job's progress fields.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Optional

from tqdm import tqdm

BAR_FORMAT = "{desc}{percentage:5.1f}%|{bar}| {stats}"


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
        parts = []
        if self.n:
            parts.append(f"N={self.n}")
        if cundall and cundall > 0:
            if self.n:
                parts.append(f"{cundall / self.n:.3g} steps/s")
            parts.append(f"Cundall {cundall:.3g}")
        if eta_s is not None and math.isfinite(eta_s):
            parts.append(f"ETA {tqdm.format_interval(max(eta_s, 0.0))}")
        if phase:
            parts.append(phase)
        return "  ".join(parts)

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
        """Callback of engine.simulate.run (an engine Progress)."""
        self.update(pr.fraction, pr.phase, pr.eta_s, pr.cundall)

    def close(self) -> None:
        self.bar.close()
