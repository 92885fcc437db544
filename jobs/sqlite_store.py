"""The embedded store: one SQLite file in the data directory, WAL journal, one writer at a time.

Every write transaction starts with ``BEGIN IMMEDIATE`` (it takes the write lock up front instead
of upgrading a read lock, which SQLite may refuse with SQLITE_BUSY under concurrency); the claim is
one ``UPDATE ... RETURNING`` inside such a transaction, so two claimers never get the same job.
Reads run in deferred transactions and do not block the writer (WAL). ``synchronous=FULL``: a
commit that returned survives a power loss, so an accepted job is never lost.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from sqlalchemy import Connection, create_engine, event
from sqlalchemy.engine import make_url

from jobs.sql_store import SqlJobStore

BUSY_TIMEOUT_MS = 30_000


class SQLiteJobStore(SqlJobStore):
    """The job table in a SQLite database file (``sqlite:///PATH``)."""

    def __init__(self, url: str, table_prefix: str = ""):
        database = make_url(url).database
        if not database or database == ":memory:":
            raise ValueError("the SQLite store needs a file (sqlite:///PATH): workers run in other processes")
        Path(database).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": BUSY_TIMEOUT_MS / 1000, "check_same_thread": False})

        @event.listens_for(engine, "connect")
        def _configure(dbapi_conn, _record):
            dbapi_conn.isolation_level = None          # the driver must not open transactions itself
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=FULL")
            cur.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
            cur.close()

        @event.listens_for(engine, "begin")
        def _begin(conn):
            conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("immediate") else "BEGIN")

        super().__init__(engine, table_prefix)
        self._writer = engine.execution_options(immediate=True)

    @contextmanager
    def _write(self) -> Iterator[Connection]:
        with self._writer.begin() as conn:
            yield conn
