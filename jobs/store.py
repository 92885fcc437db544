"""The store interface: everything the API and the workers do to the job table.

Two implementations share one SQL schema (jobs/schema.py) and one SQLAlchemy-Core body
(jobs/sql_store.py) and differ only where the databases do: the claim.

- :class:`jobs.sqlite_store.SQLiteJobStore` — embedded default, WAL, claims inside ``BEGIN IMMEDIATE``.
- :class:`jobs.postgres_store.PostgresJobStore` — several workers on several hosts, claims with
  ``SELECT ... FOR UPDATE SKIP LOCKED``.

Every transition that belongs to a worker (heartbeat, finish, release) is conditional on the lease
owner, so a worker that lost its lease can no longer write to the job. This module owns the interface
and the row types only and imports no implementation; :func:`jobs.stores.open_store` picks one by URL.
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Optional, Sequence


class LeaseLost(Exception):
    """The job is no longer leased to this worker (the reaper requeued it, or it was finished)."""


@dataclass(frozen=True)
class Job:
    """One row of the job table."""

    id: str
    state: str
    spec: dict
    batch_id: Optional[str]
    priority: int
    progress: float
    phase: Optional[str]
    step: Optional[int]
    sim_time: Optional[float]
    eta_s: Optional[float]
    created_at: float
    started_at: Optional[float]
    finished_at: Optional[float]
    loop_s: Optional[float]        # wall seconds of the engine's time loop (the successful attempt)
    job_wall_s: Optional[float]    # wall seconds of the whole run, from the spec to the closed result file
    cundall: Optional[float]
    backend: Optional[str]
    device: Optional[str]
    resumed_from_step: Optional[int]
    error: Optional[str]
    result_path: Optional[str]
    attempts: int
    max_attempts: int
    lease_owner: Optional[str]
    lease_expires_at: Optional[float]
    heartbeat_at: Optional[float]
    cancel_requested: bool

    @classmethod
    def from_row(cls, row) -> "Job":
        data = dict(row._mapping)
        data.pop("seq", None)
        data["spec"] = json.loads(data["spec"])
        data["cancel_requested"] = bool(data["cancel_requested"])
        return cls(**data)


@dataclass(frozen=True)
class WorkerInfo:
    """One row of the worker table: a worker process and the backends it can run.

    Times are UNIX seconds: ``started_at`` when it registered, ``seen_at`` its last sign of life.
    """

    worker_id: str
    host: str
    pid: int
    backends: tuple[str, ...]
    started_at: float
    seen_at: float
    device_memory: Optional[int] = None   # bytes of its GPU's memory; None: no GPU, or not known

    @classmethod
    def from_row(cls, row) -> "WorkerInfo":
        data = dict(row._mapping)
        data["backends"] = tuple(b for b in data["backends"].split(",") if b)
        return cls(**data)


@dataclass(frozen=True)
class NewJob:
    """A job to enqueue: the canonical spec JSON (already validated) and its priority."""

    spec_json: str
    priority: int = 0


class JobStore(ABC):
    """The job table. All methods are safe to call from several threads and processes."""

    # ---- schema and health ------------------------------------------------------------------------
    @abstractmethod
    def create_tables(self) -> None:
        """Create the table and its indexes if missing (idempotent)."""

    @abstractmethod
    def drop_tables(self) -> None:
        """Drop the table (tests)."""

    @abstractmethod
    def ping(self) -> None:
        """Raise if the database cannot be reached."""

    @abstractmethod
    def close(self) -> None:
        """Release the connections."""

    # ---- submitting and reading -------------------------------------------------------------------
    @abstractmethod
    def submit(self, jobs: Sequence[NewJob], batch_id: Optional[str] = None,
               max_attempts: int = 3) -> list[Job]:
        """Insert queued jobs in one transaction (all or none) and return them."""

    @abstractmethod
    def get(self, job_id: str) -> Optional[Job]:
        """The job, or None."""

    @abstractmethod
    def list(self, state: Optional[str] = None, batch_id: Optional[str] = None,
             limit: int = 50, offset: int = 0) -> tuple[list[Job], int]:
        """A page of jobs in submission order, and the total count that matches the filters."""

    @abstractmethod
    def counts(self) -> dict[str, int]:
        """Number of jobs per state."""

    @abstractmethod
    def request_cancel(self, job_id: str) -> Optional[Job]:
        """Cancel a queued job at once; mark a running one for its worker. None if unknown."""

    # ---- the worker side --------------------------------------------------------------------------
    @abstractmethod
    def claim(self, owner: str, lease_s: float, job_id: Optional[str] = None) -> Optional[Job]:
        """Atomically lease the next queued job (or exactly ``job_id``) to ``owner``; None if none."""

    @abstractmethod
    def peek_queued(self, limit: int) -> list[Job]:
        """Up to ``limit`` queued jobs in claim order (priority, then submission), without claiming them."""

    @abstractmethod
    def claim_ids(self, owner: str, lease_s: float, job_ids: Sequence[str]) -> list[Job]:
        """Atomically lease those of ``job_ids`` that are still queued (a pack); the others are skipped.

        Returns the claimed jobs in the order of ``job_ids``.
        """

    @abstractmethod
    def heartbeat(self, job_id: str, owner: str, lease_s: float,
                  progress: Optional[dict[str, Any]] = None) -> bool:
        """Renew the lease (and write progress); return whether a cancel was requested.

        Raises :class:`LeaseLost` when the job is no longer running under ``owner``.
        """

    def heartbeat_many(self, job_ids: Sequence[str], owner: str, lease_s: float,
                       progress: Optional[dict[str, dict[str, Any]]] = None) -> dict[str, bool]:
        """:meth:`heartbeat` for several jobs (a pack): {job id: cancel requested} of the jobs still
        leased to ``owner``; a job missing from the answer has lost its lease."""
        out = {}
        for job_id in job_ids:
            try:
                out[job_id] = self.heartbeat(job_id, owner, lease_s, (progress or {}).get(job_id))
            except LeaseLost:
                pass
        return out

    @abstractmethod
    def cancel_requests(self, job_ids: Sequence[str]) -> set[str]:
        """Those of ``job_ids`` whose cancel was requested (one cheap read: the worker asks every
        DEMQ_CANCEL_POLL_SECONDS for the jobs it runs)."""

    @abstractmethod
    def finish(self, job_id: str, owner: str, state: str, **fields: Any) -> bool:
        """End a leased job as done, failed or cancelled with the given columns; False if not leased."""

    def finish_many(self, owner: str, ends: Sequence[tuple[str, str, dict[str, Any]]]) -> dict[str, bool]:
        """:meth:`finish` for several jobs (a pack's jobs that ended together): ``ends`` holds (job id, state,
        columns); {job id: whether it was still leased to ``owner`` and is now ended}."""
        return {job_id: self.finish(job_id, owner, state, **fields) for job_id, state, fields in ends}

    @abstractmethod
    def release(self, job_id: str, owner: str, error: Optional[str] = None) -> bool:
        """Give a leased job back to the queue without counting the attempt (worker shutdown).

        ``error``: a note kept on the queued job (why it went back), e.g. that it must run alone.
        """

    @abstractmethod
    def reap_expired(self, now: Optional[float] = None) -> tuple[list[str], list[str]]:
        """Requeue running jobs whose lease expired while attempts remain, fail the others.

        Returns (requeued ids, failed ids). A job whose cancel was requested ends cancelled instead.
        """

    # ---- the worker registry ----------------------------------------------------------------------
    @abstractmethod
    def register_worker(self, worker_id: str, host: str, pid: int, backends: Sequence[str],
                        device_memory: Optional[int] = None) -> None:
        """Insert or replace the worker's row; ``started_at`` and ``seen_at`` become now; ``device_memory``: the
        bytes of its GPU's memory, where known."""

    @abstractmethod
    def worker_seen(self, worker_id: str) -> None:
        """Set the worker's ``seen_at`` to now (no-op for an unknown worker)."""

    @abstractmethod
    def unregister_worker(self, worker_id: str) -> None:
        """Remove the worker's row (no-op for an unknown worker)."""

    @abstractmethod
    def live_workers(self, max_age_s: float) -> list[WorkerInfo]:
        """The workers seen within the last ``max_age_s`` seconds, oldest registration first."""
