"""Real-GPU checks of the list methods of Skorych & Dosta (2022) (skipped without a GPU): multigrid contact set and
the three list modes.

Run on the GPU machine: ``python -m pytest tests/gpu -q -s``.
"""

import numpy as np
import pytest

from engine.backends.base import cuda_available
from tests.engine.test_cuda_lists_simulator import brute_pairs, contact, poly_system

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


@pytest.mark.parametrize("ratio", [1, 2, 5, 10])
def test_multigrid_contact_set_equals_brute_force(ratio):
    from engine.backends.cuda import CudaEnsemble

    sy = poly_system(1500, ratio, 0.3, seed=ratio)
    skin = 0.5 * float(sy.radius.min())
    ens = CudaEnsemble([sy], [contact(skin, 1e-4)])
    nbr, row, ids = ens.nbr.copy_to_host(), ens.nn.copy_to_host(), ens.ids.copy_to_host()
    nn = np.diff(row)
    got = [(int(ids[i]), int(ids[nbr[row[i] + k]])) for i in range(ens.n) for k in range(nn[i])]
    want = brute_pairs(np.asarray(sy.position), np.asarray(sy.radius), sy.box_length, skin)
    assert len(got) == len(set(got))
    assert set(got) == want
    assert ens.multigrid == (ratio >= 5)


def test_three_modes_same_trajectory_and_auto():
    """GPU list, CPU sequential, CPU pipelined, auto: one polydisperse start, 400 steps with rebuilds."""
    from engine.backends.cuda import CudaBackend

    out = {}
    for mode in ("gpu", "cpu-sequential", "cpu-pipelined", "auto"):
        sy = poly_system(3000, 4.0, 0.3, seed=11, speed=1.0)
        skin = 0.3 * float(sy.radius.min())
        dt = np.pi * np.sqrt(0.5 * float(sy.mass.min()) / 1.0e5) / 50
        be = CudaBackend(sy, contact(skin, dt, list_mode=mode))
        be.advance(400)
        out[mode] = (be.state()["position"], be.builds, None if be.e.lists is None else be.e.lists.summary())
    ref, builds, _ = out["gpu"]
    box = sy.box_length
    print({m: (o[1], o[2] and o[2]["restarts"]) for m, o in out.items()})
    assert builds >= 5
    for mode in ("cpu-sequential", "cpu-pipelined", "auto"):
        d = out[mode][0] - ref
        d -= box * np.round(d / box)
        # same lists and physics; only the order of the force sums differs, amplified by collisions
        assert np.abs(d).max() / box < 1e-9, (mode, np.abs(d).max() / box)
    assert out["cpu-pipelined"][2]["stages"] >= 5


def test_run_with_cpu_pipelined_list_records_the_mode(tmp_path):
    """A polydisperse spec through engine.driver.simulate.run with the pipelined CPU list: the result file names
    the mode and its measured stage times."""
    import json

    import h5py

    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=20000, volume_fraction=0.1, box_length=2.0 * (20000 / 4096) ** (1 / 3),
                          species=[{"radius_ratio": 1.0, "number_fraction": 0.1},
                                   {"radius_ratio": 0.25, "number_fraction": 0.9}],
                          t_end=2e-4, backend="cuda", list_mode="cpu-pipelined", snapshots=0)
    run(spec, tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5") as f:
        par = f["parameters"].attrs
        assert par["list_mode"] == "cpu-pipelined"
        summary = json.loads(par["list_modes"])
        assert summary["stages"] >= 2 and summary["cpu-pipelined"]["tau_cpu"] > 0
        assert np.all(np.isfinite(f["observables/kinetic_energy_translational/value"][:]))
