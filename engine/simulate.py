"""The driver: validate, derive, place, thermalise, cool, record, write; progress and cancel hooks.

Public API (used by the CLI and the job worker)::

    run(spec, output, *, progress=None, should_cancel=None, checkpoint_dir=None,
        checkpoint_interval=60.0, backend=None) -> RunSummary

The per-scene protocol below lives in one object, :class:`SceneRun`, and one loop, :func:`drive`,
advances any number of them on an ensemble (engine/backends/ensemble.py): :func:`run` is a scene of
one on a :class:`~engine.backends.ensemble.SerialEnsemble`, ``engine.ensemble.run_ensemble`` packs
many scenes into one ensemble.

Protocol (paper 001): a homogeneous non-overlapping start with Gaussian translational and angular
velocities at equal temperatures, ``thermalization`` collisions per particle with dissipation off
(e_n = 1; rough spheres keep a perfectly rough elastic spring, e_t = 1, smooth ones stay smooth), then
the cooling run from t = 0 to t_end with the spec's contact law. Observables are recorded every
``output_interval``; ``snapshots`` full frames are spread evenly over [0, t_end].

Checkpoints (for the job queue): every ``checkpoint_interval`` wall seconds the driver writes
``checkpoint_dir/state.npz`` (state, contact springs, clock) and a copy of the partial HDF5 file,
both through a temporary name and a rename. ``run`` with a ``checkpoint_dir`` that holds a checkpoint
of the same spec resumes from it; the finished file is the same as an uninterrupted run's up to
rounding (the neighbour list is rebuilt at the resume point).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from collections import deque
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.backends.base import ContactParams
from engine.backends.ensemble import SerialEnsemble, check_backend_name, ensemble_scene_builds, resolve_backend
from engine.errors import Cancelled, InstabilityError, SpecError
from engine.h5md import H5MDWriter, partial_path, replace_file, writer_process_ready
from engine.params import Q_SPHERE, Derived, derive
from engine.physics.sonine import sonine_observables
from engine.precision import output_dtype
from engine.spec import SimulationSpec, default_verlet_skin, load_spec
from engine.start_kind import device_start
from engine.startup import begin as begin_gpu_startup

#: In a dissipative run the total mechanical energy may not rise between records by more than this
#: fraction (integration error is O(dt^2) ~ 1e-4 at dt = t_c/50; a real rise means instability).
ENERGY_RISE_TOLERANCE = 1e-2


@dataclass
class Progress:
    """What the driver reports every output interval."""

    phase: str            # "thermalization" | "cooling"
    fraction: float       # 0..1 of the whole run (thermalisation + cooling), by steps
    step: int             # cooling-run step (negative during thermalisation)
    time: float           # simulated time in s (t = 0 at the start of the cooling run)
    eta_s: float          # estimated wall seconds left
    cundall: float        # particle-steps per wall second so far (time loop only)
    wall_s: float         # wall seconds since the time loop started
    resumed_from_step: Optional[int] = None   # cooling-run step this attempt resumed from (None: a fresh start)


@dataclass
class RunSummary:
    output: Path
    backend: str
    device: str
    n_particles: int
    steps: int                    # cooling + thermalisation steps advanced
    wall_s: float                 # wall seconds of the time loop (after compilation and placement)
    cundall: float                # N * steps / wall_s
    resumed_from_step: Optional[int] = None
    extra: dict = field(default_factory=dict)   # run attributes; "timings": wall s per phase (TIMINGS)


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
        k_t = None if smooth else p.k_n * Q_SPHERE / (1.0 + Q_SPHERE)  # paper 001 Eq. 4 at e_t = 1
        return ContactParams(k_n=p.k_n, gamma_n_coef=0.0, k_t=k_t, friction=None, dt=p.dt, skin=p.skin,
                             precision=spec.precision, orientation=spec.snapshots > 0,
                             overlap_limit=spec.overlap_limit, list_mode=spec.list_mode)
    return ContactParams(k_n=p.k_n, gamma_n_coef=p.gamma_n_coef, k_t=None if smooth else p.k_t,
                         friction=spec.friction, dt=p.dt, skin=p.skin, precision=spec.precision,
                         orientation=spec.snapshots > 0, overlap_limit=spec.overlap_limit,
                         list_mode=spec.list_mode)


def run_contacts(spec: SimulationSpec, p: Derived) -> tuple:
    """The contact constants a fresh run uses, in order: the thermalisation's (when it has one), the cooling's."""
    cool = contact_params(spec, p, thermalization=False)
    return (contact_params(spec, p, thermalization=True), cool) if p.n_thermalization_steps > 0 else (cool,)


def schedule(p: Derived, snapshots: int) -> tuple[np.ndarray, set]:
    """Event steps of the cooling run (records and snapshots) and the set of snapshot steps."""
    records = set(range(0, p.n_steps + 1, p.output_every)) | {p.n_steps}
    if snapshots <= 0:
        snaps = set()
    elif snapshots == 1:
        snaps = {p.n_steps}
    else:
        snaps = set(np.round(np.linspace(0, p.n_steps, snapshots)).astype(int).tolist())
    return np.array(sorted(records | snaps)), snaps


def record(obs: dict, n: int) -> dict:
    """Observables written every record (temperatures per degree of freedom, J).

    Ellipsoids: T_rot counts the two rotational degrees of freedom that exchange energy (about the
    axes perpendicular to the symmetry axis), T_rot = E_rot,perp / N (paper 003 Eq. 25b as corrected in
    PHYSICS-NOTES §3.3); kinetic_energy_rotational stays the total.

    Velocity-distribution shape (issue 18), dimensionless, where the backend reports the energy moments:
    ``sonine_a2_translational`` (a2 of the translational energies, d = 3), ``sonine_a2_rotational`` (of the
    rotational energies: spheres d = 3, spheroids the 2 active dof) and ``sonine_a11`` (the cross cumulant
    <e_tr e_rot>/(<e_tr><e_rot>) - 1), all from engine/physics/sonine.py (energy form, lab frame = centre-of-mass
    frame; 0 where the energy of those dof is zero). O(1) host work per record: the moments are per-scene sums
    of the observe kernel.
    """
    if "kinetic_energy_rotational_active" in obs:
        t_rot = 2.0 * obs["kinetic_energy_rotational_active"] / (obs.get("rotational_dof", 2) * n)
    else:
        t_rot = 2.0 * obs["kinetic_energy_rotational"] / (3.0 * n)
    return {
        "kinetic_energy_translational": obs["kinetic_energy_translational"],
        "kinetic_energy_rotational": obs["kinetic_energy_rotational"],
        "temperature_translational": 2.0 * obs["kinetic_energy_translational"] / (3.0 * n),
        "temperature_rotational": t_rot,
        "contacts": np.int64(obs["contacts"]),
        "elastic_energy": obs["elastic_energy"],
        "max_overlap": obs["max_overlap"],
        **sonine_observables(obs, n),
        # contacts begun since the scene started, thermalisation included (spheres; issue 18's collision counter)
        **({"collisions": np.int64(obs["collisions"])} if "collisions" in obs else {}),
    }


class _Checkpointer:
    """Writes and reads ``state.npz`` + ``partial.h5`` in a checkpoint directory (atomically)."""

    def __init__(self, directory, interval: float):
        self.dir = Path(directory) if directory is not None else None
        self.interval = interval
        self.last = time.monotonic()

    def load(self, spec_json: str):
        if self.dir is None or not (self.dir / "state.npz").exists():
            return None
        data = dict(np.load(self.dir / "state.npz", allow_pickle=False))
        if str(data["spec"]) != spec_json or not (self.dir / "partial.h5").exists():
            return None
        return data

    def due(self) -> bool:
        return self.dir is not None and time.monotonic() - self.last >= self.interval

    def save(self, writer: H5MDWriter, backend, *, phase: str, step_done: int, extra: dict) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        writer.flush()
        tmp_h5 = self.dir / "partial.h5.tmp"
        shutil.copyfile(writer.tmp, tmp_h5)
        st = backend.state(reuse=True)  # consumed by np.savez below
        pairs, springs = backend.contacts()
        tmp = self.dir / "state.tmp.npz"
        np.savez(tmp, phase=phase, step_done=step_done, counts=json.dumps(writer.frame_counts()),
                 pairs=pairs, springs=springs, **st, **extra)
        replace_file(tmp_h5, self.dir / "partial.h5")
        replace_file(tmp, self.dir / "state.npz")
        self.last = time.monotonic()

    def clear(self) -> None:
        if self.dir is not None and self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)


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
                 checkpoint_interval: float = 60.0, backend: Optional[str] = None):
        from engine.shapes import host, traits

        t_setup = time.perf_counter()
        spec = load_spec(spec)
        self.spec = spec
        self.shape = host(spec.shape)
        refused = traits(spec.shape).spec_error(spec)
        if refused:
            raise SpecError(refused)
        self.output = Path(output)
        self.progress, self.should_cancel = progress, should_cancel
        self.spec_json = spec.to_json()
        #: added to the RunSummary's extra only (not to the file): engine.ensemble's set-up wall time
        self.summary_extra: dict = {}
        self.ck = _Checkpointer(checkpoint_dir, checkpoint_interval)
        self.resume = resume = self.ck.load(self.spec_json)
        # the start does not depend on the Verlet skin, so the particles are placed before the backend is
        # resolved: meanwhile the GPU starts up on its own thread (engine/startup.py)
        check_backend_name(backend or spec.backend)
        p0 = derive(spec)
        self.startup = begin_gpu_startup(spec, backend or spec.backend, run_contacts(spec, p0), p0)
        # a GPU job's large sphere start is drawn by its backend on the device (engine/backends/cuda_start.py)
        if self.startup is not None and resume is None and device_start(spec):
            system = self.shape.initial_system(spec, p0, on_device=True)
        else:
            system = self.shape.initial_system(spec, p0)
        # the backend ('cpu' or 'cuda') this scene runs on: `backend` overrides the spec's, 'auto' resolved here
        self.backend = resolve_backend(backend or spec.backend, spec.shape)
        if self.backend != "cuda":
            from engine.scene import drawn_on_host

            system = drawn_on_host(system)
        # a null verlet_skin is the resolved backend's default at this volume fraction (species: the total
        # phi; the stored spec keeps null; /parameters say verlet_skin and skin); an explicit value always wins
        self.verlet_skin = spec.verlet_skin if spec.verlet_skin is not None else \
            default_verlet_skin(self.backend, spec.shape, spec.volume_fraction)
        self.p = p = derive(spec.model_copy(update={"verlet_skin": self.verlet_skin}))
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
        self.prev_energy = float(resume["prev_energy"]) if resume is not None else math.inf
        # collisions counted before a resume (the new backend's counter starts at 0)
        self.coll_base = int(resume["collisions"]) if resume is not None and "collisions" in resume else 0
        self.dissipative = spec.e_n < 1.0 or (not spec.smooth and spec.e_t < 1.0) or spec.friction is not None
        self.writer: Optional[H5MDWriter] = None
        self.done = False
        self._chunk = max(1, p.output_every)
        self.defer_file = False           # set by drive(): the file is written at the end, in a writer process
        self.timings = dict.fromkeys(TIMINGS, 0.0)
        self.timings["setup"] = time.perf_counter() - t_setup
        if phase == "thermalization":
            self._target = min(step_done + self._chunk, p.n_thermalization_steps)
        else:
            self._enter_cooling(skip_current=self.resumed_in_cooling)

    # ---- what the driver asks -------------------------------------------------------------------------

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
        from engine.scene import start_generator
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
            # file work on the I/O thread, overlapping the time loop (engine/h5md.py)
            self.writer = H5MDWriter(self.output, mass=system.mass, **self.shape.writer_fields(system, p),
                                     creator_version=__version__, background=True,
                                     deferred=self.defer_file, **common)
        self.timings["open"] += time.perf_counter() - t0

    def at_stop(self, view, defer: Optional[Callable[[Callable[[], None]], None]] = None) -> None:
        """Handle the stop the scene has reached (records, energy check, snapshot, progress, checkpoint).

        ``defer(fn)``, when given, takes the work of a stop that only records (no snapshot, checkpoint or end):
        the driver runs ``fn`` while the GPU does the next steps, and in any case before this scene's next stop
        (engine.simulate.drive, _Deferred). The observables are read now; the record, energy check and progress
        report are the same, only later."""
        p, writer = self.p, self.writer
        if self.phase == "thermalization":
            # dissipation off, nothing recorded
            self._report("thermalization", self.step_done, (self.step_done - p.n_thermalization_steps) * p.dt,
                         self.step_done - p.n_thermalization_steps)
            if self.ck.due():
                t0 = time.perf_counter()
                self.ck.save(writer, view, phase="thermalization", step_done=self.step_done,
                             extra=self._ck_extra(self._counted(view.observe())))
                self.timings["checkpoints"] += time.perf_counter() - t0
            if self.step_done >= p.n_thermalization_steps:
                self.phase, self.step_done = "cooling", 0
                view.set_contact(self.cool)
                self._enter_cooling(skip_current=False)
            else:
                self._target = min(self.step_done + self._chunk, p.n_thermalization_steps)
            return

        step_done = self.step_done
        t_sim = step_done * p.dt
        tm = self.timings
        ck_due = self.ck.due() and step_done < p.n_steps
        if defer is not None and step_done not in self.snaps and step_done < p.n_steps and not ck_due:
            obs_later = view.observe_later()

            def later() -> None:
                t0 = time.perf_counter()
                self._record(step_done, t_sim, self._counted(obs_later()))
                tm["records"] += time.perf_counter() - t0
                self._report("cooling", p.n_thermalization_steps + step_done, t_sim, step_done)

            defer(later)
            self._next_event()
            return
        t0 = time.perf_counter()
        obs = self._counted(view.observe())
        self._record(step_done, t_sim, obs)
        t1 = time.perf_counter()
        tm["records"] += t1 - t0
        if step_done in self.snaps:
            # two buffer slots (host memory reused on CUDA), shared by all scenes of the ensemble (view.slots):
            # the I/O thread writes one frame while the run goes on; a slot is reused, by any scene, only after
            # its previous frame is in the file (waited for, not raised: a failed write is its writer's error)
            slot = view.slots.take()
            view.slots.busy[slot] = writer.snapshot(step_done, t_sim, view.state(reuse=2 + slot))
            tm["snapshots"] += time.perf_counter() - t1
        self._report("cooling", p.n_thermalization_steps + step_done, t_sim, step_done)
        if ck_due:
            t0 = time.perf_counter()
            self.ck.save(writer, view, phase="cooling", step_done=step_done, extra=self._ck_extra(obs))
            tm["checkpoints"] += time.perf_counter() - t0
        self._next_event()

    def _record(self, step_done: int, t_sim: float, obs: dict) -> None:
        """Write the record of a record step and check that a dissipative run's energy did not rise."""
        p = self.p
        if step_done % p.output_every == 0 or step_done == p.n_steps:
            self.writer.observables(step_done, t_sim, record(obs, self.n))
            energy = obs["kinetic_energy_translational"] + obs["kinetic_energy_rotational"] + obs["elastic_energy"]
            if self.dissipative and energy > self.prev_energy * (1.0 + ENERGY_RISE_TOLERANCE):
                raise InstabilityError(
                    f"total energy rose by {100 * (energy / self.prev_energy - 1):.3g} % by step {step_done} "
                    f"(t = {t_sim:.4g} s) in a dissipative run: likely cause: a time step too large "
                    f"(dt = {p.dt:.3g} s, contact time {p.contact_time:.3g} s) or overlaps too deep",
                    step=step_done)
            self.prev_energy = min(self.prev_energy, energy)

    def _counted(self, obs: dict) -> dict:
        """The observables with the collisions counted before a resume added (a copy: ``obs`` may be shared)."""
        if "collisions" not in obs or not self.coll_base:
            return obs
        return {**obs, "collisions": obs["collisions"] + self.coll_base}

    def _ck_extra(self, obs: dict) -> dict:
        """What a checkpoint keeps beside the state: the spec, the energy check's reference and the collision
        count of :meth:`_counted` observables (the resumed run's series continues from it)."""
        extra = {"spec": self.spec_json, "prev_energy": self.prev_energy}
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
        tm["close"] += time.perf_counter() - t0
        return RunSummary(output=path, backend=backend, device=device, n_particles=self.n, steps=self.steps_run,
                          wall_s=self.wall, cundall=cundall, resumed_from_step=self.resumed_from,
                          extra={**(info or {}), "timings": dict(tm), **self._startup_info(),
                                 **self.summary_extra})

    def _startup_info(self) -> dict:
        """The GPU start-up thread's wall seconds and error (engine/startup.py), when this scene had one."""
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
        if self.progress is None:
            return
        total = self.total_steps
        frac = done_total / total if total else 1.0
        cund = self.n * self.steps_run / self.wall if self.wall > 0 else 0.0
        eta = (total - done_total) * self.n / cund if cund > 0 else math.inf
        self.progress(Progress(phase=phase, fraction=min(1.0, frac), step=step, time=t_sim, eta_s=eta,
                               cundall=cund, wall_s=self.wall, resumed_from_step=self.resumed_from))


class _FrameSlots:
    """The two snapshot buffer slots of an ensemble (its reused host buffers are shared by every scene) and the
    write still using each (a future, or None)."""

    def __init__(self):
        self.busy = [None, None]
        self.last = 1

    def take(self) -> int:
        """A slot for the next frame, once its earlier frame is written: the first free one (frames far apart
        all use one slot, so one set of buffers is allocated), else the one used less recently, waited for."""
        free = [k for k in (0, 1) if self.busy[k] is None or self.busy[k].done()]
        slot = free[0] if free else 1 - self.last
        if self.busy[slot] is not None:
            futures_wait([self.busy[slot]])
        self.last = slot
        return slot


class _SceneView:
    """Scene ``i`` of an ensemble, seen as a single backend by :meth:`SceneRun.at_stop`.

    ``observe()`` reads the ensemble's observables once per driver round (shared by every scene that
    stops in that round), or only this scene's where the ensemble offers ``observe_scene``.
    """

    def __init__(self, ens, i: int, cache: dict, slots: "_FrameSlots"):
        self.ens, self.i, self.cache, self.slots = ens, i, cache, slots
        # what the ensemble offers, looked up once (a view serves every stop of its scene)
        self._one = getattr(ens, "observe_scene", None)
        self._one_later = getattr(ens, "observe_scene_later", None)
        self._later = getattr(ens, "observe_later", None)

    def observe(self) -> dict:
        one = self._one
        if one is not None:
            return one(self.i)
        if "all" not in self.cache:
            self.cache["all"] = self.ens.observe()
        return self.cache["all"][self.i]

    def observe_later(self) -> Callable[[], dict]:
        """A function giving :meth:`observe`'s dict: the values are queued now (one observation per round, shared
        by the round's scenes) and read and built when it is called, where the ensemble offers
        ``observe_scene_later`` or ``observe_later`` (CUDA); else read now."""
        if self._one_later is not None:
            return self._one_later(self.i)
        later = self._later
        if later is None or self._one is not None:
            obs = self.observe()
            return lambda: obs
        if "later" not in self.cache:
            self.cache["later"] = later()
        f, i = self.cache["later"], self.i
        return lambda: f(i)

    def state(self, reuse=False) -> dict:
        """Scene i's state in id order; ``reuse`` (True or a buffer slot): the arrays may be buffers that the
        next call with the same slot overwrites."""
        if reuse is not False and getattr(self.ens, "reuses_state_buffers", False):
            return self.ens.state(self.i, reuse=reuse)
        return self.ens.state(self.i)

    def contacts(self):
        return self.ens.contacts(self.i)

    def set_contact(self, contact: ContactParams) -> None:
        self.ens.set_contact(self.i, contact)
        self.cache.pop("all", None)
        self.cache.pop("later", None)


def _set_contacts(ens, contacts: dict) -> None:
    """Set the contacts {scene: contact} of the ensemble, at once where it offers ``set_contacts``."""
    many = getattr(ens, "set_contacts", None)
    if many is not None:
        many(contacts)
    else:
        for i, c in contacts.items():
            ens.set_contact(i, c)


#: environment switch: "0" = a stop's record work is done at once, not while the GPU does the next steps
OVERLAP_RECORDS_ENV = "DEMQ_OVERLAP_RECORDS"


class _Deferred:
    """The record work of the last round's stops (issue 14 item 4: the GPU stays busy across records).

    An ensemble with an ``idle`` hook (the packed CUDA ensemble) calls :meth:`run_one` while it waits for the
    GPU in its next advance; what is left runs in :meth:`drain`, before the next round's stops. A scene's units
    run in order, and all of them before its next stop, snapshot, checkpoint or end. A unit's error (e.g. the
    energy check's InstabilityError) is kept for the driver, which ends that scene; its later units are dropped.
    Off (``on`` False) for ensembles without the hook and with DEMQ_OVERLAP_RECORDS=0.
    """

    def __init__(self, ens):
        self.on = hasattr(ens, "idle") and os.environ.get(OVERLAP_RECORDS_ENV) != "0"
        self.units: deque = deque()
        self.errors: list = []
        if self.on:
            ens.idle = self.run_one

    def for_scene(self, i: int) -> Optional[Callable]:
        return (lambda fn: self.units.append((i, fn))) if self.on else None

    def run_one(self) -> bool:
        if not self.units:
            return False
        i, fn = self.units.popleft()
        try:
            fn()
        except Exception as exc:  # this scene's error: the driver ends it
            self.errors.append((i, exc))
            self.drop(i)
        return True

    def drain(self) -> list:
        """Run every unit left; return [(scene, error)] of the units that failed since the last drain."""
        while self.run_one():
            pass
        errors, self.errors = self.errors, []
        return errors

    def drop(self, i: int) -> None:
        if any(u[0] == i for u in self.units):
            self.units = deque(u for u in self.units if u[0] != i)


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
    own distances to their next stops when the ensemble offers ``advance_each`` (and ``lockstep`` is not
    True), else all by the distance to the nearest stop of any scene (``advance``); then every scene at a
    stop handles it (a stop that only records, on an ensemble with an ``idle`` hook, hands its record work to
    the next advance's waits for the GPU: :class:`_Deferred`). A scene that blows up (InstabilityError from the
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
    # the GPU start-up threads (engine/startup.py) end before the job's own backend uses the GPU
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
    size = len(runs)
    t0 = time.perf_counter()
    try:
        rounds = max(len(r.warm_contacts) for r in runs)
        for r_ in range(rounds):
            _set_contacts(ens, {i: r.warm_contacts[min(r_, len(r.warm_contacts) - 1)] for i, r in enumerate(runs)})
            ens.warmup()
        _set_contacts(ens, {i: r.initial_contact for i, r in enumerate(runs)})
        shared["compile"] = time.perf_counter() - t0
    except Exception as exc:  # the ensemble cannot compile: every scene fails with the reason
        for k in live:
            results[k] = exc
            if on_result is not None:
                on_result(k, exc)
        return results

    active: set = set()
    frame_slots = _FrameSlots()
    deferred = _Deferred(ens)
    # per scene, made once (a stop costs host time while the GPU waits for the next round): its view of the
    # ensemble, whose round cache is one dict cleared every round, and its deferral hook
    cache: dict = {}
    views = [_SceneView(ens, i, cache, frame_slots) for i in range(size)]
    defers = [deferred.for_scene(i) for i in range(size)]

    def settle(i: int, result, deactivated: bool = False) -> None:
        results[live[i]] = result
        active.discard(i)
        if not deactivated:
            ens.deactivate(i)
        if on_result is not None:
            on_result(live[i], result)

    def end(i: int, exc: BaseException) -> None:
        deferred.drop(i)
        runs[i].abort()
        settle(i, exc)

    def finish(done: list) -> None:
        """Finish the scenes that ended this round: all files handed over first (deferred ones are then
        written in parallel by the writer processes), then each waited for and settled."""
        info = getattr(ens, "scene_info", None)
        begun = []
        for i in done:
            builds = ensemble_scene_builds(ens, i)
            try:
                begun.append((i, runs[i].finish_begin(
                    ens.name, ens.device, ens.builds if builds is None else builds,
                    {"ensemble_size": size, "ensemble_index": i, **(info(i) if info else {})},
                    shared_timings=shared)))
            except Exception as exc:
                end(i, exc)
        if not begun:
            return
        many = getattr(ens, "deactivate_many", None)
        if many is not None:
            many([i for i, _ in begun])
        for i, b in begun:
            try:
                summary = runs[i].finish_end(b)
            except Exception as exc:
                runs[i].abort()
                settle(i, exc, deactivated=many is not None)
                continue
            settle(i, summary, deactivated=many is not None)

    per_scene = hasattr(ens, "advance_each") and not lockstep
    plan = getattr(ens, "plan", None)
    if plan is not None:  # how long the run goes on (the auto list mode weighs a probe against it)
        plan(max((r.p.n_steps if r.phase == "cooling" else r.total_steps) - r.step_done for r in runs))
    if _defer_files(ens, runs):  # many small GPU scenes: files written at the end, in parallel processes
        from engine import h5md_pool

        h5md_pool.prewarm(min(len(runs), h5md_pool.MAX_PROCESSES), ready=writer_process_ready)
        for r in runs:
            r.defer_file = True
    try:
        for i, r in enumerate(runs):
            try:
                r.open()
            except Exception as exc:
                end(i, exc)
                continue
            active.add(i)
        finish([i for i in sorted(active) if runs[i].done])
        at_start = set(active)
        while active:
            for i in sorted(at_start & active):
                try:
                    runs[i].check_cancel()
                except Exception as exc:  # Cancelled, or a cancel check that failed
                    end(i, exc)
            at_start = set()
            if not active:
                break
            dist = {i: runs[i].steps_to_next() for i in active}
            failed: dict = {}
            try:
                if per_scene:
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
                        for i in active:
                            runs[i].advanced(m, wall)
            except Exception as exc:  # the ensemble itself failed: every active scene ends with it
                for i in sorted(active):
                    end(i, exc)
                break
            # the last round's records first (what the GPU's steps left of them): an error there is earlier
            for i, exc in list(deferred.drain()) + list(failed.items()):
                if i in active:
                    end(i, exc)
            cache.clear()
            done = []
            for i in sorted(i for i in active if runs[i].steps_to_next() == 0):
                try:
                    runs[i].at_stop(views[i], defers[i])
                except Exception as exc:
                    end(i, exc)
                    continue
                if runs[i].done:
                    done.append(i)
                else:
                    at_start.add(i)
            finish(done)
    except BaseException:
        for i in list(active):
            runs[i].abort()
        raise
    return results


#: an ensemble of at least this many scenes on the GPU writes its files at the end in writer processes
DEFER_MIN_SCENES = 8
#: ... if every scene's file (snapshot frames kept in memory until then) is at most this large
DEFER_MAX_BYTES = 64 << 20


def _defer_files(ens, runs: list) -> bool:
    """Whether the scenes keep their files in memory and have them written in parallel at the end
    (engine/h5md_pool.py): many small scenes on the GPU, which all finish in the same round. On the CPU the
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
    numba's CPU target with the functions of a large start of ``spec``'s shape and contact law and of a large
    sphere start (each drawn for a few particles: engine.scene.load_parallel_start), and on a GPU the driver, the
    context and the kernels of ``spec``'s specialisation (default: the default spec; engine/startup.py). Later
    jobs' results are unchanged: nothing of this is kept but loaded code."""
    from engine.scene import load_parallel_start

    spec = spec if spec is not None else SimulationSpec()
    p = derive(spec)
    started = begin_gpu_startup(spec, spec.backend, run_contacts(spec, p), p)
    if not load_parallel_start(spec, p) or spec.shape != "sphere":
        sphere = SimulationSpec()
        load_parallel_start(sphere, derive(sphere))
    if started is not None:
        started.wait()


def run(spec, output, *, progress: Optional[Callable[[Progress], None]] = None,
        should_cancel: Optional[Callable[[], bool]] = None, checkpoint_dir=None,
        checkpoint_interval: float = 60.0, backend: Optional[str] = None) -> RunSummary:
    """Run a spec to completion and write its H5MD result to ``output`` (atomically).

    ``backend`` overrides the spec's own; a null ``verlet_skin`` is the resolved backend's default
    (engine.spec.default_verlet_skin), recorded with the skin in m in the file's ``/parameters``.

    Raises SpecError / pydantic ValidationError for specs that cannot run, InstabilityError when the
    run blows up (the message names the step, the particle and the likely cause; no result file is
    left behind), Cancelled when ``should_cancel()`` returns True.
    """
    scene = SceneRun(spec, output, progress=progress, should_cancel=should_cancel, checkpoint_dir=checkpoint_dir,
                     checkpoint_interval=checkpoint_interval, backend=backend)
    (result,) = drive([scene], lambda systems, contacts: SerialEnsemble(scene.backend, systems, contacts))
    if isinstance(result, BaseException):
        raise result
    return result
