"""Many scenes in one run: ``run_ensemble`` packs specs into one ensemble backend.

::

    run_ensemble(specs, outputs, *, progress=None, should_cancel=None, backend=None,
                 checkpoint_dirs=None, checkpoint_interval=60.0) -> list[RunSummary | BaseException]

Every scene follows the protocol of :func:`engine.driver.simulate.run` — the same
:class:`~engine.driver.simulate.SceneRun` object runs it (thermalisation, switch to the cooling contact, records,
energy-rise check, snapshots, result writer, progress, cancel) — and writes its own H5MD file, the same datasets as
``run`` writes for that spec; its ``/parameters`` also say ``ensemble_size`` (scenes that started together) and
``ensemble_index``. On the CPU (a :class:`~engine.backends.ensemble.SerialEnsemble`) each file is
bit-identical to the lone run's; on the GPU (packed ``CudaEnsemble``) equal to rounding.

Rules:

- All specs share ``shape`` and ``precision`` and resolve to one backend (``backend`` overrides every
  spec's own); otherwise SpecError naming the field, the scene and the values. Everything else (N, φ,
  e_n, e_t, ξ, box, dt, skin, output schedule, t_end, seed) may differ per scene; a null ``verlet_skin``
  is that one backend's default for every scene (engine.setup.params.default_verlet_skin), as in a lone run,
  except that on CUDA the large-scene rule counts the particles of the whole pack, whose lists are rebuilt
  together (a pack of 256 scenes of 4096 spheres takes the skin of one scene of 2^20: the skin changes the cost
  only).
- The scenes advance together by the steps to the nearest next stop of any scene (on a
  ``SerialEnsemble`` each to its own next stop); each scene handles its own records and snapshots.
- A scene that finishes drops out; the others go on. ``should_cancel(k)`` → True drops scene k with
  :class:`~engine.errors.Cancelled` in its slot and its partial file removed. A scene that blows up
  gets its InstabilityError in its slot and only its file is aborted. A scene that cannot start (spec
  that cannot run, overlapping start) gets its error in its slot. The other scenes finish normally.
- Checkpoints: optional (``checkpoint_dirs``, one directory or None per scene), written and resumed
  per scene exactly as :func:`engine.driver.simulate.run` does; a resumed scene may join an ensemble whose other
  scenes start fresh. Without them (the default) an interrupted ensemble starts again from the beginning.
- ``progress(k, Progress)``: per scene, at each of its stops; the Cundall number and wall time of a
  scene count the wall time of the ensemble calls it took part in.
- ``on_result(k, result)``: called as soon as scene k has its RunSummary or exception (its file is
  complete or gone), while the other scenes run on.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Optional, Sequence

from engine.backends.ensemble import make_ensemble, resolve_backend
from engine.driver.startup import release_early, start_driver
from engine.errors import EngineError, SpecError
from engine.driver.simulate import Progress, RunSummary, SceneRun, drive
from engine.setup.spec import load_spec

#: Spec fields every scene of one ensemble must share.
SHARED_FIELDS = ("shape", "precision")


def check_compatible(specs: Sequence, backend: Optional[str] = None) -> str:
    """The backend ('cpu' or 'cuda') an ensemble of these specs runs on; SpecError if they cannot share one."""
    if not specs:
        raise SpecError("an ensemble needs at least one spec")
    shared = [s.model_dump(include=set(SHARED_FIELDS)) for s in specs]
    for name in SHARED_FIELDS:
        first = shared[0][name]
        for k, fields in enumerate(shared):
            if fields[name] != first:
                raise SpecError(f"{name} = {fields[name]!r} of scene {k} differs from {name} = {first!r} of "
                                f"scene 0: the scenes of an ensemble share {' and '.join(SHARED_FIELDS)}")
    resolved = {}
    for k, s in enumerate(specs):
        resolved.setdefault(resolve_backend(backend or s.backend, s.shape), k)
    if len(resolved) > 1:
        (a, ka), (b, kb) = list(resolved.items())[:2]
        raise SpecError(f"backend: scene {ka} resolves to {a!r} and scene {kb} to {b!r}; the scenes of an "
                        f"ensemble run on one backend (give backend= to choose it for all)")
    return next(iter(resolved))


def run_ensemble(specs, outputs, *, progress: Optional[Callable[[int, Progress], None]] = None,
                 should_cancel: Optional[Callable[[int], bool]] = None, backend: Optional[str] = None,
                 checkpoint_dirs: Optional[Sequence] = None, checkpoint_interval: float = 60.0,
                 on_result: Optional[Callable[[int, RunSummary | BaseException], None]] = None,
                 ) -> list[RunSummary | BaseException]:
    """Run the specs as one ensemble; per scene its RunSummary or the exception that ended it.

    See the module docstring. Raises (for the whole call) only for inputs that cannot form an
    ensemble: invalid specs (pydantic ValidationError), specs that differ in shape or precision or
    resolve to different backends (SpecError), mismatched ``outputs``/``checkpoint_dirs`` (ValueError).
    """
    specs = [load_spec(s) for s in specs]
    outputs = [Path(o) for o in outputs]
    if len(outputs) != len(specs):
        raise ValueError(f"outputs: {len(outputs)} paths for {len(specs)} specs; give one output per spec")
    if len({o.resolve() for o in outputs}) != len(outputs):
        raise ValueError("outputs: two scenes would write the same file; give one distinct output per spec")
    dirs = list(checkpoint_dirs) if checkpoint_dirs is not None else [None] * len(specs)
    if len(dirs) != len(specs):
        raise ValueError(f"checkpoint_dirs: {len(dirs)} entries for {len(specs)} specs; give one (or None) per spec")
    t_setup = time.perf_counter()
    start_driver(backend or specs[0].backend)  # the CUDA driver starts while check_compatible imports numba.cuda
    name = check_compatible(specs, backend)
    pack_particles = sum(s.n_particles for s in specs)

    def scene(k: int):
        cb = None if progress is None else (lambda p, k=k: progress(k, p))
        cancel = None if should_cancel is None else (lambda k=k: should_cancel(k))
        try:
            return SceneRun(specs[k], outputs[k], progress=cb, should_cancel=cancel, checkpoint_dir=dirs[k],
                            checkpoint_interval=checkpoint_interval, backend=name, pack_particles=pack_particles)
        except (EngineError, MemoryError, OSError) as exc:  # this scene cannot start; the others can
            return exc

    scenes: list = [scene(0)]   # on this thread: the imports, and the GPU start-up (engine/driver/startup.py)
    threads = _setup_threads(specs) if isinstance(scenes[0], SceneRun) else 1   # else: imports still to make
    if threads > 1:
        with ThreadPoolExecutor(threads, thread_name_prefix="demq-setup") as pool:
            scenes += list(pool.map(scene, range(1, len(specs))))
    else:
        scenes += [scene(k) for k in range(1, len(specs))]
    release_early()
    setup_s = time.perf_counter() - t_setup      # the scenes' own "setup" timings overlap when threaded
    for s in scenes:
        if isinstance(s, SceneRun):
            s.summary_extra["ensemble_setup_s"] = setup_s
            s.t_begin = t_setup          # a scene's job wall time counts the ensemble's set-up
    runs = [s for s in scenes if isinstance(s, SceneRun)]
    kw = dict(reads_state=any(s.reads_state for s in runs), orientations=any(s.spec.orientations for s in runs))
    return drive(scenes, lambda systems, contacts: make_ensemble(name, systems, contacts, **kw),
                 build_one=lambda system, contact: make_ensemble(name, [system], [contact], **kw),
                 on_result=on_result)


#: scenes of an ensemble at least this many are set up (their particles placed) on several threads
SETUP_THREADS_MIN_SCENES = 8


def _setup_threads(specs) -> int:
    """Threads for setting up the scenes of an ensemble (256 small scenes took 0.8 s on one): up to 8,
    for 8 or more scenes whose starts are all drawn sequentially (engine.setup.scene: each scene its own NumPy
    Generator, so a start does not depend on the thread; NumPy's array loops and the random sequential addition,
    compiled with nogil, release the GIL).
    One thread otherwise: the parallel generator's prange code must not be entered by two threads at once."""
    from engine.setup.scene import SEQUENTIAL_GENERATOR, start_generator

    if len(specs) < SETUP_THREADS_MIN_SCENES or any(start_generator(s) != SEQUENTIAL_GENERATOR for s in specs):
        return 1
    return max(1, min(8, _cores(), len(specs) - 1))


def _cores() -> int:
    """CPU cores this process may use (its affinity where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no sched_getaffinity on this platform
        return os.cpu_count() or 1
