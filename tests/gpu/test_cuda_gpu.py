"""Real-GPU checks of the CUDA backend (skipped without a GPU): compiled kernels agree with the CPU.

Run on the GPU machine: ``python -m pytest tests/gpu -q -s``.
"""

import dataclasses
import math

import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


def _scene(n=4096, phi=0.25, precision="float64", seed=3, friction=0.5):
    """Spec-built granular-gas start (placement and velocities of engine.setup.scene)."""
    from engine.setup.params import derive
    from engine.setup.scene import initial_spheres
    from engine.driver.simulate import contact_params
    from engine.setup.spec import SimulationSpec

    spec = SimulationSpec(n_particles=n, volume_fraction=phi, e_n=0.8, e_t=0.5, friction=friction,
                          precision=precision, seed=seed, velocity_rms=2.0)
    p = derive(spec)
    return initial_spheres(spec, p), contact_params(spec, p, thermalization=False)


def _dense(n_side=16, precision="float64", friction=0.5, seed=3):
    """n_side^3 spheres on a lattice with gaps of 4 % of the radius: contacts from step ~10 on."""
    from engine.backends.base import ContactParams, SphereSystem

    rng = np.random.default_rng(seed)
    a, spacing = 0.1, 0.204
    g = (np.arange(n_side) + 0.5) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = len(pos)
    pos = pos + rng.uniform(-0.001, 0.001, size=pos.shape)
    vel = rng.normal(size=(n, 3))
    vel -= vel.mean(0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    m = np.full(n, 1.0)
    box = n_side * spacing
    system = SphereSystem(box_length=box, position=pos % box, velocity=vel,
                          angular_velocity=rng.normal(size=(n, 3)) * 10.0, orientation=q,
                          radius=np.full(n, a), mass=m, inertia=0.4 * m * a * a)
    k_n = 1.0e5
    c = ContactParams(k_n=k_n, gamma_n_coef=2.0 * np.sqrt(k_n) * 0.2, k_t=k_n * 2 / 7 * 0.5,
                      friction=friction, dt=np.pi * np.sqrt(0.5 / k_n) / 50, skin=0.02,
                      precision=precision, orientation=True, overlap_limit=0.2)
    return system, c


def test_real_gpu_kernels_compile_and_device_is_named():
    from engine.backends.registry import make_backend

    system, c = _scene(n=512)
    be = make_backend("auto", system, c)
    assert be.name == "cuda" and be.device
    be.warmup()
    be.advance(5)


@pytest.mark.parametrize("friction", [0.5, None])
def test_cpu_and_gpu_agree_float64_200_steps(friction):
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.backends.cuda import CudaBackend

    system, c = _dense(friction=friction)
    cpu, gpu = CpuBackend(system, c), CudaBackend(system, c)
    for _ in range(4):
        cpu.advance(50)
        gpu.advance(50)
    a, b = cpu.state(), gpu.state()
    obs = cpu.observe()
    assert obs["contacts"] > 1000 and gpu.builds > 1, (obs, gpu.builds)
    box = system.box_length
    dx = np.abs(a["position"] - b["position"])
    dx = np.minimum(dx, box - dx)  # a wrap across the boundary is no difference
    rel_x = float(dx.max() / box)
    rel_v = float(np.abs(a["velocity"] - b["velocity"]).max() / np.abs(a["velocity"]).max())
    rel_w = float(np.abs(a["angular_velocity"] - b["angular_velocity"]).max()
                  / np.abs(a["angular_velocity"]).max())
    d_q = float(np.abs(a["orientation"] - b["orientation"]).max())
    print(f"\nfriction={friction}: contacts {obs['contacts']}, builds cpu {cpu.builds} gpu {gpu.builds}, "
          f"late {gpu.late_rebuilds}; max rel diff x {rel_x:.2e} v {rel_v:.2e} w {rel_w:.2e}, max |dq| {d_q:.2e}")
    assert gpu.late_rebuilds == 0
    assert rel_x <= 1e-9, rel_x
    assert rel_v <= 1e-6 and rel_w <= 1e-6, (rel_v, rel_w)
    # the orientations integrate the spins (|w| t ~ 1 rad here): they differ as the spins do
    assert d_q <= 1e-6, d_q
    o2 = gpu.observe()
    assert o2["contacts"] == obs["contacts"]
    assert math.isclose(o2["kinetic_energy_translational"], obs["kinetic_energy_translational"], rel_tol=1e-9)


def test_lazy_orientations_agree_with_the_cpu_in_a_dilute_gas():
    """The GPU's lazy sphere orientations (turned only when a torque is about to change the spin, and at
    the end of a call) against the CPU's, in a gas at phi = 0.25 (rough with a Coulomb limit) over 3000 steps in 3
    calls, in both loops: a few hundred spheres collide, once or twice each, so the FMA differences do not grow
    chaotically."""
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.backends.cuda import CudaBackend

    system, c = _scene(n=4096, phi=0.25)
    cpu = CpuBackend(system, c)
    for multistep in (True, False):
        gpu = CudaBackend(system, c)
        gpu.e.multistep = multistep
        if multistep:
            for k in (1000, 1000, 1000):
                cpu.advance(k)
        for k in (1000, 1000, 1000):
            gpu.advance(k)
        a, b = cpu.state(), gpu.state()
        box = system.box_length
        dx = np.abs(a["position"] - b["position"])
        dx = np.minimum(dx, box - dx)
        d_q = float(np.abs(a["orientation"] - b["orientation"]).max())
        rel_w = float(np.abs(a["angular_velocity"] - b["angular_velocity"]).max()
                      / np.abs(a["angular_velocity"]).max())
        turned = float(np.abs(a["orientation"] - np.asarray(system.orientation)).max())
        hit = int((np.abs(a["angular_velocity"] - np.asarray(system.angular_velocity)).max(1) > 0).sum())
        print(f"\nmultistep={multistep}: spheres whose spin changed {hit}, builds {gpu.builds}; max |dq| {d_q:.2e}, "
              f"rel dw {rel_w:.2e}, rel dx {dx.max() / box:.2e}, max |q - q0| {turned:.2f}")
        assert turned > 0.1 and hit > 100 and gpu.builds > 1
        assert d_q <= 1e-9 and rel_w <= 1e-9, (d_q, rel_w)
        # the collision counter: the same contacts begun on both backends
        cc, gc = cpu.observe()["collisions"], gpu.observe()["collisions"]
        print(f"collisions: CPU {cc}, GPU {gc}")
        assert cc == gc and cc > 100, (cc, gc)


def test_float32_accuracy_against_float64():
    """float32 on the GPU against float64 on the GPU after 200 steps (measured, printed)."""
    from engine.backends.cuda import CudaBackend

    s64, c64 = _dense(precision="float64")
    s32, c32 = _dense(precision="float32")
    g64, g32 = CudaBackend(s64, c64), CudaBackend(s32, c32)
    g64.advance(200)
    g32.advance(200)
    a, b = g64.state(), g32.state()
    box = s64.box_length
    dx = np.abs(a["position"] - b["position"].astype(np.float64))
    dx = np.minimum(dx, box - dx)
    o64, o32 = g64.observe(), g32.observe()
    e_rel = abs(o32["kinetic_energy_translational"] / o64["kinetic_energy_translational"] - 1)
    dv = np.abs(a["velocity"] - b["velocity"]).max() / np.abs(a["velocity"]).max()
    dw = np.abs(a["angular_velocity"] - b["angular_velocity"]).max() / np.abs(a["angular_velocity"]).max()
    print(f"\nfloat32 vs float64 (dense, contacts): max |dv|/max|v| {dv:.2e}, max |dw|/max|w| {dw:.2e}")
    print(f"\nfloat32 vs float64 after 200 steps: max |dx|/L {dx.max() / box:.2e}, "
          f"rel E_tr diff {e_rel:.2e}, contacts {o64['contacts']} vs {o32['contacts']}")
    assert dx.max() / box < 1e-3 and e_rel < 1e-3 and dv < 1e-2


def test_mixed_precision_agrees_with_the_cpu_and_tracks_float64():
    """Precision 'mixed' (float64 positions, float32 state) compiles on the GPU, agrees with the CPU's
    'mixed' to the float32 rounding of the state, and follows float64 far more closely than float32 does
    (dense lattice, 200 steps)."""
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.backends.cuda import CudaBackend

    runs = {}
    for prec in ("float64", "float32", "mixed"):
        system, c = _dense(precision=prec)
        g = CudaBackend(system, c)
        for multistep in (True, False):
            g.e.multistep = multistep
            g.advance(100)
        runs[prec] = g.state()
        if prec == "mixed":
            cpu = CpuBackend(system, c)
            cpu.advance(200)
            a = cpu.state()
            assert runs[prec]["position"].dtype == np.float64 and runs[prec]["velocity"].dtype == np.float32
    b = runs["mixed"]
    rel = lambda x, y, k: float(np.abs(np.asarray(x[k], np.float64) - y[k]).max() / np.abs(y[k]).max())  # noqa
    cpu_gpu = rel(b, a, "velocity")
    d32, dmx = rel(runs["float32"], runs["float64"], "velocity"), rel(b, runs["float64"], "velocity")
    print(f"\nmixed: CPU vs GPU max rel dv {cpu_gpu:.2e}; against GPU float64: mixed {dmx:.2e}, float32 {d32:.2e}")
    # float32 rounding of the stored state (6e-8 per step), through ~200 steps of contacts
    assert cpu_gpu < 1e-5, cpu_gpu
    assert dmx < d32 / 10, (dmx, d32)


def test_instability_is_reported_on_gpu():
    from engine.backends.cuda import CudaBackend
    from engine.errors import InstabilityError

    system, c = _scene(n=512)
    system.velocity[7] = [1e4, 0.0, 0.0]  # far too fast for the stiffness
    be = CudaBackend(system, c)
    with pytest.raises(InstabilityError) as err:
        be.advance(2000)
    assert "step" in str(err.value) and err.value.particle >= 0


def test_ensemble_scenes_equal_single_runs_and_both_loops_agree():
    """Four paper-size scenes (own seed and e_n) advanced together equal each run alone, in float64,
    after 400 steps with contacts and rebuilds; the many-steps-per-launch loop and the one-launch-per-phase
    loop give the same trajectory. Only the summation order of a force may differ (a list built at a
    different step lists neighbours in another order), so the bound is rounding growth, 1e-9 of L."""
    from engine.backends.cuda import CudaBackend, CudaEnsemble

    scenes = [_scene(n=4096, phi=0.058, seed=10 + k) for k in range(4)]
    for k, (_, c) in enumerate(scenes):
        scenes[k] = (scenes[k][0], dataclasses.replace(c, gamma_n_coef=c.gamma_n_coef * (1 + 0.3 * k)))
    ens = CudaEnsemble([s for s, _ in scenes], [c for _, c in scenes])
    assert ens.multistep
    singles = []
    for k, (s, c) in enumerate(scenes):
        b = CudaBackend(s, c)
        b.e.multistep = k % 2 == 0  # half of the references through the per-phase loop
        singles.append(b)
    for chunk in (150, 250):
        assert not ens.advance(chunk)
        for b in singles:
            b.advance(chunk)
    obs = ens.observe()
    for k, b in enumerate(singles):
        box = scenes[k][0].box_length
        a, e = b.state(), ens.state(k)
        dx = np.abs(a["position"] - e["position"])
        dx = np.minimum(dx, box - dx)
        rel = float(dx.max() / box)
        print(f"\nscene {k}: contacts {obs[k]['contacts']}, builds {b.builds}/{ens.builds}, max |dx|/L {rel:.2e}")
        assert rel <= 1e-9, rel
        assert math.isclose(obs[k]["kinetic_energy_translational"], b.observe()["kinetic_energy_translational"],
                            rel_tol=1e-9)


def test_cached_launches_give_the_same_trajectory(monkeypatch):
    """The launch cache (engine/loops/cuda_launch.py) launches with the argument list numba-cuda built for the
    first launch with the same arrays, scalars refilled, through the driver's cuLaunchKernel with a parameter array
    of its own (``DIRECT``) or through cuda.core: the trajectory is bit for bit the one of launches through
    numba-cuda's dispatcher (the one-launch-per-phase loop, 150 steps in 3 calls with contacts and rebuilds)."""
    import engine.loops.cuda_launch as launch
    from engine.backends.cuda import CudaBackend

    system, c = _dense()
    states = {}
    for cached, direct in ((True, True), (True, False), (False, False)):
        monkeypatch.setattr(launch, "ENABLED", cached)
        monkeypatch.setattr(launch, "DIRECT", direct)
        gpu = CudaBackend(system, c)
        gpu.e.multistep = False
        for _ in range(3):
            gpu.advance(50)
        lc = gpu.e._lc
        assert (lc.hits > 100) == cached and (lc.off_reason is None) == cached, (cached, lc.hits, lc.off_reason)
        assert (lc.direct > 100) == direct, (direct, lc.direct, lc.direct_off_reason)
        assert gpu.builds > 1
        states[cached, direct] = gpu.state()
    for key in ("position", "velocity", "angular_velocity", "orientation"):
        assert np.array_equal(states[True, True][key], states[False, False][key]), key
        assert np.array_equal(states[True, False][key], states[False, False][key]), key


@pytest.mark.parametrize("multistep", [False, True])
def test_a_contact_law_switched_on_mid_run_runs_its_own_kernels_through_the_cache(monkeypatch, multistep):
    """A scene that changes its kernel specialisation under way (Coulomb friction switched on after 50 steps
    without it, as a job's cooling follows its thermalisation) launches the new kernels through the launch cache:
    bit for bit the trajectory of launches through numba-cuda's dispatcher, in both loops (the cache once keyed
    its entries by kernel name and arrays only, and went on launching the frictionless kernels). The friction
    matters in this scene: without the switch the trajectory differs."""
    import engine.loops.cuda_launch as launch
    from engine.backends.cuda import CudaBackend

    system, c = _dense()
    frictionless = dataclasses.replace(c, friction=None)
    states = {}
    for cached, switch in ((True, True), (False, True), (False, False)):
        monkeypatch.setattr(launch, "ENABLED", cached)
        gpu = CudaBackend(system, frictionless)
        gpu.e.multistep = multistep
        gpu.advance(50)
        if switch:
            gpu.set_contact(c)
        gpu.advance(100)
        assert gpu.builds > 1
        assert (gpu.e._lc.hits > 0) == cached, gpu.e._lc.hits
        states[cached, switch] = gpu.state()
    for key in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(states[True, True][key], states[False, True][key]), key
    assert not np.array_equal(states[False, True]["angular_velocity"], states[False, False]["angular_velocity"])


def test_fused_step_gives_the_two_launch_trajectory(monkeypatch):
    """The per-phase loop's fused step (a step's forces and the next kick-drift in one launch, positions and
    velocities double-buffered, engine/loops/cuda_loop.py ``forces_kick_drift``) integrates the trajectory of the
    two launches forces then kick_drift, to rounding (the compiler may contract the same arithmetic differently in
    the two kernels): smooth spheres with a dashpot in a dense start, 150 steps in 3 calls with contacts and
    rebuilds."""
    import dataclasses

    import engine.loops.cuda_stepping as stepping
    from engine.backends.cuda import CudaBackend

    system, c = _dense()
    c = dataclasses.replace(c, k_t=None, friction=None)
    states, launches = {}, {}
    for fused in (True, False):
        monkeypatch.setattr(stepping, "FUSED", fused)
        gpu = CudaBackend(system, c)
        gpu.e.multistep = False
        assert "forces_kick_drift" in gpu.e.k
        for _ in range(3):
            gpu.advance(50)
        assert gpu.builds > 1 and gpu.e.late_rebuilds == 0
        states[fused], launches[fused] = gpu.state(), gpu.e.launches
    assert launches[True] < 0.6 * launches[False], launches
    a, b = states[True], states[False]
    box = system.box_length
    dx = np.abs(a["position"] - b["position"])
    assert float(np.minimum(dx, box - dx).max() / box) <= 1e-12
    assert float(np.abs(a["velocity"] - b["velocity"]).max() / np.abs(b["velocity"]).max()) <= 1e-9


@pytest.mark.parametrize("multistep", [False, True])
def test_rebuilds_that_leave_the_particles_in_place_keep_the_trajectory(monkeypatch, multistep):
    """A rebuild that permutes nothing (engine/loops/cuda_rebuild.py ``SORT_DRIFT_CELLS``) lists each particle's
    neighbours in the order a permuting one does: rough spheres with a Coulomb cap in a dense start, 300 steps in 3
    calls, the same state bit for bit (read back in id order) and the same contacts and history, with fewer
    permutations than rebuilds; both loops."""
    import engine.loops.cuda_rebuild as rebuild
    from engine.backends.cuda import CudaBackend

    system, c = _dense()
    got = {}
    for drift in (rebuild.SORT_DRIFT_CELLS, 0.0):
        monkeypatch.setattr(rebuild, "SORT_DRIFT_CELLS", drift)
        gpu = CudaBackend(system, c)
        gpu.e.multistep = multistep
        for _ in range(3):
            gpu.advance(100)
        got[drift] = (gpu.state(), gpu.contacts(), gpu.builds, gpu.e.sorts)
    (a, ca, builds, sorts), (b, cb, builds_ref, sorts_ref) = got.values()
    assert builds == builds_ref >= 3 and sorts_ref == builds_ref and 1 <= sorts < builds, (builds, sorts)
    for key in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(a[key], b[key]), key
    assert np.array_equal(ca[0], cb[0]) and np.array_equal(ca[1], cb[1])


def test_the_status_copy_through_the_driver_bindings_copies_and_records():
    """engine.numba_support.numba_internals.async_copy_and_record and event_waiter: the device array's bytes arrive in
    the pinned buffer once the wait for the event it records has returned, through the driver library's calls made
    with ctypes (found by name on a GPU host)."""
    from numba import cuda

    from engine.numba_support.numba_internals import _driver_call, async_copy_and_record, event_waiter

    assert all(_driver_call(n) is not None for n in ("cuMemcpyDtoHAsync_v2", "cuEventRecord", "cuEventSynchronize"))
    stream = cuda.stream()
    src = np.arange(14, dtype=np.float64) * 1.5
    dev = cuda.to_device(src, stream=stream)
    host = cuda.pinned_array(14, np.float64)
    host[:] = -1.0
    event = cuda.event(timing=False)
    copy = async_copy_and_record(dev, host, stream, event)
    wait = event_waiter(event)
    copy()
    wait()
    assert np.array_equal(host, src)
    dev.copy_to_device(src + 1.0, stream=stream)
    copy()
    wait()
    assert np.array_equal(host, src + 1.0)


def test_the_device_copy_through_the_driver_bindings_copies_in_stream_order():
    """engine.numba_support.numba_internals.async_copy_device: the source's bytes land in the destination in stream
    order (a kernel queued after the copy reads them), and a size or layout it does not handle is refused."""
    from numba import cuda

    from engine.numba_support.numba_internals import async_copy_device

    stream = cuda.stream()
    src = cuda.to_device(np.arange(24, dtype=np.float64).reshape(3, 8), stream=stream)
    dst = cuda.to_device(np.zeros((3, 8)), stream=stream)
    async_copy_device(dst, src, stream)
    stream.synchronize()
    assert np.array_equal(dst.copy_to_host(), np.arange(24, dtype=np.float64).reshape(3, 8))
    rows = cuda.to_device(np.zeros((4, 8)), stream=stream)[:3]   # the first rows of a scratch array: contiguous
    async_copy_device(rows, src, stream)
    stream.synchronize()
    assert np.array_equal(rows.copy_to_host(), src.copy_to_host())
    with pytest.raises(ValueError):
        async_copy_device(cuda.device_array((2, 8)), src, stream)
    with pytest.raises(ValueError):
        async_copy_device(cuda.device_array((3, 16))[:, ::2], src, stream)      # a strided view


@pytest.mark.parametrize("friction", [0.5, None])
def test_the_fused_many_steps_kernel_gives_the_two_pass_trajectory(monkeypatch, friction):
    """The many-steps kernel's fused pass (a step's forces and the next kick-drift, one grid sync a step;
    positions, velocities and spins double-buffered, engine/loops/cuda_loop.py ``run_steps_fused``) integrates
    the trajectory of the two-pass ``run_steps``, to rounding (the compiler may contract the same arithmetic
    differently in the two kernels): rough spheres in a dense start, 150 steps in 3 calls with contacts and
    rebuilds."""
    import engine.loops.cuda_stepping as stepping
    from engine.backends.cuda import CudaBackend

    system, c = _dense(friction=friction)
    states = {}
    for fused in (True, False):
        monkeypatch.setattr(stepping, "MULTISTEP_FUSED", fused)
        gpu = CudaBackend(system, c)
        assert gpu.e.multistep and ("run_steps_fused" in gpu.e.k)
        for _ in range(3):
            gpu.advance(50)
        assert gpu.builds > 1
        states[fused] = gpu.state()
    a, b = states[True], states[False]
    box = system.box_length
    dx = np.abs(a["position"] - b["position"])
    assert float(np.minimum(dx, box - dx).max() / box) <= 1e-12
    for key in ("velocity", "angular_velocity"):
        assert float(np.abs(a[key] - b[key]).max() / np.abs(b[key]).max()) <= 1e-9, key
