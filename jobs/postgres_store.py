"""The shared store: the job table in PostgreSQL, for one worker per GPU on any number of hosts.

The claim locks the next queued row with ``SELECT ... FOR UPDATE SKIP LOCKED`` inside the
``UPDATE ... RETURNING``, so concurrent claimers skip each other's rows instead of waiting or
taking the same job. Transitions are single conditional UPDATEs (row locks, READ COMMITTED).
"""

from __future__ import annotations

from sqlalchemy import Select, create_engine
from sqlalchemy.engine import make_url

from jobs.sql_store import SqlJobStore


def sqlalchemy_url(url: str) -> str:
    """``postgresql://...`` (libpq style) -> the SQLAlchemy URL of the psycopg 3 driver."""
    u = make_url(url)
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")
    return u.render_as_string(hide_password=False)


class PostgresJobStore(SqlJobStore):
    """The job table in PostgreSQL (``postgresql://user@host:port/db``)."""

    def __init__(self, url: str, table_prefix: str = ""):
        super().__init__(create_engine(sqlalchemy_url(url), pool_pre_ping=True), table_prefix)

    def _lock_next(self, query: Select) -> Select:
        return query.with_for_update(skip_locked=True)
