"""The worker: claims a job — or several — and runs the claim in a simulation process of its own.

At its start a worker registers in the store's worker table (the backends it can run: "cpu", and "cuda" where a
GPU is; `demq serve` registers its embedded worker before it answers a request) and claims at once. With the
default engine it also warms every kernel specialisation it can be asked for (jobs/warm.py: compiled, or loaded
from numba's disk cache) in a process group of its own beside the claims, at the lowest CPU priority and paused
while a claim runs: a claim compiles or loads only its own kernels and never waits for the others'. It refreshes
its row at every poll and heartbeat and removes it when it stops.

A claim (:meth:`Worker._next`) takes the next queued job and, with packing on (DEMQ_ENSEMBLE_MAX_JOBS > 1),
queued jobs that can go with it (jobs/packing.py), up to DEMQ_ENSEMBLE_MAX_JOBS jobs and the worker's fair
share of the queue: ceil(queued / live workers that run that backend), so that one worker does not take the
whole queue while others are idle. Several CPU jobs run one after another in one warm process, the cheapest
first (``sequence``); several GPU jobs of similar cost run as one ensemble (``ensemble``). One attempt
(:meth:`Worker.execute_pack`; :meth:`Worker.execute` for one job)::

    spawn the simulation process (jobs/runner.py; a running worker, DEMQ_WORKER_STANDBY, hands the claim to its
                    standby process instead: the one it started ahead, or the process of its last CPU claim,
                    which stays for the next claims; with a GPU claim it starts the next claim's process)
                    --pipe--> per job: (started,) progress, then done | error | cancelled
    every heartbeat (or progress, rate-limited): renew every job's lease and write its progress (one
                    transaction; a sequence's jobs that wait for their turn get phase "waiting" and the
                    ETA of their own end), read its cancel_requested
    every DEMQ_CANCEL_POLL_SECONDS: read the cancel requests of the claim's jobs
    cancel requested / worker stopping / lease lost -> set that job's cancel flag; its scene stops alone
                    (a sequence's job that has not started ends at once: cancelled, or released)
    a job's final message -> that job ends at once: done (result written atomically by the engine) |
                    failed (readable reason) | cancelled | released back to the queue (worker shutdown;
                    the attempt is not counted); the rest of the claim runs on
    a cancel not honoured within DEMQ_CANCEL_KILL_SECONDS while the process runs no other job's scene
                    (one job, or a sequence) -> SIGKILL; the job ends cancelled, its partial result and
                    checkpoints removed; the sequence's jobs that had not started go back to the queue
    another stop not honoured within the grace period -> SIGKILL if no other job of the process is still
                    running, else the job ends without waiting for its scene
    every job's final message in -> the claim is over; its process takes the lane's next claim once it
                    says "ready" (a CPU claim's), or exits (joined later, not waited for)
    process exit    -> jobs still without an end: one job fails with the reason (a sequence's running job:
                    the one that was running; its jobs that had not started go back to the queue); several
                    (a pack that died or failed as a whole) go back to the queue to run alone next time

A crash of the simulation process fails that job only (a pack's jobs are retried alone, where the
culprit fails by itself); the worker goes on with the next claim, in a fresh process. If the worker itself dies,
the leases expire and the reaper (run by every worker between claims) puts the jobs back in the queue, where the
engine resumes each from its last checkpoint.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import os
import shutil
import signal
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

from sqlalchemy.exc import SQLAlchemyError

from engine.output.h5md import partial_path
from jobs.packing import ENSEMBLE, ONE, SEQUENCE, SOLO, Packer, fair_share, particle_steps, sequence_order
from jobs.runner import child_main, standby_main
from jobs.schema import CANCELLED, DONE, FAILED, FINAL_STATES, QUEUED, RUNNING
from jobs.settings import DEFAULT_ENGINE_RUN, Settings
from jobs.store import Job, JobStore

log = logging.getLogger("demq.worker")

#: Queued rows read per claim to find jobs to pack, per allowed job of a pack.
PEEK_FACTOR = 4

#: Most messages of a simulation process read in one go before the supervisor's bookkeeping (heartbeats, cancels,
#: deadlines) runs again.
DRAIN_MESSAGES = 10_000

#: Seconds a standby process that gets no claim has to exit before it is killed.
STANDBY_CLOSE_S = 0.5

#: Seconds a lane's process that has sent every job's end of its last claim has to say that it reads the next one
#: (it does at once; a process that does not is ended and the claim gets a fresh one).
REUSE_READY_S = 2.0

#: Seconds the worker waits for a standby's hand-over lock (the standby holds it only to check its claim pipe and
#: say "warming"; one that holds it longer has died there, and the claim gets a process of its own).
HAND_OVER_LOCK_S = 2.0

#: What a standby process warms when the worker has run no claim yet: the default spec (the service's form and
#: `demq submit`'s default job).
DEFAULT_WARM_SPEC = "{}"

#: Progress keys (from engine Progress) -> job-table columns.
_PROGRESS_COLUMNS = {"fraction": "progress", "phase": "phase", "step": "step", "time": "sim_time",
                     "eta_s": "eta_s", "cundall": "cundall", "resumed_from_step": "resumed_from_step"}


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
        self._packer = Packer(settings.ensemble_max_jobs, settings.ensemble_max_particles,
                              cpu_mode=settings.cpu_packs, cost_ratio=settings.ensemble_cost_ratio)
        self._last_seen = 0.0
        self._standby: Optional[_SimProcess] = None   # the next claim's process, started up (run_forever)
        self._keep_standby = False
        self._exiting: list[_SimProcess] = []         # processes whose jobs all ended done, still exiting
        self._registered: Optional[tuple[str, ...]] = None   # the backends entered in the worker table
        self._device_memory: Optional[int] = None   # bytes of the GPU's memory (registered beside the backends)
        self._warm_up = None                          # the background warm-up (jobs/warm.py), while it runs
        self._gate = _ClaimGate()                     # claims running in this worker's lanes (pauses the warm-up)
        self._lanes: list[tuple["Worker", threading.Thread]] = []   # the other lanes (run_forever)
        self.threads: Optional[int] = None            # Numba threads of its simulation processes (None: all)
        self._is_lane = False                         # one of another worker's lanes (not the first)

    def stop(self) -> None:
        """Stop claiming; a running job is stopped (checkpointed by the engine) and released."""
        self._stop.set()
        self._wake.set()
        for lane, _ in self._lanes:
            lane.stop()

    def wake(self) -> None:
        """Look for queued jobs now instead of at the end of the idle wait (the service calls it on submit)."""
        self._wake.set()
        for lane, _ in self._lanes:
            lane.wake()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ---- loops ------------------------------------------------------------------------------------
    def run_forever(self, exit_when_idle: bool = False) -> None:
        """Claim and run jobs until :meth:`stop`; with ``exit_when_idle`` (drain mode, for Slurm job
        arrays), also return once the table holds no queued and no running job."""
        log.info("worker %s started on %s", self.owner, _safe_url(self.settings.database_url))
        backends = self.register()
        try:
            self._start_lanes(backends, exit_when_idle)
            # the first claim's process starts up (imports, GPU context, the default spec's kernels) at once, and
            # the warm-up of every other specialisation beside it: neither holds up a claim
            self._keep_standby = self.settings.standby_enabled
            if self._keep_standby and not self._stop.is_set():
                # the other lanes' processes only import the engine: a dozen processes compiling the default spec's
                # kernels at once on an empty cache would hold up the first claims (a lane's first run loads, or
                # compiles, the kernels its claims need)
                self._standby = self._spawn_standby(None, warm=not self._is_lane)
            self._warm(backends)
            while not self._stop.is_set():
                self._reap(wait=False)
                self._warm_up_progress()
                jobs = self._next(None)
                if not jobs:
                    if exit_when_idle and self._drained():
                        log.info("worker %s: no queued or running job left; exiting (drain mode)", self.owner)
                        break
                    self._wake.wait(self.settings.poll_s)
                    self._wake.clear()
                else:
                    self._run_claim(jobs)
        finally:
            self._keep_standby = False
            if self._lanes and not exit_when_idle:
                for lane, _ in self._lanes:
                    lane.stop()
            for _, thread in self._lanes:
                thread.join()
            if self._warm_up is not None:
                self._gate.attach(None)
                self._warm_up.close()
                self._warm_up = None
            if self._standby is not None:
                self._standby.close()
                self._standby = None
            self._reap(wait=True)
            self._unregister()
        log.info("worker %s stopped", self.owner)

    def _run_claim(self, jobs: list[Job]) -> dict[str, str]:
        """:meth:`execute_pack` with the background warm-up paused meanwhile (the claims have the host to
        themselves: it goes on once no lane runs one)."""
        self._gate.enter()
        try:
            return self.execute_pack(jobs)
        finally:
            self._gate.leave()

    def _start_lanes(self, backends: tuple[str, ...], exit_when_idle: bool) -> None:
        """With several lanes (Settings.lane_count), start the others: each a worker of its own in a thread of this
        process, with its own row in the worker table (so that the fair share divides the queue among lanes), its own
        claims, standby and supervision, and cores / lanes Numba threads for its simulation processes, as this one.
        Only this lane warms kernels; a claim in any lane pauses that warm-up."""
        lanes = self.settings.lane_count(backends) if not self._stop.is_set() else 1
        if lanes <= 1:
            return
        self.threads = max(1, (os.cpu_count() or 1) // lanes)
        for k in range(1, lanes):
            lane = Worker(self.store, replace(self.settings, worker_id=f"{self.owner}/lane{k}", lanes="1", warm="off"),
                          on_progress=self.on_progress)
            lane.threads, lane._gate, lane._is_lane = self.threads, self._gate, True
            lane.register(backends)
            thread = threading.Thread(target=lane.run_forever, args=(exit_when_idle,), daemon=True,
                                      name=f"demq-worker-lane{k}")
            self._lanes.append((lane, thread))
        for _, thread in self._lanes:
            thread.start()
        log.info("worker %s: %d lanes (claims at once), %d Numba threads each", self.owner, lanes, self.threads)

    # ---- the worker table and the warm-up --------------------------------------------------------
    def register(self, backends: Optional[tuple[str, ...]] = None) -> tuple[str, ...]:
        """Find the backends this worker can run (unless given) and enter them in the worker table, once; return
        them. The service calls it before it answers its first request (service/app.py), so that the admission check
        (service/backends.py) knows from then on what the embedded worker's host can run."""
        if self._registered is None:
            self._registered = backends if backends is not None else self._backends()
            if "cuda" in self._registered:
                from engine.backends.base import gpu_total_memory

                self._device_memory = gpu_total_memory()
            self._register(self._registered)
        return self._registered

    def _backends(self) -> tuple[str, ...]:
        """What this worker can run: 'cpu', and 'cuda' where a CUDA GPU is present."""
        try:
            cuda = self._packer.resolve("auto", "sphere") == "cuda"
        except Exception:  # noqa: BLE001  (numba-cuda unusable here: a CPU worker)
            cuda = False
        return ("cpu", "cuda") if cuda else ("cpu",)

    def _register(self, backends: tuple[str, ...]) -> None:
        try:
            self.store.register_worker(self.owner, socket.gethostname(), os.getpid(), list(backends),
                                       device_memory=self._device_memory)
            self._last_seen = time.monotonic()
        except SQLAlchemyError as exc:  # the claims retry the database; the fair share counts this worker later
            log.error("cannot register worker %s, going on: %s", self.owner, exc)

    def _seen(self) -> None:
        """Refresh this worker's row (at most every heartbeat/2: its liveness window is a lease)."""
        now = time.monotonic()
        if now - self._last_seen < 0.5 * self.settings.heartbeat_s:
            return
        try:
            self.store.worker_seen(self.owner)
            self._last_seen = now
        except SQLAlchemyError as exc:
            log.error("cannot refresh worker %s in the worker table: %s", self.owner, exc)

    def _unregister(self) -> None:
        try:
            self.store.unregister_worker(self.owner)
        except SQLAlchemyError as exc:  # its row ages out of live_workers after a lease
            log.error("cannot unregister worker %s: %s", self.owner, exc)

    def _warm(self, backends: tuple[str, ...]) -> None:
        """Start compiling (or loading from the disk cache) every kernel specialisation this worker can run, in a
        process group of its own beside the claims (jobs/warm.py BackgroundWarmUp: nice 19, paused while a claim
        runs), so that later jobs find their kernels compiled and no job waits for another's. Default engine only."""
        if not self.settings.warm_enabled or self._stop.is_set():
            return
        from jobs.warm import BackgroundWarmUp

        try:
            self._warm_up = BackgroundWarmUp(backends)
        except Exception as exc:  # noqa: BLE001  (each job then compiles what it needs, as without the warm-up)
            log.error("cannot start the warm-up, jobs compile their own kernels: %s", exc)
            return
        self._gate.attach(self._warm_up)
        log.info("warm-up of every kernel specialisation started beside the claims (%s)", " ".join(backends))

    def _warm_up_progress(self) -> None:
        """Log the background warm-up's report once it has one (or that it ended without one), and let it go."""
        warm_up = self._warm_up
        if warm_up is None:
            return
        report = warm_up.poll(0)
        if report is not None:
            log.info("%s", report.line())
        elif warm_up.running:
            return
        else:
            log.error("the warm-up ended without a report; jobs compile their own kernels")
        self._gate.attach(None)
        warm_up.close()
        self._warm_up = None

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
                self._reap(wait=True)
            else:
                if self.on_progress is not None:
                    self.on_progress(job, {"fraction": job.progress, "phase": job.phase or job.state,
                                           "eta_s": job.eta_s})
                self._stop.wait(self.settings.poll_s)
        return self.store.get(job_id)

    def _next(self, job_id: Optional[str]) -> list[Job]:
        """The next claim: one job (``job_id``, or the next queued), plus the compatible queued jobs
        packed with it (jobs/packing.py) when packing is on; [] if none."""
        self._seen()
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
            share = min(self._share(first), self.settings.ensemble_max_jobs)
            if share <= 1:
                return [first]
            more = self._packer.select(first, self.store.peek_queued(PEEK_FACTOR * share), max_jobs=share)
            return [first] + (self.store.claim_ids(self.owner, self.settings.lease_s, [j.id for j in more])
                              if more else [])
        except SQLAlchemyError as exc:  # the first job is ours: it runs alone
            log.error("cannot pack more jobs with %s, running it alone: %s", first.id, exc)
            return [first]

    def _share(self, first: Job) -> int:
        """The most jobs this claim may hold: its fair share of the queue, ceil(queued / live workers that run
        ``first``'s backend) with ``first`` counted as queued (jobs/packing.py fair_share), and this worker
        counted live even if its row is missing."""
        backend = self._packer.backend(first)
        if backend is None:
            return 1
        queued = self.store.counts().get(QUEUED, 0) + 1
        live = {w.worker_id for w in self.store.live_workers(self.settings.lease_s) if backend in w.backends}
        return fair_share(queued, len(live | {self.owner}))

    # ---- one attempt (one job, a sequence of CPU jobs, or a pack of jobs run as one ensemble) ------
    def execute(self, job: Job) -> str:
        """Run one claimed job to its end; return the state it was left in (or 'lost')."""
        return self.execute_pack([job])[job.id]

    def execute_pack(self, jobs: list[Job]) -> dict[str, str]:
        """Run claimed jobs in one simulation process — alone (one job), one after another, cheapest first (a CPU
        sequence) or as one ensemble (jobs/packing.py); return {job id: the state it was left in, 'released',
        'requeued' or 'lost'}."""
        s = self.settings
        mode = self._packer.mode(jobs)
        if mode == SEQUENCE:
            jobs = sequence_order(jobs)
        slots = [_Slot(job, s.result_path(job.id), s.checkpoint_dir(job.id)) for job in jobs]
        for slot in slots:
            slot.output.parent.mkdir(parents=True, exist_ok=True)
            slot.checkpoints.mkdir(parents=True, exist_ok=True)
            log.info("job %s: attempt %d of %d", slot.job.id, slot.job.attempts, slot.job.max_attempts)
        if mode == ENSEMBLE:
            log.info("packing %d jobs into one ensemble run: %s", len(slots), " ".join(j.id for j in jobs))
        elif mode == SEQUENCE:
            log.info("running %d jobs one after another, cheapest first: %s", len(slots),
                     " ".join(j.id for j in jobs))
        for slot in slots:
            if mode == SEQUENCE:   # each starts in its turn ("started" message); until then it waits
                slot.cost = particle_steps(slot.job)
                slot.pending = slot.latest = {"phase": "waiting"}
            else:
                slot.started = True

        claim = (s.engine_run_ensemble if mode == ENSEMBLE else s.engine_run, [_spec_json(j) for j in jobs],
                 [str(x.output) for x in slots], [str(x.checkpoints) for x in slots], s.checkpoint_interval,
                 mode)
        # a CPU claim's process stays for the lane's next claims (its imports and loaded code serve them all: with
        # many small claims, a process start-up per claim had cost a lane more than its jobs' runs); a GPU claim's
        # process ends with it, its device memory going back with its context
        on_gpu = self._packer.backend(jobs[0]) == "cuda"
        keep = self._keep_standby and not on_gpu
        # a GPU pack runs the packed kernels, which a standby warming one job of its spec does not compile
        packed = mode == ENSEMBLE and on_gpu
        sim = self._hand_to_standby(claim, len(slots), jobs[0].id, packed)
        if sim is None and keep:   # the lane's process, started with its first claim (or after one that died)
            self._standby = self._spawn_standby(claim[1][0] if s.engine_run == DEFAULT_ENGINE_RUN else None)
            sim = self._hand_to_standby(claim, len(slots), jobs[0].id, packed)
        if sim is None:
            ctx = multiprocessing.get_context("spawn")
            receiver, sender = ctx.Pipe(duplex=False)
            flags = ctx.RawArray("b", len(slots))  # per-job cancel flags, read by the simulation's cancel checks
            proc = ctx.Process(target=child_main, name=f"demq-job-{jobs[0].id}",
                               args=claim[:5] + (sender, flags, os.getpid(), mode, self.threads))
            proc.start()
            sender.close()
            sim = _SimProcess(proc, receiver, flags)
        if self._keep_standby and not keep:    # the next claim's process starts up while this one runs
            self._standby = self._spawn_standby(claim[1][0] if s.engine_run == DEFAULT_ENGINE_RUN else None)
        pack_error = self._supervise(slots, sim.proc, sim.receiver, sim.flags, mode)
        if all(slot.final is not None for slot in slots) and sim.proc.is_alive():
            # every job's end has come from the process (each concluded as it came): nothing of the claim is left
            # in it. A lane's process takes the next claim; another one's exit is not waited for (a GPU process's
            # context teardown takes seconds): it is joined later (_reap)
            self._conclude_rest(slots, None, pack_error, mode)
            if keep and pack_error is None and not self._stop.is_set() and self._standby is None:
                sim.claims_run += 1
                sim.ready = sim.warming = sim.compiling = False
                self._standby = sim
            else:
                sim.retire()
                self._exiting.append(sim)
            return {slot.job.id: slot.outcome for slot in slots}
        sim.retire()
        sim.receiver.close()
        sim.proc.join()
        self._conclude_rest(slots, sim.proc.exitcode, pack_error, mode)
        return {slot.job.id: slot.outcome for slot in slots}

    def _reap(self, wait: bool) -> None:
        """Join the processes of :attr:`_exiting` that have exited (all of them with ``wait``: one that does not
        exit within STANDBY_CLOSE_S is killed, its jobs are already done)."""
        for sim in list(self._exiting):
            if wait or not sim.proc.is_alive():
                sim.close()
                self._exiting.remove(sim)

    # ---- the standby simulation process (time to result) --------------------------------------------
    def _spawn_standby(self, warm_spec_json: Optional[str], warm: bool = True) -> Optional["_SimProcess"]:
        """Start the next claim's simulation process now (jobs/runner.py standby_main): its start-up
        (interpreter, imports, on a GPU the driver, context and kernels of ``warm_spec_json``'s
        specialisation, the default spec's when None and the engine is the default one; without ``warm`` the
        imports only) overlaps the worker's idle wait or the running claim. None if it cannot be started (the claim
        then spawns its own)."""
        s = self.settings
        if not warm:
            warm_spec_json = None
        elif warm_spec_json is None and s.engine_run == DEFAULT_ENGINE_RUN:
            warm_spec_json = DEFAULT_WARM_SPEC
        try:
            ctx = multiprocessing.get_context("spawn")
            receiver, sender = ctx.Pipe(duplex=False)
            claims_in, claims_out = ctx.Pipe(duplex=False)
            flags = ctx.RawArray("b", s.ensemble_max_jobs if s.packing else 1)
            claim_promised = ctx.Value("b", 0)   # set, under its lock, once a claim is to be sent (_hand_to_standby)
            targets = tuple(t for t in (s.engine_run, s.engine_run_ensemble) if t)
            proc = ctx.Process(target=standby_main, name="demq-standby",
                               args=(claims_in, sender, flags, os.getpid(), warm_spec_json, self.threads, targets,
                                     claim_promised))
            proc.start()
        except Exception as exc:  # noqa: BLE001  (out of processes or memory: claims spawn their own)
            log.error("cannot start a standby simulation process: %s", exc)
            return None
        sender.close()
        claims_in.close()
        return _SimProcess(proc, receiver, flags, claims_out, warm_key=_specialisation(warm_spec_json),
                           claim_promised=claim_promised)

    def _hand_to_standby(self, claim: tuple, n_jobs: int, job_id: str,
                         packed: bool = False) -> Optional["_SimProcess"]:
        """Give ``claim`` to the standby process (started ahead, or the lane's process after its previous claim);
        None if there is none fit to take it. A standby still compiling the kernels of another specialisation than
        the claim's (an empty kernel cache) is not waited for: it is ended (what it compiled stays in the cache) and
        the claim gets a process of its own, which compiles or loads only what the claim needs. ``packed``: the claim
        is a GPU pack, whose packed kernels are not those of the one job a standby warms, so a standby that has begun
        its warm-up is not waited for either (a pack of 256 jobs had waited 23 s for one job's kernels and host start
        functions; a standby still importing skips its warm-up for the claim it finds).
        What the standby has said is read, and the claim promised to it, under the lock of its ``claim_promised``
        byte, under which the standby decides whether to warm up: a claim decided on is never sent to a standby that
        began its warm-up unseen (the send itself waits outside the lock: a pack's claim can fill the pipe).
        A process that ran a claim takes the next one once it has said that it reads it (REUSE_READY_S)."""
        sim, self._standby = self._standby, None
        if sim is None:
            return None
        if sim.claims_run:
            sim.wait_ready(REUSE_READY_S)
            if not sim.ready:
                log.warning("job %s: the lane's simulation process (pid %s) did not come back from its last claim; "
                            "the claim gets a fresh one", job_id, sim.proc.pid)
                sim.close()
                return None
            refusal = self._standby_refusal(sim, claim, n_jobs, packed)
        else:
            lock = sim.claim_promised.get_lock() if sim.claim_promised is not None else None
            if lock is not None and not lock.acquire(timeout=HAND_OVER_LOCK_S):
                refusal = (STANDBY_CLOSE_S, "the standby process holds its hand-over lock")
            else:
                try:
                    sim.read_start_up()
                    refusal = self._standby_refusal(sim, claim, n_jobs, packed)
                    if refusal is None and sim.claim_promised is not None:
                        sim.claim_promised.value = 1
                finally:
                    if lock is not None:
                        lock.release()
        if refusal is not None:
            grace_s, why = refusal
            if why:
                log.info("job %s: %s; the claim gets a process of its own", job_id, why)
            sim.close(grace_s=grace_s)
            return None
        sim.flags[:] = bytes(len(sim.flags))   # the previous claim's cancel flags, cleared (the process waits)
        try:
            sim.claims.send(claim)
        except (BrokenPipeError, OSError):
            sim.close()
            return None
        sim.ready = False
        log.info("job %s: handed to the standby simulation process (pid %s, its claim %d)", job_id, sim.proc.pid,
                 sim.claims_run + 1)
        return sim

    @staticmethod
    def _standby_refusal(sim: "_SimProcess", claim: tuple, n_jobs: int, packed: bool) -> Optional[tuple]:
        """Why ``sim`` must not take ``claim``, from what it has said: (grace seconds to end it, reason to log or
        ""), or None when it may."""
        if not sim.proc.is_alive() or len(sim.flags) < n_jobs:
            return STANDBY_CLOSE_S, ""
        if packed and sim.warming and not sim.ready:
            return 0.0, "the standby process is warming up one job's kernels, not a GPU pack's"
        if sim.compiling and not sim.ready and sim.warm_key != _specialisation(claim[1][0]):
            return 0.0, "the standby process is still compiling another specialisation's kernels"
        return None

    def _supervise(self, slots: list["_Slot"], proc, receiver, flags, mode: str = ONE) -> Optional[str]:
        """Relay progress and heartbeats (per job) until the process ends or every job has ended done,
        concluding each job as its final message arrives; return the pack-level error message, if any."""
        s = self.settings
        sequence = mode == SEQUENCE
        pack_error = None
        last_beat = last_write = last_poll = time.monotonic()
        killed = False
        awaited = sum(x.final is None for x in slots)   # jobs whose final message has not come yet
        while True:
            now = time.monotonic()
            kill_at = min((x.kill_at for x in slots if x.outcome is None and x.kill_at is not None), default=now + 1.0)
            if receiver.poll(max(0.01, min(0.2, last_poll + s.cancel_poll_s - now, kill_at - now))):
                # everything the pipe holds is read before the bookkeeping below, which is O(jobs): with one pass
                # per message, a pack of 256 jobs had kept its process waiting on a full pipe
                ended, finals = False, []
                for _ in range(DRAIN_MESSAGES):
                    try:
                        kind, k, payload = receiver.recv()
                    except EOFError:
                        ended = True  # the process has exited (or closed its end): everything was read
                        break
                    if kind == "progress_many":
                        for j, progress in payload.items():
                            self._progress(slots, j, progress, sequence)
                    elif kind in ("warming", "compiling", "ready"):
                        pass   # a standby's start-up, said before it took this claim
                    elif k is None:
                        pack_error = payload
                    elif kind == "started":
                        slot = slots[k]
                        slot.started = True
                        if slot.outcome is None:
                            slot.latest, slot.pending = {}, {"phase": "starting", "eta_s": None}
                    elif kind == "progress":
                        self._progress(slots, k, payload, sequence)
                    else:
                        awaited -= slots[k].final is None
                        slots[k].final = (kind, payload)
                        if slots[k].outcome is None:
                            finals.append(slots[k])
                        if not awaited:
                            break   # what follows is no longer this claim's (a lane's process: "ready")
                    if not receiver.poll(0):
                        break
                if finals:
                    self._conclude_all(finals)
                if ended or not awaited:
                    break   # every job's end is in: nothing of the claim is left in the process
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
                    last_beat = last_poll = now
                    if pending:
                        last_write = now
                    for x in beating:
                        x.pending = None
                        if x.job.id not in answers:
                            log.error("job %s: lease lost; stopping its simulation", x.job.id)
                            x.stop_reason = "lease lost"
                        elif answers[x.job.id] and x.stop_reason is None:
                            x.stop_reason = "cancel"
                    self._seen()
                except SQLAlchemyError as exc:
                    log.error("heartbeat of %s failed, retrying: %s", " ".join(x.job.id for x in beating), exc)
            elif now - last_poll >= s.cancel_poll_s:   # between heartbeats: only the cancel requests, cheaply
                asking = [x.job.id for x in beating if x.stop_reason is None]
                last_poll = now
                if asking:
                    try:
                        requested = self.store.cancel_requests(asking)   # one read for the claim's jobs
                        for x in beating:
                            if x.job.id in requested:
                                x.stop_reason = "cancel"
                    except SQLAlchemyError as exc:
                        log.error("reading the cancel requests failed, retrying: %s", exc)
            for k, x in enumerate(slots):
                if x.outcome is not None:
                    continue
                if self._stop.is_set() and x.stop_reason is None:
                    x.stop_reason = "shutdown"
                if x.stop_reason is not None and x.kill_at is None:
                    log.info("job %s: stopping the simulation (%s)", x.job.id, x.stop_reason)
                    flags[k] = 1
                    if sequence and not x.started:
                        # not begun: the process skips it (a run that began meanwhile stops at its first check;
                        # whatever it left is removed when the process ends)
                        x.abandoned = True
                        self._conclude(x)
                        continue
                    alone = all(y is x or y.outcome is not None or (sequence and not y.started) for y in slots)
                    quick = x.stop_reason == "cancel" and alone
                    x.stop_within = s.cancel_kill_s if quick else s.cancel_grace_s
                    x.kill_at = now + x.stop_within
            waiting = [x for x in slots if x.outcome is None and (x.started or not sequence)]
            overdue = [x for x in waiting if x.kill_at is not None and now > x.kill_at]
            if overdue and proc.is_alive() and not killed:
                if len(overdue) == len(waiting):
                    log.warning("job(s) %s: simulation did not stop within %.3g s; killing it",
                                " ".join(x.job.id for x in overdue), min(x.stop_within for x in overdue))
                    proc.kill()
                    killed = True
                else:  # the rest of the pack runs on: stop waiting for these jobs' scenes
                    for x in overdue:
                        log.warning("job %s: its scene did not stop within %.3g s; the pack runs on, the job "
                                    "ends now", x.job.id, s.cancel_grace_s)
                        x.abandoned = True
                        self._conclude(x)
        return pack_error

    def _progress(self, slots: list["_Slot"], k: int, progress: dict, sequence: bool) -> None:
        """Job k's progress report: kept for the next heartbeat's write (and the waiting ETAs of a sequence)."""
        slot = slots[k]
        if slot.outcome is None:
            slot.pending = slot.latest = progress
            if sequence:
                _estimate_waiting(slots, k, progress)
            if self.on_progress is not None:
                self.on_progress(slot.job, progress)

    def _conclude_all(self, slots: list["_Slot"]) -> None:
        """Conclude the jobs whose final messages just arrived: those done in one transaction (a pack's jobs end
        together), each other one as :meth:`_conclude` says."""
        done = [x for x in slots if x.final[0] == "done" and x.stop_reason != "lease lost"]
        if done:
            self.store.finish_many(self.owner, [(x.job.id, DONE, self._done_columns(x)) for x in done])
            for x in done:
                self._ended(x, DONE)
        for x in slots:
            if x.outcome is None:
                self._conclude(x)

    @staticmethod
    def _done_columns(slot: "_Slot") -> dict:
        """The job-table columns of a job whose run reported done: its last progress and its run summary."""
        payload = slot.final[1]
        summary = {k: payload[k] for k in ("loop_s", "job_wall_s", "cundall", "backend", "device", "resumed_from_step")}
        return {**_columns(slot.latest), **summary, "progress": 1.0, "eta_s": 0.0, "error": None,
                "result_path": str(slot.output)}

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
            self.store.finish(job.id, self.owner, DONE, **self._done_columns(slot))
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
        self._ended(slot, state)
        return state

    @staticmethod
    def _ended(slot: "_Slot", state: str) -> None:
        """What follows a job's end written to the table: its checkpoints removed, the log line, its outcome."""
        if not slot.abandoned:  # an abandoned scene may still write there: cleaned when the process ends
            shutil.rmtree(slot.checkpoints, ignore_errors=True)
        log.info("job %s: %s", slot.job.id, state)
        slot.outcome = state

    def _conclude_rest(self, slots: list["_Slot"], exitcode, pack_error: Optional[str], mode: str = ONE) -> None:
        """After the process has ended: conclude the jobs that have no outcome yet, and remove what the
        process left of jobs that did not end done (a partial result file of a killed run, a late result).

        Jobs explained by their own message or stop reason end as those say. A sequence's jobs that had not
        started go back to the queue (not counting the attempt); the one that was running is the one the
        process died in: it fails with the reason. If a pack's process died (or the pack failed as a whole)
        while several jobs were still running, nothing tells which one caused it: each goes back to the
        queue, not counting the attempt, with the note that it runs alone next time (jobs/packing.py), where
        the culprit fails by itself. A single job ends failed with the reason, as it always has, and so does
        the first job of a sequence whose process died before any run began (no claim loops forever).
        """
        for x in slots:
            if x.outcome is None:
                self._conclude(x)
            elif x.abandoned and x.outcome in (CANCELLED, FAILED):
                shutil.rmtree(x.checkpoints, ignore_errors=True)
                if x.output.exists():  # its scene finished after all: the job stays cancelled, no result
                    x.output.unlink()
        if mode == SEQUENCE:
            first = next((x for x in slots if x.outcome is None), None)
            if first is not None and not any(x.started for x in slots):
                first.started = True    # it died before its first run began: that job bears the blame
            for x in slots:
                if x.outcome is None and not x.started:
                    self.store.release(x.job.id, self.owner)
                    log.info("job %s: back to the queue (its claim's process ended before its turn)", x.job.id)
                    x.outcome = "requeued"
        left = [x for x in slots if x.outcome is None]
        if len(left) == 1 or (left and mode == SEQUENCE):
            for x in left:
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
        for x in slots:
            if x.outcome in (CANCELLED, FAILED, "released", "requeued"):
                partial_path(x.output).unlink(missing_ok=True)   # a killed run's partial result


class _ClaimGate:
    """The claims running in a worker's lanes, counted: the background warm-up (jobs/warm.py BackgroundWarmUp) of the
    worker's first lane is paused while any lane runs a claim and goes on when none does."""

    def __init__(self):
        self._lock = threading.Lock()
        self._running = 0
        self._warm_up = None

    def attach(self, warm_up) -> None:
        """The warm-up to pause and resume (paused at once if a lane already runs a claim); None once it ended."""
        with self._lock:
            self._warm_up = warm_up
            if warm_up is not None and self._running:
                warm_up.pause()

    def enter(self) -> None:
        with self._lock:
            self._running += 1
            if self._running == 1 and self._warm_up is not None:
                self._warm_up.pause()

    def leave(self) -> None:
        with self._lock:
            self._running -= 1
            if self._running == 0 and self._warm_up is not None:
                self._warm_up.resume()


@dataclass
class _SimProcess:
    """A simulation process and the worker's ends of its pipes."""

    proc: object                       # multiprocessing Process
    receiver: object                   # its messages (jobs/runner.py's protocol)
    flags: object                      # per-job cancel bytes (shared memory)
    claims: Optional[object] = None    # a standby's claim pipe, while it may get a claim
    warm_key: Optional[tuple] = None   # a standby's: the specialisation it starts up for (_specialisation)
    claim_promised: Optional[object] = None  # a standby's: shared byte + lock, set when a claim is to come to it
    warming: bool = False              # a standby's start-up has begun to warm its spec's kernels (said "warming")
    compiling: bool = False            # a standby's start-up has compiled kernels (said "compiling")
    ready: bool = False                # a standby's start-up is done, or its last claim over (said "ready")
    claims_run: int = 0                # claims it has run to their end (a lane's process, kept for the next)

    def read_start_up(self) -> None:
        """Read what a standby has said of its start-up so far ("warming", "compiling", "ready"), without waiting."""
        self.wait_ready(0.0)

    def wait_ready(self, timeout: float) -> None:
        """Read what the process has said until it says "ready" (its start-up done, or its last claim over: it
        reads the next one), waiting up to ``timeout`` seconds for it."""
        deadline = time.monotonic() + timeout
        try:
            while not self.ready and self.receiver.poll(max(0.0, deadline - time.monotonic())):
                kind = self.receiver.recv()[0]
                self.warming |= kind in ("warming", "compiling")
                self.compiling |= kind == "compiling"
                self.ready |= kind == "ready"
        except (EOFError, OSError):   # it died: the caller sees that it is not alive
            pass

    def retire(self) -> None:
        """Tell a standby-started process to exit once its claim is over (it gets no other)."""
        if self.claims is not None:
            try:
                self.claims.send(None)
            except (BrokenPipeError, OSError):
                pass
            self.claims.close()
            self.claims = None

    def close(self, grace_s: float = STANDBY_CLOSE_S) -> None:
        """End a standby that will get no claim, a process that died or one whose jobs are all done: tell a standby,
        then wait (``grace_s``) or kill."""
        self.retire()
        self.proc.join(timeout=grace_s)
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
    started: bool = False                # its run has begun (a sequence's jobs start one after another)
    cost: float = 0.0                    # estimated particle-steps (a sequence's ETAs)
    stop_within: float = 0.0             # seconds its run was given to stop once asked


def _estimate_waiting(slots: list[_Slot], k: int, progress: dict) -> None:
    """A sequence's jobs after job k that wait for their turn: phase "waiting" and the ETA of their own end, from
    the running job's ETA and Cundall number (particle-steps per second) and each job's estimated particle-steps."""
    rate, eta = progress.get("cundall") or 0.0, progress.get("eta_s")
    if not rate > 0 or eta is None or not math.isfinite(eta):
        return
    for x in slots[k + 1:]:
        if x.outcome is None and not x.started:
            eta += x.cost / rate
            x.pending = x.latest = {"phase": "waiting", "fraction": 0.0, "eta_s": eta}


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


#: engine/loops/cpu.py SERIAL_LOOP_BELOW, the size below which a CPU scene's time loop is compiled without parallel
#: regions (that module imports numba, which the worker process does not: tests/jobs/test_worker.py checks the two
#: match). From engine/setup/start_kind.py PARALLEL_START_MIN on, a sphere scene's start compiles other code too.
SMALL_SCENE_BELOW = 1024


def _specialisation(spec_json: Optional[str]) -> Optional[tuple]:
    """What of a spec selects compiled code: backend, shape, precision, contact law, sizes (jobs/warm.py
    Specialisation) and the scene's size class; None if it does not parse."""
    if spec_json is None:
        return None
    from engine.setup.start_kind import PARALLEL_START_MIN
    from jobs.specs import parse_spec

    try:
        spec = parse_spec(json.loads(spec_json))
    except Exception:  # noqa: BLE001  (an invalid spec fails in its process, with its reason)
        return None
    n = spec.n_particles
    size = "small" if n < SMALL_SCENE_BELOW else "medium" if n < PARALLEL_START_MIN else "large"
    return (spec.backend, spec.shape, spec.precision, spec.e_t == -1.0, spec.friction is not None,
            spec.species is not None, size)
