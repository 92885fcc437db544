"""Every concrete backend and ensemble class implements its interface (engine/backends/protocol.py) in full.

The driver (engine/driver/simulate.py) calls the interface's methods without probing for them, so a class that left an
abstract method, or took other parameters than the interface names, would fail in a run. Checked here on the
classes themselves (no instance: the CUDA ones import numba.cuda, which needs no GPU, but are not built).
"""

import inspect

import pytest

from engine.backends.protocol import Backend, Ensemble


def _backend_classes():
    from engine.backends.cuda import CudaBackend
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.shapes.spheroid.cpu_backend import CpuEllipsoidBackend
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidBackend

    return [CpuBackend, CpuEllipsoidBackend, CudaBackend, CudaEllipsoidBackend]


def _ensemble_classes():
    from engine.backends.cuda import CudaEnsemble
    from engine.backends.ensemble import SerialEnsemble
    from engine.shapes.spheroid.cuda_backend import CudaEllipsoidEnsemble

    return [SerialEnsemble, CudaEnsemble, CudaEllipsoidEnsemble]


def _interface_methods(base) -> list:
    return [name for name, member in vars(base).items()
            if inspect.isfunction(member) and not name.startswith("_")]


def _check(cls, base) -> None:
    assert issubclass(cls, base), f"{cls.__name__} does not derive from {base.__name__}"
    assert not inspect.isabstract(cls), f"{cls.__name__} leaves abstract: {sorted(cls.__abstractmethods__)}"
    assert "__getattr__" not in {n for k in cls.__mro__ for n in vars(k)}, f"{cls.__name__} delegates by __getattr__"
    for name in _interface_methods(base):
        want = list(inspect.signature(getattr(base, name)).parameters.values())
        have = list(inspect.signature(getattr(cls, name)).parameters.values())
        assert [(p.name, p.kind) for p in have[:len(want)]] == [(p.name, p.kind) for p in want], \
            f"{cls.__name__}.{name}{inspect.signature(getattr(cls, name))} differs from the interface's " \
            f"{name}{inspect.signature(getattr(base, name))}"
        extra = [p.name for p in have[len(want):] if p.default is inspect.Parameter.empty
                 and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        assert not extra, f"{cls.__name__}.{name} needs parameters the interface does not pass: {extra}"
        for p_want, p_have in zip(want, have):
            assert (p_want.default is inspect.Parameter.empty) == (p_have.default is inspect.Parameter.empty), \
                f"{cls.__name__}.{name}: parameter {p_have.name} optional in one and required in the other"


@pytest.mark.parametrize("index", range(4))
def test_backend_classes_implement_the_backend_interface(index):
    _check(_backend_classes()[index], Backend)


@pytest.mark.parametrize("index", range(3))
def test_ensemble_classes_implement_the_ensemble_interface(index):
    _check(_ensemble_classes()[index], Ensemble)


def test_the_check_catches_a_missing_method_and_a_changed_signature():
    """The check above fails for a class that leaves a method out or renames a parameter (it can fail)."""
    from engine.backends.ensemble import SerialEnsemble

    class Partial(Backend):
        def set_contact(self, contact):
            pass

    with pytest.raises(AssertionError, match="leaves abstract"):
        _check(Partial, Backend)

    class Renamed(SerialEnsemble):
        def state(self, scene, reuse=False):
            return {}

    with pytest.raises(AssertionError, match="differs from the interface"):
        _check(Renamed, Ensemble)


def test_capabilities_are_declared_not_probed():
    """What a class can do is a declared attribute of the interface (True where it can), not a method that exists
    or not."""
    from engine.backends.cuda import CudaEnsemble
    from engine.backends.ensemble import SerialEnsemble

    assert SerialEnsemble.independent_steps and not CudaEnsemble.independent_steps
    assert CudaEnsemble.shares_observation and not SerialEnsemble.shares_observation


_ONE_GPU_JOB = r"""
from tests.cudasim import fast_block_polling
fast_block_polling()
import numpy as np
from engine.backends.ensemble import SerialEnsemble, make_ensemble
from engine.errors import InstabilityError
from engine.shapes import host
from tests.engine.test_cuda_simulator import contact, tiny_system

ens = make_ensemble("cuda", [tiny_system()], [contact()])
assert type(ens) is host("sphere").cuda_ensemble() and not isinstance(ens, SerialEnsemble)
assert ens.n_scenes == 1 and ens.scene_info(0) == {}            # GPU-built lists: nothing to add to the file
lone = make_ensemble("cuda", [tiny_system()], [contact(list_mode="cpu-sequential")])
assert lone.lists is not None and lone.scene_info(0)["list_mode"] == "cpu-sequential"
bad = tiny_system()
bad.position[1] = bad.position[0] + np.array([0.05, 0.0, 0.0])   # radius 0.1: an overlap of half a diameter
try:
    make_ensemble("cuda", [bad], [contact()])
except InstabilityError as exc:
    print("RAISED", exc)
print("ONE-PATH-OK")

# a driver that reads no state (no snapshots, no checkpoints) gets no host frame slot prepared
cls = host("sphere").cuda_ensemble()
prepared = []
cls._prepare_frame_slot = lambda self: prepared.append(self.reads_state)
make_ensemble("cuda", [tiny_system()], [contact()], reads_state=False)
make_ensemble("cuda", [tiny_system()], [contact()])
assert prepared == [True], prepared

# a process warms a kernel set once: the next ensemble of the same kind skips the n = 0 launches
import engine.loops.cuda_stepping as stepping
warm_launches = []
kick = cls._kick_drift
cls._kick_drift = lambda self, *a, **kw: (warm_launches.append(kw.get("n")), kick(self, *a, **kw))
for precision in ("float64", "float64", "float32"):
    make_ensemble("cuda", [tiny_system()], [contact(precision=precision)]).warmup()
assert warm_launches == [0, 0], warm_launches    # the second float64 ensemble launched nothing
print("WARM-ONCE-OK")
"""


def test_a_lone_gpu_job_is_its_ensemble_itself():
    """One scene on the GPU (engine.run's path) is the shape's CUDA ensemble itself, not wrapped: it takes the
    scene's list mode and raises a start that fails at t = 0 at once, as a CPU backend's constructor does. (The same
    child: a CUDA ensemble prepares no host frame slot for a driver that reads no state, and a process warms each
    kernel set once.)"""
    from tests.cudasim import run_children

    (rc, out, err), = run_children({"one": ["-c", _ONE_GPU_JOB]}, timeout=600).values()
    assert rc == 0, err[-3000:]
    assert ("ONE-PATH-OK" in out and "WARM-ONCE-OK" in out and "RAISED" in out and
            "overlap" in out.split("RAISED", 1)[1].lower()), out


def test_a_scene_reads_its_state_only_for_snapshots_or_checkpoints(tmp_path):
    """SceneRun.reads_state, which make_ensemble passes on (a CUDA ensemble prepares host frame buffers only then)."""
    from engine.driver.simulate import SceneRun
    from engine.setup.spec import SimulationSpec

    def scene(snapshots, checkpoint_dir=None):
        spec = SimulationSpec(n_particles=64, volume_fraction=0.05, t_end=0.001, thermalization=0.0,
                              snapshots=snapshots, backend="cpu")
        return SceneRun(spec, tmp_path / "x.h5", checkpoint_dir=checkpoint_dir)

    assert not scene(0).reads_state
    assert scene(2).reads_state
    assert scene(0, tmp_path / "ck").reads_state
