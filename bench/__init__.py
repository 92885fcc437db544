"""Benchmarks and stress tests of demq, run from a checkout: ``python -m bench <name> [--out DIR] ...``.

Not installed with the package (pyproject installs engine, jobs and service only). Every benchmark writes its
outputs under the folder named by ``--out`` (default ``./bench-out/<name>/`` under the current working
directory), never into this folder.
"""

from __future__ import annotations

from pathlib import Path


def out_dir(path: str | Path | None, name: str) -> Path:
    """The folder a benchmark writes into, created: ``path`` when given, else ./bench-out/<name>/ under the
    current working directory."""
    out = Path(path) if path else Path.cwd() / "bench-out" / name
    out.mkdir(parents=True, exist_ok=True)
    return out
