"""The body of both stores: SQLAlchemy Core statements on the one job table.

Subclasses supply the engine (connection set-up) and :meth:`SqlJobStore._lock_next`, the only
dialect-specific piece of the claim.
"""

from __future__ import annotations

import time
import uuid
from contextlib import contextmanager
from typing import Any, Iterator, Optional, Sequence

from sqlalchemy import (Connection, Engine, MetaData, String, Select, bindparam, case, cast, delete, func, inspect,
                        literal, null, select, text, update)

from jobs.schema import CANCELLED, DONE, FAILED, QUEUED, RUNNING, job_table, worker_table
from jobs.store import Job, JobStore, LeaseLost, NewJob, WorkerInfo

#: Columns a heartbeat may write as progress.
PROGRESS_COLUMNS = ("progress", "phase", "step", "sim_time", "eta_s", "cundall", "resumed_from_step")
#: Columns a worker may set when it finishes a job.
FINISH_COLUMNS = ("error", "result_path", "loop_s", "job_wall_s", "cundall", "backend", "device", "resumed_from_step",
                  "progress", "phase", "step", "sim_time", "eta_s")


class SqlJobStore(JobStore):
    """A :class:`JobStore` on a SQLAlchemy engine."""

    def __init__(self, engine: Engine, table_prefix: str = ""):
        self.engine = engine
        self.metadata = MetaData()
        self.table = job_table(self.metadata, table_prefix)
        self.workers = worker_table(self.metadata, table_prefix)

    # ---- transactions (SQLite overrides _write to take the write lock up front) ---------------------
    @contextmanager
    def _write(self) -> Iterator[Connection]:
        with self.engine.begin() as conn:
            yield conn

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        with self.engine.connect() as conn:
            yield conn

    def _lock_next(self, query: Select) -> Select:
        """Make the 'next queued job' subquery safe against concurrent claimers."""
        return query

    # ---- schema and health ------------------------------------------------------------------------
    def create_tables(self) -> None:
        with self._write() as conn:
            self.metadata.create_all(conn, checkfirst=True)
            self._add_new_columns(conn)

    def _add_new_columns(self, conn: Connection) -> None:
        """Add the columns a table created by an older demq lacks (each new column is nullable, so ALTER TABLE ...
        ADD COLUMN is all it takes; a column that is no longer used stays and is never read)."""
        inspector = inspect(conn)
        for table in self.metadata.sorted_tables:
            present = {c["name"] for c in inspector.get_columns(table.name)}
            for column in table.columns:
                if column.name not in present:
                    conn.execute(text(f"ALTER TABLE {table.name} ADD COLUMN {column.name} "
                                      f"{column.type.compile(dialect=conn.dialect)}"))

    def drop_tables(self) -> None:
        with self._write() as conn:
            self.metadata.drop_all(conn, checkfirst=True)

    def ping(self) -> None:
        with self._read() as conn:
            conn.execute(text("SELECT 1"))

    def close(self) -> None:
        self.engine.dispose()

    # ---- submitting and reading -------------------------------------------------------------------
    def submit(self, jobs: Sequence[NewJob], batch_id: Optional[str] = None,
               max_attempts: int = 3) -> list[Job]:
        if not jobs:
            return []
        t, now = self.table, time.time()
        rows = [dict(id=uuid.uuid4().hex, state=QUEUED, spec=j.spec_json, batch_id=batch_id,
                     priority=j.priority, progress=0.0, created_at=now, attempts=0,
                     max_attempts=max_attempts, cancel_requested=False) for j in jobs]
        with self._write() as conn:
            conn.execute(t.insert(), rows)
            ids = [r["id"] for r in rows]
            found = conn.execute(select(t).where(t.c.id.in_(ids)).order_by(t.c.seq)).all()
        return [Job.from_row(r) for r in found]

    def get(self, job_id: str) -> Optional[Job]:
        with self._read() as conn:
            row = conn.execute(select(self.table).where(self.table.c.id == job_id)).first()
        return Job.from_row(row) if row is not None else None

    def list(self, state: Optional[str] = None, batch_id: Optional[str] = None,
             limit: int = 50, offset: int = 0) -> tuple[list[Job], int]:
        t = self.table
        where = []
        if state is not None:
            where.append(t.c.state == state)
        if batch_id is not None:
            where.append(t.c.batch_id == batch_id)
        with self._read() as conn:
            total = conn.execute(select(func.count()).select_from(t).where(*where)).scalar_one()
            rows = conn.execute(select(t).where(*where).order_by(t.c.seq).limit(limit).offset(offset)).all()
        return [Job.from_row(r) for r in rows], total

    def counts(self) -> dict[str, int]:
        t = self.table
        with self._read() as conn:
            rows = conn.execute(select(t.c.state, func.count()).group_by(t.c.state)).all()
        return {state: n for state, n in rows}

    def request_cancel(self, job_id: str) -> Optional[Job]:
        t, now = self.table, time.time()
        with self._write() as conn:
            conn.execute(update(t).where(t.c.id == job_id, t.c.state == QUEUED)
                         .values(state=CANCELLED, cancel_requested=True, finished_at=now))
            conn.execute(update(t).where(t.c.id == job_id, t.c.state == RUNNING).values(cancel_requested=True))
            row = conn.execute(select(t).where(t.c.id == job_id)).first()
        return Job.from_row(row) if row is not None else None

    # ---- the worker side --------------------------------------------------------------------------
    def claim(self, owner: str, lease_s: float, job_id: Optional[str] = None) -> Optional[Job]:
        t, now = self.table, time.time()
        if job_id is None:
            nxt = select(t.c.seq).where(t.c.state == QUEUED).order_by(t.c.priority.desc(), t.c.seq).limit(1)
            target = t.c.seq == self._lock_next(nxt).scalar_subquery()
        else:
            target = t.c.id == job_id
        stmt = (update(t).where(target, t.c.state == QUEUED)
                .values(state=RUNNING, lease_owner=owner, lease_expires_at=now + lease_s, heartbeat_at=now,
                        attempts=t.c.attempts + 1, started_at=func.coalesce(t.c.started_at, now))
                .returning(*t.c))
        with self._write() as conn:
            row = conn.execute(stmt).first()
        return Job.from_row(row) if row is not None else None

    def peek_queued(self, limit: int) -> list[Job]:
        t = self.table
        with self._read() as conn:
            rows = conn.execute(select(t).where(t.c.state == QUEUED)
                                .order_by(t.c.priority.desc(), t.c.seq).limit(limit)).all()
        return [Job.from_row(r) for r in rows]

    def claim_ids(self, owner: str, lease_s: float, job_ids: Sequence[str]) -> list[Job]:
        if not job_ids:
            return []
        t, now = self.table, time.time()
        ids = list(job_ids)
        rows = []
        with self._write() as conn:
            for start in range(0, len(ids), 500):  # bounded IN lists
                part = ids[start:start + 500]
                pick = self._lock_next(select(t.c.seq).where(t.c.id.in_(part), t.c.state == QUEUED))
                stmt = (update(t).where(t.c.seq.in_(pick.scalar_subquery()), t.c.state == QUEUED)
                        .values(state=RUNNING, lease_owner=owner, lease_expires_at=now + lease_s, heartbeat_at=now,
                                attempts=t.c.attempts + 1, started_at=func.coalesce(t.c.started_at, now))
                        .returning(*t.c))
                rows.extend(conn.execute(stmt).all())
        claimed = {j.id: j for j in (Job.from_row(r) for r in rows)}
        return [claimed[i] for i in ids if i in claimed]

    def heartbeat(self, job_id: str, owner: str, lease_s: float,
                  progress: Optional[dict[str, Any]] = None) -> bool:
        with self._write() as conn:
            row = conn.execute(self._heartbeat_stmt(job_id, owner, lease_s, progress, time.time())).first()
        if row is None:
            raise LeaseLost(f"job {job_id} is no longer leased to {owner}")
        return bool(row[0])

    def heartbeat_many(self, job_ids: Sequence[str], owner: str, lease_s: float,
                       progress: Optional[dict[str, dict[str, Any]]] = None) -> dict[str, bool]:
        """One transaction for the whole claim (one commit, not one per job): one statement renews the leases and
        reads the cancel requests of all the jobs, and the progress columns are written by one executemany per set of
        columns (a sequence's waiting jobs share theirs), not a statement per job: a CPU lane writes its claim's rows
        every DEMQ_PROGRESS_SECONDS, in the worker thread that its lanes and the HTTP service share."""
        t, now, ids, out = self.table, time.time(), list(job_ids), {}
        groups: dict[tuple, list] = {}
        for job_id in ids:
            columns = {k: v for k, v in ((progress or {}).get(job_id) or {}).items() if k in PROGRESS_COLUMNS}
            if columns:
                groups.setdefault(tuple(sorted(columns)), []).append(
                    {"b_id": job_id, **{f"b_{k}": v for k, v in columns.items()}})
        leased = (t.c.lease_owner == owner, t.c.state == RUNNING)
        with self._write() as conn:
            for start in range(0, len(ids), 500):  # bounded IN lists
                rows = conn.execute(update(t).where(t.c.id.in_(ids[start:start + 500]), *leased)
                                    .values(lease_expires_at=now + lease_s, heartbeat_at=now)
                                    .returning(t.c.id, t.c.cancel_requested)).all()
                out.update((job_id, bool(requested)) for job_id, requested in rows)
            for columns, params in groups.items():
                stmt = update(t).where(t.c.id == bindparam("b_id"), *leased).values(
                    {k: bindparam(f"b_{k}") for k in columns})
                conn.execute(stmt, params)
        return out

    def _heartbeat_stmt(self, job_id: str, owner: str, lease_s: float, progress: Optional[dict[str, Any]],
                        now: float):
        t = self.table
        values: dict[str, Any] = dict(lease_expires_at=now + lease_s, heartbeat_at=now)
        values.update({k: v for k, v in (progress or {}).items() if k in PROGRESS_COLUMNS})
        return (update(t).where(t.c.id == job_id, t.c.lease_owner == owner, t.c.state == RUNNING)
                .values(**values).returning(t.c.cancel_requested))

    def cancel_requests(self, job_ids: Sequence[str]) -> set[str]:
        t, ids, out = self.table, list(job_ids), set()
        with self._read() as conn:
            for start in range(0, len(ids), 500):  # bounded IN lists
                part = ids[start:start + 500]
                out.update(conn.execute(select(t.c.id).where(t.c.id.in_(part), t.c.cancel_requested)).scalars())
        return out

    def finish(self, job_id: str, owner: str, state: str, **fields: Any) -> bool:
        return self.finish_many(owner, [(job_id, state, fields)])[job_id]

    def finish_many(self, owner: str, ends: Sequence[tuple[str, str, dict[str, Any]]]) -> dict[str, bool]:
        """One transaction for all of them (one commit: a pack's 256 jobs that end in the same second)."""
        now = time.time()
        statements = [(job_id, self._finish_stmt(job_id, owner, state, fields, now)) for job_id, state, fields in ends]
        with self._write() as conn:
            return {job_id: conn.execute(stmt).rowcount == 1 for job_id, stmt in statements}

    def _finish_stmt(self, job_id: str, owner: str, state: str, fields: dict[str, Any], now: float):
        if state not in (DONE, FAILED, CANCELLED):
            raise ValueError(f"finish() needs a final state, got {state!r}")
        unknown = set(fields) - set(FINISH_COLUMNS)
        if unknown:
            raise ValueError(f"finish() cannot set {sorted(unknown)}")
        t = self.table
        return (update(t).where(t.c.id == job_id, t.c.lease_owner == owner, t.c.state == RUNNING)
                .values(state=state, finished_at=now, lease_owner=None, lease_expires_at=None, **fields))

    def release(self, job_id: str, owner: str, error: Optional[str] = None) -> bool:
        t = self.table
        extra = {} if error is None else {"error": case((t.c.cancel_requested, null()), else_=literal(error))}
        stmt = (update(t).where(t.c.id == job_id, t.c.lease_owner == owner, t.c.state == RUNNING)
                .values(state=case((t.c.cancel_requested, CANCELLED), else_=QUEUED),
                        finished_at=case((t.c.cancel_requested, time.time()), else_=None),
                        attempts=t.c.attempts - 1, lease_owner=None, lease_expires_at=None, **extra))
        with self._write() as conn:
            return conn.execute(stmt).rowcount == 1

    def reap_expired(self, now: Optional[float] = None) -> tuple[list[str], list[str]]:
        t = self.table
        now = time.time() if now is None else now
        expired = (t.c.state == RUNNING, t.c.lease_expires_at < now)
        cleared = dict(lease_owner=None, lease_expires_at=None)
        attempts = cast(t.c.attempts, String) + literal(" of ") + cast(t.c.max_attempts, String)
        with self._write() as conn:
            conn.execute(update(t).where(*expired, t.c.cancel_requested)
                         .values(state=CANCELLED, finished_at=now, **cleared))
            requeued = conn.execute(
                update(t).where(*expired, t.c.attempts < t.c.max_attempts)
                .values(state=QUEUED, error=literal("its worker was lost (lease expired) on attempt ") + attempts
                        + literal("; requeued"), **cleared)
                .returning(t.c.id)).scalars().all()
            failed = conn.execute(
                update(t).where(*expired, t.c.attempts >= t.c.max_attempts)
                .values(state=FAILED, finished_at=now,
                        error=literal("its worker was lost (lease expired) on every attempt, ") + attempts
                        + literal(": the simulation may be killing its worker (out of memory?)"), **cleared)
                .returning(t.c.id)).scalars().all()
        return list(requeued), list(failed)

    # ---- the worker registry ----------------------------------------------------------------------
    def register_worker(self, worker_id: str, host: str, pid: int, backends: Sequence[str],
                        device_memory: Optional[int] = None) -> None:
        w, now = self.workers, time.time()
        row = dict(host=host, pid=int(pid), backends=",".join(backends), started_at=now, seen_at=now,
                   device_memory=None if device_memory is None else int(device_memory))
        with self._write() as conn:  # portable upsert: the write transaction serialises it
            if conn.execute(update(w).where(w.c.worker_id == worker_id).values(**row)).rowcount == 0:
                conn.execute(w.insert().values(worker_id=worker_id, **row))

    def worker_seen(self, worker_id: str) -> None:
        w = self.workers
        with self._write() as conn:
            conn.execute(update(w).where(w.c.worker_id == worker_id).values(seen_at=time.time()))

    def unregister_worker(self, worker_id: str) -> None:
        w = self.workers
        with self._write() as conn:
            conn.execute(delete(w).where(w.c.worker_id == worker_id))

    def live_workers(self, max_age_s: float) -> list[WorkerInfo]:
        w = self.workers
        with self._read() as conn:
            rows = conn.execute(select(w).where(w.c.seen_at >= time.time() - max_age_s)
                                .order_by(w.c.started_at, w.c.worker_id)).all()
        return [WorkerInfo.from_row(r) for r in rows]
