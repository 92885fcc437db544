"""The job and worker tables: one SQL schema (SQLAlchemy Core) shared by the SQLite and PostgreSQL stores.

Times are UNIX seconds (float) taken from the clock of the process that writes them; workers on
several hosts therefore need synchronised clocks (NTP) for leases to mean the same everywhere.
"""

from __future__ import annotations

from sqlalchemy import BigInteger, Boolean, Column, Float, Index, Integer, MetaData, String, Table, Text

#: Job states. ``queued`` and ``running`` are live; the other three are final.
QUEUED, RUNNING, DONE, FAILED, CANCELLED = "queued", "running", "done", "failed", "cancelled"
STATES = (QUEUED, RUNNING, DONE, FAILED, CANCELLED)
FINAL_STATES = (DONE, FAILED, CANCELLED)


def job_table(metadata: MetaData, prefix: str = "") -> Table:
    """Define ``<prefix>jobs`` on ``metadata``."""
    name = f"{prefix}jobs"
    return Table(
        name, metadata,
        Column("seq", Integer, primary_key=True, autoincrement=True),   # FIFO order within a priority
        Column("id", String(32), nullable=False, unique=True),
        Column("state", String(16), nullable=False),
        Column("spec", Text, nullable=False),               # canonical JSON of the validated spec
        Column("batch_id", String(32)),
        Column("priority", Integer, nullable=False, default=0),
        # progress, written by the worker (rate-limited)
        Column("progress", Float, nullable=False, default=0.0),
        Column("phase", String(32)),
        Column("step", Integer),
        Column("sim_time", Float),
        Column("eta_s", Float),
        # timings and result
        Column("created_at", Float, nullable=False),
        Column("started_at", Float),                        # first claim
        Column("finished_at", Float),
        Column("loop_s", Float),                            # wall s of the engine's time loop (successful attempt)
        Column("job_wall_s", Float),                        # wall s of the whole run, spec to closed result file
        Column("cundall", Float),                           # particle-steps per wall second
        Column("backend", String(32)),
        Column("device", String(200)),
        Column("resumed_from_step", Integer),
        Column("error", Text),
        Column("result_path", Text),
        # lease
        Column("attempts", Integer, nullable=False, default=0),
        Column("max_attempts", Integer, nullable=False),
        Column("lease_owner", String(200)),
        Column("lease_expires_at", Float),
        Column("heartbeat_at", Float),
        Column("cancel_requested", Boolean, nullable=False, default=False),
        Index(f"ix_{name}_claim", "state", "priority", "seq"),
        Index(f"ix_{name}_batch", "batch_id"),
    )


def worker_table(metadata: MetaData, prefix: str = "") -> Table:
    """Define ``<prefix>workers`` on ``metadata``: one row per running worker process.

    A worker registers when it starts, refreshes ``seen_at`` while it runs and removes its row when
    it stops; a worker that died without unregistering is recognised by an old ``seen_at``.
    ``backends`` is a comma-separated list of the backends it can run ("cpu" or "cpu,cuda");
    ``device_memory`` the total memory (bytes) of its GPU, null when it has none or it is not known.
    """
    return Table(
        f"{prefix}workers", metadata,
        Column("worker_id", String(200), primary_key=True),
        Column("host", String(200), nullable=False),
        Column("pid", Integer, nullable=False),
        Column("backends", String(200), nullable=False),
        Column("started_at", Float, nullable=False),
        Column("seen_at", Float, nullable=False),
        Column("device_memory", BigInteger, nullable=True),
    )
