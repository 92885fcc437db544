"""Which job store a database URL gets: the factory over the store implementations.

Kept out of jobs/store.py (the interface, which the implementations import) so the imports run one way:
stores.py -> sqlite_store.py / postgres_store.py -> sql_store.py -> store.py.
"""

from __future__ import annotations

from jobs.store import JobStore


def open_store(url: str, table_prefix: str = "", create: bool = True) -> JobStore:
    """The store for a database URL: ``sqlite:///path`` or ``postgresql://...``."""
    if url.startswith("sqlite"):
        from jobs.sqlite_store import SQLiteJobStore
        store: JobStore = SQLiteJobStore(url, table_prefix)
    elif url.startswith(("postgresql", "postgres")):
        from jobs.postgres_store import PostgresJobStore
        store = PostgresJobStore(url, table_prefix)
    else:
        raise ValueError(f"unsupported database URL {url!r}: use sqlite:///PATH or postgresql://...")
    if create:
        store.create_tables()
    return store
