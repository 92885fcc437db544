"""Snapshots of a large scene in pieces (engine/output/pieces.py FRAME_PIECE_ROWS; engine/loops/cuda_frames.py
``_state_pieces``; engine/output/h5md.py ``snapshot_pieces``), and spheres without orientations (the spec's
``orientations``).

Under the CUDA simulator, with the piece shrunk to 48 particles: a 200-sphere run writes the same frames as with
whole frames (five pieces, the last one short), through piece-sized staging and host buffers only, never a host slot
of the whole frame. ``orientations = false`` leaves the orientation out of the file and off the device, and the
trajectory is the one with orientations, bit for bit. On the host: the writer's pieces, one chunk each, equal the
whole frame; a piece that is not finite raises and leaves no result."""

from __future__ import annotations

import numpy as np
import pytest

from tests.cudasim import run_children

SCRIPT = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_frames as frames
import engine.output.h5md as h5md
import engine.output.pieces as pieces
import engine.output.writers.snapshots as snaps
from engine import run
from engine.setup.spec import SimulationSpec

# the first frame slot made ahead during the build, as on a GPU (not under the simulator, nor for a small slot)
frames.SIM, frames.PINNED_SLOT_BYTES = False, 0
made, used = [], {"pieces": 0, "whole": 0, "ahead": 0}
prepare = frames.StateFrames._prepare_frame_slot
def ahead(self):
    prepare(self)
    used["ahead"] += self._slot_prep is not None
frames.StateFrames._prepare_frame_slot = ahead
init = ens.CudaEnsembleBase.__init__
def keep(self, *a, **k):
    made.append(self)
    init(self, *a, **k)
ens.CudaEnsembleBase.__init__ = keep
host_slot, write_pieces = frames.StateFrames._host_slot, h5md.H5MDWriter.snapshot_pieces
def whole(self, *a, **k):
    used["whole"] += 1
    return host_slot(self, *a, **k)
def pieced(self, *a, **k):
    used["pieces"] += 1
    return write_pieces(self, *a, **k)
frames.StateFrames._host_slot, h5md.H5MDWriter.snapshot_pieces = whole, pieced

def files(rows, orientations=True):
    for mod in (pieces, frames, h5md, snaps):
        mod.FRAME_PIECE_ROWS = rows
    spec = SimulationSpec(n_particles=200, volume_fraction=0.1, e_n=0.8, e_t=0.8, thermalization=0.0, snapshots=3,
                          backend="cuda", t_end=6e-4, velocity_rms=8.0, verlet_skin=0.2, seed=2,
                          orientations=orientations)
    made.clear()
    used.update(pieces=0, whole=0, ahead=0)
    s = run(spec, Path(tempfile.mkdtemp()) / "x.h5", backend="cuda")
    e = made[-1]
    with h5py.File(s.output) as f:
        part = f["particles/all"]
        data = {k: part[f"{k}/value"][...]
                for k in part if isinstance(part[k], h5py.Group) and "value" in part[k]}
        chunks = {k: part[f"{k}/value"].chunks for k in data}
    return data, chunks, dict(used), e

whole_data, whole_chunks, u, e = files(1 << 24)
assert u == {"pieces": 0, "whole": 3, "ahead": 1} and whole_chunks["position"] == (1, 200, 3), (u, whole_chunks)
assert sorted(whole_data) == ["angular_velocity", "orientation", "position", "velocity"], sorted(whole_data)
piece_data, piece_chunks, u, e = files(48)
assert u == {"pieces": 3, "whole": 0, "ahead": 0}, u
assert piece_chunks["position"] == (1, 48, 3) and piece_chunks["orientation"] == (1, 48, 4), piece_chunks
assert all(s.size == 4 * 48 for s in e._stage.values()) and not e._stage_h, ({k: s.size for k, s in e._stage.items()})
assert [b["position"].shape for b in e._piece_h] == [(48, 3)] * frames.PIECE_BUFFERS
for k, a in whole_data.items():
    assert a.shape == (3, 200, a.shape[2]) and np.array_equal(a, piece_data[k]), k
assert not np.array_equal(whole_data["position"][0], whole_data["position"][-1])

bare, _, u, e = files(48, orientations=False)
assert u == {"pieces": 3, "whole": 0, "ahead": 0} and not e.orientations_held and e.quat.size == 4, u
assert sorted(bare) == ["angular_velocity", "position", "velocity"], sorted(bare)
for k, a in bare.items():
    assert np.array_equal(a, whole_data[k]), k
print("PIECES-OK")
'''


def test_a_large_scene_s_snapshots_are_written_in_pieces_and_orientations_can_be_left_out():
    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "PIECES-OK" in out, out[-3000:] + err[-3000:]


def _writer(tmp_path, n, dtype):
    from engine.output.h5md import H5MDWriter

    return H5MDWriter(tmp_path / "x.h5", n=n, box_length=1.0, spec_json="{}", derived={}, dtype=dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_frame_in_pieces_equals_the_whole_frame(tmp_path, monkeypatch, dtype):
    """Pieces of 16 rows (the last one 4) of a 100-particle frame, each one chunk of the dataset (written as it is
    where its type is the file's, through HDF5 otherwise), and a second, whole frame: the same values."""
    import h5py

    import engine.output.h5md as h5md

    monkeypatch.setattr(h5md, "FRAME_PIECE_ROWS", 16)
    n = 100
    rng = np.random.default_rng(1)
    frame = {"position": rng.random((n, 3)).astype(np.float32), "velocity": rng.random((n, 3)),
             "orientation": rng.random((n, 4)).astype(np.float32)}
    w = _writer(tmp_path, n, dtype)
    w.snapshot_pieces(5, 0.5, n, ((lo, {k: a[lo:lo + 16] for k, a in frame.items()}) for lo in range(0, n, 16)),
                      left_out=("orientation",))
    w.snapshot(9, 0.9, frame)
    w.finish({})
    with h5py.File(tmp_path / "x.h5") as f:
        part = f["particles/all"]
        assert part["position/value"].chunks == (1, 16, 3)
        assert list(part["position/step"][...]) == [5, 9] and list(part["orientation/step"][...]) == [9]
        for k in ("position", "velocity"):
            got = part[f"{k}/value"][...]
            assert got.dtype == dtype and got.shape == (2, n, 3)
            assert np.array_equal(got[0], frame[k].astype(dtype)) and np.array_equal(got[1], got[0]), k


def test_a_piece_that_is_not_finite_stops_the_frame(tmp_path, monkeypatch):
    from engine.errors import InstabilityError
    import engine.output.h5md as h5md

    monkeypatch.setattr(h5md, "FRAME_PIECE_ROWS", 16)
    n = 40
    pos = np.zeros((n, 3))
    pos[30, 1] = np.nan
    w = _writer(tmp_path, n, np.float64)
    with pytest.raises(InstabilityError, match="position is not finite at step 7"):
        w.snapshot_pieces(7, 0.7, n, ((lo, {"position": pos[lo:lo + 16]}) for lo in range(0, n, 16)))
    w.abort()
    assert not list(tmp_path.iterdir())


def test_a_uniform_per_particle_constant_takes_no_disk(tmp_path, monkeypatch):
    """One radius for all (a broadcast view) and one species: datasets whose fill value is that value, no chunk
    written; masses that differ and the ids are written, in pieces of 16."""
    import h5py

    import engine.output.h5md as h5md
    from engine.output.h5md import H5MDWriter

    monkeypatch.setattr(h5md, "FRAME_PIECE_ROWS", 16)
    n = 100
    mass = np.linspace(1.0, 2.0, n)
    w = H5MDWriter(tmp_path / "x.h5", n=n, box_length=1.0, spec_json="{}", derived={},
                   radius=np.broadcast_to(np.float64(0.01), (n,)), mass=mass)
    w.finish({})
    with h5py.File(tmp_path / "x.h5") as f:
        part = f["particles/all"]
        for name, value in (("radius", 0.01), ("species", 0)):
            assert part[name].id.get_storage_size() == 0 and np.array_equal(part[name][...], np.full(n, value))
        assert np.array_equal(part["mass"][...], mass) and np.array_equal(part["id"][...], np.arange(n))
