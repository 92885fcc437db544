"""The driver: validate, derive, place, thermalise, cool, record, write; progress and cancel hooks.

Public API (used by the CLI and the job worker)::

    run(spec, output, *, progress=None, should_cancel=None, checkpoint_dir=None,
        checkpoint_interval=60.0, backend=None) -> RunSummary
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
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
    wall_s: float         # wall seconds since the time loop started


@dataclass
class RunSummary:
    output: Path
    backend: str
    device: str
    n_particles: int
    steps: int                    # cooling + thermalisation steps advanced
    wall_s: float                 # wall seconds of the time loop (after compilation and placement)
    cundall: float                # N * steps / wall_s
    resumed_from_step: Optional[int] = None
    extra: dict = field(default_factory=dict)


def run(spec, output, *, progress: Optional[Callable[[Progress], None]] = None,
        should_cancel: Optional[Callable[[], bool]] = None, checkpoint_dir=None,
        checkpoint_interval: float = 60.0, backend: Optional[str] = None) -> RunSummary:
    raise NotImplementedError("engine.simulate.run is being written")
