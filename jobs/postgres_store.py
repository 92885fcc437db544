"""The shared store: the job table in PostgreSQL, for one worker per GPU on any number of hosts.

The claim locks the next queued row with ``SELECT ... FOR UPDATE SKIP LOCKED`` inside the
``UPDATE ... RETURNING``, so concurrent claimers skip each other's rows instead of waiting or
taking the same job. Transitions are single conditional UPDATEs (row locks, READ COMMITTED).
"""

from __future__ import annotations

from sqlalchemy import Select, create_engine, text
from sqlalchemy.engine import make_url

from engine.optional import require
from jobs.sql_store import SqlJobStore

#: The extra (pyproject.toml) that installs the driver: the light install runs the SQLite queue only.
EXTRA = "postgres"


def sqlalchemy_url(url: str) -> str:
    """``postgresql://...`` (libpq style) -> the SQLAlchemy URL of the psycopg 3 driver."""
    u = make_url(url)
    if u.drivername in ("postgresql", "postgres"):
        u = u.set(drivername="postgresql+psycopg")
    return u.render_as_string(hide_password=False)


#: Key of the advisory lock that serialises CREATE TABLE between processes (bytes of "demq").
_SCHEMA_LOCK = 0x64656D71


class PostgresJobStore(SqlJobStore):
    """The job table in PostgreSQL (``postgresql://user@host:port/db``)."""

    def __init__(self, url: str, table_prefix: str = ""):
        # the psycopg 3 driver comes with the `postgres` extra: without it, engine.optional.MissingExtra naming the
        # extra (an ImportError), rather than SQLAlchemy's bare "No module named 'psycopg'"
        require("psycopg", EXTRA, "a PostgreSQL job queue (a postgresql:// database URL)")
        super().__init__(create_engine(sqlalchemy_url(url), pool_pre_ping=True), table_prefix)

    def _lock_next(self, query: Select) -> Select:
        return query.with_for_update(skip_locked=True)

    def create_tables(self) -> None:
        """Create the table under a transaction-scoped advisory lock: workers that start together
        (a Slurm job array, a compose project) otherwise race in CREATE TABLE and fail with
        UniqueViolation/DuplicateTable."""
        with self._write() as conn:
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _SCHEMA_LOCK})
            self.metadata.create_all(conn, checkfirst=True)
            self._add_new_columns(conn)
