"""The driver: validate, derive, place, thermalise, cool, record, write; progress and cancel hooks.

Public API (used by the CLI and the job worker)::

    run(spec, output, *, progress=None, should_cancel=None, checkpoint_dir=None,
        checkpoint_interval=60.0, backend=None) -> RunSummary

The per-scene protocol below lives in one object, :class:`SceneRun`, and one loop, :func:`drive`,
advances any number of them on an ensemble (engine/backends/ensemble.py, the interface
engine/backends/protocol.py): :func:`run` is an ensemble of one scene (``make_ensemble``: on the CPU a
:class:`~engine.backends.ensemble.SerialEnsemble`, on the GPU the shape's CUDA ensemble itself),
``engine.driver.ensemble.run_ensemble`` packs many scenes into one ensemble.

Protocol (Hidalgo et al. 2013): a homogeneous non-overlapping start with Gaussian translational and angular
velocities at equal temperatures, ``thermalization`` collisions per particle with dissipation off
(e_n = 1; rough spheres keep a perfectly rough elastic spring, e_t = 1, smooth ones stay smooth), then
the cooling run from t = 0 to t_end with the spec's contact law. Observables are recorded every
``output_interval``; ``snapshots`` full frames are spread evenly over [0, t_end].

Outputs are writers with triggers (engine/output/writers/): the records writer (observables and the energy check) at the
record steps, the snapshot writer at the snapshot steps, the progress writer at every stop, the checkpoint writer
every ``checkpoint_interval`` wall seconds; :func:`drive` only advances the scenes stop to stop (:class:`_Runner`).

Checkpoints (for the job queue): every ``checkpoint_interval`` wall seconds the driver writes
``checkpoint_dir/state.npz`` (state, contact springs, clock) and a copy of the partial HDF5 file,
both through a temporary name and a rename. ``run`` with a ``checkpoint_dir`` that holds a checkpoint
of the same spec resumes from it; the finished file is the same as an uninterrupted run's up to
rounding (the neighbour list is rebuilt at the resume point).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from types import SimpleNamespace
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.backends.base import ContactParams
from engine.backends.ensemble import check_backend_name, make_ensemble, resolve_backend
from engine.driver.startup import begin as begin_gpu_startup
from engine.errors import Cancelled, SpecError
from engine.output.h5md import H5MDWriter, partial_path, writer_process_ready
from engine.output.writers.checkpoints import Checkpointer
from engine.output.writers.progress import Progress, ProgressWriter
from engine.output.writers.records import ENERGY_RISE_TOLERANCE, RecordWriter, record
from engine.output.writers.snapshots import FrameSlots, SnapshotWriter
from engine.setup.params import Q_SPHERE, Derived, derive, verlet_skin_radii, with_backend
from engine.setup.precision import output_dtype
from engine.setup.spec import SimulationSpec, load_spec
from engine.setup.start_kind import device_start

#: the names this module has always offered (the writers moved to engine/output/writers/)
__all__ = ["ENERGY_RISE_TOLERANCE", "Progress", "RunSummary", "SceneRun", "TIMINGS", "SHARED_TIMINGS", "contact_params",
           "drive", "record", "run", "run_contacts", "schedule", "warm_process"]
_FrameSlots = FrameSlots

@dataclass
class RunSummary:
    """What a finished run reports. Two wall times: ``loop_s``, the time loop's (thermalisation + cooling
    steps, after compilation and placement), and ``job_wall_s``, the whole job's, from the spec to the closed
    result file. Cundall numbers (particle-steps per wall second): ``cundall`` of the loop, ``cundall_e2e`` of the
    whole job."""

    output: Path
    backend: str
    device: str
    n_particles: int
    steps: int                    # cooling + thermalisation steps advanced
    loop_s: float                 # wall seconds of the time loop
    cundall: float                # N * steps / loop_s
    resumed_from_step: Optional[int] = None
    extra: dict = field(default_factory=dict)   # run attributes; "timings": wall s per phase (TIMINGS)
    job_wall_s: Optional[float] = None          # wall seconds from the spec to the closed result file
    cundall_e2e: Optional[float] = None         # N * steps / job_wall_s


#: Where a job's wall time goes (RunSummary.extra["timings"], /parameters@timings), seconds:
#: setup = spec checks, derived parameters and the initial state (placement, velocities, spins);
#: build = the backend (device upload, first neighbour list); compile = kernel compilation or cache load;
#: loop = the time loop (thermalisation + cooling steps); records, snapshots, checkpoints = output stops;
#: open/close = creating and finishing the result file. build and compile are the ensemble's (shared by its
#: scenes: SHARED_TIMINGS); the others are the scene's own.
TIMINGS = ("setup", "build", "compile", "loop", "records", "snapshots", "checkpoints", "open", "close")
SHARED_TIMINGS = ("build", "compile")


def contact_params(spec: SimulationSpec, p: Derived, *, thermalization: bool) -> ContactParams:
    """Contact constants for the cooling run or the dissipation-free thermalisation."""
    smooth = spec.smooth
    if thermalization:
        k_t = None if smooth else p.k_n * Q_SPHERE / (1.0 + Q_SPHERE)  # Hidalgo et al. (2013) Eq. 4 at e_t = 1
        return ContactParams(k_n=p.k_n, gamma_n_coef=0.0, k_t=k_t, friction=None, dt=p.dt, skin=p.skin,
                             precision=spec.precision, orientation=tracks_orientations(spec),
                             overlap_limit=spec.overlap_limit, list_mode=spec.list_mode)
    return ContactParams(k_n=p.k_n, gamma_n_coef=p.gamma_n_coef, k_t=None if smooth else p.k_t,
                         friction=spec.friction, dt=p.dt, skin=p.skin, precision=spec.precision,
                         orientation=tracks_orientations(spec), overlap_limit=spec.overlap_limit,
                         list_mode=spec.list_mode)


def tracks_orientations(spec: SimulationSpec) -> bool:
    """Whether a run integrates its spheres' orientations: only where its snapshots hold them (a sphere's
    orientation changes nothing else; a spheroid's turns are its dynamics, which the shape's own law integrates)."""
    return spec.snapshots > 0 and spec.orientations


def run_contacts(spec: SimulationSpec, p: Derived) -> tuple:
    """The contact constants a fresh run uses, in order: the thermalisation's (when it has one), the cooling's."""
    cool = contact_params(spec, p, thermalization=False)
    return (contact_params(spec, p, thermalization=True), cool) if p.n_thermalization_steps > 0 else (cool,)


def schedule(p: Derived, snapshots: int) -> tuple[np.ndarray, set]:
    """Event steps of the cooling run (the record and snapshot writers' trigger steps) and the snapshot steps."""
    records = RecordWriter(p, 0, False).trigger.steps()
    snaps = SnapshotWriter(p.n_steps, snapshots).trigger.steps()
    return np.array(sorted(records | snaps)), snaps


class SceneRun:
    """The protocol of one scene, step by step: everything :func:`run` and ``run_ensemble`` share.

    It owns the scene's spec, derived parameters, initial state (or checkpoint), contact constants,
    event schedule, result writer, energy-rise check, progress, cancel check and checkpoints; it does
    not own a backend. A driver (:func:`drive`) advances the scene's backend (or its slot in an
    ensemble) by :meth:`steps_to_next` steps, tells it :meth:`advanced`, and calls :meth:`at_stop`
    when the scene has reached its next stop, passing a *view* of the scene's state with ``observe()``,
    ``state()``, ``contacts()`` and ``set_contact(contact)``.

    Stops: during thermalisation every ``output_every`` steps (progress, checkpoint; the last one
    switches to the cooling contact); during the cooling run the record and snapshot steps of
    :func:`schedule`. Before advancing to a stop the driver calls :meth:`check_cancel` once.
    """

    def __init__(self, spec, output, *, progress: Optional[Callable[[Progress], None]] = None,
                 should_cancel: Optional[Callable[[], bool]] = None, checkpoint_dir=None,
                 checkpoint_interval: float = 60.0, backend: Optional[str] = None,
                 pack_particles: Optional[int] = None):
        from engine.shapes import host, traits

        t_setup = time.perf_counter()
        #: when this job began (its spec given); run_ensemble sets the ensemble's start: the job wall time's origin
        self.t_begin = t_setup
        spec = load_spec(spec)
        self.spec = spec
        self.shape = host(spec.shape)
        refused = traits(spec.shape).spec_error(spec)
        if refused:
            raise SpecError(refused)
        self.output = Path(output)
        self.progress, self.should_cancel = progress, should_cancel
        self.spec_json = spec.to_json()
        #: added to the RunSummary's extra only (not to the file): engine.driver.ensemble's set-up wall time
        self.summary_extra: dict = {}
        self.ck = Checkpointer(checkpoint_dir, checkpoint_interval)
        self.resume = resume = self.ck.load(self.spec_json)
        # the start does not depend on the Verlet skin, so the particles are placed before the backend is
        # resolved: meanwhile the GPU starts up on its own thread (engine/driver/startup.py)
        check_backend_name(backend or spec.backend)
        # every derived parameter, once; the skin (and the cutoff) follow the backend once it is resolved, below
        p = derive(spec)
        self.startup = begin_gpu_startup(spec, backend or spec.backend, run_contacts(spec, p), p)
        # a GPU job's large sphere start is drawn by its backend on the device (engine/loops/cuda_start.py)
        if self.startup is not None and resume is None and device_start(spec):
            system = self.shape.initial_system(spec, p, on_device=True)
        else:
            system = self.shape.initial_system(spec, p)
        # the backend ('cpu' or 'cuda') this scene runs on: `backend` overrides the spec's, 'auto' resolved here
        self.backend = resolve_backend(backend or spec.backend, spec.shape)
        if self.backend != "cuda":
            from engine.setup.scene import drawn_on_host

            system = drawn_on_host(system)
        # a null verlet_skin is the resolved backend's default at this volume fraction (species: the total
        # phi; the stored spec keeps null; /parameters say verlet_skin and skin); an explicit value always wins.
        # A CUDA pack rebuilds its scenes' lists together: the large-scene rule counts its particles
        pack = pack_particles if self.backend == "cuda" else None
        self.verlet_skin = verlet_skin_radii(spec, self.backend, pack)
        self.p = p = with_backend(p, spec, self.backend, pack)
        if self.backend == "cuda" and spec.shape == "sphere":   # before the GPU holds anything of this job
            from engine.backends.base import cuda_available
            from engine.loops.cuda_memory import refuse_oversize

            # an explicit backend = 'cuda' is not probed on this thread: wait here for the start-up thread's probe,
            # which starts numba-cuda's driver; the memory query's first driver call beside it failed with
            # CUDA_ERROR_NOT_INITIALIZED (numba-cuda's driver start is not safe across threads)
            cuda_available()

            refuse_oversize(spec.model_copy(update={"verlet_skin": self.verlet_skin}), p,
                            reads_state=spec.snapshots > 0 or checkpoint_dir is not None)
        phase, step_done = "thermalization", 0
        # a cooling checkpoint was written after its own record at step_done, which the file already holds
        self.resumed_in_cooling = resume is not None and str(resume["phase"]) == "cooling"
        if resume is not None:
            phase, step_done = str(resume["phase"]), int(resume["step_done"])
            system = dataclasses.replace(
                system, position=resume["position"], velocity=resume["velocity"],
                angular_velocity=resume["angular_velocity"], orientation=resume["orientation"],
                contact_pairs=resume["pairs"], contact_springs=resume["springs"])
        if p.n_thermalization_steps == 0 and phase == "thermalization":
            phase = "cooling"
        self.resumed_from = (step_done if phase == "cooling" else step_done - p.n_thermalization_steps) \
            if resume is not None else None
        if phase == "thermalization" and step_done >= p.n_thermalization_steps:
            phase, step_done = "cooling", 0  # resumed right after the last thermalisation chunk
        self.system = system
        self.phase, self.step_done = phase, step_done
        self.cool = contact_params(spec, p, thermalization=False)
        self.therm = contact_params(spec, p, thermalization=True)

        self.n = spec.n_particles
        self.total_steps = p.n_thermalization_steps + p.n_steps
        self.events, self.snaps = schedule(p, spec.snapshots)
        self._event_steps = self.events.tolist()   # the same as Python ints: read at every stop
        self.wall = 0.0       # wall seconds of this attempt's time loop (advances this scene took part in)
        self.steps_run = 0
        dissipative = spec.e_n < 1.0 or (not spec.smooth and spec.e_t < 1.0) or spec.friction is not None
        # the output writers (engine/output/writers/): records with the energy check, snapshots, progress;
        # checkpoints: ck
        self.records = RecordWriter(p, self.n, dissipative,
                                    float(resume["prev_energy"]) if resume is not None else None)
        self.snapshots = SnapshotWriter(p.n_steps, spec.snapshots, n_particles=spec.n_particles,
                                        orientations=spec.orientations)
        self.progress_writer = ProgressWriter(progress, self.n, self.total_steps, self.resumed_from)
        # collisions counted before a resume (the new backend's counter starts at 0)
        self.coll_base = int(resume["collisions"]) if resume is not None and "collisions" in resume else 0
        self.writer: Optional[H5MDWriter] = None
        self.done = False
        self._chunk = max(1, p.output_every)
        self.defer_file = False           # set by drive(): the file is written at the end, in a writer process
        self.file_thread = False          # set by drive(): file work on the I/O thread (engine/output/h5md.py)
        self.timings = dict.fromkeys(TIMINGS, 0.0)
        self.timings["setup"] = time.perf_counter() - t_setup
        if phase == "thermalization":
            self._target = min(step_done + self._chunk, p.n_thermalization_steps)
        else:
            self._enter_cooling(skip_current=self.resumed_in_cooling)

    # ---- what the driver asks -------------------------------------------------------------------------

    @property
    def reads_state(self) -> bool:
        """Whether the run copies the scene's state to the host: snapshots, or checkpoints (a checkpoint directory).
        A scene that only records its observables never does; its backend need not prepare for it."""
        return bool(self.snaps) or self.ck.dir is not None

    @property
    def initial_contact(self) -> ContactParams:
        """Contact constants the scene's backend starts with."""
        return self.therm if self.phase == "thermalization" else self.cool

    @property
    def warm_contacts(self) -> tuple:
        """Contact constants to compile for, in order (the last one is :attr:`initial_contact`'s successor)."""
        return (self.therm, self.cool) if self.phase == "thermalization" else (self.cool,)

    def steps_to_next(self) -> int:
        """Steps from the current position to the scene's next stop (0: it is at a stop)."""
        return self._target - self.step_done

    def stops_ahead(self, limit: int) -> list:
        """Steps from the current position to the stops one advance call may run through: the next stop, then, while
        each stop passed is a record stop only (no snapshot, not the run's last stop, in the cooling run), the
        following ones within ``limit`` steps."""
        out = [self.steps_to_next()]
        if self.phase != "cooling" or self.done:
            return out
        ev, idx = self._event_steps, self._idx
        while idx + 1 < len(ev) and self.records.trigger(ev[idx]) and not self.snapshots.trigger(ev[idx]):
            idx += 1
            if ev[idx] - self.step_done > limit:
                break
            out.append(ev[idx] - self.step_done)
        return out

    def at_record(self, obs: dict, k: int, wall_s: float) -> None:
        """A record stop passed inside a longer advance call (:meth:`stops_ahead`): advanced k steps in wall_s, then
        :meth:`at_stop` with the observables the time loop summed there (no snapshot is due at such a stop; a due
        checkpoint waits for the call's last stop, where the state can be read)."""
        self.advanced(k, wall_s)
        self.at_stop(SimpleNamespace(observe=lambda: obs), checkpoint=False)

    def check_cancel(self) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise Cancelled("run cancelled on request")

    def advanced(self, k: int, wall_s: float) -> None:
        """The scene was advanced by k steps in a call of wall_s seconds."""
        self.step_done += k
        self.steps_run += k
        self.wall += wall_s

    def open(self) -> None:
        """Create the result writer (``<output>.part``; a resumed scene continues its checkpointed file)."""
        from engine.setup.scene import start_generator
        from engine.version import __version__

        t0 = time.perf_counter()
        spec, p = self.spec, self.p
        dtype = output_dtype(spec.precision)
        derived = {k: v for k, v in p.as_dict().items()}
        derived.update(engine_version=__version__, q=Q_SPHERE, e_n=spec.e_n, e_t=spec.e_t,
                       start_generator=start_generator(spec),
                       verlet_skin=self.verlet_skin)
        common = dict(n=spec.n_particles, box_length=spec.box_length, spec_json=self.spec_json,
                      derived=derived, dtype=dtype)
        if self.resume is not None:
            shutil.copyfile(self.ck.dir / "partial.h5", partial_path(self.output))
            self.writer = H5MDWriter(self.output, resume=True, **common)
            self.writer.truncate(json.loads(str(self.resume["counts"])))
        else:
            system = self.system
            self.writer = H5MDWriter(self.output, mass=system.mass, **self.shape.writer_fields(system, p),
                                     creator_version=__version__, background=self.file_thread,
                                     deferred=self.defer_file, **common)
        self.timings["open"] += time.perf_counter() - t0

    def at_stop(self, view, checkpoint: bool = True) -> None:
        """Handle the stop the scene has reached: each writer whose trigger fires here acts (engine/output/writers/:
        records with the energy check, snapshot, progress, checkpoint; ``checkpoint`` False: not here)."""
        if self.phase == "thermalization":
            self._thermalization_stop(view)
            return
        p = self.p
        step_done = self.step_done
        t_sim = step_done * p.dt
        ck_due = checkpoint and self.ck.due() and step_done < p.n_steps
        tm = self.timings
        t0 = time.perf_counter()
        obs = self._counted(view.observe())
        self._record(step_done, t_sim, obs)
        t1 = time.perf_counter()
        tm["records"] += t1 - t0
        if self.snapshots.trigger(step_done):
            self.snapshots.write(self.writer, step_done, t_sim, view)
            tm["snapshots"] += time.perf_counter() - t1
        self._report("cooling", p.n_thermalization_steps + step_done, t_sim, step_done)
        if ck_due:
            t0 = time.perf_counter()
            self.ck.save(self.writer, view, phase="cooling", step_done=step_done, extra=self._ck_extra(obs))
            tm["checkpoints"] += time.perf_counter() - t0
        self._next_event()

    def _thermalization_stop(self, view) -> None:
        """A stop of the thermalisation (dissipation off, nothing recorded): progress, checkpoint when due, and at
        its end the switch to the cooling contact."""
        p = self.p
        self._report("thermalization", self.step_done, (self.step_done - p.n_thermalization_steps) * p.dt,
                     self.step_done - p.n_thermalization_steps)
        if self.ck.due():
            t0 = time.perf_counter()
            self.ck.save(self.writer, view, phase="thermalization", step_done=self.step_done,
                         extra=self._ck_extra(self._counted(view.observe())))
            self.timings["checkpoints"] += time.perf_counter() - t0
        if self.step_done >= p.n_thermalization_steps:
            self.phase, self.step_done = "cooling", 0
            view.set_contact(self.cool)
            self._enter_cooling(skip_current=False)
        else:
            self._target = min(self.step_done + self._chunk, p.n_thermalization_steps)

    def _record(self, step_done: int, t_sim: float, obs: dict) -> None:
        """The records writer at a stop (engine/output/writers/records.py: the record when its trigger fires there, and
        the energy check)."""
        self.records.write(self.writer, step_done, t_sim, obs)

    def _counted(self, obs: dict) -> dict:
        """The observables with the collisions counted before a resume added (a copy: ``obs`` may be shared)."""
        if "collisions" not in obs or not self.coll_base:
            return obs
        return {**obs, "collisions": obs["collisions"] + self.coll_base}

    def _ck_extra(self, obs: dict) -> dict:
        """What a checkpoint keeps beside the state: the spec, the energy check's reference and the collision
        count of :meth:`_counted` observables (the resumed run's series continues from it)."""
        extra = {"spec": self.spec_json, "prev_energy": self.records.prev_energy}
        if "collisions" in obs:
            extra["collisions"] = obs["collisions"]
        return extra

    def finish(self, backend: str, device: str, builds: int, info: Optional[dict] = None,
               shared_timings: Optional[dict] = None) -> RunSummary:
        """Write the run attributes, rename the result to its final name, clear the checkpoints.

        ``shared_timings``: the ensemble's build and compile seconds (SHARED_TIMINGS), reported with the
        scene's own in ``extra["timings"]`` and ``/parameters@timings`` (the file's lacks ``close``)."""
        return self.finish_end(self.finish_begin(backend, device, builds, info, shared_timings))

    def finish_begin(self, backend: str, device: str, builds: int, info: Optional[dict] = None,
                     shared_timings: Optional[dict] = None) -> tuple:
        """:meth:`finish` in two halves: this one hands the file its run attributes (a deferred file is then
        written by a writer process while other scenes finish); :meth:`finish_end` waits for it."""
        cundall = self.n * self.steps_run / self.wall if self.wall > 0 else 0.0
        tm = self.timings
        tm["loop"] = self.wall
        tm.update(shared_timings or {})
        run_info = {"backend": backend, "device": device, "wall_time": self.wall, "cundall_number": cundall,
                    "steps_total": self.total_steps, "neighbour_builds": builds,
                    "resumed_from_step": -1 if self.resumed_from is None else self.resumed_from,
                    **(info or {}), "timings": {k: round(v, 6) for k, v in tm.items()}}
        t0 = time.perf_counter()
        fut = self.writer.finish_async(run_info)
        tm["close"] = time.perf_counter() - t0
        return fut, cundall, backend, device, info

    def finish_end(self, begun: tuple) -> RunSummary:
        fut, cundall, backend, device, info = begun
        tm = self.timings
        t0 = time.perf_counter()
        path = fut.result()
        self.ck.clear()
        t1 = time.perf_counter()
        tm["close"] += t1 - t0
        job_wall = t1 - self.t_begin
        return RunSummary(output=path, backend=backend, device=device, n_particles=self.n, steps=self.steps_run,
                          loop_s=self.wall, cundall=cundall, resumed_from_step=self.resumed_from,
                          job_wall_s=job_wall, cundall_e2e=self.n * self.steps_run / job_wall if job_wall > 0 else 0.0,
                          extra={**(info or {}), "timings": dict(tm), **self._startup_info(),
                                 **self.summary_extra})

    def _startup_info(self) -> dict:
        """The GPU start-up thread's wall seconds and error (engine/driver/startup.py), when this scene had one."""
        s = self.startup
        return {} if s is None else {"gpu_startup": {"seconds": s.seconds, "error": s.error}}

    def abort(self) -> None:
        """Delete the partial result (checkpoints stay for a later attempt)."""
        if self.writer is not None:
            self.writer.abort()
            self.writer = None

    # ---- internals --------------------------------------------------------------------------------------

    def _enter_cooling(self, skip_current: bool) -> None:
        side = "right" if skip_current else "left"
        self._idx = int(np.searchsorted(self.events, self.step_done, side=side))
        self._set_cooling_target()

    def _next_event(self) -> None:
        self._idx += 1
        self._set_cooling_target()

    def _set_cooling_target(self) -> None:
        if self._idx >= len(self._event_steps):
            self.done = True
            self._target = self.step_done
        else:
            self._target = self._event_steps[self._idx]

    def _report(self, phase: str, done_total: int, t_sim: float, step: int) -> None:
        """The progress writer at a stop (the time loop's steps and wall seconds so far)."""
        self.progress_writer.write(phase, done_total, t_sim, step, self.steps_run, self.wall)


class _SceneView:
    """Scene ``i`` of an ensemble, seen as a single backend by :meth:`SceneRun.at_stop`.

    ``observe()`` reads the ensemble's observables once per driver round, shared by every scene that stops in
    that round, where the ensemble ``shares_observation`` (packed CUDA); else only this scene's.
    """

    def __init__(self, ens, i: int, cache: dict, slots: "_FrameSlots"):
        self.ens, self.i, self.cache, self.slots = ens, i, cache, slots
        self._shared = ens.shares_observation

    def observe(self) -> dict:
        if not self._shared:
            return self.ens.observe_scene(self.i)
        if "all" not in self.cache:
            self.cache["all"] = self.ens.observe()
        return self.cache["all"][self.i]

    def state(self, reuse=False) -> dict:
        """Scene i's state in id order; ``reuse`` (True or a buffer slot): the arrays may be buffers that the
        next call with the same slot overwrites."""
        return self.ens.state(self.i, reuse=reuse)

    def state_pieces(self, rows: int):
        """Scene i's state in id order in pieces of ``rows`` particles (the ensemble's ``state_pieces``: a large
        frame without a host copy of the whole), or None where the ensemble copies whole frames only."""
        pieces = getattr(self.ens, "state_pieces", None)
        return None if pieces is None else pieces(self.i, rows)

    def contacts(self):
        return self.ens.contacts(self.i)

    def set_contact(self, contact: ContactParams) -> None:
        self.ens.set_contact(self.i, contact)
        self.cache.pop("all", None)


def drive(scenes: list, build: Callable, build_one: Optional[Callable] = None,
          lockstep: Optional[bool] = None,
          on_result: Optional[Callable[[int, object], None]] = None) -> list:
    """Run scenes together on one ensemble; return per scene its RunSummary or the exception that ended it.

    ``scenes``: :class:`SceneRun` objects, or exceptions for scenes that failed before they started
    (kept in their slots). ``build(systems, contacts)`` makes the ensemble (see
    engine/backends/ensemble.py); if it fails with several scenes, ``build_one(system, contact)`` is tried
    per scene to find the scenes that cannot start (their error goes in their slot), and the ensemble is
    built again from the others. With one scene the build error is that scene's.

    Each round: every scene that stands at the start of a segment checks its cancel request (a cancelled
    scene drops out with Cancelled, its partial file removed); the active scenes are advanced — by their
    own distances to their next stops when the ensemble has ``independent_steps`` (and ``lockstep`` is not
    True), else all by the distance to the nearest stop of any scene (``advance``); then every scene at a
    stop handles it. A scene that blows up (InstabilityError from the
    ensemble or its own checks) drops out with that error and only its file is aborted; a finished scene writes
    its file and drops out.
    An error of the ensemble itself (not of one scene) ends every active scene with that error;
    KeyboardInterrupt and other BaseExceptions abort every open file and propagate.

    ``on_result(k, result)`` is called as soon as scene k has its result (a job can be reported done,
    failed or cancelled while the other scenes run on).
    """
    results: list = [s if isinstance(s, BaseException) else None for s in scenes]
    live = [k for k, s in enumerate(scenes) if not isinstance(s, BaseException)]
    if on_result is not None:
        for k, r in enumerate(results):
            if r is not None:
                on_result(k, r)
    if not live:
        return results
    t0 = time.perf_counter()
    # the GPU start-up threads (engine/driver/startup.py) end before the job's own backend uses the GPU
    for startup in {id(scenes[k].startup): scenes[k].startup for k in live if scenes[k].startup}.values():
        startup.wait()
    ens, live = _build(scenes, live, results, build, build_one)
    shared = {"build": time.perf_counter() - t0, "compile": 0.0}
    if on_result is not None:
        for k, s in enumerate(scenes):
            if not isinstance(s, BaseException) and k not in live:
                on_result(k, results[k])
    if ens is None:
        return results
    runs = [scenes[k] for k in live]          # ensemble index i -> SceneRun
    t0 = time.perf_counter()
    try:
        _compile(ens, runs)
        shared["compile"] = time.perf_counter() - t0
    except Exception as exc:  # the ensemble cannot compile: every scene fails with the reason
        for k in live:
            results[k] = exc
            if on_result is not None:
                on_result(k, exc)
        return results
    _Runner(ens, runs, live, results, on_result, shared, lockstep).run()
    return results


def _compile(ens, runs: list) -> None:
    """Compile (or load) the kernels of every contact the scenes will use, in their order, and set the first."""
    rounds = max(len(r.warm_contacts) for r in runs)
    for r_ in range(rounds):
        ens.set_contacts({i: r.warm_contacts[min(r_, len(r.warm_contacts) - 1)] for i, r in enumerate(runs)})
        ens.warmup()
    ens.set_contacts({i: r.initial_contact for i, r in enumerate(runs)})


class _Runner:
    """The scenes of one built and compiled ensemble, advanced stop to stop until each has its result (see
    :func:`drive`): ``runs[i]`` is the SceneRun of ensemble index i, ``live[i]`` its slot in ``results``."""

    def __init__(self, ens, runs: list, live: list, results: list, on_result, shared: dict, lockstep):
        self.ens, self.runs, self.live, self.results = ens, runs, live, results
        self.on_result, self.shared = on_result, shared
        self.size = len(runs)
        self.active: set = set()
        # per scene, made once (a stop costs host time while the GPU waits for the next round): its view of the
        # ensemble, whose round cache is one dict cleared every round
        self.cache: dict = {}
        frame_slots = FrameSlots()
        self.views = [_SceneView(ens, i, self.cache, frame_slots) for i in range(self.size)]
        self.per_scene = ens.independent_steps and not lockstep

    def run(self) -> None:
        ens, runs = self.ens, self.runs
        # how long the run goes on (the auto list mode weighs a probe against it)
        ens.plan(max((r.p.n_steps if r.phase == "cooling" else r.total_steps) - r.step_done for r in runs))
        if _defer_files(ens, runs):  # many small GPU scenes: files written at the end, in parallel processes
            from engine.output import h5md_pool

            h5md_pool.prewarm(min(len(runs), h5md_pool.MAX_PROCESSES), ready=writer_process_ready)
            for r in runs:
                r.defer_file = True
        file_thread = _file_thread(ens)
        for r in runs:
            r.file_thread = file_thread
        try:
            self.open_all()
            at_start = set(self.active)
            while self.active:
                self.check_cancels(at_start)
                if not self.active:
                    break
                failed = self.advance()
                if failed is None:
                    break
                for i, exc in failed.items():
                    if i in self.active:
                        self.end(i, exc)
                self.cache.clear()
                at_start = self.stops()
        except BaseException:
            for i in list(self.active):
                runs[i].abort()
            raise

    def open_all(self) -> None:
        """Open every scene's result file; the scenes that are done at once (nothing to run) finish."""
        for i, r in enumerate(self.runs):
            try:
                r.open()
            except Exception as exc:
                self.end(i, exc)
                continue
            self.active.add(i)
        self.finish([i for i in sorted(self.active) if self.runs[i].done])

    def check_cancels(self, at_start: set) -> None:
        """Every scene at the start of a segment checks its cancel request (Cancelled ends it)."""
        for i in sorted(at_start & self.active):
            try:
                self.runs[i].check_cancel()
            except Exception as exc:  # Cancelled, or a cancel check that failed
                self.end(i, exc)

    def advance(self) -> Optional[dict]:
        """Advance the active scenes to their next stops (per scene, or all by the nearest stop); {i: error} of the
        scenes that failed, or None when the ensemble itself failed (every active scene then ended with it)."""
        runs, ens = self.runs, self.ens
        if not self.per_scene and len(self.active) == 1 and ens.observes_in_loop():
            i = next(iter(self.active))
            at = runs[i].stops_ahead(self._steps_within(runs[i], RECORDS_CALL_S))
            if len(at) > 1:
                return self.advance_through_records(i, at)
        dist = {i: runs[i].steps_to_next() for i in self.active}
        failed: dict = {}
        try:
            if self.per_scene:
                todo = {i: d for i, d in dist.items() if d > 0}
                if todo:
                    t0 = time.perf_counter()
                    failed = ens.advance_each(todo)
                    wall = time.perf_counter() - t0
                    for i, d in todo.items():
                        runs[i].advanced(d, wall)
            else:
                m = min(dist.values())
                if m > 0:
                    t0 = time.perf_counter()
                    failed = ens.advance(m)
                    wall = time.perf_counter() - t0
                    for i in self.active:
                        runs[i].advanced(m, wall)
        except Exception as exc:  # the ensemble itself failed: every active scene ends with it
            for i in sorted(self.active):
                self.end(i, exc)
            return None
        return failed

    @staticmethod
    def _steps_within(run: SceneRun, seconds: float) -> int:
        """The steps scene ``run`` takes in about ``seconds`` of its time loop so far (0 before its first call)."""
        return int(seconds * run.steps_run / run.wall) if run.wall > 0 else 0

    def advance_through_records(self, i: int, at: list) -> Optional[dict]:
        """Scene i alone, on an ensemble that sums observables in its time loop (``observes_in_loop``): one advance
        through the stops ``at`` (SceneRun.stops_ahead), each record passed on the way handed its observables
        (SceneRun.at_record); the last stop is then handled as every stop is, its observables answering observe()."""
        run = self.runs[i]
        t0 = time.perf_counter()
        try:
            failed, obs = self.ens.advance_observing(at[-1], at)
        except Exception as exc:  # the ensemble itself failed
            self.end(i, exc)
            return None
        wall = time.perf_counter() - t0
        if i in failed:
            return failed
        done = 0
        try:
            for k, o in zip(at[:-1], obs[:-1]):
                run.at_record(o[i], k - done, wall * (k - done) / at[-1])
                done = k
        except Exception as exc:  # a record's energy check
            self.end(i, exc)
            return {}
        run.advanced(at[-1] - done, wall * (at[-1] - done) / at[-1])
        return failed

    def stops(self) -> set:
        """Every scene at a stop handles it; the finished ones finish. Returns the scenes that start a segment."""
        runs = self.runs
        done, at_start = [], set()
        for i in sorted(i for i in self.active if runs[i].steps_to_next() == 0):
            try:
                runs[i].at_stop(self.views[i])
            except Exception as exc:
                self.end(i, exc)
                continue
            if runs[i].done:
                done.append(i)
            else:
                at_start.add(i)
        self.finish(done)
        return at_start

    def settle(self, i: int, result, deactivated: bool = False) -> None:
        self.results[self.live[i]] = result
        self.active.discard(i)
        if not deactivated:
            self.ens.deactivate(i)
        if self.on_result is not None:
            self.on_result(self.live[i], result)

    def end(self, i: int, exc: BaseException) -> None:
        self.runs[i].abort()
        self.settle(i, exc)

    def finish(self, done: list) -> None:
        """Finish the scenes that ended this round: all files handed over first (deferred ones are then
        written in parallel by the writer processes), then each waited for and settled."""
        ens, runs = self.ens, self.runs
        begun = []
        for i in done:
            try:
                begun.append((i, runs[i].finish_begin(
                    ens.name, ens.device, ens.scene_builds(i),
                    {"ensemble_size": self.size, "ensemble_index": i, **ens.scene_info(i)},
                    shared_timings=self.shared)))
            except Exception as exc:
                self.end(i, exc)
        if not begun:
            return
        ens.deactivate_many([i for i, _ in begun])
        for i, b in begun:
            try:
                summary = runs[i].finish_end(b)
            except Exception as exc:
                runs[i].abort()
                self.settle(i, exc, deactivated=True)
                continue
            self.settle(i, summary, deactivated=True)


#: wall seconds of time loop one advance call of a lone scene may run through records (``observes_in_loop``): the
#: cancel checks and checkpoints wait for the call's end
RECORDS_CALL_S = 0.25
#: an ensemble of at least this many scenes on the GPU writes its files at the end in writer processes
DEFER_MIN_SCENES = 8
#: ... if every scene's file (snapshot frames kept in memory until then) is at most this large
DEFER_MAX_BYTES = 64 << 20


def _file_thread(ens) -> bool:
    """Whether a scene's file work (frames, blocks of records, the close) goes to the I/O thread
    (engine/output/h5md.py), overlapping the time loop: on the GPU, whose host thread mostly waits for the device. A CPU
    time loop holds the core and the GIL; there the thread's work only waited for the GIL at every return to Python, and
    the hand-overs cost more than the writes: a 64-sphere job took 66-83 ms writing in place against 94-109 ms through
    the thread (2-core VM, 2026-11-28), and a CPU scene's frames are written in milliseconds beside its loop."""
    return ens.name == "cuda"


def _defer_files(ens, runs: list) -> bool:
    """Whether the scenes keep their files in memory and have them written in parallel at the end
    (engine/output/h5md_pool.py): many small scenes on the GPU, which all finish in the same round. On the CPU the
    cores integrate, and one large scene gains nothing."""
    if ens.name != "cuda" or len(runs) < DEFER_MIN_SCENES:
        return False
    for r in runs:
        frames = len(r.snaps) * r.n * 13 * np.dtype(output_dtype(r.spec.precision)).itemsize
        if r.resume is not None or frames > DEFER_MAX_BYTES:
            return False
    return True


def _build(scenes, live, results, build, build_one):
    """The ensemble over the live scenes; scenes that cannot start get their error (see :func:`drive`)."""
    try:
        return build([scenes[k].system for k in live], [scenes[k].initial_contact for k in live]), live
    except Exception as exc:
        if len(live) == 1 or build_one is None:
            for k in live:
                results[k] = exc
            return None, []
        first = exc
    ok = []
    for k in live:
        try:
            build_one(scenes[k].system, scenes[k].initial_contact)
            ok.append(k)
        except Exception as exc:
            results[k] = exc
    if not ok:
        return None, []
    if len(ok) == len(live):  # no single scene is at fault: the ensemble as a whole cannot be built
        for k in live:
            results[k] = first
        return None, []
    return _build(scenes, ok, results, build, build_one)


def warm_process(spec=None) -> None:
    """Pay this process's one-off start-up ahead of its first job (the worker's standby process, jobs/runner.py):
    on a GPU the driver, the context and the kernels of ``spec``'s specialisation (default: the default spec;
    engine/driver/startup.py), and the host's compiled start functions where a job of ``spec`` calls them itself
    (engine.setup.scene.load_parallel_start, each drawn for a few particles, where calls_compiled_start says so:
    a large start drawn on the host; a random spheroid start, whose cell rounds a small one runs on one thread). A
    job whose start NumPy or the device draws (engine.setup.start_kind.device_start) calls none of them, and nothing
    is loaded for other specs' starts: on an empty cache their compile held numba's compiler lock while the claim
    handed to this process waited (a GPU pack of 256 default-size jobs 23 s; the worker's warm-up process loads them
    beside the claims instead, jobs/warm.py). Later jobs' results are unchanged: nothing of this is kept but loaded
    code."""
    from engine.setup.scene import calls_compiled_start, load_parallel_start
    from engine.setup.start_kind import device_start

    spec = spec if spec is not None else SimulationSpec()
    p = derive(spec)
    started = begin_gpu_startup(spec, spec.backend, run_contacts(spec, p), p)
    on_device = started is not None and device_start(spec)
    if not on_device and calls_compiled_start(spec):
        load_parallel_start(spec, p)
    if started is not None:
        started.wait()


def run(spec, output, *, progress: Optional[Callable[[Progress], None]] = None,
        should_cancel: Optional[Callable[[], bool]] = None, checkpoint_dir=None,
        checkpoint_interval: float = 60.0, backend: Optional[str] = None) -> RunSummary:
    """Run a spec to completion and write its H5MD result to ``output`` (atomically).

    ``backend`` overrides the spec's own; a null ``verlet_skin`` is the resolved backend's default
    (engine.setup.params.default_verlet_skin), recorded with the skin in m in the file's ``/parameters``.

    Raises SpecError / pydantic ValidationError for specs that cannot run, InstabilityError when the
    run blows up (the message names the step, the particle and the likely cause; no result file is
    left behind), Cancelled when ``should_cancel()`` returns True.
    """
    scene = SceneRun(spec, output, progress=progress, should_cancel=should_cancel, checkpoint_dir=checkpoint_dir,
                     checkpoint_interval=checkpoint_interval, backend=backend)
    (result,) = drive([scene], lambda systems, contacts: make_ensemble(
        scene.backend, systems, contacts, reads_state=scene.reads_state, orientations=scene.spec.orientations))
    if isinstance(result, BaseException):
        raise result
    return result
