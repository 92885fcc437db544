"""The "add a shape" steps of docs/design.md §6, followed for a real new shape: ``hertz``
(tests/engine/shapes_demo/hertz/: smooth elastic spheres with a Hertz normal force F = k_n delta sqrt(delta /
R_eff) in its own njit and device functions, on top of the sphere's state, rotation and start).

The package lives in the tests tree and is registered through the public plug-in path,
``engine.shapes.register``; nothing under engine/ names it. The test runs a small dense scene (27 spheres, about
400 steps, some twenty collisions) through ``engine.run`` on the CPU and, in a child process, with backend
"cuda" under the CUDA simulator, and checks the physics: the total energy of the elastic Hertz law is conserved,
and the simulator's result is the CPU's to rounding.
"""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from engine.shapes import SHAPES, register, unregister

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = "tests.engine.shapes_demo.hertz"
#: 27 spheres at phi = 0.35, soft (dt ~ 2.5e-4 s) and slow enough that a collision stays below 0.1 radii of
#: overlap; 0.1 s is ~400 steps with ~20 collisions and up to a dozen contacts at once
SPEC = dict(shape="hertz", n_particles=27, volume_fraction=0.35, box_length=0.5, stiffness=1e5, e_n=1.0,
            e_t=-1.0, velocity_rms=0.5, overlap_limit=0.2, thermalization=0.0, t_end=0.1, snapshots=2)


@pytest.fixture
def hertz():
    from engine.numba_support.jitcache import source_digest

    engine_digest = source_digest()
    register("hertz", PACKAGE)
    assert source_digest() != engine_digest     # the package's sources are in the compiled code's cache key
    yield
    unregister("hertz")
    assert "hertz" not in SHAPES and source_digest() == engine_digest


def _series(path) -> dict:
    with h5py.File(path) as f:
        out = {k: f[f"observables/{k}/value"][()] for k in ("kinetic_energy_translational", "elastic_energy",
                                                              "contacts", "collisions")}
        out["position"] = f["particles/all/position/value"][()]
        out["steps"] = f["observables/kinetic_energy_translational/step"][()]
    return out


def test_register_checks_the_package_and_refuses_a_taken_name(hertz):
    with pytest.raises(ValueError, match="'sphere' is taken"):
        register("sphere", PACKAGE)
    with pytest.raises(ValueError, match="lacks NAME"):           # a package that is no shape
        register("demo", "tests.engine.shapes_demo")
    with pytest.raises(ValueError, match="NAME is 'hertz', expected 'other'"):
        register("other", PACKAGE)
    assert "demo" not in SHAPES and "other" not in SHAPES
    with pytest.raises(ValueError, match="'sphere' is built in"):
        unregister("sphere")


def test_a_registered_shape_is_a_valid_spec_value_and_its_refusals_hold(hertz):
    from pydantic import ValidationError

    from engine.setup.spec import SimulationSpec

    assert SimulationSpec(**SPEC).shape == "hertz"
    assert SimulationSpec.model_json_schema()["properties"]["shape"]["enum"] == list(SHAPES)
    with pytest.raises(ValidationError, match="shape = 'cube' is not a registered shape"):
        SimulationSpec(**{**SPEC, "shape": "cube"})


def test_a_spec_the_shape_does_not_run_is_refused_before_anything_is_written(hertz, tmp_path):
    from engine import run
    from engine.errors import SpecError
    from engine.setup.spec import SimulationSpec

    with pytest.raises(SpecError, match="e_n = 0.9 but shape 'hertz' is elastic"):
        run(SimulationSpec(**{**SPEC, "e_n": 0.9}), tmp_path / "refused.h5")
    assert not (tmp_path / "refused.h5").exists()


def test_the_new_shape_runs_on_the_cpu_and_under_the_cuda_simulator(hertz, tmp_path):
    from engine import run
    from engine.setup.spec import SimulationSpec
    from tests.cudasim import run_children

    cpu_file, sim_file = tmp_path / "cpu.h5", tmp_path / "sim.h5"
    summary = run(SimulationSpec(**SPEC, backend="cpu"), cpu_file)
    assert summary.backend == "cpu"
    cpu = _series(cpu_file)

    # the law ran: collisions happened and the Hertz energy was a sizeable part of the total at times
    e0 = cpu["kinetic_energy_translational"][0] + cpu["elastic_energy"][0]
    assert cpu["collisions"][-1] >= 10 and cpu["contacts"].max() >= 3, (cpu["collisions"][-1], cpu["contacts"])
    assert cpu["elastic_energy"].max() > 0.05 * e0
    # energy: velocity Verlet on a smooth conservative force keeps E within O((dt/t_c)^2) of E0 (dt ~ t_c/50,
    # and the Hertz contact is softer than the linear one dt is set by: < 1e-3; measured 3e-5); the linear
    # spring's energy in its place would miss by the elastic share checked above (> 5e-2)
    e = cpu["kinetic_energy_translational"] + cpu["elastic_energy"]
    assert np.max(np.abs(e - e0)) / e0 < 1e-3, np.max(np.abs(e - e0)) / e0

    (rc, out, err), = run_children({"sim": [__file__, "--child", sim_file]}, timeout=900).values()
    assert rc == 0 and "SIMULATOR-OK" in out, out[-4000:] + err[-4000:]
    sim = _series(sim_file)
    assert np.array_equal(sim["steps"], cpu["steps"])
    assert np.array_equal(sim["collisions"], cpu["collisions"])
    assert np.array_equal(sim["contacts"], cpu["contacts"])
    # float64 on both, the same njit law; the observe sums run in another order (measured: 4e-16 relative,
    # positions bit-identical), and collisions could amplify last-bit differences of the trajectory
    for key in ("kinetic_energy_translational", "elastic_energy"):
        np.testing.assert_allclose(sim[key], cpu[key], rtol=1e-12, atol=1e-12 * e0, err_msg=key)
    np.testing.assert_allclose(sim["position"], cpu["position"], rtol=0, atol=1e-12 * SPEC["box_length"])


def _child(out: str) -> None:
    from tests.cudasim import fast_block_polling

    fast_block_polling()
    register("hertz", PACKAGE)
    from engine import run
    from engine.setup.spec import SimulationSpec

    summary = run(SimulationSpec(**SPEC, backend="cuda"), out)
    assert summary.backend == "cuda", summary
    print("SIMULATOR-OK")


if __name__ == "__main__" and "--child" in sys.argv:
    sys.path.insert(0, str(ROOT))
    _child(sys.argv[sys.argv.index("--child") + 1])
