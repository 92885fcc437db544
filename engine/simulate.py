"""The driver: validate, derive, place, thermalise, cool, record, write; progress and cancel hooks.

Public API (used by the CLI and the job worker)::

    run(spec, output, *, progress=None, should_cancel=None, checkpoint_dir=None,
        checkpoint_interval=60.0, backend=None) -> RunSummary

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.backends.base import ContactParams, make_backend
from engine.errors import Cancelled, InstabilityError, SpecError
from engine.h5md import H5MDWriter, partial_path
from engine.params import Q_SPHERE, Derived, derive
from engine.spec import SimulationSpec, load_spec

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
    extra: dict = field(default_factory=dict)


def contact_params(spec: SimulationSpec, p: Derived, *, thermalization: bool) -> ContactParams:
    """Contact constants for the cooling run or the dissipation-free thermalisation."""
    smooth = spec.smooth
    if thermalization:
        k_t = None if smooth else p.k_n * Q_SPHERE / (1.0 + Q_SPHERE)  # paper 001 Eq. 4 at e_t = 1
        return ContactParams(k_n=p.k_n, gamma_n_coef=0.0, k_t=k_t, friction=None, dt=p.dt, skin=p.skin,
                             precision=spec.precision, orientation=spec.snapshots > 0,
                             overlap_limit=spec.overlap_limit)
    return ContactParams(k_n=p.k_n, gamma_n_coef=p.gamma_n_coef, k_t=None if smooth else p.k_t,
                         friction=spec.friction, dt=p.dt, skin=p.skin, precision=spec.precision,
                         orientation=spec.snapshots > 0, overlap_limit=spec.overlap_limit)


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
        st = backend.state()
        pairs, springs = backend.contacts()
        tmp = self.dir / "state.tmp.npz"
        np.savez(tmp, phase=phase, step_done=step_done, counts=json.dumps(writer.frame_counts()),
                 pairs=pairs, springs=springs, **st, **extra)
        os.replace(tmp_h5, self.dir / "partial.h5")
        os.replace(tmp, self.dir / "state.npz")
        self.last = time.monotonic()

    def clear(self) -> None:
        if self.dir is not None and self.dir.exists():
            shutil.rmtree(self.dir, ignore_errors=True)


def run(spec, output, *, progress: Optional[Callable[[Progress], None]] = None,
        should_cancel: Optional[Callable[[], bool]] = None, checkpoint_dir=None,
        checkpoint_interval: float = 60.0, backend: Optional[str] = None) -> RunSummary:
    """Run a spec to completion and write its H5MD result to ``output`` (atomically).

    Raises SpecError / pydantic ValidationError for specs that cannot run, InstabilityError when the
    run blows up (the message names the step, the particle and the likely cause; no result file is
    left behind), Cancelled when ``should_cancel()`` returns True.
    """
    from engine import __version__
    from engine.scene import initial_ellipsoids, initial_spheres

    spec = load_spec(spec)
    ellipsoid = spec.shape == "ellipsoid"
    if ellipsoid and not spec.smooth:
        raise SpecError(f"shape = 'ellipsoid' runs frictionless contacts only (paper 003): e_t = {spec.e_t:g} "
                        f"and friction = {spec.friction} must be e_t = -1 (or friction = 0)")
    p = derive(spec)
    spec_json = spec.to_json()
    output = Path(output)
    ck = _Checkpointer(checkpoint_dir, checkpoint_interval)
    resume = ck.load(spec_json)

    system = initial_ellipsoids(spec, p) if ellipsoid else initial_spheres(spec, p)
    phase, step_done = "thermalization", 0
    # a cooling checkpoint was written after its own record at step_done, which the file already holds
    resumed_in_cooling = resume is not None and str(resume["phase"]) == "cooling"
    if resume is not None:
        phase, step_done = str(resume["phase"]), int(resume["step_done"])
        system = dataclasses.replace(
            system, position=resume["position"], velocity=resume["velocity"],
            angular_velocity=resume["angular_velocity"], orientation=resume["orientation"],
            contact_pairs=resume["pairs"], contact_springs=resume["springs"])
        shutil.copyfile(ck.dir / "partial.h5", partial_path(output))
    if p.n_thermalization_steps == 0 and phase == "thermalization":
        phase = "cooling"

    name = backend or spec.backend
    cool = contact_params(spec, p, thermalization=False)
    therm = contact_params(spec, p, thermalization=True)
    be = make_backend(name, system, therm if phase == "thermalization" else cool)
    for c in ((therm, cool) if phase == "thermalization" else (cool,)):
        be.set_contact(c)
        be.warmup()
    be.set_contact(therm if phase == "thermalization" else cool)

    dtype = np.float64 if spec.precision == "float64" else np.float32
    derived = {k: v for k, v in p.as_dict().items()}
    derived.update(engine_version=__version__, q=Q_SPHERE, e_n=spec.e_n, e_t=spec.e_t)
    if resume is not None:
        writer = H5MDWriter(output, n=spec.n_particles, box_length=spec.box_length, spec_json=spec_json,
                            derived=derived, dtype=dtype, resume=True)
        writer.truncate(json.loads(str(resume["counts"])))
    else:
        writer = H5MDWriter(output, n=spec.n_particles, box_length=spec.box_length, spec_json=spec_json,
                            derived=derived, radius=None if ellipsoid else system.radius,
                            semi_axes=system.semi_axes if ellipsoid else None, mass=system.mass,
                            creator_version=__version__, dtype=dtype)

    n = spec.n_particles
    total_steps = p.n_thermalization_steps + p.n_steps
    events, snaps = schedule(p, spec.snapshots)
    wall = 0.0  # wall seconds of this attempt's time loop
    steps_run = 0
    prev_energy = float(resume["prev_energy"]) if resume is not None else math.inf
    dissipative = spec.e_n < 1.0 or (not spec.smooth and spec.e_t < 1.0) or spec.friction is not None
    resumed_from = (step_done if phase == "cooling" else step_done - p.n_thermalization_steps) \
        if resume is not None else None

    def report(ph: str, done_total: int, t_sim: float, step: int):
        if progress is None:
            return
        frac = done_total / total_steps if total_steps else 1.0
        cund = n * steps_run / wall if wall > 0 else 0.0
        eta = (total_steps - done_total) * n / cund if cund > 0 else math.inf
        progress(Progress(phase=ph, fraction=min(1.0, frac), step=step, time=t_sim, eta_s=eta,
                          cundall=cund, wall_s=wall))

    def check_cancel():
        if should_cancel is not None and should_cancel():
            raise Cancelled("run cancelled on request")

    def advance(k: int):
        nonlocal wall, steps_run
        t0 = time.perf_counter()
        be.advance(k)
        wall += time.perf_counter() - t0
        steps_run += k

    try:
        # ---- thermalisation: dissipation off, nothing recorded -------------------------------------
        if phase == "thermalization":
            chunk = max(1, p.output_every)
            while step_done < p.n_thermalization_steps:
                check_cancel()
                k = min(chunk, p.n_thermalization_steps - step_done)
                advance(k)
                step_done += k
                report("thermalization", step_done, (step_done - p.n_thermalization_steps) * p.dt,
                       step_done - p.n_thermalization_steps)
                if ck.due():
                    ck.save(writer, be, phase=phase, step_done=step_done,
                            extra={"spec": spec_json, "prev_energy": prev_energy})
            phase, step_done = "cooling", 0
            be.set_contact(cool)

        # ---- cooling run ---------------------------------------------------------------------------
        for ev in events:
            ev = int(ev)
            if ev < step_done or (ev == step_done and resumed_in_cooling):
                continue
            check_cancel()
            if ev > step_done:
                advance(ev - step_done)
                step_done = ev
            t_sim = step_done * p.dt
            obs = be.observe()
            if step_done % p.output_every == 0 or step_done == p.n_steps:
                writer.observables(step_done, t_sim, record(obs, n))
                energy = obs["kinetic_energy_translational"] + obs["kinetic_energy_rotational"] + \
                    obs["elastic_energy"]
                if dissipative and energy > prev_energy * (1.0 + ENERGY_RISE_TOLERANCE):
                    raise InstabilityError(
                        f"total energy rose by {100 * (energy / prev_energy - 1):.3g} % by step {step_done} "
                        f"(t = {t_sim:.4g} s) in a dissipative run: likely cause: a time step too large "
                        f"(dt = {p.dt:.3g} s, contact time {p.contact_time:.3g} s) or overlaps too deep",
                        step=step_done)
                prev_energy = min(prev_energy, energy)
            if step_done in snaps:
                writer.snapshot(step_done, t_sim, be.state())
            report("cooling", p.n_thermalization_steps + step_done, t_sim, step_done)
            if ck.due() and step_done < p.n_steps:
                ck.save(writer, be, phase="cooling", step_done=step_done,
                        extra={"spec": spec_json, "prev_energy": prev_energy})
    except BaseException:
        writer.abort()
        raise

    cundall = n * steps_run / wall if wall > 0 else 0.0
    run_info = {"backend": be.name, "device": be.device, "wall_time": wall, "cundall_number": cundall,
                "steps_total": total_steps, "neighbour_builds": be.builds,
                "resumed_from_step": -1 if resumed_from is None else resumed_from}
    path = writer.finish(run_info)
    ck.clear()
    return RunSummary(output=path, backend=be.name, device=be.device, n_particles=n, steps=steps_run,
                      wall_s=wall, cundall=cundall, resumed_from_step=resumed_from)
