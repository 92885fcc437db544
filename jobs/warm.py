"""Warm-up: compile (or load from numba's disk cache) every kernel specialisation a worker can be asked for, before
its first job, so that no job waits for the compiler ("only what the scene needs": the first GPU job on a fresh
host spent 16.9 s of its 21 s compiling).

The engine compiles per *specialisation*: backend ('cpu', 'cuda') x shape (engine/shapes/) x precision (float64,
float32, mixed) x contact law (rough, smooth, rough with Coulomb friction; thermalisation and cooling contacts) x
sizes (one size, or species: the multigrid lists), and on the CPU x scene size (the small scenes' time loop
without parallel regions, the larger ones' in regions: engine/loops/cpu.py SERIAL_LOOP_BELOW). Everything else in a
spec (N, phi, e_n, dt, seeds, ...) is a run-time value of the same compiled code. :func:`specialisations` lists the
combinations the engine accepts (a shape refuses some: spheroids run neither species nor mixed precision);
:func:`warm` runs a tiny scene of each (on the CPU also one of SERIAL_LOOP_BELOW particles) through the same entry
point a job uses (engine.driver.simulate.run, plus a two-scene engine.driver.ensemble.run_ensemble on the
GPU for the packed kernels), and draws a large start's kernels (engine.setup.scene.load_parallel_start; on the GPU also
the device start's, engine.loops.cuda_start.load). Compiled code
goes to numba's disk cache (engine/numba_support/jitcache.py; NUMBA_CACHE_DIR if set), where the simulation processes of
later jobs load it from. Nothing of a warm-up's scenes is kept.

Used by the worker before its first claim (jobs/worker.py, in a process of its own: the worker process itself
never holds a GPU context) and by ``demq warm`` (service/cli.py; the worker image runs it at build time, so a fresh
container finds the CPU kernels compiled: deploy/docker/worker.Dockerfile).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional, Sequence

log = logging.getLogger("demq.warm")

#: the contact laws that compile differently (spec fields)
CONTACT_LAWS = {"rough": {"e_t": 0.8}, "smooth": {"e_t": -1.0}, "friction": {"e_t": 0.8, "friction": 0.5}}
#: one size, or a two-size mixture (multigrid neighbour lists)
SIZES = {"uniform": {}, "species": {"species": [{"radius_ratio": 1.0, "number_fraction": 0.5},
                                                {"radius_ratio": 0.6, "number_fraction": 0.5}]}}
PRECISIONS = ("float64", "float32", "mixed")
#: a scene of a few milliseconds once compiled, with a thermalisation (both contacts) and one record interval
TINY_SCENE = {"n_particles": 64, "volume_fraction": 0.05, "box_length": 0.5, "t_end": 0.0005,
              "thermalization": 0.01, "snapshots": 1}


@dataclass(frozen=True)
class Specialisation:
    """One compiled variant of the engine: what a job's spec selects at compile time."""

    backend: str
    shape: str
    precision: str
    law: str
    sizes: str

    def name(self) -> str:
        return f"{self.backend}/{self.shape}/{self.precision}/{self.law}/{self.sizes}"

    def spec_dict(self) -> dict:
        extra = {"elongation": 1.5} if self.shape == "ellipsoid" else {}
        return {**TINY_SCENE, **extra, **CONTACT_LAWS[self.law], **SIZES[self.sizes], "shape": self.shape,
                "precision": self.precision, "backend": self.backend}


@dataclass
class WarmReport:
    """What a warm-up did: specialisations warmed, numba compilations among them (the rest were disk-cache loads),
    wall seconds, and the specialisations that failed (with the reason)."""

    kernels: int = 0
    compiled: int = 0
    seconds: float = 0.0
    failed: list = field(default_factory=list)

    def line(self) -> str:
        text = (f"warm: {self.kernels} kernels in {self.seconds:.1f} s ({self.compiled} functions compiled, the "
                f"rest loaded from the disk cache)")
        if self.failed:
            text += f"; {len(self.failed)} failed: " + "; ".join(f"{n}: {e}" for n, e in self.failed)
        return text


def specialisations(backends: Sequence[str], shapes: Optional[Sequence[str]] = None,
                    precisions: Optional[Sequence[str]] = None) -> list[Specialisation]:
    """Every specialisation of ``backends`` (and the given shapes and precisions, default all) that the engine
    accepts: a spec it validates and the shape does not refuse."""
    from pydantic import ValidationError

    from engine.shapes import SHAPES, traits
    from engine.setup.spec import SimulationSpec

    out = []
    for backend in backends:
        for shape in shapes or SHAPES:
            for precision in precisions or PRECISIONS:
                for law in CONTACT_LAWS:
                    for sizes in SIZES:
                        sp = Specialisation(backend, shape, precision, law, sizes)
                        try:
                            spec = SimulationSpec.model_validate(sp.spec_dict())
                        except ValidationError:
                            continue
                        if traits(shape).spec_error(spec):
                            continue
                        out.append(sp)
    return out


def local_backends() -> tuple[str, ...]:
    """The backends this host runs: 'cpu', and 'cuda' where a CUDA GPU is present."""
    from engine.backends.ensemble import resolve_backend

    return ("cpu", "cuda") if resolve_backend("auto") == "cuda" else ("cpu",)


def warm(backends: Optional[Sequence[str]] = None, shapes: Optional[Sequence[str]] = None,
         precisions: Optional[Sequence[str]] = None, processes: Optional[int] = None) -> WarmReport:
    """Compile or load every specialisation (:func:`specialisations`; default: this host's backends); a
    specialisation that fails is reported and skipped (its jobs compile it themselves).

    With ``processes`` > 1 (default :func:`warm_processes`), the specialisations are first compiled in that many
    spawned processes, one (backend, precision) group at a time each (a group's specialisations share most of their
    kernels), then all of them run once more in this process, which loads them from the disk cache and compiles
    whatever the parallel pass left out (a save that found its index's lock held for
    engine.numba_support.numba_internals.SAVE_LOCK_WAIT_S caches nothing). The report's ``compiled`` counts the
    compilations of all the processes, its ``failed`` those of the last pass."""
    todo = specialisations(backends or local_backends(), shapes, precisions)
    n = warm_processes(len(todo)) if processes is None else processes
    t0 = time.perf_counter()
    compiled_apart = 0
    if n > 1:
        groups: dict = {}
        for sp in todo:
            groups.setdefault((sp.backend, sp.precision), []).append(sp)
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(n, len(groups)), mp_context=ctx,
                                 initializer=_die_with_parent) as pool:
            compiled_apart = sum(part.compiled for part in pool.map(_warm_list, groups.values()))
    report = _warm_list(todo)
    report.compiled += compiled_apart
    report.seconds = time.perf_counter() - t0
    return report


def warm_processes(count: int) -> int:
    """Processes of a warm-up of ``count`` specialisations: half the CPU cores, at most 8 (each holds a numba
    compiler and, on a GPU host, a CUDA context); 1 on a machine of 3 cores or fewer."""
    return max(1, min(count, 8, (os.cpu_count() or 1) // 2)) if (os.cpu_count() or 1) > 3 else 1


@contextmanager
def numba_compiles(on_start: Callable[[], None]) -> Iterator[None]:
    """Call ``on_start()`` as each numba compilation inside the block begins (numba's "numba:compile" events): what
    a warm-up or a standby start-up had to compile rather than load from the disk cache."""
    from numba.core import event

    class _Listener(event.Listener):
        def on_start(self, ev) -> None:
            on_start()

        def on_end(self, ev) -> None:
            pass

    listener = _Listener()
    event.register("numba:compile", listener)
    try:
        yield
    finally:
        event.unregister("numba:compile", listener)


def _warm_list(todo: list) -> WarmReport:
    """Run a tiny scene of each specialisation in ``todo`` in this process (compiling or loading its kernels)."""
    from engine.driver.ensemble import run_ensemble
    from engine.loops.cpu import SERIAL_LOOP_BELOW
    from engine.setup.params import derive
    from engine.setup.scene import load_parallel_start
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec

    report = WarmReport()
    t0 = time.perf_counter()

    def count() -> None:
        report.compiled += 1

    with numba_compiles(count):
        with tempfile.TemporaryDirectory(prefix="demq-warm-") as tmp:
            for k, sp in enumerate(todo):
                spec = SimulationSpec.model_validate(sp.spec_dict())
                try:
                    run(spec, Path(tmp) / f"{k}.h5")
                    if sp.backend == "cpu":   # the time loop of the larger scenes (parallel regions)
                        run(spec.model_copy(update={"n_particles": SERIAL_LOOP_BELOW}), Path(tmp) / f"{k}p.h5")
                    if sp.backend == "cuda":   # the packed kernels of an ensemble of several scenes
                        run_ensemble([spec, spec.model_copy(update={"seed": 1})],
                                     [Path(tmp) / f"{k}a.h5", Path(tmp) / f"{k}b.h5"])
                    load_parallel_start(spec, derive(spec))      # a large start's functions (host)
                    if sp.backend == "cuda" and sp.shape == "sphere" and sp.sizes == "uniform":
                        _load_device_start(spec.precision)       # a large GPU sphere start, drawn on the device
                    report.kernels += 1
                except Exception as exc:  # noqa: BLE001  (reported; that specialisation's jobs compile it)
                    report.failed.append((sp.name(), f"{type(exc).__name__}: {exc}"))
    report.seconds = time.perf_counter() - t0
    return report


def _load_device_start(precision: str) -> None:
    """The kernels of a large sphere start drawn on the GPU (engine/loops/cuda_start.py) in ``precision``."""
    from engine.loops.cuda_start import load
    from engine.setup.precision import position_dtype, state_dtype

    load(position_dtype(precision), state_dtype(precision))


def _warm_main(conn, backends, shapes=None, precisions=None, background=False) -> None:
    """Entry point of the worker's warm-up process. ``background``: it runs beside the worker's claims, so it leads a
    process group of its own (the worker pauses, resumes and ends the group: :class:`BackgroundWarmUp`), at the
    lowest CPU priority, and dies with the worker."""
    if background:
        _lead_low_priority_group()
    try:
        conn.send(warm(backends, shapes, precisions))
    except Exception as exc:  # noqa: BLE001
        conn.send(WarmReport(failed=[("all", f"{type(exc).__name__}: {exc}")]))
    finally:
        conn.close()


def _lead_low_priority_group() -> None:
    """Make this process the leader of a new process group (its compile processes join it), at nice 19, killed
    with its parent (Linux)."""
    try:
        os.setpgid(0, 0)
    except OSError:   # already made the leader by the worker (BackgroundWarmUp)
        pass
    try:
        os.nice(19)
    except OSError:   # (lowering one's own priority needs no privilege; this only guards odd platforms)
        pass
    _die_with_parent()


def _die_with_parent() -> None:
    """SIGKILL this process when its parent exits (Linux: a worker killed with -9 leaves no paused warm-up)."""
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def warm_in_process(backends: Sequence[str], stop: Optional[threading.Event] = None,
                    shapes: Optional[Sequence[str]] = None,
                    precisions: Optional[Sequence[str]] = None) -> Optional[WarmReport]:
    """:func:`warm` in a spawned process (the caller holds no compiled code and no GPU context), waited for; its
    report, or None if ``stop`` was set first (the process is then killed) or it died without one."""
    warm_up = BackgroundWarmUp(backends, shapes, precisions, background=False)
    try:
        while True:
            report = warm_up.poll(0.2)
            if report is not None or not warm_up.running:
                return report
            if stop is not None and stop.is_set():
                return None   # its work is lost: a later warm-up (or each job) compiles what it had not stored
    finally:
        warm_up.close()


class BackgroundWarmUp:
    """The worker's warm-up (:func:`warm`) in a spawned process that runs beside the claims and never delays one.

    The process leads its own process group (its parallel compile processes are in it too) at nice 19. The worker
    :meth:`pause` s the group (SIGSTOP) while a claim's simulation process runs, so the claim has the cores, the
    GPU and the memory bandwidth to itself, and :meth:`resume` s it (SIGCONT) while the worker waits for work. A
    claim whose kernels the warm-up has not reached yet compiles (or loads) its own, as a job does without a
    warm-up. Numba's disk cache replaces its files atomically, so a claim and the warm-up may store the same
    function. :meth:`close` kills the group (its work so far stays in the cache).

    Only what the claims leave: on a worker that always has work, the warm-up waits; on an idle one it fills the
    cache for the claims to come.
    """

    def __init__(self, backends: Sequence[str], shapes: Optional[Sequence[str]] = None,
                 precisions: Optional[Sequence[str]] = None, background: bool = True):
        ctx = multiprocessing.get_context("spawn")
        self._receiver, sender = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_warm_main, args=(sender, tuple(backends), shapes, precisions, background),
                                 name="demq-warm")
        self._proc.start()
        sender.close()
        self._group = background
        if background:   # the group exists from here on; the process also forms it itself (a race either way)
            try:
                os.setpgid(self._proc.pid, self._proc.pid)
            except OSError:
                pass
        self._paused = False
        self.report: Optional[WarmReport] = None

    @property
    def running(self) -> bool:
        """Whether the warm-up has neither reported nor exited."""
        if self.report is not None or self._receiver.closed:
            return False
        return self._proc.is_alive() or self._receiver.poll(0)

    @property
    def paused(self) -> bool:
        return self._paused

    def poll(self, timeout: float = 0.0) -> Optional[WarmReport]:
        """The report once the warm-up has sent it (waiting up to ``timeout`` seconds), else None."""
        if self.report is None and not self._receiver.closed:
            try:
                if self._receiver.poll(timeout):
                    self.report = self._receiver.recv()
            except (EOFError, OSError):   # it died without a report
                self._receiver.close()
        return self.report

    def pause(self) -> None:
        """Stop the warm-up's processes where they are (SIGSTOP to its group) while a claim runs."""
        if self._group and not self._paused and self.running:
            self._signal(signal.SIGSTOP)
            self._paused = True

    def resume(self) -> None:
        """Let a paused warm-up go on (SIGCONT)."""
        if self._paused:
            self._signal(signal.SIGCONT)
            self._paused = False

    def close(self) -> None:
        """End the warm-up now (its processes killed if still running) and reap its process."""
        if self._proc.is_alive():
            if self._group:
                self._signal(signal.SIGKILL)
            else:
                self._proc.kill()
        self._proc.join(timeout=5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        self._paused = False
        if not self._receiver.closed:
            self._receiver.close()

    def _signal(self, sig: int) -> None:
        try:
            os.killpg(self._proc.pid, sig)
        except (ProcessLookupError, PermissionError):   # the group has exited (or not formed yet: below)
            try:
                os.kill(self._proc.pid, sig)
            except ProcessLookupError:
                pass
