"""The checkpoint writer: ``state.npz`` (state, contact springs, clock) and a copy of the partial result file in a
checkpoint directory, both through a temporary name and a rename; trigger: every ``interval`` wall seconds
(engine/output/writers/__init__.py). It also reads a checkpoint back for a resume."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from engine.output.h5md import H5MDWriter, replace_file
from engine.output.writers.triggers import WallClock


class Checkpointer:
    """Writes and reads ``state.npz`` + ``partial.h5`` in a checkpoint directory (atomically)."""

    def __init__(self, directory, interval: float):
        self.dir = Path(directory) if directory is not None else None
        self.interval = interval
        self.clock = WallClock(interval if self.dir is not None else None)

    def load(self, spec_json: str):
        if self.dir is None or not (self.dir / "state.npz").exists():
            return None
        data = dict(np.load(self.dir / "state.npz", allow_pickle=False))
        if str(data["spec"]) != spec_json or not (self.dir / "partial.h5").exists():
            return None
        return data

    def due(self) -> bool:
        """A checkpoint is due (a directory is set and ``interval`` wall seconds have passed since the last)."""
        return self.clock.due()

    def save(self, writer: H5MDWriter, backend, *, phase: str, step_done: int, extra: dict) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        writer.flush()
        tmp_h5 = self.dir / "partial.h5.tmp"
        shutil.copyfile(writer.tmp, tmp_h5)
        st = backend.state(reuse=True)  # consumed by np.savez below
        pairs, springs = backend.contacts()
        tmp = self.dir / "state.tmp.npz"
        np.savez(tmp, phase=phase, step_done=step_done, counts=json.dumps(writer.frame_counts()),
                 pairs=pairs, springs=springs, **st, **extra)
        replace_file(tmp_h5, self.dir / "partial.h5")
        replace_file(tmp, self.dir / "state.npz")
        self.clock.reset()

    def clear(self) -> None:
        if self.dir is not None and self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)
