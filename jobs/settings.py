"""All configuration of the queue, the worker, the HTTP service and the client, in one place.

Every setting is read from an environment variable with the ``DEMQ_`` prefix; command-line flags
override the environment (``Settings.from_env(**overrides)``, where ``None`` means "not given").

=============================  ==================================  =================================================
Variable                       Default                             Meaning
=============================  ==================================  =================================================
DEMQ_DATA_DIR                  ``./demq-data``                     Data directory: ``results/<job_id>.h5``,
                                                                   ``checkpoints/<job_id>/``, ``batches/<batch_id>.h5``
                                                                   and the SQLite file.
DEMQ_DATABASE_URL              ``sqlite:///<data_dir>/demq.sqlite3``  Job table: ``sqlite:///PATH`` (embedded, WAL) or
                                                                   ``postgresql://user@host:port/db`` (several workers).
DEMQ_TABLE_PREFIX              (empty)                             Prefix of the table name (``<prefix>jobs``), so
                                                                   several queues can share one database.
DEMQ_TOKEN                     (unset: auth off)                   Bearer token required on every route but /healthz.
DEMQ_MAX_PARTICLE_STEPS        ``1e12``                            Refuse (422) a spec whose N x steps exceeds this.
DEMQ_MAX_MEMORY_BYTES          ``68719476736`` (64 GiB)            Refuse (422) a spec whose estimated memory
                                                                   exceeds this.
DEMQ_MAX_BODY_BYTES            ``1048576`` (1 MiB)                 Refuse (413) request bodies larger than this.
DEMQ_MAX_BATCH_JOBS            ``1000``                            Refuse (422) a batch that expands to more jobs.
DEMQ_MAX_ATTEMPTS              ``3``                               Claims of a job before a lost lease fails it.
DEMQ_LEASE_SECONDS             ``60``                              Lease of a claimed job; an unrenewed lease expires
                                                                   and the reaper returns the job to the queue.
DEMQ_HEARTBEAT_SECONDS         ``10``                              Interval of lease renewals (must be < lease).
DEMQ_POLL_SECONDS              ``1.0``                             Idle worker: wait between claim attempts (the
                                                                   embedded worker of ``demq serve`` is also woken
                                                                   by every submit).
DEMQ_PROGRESS_SECONDS          ``1.0``                             Least interval between progress writes to the row.
DEMQ_CANCEL_GRACE_SECONDS      ``10``                              Time a simulation gets to stop on shutdown (or on
                                                                   cancel, while its process runs other jobs' scenes
                                                                   too) before the worker kills its process.
DEMQ_CANCEL_KILL_SECONDS       ``0.3``                             Time a cancelled job's simulation gets to stop at
                                                                   its next stop when its process runs no other
                                                                   job's scene; then the process is killed and the
                                                                   job's partial result removed (the rest of a CPU
                                                                   claim goes back to the queue).
DEMQ_CANCEL_POLL_SECONDS       ``0.2``                             Interval of the worker's reads of cancel requests
                                                                   of its running jobs.
DEMQ_CHECKPOINT_INTERVAL       ``60``                              Wall seconds between engine checkpoints.
DEMQ_ENGINE_RUN                ``engine.driver.simulate:run``      ``module:function`` the simulation process calls
                                                                   (same signature as engine.driver.simulate.run);
                                                                   tests and the load bench point it at a fake
                                                                   engine.
DEMQ_ENGINE_RUN_ENSEMBLE       (auto)                              ``module:function`` that runs a pack of jobs (same
                                                                   signature as engine.driver.ensemble.run_ensemble).
                                                                   Auto: ``engine.driver.ensemble:run_ensemble``
                                                                   with the default DEMQ_ENGINE_RUN, none (no
                                                                   packing) with another.
DEMQ_ENSEMBLE_MAX_JOBS         ``256``                             Most queued jobs a worker claims at once (one
                                                                   ensemble on the GPU, one sequence on the CPU:
                                                                   jobs/packing.py); also capped at the worker's fair
                                                                   share of the queue; 1 disables packing.
DEMQ_ENSEMBLE_MAX_PARTICLES    ``4194304``                         Most particles of all jobs of one pack together (a
                                                                   memory bound: ~1.1 kB per float64 particle); a
                                                                   single larger job still runs, alone.
DEMQ_ENSEMBLE_COST_RATIO       ``4``                               An ensemble holds jobs whose estimated particle-
                                                                   steps (N x steps) are within this factor of the
                                                                   first job's, so a small job does not wait for a
                                                                   large one's scene (>= 1; a huge value: any mix).
DEMQ_CPU_PACKS                 ``sequence``                        How a claim of several CPU jobs runs: ``sequence``
                                                                   (one after another in one warm process, cheapest
                                                                   first: each job ends when its own run does) or
                                                                   ``ensemble`` (all scenes together, as on the GPU).
DEMQ_HOST / DEMQ_PORT          ``127.0.0.1`` / ``8000``            Where ``demq serve`` listens.
DEMQ_URL                       ``http://127.0.0.1:8000``           Service that ``demq submit/status/fetch`` talk to.
DEMQ_WORKER_ID                 ``<hostname>:<pid>:<random>``       Lease owner name of a worker.
DEMQ_WORKER_STANDBY            ``auto``                            ``on``: a running worker keeps the next claim's
                                                                   simulation process started up (interpreter,
                                                                   imports, GPU context and kernels) while it waits
                                                                   or runs a claim, and a CPU claim's process for
                                                                   the next claims; ``off``: each claim spawns its
                                                                   own; ``auto``: on where an NVIDIA driver is or
                                                                   the host has more than one CPU core.
DEMQ_WORKER_WARM               ``on``                              ``on``: with the default engine, a worker compiles
                                                                   (or loads from numba's disk cache) every kernel
                                                                   specialisation it can run, beside its claims, at
                                                                   the lowest priority and paused while a claim runs
                                                                   (jobs/warm.py, also ``demq warm``); ``off``: not.
DEMQ_WORKER_LANES              ``auto``                            Claims a worker runs at once, each in its own
                                                                   simulation process with cores / lanes Numba
                                                                   threads; ``auto``: one per core on a CPU-only
                                                                   host of more than 3 cores, else 1 (a GPU worker:
                                                                   1, its claims share the GPU).
=============================  ==================================  =================================================

Test hook (not a setting): ``DEMQ_TEST_CRASH=<seed>`` makes the simulation process of a job whose
spec has that seed kill itself with SIGSEGV at its first progress report (see jobs/runner.py).
"""

from __future__ import annotations

import os
import socket
import uuid
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Optional

from engine.setup.limits import DEFAULT_MAX_MEMORY_BYTES, DEFAULT_MAX_PARTICLE_STEPS

_ENV = {
    "data_dir": "DEMQ_DATA_DIR",
    "database_url": "DEMQ_DATABASE_URL",
    "table_prefix": "DEMQ_TABLE_PREFIX",
    "token": "DEMQ_TOKEN",
    "max_particle_steps": "DEMQ_MAX_PARTICLE_STEPS",
    "max_memory_bytes": "DEMQ_MAX_MEMORY_BYTES",
    "max_body_bytes": "DEMQ_MAX_BODY_BYTES",
    "max_batch_jobs": "DEMQ_MAX_BATCH_JOBS",
    "max_attempts": "DEMQ_MAX_ATTEMPTS",
    "lease_s": "DEMQ_LEASE_SECONDS",
    "heartbeat_s": "DEMQ_HEARTBEAT_SECONDS",
    "poll_s": "DEMQ_POLL_SECONDS",
    "progress_s": "DEMQ_PROGRESS_SECONDS",
    "cancel_grace_s": "DEMQ_CANCEL_GRACE_SECONDS",
    "cancel_kill_s": "DEMQ_CANCEL_KILL_SECONDS",
    "cancel_poll_s": "DEMQ_CANCEL_POLL_SECONDS",
    "checkpoint_interval": "DEMQ_CHECKPOINT_INTERVAL",
    "engine_run": "DEMQ_ENGINE_RUN",
    "engine_run_ensemble": "DEMQ_ENGINE_RUN_ENSEMBLE",
    "ensemble_max_jobs": "DEMQ_ENSEMBLE_MAX_JOBS",
    "ensemble_max_particles": "DEMQ_ENSEMBLE_MAX_PARTICLES",
    "ensemble_cost_ratio": "DEMQ_ENSEMBLE_COST_RATIO",
    "cpu_packs": "DEMQ_CPU_PACKS",
    "host": "DEMQ_HOST",
    "port": "DEMQ_PORT",
    "url": "DEMQ_URL",
    "worker_id": "DEMQ_WORKER_ID",
    "standby": "DEMQ_WORKER_STANDBY",
    "warm": "DEMQ_WORKER_WARM",
    "lanes": "DEMQ_WORKER_LANES",
}


DEFAULT_ENGINE_RUN = "engine.driver.simulate:run"
STANDBY_VALUES = ("auto", "on", "off", "1", "0")
SWITCH_VALUES = ("on", "off", "1", "0")
CPU_PACK_VALUES = ("sequence", "ensemble")
DEFAULT_ENGINE_RUN_ENSEMBLE = "engine.driver.ensemble:run_ensemble"


def _default_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


@dataclass(frozen=True)
class Settings:
    """Resolved configuration; see the module docstring for the environment variables."""

    data_dir: Path = Path("demq-data")
    database_url: Optional[str] = None
    table_prefix: str = ""
    token: Optional[str] = None
    max_particle_steps: float = DEFAULT_MAX_PARTICLE_STEPS
    max_memory_bytes: int = DEFAULT_MAX_MEMORY_BYTES
    max_body_bytes: int = 2**20
    max_batch_jobs: int = 1000
    max_attempts: int = 3
    lease_s: float = 60.0
    heartbeat_s: float = 10.0
    poll_s: float = 1.0
    progress_s: float = 1.0
    cancel_grace_s: float = 10.0
    cancel_kill_s: float = 0.3
    cancel_poll_s: float = 0.2
    checkpoint_interval: float = 60.0
    engine_run: str = DEFAULT_ENGINE_RUN
    engine_run_ensemble: str = ""
    ensemble_max_jobs: int = 256
    ensemble_max_particles: int = 4 * 2**20
    ensemble_cost_ratio: float = 4.0
    cpu_packs: str = "sequence"
    host: str = "127.0.0.1"
    port: int = 8000
    url: str = "http://127.0.0.1:8000"
    worker_id: str = ""
    standby: str = "auto"
    warm: str = "on"
    lanes: str = "auto"

    @classmethod
    def from_env(cls, environ=None, **overrides) -> "Settings":
        """Defaults, then ``DEMQ_*`` variables, then the non-None ``overrides`` (command-line flags)."""
        env = os.environ if environ is None else environ
        values = {}
        for f in fields(cls):
            raw = env.get(_ENV[f.name])
            if raw is not None and raw != "":
                try:
                    values[f.name] = _convert(f.default, raw)
                except ValueError:
                    raise ValueError(f"{_ENV[f.name]}={raw!r} is not a valid {type(f.default).__name__}") from None
        values.update({k: v for k, v in overrides.items() if v is not None})
        s = cls(**values)
        return s.resolved()

    def resolved(self) -> "Settings":
        """Fill the derived defaults (database URL in the data directory, worker id) and check."""
        data_dir = Path(self.data_dir).expanduser().absolute()
        url = self.database_url or f"sqlite:///{data_dir / 'demq.sqlite3'}"
        ensemble = self.engine_run_ensemble or (DEFAULT_ENGINE_RUN_ENSEMBLE if self.engine_run == DEFAULT_ENGINE_RUN
                                                else "")
        s = replace(self, data_dir=data_dir, database_url=url, worker_id=self.worker_id or _default_worker_id(),
                    token=self.token or None, engine_run_ensemble=ensemble)
        if not 0 < s.heartbeat_s < s.lease_s:
            raise ValueError(f"heartbeat ({s.heartbeat_s} s) must be positive and shorter than the lease "
                             f"({s.lease_s} s)")
        if s.max_attempts < 1:
            raise ValueError(f"max_attempts = {s.max_attempts} must be >= 1")
        if s.standby not in STANDBY_VALUES:
            raise ValueError(f"DEMQ_WORKER_STANDBY = {s.standby!r} must be one of {', '.join(STANDBY_VALUES)}")
        if s.warm not in SWITCH_VALUES:
            raise ValueError(f"DEMQ_WORKER_WARM = {s.warm!r} must be one of {', '.join(SWITCH_VALUES)}")
        if s.lanes != "auto" and not (s.lanes.isdigit() and int(s.lanes) >= 1):
            raise ValueError(f"DEMQ_WORKER_LANES = {s.lanes!r} must be 'auto' or a whole number >= 1")
        if not s.ensemble_cost_ratio >= 1:
            raise ValueError(f"DEMQ_ENSEMBLE_COST_RATIO = {s.ensemble_cost_ratio} must be >= 1")
        if s.cpu_packs not in CPU_PACK_VALUES:
            raise ValueError(f"DEMQ_CPU_PACKS = {s.cpu_packs!r} must be one of {', '.join(CPU_PACK_VALUES)}")
        if not 0 < s.cancel_poll_s <= s.heartbeat_s:
            raise ValueError(f"DEMQ_CANCEL_POLL_SECONDS = {s.cancel_poll_s} must be positive and at most the "
                             f"heartbeat ({s.heartbeat_s} s)")
        if s.cancel_kill_s < 0:
            raise ValueError(f"DEMQ_CANCEL_KILL_SECONDS = {s.cancel_kill_s} must be >= 0")
        if s.ensemble_max_jobs < 1:
            raise ValueError(f"DEMQ_ENSEMBLE_MAX_JOBS = {s.ensemble_max_jobs} must be >= 1 (1 disables packing)")
        if s.ensemble_max_particles < 2:
            raise ValueError(f"DEMQ_ENSEMBLE_MAX_PARTICLES = {s.ensemble_max_particles} must be >= 2 "
                             f"(the smallest job has 2 particles)")
        return s

    @property
    def standby_enabled(self) -> bool:
        """Whether a running worker keeps its next claim's simulation process started up (jobs/worker.py). Auto: on
        a GPU host, and on a CPU host of more than one core, where the standby starts up beside a running claim
        without taking its core. A lone 64-sphere CPU job through ``demq serve`` was done 0.20-0.27 s after its
        submission with a standby against 0.72-0.99 s without (2-core VM, 2026-11-28, bench/small_jobs.py
        ``--lone``); a CPU standby holds about 160 MB of memory while it waits."""
        if self.standby == "auto":
            from engine.driver.startup import nvidia_driver

            return nvidia_driver() or (os.cpu_count() or 1) > 1
        return self.standby in ("on", "1")

    @property
    def warm_enabled(self) -> bool:
        """Whether a worker warms every kernel specialisation before its first claim (jobs/warm.py): only for the
        default engine (another engine, e.g. the tests' fake one, compiles nothing of the engine's)."""
        return self.warm in ("on", "1") and self.engine_run == DEFAULT_ENGINE_RUN

    def lane_count(self, backends) -> int:
        """Claims a worker runs at once (jobs/worker.py lanes): DEMQ_WORKER_LANES, or with ``auto`` one per CPU core
        on a host that runs only CPU jobs (``backends`` without 'cuda') and has more than 3 cores, else 1 (16 lanes
        on 16 cores ran 200 small jobs at x13.5 of one lane, 8 lanes at x7.8: docs/performance.md). A GPU worker
        keeps one lane: its claims share one GPU."""
        if self.lanes != "auto":
            return int(self.lanes)
        cores = os.cpu_count() or 1
        return 1 if "cuda" in backends or cores <= 3 else cores

    @property
    def packing(self) -> bool:
        """Whether the worker packs compatible queued jobs into one ensemble run."""
        return self.ensemble_max_jobs > 1 and bool(self.engine_run_ensemble)

    @property
    def results_dir(self) -> Path:
        return self.data_dir / "results"

    @property
    def checkpoints_dir(self) -> Path:
        return self.data_dir / "checkpoints"

    def result_path(self, job_id: str) -> Path:
        return self.results_dir / f"{job_id}.h5"

    def checkpoint_dir(self, job_id: str) -> Path:
        return self.checkpoints_dir / job_id

    def batch_result_path(self, batch_id: str) -> Path:
        """Seed statistics of a batch (jobs/batch_results.py), rebuilt on request."""
        return self.data_dir / "batches" / f"{batch_id}.h5"


def _convert(default, raw: str):
    if isinstance(default, int):
        return int(float(raw))
    if isinstance(default, float):
        return float(raw)
    if isinstance(default, Path):
        return Path(raw)
    return raw
