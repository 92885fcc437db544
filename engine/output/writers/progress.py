"""The progress writer: the run's progress callback at every stop (engine/output/writers/__init__.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional


@dataclass
class Progress:
    """What the driver reports every output interval."""

    phase: str            # "thermalization" | "cooling"
    fraction: float       # 0..1 of the whole run (thermalisation + cooling), by steps
    step: int             # cooling-run step (negative during thermalisation)
    time: float           # simulated time in s (t = 0 at the start of the cooling run)
    eta_s: float          # estimated wall seconds left
    cundall: float        # particle-steps per wall second so far (time loop only)
    loop_s: float         # wall seconds of the time loop so far
    resumed_from_step: Optional[int] = None   # cooling-run step this attempt resumed from (None: a fresh start)


class ProgressWriter:
    """Calls ``callback(Progress)`` (None: nothing) with the fraction done, the Cundall number of the time loop so
    far (particle-steps per wall second) and the wall seconds left at that rate."""

    def __init__(self, callback: Optional[Callable[[Progress], None]], n: int, total_steps: int,
                 resumed_from_step: Optional[int] = None):
        self.callback, self.n, self.total_steps = callback, n, total_steps
        self.resumed_from_step = resumed_from_step

    def write(self, phase: str, done_total: int, t_sim: float, step: int, steps_run: int, wall_s: float) -> None:
        """Report ``done_total`` of the run's steps done (``steps_run`` of them in ``wall_s`` loop seconds)."""
        if self.callback is None:
            return
        total = self.total_steps
        frac = done_total / total if total else 1.0
        cund = self.n * steps_run / wall_s if wall_s > 0 else 0.0
        eta = (total - done_total) * self.n / cund if cund > 0 else math.inf
        self.callback(Progress(phase=phase, fraction=min(1.0, frac), step=step, time=t_sim, eta_s=eta,
                               cundall=cund, loop_s=wall_s, resumed_from_step=self.resumed_from_step))
