"""The worker: claims one job at a time and runs it in its own simulation process.

One attempt (:meth:`Worker.execute`)::

    spawn the simulation process (jobs/runner.py) --pipe--> progress, then done | error | cancelled
    every heartbeat (or progress, rate-limited): renew the lease, write progress, read cancel_requested
    cancel requested / worker stopping / lease lost -> set the cancel event; SIGKILL after the grace period
    process exit -> done (result written atomically by the engine) | failed (readable reason) |
                    cancelled | released back to the queue (worker shutdown; the attempt is not counted)

A crash of the simulation process fails that job only; the worker goes on with the next one. If
the worker itself dies, its lease expires and the reaper (run by every worker between jobs) puts the
job back in the queue, where the engine resumes it from its last checkpoint.
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
from typing import Callable, Optional

from sqlalchemy.exc import SQLAlchemyError

from jobs.runner import child_main
from jobs.schema import CANCELLED, DONE, FAILED, FINAL_STATES, QUEUED, RUNNING
from jobs.settings import Settings
from jobs.store import Job, JobStore, LeaseLost

log = logging.getLogger("demq.worker")

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
        self._last_reap = 0.0

    def stop(self) -> None:
        """Stop claiming; a running job is stopped (checkpointed by the engine) and released."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ---- loops ------------------------------------------------------------------------------------
    def run_forever(self, exit_when_idle: bool = False) -> None:
        """Claim and run jobs until :meth:`stop`; with ``exit_when_idle`` (drain mode, for Slurm job
        arrays), also return once the table holds no queued and no running job."""
        log.info("worker %s started on %s", self.owner, _safe_url(self.settings.database_url))
        while not self._stop.is_set():
            job = self._next(None)
            if job is None:
                if exit_when_idle and self._drained():
                    log.info("worker %s: no queued or running job left; exiting (drain mode)", self.owner)
                    break
                self._stop.wait(self.settings.poll_s)
            else:
                self.execute(job)
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
            if claimed is not None:
                self.execute(claimed)
            else:
                if self.on_progress is not None:
                    self.on_progress(job, {"fraction": job.progress, "phase": job.phase or job.state,
                                           "eta_s": job.eta_s})
                self._stop.wait(self.settings.poll_s)
        return self.store.get(job_id)

    def _next(self, job_id: Optional[str]) -> Optional[Job]:
        try:
            if time.monotonic() - self._last_reap >= self.settings.heartbeat_s:
                requeued, failed = self.store.reap_expired()
                self._last_reap = time.monotonic()
                if requeued or failed:
                    log.warning("reaper: requeued %s, failed %s (expired leases)", requeued, failed)
            return self.store.claim(self.owner, self.settings.lease_s, job_id)
        except SQLAlchemyError as exc:
            log.error("cannot reach the job table, retrying: %s", exc)
            return None

    # ---- one attempt ------------------------------------------------------------------------------
    def execute(self, job: Job) -> str:
        """Run one claimed job to its end; return the state it was left in (or 'lost')."""
        s = self.settings
        output, checkpoints = s.result_path(job.id), s.checkpoint_dir(job.id)
        output.parent.mkdir(parents=True, exist_ok=True)
        checkpoints.mkdir(parents=True, exist_ok=True)
        log.info("job %s: attempt %d of %d", job.id, job.attempts, job.max_attempts)

        ctx = multiprocessing.get_context("spawn")
        receiver, sender = ctx.Pipe(duplex=False)
        cancel = ctx.Event()
        proc = ctx.Process(target=child_main, name=f"demq-job-{job.id}", args=(
            s.engine_run, _spec_json(job), str(output), str(checkpoints), s.checkpoint_interval,
            sender, cancel, os.getpid()))
        proc.start()
        sender.close()
        final, stop_reason, latest = self._supervise(job, proc, receiver, cancel)
        receiver.close()
        proc.join()
        return self._conclude(job, proc.exitcode, final, stop_reason, _columns(latest), output, checkpoints)

    def _supervise(self, job: Job, proc, receiver, cancel) -> tuple[Optional[tuple], Optional[str], dict]:
        """Relay progress and heartbeats until the process ends; return (final message, stop reason,
        latest progress)."""
        s = self.settings
        final, stop_reason, kill_at = None, None, None
        pending: Optional[dict] = None
        latest: dict = {}
        last_beat = last_write = time.monotonic()
        while True:
            if receiver.poll(0.2):
                try:
                    kind, payload = receiver.recv()
                except EOFError:
                    break  # the process has exited (or closed its end): everything was read
                if kind == "progress":
                    pending = latest = payload
                    if self.on_progress is not None:
                        self.on_progress(job, payload)
                else:
                    final = (kind, payload)
            elif not proc.is_alive():
                break
            now = time.monotonic()
            due = now - last_beat >= s.heartbeat_s or (pending is not None and now - last_write >= s.progress_s)
            if due and stop_reason != "lease lost":
                try:
                    cancel_requested = self.store.heartbeat(job.id, self.owner, s.lease_s, _columns(pending))
                    last_beat = now
                    if pending is not None:
                        last_write, pending = now, None
                    if cancel_requested and stop_reason is None:
                        stop_reason = "cancel"
                except LeaseLost:
                    log.error("job %s: lease lost; stopping its simulation", job.id)
                    stop_reason = "lease lost"
                except SQLAlchemyError as exc:
                    log.error("job %s: heartbeat failed, retrying: %s", job.id, exc)
            if self._stop.is_set() and stop_reason is None:
                stop_reason = "shutdown"
            if stop_reason is not None and kill_at is None:
                log.info("job %s: stopping the simulation (%s)", job.id, stop_reason)
                cancel.set()
                kill_at = now + s.cancel_grace_s
            if kill_at is not None and now > kill_at and proc.is_alive():
                log.warning("job %s: simulation did not stop within %.0f s; killing it", job.id, s.cancel_grace_s)
                proc.kill()
        return final, stop_reason, latest

    def _conclude(self, job: Job, exitcode, final, stop_reason, progress: dict, output, checkpoints) -> str:
        kind, payload = final if final is not None else (None, None)
        if stop_reason == "lease lost":
            return "lost"
        if kind == "done":
            state = DONE
            summary = {k: payload[k] for k in ("wall_s", "cundall", "backend", "device", "resumed_from_step")}
            self.store.finish(job.id, self.owner, DONE, **{**progress, **summary, "progress": 1.0, "eta_s": 0.0},
                              error=None, result_path=str(output))
        elif kind == "error":
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, error=payload, **progress)
        elif stop_reason == "shutdown":
            self.store.release(job.id, self.owner)
            log.info("job %s: released to the queue (worker stopping); checkpoints kept", job.id)
            return "released"
        elif stop_reason == "cancel":
            state = CANCELLED
            self.store.finish(job.id, self.owner, CANCELLED, error=None, **progress)
        elif kind == "cancelled":
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, **progress,
                              error=f"the simulation stopped without being asked: {payload}")
        else:
            state = FAILED
            self.store.finish(job.id, self.owner, FAILED, error=describe_exit(exitcode), **progress)
        shutil.rmtree(checkpoints, ignore_errors=True)
        log.info("job %s: %s", job.id, state)
        return state


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
