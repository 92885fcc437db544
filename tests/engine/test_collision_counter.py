"""The collision counter (observable ``collisions``: contacts begun since the scene started, spheres).

Each contact that begins (overlap > 0 after a step without one) counts once; the CPU backend here, the CUDA code
against it in tests/engine/test_cuda_simulator.py and tests/gpu/test_cuda_gpu.py, checkpoint/resume in
tests/engine/test_simulate.py.
"""

import h5py
import numpy as np

from tests.engine.test_mixed_precision import _pair


def test_one_head_on_collision_counts_once_however_many_steps_it_lasts():
    be, _ = _pair("float64", 0.8, 2.0)      # the spheres touch after ~5 steps, the contact lasts ~50
    be.advance(2)
    counts = [be.observe()["collisions"]]
    for _ in range(8):
        be.advance(20)                       # the contact spans several calls
        counts.append(be.observe()["collisions"])
    assert counts == [0] + [1] * 8, counts


def test_the_result_file_counts_every_collision(tmp_path):
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    out = tmp_path / "c.h5"
    run(SimulationSpec(n_particles=256, volume_fraction=0.1, t_end=0.01, thermalization=0.5, snapshots=0,
                       backend="cpu", seed=2), out)
    with h5py.File(out) as f:
        c = f["observables/collisions/value"][()]
        contacts = f["observables/contacts/value"][()]
    assert c.dtype == np.int64 and np.all(np.diff(c) >= 0)
    # the elastic thermalisation from the lattice start and the cooling both collide
    assert 0 < c[0] < c[-1], (c[0], c[-1])
    # a contact open at a record has begun since the previous one or is still open from before
    assert np.all(np.diff(c) + contacts[:-1] >= contacts[1:])
