"""The durable job queue of demq: the job table (SQLite or PostgreSQL) and the worker that drains it.

Depends on the engine only; never on the HTTP service.
"""
