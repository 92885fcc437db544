"""The device-memory account of a sphere scene (engine/loops/cuda_memory.py) against what a CUDA ensemble really
allocates (CUDA simulator, child processes: tests/cudasim.py), the list's predicted slots, and the up-front
refusal of a spec that does not fit the device."""

import json
import sys

import pytest

from tests.cudasim import kept_ensembles, run_children

CASES = {
    # name: spec fields (n = 216: the many-steps loop; the account's flags are read off the ensemble)
    "rough-f32": dict(precision="float32", e_t=0.8, snapshots=0),
    "smooth-f64-snapshots": dict(precision="float64", e_t=-1.0, snapshots=2),
    "rough-mixed-snapshots": dict(precision="mixed", e_t=0.8, snapshots=1),
}


def _child(case: str) -> None:
    """Run the case's spec through engine.run, keep its ensemble, and print the allocations found on it and the
    account of the same layout."""
    import os
    import tempfile

    from tests.cudasim import fast_block_polling

    fast_block_polling()
    import engine
    from engine.loops import cuda_kernels as K
    from engine.loops.cuda_memory import SphereLayout, device_allocations, sphere_account
    from engine.setup.params import derive
    from engine.setup.precision import position_dtype, state_dtype
    from engine.setup.spec import SimulationSpec

    kept = kept_ensembles()
    spec = SimulationSpec(n_particles=216, volume_fraction=0.058, e_n=0.8, backend="cuda", thermalization=0,
                          **CASES[case])
    spec = spec.model_copy(update={"t_end": 40 * derive(spec).dt})
    with tempfile.TemporaryDirectory() as tmp:
        engine.run(spec, os.path.join(tmp, "out.h5"))
    (e,) = kept
    import numpy as np

    layout = SphereLayout(n=e.n, word=np.dtype(state_dtype(spec.precision)).itemsize,
                          pos_word=np.dtype(position_dtype(spec.precision)).itemsize, rough=not spec.smooth,
                          uniform=e.uniform, hist_slots=e.hist.shape[1], store_cap=e.store_cap,
                          ncell=e.ncell, tpb=e.tpb,
                          multistep=e.multistep, reads_state=e._stage is not None,
                          orientations=e.orientations_held, xref_word=e.x_ref.dtype.itemsize,
                          scene_words=(K.ND, K.NF, K.NI, K.status_len(e.n_scenes)))
    import dataclasses

    account = sphere_account(layout)
    doubled = sphere_account(dataclasses.replace(layout, n=2 * e.n))
    from engine.loops.cuda_records import RECORD_ROWS

    # the account's defaults (it is read where the CUDA modules are not imported) are the kernels' own sizes
    assert (SphereLayout.hist_words, SphereLayout.nobs, SphereLayout.record_rows) == (e.hist_words, e._NOBS,
                                                                                         RECORD_ROWS)
    print(json.dumps({"found": device_allocations(e), "account": account, "reads_state": e._stage is not None,
                      "orientations": e.orientations_held, "xref": e.x_ref.dtype.str,
                      "per_particle": sorted(k for k in account if doubled[k] != account[k])}))


def test_account_lists_every_device_array_of_a_sphere_ensemble():
    """Every allocation the ensemble holds is in the account under its name, and every per-particle array (the
    memory that scales with N) has exactly the account's size (the cases side by side, one child each)."""
    for case, (rc, out, err) in run_children({c: [__file__, c] for c in CASES}, timeout=600).items():
        assert rc == 0, err[-3000:]
        got = json.loads(out.strip().splitlines()[-1])
        found, account, per_particle = got["found"], got["account"], set(got["per_particle"])
        missing = sorted(set(found) - set(account))
        assert not missing, f"{case}: arrays missing from the account: {missing}"
        assert all(found[k] == account[k] for k in ("spd", "spf", "spi", "status")), case
        assert {k: found[k] for k in per_particle if k in found} == \
            {k: account[k] for k in per_particle if k in found}, case
        # a per-particle array of the account that the run did not make is one of the lazily made double buffers
        assert per_particle - set(found) <= {"_alt[0]", "_alt[1]", "_alt_spin"}, (case, per_particle - set(found))
        assert got["reads_state"] == (CASES[case]["snapshots"] > 0), case
        # orientations are held only where something reads or tracks them (snapshots here)
        assert got["orientations"] == (CASES[case]["snapshots"] > 0), case
        assert (found["quat"] < 4 * 216) == (not got["orientations"]), case
        # the list's reference positions are float32 at every precision in these small boxes (cuda_memory.xref_dtype)
        assert got["xref"] == "<f4", case


def test_predicted_list_slots_bound_an_equilibrium_gas():
    """The mean count of neighbours within the CUDA list's reach (2.8 a at phi = 0.058) that the prediction takes
    bounds the one counted in a random (RSA) start of 131 072 spheres from above, by less than 15 %; the list holds
    N + HIST_MARGIN slots while that mean is below one neighbour a sphere (phi = 0.058), 5/4 of the mean's slots
    beyond (phi = 0.2), and its neighbour indices take 4 B a slot (packed rows, no stride)."""
    import math

    import numpy as np

    from engine.analysis.pairs import periodic_pairs
    from engine.loops.cuda_memory import HIST_MARGIN, grown_history, grown_stride, mean_list_neighbours, \
        predict_sphere_device
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.setup.spec import SimulationSpec

    # the general rule's CUDA skin, 0.8 a, given (this many spheres would take the thinner large-scene rule)
    spec = SimulationSpec(n_particles=131072, volume_fraction=0.058, start="random", backend="cuda", seed=3,
                          verlet_skin=0.8)
    p = derive(spec)
    reach = (2.0 * p.radius + p.skin) / (2.0 * p.radius)
    assert abs(reach - 1.4) < 1e-12
    pairs = periodic_pairs(initial_spheres(spec, p).position, spec.box_length, 2.0 * p.radius + p.skin)
    counts = np.bincount(pairs.ravel(), minlength=spec.n_particles)
    # the Carnahan-Starling contact value over the whole shell bounds the mean from above (g falls across it)
    assert counts.mean() < mean_list_neighbours(0.058, 1.4) < 1.15 * counts.mean()
    pred = predict_sphere_device(spec, p)
    assert pred.slots == spec.n_particles + HIST_MARGIN and pred.table["nbr"] == 4 * pred.slots
    dense = spec.model_copy(update={"volume_fraction": 0.2})
    pd = derive(dense)
    mean = mean_list_neighbours(0.2, (2.0 * pd.radius + pd.skin) / (2.0 * pd.radius))
    assert mean > 1.0 and predict_sphere_device(dense, pd).slots == grown_history(int(math.ceil(mean * 131072)))
    # a list built on the host widens its rows there (the device's rows are packed on upload)
    assert grown_stride(0) == grown_stride(8) == 8 and grown_stride(9) == 12 and grown_stride(14) == 16


def test_the_predicted_start_of_a_random_start_on_the_device_counts_its_cells():
    """A large random start drawn on the device holds its cells (tests/engine/test_device_start_simulator.py checks
    random_start_bytes against what the draw holds at its peak) beside the positions alone, then frees them before
    the other state arrays and the streams' scratch rows are made; a lattice start holds no cells. In float32 at phi = 0.058 the loop's arrays are the
    peak, above either start."""
    from engine.loops.cuda_memory import START_ROWS, predict_sphere_device, random_start_bytes
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    n = 1 << 21
    for start in ("random", "lattice"):
        spec = SimulationSpec(n_particles=n, volume_fraction=0.058, precision="float32", backend="cuda", start=start)
        p = derive(spec)
        pred = predict_sphere_device(spec, p)
        placed = sum(pred.table[k] for k in ("ids", "sc", "pos"))
        state = placed + sum(pred.table[k] for k in ("vel", "omega", "quat"))
        rows = START_ROWS if pred.table["quat"] > 4 * 4 else START_ROWS - 1     # the orientation stream, if held
        cells = random_start_bytes(n, spec.box_length, p.radius) if start == "random" else 0
        assert pred.start_bytes == max(state + 8 * rows * n, placed + cells), start
        assert pred.peak_bytes == pred.loop_bytes > pred.start_bytes, start
    assert random_start_bytes(n, spec.box_length, p.radius) > 50 * n


def test_refusal_names_the_estimate_and_the_largest_n_that_fits():
    from engine.loops.cuda_memory import USABLE_FRACTION, memory_refusal, predict_sphere_device
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=10**9, volume_fraction=0.058, precision="float32", backend="cuda")
    free = 141e9
    why = memory_refusal(spec, derive(spec), free, "NVIDIA H200", derive)
    assert why is not None and why.startswith("n_particles = 1000000000: the run needs about")
    assert "NVIDIA H200 has 141 GB free" in why
    fits = int(float(why.split("that fits is about ", 1)[1].split(";")[0]))
    budget = USABLE_FRACTION * free
    # its 5 snapshots hold orientations; without them (24 B a particle less) the same N fits: the message says so
    bare = predict_sphere_device(spec.model_copy(update={"orientations": False}), derive(spec)).peak_bytes
    assert bare <= budget < predict_sphere_device(spec, derive(spec)).peak_bytes
    assert why.endswith(f"(orientations = false) it needs about {bare / 1e9:.3g} GB and fits")
    at = lambda n: predict_sphere_device(spec.model_copy(update={"n_particles": n}),  # noqa: E731
                                         derive(spec.model_copy(update={"n_particles": n}))).peak_bytes
    assert at(int(fits * 0.99)) <= budget < at(int(fits * 1.02))
    assert memory_refusal(spec.model_copy(update={"n_particles": int(fits * 0.99)}),
                          derive(spec.model_copy(update={"n_particles": int(fits * 0.99)})), free, "x", derive) is None


def test_a_list_beyond_int32_row_offsets_is_refused_whatever_the_memory():
    """2e9 spheres at phi = 0.2 with the general rule's skin (0.34 a: about 1.66 list slots a sphere) would need more
    list slots than int32 row offsets address: refused with the slot count and the largest N, even on a device with
    memory to spare."""
    from engine.loops.cuda_memory import MAX_LIST_SLOTS, memory_refusal, predict_sphere_device
    from engine.setup.params import default_verlet_skin, derive
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=2 * 10**9, volume_fraction=0.2, precision="float32", backend="cuda",
                          verlet_skin=default_verlet_skin("cuda", "sphere", 0.2))
    why = memory_refusal(spec, derive(spec), 1e13, "a 10 TB device", derive)
    assert why is not None and "Verlet list would hold about" in why and str(MAX_LIST_SLOTS - 1) in why
    largest = int(float(why.rsplit("about ", 1)[1]))
    fits = spec.model_copy(update={"n_particles": largest})
    assert predict_sphere_device(fits, derive(fits)).rows_slots < MAX_LIST_SLOTS
    assert memory_refusal(fits, derive(fits), 1e13, "a 10 TB device", derive) is None


def test_engine_run_refuses_before_the_device_holds_anything(tmp_path, monkeypatch):
    """engine.run of a CUDA sphere spec larger than the device's free memory raises SpecError with the estimate,
    before any ensemble is made and without a result file."""
    from engine.errors import SpecError
    from engine.loops import cuda_memory
    from engine.setup.spec import SimulationSpec

    monkeypatch.setattr(cuda_memory, "device_memory", lambda: (10**6, 10**6, "a 1 MB test device"))
    monkeypatch.setattr("engine.driver.simulate.resolve_backend", lambda name, shape="sphere": "cuda")
    monkeypatch.setattr("engine.driver.simulate.make_ensemble", lambda *a, **k: pytest.fail("an ensemble was made"))
    spec = SimulationSpec(n_particles=4096, volume_fraction=0.058, t_end=1e-4, backend="cuda", thermalization=0)
    import engine

    with pytest.raises(SpecError, match=r"n_particles = 4096: the run needs about .* a 1 MB test device has"):
        engine.run(spec, tmp_path / "out.h5")
    assert not list(tmp_path.iterdir())


def test_demq_run_refuses_in_one_line_with_exit_2(tmp_path, monkeypatch, capsys):
    """`demq run` of a spec the device cannot hold: one line naming the estimate, exit 2, no result file."""
    from engine.loops import cuda_memory
    from service import cli

    monkeypatch.setattr(cuda_memory, "device_memory", lambda: (10**6, 10**6, "a 1 MB test device"))
    monkeypatch.setattr("engine.driver.simulate.resolve_backend", lambda name, shape="sphere": "cuda")
    out = tmp_path / "out.h5"
    with pytest.raises(SystemExit) as ended:
        cli.main(["run", "--set", "n_particles=4096", "--set", "t_end=1e-4", "--set", "thermalization=0",
                  "--quiet", "-o", str(out)])
    rc = ended.value.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("demq run: refused: n_particles = 4096: the run needs")
    assert not out.exists()


if __name__ == "__main__":
    _child(sys.argv[1])


def test_the_loop_kind_by_size_from_2_to_the_19():
    """From 2^19 particles on a scene runs the per-phase loop (engine.loops.system.MULTISTEP_MAX_PARTICLES; measured
    x1.7-1.8 faster than the many-steps loop there, docs/performance.md "Packed ensembles"), below it the many-steps
    loop, whose double buffers of positions, velocities and spins the device-memory account then holds."""
    from engine.loops.cuda_memory import predict_sphere_device
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    accounts = {}
    for n in ((1 << 19) - 1, 1 << 19):
        spec = SimulationSpec(n_particles=n, volume_fraction=0.058, e_t=0.8, backend="cuda")
        accounts[n] = predict_sphere_device(spec, derive(spec)).table
    assert "_alt_spin" in accounts[(1 << 19) - 1] and "_alt[0]" in accounts[(1 << 19) - 1]
    assert "_alt_spin" not in accounts[1 << 19] and "_alt[0]" not in accounts[1 << 19]


def test_dense_sphere_scenes_run_the_per_phase_loop_from_2_to_the_18():
    """From 2^18 spheres at a volume fraction of at least 0.15 the per-phase loop (engine.loops.system
    PER_PHASE_DENSE_PARTICLES, PER_PHASE_DENSE_PHI: measured faster there), and the device-memory account follows."""
    from engine.loops.cuda_memory import predict_sphere_device
    from engine.loops.system import many_steps_loop
    from engine.setup.params import derive
    from engine.setup.spec import SimulationSpec

    assert many_steps_loop((1 << 18) - 1, 0.3) and many_steps_loop(1 << 18, 0.1) and many_steps_loop(1 << 18, None)
    assert not many_steps_loop(1 << 18, 0.15) and not many_steps_loop(1 << 19, 0.01)
    multistep = {}
    for n, phi in (((1 << 18) - 1, 0.2), (1 << 18, 0.2), (1 << 18, 0.1)):
        spec = SimulationSpec(n_particles=n, volume_fraction=phi, e_t=0.8, backend="cuda")
        multistep[n, phi] = "_alt_spin" in predict_sphere_device(spec, derive(spec)).table
    assert multistep == {((1 << 18) - 1, 0.2): True, (1 << 18, 0.2): False, (1 << 18, 0.1): True}


def test_packed_scenes_keep_the_size_rule():
    """The dense rule is one scene's (packed rough scenes ran slower per phase at 2^18, phi = 0.2)."""
    from types import SimpleNamespace

    import numpy as np

    from engine.loops.system import ensemble_many_steps_loop

    def scene(n):       # phi = 0.2: n spheres of radius r in a box of 1
        r = (0.2 / (n * 4.0 / 3.0 * np.pi)) ** (1.0 / 3.0)
        return SimpleNamespace(shape="sphere", n=n, box_length=1.0, radius=np.broadcast_to(np.float64(r), (n,)))

    assert ensemble_many_steps_loop([scene(1 << 18)]) is False
    assert ensemble_many_steps_loop([scene(1 << 17), scene(1 << 17)]) is True
    assert ensemble_many_steps_loop([scene((1 << 18) - 1)]) is True


def test_sphere_volume_fraction_of_a_scene():
    """The spheres' volume over the box's, one-size (a broadcast radius) and mixed; None for other shapes."""
    from types import SimpleNamespace

    import numpy as np

    from engine.loops.system import sphere_volume_fraction

    one = SimpleNamespace(shape="sphere", box_length=2.0, radius=np.broadcast_to(np.float64(0.5), (3,)))
    mixed = SimpleNamespace(shape="sphere", box_length=1.0, radius=np.array([0.1, 0.2]))
    vol = 4.0 / 3.0 * np.pi
    assert sphere_volume_fraction(one) == pytest.approx(3 * vol * 0.125 / 8.0)
    assert sphere_volume_fraction(mixed) == pytest.approx(vol * 0.009)
    assert sphere_volume_fraction(SimpleNamespace(shape="ellipsoid", box_length=1.0)) is None


LOOP_KIND = r'''
from tests.cudasim import fast_block_polling
fast_block_polling()
import engine.loops.system as system
from engine.backends.cuda import CudaBackend
from engine.driver.simulate import contact_params
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.setup.spec import SimulationSpec

system.PER_PHASE_DENSE_PARTICLES = 64      # the rule at a size the simulator builds at once
got = []
for phi in (0.2, 0.1):
    spec = SimulationSpec(n_particles=64, volume_fraction=phi, e_t=0.8, backend="cuda", seed=2)
    p = derive(spec)
    gpu = CudaBackend(initial_spheres(spec, p), contact_params(spec, p, thermalization=False))
    got.append(gpu.e.multistep)
print("LOOP-KIND", got)
'''


def test_a_dense_ensemble_takes_the_per_phase_loop():
    """The CUDA ensemble asks engine.loops.system.ensemble_many_steps_loop with its scenes' volume fraction: with the
    dense rule's size lowered to 64 spheres, at phi = 0.2 the per-phase loop, at 0.1 the many-steps loop."""
    (rc, out, err), = run_children({"kind": ["-c", LOOP_KIND]}, timeout=600).values()
    assert rc == 0 and "LOOP-KIND [False, True]" in out, out[-2000:] + err[-3000:]
