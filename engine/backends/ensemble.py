"""Ensembles: K independent scenes advanced together by one backend.

The interface every ensemble implements in full (:class:`engine.backends.protocol.Ensemble`, an abstract base
class; what an ensemble cannot do is the base class's explicit default)::

    name: str; device: str; builds: int; n_scenes: int
    set_contact(k, contact)     contact constants of scene k (thermalisation -> cooling switch)
    warmup()                    compile (or load) the kernels for the current contact parameters
    advance(nsteps) -> {k: err} advance every ACTIVE scene by nsteps; a scene that blows up is
                                deactivated and returned (InstabilityError naming its step and particle);
                                the others complete the nsteps
    deactivate(k)               a finished / cancelled / failed scene drops out; never advanced again
    observe() -> [dict | None]  per scene, the keys of a single backend's observe(); None when inactive
    state(k, reuse), contacts(k) host copies of scene k (snapshots, checkpoints)
    set_contacts, advance_each, deactivate_many, observe_scene, plan, scene_builds, scene_info;
    independent_steps, shares_observation

Scene indices are the positions of the systems given to the constructor and never change.

Implementations:

- :class:`SerialEnsemble` wraps K single backends (:func:`engine.backends.base.make_backend`) and
  advances the active scenes one after another. On the CPU there is no launch overhead to amortise —
  a CPU time loop is already compiled whole and uses every core for one scene — so serial advancing is
  the right CPU implementation; it also makes every scene bit-identical to the same scene run alone.
  Its :meth:`SerialEnsemble.advance_each` takes a different number of steps per scene in one call
  (``independent_steps``), so the driver advances every scene in exactly the chunks a lone run would use
  (the velocity-Verlet half kicks at chunk ends make the last bits depend on the chunking).
- ``engine.shapes.sphere.cuda_backend.CudaEnsemble`` (spheres) and
  ``engine.shapes.spheroid.cuda_backend.CudaEllipsoidEnsemble`` (ellipsoids) store the scenes back to back on the GPU
  and advance them with the same kernel launches (packed ensemble).

:func:`make_ensemble` picks one by backend name, like :func:`engine.backends.base.make_backend` does for
a single scene; :func:`resolve_backend` says which backend a name resolves to without building one.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Mapping, Sequence

import numba

from engine.backends.base import ContactParams, cuda_available
from engine.backends.protocol import Ensemble
from engine.backends.registry import make_backend
from engine.errors import BackendUnavailable
from engine.shapes import host, shape_of

BACKEND_NAMES = ("auto", "cpu", "cuda")

#: A CPU scene of fewer particles than this is built and advanced on one Numba thread. Each time step of the CPU
#: loop is a ``parallel=True`` region whose threads meet at its end; for a small scene that meeting costs more
#: than the step's work, and beside a busy process it waits for that process's time slices. Loop time per
#: particle-step on the 2-core VM (2026-11-27, default spec otherwise, one thread against two): 52 against 96 ns
#: at N = 64, 30 against 39 ns at 256, 19-26 against 20-220 ns at 1024, 18-25 against 14-134 ns at 2048, 23
#: against 14 ns at 4096 (the wide ranges: another process busy on the machine); a default 64-sphere job's loop
#: took 0.08-0.13 s on one thread, 0.4-21 s on two. The numbers written do not depend on the thread count
#: (tests/engine/test_threads.py), only the time does. Such a scene also advances in the loop compiled without
#: parallel regions (engine.loops.cpu.SERIAL_LOOP_BELOW, the same size), faster again on one thread.
ONE_THREAD_BELOW = 1024


@contextmanager
def scene_threads(n_particles: int):
    """Numba's thread count (this calling thread's) for advancing a CPU scene of ``n_particles``: one below
    :data:`ONE_THREAD_BELOW`, else unchanged; restored on exit."""
    before = numba.get_num_threads()
    if n_particles >= ONE_THREAD_BELOW or before == 1:
        yield before
        return
    numba.set_num_threads(1)
    try:
        yield 1
    finally:
        numba.set_num_threads(before)


@contextmanager
def numba_threads(count: int):
    """Numba's thread count (this calling thread's) set to ``count`` inside the block, restored on exit."""
    before = numba.get_num_threads()
    if count == before:
        yield count
        return
    numba.set_num_threads(count)
    try:
        yield count
    finally:
        numba.set_num_threads(before)


class ThreadChoice:
    """The Numba thread count for the next advance of one CPU scene: one or all, whichever took less wall time
    per step in its latest advance (:meth:`pick`, then :meth:`record` the advance's steps, wall and CPU seconds).

    Why: every step of the CPU loop is a few ``parallel=True`` regions whose threads meet at each region's end
    (engine/loops/cpu.py). On an idle machine all threads are faster from about :data:`ONE_THREAD_BELOW` particles
    up: the default job's time loop (4096 spheres, 127 000 steps) took 1.8 s on two threads against 3.0 s on one
    on the 2-core VM (2026-11-27). But when another process keeps a core busy, the OS deschedules one of the two
    threads for whole time slices while the other waits at the meeting: two threads took 9.6 and 14.7 s beside
    another session's tests (one thread: 3.0-3.1 s), and the job before this class took 9.5-10.8 s beside one busy
    loop (3.4-3.7 s with it) and 56-110 s beside two (8-12 s). Which count is faster depends on the machine's load
    at the time, so the scene measures it. It starts on one thread; all threads are
    tried only after an advance on one thread that had its core to itself (the thread's CPU time at least 90 % of
    the wall time: on a machine with every core busy, all threads lose by far, and even one trial costs more than
    the choice saves); then it advances on the faster count, and the slower one is tried again after a number of
    advances that grows with how much slower it was (16 (ratio - 1), at least 4, at most 256: trials cost about
    1/16 of the time), or on the next advance when the faster one has become slower than the other was. Scenes
    below :data:`ONE_THREAD_BELOW` particles always run on one thread. The numbers written do not depend on the
    thread count (tests/engine/test_threads.py), only the time does.
    """

    def __init__(self, n_particles: int, threads: int | None = None):
        most = numba.get_num_threads() if threads is None else int(threads)
        self.counts = (1, most) if n_particles >= ONE_THREAD_BELOW and most > 1 else (1,)
        self.cost: dict = {}          # thread count -> wall seconds per step of its latest advance
        self.best = 1
        self.wait = 0                 # advances on the best count before the other is tried again
        self.core_free = False        # the latest advance on one thread had its core to itself

    def pick(self) -> int:
        """The thread count for the next advance."""
        if len(self.counts) == 1 or 1 not in self.cost:
            return 1
        most = self.counts[1]
        if most not in self.cost or (self.wait <= 0 and self.best == 1):
            return most if self.core_free else 1      # all threads only where a core was free
        if self.wait <= 0:
            return 1
        return self.best

    def record(self, count: int, steps: int, seconds: float, cpu_seconds: float | None = None) -> None:
        """An advance of ``steps`` steps on ``count`` threads took ``seconds`` of wall time and ``cpu_seconds`` of the
        calling thread's CPU time (None: not measured, taken as a free core)."""
        if count == 1:
            self.core_free = cpu_seconds is None or cpu_seconds >= 0.9 * seconds
        if steps <= 0 or count not in self.counts or len(self.counts) == 1:
            return
        self.cost[count] = seconds / steps
        if len(self.cost) < len(self.counts):
            return
        other = self.counts[1] if count == 1 else 1
        if count == self.best:
            self.wait -= 1
            if self.cost[count] > self.cost[other]:
                self.wait = 0     # slower now than the other count was at its trial: try it next
            return
        # a trial of the other count (or the first measurement of both): choose again, schedule the next trial
        self.best = min(self.counts, key=lambda c: self.cost[c])
        fast, slow = sorted((self.cost[count], self.cost[other]))
        ratio = slow / fast if fast > 0 else 1.0
        self.wait = int(min(256, max(4, round(16 * (ratio - 1)))))


def check_backend_name(name: str) -> None:
    """BackendUnavailable unless ``name`` is 'auto', 'cpu' or 'cuda'."""
    if name not in BACKEND_NAMES:
        raise BackendUnavailable(f"unknown backend {name!r}; expected 'auto', 'cpu' or 'cuda'")


def resolve_backend(name: str, shape: str = "sphere") -> str:
    """The backend ('cpu' or 'cuda') that ``name`` ('auto', 'cpu', 'cuda') resolves to for ``shape``.

    Same rules as :func:`engine.backends.base.make_backend`, for spheres and ellipsoids alike: 'auto'
    takes CUDA when a real GPU is present.
    """
    check_backend_name(name)
    if name == "auto":
        return "cuda" if cuda_available() else "cpu"
    return name


class SerialEnsemble(Ensemble):
    """K single backends advanced one after another (the CPU ensemble; see the module docstring).

    On the CPU there is no kernel-launch overhead to amortise: each scene's time loop is one compiled
    call that already uses all the cores, so packing scenes into one loop would gain nothing, and
    advancing the active scenes in turn is the right implementation. Each scene keeps its own
    backend object, so its trajectory is bit-identical to the same scene run alone.
    """

    #: each scene is advanced by its own number of steps (the chunks a lone run uses)
    independent_steps = True

    def __init__(self, name: str, systems: Sequence, contacts: Sequence[ContactParams]):
        if len(systems) != len(contacts) or not systems:
            raise ValueError("an ensemble needs one ContactParams per scene and at least one scene")
        self._backends: list = []
        self._sizes = [int(system.n) for system in systems]   # particles per scene (their Numba thread count)
        self._threads = [ThreadChoice(n) for n in self._sizes]   # each scene's thread count per advance
        for system, contact in zip(systems, contacts):
            with scene_threads(system.n):   # the build's list and first forces are parallel loops too
                self._backends.append(make_backend(name, system, contact))
        first = self._backends[0]
        self.name = first.name
        self.device = first.device
        self.n_scenes = len(self._backends)
        self._active = [True] * self.n_scenes
        self._builds_of_dropped = 0

    # ---- the Ensemble interface -------------------------------------------------------------------

    @property
    def builds(self) -> int:
        """Neighbour-list builds of all scenes so far (dropped scenes included)."""
        return self._builds_of_dropped + sum(b.builds for b in self._backends if b is not None)

    def scene_builds(self, k: int) -> int:
        """Neighbour-list builds of scene k (while it is active)."""
        return self._backend(k).builds

    def scene_info(self, k: int) -> dict:
        """Extra run attributes of scene k for its result file (its backend's :meth:`list_info`)."""
        return self._backend(k).list_info()

    def set_contact(self, k: int, contact: ContactParams) -> None:
        self._backend(k).set_contact(contact)

    def plan(self, steps: int) -> None:
        for b in self._backends:
            if b is not None:
                b.plan(steps)

    def warmup(self) -> None:
        for b in self._backends:
            if b is not None:
                b.warmup()

    def advance(self, nsteps: int) -> dict:
        """Advance every active scene by nsteps; {k: error} of the scenes that failed (deactivated)."""
        return self.advance_each({k: nsteps for k in self.active_scenes()})

    def advance_each(self, steps: Mapping[int, int]) -> dict:
        """Advance scene k by steps[k] (active scenes only); {k: error} of the scenes that failed.

        A scene's failure (InstabilityError, or any other error of its backend) deactivates that scene
        only; the others still complete their steps.
        """
        failed: dict = {}
        for k, n in steps.items():
            if n <= 0 or not self._active[k]:
                continue
            backend = self._backends[k]
            choice = self._threads[k]
            try:
                with numba_threads(choice.pick()) as count:
                    t0, c0 = time.perf_counter(), time.thread_time()
                    backend.advance(int(n))
                    choice.record(count, int(n), time.perf_counter() - t0, time.thread_time() - c0)
            except Exception as exc:  # one scene's failure: the others go on
                failed[k] = exc
                self.deactivate(k)
        return failed

    def deactivate(self, k: int) -> None:
        if self._active[k]:
            self._active[k] = False
            self._builds_of_dropped += self._backends[k].builds
            self._backends[k] = None  # free its memory

    def observe(self) -> list:
        return [b.observe() if b is not None else None for b in self._backends]

    def observe_scene(self, k: int) -> dict:
        return self._backend(k).observe()

    def state(self, k: int, reuse=False) -> dict:
        return self._backend(k).state(reuse=reuse)

    def contacts(self, k: int):
        return self._backend(k).contacts()

    # ---- helpers ----------------------------------------------------------------------------------

    def active_scenes(self) -> list:
        return [k for k, a in enumerate(self._active) if a]

    def _backend(self, k: int):
        b = self._backends[k]
        if b is None:
            raise ValueError(f"scene {k} of the ensemble is no longer active")
        return b


def make_ensemble(name: str, systems: Sequence, contacts: Sequence[ContactParams], *,
                  reads_state: bool = True, orientations: bool = True) -> Ensemble:
    """An ensemble of the scenes for backend 'cpu', 'cuda' or 'auto'.

    'cpu' -> :class:`SerialEnsemble` of CPU backends; 'cuda' -> the shape's packed CUDA ensemble
    (engine.shapes.host(shape).cuda_ensemble), also for a single scene (a lone GPU job: one object, whose
    :meth:`start_alone` takes the scene's list mode and raises a start that fails at t = 0, as a CPU backend's
    constructor does); 'auto' -> 'cuda' when a CUDA GPU is present, else 'cpu'. All scenes must have the same
    shape.
    ``reads_state``: whether the driver will copy scenes' state to the host (snapshots, checkpoints); False lets a
    CUDA ensemble skip the host buffers it would prepare for it. ``orientations`` False: no scene's spheres have
    orientations (their spec's ``orientations``), which a CUDA ensemble then never holds.
    """
    shapes = {shape_of(s) for s in systems}
    if len(shapes) > 1:
        raise ValueError(f"an ensemble holds scenes of one shape: got {' and '.join(sorted(shapes))} together")
    shape = shapes.pop() if shapes else "sphere"
    resolved = resolve_backend(name, shape)
    if resolved == "cuda":
        ensemble = host(shape).cuda_ensemble()(list(systems), list(contacts), reads_state=reads_state,
                                               orientations=orientations)
        if len(systems) == 1:
            ensemble.start_alone(contacts[0])
        return ensemble
    return SerialEnsemble(resolved, systems, contacts)
