"""The snapshot writer: full frames (position, velocity, angular velocity, orientation) at the snapshot steps, spread
evenly over the cooling run (engine/output/writers/__init__.py), through the ensemble's two reused host buffer slots;
a frame of more than FRAME_PIECE_ROWS particles in pieces (engine/output/pieces.py), where the ensemble can give
them, without a host copy of the whole frame."""

from __future__ import annotations

from concurrent.futures import wait as futures_wait

import numpy as np

from engine.output.pieces import FRAME_PIECE_ROWS
from engine.output.writers.triggers import AtSteps


def snapshot_steps(n_steps: int, snapshots: int) -> set:
    """The cooling-run steps of ``snapshots`` frames spread evenly over [0, n_steps] (one: the last step)."""
    if snapshots <= 0:
        return set()
    if snapshots == 1:
        return {n_steps}
    return set(np.round(np.linspace(0, n_steps, snapshots)).astype(int).tolist())


class SnapshotWriter:
    """Writes a frame at every snapshot step (trigger: :func:`snapshot_steps`) of a scene of ``n_particles``;
    without ``orientations`` the frames leave the orientation out (the spec's ``orientations``)."""

    def __init__(self, n_steps: int, snapshots: int, n_particles: int = 0, orientations: bool = True):
        self.trigger = AtSteps(snapshot_steps(n_steps, snapshots))
        self.n_particles = n_particles
        self.left_out = () if orientations else ("orientation",)

    def write(self, writer, step_done: int, t_sim: float, view) -> None:
        """Scene ``view``'s frame of ``step_done`` into ``writer`` (the I/O thread writes it while the run goes on).

        Two buffer slots (host memory reused on CUDA), shared by all scenes of the ensemble (``view.slots``): a
        slot is reused, by any scene, only after its previous frame is in the file (waited for, not raised: a
        failed write is its writer's error). A scene of more than FRAME_PIECE_ROWS particles whose ensemble hands
        out pieces (``view.state_pieces``) is written a piece at a time instead, and the run waits for the frame."""
        pieces = view.state_pieces(FRAME_PIECE_ROWS) if self.n_particles > FRAME_PIECE_ROWS else None
        if pieces is not None:
            writer.snapshot_pieces(step_done, t_sim, self.n_particles, pieces, left_out=self.left_out)
            return
        slot = view.slots.take()
        arrays = view.state(reuse=2 + slot)
        for key in self.left_out:
            arrays.pop(key, None)
        view.slots.busy[slot] = writer.snapshot(step_done, t_sim, arrays)


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
