"""Real-GPU check of a large scene's snapshots written in pieces (engine/output/pieces.py FRAME_PIECE_ROWS,
engine/loops/cuda_frames.py ``_state_pieces``), with the piece shrunk to 6000 of 40 000 spheres (the last piece
short): the same frames, bit for bit, as whole frames; and of ``orientations = false``: the same trajectory with no
orientation in the file. Skipped without a GPU."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


def _frames(tmp_path, monkeypatch, name: str, rows: int, **kw) -> dict:
    import engine.loops.cuda_frames as frames
    import engine.output.h5md as h5md
    import engine.output.pieces as pieces
    import engine.output.writers.snapshots as snaps
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    for mod in (pieces, frames, h5md, snaps):
        monkeypatch.setattr(mod, "FRAME_PIECE_ROWS", rows)
    spec = SimulationSpec(n_particles=40000, volume_fraction=0.1, e_n=0.8, e_t=0.5, t_end=0.01, snapshots=3, seed=5,
                          thermalization=0, backend="cuda", **kw)
    s = run(spec, tmp_path / f"{name}.h5")
    with h5py.File(s.output) as f:
        part = f["particles/all"]
        return {k: (part[k]["value"][...], part[k]["value"].chunks) for k in part
                if isinstance(part[k], h5py.Group) and "value" in part[k]}


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_frames_in_pieces_equal_whole_frames_and_orientations_can_be_left_out(tmp_path, monkeypatch, precision):
    whole = _frames(tmp_path, monkeypatch, "whole", 1 << 24, precision=precision)
    pieced = _frames(tmp_path, monkeypatch, "pieces", 6000, precision=precision)
    bare = _frames(tmp_path, monkeypatch, "bare", 6000, precision=precision, orientations=False)
    assert sorted(whole) == sorted(pieced) == ["angular_velocity", "orientation", "position", "velocity"]
    assert whole["position"][1] == (1, 40000, 3) and pieced["position"][1] == (1, 6000, 3)
    assert sorted(bare) == ["angular_velocity", "position", "velocity"]
    for k, (a, _) in whole.items():
        assert a.shape == (3, 40000, a.shape[2]) and np.array_equal(a, pieced[k][0]), k
        if k != "orientation":
            assert np.array_equal(a, bare[k][0]), k
    assert not np.array_equal(whole["orientation"][0][0], whole["orientation"][0][-1])
