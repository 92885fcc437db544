"""The snapshot writer: full frames (position, velocity, angular velocity, orientation) at the snapshot steps, spread
evenly over the cooling run (engine/output/writers/__init__.py), through the ensemble's two reused host buffer slots."""

from __future__ import annotations

from concurrent.futures import wait as futures_wait

import numpy as np

from engine.output.writers.triggers import AtSteps


def snapshot_steps(n_steps: int, snapshots: int) -> set:
    """The cooling-run steps of ``snapshots`` frames spread evenly over [0, n_steps] (one: the last step)."""
    if snapshots <= 0:
        return set()
    if snapshots == 1:
        return {n_steps}
    return set(np.round(np.linspace(0, n_steps, snapshots)).astype(int).tolist())


class SnapshotWriter:
    """Writes a frame at every snapshot step (trigger: :func:`snapshot_steps`)."""

    def __init__(self, n_steps: int, snapshots: int):
        self.trigger = AtSteps(snapshot_steps(n_steps, snapshots))

    def write(self, writer, step_done: int, t_sim: float, view) -> None:
        """Scene ``view``'s frame of ``step_done`` into ``writer`` (the I/O thread writes it while the run goes on).

        Two buffer slots (host memory reused on CUDA), shared by all scenes of the ensemble (``view.slots``): a
        slot is reused, by any scene, only after its previous frame is in the file (waited for, not raised: a
        failed write is its writer's error)."""
        slot = view.slots.take()
        view.slots.busy[slot] = writer.snapshot(step_done, t_sim, view.state(reuse=2 + slot))


class FrameSlots:
    """The two snapshot buffer slots of an ensemble (its reused host buffers are shared by every scene) and the
    write still using each (a future, or None)."""

    def __init__(self):
        self.busy = [None, None]
        self.last = 1

    def take(self) -> int:
        """A slot for the next frame, once its earlier frame is written: the first free one (frames far apart
        all use one slot, so one set of buffers is allocated), else the one used less recently, waited for."""
        free = [k for k in (0, 1) if self.busy[k] is None or self.busy[k].done()]
        slot = free[0] if free else 1 - self.last
        if self.busy[slot] is not None:
            futures_wait([self.busy[slot]])
        self.last = slot
        return slot
