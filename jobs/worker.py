"""The worker: claims a job — or a pack of compatible jobs — and runs it in its own simulation process.

A claim (:meth:`Worker._next`) takes the next queued job and, with packing on (DEMQ_ENSEMBLE_MAX_JOBS > 1),
the queued jobs that can share an ensemble with it (same shape, precision and resolved backend; at most
DEMQ_ENSEMBLE_MAX_JOBS jobs and DEMQ_ENSEMBLE_MAX_PARTICLES particles; jobs/packing.py). One attempt
(:meth:`Worker.execute_pack`; :meth:`Worker.execute` for one job)::

    spawn the simulation process (jobs/runner.py; a running worker hands the claim to the standby process it
                    started ahead, DEMQ_WORKER_STANDBY, and starts the next one)
                    --pipe--> per job: progress, then done | error | cancelled
    every heartbeat (or progress, rate-limited): renew every job's lease and write its progress (one
                    transaction), read its cancel_requested
    cancel requested / worker stopping / lease lost -> set that job's cancel flag; its scene stops alone
    a job's final message -> that job ends at once: done (result written atomically by the engine) |
                    failed (readable reason) | cancelled | released back to the queue (worker shutdown;
                    the attempt is not counted); the rest of the pack runs on
    a stop not honoured within the grace period -> SIGKILL if no other job of the process is still
                    running, else the job ends without waiting for its scene
    process exit    -> jobs still without an end: one job fails with the reason; several (a pack that
                    died or failed as a whole) go back to the queue to run alone next time

A crash of the simulation process fails that job only (a pack's jobs are retried alone, where the
culprit fails by itself); the worker goes on with the next claim. If the worker itself dies, the leases
expire and the reaper (run by every worker between claims) puts the jobs back in the queue, where the
engine resumes each from its last checkpoint.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import shutil
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from sqlalchemy.exc import SQLAlchemyError

from jobs.packing import SOLO, Packer
from jobs.runner import child_main, standby_main
from jobs.schema import CANCELLED, DONE, FAILED, FINAL_STATES, QUEUED, RUNNING
from jobs.settings import DEFAULT_ENGINE_RUN, Settings
from jobs.store import Job, JobStore

log = logging.getLogger("demq.worker")

#: Queued rows read per claim to find jobs to pack, per allowed job of a pack.
PEEK_FACTOR = 4

#: Seconds a standby process that gets no claim has to exit before it is killed.
STANDBY_CLOSE_S = 0.5

#: What a standby process warms when the worker has run no claim yet: the default spec (the service's form and
#: `demq submit`'s default job).
DEFAULT_WARM_SPEC = "{}"

#: Progress keys (from engine Progress) -> job-table columns.
_PROGRESS_COLUMNS = {"fraction": "progress", "phase": "phase", "step": "step", "time": "sim_time",
                     "eta_s": "eta_s", "cundall": "cundall"}


def describe_exit(code: Optional[int]) -> str:
    """A readable reason for a simulation process that ended without reporting a result."""
    if code is not None and code < 0:
        name = signal.Signals(-code).name
        hint = " (out of memory? the kernel's OOM killer sends SIGKILL)" if -code == signal.SIGKILL else ""
        return f"simulation process killed by signal {name}{hint}"
    return f"simulation process exited with code {code} without reporting a result"


class Worker:
    """Drains the queue of ``store``; thread-safe :meth:`stop` for signal handlers and servers."""

    def __init__(self, store: JobStore, settings: Settings,
                 on_progress: Optional[Callable[[Job, dict], None]] = None):
        self.store, self.settings, self.on_progress = store, settings, on_progress
        self.owner = settings.worker_id
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._last_reap = 0.0
        self._packer = Packer(settings.ensemble_max_jobs, settings.ensemble_max_particles)
        self._standby: Optional[_SimProcess] = None   # the next claim's process, started up (run_forever)
        self._keep_standby = False

    def stop(self) -> None:
        """Stop claiming; a running job is stopped (checkpointed by the engine) and released."""
        self._stop.set()
        self._wake.set()

    def wake(self) -> None:
        """Look for queued jobs now instead of at the end of the idle wait (the service calls it on submit)."""
        self._wake.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ---- loops ------------------------------------------------------------------------------------
    def run_forever(self, exit_when_idle: bool = False) -> None:
        """Claim and run jobs until :meth:`stop`; with ``exit_when_idle`` (drain mode, for Slurm job
        arrays), also return once the table holds no queued and no running job."""
        log.info("worker %s started on %s", self.owner, _safe_url(self.settings.database_url))
        self._keep_standby = self.settings.standby_enabled
        if self._keep_standby:
            self._standby = self._spawn_standby(None)
        try:
            while not self._stop.is_set():
                jobs = self._next(None)
                if not jobs:
                    if exit_when_idle and self._drained():
                        log.info("worker %s: no queued or running job left; exiting (drain mode)", self.owner)
                        break
                    self._wake.wait(self.settings.poll_s)
                    self._wake.clear()
                else:
                    self.execute_pack(jobs)
        finally:
            self._keep_standby = False
            if self._standby is not None:
                self._standby.close()
                self._standby = None
        log.info("worker %s stopped", self.owner)

    def _drained(self) -> bool:
        """No job queued and none running anywhere (a running job's worker may still die and the
        reaper requeue it, so a draining worker waits for those too)."""
        try:
            counts = self.store.counts()
        except SQLAlchemyError as exc:
            log.error("cannot reach the job table, retrying: %s", exc)
            return False
        return not counts.get(QUEUED) and not counts.get(RUNNING)

    def run_job(self, job_id: str) -> Optional[Job]:
        """Run exactly ``job_id`` here (or wait while another worker runs it); return it when final."""
        while not self._stop.is_set():
            job = self.store.get(job_id)
            if job is None or job.state in FINAL_STATES:
                return job
            claimed = self._next(job_id)
            if claimed:
                self.execute_pack(claimed)
            else:
                if self.on_progress is not None:
                    self.on_progress(job, {"fraction": job.progress, "phase": job.phase or job.state,
                                           "eta_s": job.eta_s})
                self._stop.wait(self.settings.poll_s)
        return self.store.get(job_id)

    def _next(self, job_id: Optional[str]) -> list[Job]:
        """The next claim: one job (``job_id``, or the next queued), plus the compatible queued jobs
        packed with it (jobs/packing.py) when packing is on; [] if none."""
        try:
            if time.monotonic() - self._last_reap >= self.settings.heartbeat_s:
                requeued, failed = self.store.reap_expired()
                self._last_reap = time.monotonic()
                if requeued or failed:
                    log.warning("reaper: requeued %s, failed %s (expired leases)", requeued, failed)
            first = self.store.claim(self.owner, self.settings.lease_s, job_id)
        except SQLAlchemyError as exc:
            log.error("cannot reach the job table, retrying: %s", exc)
            return []
        if first is None:
            return []
        if job_id is not None or not self.settings.packing:
            return [first]
        try:
            more = self._packer.select(first, self.store.peek_queued(PEEK_FACTOR * self.settings.ensemble_max_jobs))
            return [first] + (self.store.claim_ids(self.owner, self.settings.lease_s, [j.id for j in more])
                              if more else [])
        except SQLAlchemyError as exc:  # the first job is ours: it runs alone
            log.error("cannot pack more jobs with %s, running it alone: %s", first.id, exc)
            return [first]

    # ---- one attempt (one job, or a pack of jobs run as one ensemble) ------------------------------
    def execute(self, job: Job) -> str:
        """Run one claimed job to its end; return the state it was left in (or 'lost')."""
        return self.execute_pack([job])[job.id]

    def execute_pack(self, jobs: list[Job]) -> dict[str, str]:
        """Run claimed jobs in one simulation process — alone (one job) or as one ensemble (several);
        return {job id: the state it was left in, 'released', 'requeued' or 'lost'}."""
        s = self.settings
        slots = [_Slot(job, s.result_path(job.id), s.checkpoint_dir(job.id)) for job in jobs]
        for slot in slots:
            slot.output.parent.mkdir(parents=True, exist_ok=True)
            slot.checkpoints.mkdir(parents=True, exist_ok=True)
            log.info("job %s: attempt %d of %d", slot.job.id, slot.job.attempts, slot.job.max_attempts)
        ensemble = len(slots) > 1
        if ensemble:
            log.info("packing %d jobs into one ensemble run: %s", len(slots), " ".join(j.id for j in jobs))

        claim = (s.engine_run_ensemble if ensemble else s.engine_run, [_spec_json(j) for j in jobs],
                 [str(x.output) for x in slots], [str(x.checkpoints) for x in slots], s.checkpoint_interval,
                 ensemble)
        sim = self._hand_to_standby(claim, len(slots), jobs[0].id)
        if sim is None:
            ctx = multiprocessing.get_context("spawn")
            receiver, sender = ctx.Pipe(duplex=False)
            flags = ctx.RawArray("b", len(slots))  # per-job cancel flags, read by the simulation's cancel checks
            proc = ctx.Process(target=child_main, name=f"demq-job-{jobs[0].id}",
                               args=claim[:5] + (sender, flags, os.getpid(), ensemble))
            proc.start()
            sender.close()
            sim = _SimProcess(proc, receiver, flags)
        if self._keep_standby:    # the next claim's process starts up while this one runs
            self._standby = self._spawn_standby(claim[1][0] if s.engine_run == DEFAULT_ENGINE_RUN else None)
        pack_error = self._supervise(slots, sim.proc, sim.receiver, sim.flags)
        sim.receiver.close()
        sim.proc.join()
        self._conclude_rest(slots, sim.proc.exitcode, pack_error)
        return {slot.job.id: slot.outcome for slot in slots}

    # ---- the standby simulation process (issue 14: time to result) ----------------------------------
    def _spawn_standby(self, warm_spec_json: Optional[str]) -> Optional["_SimProcess"]:
        """Start the next claim's simulation process now (jobs/runner.py standby_main): its start-up
        (interpreter, imports, on a GPU the driver, context and kernels of ``warm_spec_json``'s
        specialisation, the default spec's when None and the engine is the default one) overlaps the
        worker's idle wait or the running claim. None if it cannot be started (the claim then spawns its own)."""
        s = self.settings
        if warm_spec_json is None and s.engine_run == DEFAULT_ENGINE_RUN:
            warm_spec_json = DEFAULT_WARM_SPEC
        try:
            ctx = multiprocessing.get_context("spawn")
            receiver, sender = ctx.Pipe(duplex=False)
            claims_in, claims_out = ctx.Pipe(duplex=False)
            flags = ctx.RawArray("b", s.ensemble_max_jobs if s.packing else 1)
            proc = ctx.Process(target=standby_main, name="demq-standby",
                               args=(claims_in, sender, flags, os.getpid(), warm_spec_json))
            proc.start()
        except Exception as exc:  # noqa: BLE001  (out of processes or memory: claims spawn their own)
            log.error("cannot start a standby simulation process: %s", exc)
            return None
        sender.close()
        claims_in.close()
        return _SimProcess(proc, receiver, flags, claims_out)

    def _hand_to_standby(self, claim: tuple, n_jobs: int, job_id: str) -> Optional["_SimProcess"]:
        """Give ``claim`` to the standby process; None if there is none fit to take it."""
        sim, self._standby = self._standby, None
        if sim is None:
            return None
        if not sim.proc.is_alive() or len(sim.flags) < n_jobs:
            sim.close()
            return None
        try:
            sim.claims.send(claim)
        except (BrokenPipeError, OSError):
            sim.close()
            return None
        sim.claims.close()
        sim.claims = None
        log.info("job %s: handed to the standby simulation process (pid %s)", job_id, sim.proc.pid)
        return sim

    def _supervise(self, slots: list["_Slot"], proc, receiver, flags) -> Optional[str]:
        """Relay progress and heartbeats (per job) until the process ends, concluding each job as its
        final message arrives; return the pack-level error message, if any."""
        s = self.settings
        pack_error = None
        last_beat = last_write = time.monotonic()
        while True:
            if receiver.poll(0.2):
                try:
                    kind, k, payload = receiver.recv()
                except EOFError:
                    break  # the process has exited (or closed its end): everything was read
                if k is None:
                    pack_error = payload
                    continue
                slot = slots[k]
                if kind == "progress":
                    if slot.outcome is None:
                        slot.pending = slot.latest = payload
                        if self.on_progress is not None:
                            self.on_progress(slot.job, payload)
                else:
                    slot.final = (kind, payload)
                    if slot.outcome is None:
                        self._conclude(slot)
            elif not proc.is_alive():
                if receiver.poll(0):
                    continue   # it sent its last messages and exited between the poll and this check: read them
                break
            now = time.monotonic()
            beating = [x for x in slots if x.outcome is None and x.stop_reason != "lease lost"]
            pending = any(x.pending is not None for x in beating)
            due = now - last_beat >= s.heartbeat_s or (pending and now - last_write >= s.progress_s)
            if due and beating:
                try:
                    answers = self.store.heartbeat_many([x.job.id for x in beating], self.owner, s.lease_s,
                                                        {x.job.id: _columns(x.pending) for x in beating})
                    last_beat = now
                    if pending:
                        last_write = now
                    for x in beating:
                        x.pending = None
                        if x.job.id not in answers:
                            log.error("job %s: lease lost; stopping its simulation", x.job.id)
                            x.stop_reason = "lease lost"
                        elif answers[x.job.id] and x.stop_reason is None:
                            x.stop_reason = "cancel"
                except SQLAlchemyError as exc:
                    log.error("heartbeat of %s failed, retrying: %s", " ".join(x.job.id for x in beating), exc)
            for k, x in enumerate(slots):
                if x.outcome is not None:
                    continue
                if self._stop.is_set() and x.stop_reason is None:
                    x.stop_reason = "shutdown"
                if x.stop_reason is not None and x.kill_at is None:
                    log.info("job %s: stopping the simulation (%s)", x.job.id, x.stop_reason)
                    flags[k] = 1
                    x.kill_at = now + s.cancel_grace_s
            waiting = [x for x in slots if x.outcome is None]
            overdue = [x for x in waiting if x.kill_at is not None and now > x.kill_at]
            if overdue and proc.is_alive():
                if len(overdue) == len(waiting):
                    log.warning("job(s) %s: simulation did not stop within %.3g s; killing it",
                                " ".join(x.job.id for x in overdue), s.cancel_grace_s)
                    proc.kill()
                else:  # the rest of the pack runs on: stop waiting for these jobs' scenes
                    for x in overdue:
                        log.warning("job %s: its scene did not stop within %.3g s; the pack runs on, the job "
                                    "ends now", x.job.id, s.cancel_grace_s)
                        x.abandoned = True
                        self._conclude(x)
        return pack_error

    def _conclude(self, slot: "_Slot", exitcode=None) -> Optional[str]:
        """Write a job's end to the table from its final message and stop reason; None if neither
        explains it (the process died: see :meth:`_conclude_rest`)."""
        job = slot.job
        kind, payload = slot.final if slot.final is not None else (None, None)
        progress = _columns(slot.latest)
        if slot.stop_reason == "lease lost":
            slot.outcome = "lost"
            return slot.outcome
        if kind == "done":
            state = DONE
            summary = {k: payload[k] for k in ("wall_s", "cundall", "backend", "device", "resumed_from_step")}
            self.store.finish(job.id, self.owner, DONE, **{**progress, **summary, "progress": 1.0, "eta_s": 0.0},
                              error=None, result_path=str(slot.output))
        elif kind == "error":
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, error=payload, **progress)
        elif slot.stop_reason == "shutdown":
            self.store.release(job.id, self.owner)
            log.info("job %s: released to the queue (worker stopping); checkpoints kept", job.id)
            slot.outcome = "released"
            return slot.outcome
        elif slot.stop_reason == "cancel":
            state = CANCELLED
            self.store.finish(job.id, self.owner, CANCELLED, error=None, **progress)
        elif kind == "cancelled":
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, **progress,
                              error=f"the simulation stopped without being asked: {payload}")
        elif exitcode is not None:
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, error=describe_exit(exitcode), **progress)
        else:
            return None
        if not slot.abandoned:  # an abandoned scene may still write there: cleaned when the process ends
            shutil.rmtree(slot.checkpoints, ignore_errors=True)
        log.info("job %s: %s", job.id, state)
        slot.outcome = state
        return state

    def _conclude_rest(self, slots: list["_Slot"], exitcode, pack_error: Optional[str]) -> None:
        """After the process has ended: conclude the jobs that have no outcome yet.

        Jobs explained by their own message or stop reason end as those say. If the process died (or
        the pack failed as a whole) while several jobs were still running, nothing tells which one
        caused it: each goes back to the queue, not counting the attempt, with the note that it runs
        alone next time (jobs/packing.py), where the culprit fails by itself. A single job ends failed
        with the reason, as it always has.
        """
        for x in slots:
            if x.outcome is None:
                self._conclude(x)
            elif x.abandoned and x.outcome in (CANCELLED, FAILED):
                shutil.rmtree(x.checkpoints, ignore_errors=True)
                if x.output.exists():  # its scene finished after all: the job stays cancelled, no result
                    x.output.unlink()
        left = [x for x in slots if x.outcome is None]
        if len(left) == 1:
            x = left[0]
            if pack_error is not None:
                x.final = ("error", pack_error)
            self._conclude(x, exitcode=exitcode)
        elif left:
            reason = pack_error or describe_exit(exitcode)
            for x in left:
                self.store.release(x.job.id, self.owner, error=f"{SOLO}its pack of {len(slots)} jobs failed "
                                                               f"as a whole ({reason})")
                log.warning("job %s: its pack failed as a whole (%s); requeued to run alone", x.job.id, reason)
                x.outcome = "requeued"


@dataclass
class _SimProcess:
    """A simulation process and the worker's ends of its pipes."""

    proc: object                       # multiprocessing Process
    receiver: object                   # its messages (jobs/runner.py's protocol)
    flags: object                      # per-job cancel bytes (shared memory)
    claims: Optional[object] = None    # a standby's claim pipe, until it has its claim

    def close(self) -> None:
        """End a standby that will get no claim (or a process that died): tell it, then wait or kill."""
        if self.claims is not None:
            try:
                self.claims.send(None)
            except (BrokenPipeError, OSError):
                pass
            self.claims.close()
            self.claims = None
        self.proc.join(timeout=STANDBY_CLOSE_S)
        if self.proc.is_alive():   # still starting up (it reads the pipe only then): its start-up is not needed
            self.proc.kill()
            self.proc.join()
        self.receiver.close()


@dataclass
class _Slot:
    """A job of the running simulation process and what the worker knows of it."""

    job: Job
    output: Path
    checkpoints: Path
    final: Optional[tuple] = None        # (kind, payload) of the simulation's final message
    stop_reason: Optional[str] = None    # cancel | shutdown | lease lost
    kill_at: Optional[float] = None      # monotonic deadline for the scene to stop
    pending: Optional[dict] = None       # progress not yet written to the table
    latest: dict = field(default_factory=dict)
    outcome: Optional[str] = None        # what the job was left in, once concluded
    abandoned: bool = False              # concluded while its scene was still running (deaf to a stop)


def _columns(progress: Optional[dict]) -> dict:
    """Engine progress -> job-table columns."""
    return {_PROGRESS_COLUMNS[k]: v for k, v in (progress or {}).items() if k in _PROGRESS_COLUMNS}


def _safe_url(url: str) -> str:
    """The database URL without its password, for the log."""
    try:
        from sqlalchemy.engine import make_url
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # not a URL SQLAlchemy parses: log nothing of it
        return "<database>"


def _spec_json(job: Job) -> str:
    return json.dumps(job.spec)
